"""jaxnm.transfer.raycast_normal_map: ray-cast bakes from a high-poly mesh to a low-poly one.

Against analytic answers (a sphere, rays through triangle edges and vertices), against
itself (chunking changes no bit), its messages on bad input, and against Blender's Cycles
"selected to active" bake (tests/blender_ref.py, run in its own environment; skipped
without it except in CI, JAXNM_REQUIRE_BLENDER=1): Suzanne subdivided and displaced onto
Suzanne (an extrusion and a max ray distance), and a displaced torus onto a torus with
mirrored uvs (a cage object), both sides at 32 samples per texel, within 0.2 deg mean and
1 deg p99 inside the uv triangles, the same texels covered and the same margin; and
Cycles' sample jitter, where it shows (256 samples on large triangles).
"""

import dataclasses
import os
import re
import subprocess
import sys
import warnings
from pathlib import Path

import jax.numpy as jnp
import numpy as np
import pytest

import jaxnm
from jaxnm import frames as F
from jaxnm.transfer import BakeWarning, raycast_normal_map
from scripts.benchmarks import bake_pairs as P
from scripts.studies import blender_bake_cases as C

ROOT = Path(__file__).resolve().parents[1]
BLENDER = C.blender_python()


def _angle(a, b):
    """Degrees between rows, atan2(|a x b|, a . b) in float64."""
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    return np.degrees(np.arctan2(np.linalg.norm(np.cross(a, b), axis=-1), np.sum(a * b, -1)))


def _mesh(p, f, uv=None, n=None):
    return jaxnm.Mesh(jnp.asarray(p, jnp.float32), jnp.asarray(f, jnp.int32),
                      None if uv is None else jnp.asarray(uv, jnp.float32),
                      None if n is None else jnp.asarray(n, jnp.float32))


def uv_sphere(radius, n_lon=24, n_lat=12):
    """A latitude-longitude sphere with a uv seam and radial normals."""
    th, ph = np.meshgrid(np.linspace(0, np.pi, n_lat + 1), np.linspace(0, 2 * np.pi, n_lon + 1),
                         indexing="ij")
    unit = np.stack([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)], -1)
    uv = np.stack([ph / (2 * np.pi), 1 - th / np.pi], -1).reshape(-1, 2)
    k = np.arange((n_lat + 1) * (n_lon + 1)).reshape(n_lat + 1, n_lon + 1)
    a, b, c, d = k[:-1, :-1], k[:-1, 1:], k[1:, 1:], k[1:, :-1]
    faces = np.concatenate([np.stack([a, d, b], -1)[1:].reshape(-1, 3),
                            np.stack([b, d, c], -1)[:-1].reshape(-1, 3)])
    unit = unit.reshape(-1, 3)
    return _mesh(radius * unit, faces, uv, unit)


def ico_sphere(subdivisions=4):
    """A unit icosphere whose vertex normals are its (unit) positions."""
    import trimesh

    m = trimesh.creation.icosphere(subdivisions=subdivisions)
    p = m.vertices / np.linalg.norm(m.vertices, axis=1, keepdims=True)
    return _mesh(p, m.faces, None, p)


def _texel_points(res, low):
    """Per baked texel (inside, hit): its LOW face and barycentrics, recomputed from its uv."""
    h, w = res.face.shape
    r, c = np.nonzero(res.inside & ~res.missed)
    f = res.face[r, c]
    q = np.stack([(c + 0.5) / w, 1 - (r + 0.5) / h], -1)
    t = np.asarray(low.uv, np.float64)[np.asarray(low.faces)[f]]
    m = np.stack([t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]], -1)  # columns: uv edges
    l12 = np.linalg.solve(m, (q - t[:, 0])[..., None])[..., 0]
    return r, c, f, np.concatenate([1 - l12.sum(-1, keepdims=True), l12], -1)


