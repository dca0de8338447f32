"""Visibility against an independent float64 reference, watertightness, clipping, bad input."""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import box, clip_of, grid_plane, icosphere, perspective_mvp, random_soup
from refraster import rasterize_ref

import jaxnm
from jaxnm._exec import depth as tiled
from jaxnm._exec import triangles
from jaxnm._exec.slots import slot_passes
from jaxnm.raster import RasterStrategy, overdraw

#: `raster._window_corners` compiled, as the rasterizer runs it (run eagerly, each of its
#: operations would be compiled on its own)
_window_corners = jax.jit(jaxnm.raster._window_corners,
                          static_argnames=("width", "height", "subpixel_bits"))


def _unsnapped_depth(ref, clip, faces):
    """Window depth from the reference's (unsnapped) perspective-correct barycentrics."""
    c = np.asarray(clip, np.float64)[np.asarray(faces)[np.maximum(ref["triangle_id"], 0)]]
    b = ref["bary"][..., None]
    w = (b * c[..., 3:4]).sum(-2)[..., 0]
    z = (b * c[..., 2:3]).sum(-2)[..., 0] / np.where(ref["triangle_id"] >= 0, w, 1.0)
    return (z + 1) / 2


def _ambiguous(ref, tol=1e-3):
    return np.minimum(ref["edge_distance"], ref["any_edge_distance"]) < tol


@pytest.mark.parametrize("seed,size", [(0, (48, 40)), (1, (33, 21)), (2, (40, 40))])
@pytest.mark.parametrize("cull", [False, True])
def test_matches_float64_reference(seed, size, cull):
    """Same coverage, winner, depth and facing as a clip-divide-2D-edge float64 rasterizer."""
    w, h = size
    pos, faces = random_soup(seed)
    clip = clip_of(pos, perspective_mvp((0.3, 0.4, 2.5), aspect=w / h)).astype(np.float32)
    ref = rasterize_ref(clip.astype(np.float64), faces, w, h, cull_back=cull, subpixel_bits=8)
    fr = jaxnm.rasterize(clip, faces, width=w, height=h, cull_back=cull)
    tid = np.asarray(fr.triangle_id)
    amb = _ambiguous(ref)
    assert (tid >= 0).sum() > 0.2 * w * h
    assert np.array_equal(tid[~amb], ref["triangle_id"][~amb])
    assert (tid != ref["triangle_id"]).sum() <= 2  # only within 1e-3 px of an edge
    cov = (tid >= 0) & (tid == ref["triangle_id"])
    np.testing.assert_allclose(np.asarray(fr.depth)[cov], _unsnapped_depth(ref, clip, faces)[cov],
                               atol=2e-6)
    assert np.array_equal(np.asarray(fr.front_facing)[cov], ref["front_facing"][cov])
    assert np.all(np.asarray(fr.depth)[tid < 0] == 1.0)


def test_unsnapped_coverage_matches_exact_reference():
    pos, faces = random_soup(3)
    clip = clip_of(pos, perspective_mvp((0.5, -0.2, 2.2))).astype(np.float32)
    ref = rasterize_ref(clip.astype(np.float64), faces, 48, 48)
    fr = jaxnm.rasterize(clip, faces, width=48, height=48, subpixel_bits=None)
    amb = _ambiguous(ref, 1e-4)
    assert np.array_equal(np.asarray(fr.triangle_id)[~amb], ref["triangle_id"][~amb])


def _quad(ndc=1.0, diagonal="main"):
    c = np.array([[-ndc, -ndc, 0, 1], [ndc, -ndc, 0, 1], [ndc, ndc, 0, 1], [-ndc, ndc, 0, 1]],
                 np.float32)
    faces = [[0, 1, 2], [0, 2, 3]] if diagonal == "main" else [[0, 1, 3], [1, 2, 3]]
    return c, np.array(faces)


@pytest.mark.parametrize("diagonal", ["main", "anti"])
@pytest.mark.parametrize("size", [(8, 8), (7, 5), (16, 9)])
def test_shared_edge_covers_each_pixel_once(diagonal, size):
    """A viewport-filling quad: its diagonal passes exactly through pixel centres (8x8)."""
    clip, faces = _quad(1.0, diagonal)
    w, h = size
    count = np.asarray(overdraw(clip, faces, width=w, height=h))
    assert np.all(count == 1)
    fr = jaxnm.rasterize(clip, faces, width=w, height=h)
    assert np.all(np.asarray(fr.triangle_id) >= 0)


