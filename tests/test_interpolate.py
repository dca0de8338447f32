"""Interpolation and screen-space derivatives against analytic answers and a float64 reference."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import clip_of, grid_plane, icosphere, perspective_mvp, random_soup
from jax.test_util import check_grads
from refraster import interpolate_ref, rasterize_ref

import jaxnm
from jaxnm.camera import orthographic

MODES = ("analytic", "fine", "coarse")


@pytest.mark.parametrize("size", [(48, 40), (33, 21)])
def test_matches_float64_reference_all_modes(size):
    """Values and analytic/fine/coarse derivatives (helper pixels included) vs float64."""
    w, h = size
    pos, faces = random_soup(7)
    clip = clip_of(pos, perspective_mvp((0.4, -0.3, 2.4), aspect=w / h)).astype(np.float32)
    attr = np.random.default_rng(0).normal(size=(len(pos), 3)).astype(np.float32)
    ref = rasterize_ref(clip.astype(np.float64), faces, w, h, subpixel_bits=8)
    fr = jaxnm.rasterize(clip, faces, width=w, height=h)
    same = (np.asarray(fr.triangle_id) == ref["triangle_id"]) & (ref["triangle_id"] >= 0)
    for mode in MODES:
        v, dx, dy = interpolate_ref(attr.astype(np.float64), faces, ref,
                                    clip.astype(np.float64), w, h, derivatives=mode)
        a = jaxnm.interpolate(attr, fr, derivatives=mode)
        for got, want in ((a.value, v), (a.ddx, dx), (a.ddy, dy)):
            got = np.asarray(got)[same]
            want = want[same]
            err = np.abs(got - want) / np.maximum(1.0, np.abs(want))
            assert err.max() < 2e-5, (mode, err.max())
        assert np.all(np.asarray(a.value)[~np.asarray(fr.mask)] == 0)


def _plane_scene(ortho: bool, size=(32, 32)):
    """A tilted plane z = 0 (uv = affine in x, y), camera looking down at it obliquely: two
    triangles with their own corners (six vertices, the shape of `_seam_scene`)."""
    w, h = size
    s = 12.0
    pos = np.array([[-s, -s, 0], [s, -s, 0], [s, s, 0], [-s, s, 0]], np.float64)[[0, 1, 2, 0, 2, 3]]
    faces = np.array([[0, 1, 2], [3, 4, 5]])
    a_uv = np.array([[0.30, 0.05], [-0.07, 0.22]])  # sheared affine uv map
    uv = pos[:, :2] @ a_uv.T + [0.5, 0.4]
    eye, target = np.array([0.4, -1.6, 1.3]), np.array([0.1, 0.2, 0.0])
    view = jaxnm.look_at(eye, target, (0, 0, 1))
    proj = orthographic(-1.2, 1.2, -1.2, 1.2, 0.1, 10) if ortho else jaxnm.perspective(
        50, w / h, 0.1, 50)
    return pos, faces, uv, a_uv, eye, proj @ view, size


def _plane_truth(a_uv, eye, mvp, size):
    """Exact per-pixel p, uv, window depth and their window-space derivatives (float64)."""
    w, h = size
    inv = np.linalg.inv(mvp)
    x = np.arange(w) + 0.5
    y = (h - 1 - np.arange(h)) + 0.5
    X, Y = np.meshgrid(x, y)

    def hit(xw, yw):
        ndc = np.stack([2 * xw / w - 1, 2 * yw / h - 1], -1)
        a = np.concatenate([ndc, -np.ones_like(ndc[..., :1]), np.ones_like(ndc[..., :1])], -1)
        b = a.copy()
        b[..., 2] = 1
        pa, pb = a @ inv.T, b @ inv.T
        pa, pb = pa[..., :3] / pa[..., 3:], pb[..., :3] / pb[..., 3:]
        t = -pa[..., 2] / (pb[..., 2] - pa[..., 2])
        p = pa + t[..., None] * (pb - pa)
        c = np.concatenate([p, np.ones_like(p[..., :1])], -1) @ mvp.T
        depth = (c[..., 2] / c[..., 3] + 1) / 2
        return p, depth

    p, depth = hit(X, Y)
    eps = 1e-4  # central differences of an analytic function (float64): error ~ eps^2
    px = (hit(X + eps, Y)[0] - hit(X - eps, Y)[0]) / (2 * eps)
    py = (hit(X, Y + eps)[0] - hit(X, Y - eps)[0]) / (2 * eps)
    return p, depth, px, py, px[..., :2] @ a_uv.T, py[..., :2] @ a_uv.T


@pytest.mark.parametrize("ortho", [False, True])
def test_plane_analytic_depth_uv_and_derivatives(ortho):
    pos, faces, uv, a_uv, eye, mvp, size = _plane_scene(ortho)
    clip = clip_of(pos, mvp).astype(np.float32)
    fr = jaxnm.rasterize(clip, faces, width=size[0], height=size[1])
    assert np.asarray(fr.mask).all()
    p, depth, px, py, uvx, uvy = _plane_truth(a_uv, eye, mvp, size)
    np.testing.assert_allclose(np.asarray(fr.depth), depth, atol=2e-6)
    out = jaxnm.interpolate({"p": pos.astype(np.float32), "uv": uv.astype(np.float32)}, fr,
                            derivatives="analytic")
    np.testing.assert_allclose(out["p"].value, p, atol=3e-6 * 4)
    np.testing.assert_allclose(out["uv"].value, p[..., :2] @ a_uv.T + [0.5, 0.4], atol=3e-6)
    scale = np.abs(px).max()
    np.testing.assert_allclose(out["p"].ddx, px, atol=2e-5 * scale)
    np.testing.assert_allclose(out["p"].ddy, py, atol=2e-5 * scale)
    np.testing.assert_allclose(out["uv"].ddx, uvx, atol=2e-5 * np.abs(uvx).max())
    np.testing.assert_allclose(out["uv"].ddy, uvy, atol=2e-5 * np.abs(uvy).max())
    if not ortho:  # strong perspective: derivatives vary a lot over the image
        assert np.abs(px).max() > 3 * np.abs(px).min()


def test_orthographic_all_modes_agree_on_affine_attributes():
    """Under an orthographic camera every attribute is affine in screen space."""
    pos, faces, uv, *_ = _plane_scene(True)
    mvp = _plane_scene(True)[5]
    clip = clip_of(pos, mvp).astype(np.float32)
    fr = jaxnm.rasterize(clip, faces, width=32, height=32)
    outs = {m: jaxnm.interpolate(uv.astype(np.float32), fr, derivatives=m) for m in MODES}
    ref = outs["analytic"]
    for m in ("fine", "coarse"):
        np.testing.assert_allclose(outs[m].ddx, ref.ddx, rtol=1e-5, atol=1e-7)
        np.testing.assert_allclose(outs[m].ddy, ref.ddy, rtol=1e-5, atol=1e-7)
    # the plane covers the whole image, so even gbuffer agrees away from the diagonal
    g = jaxnm.interpolate(uv.astype(np.float32), fr, derivatives="gbuffer")
    np.testing.assert_allclose(g.ddx, ref.ddx, atol=1e-5)


def _seam_scene():
    """Orthographic two-triangle quad whose triangles have *different* uv mappings."""
    pos = np.array([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, -1, 0], [1, 1, 0], [-1, 1, 0]],
                   np.float64) * 0.8
    uv = np.array([[0, 0], [1, 0], [1, 1], [0, 0], [3, 2], [-2, 1]], np.float64)  # seam
    faces = np.array([[0, 1, 2], [3, 4, 5]])
    mvp = orthographic(-1, 1, -1, 1, -1, 1)
    return clip_of(pos, mvp).astype(np.float32), faces, uv.astype(np.float32)


def test_helper_pixels_at_uv_seam_and_silhouette():
    """Quad derivatives = the pixel's own triangle's analytic derivative; gbuffer is not."""
    clip, faces, uv = _seam_scene()
    fr = jaxnm.rasterize(clip, faces, width=32, height=32)
    mask = np.asarray(fr.mask)
    tid = np.asarray(fr.triangle_id)
    ana = jaxnm.interpolate(uv, fr, derivatives="analytic")
    # per triangle, the analytic derivative is constant: check that (independent truth)
    for t in (0, 1):
        d = np.asarray(ana.ddx)[tid == t]
        np.testing.assert_allclose(d, np.broadcast_to(d[0], d.shape), rtol=1e-5, atol=1e-6)
    for mode in ("fine", "coarse"):
        q = jaxnm.interpolate(uv, fr, derivatives=mode)
        np.testing.assert_allclose(q.ddx, ana.ddx, rtol=1e-5, atol=1e-6)
        np.testing.assert_allclose(q.ddy, ana.ddy, rtol=1e-5, atol=1e-6)
    g = jaxnm.interpolate(uv, fr, derivatives="gbuffer")
    bad = np.abs(np.asarray(g.ddx) - np.asarray(ana.ddx)).max(-1) > 1e-3
    bad |= np.abs(np.asarray(g.ddy) - np.asarray(ana.ddy)).max(-1) > 1e-3
    # gbuffer is wrong exactly where a quad straddles the seam or the silhouette
    x_part = np.arange(32) ^ 1
    rows = 31 - ((31 - np.arange(32)) ^ 1)
    straddles = (tid != tid[:, x_part]) | (tid != tid[rows, :])
    assert np.array_equal(bad & mask, straddles & mask)
    assert (bad & mask).sum() > 20


def test_gbuffer_odd_size_uses_zero_outside_image():
    clip, faces, uv = _seam_scene()
    fr = jaxnm.rasterize(clip * np.array([2, 2, 1, 1], np.float32), faces, width=7, height=5)
    g = jaxnm.interpolate(uv, fr, derivatives="gbuffer")
    f = jaxnm.interpolate(uv, fr, derivatives="fine")
    assert np.all(np.isfinite(np.asarray(g.ddx)))
    # rightmost column (x = 6, even) pairs with x = 7, outside the image, which stores 0:
    # dFdx = f(odd) - f(even) = 0 - value
    m = np.asarray(fr.mask)[:, 6]
    np.testing.assert_allclose(np.asarray(g.ddx)[m, 6], -np.asarray(g.value)[m, 6])
    # the fine derivative extends the triangle beyond the image instead
    assert np.all(np.isfinite(np.asarray(f.ddx)))


def test_fine_equals_analytic_times_w_ratio():
    """Documented relation: fine = analytic * w(partner) / w(pixel) for the barycentrics."""
    pos, faces = icosphere(1)
    clip = clip_of(pos, perspective_mvp((0.3, 0.2, 2.2))).astype(np.float32)
    fr = jaxnm.rasterize(clip, faces, width=24, height=24)
    b_f = jaxnm.barycentrics(fr, derivatives="fine")
    b_a = jaxnm.barycentrics(fr, derivatives="analytic")
    w = jaxnm.interpolate(clip[:, 3:], fr, derivatives=None).value[..., 0]
    # w at the horizontal partner: evaluate interpolant there via the fine difference of w
    wf = jaxnm.interpolate(clip[:, 3:], fr, derivatives="fine")
    x_even = (np.arange(24) % 2 == 0)[None, :]
    w_partner = np.where(x_even, w + wf.ddx[..., 0], w - wf.ddx[..., 0])
    m = np.asarray(fr.mask)
    lhs = np.asarray(b_f.ddx)[m]
    rhs = (np.asarray(b_a.ddx) * (w_partner / w)[..., None])[m]
    np.testing.assert_allclose(lhs, rhs, rtol=1e-4, atol=1e-6)


def test_far_from_origin_keeps_derivative_precision():
    """Geometry 1e5 from the origin: derivatives stay as accurate as near the origin."""
    pos, faces, uv = grid_plane(2)
    offset = np.array([1e5, -2e5, 3e4])
    res = []
    for off in (np.zeros(3), offset):
        eye = np.array([0.3, -0.8, 1.5]) + off
        cam = jaxnm.Camera.look_at(eye, off, (0, 0, 1), fov_y_deg=60)
        clip = jaxnm.to_clip(jnp.asarray(pos + off, jnp.float32), cam)
        fr = jaxnm.rasterize(clip, faces, width=16, height=16)
        rel = jnp.asarray(pos + off, jnp.float32) - cam.eye[None, :]
        res.append(jaxnm.interpolate(rel, fr, derivatives="fine"))
    # positions are float32-rounded at 1e5 (ulp ~ 0.008), so compare to the mesh spacing
    np.testing.assert_allclose(res[1].ddx, res[0].ddx, atol=2e-3 * np.abs(res[0].ddx).max())


def test_gradients_wrt_vertex_attributes_and_positions():
    pos, faces, uv = grid_plane(1)
    mvp = perspective_mvp((0.3, -0.5, 2.0))
    with jax.enable_x64(True):
        clip = jnp.asarray(clip_of(pos, mvp))
        fr = jaxnm.rasterize(clip, faces, width=8, height=8)
        assert fr.mask.sum() > 20
        uvj = jnp.asarray(uv)
        for mode in ("analytic", "fine", "coarse"):
            @jax.jit
            def f(attr, clip_):
                fr2 = jaxnm.raster.Fragments(fr.triangle_id, fr.depth, fr.front_facing, clip_,
                                             fr.faces)
                a = jaxnm.interpolate(attr, fr2, derivatives=mode)
                return a.value.sum() + (a.ddx ** 2).sum() + (a.ddy * a.value).sum()
            check_grads(f, (uvj, clip), order=1, modes=("fwd", "rev"), atol=1e-5, rtol=1e-5)


def test_gradients_finite_at_silhouettes_and_background():
    pos, faces = icosphere(1)
    clip = jnp.asarray(clip_of(pos, perspective_mvp((0.0, 0.0, 2.0))), jnp.float32)
    # (the size of `test_fine_equals_analytic_times_w_ratio`'s sphere: one rasterizer)
    fr = jaxnm.rasterize(clip, faces, width=24, height=24)
    for mode in ("analytic", "fine", "coarse", "gbuffer"):
        @jax.jit
        def f(c, a):
            fr2 = jaxnm.raster.Fragments(fr.triangle_id, fr.depth, fr.front_facing, c, fr.faces)
            out = jaxnm.interpolate(a, fr2, derivatives=mode)
            return (out.ddx ** 2).sum() + (out.ddy ** 2).sum() + out.value.sum()
        gc, ga = jax.jit(jax.grad(f, argnums=(0, 1)))(clip, jnp.asarray(pos, jnp.float32))
        assert np.all(np.isfinite(np.asarray(gc))) and np.all(np.isfinite(np.asarray(ga)))


def test_unknown_mode_and_bad_attribute_shape():
    clip, faces, uv = _seam_scene()
    fr = jaxnm.rasterize(clip, faces, width=32, height=32)  # (the seam tests' rasterizer)
    with pytest.raises(ValueError, match="unknown derivatives mode"):
        jaxnm.interpolate(uv, fr, derivatives="medium")
    with pytest.raises(ValueError, match="vertices"):
        jaxnm.interpolate(uv[:3], fr)
    with pytest.raises(ValueError, match="derivatives='analytic'"):
        jaxnm.interpolate(uv, fr, derivatives="fine",
                          bary=jaxnm.barycentrics(fr, derivatives="analytic"))