def _decode(low, frame, f, bary, m):
    """The renderer's decode of map vectors ``m`` at LOW points (jaxnm.frames)."""
    corners = np.asarray(low.faces)[f]

    def interp(a, per_corner=False):
        a = np.asarray(a, np.float64)
        return np.einsum("tk,tkc->tc", bary, a[f] if per_corner else a[corners])

    n = interp(low.normals)
    if frame == "vertex":
        fr = F.compute_frame("vertex", jnp.asarray(n, jnp.float32), inputs=F.FrameInputs(
            tangent=jnp.asarray(interp(low.tangents, True), jnp.float32)))
    else:
        fr = F.compute_frame("exact", jnp.asarray(n, jnp.float32), inputs=F.FrameInputs(
            tri_p=jnp.asarray(np.asarray(low.positions)[corners], jnp.float32),
            tri_uv=jnp.asarray(np.asarray(low.uv)[corners], jnp.float32)))
    return np.asarray(F.perturb_normal(fr, jnp.asarray(m, jnp.float32)), np.float64), interp(
        low.positions)


# --------------------------------------------------------------------------------------
# analytic answers
# --------------------------------------------------------------------------------------


@pytest.mark.parametrize("frame", ["vertex", "cotangent"])
@pytest.mark.parametrize("with_cage_mesh", [False, True])
def test_a_sphere_bakes_its_radial_normals(frame, with_cage_mesh):
    """LOW inscribed in HIGH, both with radial normals: every ray passes through the
    centre (LOW's interpolated normal is parallel to its point; a cage mesh scaled about the
    centre aims there too), and HIGH's interpolated normal at any point of a triangle is
    parallel to that point. So the decoded normal must be the direction of the texel's own
    point on LOW, to float32 rounding, wherever the ray hits."""
    low = uv_sphere(0.9).with_tangents()
    cage = None
    if with_cage_mesh:
        cage = dataclasses.replace(low, positions=low.positions * 1.3)
    res = raycast_normal_map(ico_sphere(), low, 64, frame=frame, cage_mesh=cage)
    assert res.texels_missed == 0 and res.texels_inside > 3000
    assert res.cage_source == ("mesh" if with_cage_mesh else "automatic")
    r, c, f, bary = _texel_points(res, low)
    decoded, p = _decode(low, frame, f, bary, res.normals[r, c])
    err = _angle(decoded, p)
    assert err.max() < 2e-3, err.max()


@pytest.mark.parametrize("engine", ["direct", "embreex"])
def test_rays_through_edges_and_vertices_hit(engine):
    """HIGH is a grid of triangles at z = 0 with normals that vary; at 8x8 every texel's ray
    meets a grid vertex, at 16x16 the midpoint of a diagonal edge. Embree runs in robust
    mode: no ray falls through, and each gets the normal interpolated there."""
    k = np.arange(17) / 16
    x, y = np.meshgrid(k, k, indexing="xy")
    p = np.stack([x, y, 0 * x], -1).reshape(-1, 3)
    n = np.stack([0.6 * (x - 0.5), -0.4 * (y - 0.5), np.ones_like(x)], -1).reshape(-1, 3)
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    j, i = np.meshgrid(np.arange(16), np.arange(16), indexing="ij")
    a = (j * 17 + i).ravel()
    faces = np.concatenate([np.stack([a, a + 1, a + 18], 1), np.stack([a, a + 18, a + 17], 1)])
    high = _mesh(p, faces, None, n)
    q = np.array([[0, 0, 0.25], [1, 0, 0.25], [1, 1, 0.25], [0, 1, 0.25]])
    low = _mesh(q, [[0, 1, 2], [0, 2, 3]], q[:, :2], np.tile([0.0, 0, 1], (4, 1)))
    for size in (8, 16):
        res = raycast_normal_map(high, low, size, margin=0, engine=engine)
        assert res.texels_inside == size * size and res.texels_missed == 0
        c = (np.arange(size) + 0.5) / size
        u, v = np.meshgrid(c, c[::-1], indexing="xy")
        want = np.stack([0.6 * (u - 0.5), -0.4 * (v - 0.5), np.ones_like(u)], -1)
        if size == 16:  # the mean of the two unit normals at the ends of the diagonal
            d = 0.5 / 16
            lo = np.stack([0.6 * (u - d - 0.5), -0.4 * (v - d - 0.5), np.ones_like(u)], -1)
            hi = np.stack([0.6 * (u + d - 0.5), -0.4 * (v + d - 0.5), np.ones_like(u)], -1)
            want = (lo / np.linalg.norm(lo, axis=-1, keepdims=True)
                    + hi / np.linalg.norm(hi, axis=-1, keepdims=True))
        # a flat LOW with uv = xy has the tangent frame (x, y, z): the map is the normal
        assert _angle(res.normals, want).max() < 1e-3