def test_tie_rule_left_bottom_window():
    """Centres exactly on an edge: left and bottom edges (window y up) own them (llvmpipe)."""
    # a rectangle [2, 6] x [2, 6] in window pixels of an 8x8 image, edges through centres?
    # NDC -0.375 -> window 2.5 (a centre); 0.625 -> 6.5
    lo, hi = -0.375, 0.625
    clip = np.array([[lo, lo, 0, 1], [hi, lo, 0, 1], [hi, hi, 0, 1], [lo, hi, 0, 1]], np.float32)
    fr = jaxnm.rasterize(clip, [[0, 1, 2], [0, 2, 3]], width=8, height=8)
    mask = np.asarray(fr.mask)[::-1]  # window layout: row j = window y
    # window x centres 2.5 .. 6.5 on the left edge (2.5) included, right (6.5) excluded
    expected = np.zeros((8, 8), bool)
    expected[2:6, 2:6] = True
    assert np.array_equal(mask, expected)


def test_closed_mesh_is_watertight():
    """A closed sphere seen from outside: every pixel is covered 0 or 2 times (front + back)."""
    pos, faces = icosphere(3)
    for eye in [(0.0, 0.0, 3.0), (1.3, 0.7, 2.1)]:
        clip = clip_of(pos, perspective_mvp(eye)).astype(np.float32)
        count = np.asarray(overdraw(clip, faces, width=64, height=64))
        assert set(np.unique(count)) == {0, 2}
        fr = jaxnm.rasterize(clip, faces, width=64, height=64, cull_back=True)
        assert np.array_equal(np.asarray(fr.mask), count == 2)
        assert np.all(np.asarray(fr.front_facing) == np.asarray(fr.mask))


def test_grid_plane_has_no_cracks():
    pos, faces, _ = grid_plane(7)
    clip = clip_of(pos * 0.9, perspective_mvp((0.4, 0.3, 1.6))).astype(np.float32)
    count = np.asarray(overdraw(clip, faces, width=64, height=64))
    assert count.max() == 1
    # inside the projected outline every pixel is covered: compare with one big quad
    outline = np.array([0, 7, 63, 56])  # corners of the 8x8 vertex grid
    big = np.asarray(overdraw(clip[outline], [[0, 1, 2], [0, 2, 3]], width=64, height=64))
    assert np.array_equal(count, big)


def test_camera_inside_box_sees_every_pixel_once():
    """Near-plane clipping: triangles crossing the near plane, camera inside a closed box."""
    pos, faces = box(2.0)
    mvp = perspective_mvp((0.3, -0.2, 0.5), (1.0, 0.4, -0.3), fov=100.0, near=0.05)
    clip = clip_of(pos, mvp).astype(np.float32)
    assert (clip[:, 3] < 0).any()  # some vertices are behind the camera
    count = np.asarray(overdraw(clip, faces, width=48, height=48))
    assert np.all(count == 1)
    ref = rasterize_ref(clip.astype(np.float64), faces, 48, 48, subpixel_bits=8)
    fr = jaxnm.rasterize(clip, faces, width=48, height=48)
    amb = _ambiguous(ref, 2e-3)  # clipped triangles are not snapped (see raster docs)
    assert np.array_equal(np.asarray(fr.triangle_id)[~amb], ref["triangle_id"][~amb])
    # interpolated positions lie on the box surface and on each pixel's view ray
    p = np.asarray(jaxnm.interpolate(pos.astype(np.float32), fr, derivatives=None).value)
    # (a pixel next to an edge may be covered only thanks to the 1/256 px vertex snapping; its
    # unsnapped interpolant then extrapolates slightly past the face, as on a GPU)
    assert np.allclose(np.abs(p).max(-1), 1.0, atol=2e-4)
    ndc = clip_of(p.reshape(-1, 3), mvp)
    ndc = ndc[:, :2] / ndc[:, 3:]
    x = (np.arange(48) + 0.5) / 24 - 1
    y = 1 - (np.arange(48) + 0.5) / 24
    np.testing.assert_allclose(ndc.reshape(48, 48, 2)[..., 0], np.broadcast_to(x, (48, 48)),
                               atol=1e-4)
    np.testing.assert_allclose(ndc.reshape(48, 48, 2)[..., 1],
                               np.broadcast_to(y[:, None], (48, 48)), atol=1e-4)