@pytest.mark.parametrize("engine", ["direct", "embreex"])
def test_texels_on_the_rim_of_an_open_surface_hit(engine):
    """LOW and HIGH are the same open square at z = 0, LOW's uvs placed so that the 16x16
    map's outer texel centres lie on the square's edges (as xatlas places a chart's rim):
    their rays graze HIGH's boundary. Every texel hits, with HIGH's normal (z: the map's
    normal, LOW's frame being x, y, z)."""
    k = np.arange(5) / 4
    x, y = np.meshgrid(k, k, indexing="xy")
    p = np.stack([x, y, 0 * x], -1).reshape(-1, 3)
    j, i = np.meshgrid(np.arange(4), np.arange(4), indexing="ij")
    a = (j * 5 + i).ravel()
    faces = np.concatenate([np.stack([a, a + 1, a + 6], 1), np.stack([a, a + 6, a + 5], 1)])
    high = _mesh(p, faces, None, np.tile([0.0, 0, 1], (len(p), 1)))
    q = np.array([[0, 0, 0.0], [1, 0, 0], [1, 1, 0], [0, 1, 0]])
    uv = 1 / 32 + q[:, :2] * 15 / 16  # texel centres (c + 1/2) / 16 at x, y = c / 15
    low = _mesh(q, [[0, 1, 2], [0, 2, 3]], uv, np.tile([0.0, 0, 1], (4, 1)))
    res = raycast_normal_map(high, low, 16, margin=0, engine=engine)
    assert res.texels_inside == 256 and res.texels_missed == 0
    assert _angle(res.normals.reshape(-1, 3), [0, 0, 1]).max() < 1e-3


def test_chunks_threads_and_engines_change_no_bit():
    low, high = uv_sphere(0.9), ico_sphere(3)
    one = raycast_normal_map(high, low, 48, samples=4, cage=0.2, workers=1)
    for kw in (dict(chunk_texels=97, workers=3), dict(engine="embreex"),
               dict(engine="direct", chunk_texels=1000, workers=2)):
        other = raycast_normal_map(high, low, 48, samples=4, cage=0.2, **kw)
        assert np.array_equal(one.normals, other.normals), kw
        assert np.array_equal(one.missed, other.missed) and np.array_equal(one.filled,
                                                                            other.filled)
    other = raycast_normal_map(high, low, 48, samples=4, cage=0.2, seed=1)
    assert not np.array_equal(one.normals, other.normals)  # the jitter does depend on the seed


def test_the_margin_extends_blenders_way():
    """Each pass fills the empty texels that touch a filled one across an edge, with the
    2-1 weighted mean of their filled neighbours."""
    from jaxnm.transfer._texels import extend_margin

    vals = np.zeros((5, 5, 1))
    mask = np.zeros((5, 5), bool)
    vals[2, 2], mask[2, 2] = 4.0, True
    vals[2, 3], mask[2, 3] = 1.0, True
    out, done = extend_margin(vals, mask, 1)
    assert done.sum() == 2 + 6 and not done[1, 1]  # the corner (1, 1) touches only diagonally
    assert out[1, 2, 0] == pytest.approx((2 * 4 + 1) / 3)  # edge 4, corner 1
    assert out[2, 1, 0] == 4.0 and out[2, 4, 0] == 1.0
    out2, done2 = extend_margin(vals, mask, 2)
    assert done2[1, 1] and done2.sum() > done.sum()


# --------------------------------------------------------------------------------------
# bad input: one line each, naming the mesh
# --------------------------------------------------------------------------------------


def test_meshes_that_do_not_overlap_are_an_error():
    far = dataclasses.replace(ico_sphere(2), positions=ico_sphere(2).positions + 10.0)
    with pytest.raises(ValueError, match=r"^hi.obj and lo.obj do not overlap: none of the \d+ "
                                         r"rays"):
        raycast_normal_map(far, uv_sphere(0.9), 16, cage=0.2, high_name="hi.obj",
                           low_name="lo.obj")


def test_input_errors_name_the_mesh():
    low, high = uv_sphere(0.9), ico_sphere(2)
    with pytest.raises(ValueError, match="^lo.obj: the mesh has no texture coordinates"):
        raycast_normal_map(high, dataclasses.replace(low, uv=None), 16, low_name="lo.obj")
    with pytest.raises(ValueError, match="frame must be one of vertex, cotangent"):
        raycast_normal_map(high, low, 16, frame="nonperspective")
    with pytest.raises(ValueError, match="samples must be an int >= 1"):
        raycast_normal_map(high, low, 16, samples=0)
    with pytest.raises(ValueError, match="not both"):
        raycast_normal_map(high, low, 16, cage=0.1, cage_mesh=low)
    with pytest.raises(ValueError, match="^cage mesh: a cage mesh must have LOW's triangles "
                                         "in LOW's order; it has 120 faces, LOW 528$"):
        raycast_normal_map(high, low, 16, cage_mesh=uv_sphere(1.2, 12, 6))
    turned = dataclasses.replace(low, faces=np.asarray(low.faces)[:, [1, 2, 0]])
    with pytest.raises(ValueError, match=r"^cage.obj: a cage mesh must have lo.obj's triangles"
                                         r" in lo.obj's order; its faces put \d+ of lo.obj's "
                                         r"vertices at two places \(the first in face 0\)$"):
        raycast_normal_map(high, low, 16, cage_mesh=turned, low_name="lo.obj",
                           cage_name="cage.obj")


def test_a_cage_split_at_other_seams_moves_the_same_points():
    """A cage is matched to LOW corner by corner, face by face: a cage welded where LOW is
    split at its uv seam (a cage saved without uvs) starts the rays where LOW's own vertices
    moved the same way start them, ray for ray: the same map, bit for bit."""
    from jaxnm.transfer.remesh import weld

    low = uv_sphere(0.9).with_tangents()
    cage = dataclasses.replace(low, positions=low.positions * 1.3)
    p, f = weld(np.asarray(cage.positions), np.asarray(cage.faces))
    welded = jaxnm.Mesh(positions=jnp.asarray(p, jnp.float32), faces=jnp.asarray(f, jnp.int32))
    assert len(p) < len(np.asarray(low.positions))  # split at the seam and the poles
    own = raycast_normal_map(ico_sphere(3), low, 32, cage_mesh=cage)
    res = raycast_normal_map(ico_sphere(3), low, 32, cage_mesh=welded)
    np.testing.assert_array_equal(res.normals, own.normals)
    assert res.texels_inside > 500 and res.texels_missed == 0


def test_bad_arguments_and_non_finite_attributes_are_named_before_any_ray():
    low, high = uv_sphere(0.9), ico_sphere(2)
    uv = np.asarray(low.uv).copy()
    uv[[3, 7]] = np.nan
    normals = np.asarray(low.normals).copy()
    normals[5] = np.inf
    for kw, message in (
            (dict(low=dataclasses.replace(low, uv=jnp.asarray(uv))),
             "lo.obj: 2 of 325 vertex uvs are NaN or infinite"),
            (dict(low=dataclasses.replace(low, normals=jnp.asarray(normals))),
             "lo.obj: 1 of 325 vertex normals are NaN or infinite"),
            (dict(size=True), "raycast_normal_map: size must be a positive int or (height, "
                              "width), got True"),
            (dict(chunk_texels=0), "raycast_normal_map: chunk_texels must be an int >= 1 or "
                                   "None, got 0"),
            (dict(workers=1.5), "raycast_normal_map: workers must be an int >= 1 or None, "
                                "got 1.5"),
            (dict(engine="optix"), "raycast_normal_map: engine must be one of direct, embreex "
                                   "or None, got 'optix'")):
        args = dict(high=high, low=low, size=16, low_name="lo.obj") | kw
        with pytest.raises(ValueError, match="^" + re.escape(message) + "$"):
            raycast_normal_map(args.pop("high"), args.pop("low"), args.pop("size"), **args)