def test_triangle_crossing_near_plane():
    mvp = perspective_mvp((0.0, 0.0, 1.0), (0.0, 0.0, 0.0), near=0.5)
    pos = np.array([[-1.0, -0.3, -2.0], [1.0, -0.3, -2.0], [0.0, -0.3, 3.0]])  # third behind eye
    clip = clip_of(pos, mvp).astype(np.float32)
    assert clip[2, 3] < 0
    ref = rasterize_ref(clip.astype(np.float64), [[0, 1, 2]], 32, 32, subpixel_bits=8)
    fr = jaxnm.rasterize(clip, [[0, 1, 2]], width=32, height=32)
    amb = _ambiguous(ref, 2e-3)
    assert (ref["triangle_id"] >= 0).sum() > 100
    assert np.array_equal(np.asarray(fr.triangle_id)[~amb], ref["triangle_id"][~amb])
    cov = np.asarray(fr.mask) & (ref["triangle_id"] >= 0)
    np.testing.assert_allclose(np.asarray(fr.depth)[cov],
                               _unsnapped_depth(ref, clip, [[0, 1, 2]])[cov], atol=2e-6)
    p = np.asarray(jaxnm.interpolate(pos.astype(np.float32), fr, derivatives=None).value)
    # every visible point is in front of the near plane (eye z = 1, looking down -z)
    assert np.all(p[np.asarray(fr.mask)][:, 2] <= 0.5 + 1e-5)


def test_a_clipped_triangle_elsewhere_changes_no_other_pixel():
    """A mesh wholly in front of the near plane takes the corners' box (no crossings); one
    triangle crossing the plane, added where it draws nothing, switches the whole mesh to
    the clipped box: every fragment must stay the same."""
    w, h = 48, 40
    pos, faces = random_soup(3)
    clip = clip_of(pos, perspective_mvp((0.3, 0.4, 2.5), aspect=w / h)).astype(np.float32)
    assert np.all(clip[:, 2] >= -clip[:, 3])  # all in front of the near plane
    # off to the side, crossing the near plane: its clipped box lies outside the image
    extra = np.array([[-50.0, 0.0, -0.5, 1.0], [-49.0, 0.0, -0.5, 1.0], [-50.0, 1.0, -3.0, 1.0]],
                     np.float32)
    more = np.concatenate([clip, extra])
    assert (more[:, 2] < -more[:, 3]).sum() == 1  # one corner behind the near plane
    more_faces = np.concatenate([faces, len(clip) + np.arange(3)[None]])
    a = jaxnm.rasterize(clip, faces, width=w, height=h)
    b = jaxnm.rasterize(more, more_faces, width=w, height=h)
    assert np.asarray(a.mask).sum() > 0.2 * w * h
    for field in ("triangle_id", "depth", "front_facing"):
        np.testing.assert_array_equal(np.asarray(getattr(a, field)), np.asarray(getattr(b, field)))


@pytest.mark.parametrize("cull", [False, True])
def test_snapped_setup_equals_the_general_one(cull):
    """Where every vertex is snapped (w = 1) with a depth in [0, 1], the triangle set-up
    takes a short way (corners' x and y only); it must give what the general set-up (near
    plane clipping, divisions, validity checks) gives, bit for bit, but for the sub-pixel
    triangles it drops: random triangles, degenerate ones, ones partly and wholly off
    screen, slivers between pixel centres."""
    w, h = 37, 29
    pos, faces = random_soup(4, n_vertices=60, n_faces=120)
    clip = clip_of(pos, perspective_mvp((0.3, 0.4, 2.5), aspect=w / h)).astype(np.float32)
    extra = np.array([
        [0.1, 0.1, 0, 1], [0.3, 0.3, 0, 1], [0.5, 0.5, 0, 1],  # collinear (before snapping)
        [0.2, 0.2, 0, 1], [0.2, 0.2, 0, 1], [0.2, 0.2, 0, 1],  # a point
        [-9, -9, 0, 1], [-8, -9, 0, 1], [-9, -8, 0, 1],  # off screen
        [-1.5, 0.2, 0.3, 1], [0.1, 0.25, 0.3, 1], [-1.5, 0.3, 0.3, 1],  # partly off screen
        [0.01, 0.0, 0.5, 2], [0.02, 0.0, 0.5, 2], [0.015, 1e-3, 0.5, 2],  # a sliver
    ], np.float32)
    clip = np.concatenate([clip, extra])
    faces = np.concatenate([faces, len(clip) - len(extra) + np.arange(len(extra)).reshape(-1, 3)])
    tri, _ = _window_corners(jnp.asarray(clip), jnp.asarray(faces, jnp.int32), width=w,
                             height=h, subpixel_bits=8)
    hv = np.asarray(tri.vertices)
    assert np.all(hv[:, 3] == 1) and np.all((hv[:, 2] >= 0) & (hv[:, 2] <= 1))
    kw = dict(width=w, height=h, block=4, cull_back=cull)
    # compiled, as in a frame (XLA contracts products into FMAs, eagerly nothing is)
    short = [np.asarray(x) for x in jax.jit(functools.partial(triangles._snapped_setup, **kw))(
        tri.vertices, tri.faces, True)]
    general = [np.asarray(x) for x in jax.jit(functools.partial(triangles._general_setup, **kw))(
        tri.vertices, tri.faces)]
    for a, b in zip(short[:3], general[:3]):  # orientation, first tile
        np.testing.assert_array_equal(a, b)
    # the same slots, but for the triangles the short way drops (they cover nothing: next test)
    kept = short[4] > 0
    np.testing.assert_array_equal(short[4][kept], general[4][kept])
    np.testing.assert_array_equal(short[3][kept], general[3][kept])
    assert kept.sum() > 0.9 * (general[4] > 0).sum()
    counts = general[4]
    assert (counts > 0).sum() > 0.3 * len(faces) and (counts == 0).sum() >= 3
    sigma = np.asarray(general[0])
    assert set(np.unique(sigma)) == {-1, 0, 1}  # both orientations and degenerate ones
    assert np.all(counts[sigma == 0] == 0)
    assert np.any(counts[sigma < 0] > 0) != cull