def test_what_is_not_a_mesh_is_refused_naming_it():
    with pytest.raises(TypeError, match=r"^hi.obj: expected a jaxnm Mesh "
                                        r"\(jaxnm.io.load_mesh\), got str$"):
        raycast_normal_map("hi.obj", uv_sphere(0.9), 16, high_name="hi.obj")


def test_a_cage_that_misses_is_reported_with_where():
    """HIGH is the upper half of the sphere: the rays of LOW's lower half hit nothing within
    the max distance; the warning counts them and says where, the margin fills what it
    reaches."""
    full = ico_sphere(3)
    f = np.asarray(full.faces)
    upper = f[np.asarray(full.positions)[f][:, :, 2].min(1) > 0]
    high = dataclasses.replace(full, faces=jnp.asarray(upper, jnp.int32))
    with pytest.warns(BakeWarning, match=r"^lo.obj: the rays of \d+ of \d+ texels hit nothing "
                                         r"on HIGH \(given cage 0.2\): uv \[0.0"):
        res = raycast_normal_map(high, uv_sphere(0.9), 32, cage=0.2, max_distance=0.5,
                                 low_name="lo.obj")
    assert 0.4 < res.texels_missed / res.texels_inside < 0.6
    v_missed = 1 - (np.nonzero(res.missed)[0] + 0.5) / 32
    assert v_missed.max() < 0.55 and res.missed_uv_box[3] < 0.55  # the lower half: v < 1/2
    assert res.missed_faces.size > 0 and res.filled[res.missed].any()


def test_a_low_mesh_wound_inwards_warns():
    """LOW's faces reversed, its normals computed from them (inwards): a closed mesh turned
    inside out is named, and the rays find HIGH facing away from it (the map's z < 0). The
    same LOW wound outwards warns of neither."""
    high, low = uv_sphere(1.0), uv_sphere(0.9)
    out = _mesh(low.positions, low.faces, low.uv)
    inward = _mesh(low.positions, np.asarray(low.faces)[:, ::-1], low.uv)
    with pytest.warns(BakeWarning) as record:
        res = raycast_normal_map(high, inward, 16, low_name="lo.obj")
    said = [str(w.message) for w in record]
    assert any(m.startswith("lo.obj: a closed mesh whose faces wind inwards") for m in said)
    away = [re.match(r"HIGH faces away from lo.obj: at (\d+) of (\d+) texels whose ray hit it",
                     m) for m in said]
    k, n = map(int, next(m.groups() for m in away if m))
    assert n == int((res.inside & ~res.missed).sum()) and k > n // 2
    assert np.median(res.normals[res.inside & ~res.missed][:, 2]) < 0
    with warnings.catch_warnings():
        warnings.simplefilter("error", BakeWarning)
        res = raycast_normal_map(high, out, 16, low_name="lo.obj")
    assert np.median(res.normals[res.inside & ~res.missed][:, 2]) > 0.99


def test_uvs_outside_the_unit_square_warn():
    """A tiled (or UDIM) layout: the map covers [0, 1] only, so the second tile's triangle
    gets no texel of its own; it warns, naming the range. A corner a hair past 1 does not."""
    plane = _mesh(np.array([[-1, -1, 0], [2, -1, 0], [2, 2, 0], [-1, 2, 0]]), [[0, 1, 2],
                                                                               [0, 2, 3]],
                  None, np.tile([0.0, 0, 1], (4, 1)))
    q = np.array([[0, 0, 0.1], [1, 0, 0.1], [1, 1, 0.1], [0, 1, 0.1]])
    two = np.concatenate([q, q + [1, 0, 0]])  # side by side, the second in the next tile
    low = _mesh(two, [[0, 1, 2], [4, 5, 6]], two[:, :2], np.tile([0.0, 0, 1], (8, 1)))
    with pytest.warns(BakeWarning, match=r"^LOW: 1 of 2 triangles reach outside the unit uv "
                                         r"square \(u 1 to 2, v 0 to 1; first: face 1\); the "
                                         r"map covers \[0, 1\] only"):
        res = raycast_normal_map(plane, low, 8, cage=0.2)
    assert set(np.unique(res.face[res.inside])) == {0}  # the second tile's triangle: no texel
    hair = _mesh(q, [[0, 1, 2], [0, 2, 3]], q[:, :2] * (1 + 1e-6), np.tile([0.0, 0, 1], (4, 1)))
    with warnings.catch_warnings():
        warnings.simplefilter("error", BakeWarning)
        raycast_normal_map(plane, hair, 8, cage=0.2)


def test_overlapping_islands_degenerate_and_non_manifold_triangles_warn():
    q = np.array([[0, 0, 0.1], [1, 0, 0.1], [1, 1, 0.1], [0, 1, 0.1]])
    plane = _mesh(np.array([[-1, -1, 0], [2, -1, 0], [2, 2, 0], [-1, 2, 0]]), [[0, 1, 2],
                                                                               [0, 2, 3]],
                  None, np.tile([0.0, 0, 1], (4, 1)))
    two = np.concatenate([q, q + [0, 0, 0.1]])  # a second quad above, the same uvs
    uv = np.concatenate([q[:, :2], q[:, :2]])
    low = _mesh(two, [[0, 1, 2], [0, 2, 3], [4, 5, 6], [4, 6, 7]], uv, np.tile([0.0, 0, 1], (8, 1)))
    with pytest.warns(BakeWarning, match=r"^LOW: \d+ texels lie inside more than one uv "
                                         r"triangle \(overlapping uv islands; first: faces 1 and "
                                         r"3\).*highest index"):
        res = raycast_normal_map(plane, low, 8, cage=0.2)
    assert res.overlapping > 0 and set(np.unique(res.face[res.inside])) == {2, 3}
    degenerate = _mesh(np.concatenate([q, [[0.5, 0.5, 0.1]]]), [[0, 1, 2], [0, 2, 3], [4, 4, 0]],
                       np.concatenate([q[:, :2], [[0.9, 0.9]]]), np.tile([0.0, 0, 1], (5, 1)))
    with pytest.warns(BakeWarning, match=r"^LOW: 1 degenerate \(zero-area\) triangles \(first: "
                                         r"face 2\)"):
        raycast_normal_map(plane, degenerate, 8, cage=0.2)
    fin = np.concatenate([q, [[0.5, 0.5, 0.6]]])  # a third triangle on the edge 0-2
    sheet = _mesh(fin, [[0, 1, 2], [0, 2, 3], [0, 2, 4]], np.concatenate([q[:, :2] * 0.5,
                                                                          [[0.9, 0.9]]]),
                  np.tile([0.0, 0, 1], (5, 1)))
    with pytest.warns(BakeWarning, match=r"^LOW: 1 edges are shared by more than two "
                                         r"triangles \(non-manifold"):
        raycast_normal_map(plane, sheet, 8, cage=0.2)


def test_without_the_bake_extra_the_error_says_how_to_install(monkeypatch):
    monkeypatch.setitem(sys.modules, "embreex", None)
    with pytest.raises(ImportError, match=r'^ray-cast baking needs Embree \(embreex\): pip '
                                          r'install -e "\.\[bake\]"$'):
        raycast_normal_map(ico_sphere(1), uv_sphere(0.9, 8, 4), 8, cage=0.2)