def _tiny_triangles_on_centres(seed, w, h, n=3000):
    """Sub-pixel triangles with corners on the 1/256 grid a few steps from pixel centres:
    many of their edges and corners fall exactly on a centre (ties), many miss every
    centre by a grid step or less. Clip coordinates (w = 1), depths in (0, 1)."""
    rng = np.random.default_rng(seed)
    centre = np.stack([rng.integers(0, w, n), rng.integers(0, h, n)], -1) + 0.5
    corners = centre[:, None, :] + rng.integers(-160, 161, (n, 3, 2)) / 256.0
    through = rng.random(n) < 0.3  # an edge through the centre: corner 2 opposite corner 1
    corners[through, 2] = 2 * centre[through] - corners[through, 1]
    on = rng.random((n, 3)) < 0.15  # a corner on the centre
    corners = np.where(on[..., None], centre[:, None, :], corners)
    ndc = corners / np.array([w, h]) * 2.0 - 1.0
    z = rng.uniform(-0.9, 0.9, (n, 3, 1))
    clip = np.concatenate([ndc, z, np.ones((n, 3, 1))], -1).reshape(-1, 4).astype(np.float32)
    return clip, np.arange(3 * n).reshape(n, 3)


@pytest.mark.parametrize("cull", [False, True])
def test_triangles_dropped_before_their_slots_cover_nothing(cull, monkeypatch):
    """The short set-up drops triangles whose one or two box centres it finds clearly
    missed (`triangles._misses_centre`). Against the general set-up, which drops none: the
    same winners and depths, and the same count of fragments per pixel (`overdraw`), on
    sub-pixel triangles whose edges run through or within a grid step of pixel centres."""
    w, h = 24, 20
    clip, faces = _tiny_triangles_on_centres(5, w, h)
    tri, _ = _window_corners(jnp.asarray(clip), jnp.asarray(faces, jnp.int32), width=w,
                             height=h, subpixel_bits=8)
    kw = dict(width=w, height=h, block=4, cull_back=cull)
    short = jax.jit(functools.partial(triangles._snapped_setup, **kw))(tri.vertices, tri.faces,
                                                                       True)
    general = jax.jit(functools.partial(triangles._general_setup, **kw))(tri.vertices, tri.faces)
    drawn = [np.asarray(s[4]) > 0 for s in (short, general)]
    assert np.all(drawn[0] <= drawn[1])
    assert (drawn[1] & ~drawn[0]).sum() > 0.15 * drawn[1].sum()  # many dropped
    kw = dict(width=w, height=h, cull_back=cull)
    a = jaxnm.rasterize(clip, faces, **kw)
    count_a = np.asarray(overdraw(clip, faces, **kw))
    jax.clear_caches()
    general_setup = triangles._general_setup
    monkeypatch.setattr(triangles, "_snapped_setup",
                        lambda h, faces, on_grid, **kw: general_setup(h, faces, **kw))
    b = jaxnm.rasterize(clip, faces, **kw)
    count_b = np.asarray(overdraw(clip, faces, **kw))
    jax.clear_caches()
    assert np.asarray(a.mask).sum() > 0.3 * w * h
    assert count_b.sum() > np.asarray(a.mask).sum()  # hidden fragments counted too
    np.testing.assert_array_equal(count_a, count_b)
    for field in ("triangle_id", "depth", "front_facing"):
        np.testing.assert_array_equal(np.asarray(getattr(a, field)), np.asarray(getattr(b, field)))