def test_import_jaxnm_loads_no_bake_dependency():
    code = ("import sys, jaxnm; print(sorted(m for m in ('embreex', 'xatlas', "
            "'fast_simplification', 'flip_evaluator', 'jaxnm.transfer') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True, cwd=ROOT)
    assert out.stdout.strip() == "[]"


# --------------------------------------------------------------------------------------
# the mirrored torus: seams after the margin
# --------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def torus():
    pair = P.torus_pair()
    low, high = P.low_mesh(pair).with_tangents(), P.high_mesh(pair)
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", "LOW: .*overlapping uv islands", BakeWarning)
        res = raycast_normal_map(high, low, 512, samples=1)
    return pair, low, res


def _bilinear(img, uv):
    """Bilinear, clamped, image layout (row 0 = v near 1)."""
    h, w, _ = img.shape
    x = np.clip(uv[:, 0] * w - 0.5, 0, w - 1)
    y = np.clip((1 - uv[:, 1]) * h - 0.5, 0, h - 1)
    x0, y0 = np.minimum(np.floor(x).astype(int), w - 2), np.minimum(np.floor(y).astype(int), h - 2)
    fx, fy = (x - x0)[:, None], (y - y0)[:, None]
    im = img.astype(np.float64)
    return ((1 - fy) * ((1 - fx) * im[y0, x0] + fx * im[y0, x0 + 1])
            + fy * ((1 - fx) * im[y0 + 1, x0] + fx * im[y0 + 1, x0 + 1]))


def test_the_mirrored_torus_is_continuous_across_its_seams(torus):
    """Under the automatic cage no ray misses; along every edge where the uv layout is cut
    (the tube's seam) or mirrored (the two mirror lines), decoding the map with the faces on
    either side (bilinear, so the texels of the margin take part) gives the same normal to
    within 1 deg."""
    pair, low, res = torus
    assert res.cage_source == "automatic" and res.texels_missed == 0
    faces, cuv = pair["lo_faces"], pair["lo_corner_uv"]
    edges = {}
    for f in range(len(faces)):
        for k in range(3):
            key = tuple(sorted((faces[f, k], faces[f, (k + 1) % 3])))
            edges.setdefault(key, []).append((f, k))
    e1, e2 = cuv[:, 1] - cuv[:, 0], cuv[:, 2] - cuv[:, 0]
    area = e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]
    errs, kinds = [], set()
    for (a, b), sides in edges.items():
        (f1, k1), (f2, k2) = sides
        uv1 = {faces[f1, k]: cuv[f1, k] for k in range(3)}
        uv2 = {faces[f2, k]: cuv[f2, k] for k in range(3)}
        cut = not (np.allclose(uv1[a], uv2[a]) and np.allclose(uv1[b], uv2[b]))
        mirror = np.sign(area[f1]) != np.sign(area[f2])
        if not (cut or mirror):
            continue
        kinds.add("cut" if cut else "mirror")
        for s in (0.25, 0.5, 0.75):
            decoded = []
            for f in (f1, f2):
                bary = np.array([[(1 - s) * (v == a) + s * (v == b) for v in faces[f]]])
                uv = bary @ cuv[f]
                m = _bilinear(res.normals, uv)
                decoded.append(_decode(low, "vertex", np.array([f]), bary, m)[0])
            errs.append(_angle(*decoded)[0])
    assert kinds == {"cut", "mirror"} and len(errs) > 100
    assert max(errs) < 1.0, max(errs)


# --------------------------------------------------------------------------------------
# against Blender's Cycles bake
# --------------------------------------------------------------------------------------

SAMPLES, SIZE = 32, 256


def _blender(tmp, name, *args):
    run = subprocess.run([BLENDER, str(ROOT / "tests" / "blender_ref.py"), name, *map(str, args)],
                         capture_output=True, text=True, timeout=900)
    assert run.returncode == 0, run.stderr[-2000:]


def _suzanne_pair(tmp, levels=3):
    _blender(tmp, "suzanne", levels, tmp / "suzanne.npz")
    s = np.load(tmp / "suzanne.npz")

    def height(p):
        return 0.02 * np.sin(9 * p[:, 0]) * np.sin(8 * p[:, 1] + 0.5) * np.sin(7 * p[:, 2] + 1)

    return dict(hi_positions=P.displaced(s["sub_positions"], s["sub_faces"], height),
                hi_faces=s["sub_faces"], lo_positions=s["positions"], lo_faces=s["faces"],
                lo_corner_uv=s["corner_uv"])


def _cycles(tmp, pair, settings, size=SIZE, samples=SAMPLES):
    """Blender's bakes at margins 0 and 16, as unit vectors, and where Blender wrote."""
    np.savez(tmp / "spec.npz", **pair, size=size, samples=samples, margins=np.array([0, 16]),
             **settings)
    _blender(tmp, "transfer", tmp / "spec.npz", tmp / "out.npz")
    images = np.load(tmp / "out.npz")["images"].astype(np.float64)
    wrote = images[..., 0] >= 0
    n = 2 * (images - 0.5 - 1e-5)  # Blender's encoding adds 1e-5
    n /= np.where(wrote[..., None], np.linalg.norm(n, axis=-1, keepdims=True), 1)
    return n, wrote


def _ours(pair, settings, cage_mesh=None, size=SIZE, samples=SAMPLES):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", BakeWarning)
        return raycast_normal_map(
            P.high_mesh(pair), P.low_mesh(pair), size, samples=samples,
            cage=None if cage_mesh is not None else settings["cage_extrusion"],
            cage_mesh=cage_mesh, max_distance=settings["max_ray_distance"], margin=16)


@pytest.mark.slow
@pytest.mark.skipif(BLENDER is None and os.environ.get("JAXNM_REQUIRE_BLENDER") != "1",
                    reason="no Blender Python (set JAXNM_BLENDER_PYTHON or make .venv-blender)")
@pytest.mark.parametrize("case", ["suzanne", "torus"])
def test_the_bake_matches_cycles(case, tmp_path):
    assert BLENDER is not None, "JAXNM_REQUIRE_BLENDER=1 but no Blender Python was found"
    if case == "suzanne":  # an extrusion and a max ray distance
        pair = _suzanne_pair(tmp_path)
        settings = dict(cage_extrusion=0.1, max_ray_distance=0.4)
        res = _ours(pair, settings)
    else:  # a cage object: the low-poly torus inflated along its normals
        pair = P.torus_pair()
        cage = pair["lo_positions"] + 0.08 * P.angle_normals(pair["lo_positions"],
                                                             pair["lo_faces"])
        settings = dict(cage_extrusion=0.0, max_ray_distance=0.0, cage_positions=cage)
        res = _ours(pair, settings, P.low_mesh(dict(pair, cage=cage), "cage"))
    n, wrote = _cycles(tmp_path, pair, settings)
    baked = res.inside & ~res.missed
    # the same texels: Blender writes the covered texels whose ray hit (its texel centres
    # are 0.001 texel off, which can tip a texel on an island's edge or a ray's reach)
    assert (wrote[0] ^ baked).sum() <= 1e-3 * baked.sum(), (wrote[0] ^ baked).sum()
    baked &= wrote[0]
    err = _angle(res.normals, n[0])[baked]
    print(f"{case}: {err.size} texels, {err.mean():.4f} deg mean, "
          f"{np.percentile(err, 99):.4f} deg p99")
    assert err.mean() <= 0.2 and np.percentile(err, 99) <= 1.0
    # the margin reaches the same texels, with the same values up to the noise it spreads
    assert (wrote[1] ^ res.filled).sum() <= 1e-3 * res.filled.sum()
    margin = res.filled & wrote[1] & ~res.inside
    err_m = _angle(res.normals, n[1])[margin]
    assert err_m.size > 1000 and np.median(err_m) <= 0.2


@pytest.mark.slow
@pytest.mark.skipif(BLENDER is None and os.environ.get("JAXNM_REQUIRE_BLENDER") != "1",
                    reason="no Blender Python (set JAXNM_BLENDER_PYTHON or make .venv-blender)")
def test_the_sample_jitter_matches_cycles(tmp_path):
    """Where HIGH's triangles span several texels and their normals turn fast (Suzanne
    subdivided twice, a 64x64 map), Cycles' jitter within the hit triangle shows at 256
    samples: jaxnm's footprint (half a texel's step, carried onto the triangle) agrees, and a
    bake without jitter does not."""
    assert BLENDER is not None, "JAXNM_REQUIRE_BLENDER=1 but no Blender Python was found"
    pair = _suzanne_pair(tmp_path, levels=2)
    settings = dict(cage_extrusion=0.1, max_ray_distance=0.4)
    n, wrote = _cycles(tmp_path, pair, settings, size=64, samples=256)
    errs = {}
    for ours in (256, 1):
        res = _ours(pair, settings, size=64, samples=ours)
        baked = res.inside & ~res.missed & wrote[0]
        errs[ours] = _angle(res.normals, n[0])[baked]
    print({k: (round(float(e.mean()), 4), round(float(np.percentile(e, 99)), 3))
           for k, e in errs.items()})
    assert errs[256].mean() <= 0.3 and np.percentile(errs[256], 99) <= 1.5
    assert errs[1].mean() > 2 * errs[256].mean()