def test_corners_off_the_snapping_grid_drop_no_triangle():
    """Unsnapped corners with w = 1 (`subpixel_bits=None`, an orthographic camera) take the
    short set-up, but are not on the 1/256 grid that `triangles._misses_centre`'s bound needs:
    no triangle is dropped, and the slots are the general set-up's."""
    w, h = 24, 20
    clip, faces = _tiny_triangles_on_centres(6, w, h, n=600)
    clip[:, :2] += np.float32(1e-4)  # off the grid
    tri, _ = _window_corners(jnp.asarray(clip), jnp.asarray(faces, jnp.int32), width=w,
                             height=h, subpixel_bits=None)
    q = np.asarray(tri.vertices)[:, :2] * 256
    assert np.all(np.asarray(tri.vertices)[:, 3] == 1) and not np.all(q == np.round(q))
    kw = dict(width=w, height=h, block=4, cull_back=False)
    setup = jax.jit(lambda t: triangles.triangle_setup(t, w, h, 4, False))(tri)
    general = jax.jit(functools.partial(triangles._general_setup, **kw))(tri.vertices, tri.faces)
    np.testing.assert_array_equal(np.asarray(setup[4]), np.asarray(general[4]))
    on = jax.jit(functools.partial(triangles._snapped_setup, **kw))(tri.vertices, tri.faces, True)
    assert (np.asarray(on[4]) < np.asarray(general[4])).sum() > 50  # (it would drop these)


def test_a_vertex_outside_the_snapping_range_changes_no_other_pixel():
    """Vertices too far out to be snapped (they keep their w, here 2) send the whole mesh
    through the general set-up: every fragment must stay the same."""
    w, h = 48, 40
    pos, faces = random_soup(3)
    clip = clip_of(pos, perspective_mvp((0.3, 0.4, 2.5), aspect=w / h)).astype(np.float32)
    far_out = np.array([[-6e4, 0.0, 0.0, 2.0], [-6e4 + 2, 0.0, 0.0, 2.0],
                        [-6e4, 2.0, 0.0, 2.0]], np.float32)  # ~7e5 px left of the image
    more = np.concatenate([clip, far_out])
    more_faces = np.concatenate([faces, len(clip) + np.arange(3)[None]])

    tri, _ = _window_corners(jnp.asarray(more), jnp.asarray(more_faces, jnp.int32),
                             width=w, height=h, subpixel_bits=8)
    assert not np.all(np.asarray(tri.vertices)[:, 3] == 1)
    a = jaxnm.rasterize(clip, faces, width=w, height=h)
    b = jaxnm.rasterize(more, more_faces, width=w, height=h)
    assert np.asarray(a.mask).sum() > 0.2 * w * h
    for field in ("triangle_id", "depth", "front_facing"):
        np.testing.assert_array_equal(np.asarray(getattr(a, field)), np.asarray(getattr(b, field)))


def test_fully_clipped_and_degenerate_triangles_draw_nothing():
    clip = np.array([
        [0, 0, -3, 1], [1, 0, -3, 1], [0, 1, -3, 1],   # in front of near plane entirely
        [0, 0, 0, 1], [1, 1, 0, 1], [2, 2, 0, 1],      # collinear: zero area
        [0, 0, 0, 1], [0, 0, 0, 1], [0, 0, 0, 1],      # a point
        [-9, -9, 0, 1], [-8, -9, 0, 1], [-9, -8, 0, 1],  # off screen
    ], np.float32)
    faces = np.arange(12).reshape(4, 3)
    fr = jaxnm.rasterize(clip, faces, width=16, height=16)
    assert not np.asarray(fr.mask).any()
    b = jaxnm.barycentrics(fr, derivatives="fine")
    assert np.all(np.isfinite(np.asarray(b.ddx)))


def test_depth_test_nearest_wins_and_ties_go_to_lower_index():
    near = [[-1, -1, -0.5, 1], [1, -1, -0.5, 1], [0, 1, -0.5, 1]]
    far = [[-1, -1, 0.5, 1], [1, -1, 0.5, 1], [0, 1, 0.5, 1]]
    clip = np.array(far + near + near + far, np.float32)
    faces = np.arange(12).reshape(4, 3)
    tid = np.asarray(jaxnm.rasterize(clip, faces, width=16, height=16).triangle_id)
    assert set(np.unique(tid)) == {-1, 1}


def test_depth_keys_order_fragments_as_the_depth_test():
    """One scatter-min of 64-bit keys (32-bit depths) and the pair of depth and triangle
    buffers (wider depths) both keep, per pixel, the nearest fragment and on equal depth the
    lowest triangle index (-0 equal to +0); checked against a plain loop."""

    rng = np.random.default_rng(0)
    tiles, block, slots = 6, 2, 300
    values = np.array([0.0, -0.0, 0.25, 0.5, 1.0, np.inf], np.float32)
    depth = values[rng.integers(0, len(values), (slots, block, block))]
    t = rng.integers(0, 40, slots).astype(np.int32)
    tile = rng.integers(0, tiles, slots).astype(np.int32)
    want = np.full((tiles, block, block), tiled.NO_TRIANGLE, np.int64)
    near = np.full((tiles, block, block), np.inf, np.float32)
    for s in range(slots):
        for dy in range(block):
            for dx in range(block):
                d, w = depth[s, dy, dx], want[tile[s], dy, dx]
                if d < np.inf and (d < near[tile[s], dy, dx] or (d == near[tile[s], dy, dx]
                                                                  and t[s] < w)):
                    near[tile[s], dy, dx], want[tile[s], dy, dx] = d, t[s]
    assert (want != tiled.NO_TRIANGLE).mean() > 0.5
    keyed = tiled.empty_buffer(tiles, block, jnp.float32)
    with jax.enable_x64(True):
        keyed = keyed.at[tile].min(tiled.depth_keys(jnp.asarray(depth), jnp.asarray(t)))
    assert np.array_equal(np.asarray(tiled.winners(keyed)), want)
    with jax.enable_x64(True):
        pair = tiled.empty_buffer(tiles, block, jnp.float64)
        assert isinstance(pair, tuple)
        for half in (slice(0, slots // 2), slice(slots // 2, slots)):  # two rounds
            pair = tiled._write_pair(pair, jnp.asarray(tile[half]),
                                           jnp.asarray(depth[half], jnp.float64),
                                           jnp.asarray(t[half]))
        assert np.array_equal(np.asarray(tiled.winners(pair)), want)


@pytest.mark.parametrize("x64", [False, True])
def test_float64_clip_and_64_bit_callers_rasterize_alike(x64):
    """With ``jax_enable_x64`` on, float32 input takes the keyed depth test and float64 input
    the pair of buffers; both agree with the float64 reference away from edges."""
    pos, faces = random_soup(4)
    clip = clip_of(pos, perspective_mvp((0.3, 0.4, 2.5))).astype(np.float32)
    ref = rasterize_ref(clip.astype(np.float64), faces, 40, 40, subpixel_bits=8)
    amb = _ambiguous(ref)
    with jax.enable_x64(x64):
        dtype = jnp.float64 if x64 else jnp.float32
        tid = np.asarray(jaxnm.rasterize(jnp.asarray(clip, dtype), faces, width=40,
                                         height=40).triangle_id)
        tid32 = np.asarray(jaxnm.rasterize(jnp.asarray(clip), faces, width=40,
                                           height=40).triangle_id)
        # and in many passes (the frames of over 2**30 slots)
        from jaxnm import raster

        kw = dict(width=40, height=40, cull_back=False, subpixel_bits=8)
        for c, want in ((jnp.asarray(clip, dtype), tid), (jnp.asarray(clip), tid32)):
            passes = raster._rasterize(c, jnp.asarray(faces, jnp.int32),
                                       strategy=raster.RasterStrategy(slots=64, pass_slots=32),
                                       **kw)
            assert np.array_equal(np.asarray(passes[0]), want)
    assert (tid >= 0).mean() > 0.2
    assert np.array_equal(tid[~amb], ref["triangle_id"][~amb])
    assert np.array_equal(tid32[~amb], ref["triangle_id"][~amb])


def test_triangle_ids_and_orientation_give_rasterize_and_compact():
    """`triangle_ids` is `rasterize`'s ids, its orientations give `rasterize`'s facing, and
    `compact` given them packs the same fragments as without (which computes the facing
    from each fragment's corners)."""
    from jaxnm.raster import compact, triangle_ids

    pos, faces = random_soup(5)
    clip = clip_of(pos, perspective_mvp((0.3, 0.4, 2.5))).astype(np.float32)
    fr = jaxnm.rasterize(clip, faces, width=40, height=40)
    tid, orientation = triangle_ids(clip, faces, width=40, height=40)
    pack = compact
    assert np.array_equal(np.asarray(tid), np.asarray(fr.triangle_id))
    covered = np.asarray(fr.mask)
    front = np.asarray(orientation)[np.maximum(np.asarray(tid), 0)] > 0
    assert covered.mean() > 0.2 and 0 < front[covered].mean() < 1  # both facings seen
    assert np.array_equal(front & covered, np.asarray(fr.front_facing))
    n = int(covered.sum())
    # fewer slots than triangles (the facing from each fragment's corners: some covered
    # pixels dropped, the same in both), and more (from each triangle's)
    for capacity in (len(faces) - 1, n + 3, 40 * 40):
        a, ia = pack(fr.triangle_id, fr.clip, fr.faces, capacity)
        b, ib = pack(fr.triangle_id, fr.clip, fr.faces, capacity, orientation=orientation)
        assert np.array_equal(np.asarray(ia), np.asarray(ib))
        for field in ("triangle_id", "front_facing", "depth", "pixels"):
            assert np.array_equal(np.asarray(getattr(a, field)), np.asarray(getattr(b, field)))


def test_visibility_helpers_called_eagerly_compile_once():
    """`triangle_ids`, `compact` and `expand` called outside any jit each run one compiled
    program (not their operations one by one), and a second call compiles nothing; the
    round trip puts each pixel's triangle back where `rasterize` has it."""
    from jaxnm.raster import compact, expand, triangle_ids

    compiles, counting = [], [True]

    def listen(name, seconds, **kwargs):
        if counting[0] and name == "/jax/core/compile/backend_compile_duration":
            compiles.append(kwargs.get("fun_name", "?"))

    jax.monitoring.register_event_duration_secs_listener(listen)  # (0.8.0: cannot unregister)
    pos, faces = random_soup(7)
    clip = jnp.asarray(clip_of(pos, perspective_mvp((0.3, 0.4, 2.5))).astype(np.float32))
    faces = jnp.asarray(faces, jnp.int32)

    def round_trip():
        tid, orientation = triangle_ids(clip, faces, width=40, height=40)
        frags, index = compact(tid, clip, faces, 40 * 40, orientation=orientation)
        return jax.block_until_ready(expand(frags.triangle_id, index, 40, 40, fill=-1))

    try:
        first = round_trip()
        n_first = len(compiles)
        again = round_trip()
    finally:
        counting[0] = False
    assert n_first <= 6, compiles  # the three programs and a few small ones, not hundreds
    assert len(compiles) == n_first, compiles[n_first:]
    ref = jaxnm.rasterize(clip, faces, width=40, height=40)
    assert np.asarray(ref.mask).mean() > 0.2
    np.testing.assert_array_equal(np.asarray(first), np.asarray(ref.triangle_id))
    np.testing.assert_array_equal(np.asarray(again), np.asarray(first))


def test_many_rounds_and_passes_give_the_same_image():
    """A tiny slot budget forces many rounds, a tiny pass size many passes (the int32
    overflow path of frames with over 2**30 slots; `raster.RasterStrategy`): the result must
    not change."""
    from jaxnm import raster
    from jaxnm.raster import RasterStrategy

    pos, faces = icosphere(2)
    clip = clip_of(pos, perspective_mvp((0.2, 0.5, 2.6))).astype(np.float32)
    a = jaxnm.rasterize(clip, faces, width=40, height=40)
    b = jaxnm.rasterize(clip, faces, width=40, height=40,
                        strategy=RasterStrategy(slots=7, block=2))
    assert np.array_equal(np.asarray(a.triangle_id), np.asarray(b.triangle_id))

    kw = dict(width=40, height=40, cull_back=False, subpixel_bits=8)
    passes = RasterStrategy(slots=64, pass_slots=32)
    reference = np.asarray(raster.overdraw(clip, faces, width=40, height=40))
    c_tid, c_depth, c_front = raster._rasterize(
        jnp.asarray(clip), jnp.asarray(faces, jnp.int32), strategy=passes, **kw)
    assert np.array_equal(np.asarray(a.triangle_id), np.asarray(c_tid))
    assert np.array_equal(np.asarray(a.front_facing), np.asarray(c_front))
    counts = raster._overdraw(jnp.asarray(clip), jnp.asarray(faces, jnp.int32),
                              strategy=passes, **kw)
    assert np.array_equal(np.asarray(counts), reference)
    # that was many passes
    tri, _ = _window_corners(jnp.asarray(clip), jnp.asarray(faces, jnp.int32), width=40,
                             height=40, subpixel_bits=8)
    count = jax.jit(triangles.triangle_setup, static_argnums=(1, 2, 3, 4))(tri, 40, 40, 4,
                                                                           False)[4]
    assert int(slot_passes(count, 32)[1]) > 5
    # a pass size the faces x tiles bound exceeds but the frame's slots fit: one pass,
    # found by the float32 sum (not the exact running sums), the same image again
    total = int(jnp.sum(count))
    one = 1 << total.bit_length()
    assert len(faces) * 100 > one > total
    d_tid, _, _ = raster._rasterize(jnp.asarray(clip), jnp.asarray(faces, jnp.int32),
                                    strategy=RasterStrategy(slots=64, pass_slots=one), **kw)
    assert np.array_equal(np.asarray(a.triangle_id), np.asarray(d_tid))


def test_the_strategy_by_backend_does_not_change_the_image():
    """`default_strategy`: a GPU takes larger rounds than the CPU
    (`jaxnm._exec.slots.MAX_SLOTS`); the frame is the same."""
    from jaxnm import procedural, raster

    def strategy(faces, size, backend):
        return raster.default_strategy(faces, size, size, backend=backend)

    assert strategy(20480, 512, "cpu").slots == 2**15
    assert strategy(20480, 512, "gpu").slots == 2**17
    assert strategy(200_000, 1024, "gpu").slots == 2**19
    assert strategy(10, 16, "gpu").slots == 256  # small scenes: one round
    torus = procedural.torus(1.0, 0.4, 128, 80)
    clip = clip_of(np.asarray(torus.positions, np.float64),
                   perspective_mvp((0.3, 2.0, 2.2))).astype(np.float32)
    kw = dict(width=48, height=48)
    cpu, gpu = (strategy(len(torus.faces), 48, b) for b in ("cpu", "gpu"))
    assert (cpu.slots, gpu.slots) == (2**15, 2**17)
    a = jaxnm.rasterize(clip, torus.faces, strategy=cpu, **kw)
    b = jaxnm.rasterize(clip, torus.faces, strategy=gpu, **kw)
    assert (np.asarray(a.triangle_id) >= 0).mean() > 0.2
    for field in ("triangle_id", "depth", "front_facing"):
        assert np.array_equal(np.asarray(getattr(a, field)), np.asarray(getattr(b, field)))
    with pytest.raises(ValueError, match="power of two"):
        raster.RasterStrategy(pass_slots=3)
    with pytest.raises(ValueError, match="`block` must be a positive int"):
        raster.RasterStrategy(block=0)


def test_slot_passes_count_past_int32():
    """Each triangle's pass is floor(first slot / pass size), its first slot counted exactly
    though the frame's total wraps around uint32 several times."""

    rng = np.random.default_rng(3)
    counts = rng.integers(0, 2**28, 200).astype(np.int64)
    counts[rng.random(200) < 0.3] = 0
    starts = np.cumsum(counts) - counts
    assert starts[-1] > 3 * 2**32
    for pass_slots in (2**30, 2**24):
        passes, n = slot_passes(jnp.asarray(counts, jnp.int32), pass_slots)
        np.testing.assert_array_equal(np.asarray(passes), starts // pass_slots)
        assert int(n) == starts[-1] // pass_slots + 1


@pytest.mark.parametrize(
    "clip,faces,kw,match",
    [
        (np.zeros((3, 4)), [[0, 1, 2]], dict(width=0, height=8), "image size"),
        (np.zeros((3, 4)), [[0, 1, 2]], dict(width=8, height=-1), "image size"),
        (np.zeros((3, 3)), [[0, 1, 2]], dict(width=8, height=8), r"\(V, 4\)"),
        (np.zeros((3, 4)), [[0, 1]], dict(width=8, height=8), r"\(F, 3\)"),
        (np.zeros((3, 4)), [[0, 1, 3]], dict(width=8, height=8), "face indices"),
        (np.zeros((3, 4)), [[0, -1, 2]], dict(width=8, height=8), "face indices"),
        (np.array([[0, 0, 0, 1], [np.nan, 0, 0, 1], [0, 1, 0, 1]]), [[0, 1, 2]],
         dict(width=8, height=8), "non-finite"),
        (np.zeros((3, 4)), [[0.0, 1.0, 2.0]], dict(width=8, height=8), "integers"),
        (np.zeros((3, 4)), [[0, 1, 2]], dict(width=65536, height=32768), "too large"),
        (np.zeros((3, 4)), [[0, 1, 2]],
         dict(width=32768, height=32768, strategy=RasterStrategy(block=1)), "too large"),
    ],
)
def test_bad_arguments_raise_clear_errors(clip, faces, kw, match):
    with pytest.raises(ValueError, match=match):
        jaxnm.rasterize(clip, np.asarray(faces), **kw)


def test_no_faces_gives_background():
    fr = jaxnm.rasterize(np.zeros((3, 4), np.float32), np.zeros((0, 3), np.int32), width=4,
                         height=4)
    assert np.all(np.asarray(fr.triangle_id) == -1)
