"""Tests for jaxnm.textures: GL sampling conventions, mipmaps, LOD, normal-map codecs, sRGB.

References are independent float64 NumPy/pure-Python implementations written
differently from the library (loops over texels, image-row coordinates,
iterative mirroring, interval-overlap box filters).
"""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from jax.test_util import check_grads

from jaxnm.interpolate import Attribute
from jaxnm.numerics import safe_normalize
from jaxnm.textures import (
    SamplePlan,
    apply_plan,
    box_filter_matrix,
    build_mipmaps,
    decode_normal_map,
    encode_normal_map,
    linear_to_srgb,
    lod,
    mip_sizes,
    plan_sample,
    plan_sum_tables,
    sample,
    srgb_to_linear,
    transpose_plan,
)

WRAPS = ("repeat", "clamp", "mirror")
ORIGINS = ("bottom_left", "top_left")


# --------------------------------------------------------------------------- references


def ref_wrap(i: int, n: int, mode: str) -> int:
    if mode == "repeat":
        return i % n
    if mode == "clamp":
        return min(max(i, 0), n - 1)
    while not 0 <= i < n:  # reflect at the nearer border until inside
        i = -1 - i if i < 0 else 2 * n - 1 - i
    return i


def ref_coords(tex_hw, u, v, origin):
    """Continuous (column, image row) coordinates; texel centres at integers."""
    h, w = tex_hw
    x = u * w - 0.5
    y = (1.0 - v) * h - 0.5 if origin == "bottom_left" else v * h - 0.5
    return x, y


def ref_bilinear(tex, u, v, wrap, origin):
    """Loop over every texel, summing the tent weights of the lattice points that wrap onto it."""
    tex = np.asarray(tex, np.float64)
    h, w, _ = tex.shape
    x, y = ref_coords((h, w), float(u), float(v), origin)
    near_x = range(math.floor(x) - 1, math.floor(x) + 3)
    near_y = range(math.floor(y) - 1, math.floor(y) + 3)
    out = np.zeros(tex.shape[-1])
    for r in range(h):
        for c in range(w):
            weight = 0.0
            for j in near_y:
                for i in near_x:
                    if ref_wrap(i, w, wrap) == c and ref_wrap(j, h, wrap) == r:
                        weight += max(0.0, 1 - abs(x - i)) * max(0.0, 1 - abs(y - j))
            out += weight * tex[r, c]
    return out


def ref_nearest(tex, u, v, wrap, origin):
    tex = np.asarray(tex, np.float64)
    h, w, _ = tex.shape
    x, y = ref_coords((h, w), float(u), float(v), origin)
    return tex[ref_wrap(round(y), h, wrap), ref_wrap(round(x), w, wrap)]


def ref_box_matrix(n_in: int) -> np.ndarray:
    """Area-overlap weights (n_out, n_in) of the exact box filter to max(1, n_in // 2)."""
    n_out = max(1, n_in // 2)
    width = n_in / n_out
    m = np.zeros((n_out, n_in))
    for i in range(n_out):
        lo, hi = i * width, (i + 1) * width
        for k in range(n_in):
            m[i, k] = max(0.0, min(hi, k + 1) - max(lo, k)) / width
    return m


def ref_mipmaps(tex):
    levels = [np.asarray(tex, np.float64)]
    while levels[-1].shape[:2] != (1, 1):
        x = levels[-1]
        a, b = ref_box_matrix(x.shape[0]), ref_box_matrix(x.shape[1])
        levels.append(np.einsum("ih,hwc,jw->ijc", a, x, b))
    return levels


def ref_lod(duvdx, duvdy, h, w):
    rx = math.hypot(duvdx[0] * w, duvdx[1] * h)
    ry = math.hypot(duvdy[0] * w, duvdy[1] * h)
    return math.log2(max(rx, ry))


def away_from(values, lattice_scale, margin=1e-3):
    """True where values * scale is at least `margin` from an integer."""
    f = np.asarray(values, np.float64) * lattice_scale
    return np.abs(f - np.round(f)) > margin


# --------------------------------------------------------------------------- fixtures
# Shared shapes, so that the jitted sampler compiles once per mode across tests.

TEX = np.random.default_rng(1234).random((4, 8, 3)).astype(np.float32)  # non-square
TEX_HW = TEX.shape[:2]
N = 32
UV = np.random.default_rng(0).uniform(-1.7, 2.6, (N, 2)).astype(np.float32)
DUV = (np.random.default_rng(1).normal(size=(2, N, 2)) * 0.25).astype(np.float32)


def texel_centres(h, w, origin):
    r, c = np.divmod(np.arange(h * w), w)
    v = 1 - (r + 0.5) / h if origin == "bottom_left" else (r + 0.5) / h
    return np.stack([(c + 0.5) / w, v], -1).astype(np.float32)


# --------------------------------------------------------------------------- mipmaps


def test_mip_sizes_follow_gl():
    assert mip_sizes((256, 256))[-1] == (1, 1) and len(mip_sizes((256, 256))) == 9
    assert mip_sizes((5, 3)) == ((5, 3), (2, 1), (1, 1))
    assert mip_sizes((1, 8)) == ((1, 8), (1, 4), (1, 2), (1, 1))
    assert mip_sizes((8, 8), 2) == ((8, 8), (4, 4))
    with pytest.raises(ValueError, match="between 1 and 4"):
        mip_sizes((8, 8), 5)


@pytest.mark.parametrize("shape", [(4, 4, 1), (7, 5, 3), (6, 3, 2), (1, 5, 1), (9, 2, 1)])
def test_mipmap_of_constant_is_constant(shape):
    mips = build_mipmaps(jnp.full(shape, 0.37, jnp.float32))
    assert mips[-1].shape[:2] == (1, 1)
    for m in mips:
        np.testing.assert_allclose(m, 0.37, rtol=1e-6)


def test_mipmap_of_checkerboard_is_its_average():
    checker = (np.indices((4, 4)).sum(0) % 2).astype(np.float32)[..., None]
    mips = build_mipmaps(jnp.asarray(checker))
    assert [m.shape for m in mips] == [(4, 4, 1), (2, 2, 1), (1, 1, 1)]
    np.testing.assert_array_equal(mips[1], 0.5)
    np.testing.assert_array_equal(mips[2], 0.5)


@pytest.mark.parametrize("shape", [(8, 8, 2), (7, 5, 3), (6, 3, 1), (1, 5, 2), (9, 2, 1)])
def test_mipmaps_match_area_reference_and_keep_the_mean(shape):
    tex = np.random.default_rng(sum(shape)).random(shape).astype(np.float32)
    got = build_mipmaps(jnp.asarray(tex))
    want = ref_mipmaps(tex)
    assert len(got) == len(want)
    for g, w in zip(got, want):
        assert g.shape == w.shape
        np.testing.assert_allclose(g, w, rtol=1e-5, atol=1e-6)
        np.testing.assert_allclose(np.mean(g, (0, 1)), tex.mean((0, 1)), rtol=1e-5)


def test_mipmap_levels_argument():
    assert len(build_mipmaps(jnp.zeros((8, 8, 1)), levels=2)) == 2
    assert len(build_mipmaps(jnp.zeros((8, 8, 1)))) == 4


def test_mipmap_renormalize_gives_unit_vectors_and_keeps_extra_channels():
    n = np.random.default_rng(3).normal(size=(8, 8, 3))
    n[..., 2] = np.abs(n[..., 2]) + 0.5
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    alpha = np.random.default_rng(4).random((8, 8, 1))
    tex = jnp.asarray(np.concatenate([n, alpha], -1), jnp.float32)
    mips = build_mipmaps(tex, renormalize=True)
    np.testing.assert_array_equal(mips[0], tex)
    plain = build_mipmaps(tex)
    for m, p in zip(mips[1:], plain[1:]):
        np.testing.assert_allclose(np.linalg.norm(m[..., :3], axis=-1), 1.0, rtol=1e-5)
        np.testing.assert_allclose(m[..., 3], p[..., 3], rtol=1e-5)  # alpha filtered only


def test_mipmap_renormalize_of_cancelling_normals_is_zero_without_nan():
    tex = jnp.asarray([[[1.0, 0, 0], [-1.0, 0, 0]]] * 2, jnp.float32)  # (2, 2, 3)
    mips = build_mipmaps(tex, renormalize=True)
    np.testing.assert_array_equal(mips[1], 0.0)
    g = jax.grad(lambda t: jnp.sum(build_mipmaps(t, renormalize=True)[1]))(tex)
    assert np.all(np.isfinite(g))


def test_build_mipmaps_rejects_bad_input():
    with pytest.raises(ValueError, match=r"\(H, W, C\)"):
        build_mipmaps(jnp.zeros((4, 4)))
    with pytest.raises(ValueError, match="floating point"):
        build_mipmaps(jnp.zeros((4, 4, 3), jnp.uint8))
    with pytest.raises(ValueError, match="3 channels"):
        build_mipmaps(jnp.zeros((4, 4, 2)), renormalize=True)


# --------------------------------------------------------------------------- LOD


def test_lod_from_known_derivatives():
    def lam(dx, dy, hw=(256, 256)):
        return float(lod(jnp.asarray(dx, jnp.float32), jnp.asarray(dy, jnp.float32), hw))

    assert lam([1 / 256, 0], [0, 1 / 256]) == pytest.approx(0.0, abs=1e-6)
    assert lam([4 / 256, 0], [0, 4 / 256]) == pytest.approx(2.0, abs=1e-6)
    assert lam([0, -4 / 256], [1 / 256, 0]) == pytest.approx(2.0, abs=1e-6)  # sign-free
    assert lam([1 / 256, 0], [0, 8 / 256]) == pytest.approx(3.0, abs=1e-6)  # max of the two
    # non-square: v is scaled by H, u by W
    assert lam([0, 2 / 8], [0, 0], hw=(8, 32)) == pytest.approx(1.0, abs=1e-6)
    assert lam([2 / 32, 0], [0, 0], hw=(8, 32)) == pytest.approx(1.0, abs=1e-6)
    rng = np.random.default_rng(5)
    for _ in range(5):
        dx, dy = rng.normal(size=2) * 0.1, rng.normal(size=2) * 0.1
        assert lam(dx, dy, (16, 32)) == pytest.approx(ref_lod(dx, dy, 16, 32), abs=1e-5)


def test_lod_is_safe_at_zero_derivatives():
    z = jnp.zeros((3, 2), jnp.float32)
    value = lod(z, z, (64, 64))
    assert np.all(np.isfinite(value)) and np.all(value < -40)
    g = jax.grad(lambda d: jnp.sum(lod(d, d, (64, 64))))(z)
    np.testing.assert_array_equal(g, 0.0)


# --------------------------------------------------------------------------- sampling


@pytest.mark.parametrize("wrap", WRAPS)
@pytest.mark.parametrize("origin", ORIGINS)
def test_bilinear_matches_reference(wrap, origin):
    got = sample(TEX, UV, filter="bilinear", wrap=wrap, uv_origin=origin)
    want = np.stack([ref_bilinear(TEX, u, v, wrap, origin) for u, v in UV])
    np.testing.assert_allclose(got, want, atol=2e-5)


@pytest.mark.parametrize("wrap", WRAPS)
@pytest.mark.parametrize("origin", ORIGINS)
def test_nearest_matches_reference(wrap, origin):
    h, w = TEX_HW
    assert np.all(away_from(UV[:, 0], w) & away_from(UV[:, 1], h))  # no ties on texel edges
    got = sample(TEX, UV, filter="nearest", wrap=wrap, uv_origin=origin)
    want = np.stack([ref_nearest(TEX, u, v, wrap, origin) for u, v in UV])
    np.testing.assert_array_equal(got, want.astype(np.float32))


@pytest.mark.parametrize("wrap", WRAPS)
@pytest.mark.parametrize("origin", ORIGINS)
def test_sampling_at_texel_centres_returns_the_texel(wrap, origin):
    uv = texel_centres(*TEX_HW, origin)
    texels = TEX.reshape(-1, 3)  # row-major: entry k is texel (k // W, k % W)
    for filter in ("nearest", "bilinear"):
        got = sample(TEX, uv, filter=filter, wrap=wrap, uv_origin=origin)
        np.testing.assert_array_equal(got, texels, err_msg=filter)


def test_uv_origin_on_a_2x2_image_with_distinct_rows():
    tex = jnp.asarray([[[10.0], [10.0]], [[20.0], [20.0]]])  # row 0 (top) = 10, row 1 = 20
    uv = jnp.asarray([[0.25, 0.25], [0.75, 0.75]])  # lower half, upper half (bottom_left)
    for filter in ("nearest", "bilinear"):
        bl = sample(tex, uv, filter=filter, wrap="clamp", uv_origin="bottom_left")
        tl = sample(tex, uv, filter=filter, wrap="clamp", uv_origin="top_left")
        np.testing.assert_array_equal(bl[:, 0], [20.0, 10.0])  # v = 0 is the bottom edge
        np.testing.assert_array_equal(tl[:, 0], [10.0, 20.0])  # v = 0 is the top edge


def test_wrap_modes_at_the_borders():
    tex = jnp.asarray(np.arange(12, dtype=np.float32).reshape(3, 4, 1))  # value = 4 r + c
    v_row1 = 0.5  # image row 1 (centre), both origins
    # bilinear along u; columns hold c = 0..3 (W = 4)
    lin = {  # u -> column value per mode
        0.0: dict(repeat=1.5, clamp=0.0, mirror=0.0),  # x = -0.5: halfway col -1 / col 0
        -0.5 / 4: dict(repeat=3.0, clamp=0.0, mirror=0.0),  # x = -1
        -1.5 / 4: dict(repeat=2.0, clamp=0.0, mirror=1.0),  # x = -2
        1.0: dict(repeat=1.5, clamp=3.0, mirror=3.0),  # x = W - 0.5
        1 + 0.5 / 4: dict(repeat=0.0, clamp=3.0, mirror=3.0),  # x = W
        1 + 1.5 / 4: dict(repeat=1.0, clamp=3.0, mirror=2.0),  # x = W + 1
    }
    near_u = {-0.1: dict(repeat=3, clamp=0, mirror=0), 1.1: dict(repeat=0, clamp=3, mirror=3),
              1.3: dict(repeat=1, clamp=3, mirror=2)}
    # nearest along v (bottom_left): just below v = 0 is GL row -1, which wraps to the
    # top image row (repeat) or stays at the bottom row (clamp, mirror)
    near_v = {-0.1: dict(repeat=0, clamp=2, mirror=2), 1.1: dict(repeat=2, clamp=0, mirror=0)}
    for wrap in WRAPS:
        uv = jnp.asarray([[u, v_row1] for u in lin], jnp.float32)
        got = sample(tex, uv, filter="bilinear", wrap=wrap)[:, 0]
        np.testing.assert_allclose(got, [4 + c[wrap] for c in lin.values()], atol=1e-6,
                                   err_msg=wrap)
        uv = jnp.asarray([[u, v_row1] for u in near_u] + [[0.6, v] for v in near_v])
        got = np.asarray(sample(tex, uv, filter="nearest", wrap=wrap)[:, 0])
        want = [4 + c[wrap] for c in near_u.values()] + [4 * c[wrap] + 2 for c in near_v.values()]
        np.testing.assert_array_equal(got, want, err_msg=wrap)


def test_clamp_at_u_zero_returns_column_zero():
    h, w = TEX_HW
    uv = np.stack([np.zeros(h), 1 - (np.arange(h) + 0.5) / h], -1).astype(np.float32)
    got = sample(TEX, uv, filter="bilinear", wrap="clamp")
    np.testing.assert_array_equal(got, TEX[:, 0])


_sample_jit = jax.jit(sample, static_argnames=("filter", "wrap", "uv_origin"))
coord = st.floats(-3.0, 3.0, allow_nan=False, width=32)


@settings(max_examples=30, deadline=None)
@given(u=coord, v=coord)
def test_wrap_symmetries(u, v):
    def f(uu, vv, wrap, origin="bottom_left"):
        return _sample_jit(TEX, jnp.asarray([[uu, vv]], jnp.float32), wrap=wrap,
                           uv_origin=origin)

    tol = dict(atol=3e-5)
    np.testing.assert_allclose(f(u + 1, v - 2, "repeat"), f(u, v, "repeat"), **tol)
    np.testing.assert_allclose(f(-u, v, "mirror"), f(u, v, "mirror"), **tol)
    np.testing.assert_allclose(f(u, 2 - v, "mirror"), f(u, v, "mirror"), **tol)
    h, w = TEX_HW
    uc = float(np.clip(u, 0.5 / w, 1 - 0.5 / w))
    vc = float(np.clip(v, 0.5 / h, 1 - 0.5 / h))
    np.testing.assert_allclose(f(u, v, "clamp"), f(uc, vc, "clamp"), **tol)
    # top_left is bottom_left with v -> 1 - v
    np.testing.assert_allclose(f(u, v, "repeat", "top_left"), f(u, 1 - v, "repeat"), **tol)


# --------------------------------------------------------------------------- trilinear

MIPS = build_mipmaps(jnp.asarray(TEX))  # (4, 8), (2, 4), (1, 2), (1, 1)
REF_MIPS = ref_mipmaps(TEX)


def isotropic(rho_texels):
    """Screen derivatives of `rho_texels` texels per pixel along both axes, (N, 2) each."""
    h, w = TEX_HW
    dx = np.tile([rho_texels / w, 0.0], (N, 1)).astype(np.float32)
    dy = np.tile([0.0, rho_texels / h], (N, 1)).astype(np.float32)
    return dx, dy


def test_trilinear_at_integer_and_half_lod():
    bil = [np.stack([ref_bilinear(m, u, v, "repeat", "bottom_left") for u, v in UV])
           for m in REF_MIPS]
    for level in range(len(MIPS)):
        got = sample(MIPS, UV, *isotropic(2.0**level), filter="trilinear")
        np.testing.assert_allclose(got, bil[level], atol=2e-5, err_msg=f"level {level}")
    got = sample(MIPS, UV, *isotropic(2.0**1.5), filter="trilinear")
    np.testing.assert_allclose(got, 0.5 * (bil[1] + bil[2]), atol=2e-5)
    # magnification uses level 0; beyond the last level the last level
    np.testing.assert_allclose(sample(MIPS, UV, *isotropic(0.25), filter="trilinear"), bil[0],
                               atol=2e-5)
    np.testing.assert_allclose(sample(MIPS, UV, *isotropic(64.0), filter="trilinear"), bil[3],
                               atol=2e-5)
    # lod_bias shifts lambda
    got = sample(MIPS, UV, *isotropic(1.0), filter="trilinear", lod_bias=2.0)
    np.testing.assert_allclose(got, bil[2], atol=2e-5)
    # an incomplete chain clamps lambda to its last level
    got = sample(MIPS[:2], UV, *isotropic(8.0), filter="trilinear")
    np.testing.assert_allclose(got, bil[1], atol=2e-5)


@pytest.mark.parametrize("wrap", WRAPS)
def test_trilinear_matches_reference(wrap):
    dx, dy = DUV
    got = sample(MIPS, UV, dx, dy, filter="trilinear", wrap=wrap)
    top = len(MIPS) - 1
    for k in range(N):
        lam = min(max(ref_lod(dx[k], dy[k], *TEX_HW), 0.0), top)
        d = math.floor(lam)
        a = ref_bilinear(REF_MIPS[d], *UV[k], wrap, "bottom_left")
        b = ref_bilinear(REF_MIPS[min(d + 1, top)], *UV[k], wrap, "bottom_left")
        np.testing.assert_allclose(got[k], (1 - (lam - d)) * a + (lam - d) * b, atol=3e-5)


def test_trilinear_without_mips_builds_them():
    a = sample(TEX, UV, *DUV, filter="trilinear")
    b = sample(MIPS, UV, *DUV, filter="trilinear")
    np.testing.assert_array_equal(a, b)


def test_background_pixels_are_finite():
    zeros = np.zeros((N, 2), np.float32)  # background: uv = 0, derivatives = 0
    for filter in ("nearest", "bilinear", "trilinear"):
        out = sample(MIPS, zeros, zeros, zeros, filter=filter)
        assert out.shape == (N, 3) and np.all(np.isfinite(out))

    def loss(uv, d):
        return jnp.sum(sample(MIPS, uv, d, d, filter="trilinear") ** 2)

    gu, gd = jax.grad(loss, (0, 1))(zeros, zeros)
    assert np.all(np.isfinite(gu)) and np.all(np.isfinite(gd))


# --------------------------------------------------------------------------- plans


def test_plan_structure_and_pytree():
    uv = UV.reshape(4, 8, 2)
    dx, dy = (d.reshape(4, 8, 2) for d in DUV)
    plans = {f: plan_sample(uv, dx, dy, size_hw=TEX_HW, levels=4, filter=f)
             for f in ("nearest", "bilinear", "trilinear")}
    total = sum(h * w for h, w in mip_sizes(TEX_HW))
    for f, taps in (("nearest", 1), ("bilinear", 4), ("trilinear", 8)):
        p = plans[f]
        assert isinstance(p, SamplePlan)
        assert p.index.shape == (4, 8, taps) and p.index.dtype == jnp.int32
        assert p.num_taps == taps
        np.testing.assert_allclose(np.sum(p.weight, -1), 1.0, rtol=1e-6)
        assert np.all((np.asarray(p.index) >= 0) & (np.asarray(p.index) < total))
    leaves, treedef = jax.tree_util.tree_flatten(plans["trilinear"])
    assert len(leaves) == 2
    rebuilt = jax.tree_util.tree_unflatten(treedef, leaves)
    assert rebuilt.level_shapes == mip_sizes(TEX_HW)
    assert plans["bilinear"].level_shapes == (TEX_HW,)


def test_plan_under_jit_matches_eager_and_accepts_attribute():
    dx, dy = DUV
    eager = apply_plan(plan_sample(UV, dx, dy, size_hw=TEX_HW, levels=4, filter="trilinear",
                                   wrap="mirror"), MIPS)
    planner = jax.jit(plan_sample, static_argnames=("size_hw", "levels", "filter", "wrap"))
    plan = planner(UV, dx, dy, size_hw=TEX_HW, levels=4, filter="trilinear", wrap="mirror")
    jitted = jax.jit(apply_plan)(plan, MIPS)
    np.testing.assert_allclose(jitted, eager, rtol=1e-6)
    attr = Attribute(jnp.asarray(UV), jnp.asarray(dx), jnp.asarray(dy))
    via_attr = sample(MIPS, attr, filter="trilinear", wrap="mirror")
    np.testing.assert_allclose(via_attr, eager, rtol=1e-6)


def test_option_validation():
    uv = jnp.zeros((2, 2))
    for kw, name in ((dict(filter="linear"), "filter"), (dict(wrap="wrap"), "wrap"),
                     (dict(uv_origin="top"), "uv_origin")):
        with pytest.raises(ValueError, match=f"unknown {name}=.*expected one of"):
            plan_sample(uv, size_hw=(4, 4), **kw)
    with pytest.raises(ValueError, match="needs duvdx and duvdy"):
        plan_sample(uv, size_hw=(4, 4), levels=3, filter="trilinear")
    with pytest.raises(ValueError, match="reads 4 mip levels"):
        apply_plan(plan_sample(UV, *DUV, size_hw=TEX_HW, levels=4, filter="trilinear"),
                   MIPS[:1])
    with pytest.raises(ValueError, match="the plan expects"):
        apply_plan(plan_sample(uv, size_hw=(4, 4)), jnp.zeros((4, 5, 1)))
    with pytest.raises(ValueError, match="unknown encoding"):
        decode_normal_map(jnp.zeros(3), encoding="snorm")
    with pytest.raises(ValueError, match="unknown green"):
        decode_normal_map(jnp.zeros(3), green="left")
    with pytest.raises(ValueError, match="unknown channels"):
        encode_normal_map(jnp.zeros(3), channels=4)
    with pytest.raises(ValueError, match="at least 3 channels"):
        decode_normal_map(jnp.zeros(2))


# --------------------------------------------------------------------------- gradients


def test_apply_plan_gradients_wrt_texels():
    with jax.enable_x64(True):
        tex = jnp.asarray(TEX - 0.5, jnp.float64)  # centred, for the renormalised chain
        uv = jnp.asarray(UV[:8], jnp.float64)
        dx, dy = (jnp.asarray(d[:8], jnp.float64) for d in DUV)
        nearest = plan_sample(uv, size_hw=TEX_HW, filter="nearest")
        bilinear = plan_sample(uv, size_hw=TEX_HW, filter="bilinear")
        trilinear = plan_sample(uv, dx, dy, size_hw=TEX_HW, levels=4, filter="trilinear")

        @jax.jit
        def f(t):  # w.r.t. level 0, through the mip chain (plain and renormalised)
            return jnp.stack([apply_plan(nearest, t), apply_plan(bilinear, t),
                              apply_plan(trilinear, build_mipmaps(t)),
                              apply_plan(trilinear, build_mipmaps(t, renormalize=True))])

        check_grads(f, (tex,), order=1, modes=("fwd", "rev"))


def test_transpose_plan_is_apply_plans_vjp_in_a_fixed_order():
    """`transpose_plan` through `plan_sum_tables` gives what ``jax.vjp`` of `apply_plan`
    gives w.r.t. the mip chain (a scatter-add): trilinear taps over several levels, a level
    the plan does not read (zeros), pixels in a (2, n) batch; and the same bits each call."""
    rng = np.random.default_rng(5)
    uv = jnp.asarray(rng.uniform(0, 1, (2, 300, 2)), jnp.float32)
    dx = jnp.asarray(rng.uniform(0.2, 3.0, (2, 300, 2)) / 16, jnp.float32)
    dy = jnp.asarray(rng.uniform(0.2, 3.0, (2, 300, 2)) / 16, jnp.float32)
    mips = build_mipmaps(jnp.asarray(rng.normal(size=(16, 16, 3)), jnp.float32))
    plan = plan_sample(uv, dx, dy, size_hw=(16, 16), levels=3, filter="trilinear")
    assert len(mips) > 3 and plan.index.shape == (2, 300, 8)
    cot = jnp.asarray(rng.normal(size=(2, 300, 3)), jnp.float32)
    _, pull = jax.vjp(lambda m: apply_plan(plan, m), mips)
    want = pull(cot)[0]
    tables = plan_sum_tables(plan)
    got = jax.jit(transpose_plan)(plan, tables, cot, mips)
    assert len(got) == len(mips)
    for g, w, m in zip(got, want, mips):
        assert g.shape == m.shape and g.dtype == m.dtype
        np.testing.assert_allclose(np.asarray(g), np.asarray(w), rtol=1e-5, atol=1e-5)
    assert not any(np.asarray(g).any() for g in got[3:])
    again = jax.jit(transpose_plan)(plan, tables, cot, mips)
    for g, h in zip(got, again):
        np.testing.assert_array_equal(np.asarray(g), np.asarray(h))
    # stacked: the tables of two halves, each used on its own half
    halves = plan_sum_tables(plan, [plan.index[:, :150], plan.index[:, 150:]])
    for k, cut in enumerate((slice(0, 150), slice(150, 300))):
        part = jax.tree_util.tree_map(lambda x, cut=cut: x[:, cut], plan)
        one = jax.tree_util.tree_map(lambda x, k=k: x[k], halves)
        _, pull = jax.vjp(lambda m, part=part: apply_plan(part, m), mips)
        for g, w in zip(transpose_plan(part, one, cot[:, cut], mips), pull(cot[:, cut])[0]):
            np.testing.assert_allclose(np.asarray(g), np.asarray(w), rtol=1e-5, atol=1e-5)


def test_sample_gradients_wrt_uv_and_derivatives():
    with jax.enable_x64(True):
        tex = jnp.asarray(TEX, jnp.float64)
        mips = build_mipmaps(tex)
        uv = UV.astype(np.float64)
        for size in (8, 4, 2):  # stay off the kinks (texel centres) of the levels used
            uv = uv[away_from(uv[:, 0] * size - 0.5, 1, 0.05)
                    & away_from(uv[:, 1] * size / 2 - 0.5, 1, 0.05)]
        assert uv.shape[0] >= 3
        uv = jnp.asarray(uv)
        # trilinear: lambda = log2(2.5) (not an integer), the x derivative dominates
        h, w = TEX_HW
        dx = jnp.tile(jnp.asarray([[2.5 / w, 0.1 / h]]), (uv.shape[0], 1))
        dy = jnp.tile(jnp.asarray([[0.2 / w, 1.0 / h]]), (uv.shape[0], 1))

        @jax.jit
        def f(x, a, b):
            return jnp.stack([sample(tex, x, wrap=wrap) for wrap in WRAPS]
                             + [sample(mips, x, a, b, filter="trilinear")])

        # reverse mode runs the custom JVP rule of the gather and its transpose
        check_grads(f, (uv, dx, dy), order=1, modes=("rev",))


def test_decode_gradients_are_finite_at_degenerate_texels():
    raw = jnp.asarray([[0.5, 0.5, 0.5],  # decodes to the zero vector
                       [1.0, 1.0, 0.5],  # 2-channel: |xy| > 1 -> z = 0
                       [1.0, 0.5, 0.5]])  # 2-channel: |xy| = 1 exactly
    normal = jnp.asarray([[0.0, 0.0, 1.0]])
    for channels in (2, 3):
        def f(r):
            n = decode_normal_map(r, channels=channels)
            return jnp.sum(safe_normalize(n, fallback=normal) + n)

        g = jax.jit(jax.grad(f))(raw)
        assert np.all(np.isfinite(g)), channels
    n = decode_normal_map(raw[:1])
    np.testing.assert_array_equal(n, 0.0)
    np.testing.assert_array_equal(safe_normalize(n, fallback=normal), [[0.0, 0.0, 1.0]])


# --------------------------------------------------------------------------- normal maps


def test_exact_sign_expansion_8_bit():
    codes = np.arange(256)
    for raw in (np.float32(codes) / np.float32(255), np.float32(codes) * np.float32(1 / 255)):
        x = np.asarray(decode_normal_map(np.stack([raw] * 3, -1),
                                         encoding="unsigned_exact"))[:, 0]
        assert x[128] == 0.0 and x[255] == 1.0 and x[1] == -1.0
        assert x[0] == -1.0  # -128/127 clamps to -1, like snorm
        np.testing.assert_allclose(x[1:], (codes[1:] - 128) / 127, atol=1e-6)
        assert np.all(np.diff(x[1:]) > 0)


def test_exact_sign_expansion_16_bit():
    codes = np.asarray([0, 1, 2, 32767, 32768, 32769, 65534, 65535])
    raw = np.float32(codes) / np.float32(65535)
    x = np.asarray(decode_normal_map(np.stack([raw] * 3, -1), encoding="unsigned_exact",
                                     bits=16))[:, 0]
    assert x[4] == 0.0 and x[-1] == 1.0 and x[1] == -1.0 and x[0] == -1.0
    np.testing.assert_allclose(x[1:], (codes[1:] - 32768) / 32767, atol=1e-6)


def test_unsigned_and_signed_expansion():
    raw = jnp.asarray([[0.0, 0.5, 1.0]])
    np.testing.assert_array_equal(decode_normal_map(raw), [[-1.0, 0.0, 1.0]])
    signed = jnp.asarray([[-0.3, 0.2, 0.9]])
    np.testing.assert_array_equal(decode_normal_map(signed, encoding="signed"), signed)


def test_two_channel_z_reconstruction():
    xy = np.asarray([[0.0, 0.0], [0.6, 0.0], [0.6, -0.8], [0.9, 0.9], [-1.0, 0.0]], np.float32)
    raw = np.concatenate([xy, np.full((5, 1), 0.123, np.float32)], -1)  # 3rd channel ignored
    n = np.asarray(decode_normal_map(raw, encoding="signed", channels=2))
    np.testing.assert_allclose(n[:, :2], xy)
    np.testing.assert_allclose(n[:, 2], [1.0, 0.8, 0.0, 0.0, 0.0], atol=1e-6)
    assert np.all(np.isfinite(n))


def test_green_convention_in_terms_of_v():
    raw = jnp.asarray([0.5, 0.75, 0.5])  # stored green > 0.5: +green
    y = {(g, o): float(decode_normal_map(raw, green=g, uv_origin=o)[1])
         for g in ("up", "down") for o in ORIGINS}
    # bottom_left: +v is the image top, so green-up maps point along +v
    assert y[("up", "bottom_left")] == 0.5 and y[("down", "bottom_left")] == -0.5
    # top_left: +v is the image bottom (Schueler's GLSL negates y for GREEN_UP)
    assert y[("up", "top_left")] == -0.5 and y[("down", "top_left")] == 0.5


def test_strength_scales_xy_only():
    raw = jnp.asarray([[0.8, 0.3, 0.9]])
    base = decode_normal_map(raw)
    strong = decode_normal_map(raw, strength=2.5)
    np.testing.assert_allclose(strong[:, :2], 2.5 * base[:, :2], rtol=1e-6)
    np.testing.assert_array_equal(strong[:, 2], base[:, 2])
    flat = decode_normal_map(raw, strength=0.0, channels=2)
    np.testing.assert_allclose(flat[:, :2], 0.0)
    np.testing.assert_allclose(flat[:, 2], np.sqrt(1 - 0.6**2 - 0.4**2), rtol=1e-6)


def _unit_normals(n, seed, z_min=0.05):
    v = np.random.default_rng(seed).normal(size=(n, 3))
    v[:, 2] = np.abs(v[:, 2]) + z_min
    return (v / np.linalg.norm(v, axis=-1, keepdims=True)).astype(np.float32)


ROUND_TRIPS = [(enc, ch, "up", "bottom_left") for enc in ("unsigned", "unsigned_exact", "signed")
               for ch in (2, 3)] + [("unsigned", 3, "down", "bottom_left"),
                                    ("unsigned_exact", 2, "down", "top_left"),
                                    ("signed", 3, "up", "top_left")]


def test_encode_decode_round_trip():
    n = _unit_normals(64, seed=5, z_min=0.3)
    for encoding, channels, green, origin in ROUND_TRIPS:
        kw = dict(encoding=encoding, channels=channels, green=green, uv_origin=origin)
        stored = encode_normal_map(n, **kw)
        assert stored.shape == (64, channels)
        lo = -1.0 if encoding == "signed" else 0.0
        assert np.all((stored >= lo) & (stored <= 1.0))
        np.testing.assert_allclose(decode_normal_map(stored, **kw), n, atol=1e-5, err_msg=kw)


def test_quantised_round_trip():
    n = _unit_normals(64, seed=6)
    for bits in (8, 16):
        top = 2**bits - 1
        for encoding in ("unsigned", "unsigned_exact"):
            stored = np.asarray(encode_normal_map(n, encoding=encoding, bits=bits))
            raw = (np.round(stored.astype(np.float64) * top) / top).astype(np.float32)
            back = np.asarray(decode_normal_map(raw, encoding=encoding, bits=bits))
            assert np.max(np.abs(back - n)) <= 1.01 / (2 ** (bits - 1) - 1)
        # the exact lattice k / (2^(b-1) - 1) survives quantisation exactly
        half = 2 ** (bits - 1)
        vals = np.asarray([-1.0, -((half - 1) // 2) / (half - 1), 0.0, 1.0], np.float32)
        lattice = np.stack([vals, vals[::-1], np.abs(vals)], -1)
        stored = np.asarray(encode_normal_map(lattice, encoding="unsigned_exact", bits=bits))
        raw = (np.round(stored.astype(np.float64) * top) / top).astype(np.float32)
        back = np.asarray(decode_normal_map(raw, encoding="unsigned_exact", bits=bits))
        np.testing.assert_allclose(back, lattice, atol=1e-6)
        assert back[2, 0] == 0.0 and back[0, 0] == -1.0 and back[3, 0] == 1.0


def test_decode_after_filtering_commutes_for_linear_encodings():
    # filter stored values, then decode (GPU order) == filter decoded values (linear decode)
    raw = np.random.default_rng(8).random(TEX.shape).astype(np.float32)
    a = decode_normal_map(sample(raw, UV))
    b = sample(decode_normal_map(raw), UV)
    np.testing.assert_allclose(a, b, atol=1e-6)


# --------------------------------------------------------------------------- sRGB


def test_srgb_known_values_and_round_trip():
    x = jnp.asarray([0.0, 0.04045, 0.5, 1.0, 128 / 255])
    lin = np.asarray(srgb_to_linear(x))
    np.testing.assert_allclose(lin[:4], [0.0, 0.04045 / 12.92, 0.21404114, 1.0], rtol=1e-6)
    np.testing.assert_allclose(lin[4], 0.21586050, rtol=1e-6)
    np.testing.assert_allclose(linear_to_srgb(jnp.asarray([0.0, 0.5, 1.0])),
                               [0.0, 0.7353569, 1.0], rtol=1e-6)
    t = jnp.linspace(0.0, 1.0, 257)
    np.testing.assert_allclose(linear_to_srgb(srgb_to_linear(t)), t, atol=2e-6)
    np.testing.assert_allclose(srgb_to_linear(linear_to_srgb(t)), t, atol=2e-6)
    # the two pieces meet at the knees
    for f, knee in ((srgb_to_linear, 0.04045), (linear_to_srgb, 0.0031308)):
        with jax.enable_x64(True):
            below, above = f(jnp.asarray([knee, knee * (1 + 1e-12)]))
            assert abs(float(above) - float(below)) < 1e-7  # IEC knees: gaps of 2e-9, 3e-8


def test_srgb_gradients_are_finite_at_zero():
    g1 = jax.grad(lambda x: jnp.sum(srgb_to_linear(x)))(jnp.zeros(3))
    g2 = jax.grad(lambda x: jnp.sum(linear_to_srgb(x)))(jnp.zeros(3))
    np.testing.assert_allclose(g1, 1 / 12.92, rtol=1e-6)
    np.testing.assert_allclose(g2, 12.92, rtol=1e-6)
    g3 = jax.grad(lambda x: jnp.sum(linear_to_srgb(x)))(jnp.asarray([0.2, 1.0]))
    assert np.all(np.isfinite(g3))


# --------------------------------------------------------------------------- real GL


_GL_VS = """#version 450
void main() {
    gl_Position = vec4(float((gl_VertexID & 1) * 4 - 1), float((gl_VertexID >> 1) * 4 - 1), 0, 1);
}"""
_GL_FS = """#version 450
layout(binding = 0) uniform sampler2D tex;
layout(binding = 1) uniform sampler2D uvs;  // (u, v, lod, use_lod) per output pixel
out vec4 color;
void main() {
    vec4 q = texelFetch(uvs, ivec2(gl_FragCoord.xy), 0);
    color = q.w > 0.5 ? textureLod(tex, q.xy, q.z) : texture(tex, q.xy);
}"""


def _gl_sample(levels, uv, *, wrap, filter, origin="bottom_left", lods=None):
    """Sample RGBA32F `levels` with the GL texture unit (llvmpipe) at `uv`, (n, 2)."""
    import ctypes

    import moderngl
    from glref import _get_state  # the shared context of the GL reference renderer

    ctx = _get_state()["ctx"]
    egl = ctypes.CDLL("libEGL.so.1")
    egl.eglGetProcAddress.restype = ctypes.c_void_p
    egl.eglGetProcAddress.argtypes = [ctypes.c_char_p]
    u, i = ctypes.c_uint, ctypes.c_int
    bind = ctypes.CFUNCTYPE(None, u, u)(egl.eglGetProcAddress(b"glBindTexture"))
    param = ctypes.CFUNCTYPE(None, u, u, i)(egl.eglGetProcAddress(b"glTexParameteri"))
    gl_wrap = {"repeat": 0x2901, "clamp": 0x812F, "mirror": 0x8370}[wrap]
    gl_min = {"nearest": 0x2600, "bilinear": 0x2601, "trilinear": 0x2703}[filter]
    h, w, c = levels[0].shape
    n = uv.shape[0]
    objects = []
    try:
        tex = ctx.texture((w, h), 4, dtype="f4")
        objects.append(tex)
        if len(levels) > 1:
            tex.build_mipmaps(0, len(levels) - 1)
        for k, level in enumerate(levels):
            rgba = np.zeros(level.shape[:2] + (4,), np.float32)
            rgba[..., :c] = level
            if origin == "bottom_left":  # the usual flip on upload: image bottom row at t = 0
                rgba = rgba[::-1]
            tex.write(np.ascontiguousarray(rgba).tobytes(), level=k)
        bind(0x0DE1, tex.glo)  # GL_TEXTURE_2D
        for pname, value in ((0x2802, gl_wrap), (0x2803, gl_wrap), (0x2801, gl_min),
                             (0x2800, 0x2600 if filter == "nearest" else 0x2601),
                             (0x813D, len(levels) - 1)):  # WRAP_S/T, MIN/MAG, MAX_LEVEL
            param(0x0DE1, pname, value)
        q = np.zeros((1, n, 4), np.float32)
        q[0, :, :2] = uv
        if lods is not None:
            q[0, :, 2], q[0, :, 3] = lods, 1.0
        uvs = ctx.texture((n, 1), 4, q.tobytes(), dtype="f4")
        uvs.filter = (moderngl.NEAREST, moderngl.NEAREST)
        target = ctx.renderbuffer((n, 1), 4, dtype="f4")
        fbo = ctx.framebuffer([target])
        prog = ctx.program(vertex_shader=_GL_VS, fragment_shader=_GL_FS)
        vao = ctx.vertex_array(prog, [])
        objects += [uvs, target, fbo, prog, vao]
        fbo.use()
        ctx.viewport = (0, 0, n, 1)
        tex.use(0)
        uvs.use(1)
        vao.render(moderngl.TRIANGLES, vertices=3)
        out = np.frombuffer(fbo.read(components=4, dtype="f4"), np.float32)
        return out.reshape(n, 4)[:, :c]
    finally:
        for obj in reversed(objects):
            obj.release()


def _gl_ok():
    try:
        from glref import gl_available

        return gl_available()
    except Exception as exc:  # noqa: BLE001 - moderngl missing etc.
        return False, str(exc)


_GL = _gl_ok()


@pytest.mark.gl
@pytest.mark.skipif(not _GL[0], reason=f"no OpenGL: {_GL[1]}")
def test_matches_the_gl_texture_unit():
    for origin in ORIGINS:
        for wrap in WRAPS:
            for filter in ("nearest", "bilinear"):
                gl = _gl_sample([TEX], UV, wrap=wrap, filter=filter, origin=origin)
                ours = sample(TEX, UV, filter=filter, wrap=wrap, uv_origin=origin)
                np.testing.assert_allclose(ours, gl, atol=2e-6, err_msg=(origin, wrap, filter))
    # level selection and blending: textureLod(lambda) vs derivatives with rho = 2^lambda
    lods = np.linspace(-0.5, 3.5, N).astype(np.float32)
    gl = _gl_sample([np.asarray(m) for m in MIPS], UV, wrap="repeat", filter="trilinear",
                    lods=lods)
    dx = np.stack([2.0**lods / TEX_HW[1], np.zeros(N)], -1).astype(np.float32)
    ours = sample(MIPS, UV, dx, np.zeros_like(dx), filter="trilinear")
    np.testing.assert_allclose(ours, gl, atol=2e-6)


@pytest.mark.parametrize("shape", [(8, 6), (7, 9), (1, 5), (3, 1)])
def test_box_filter_matrix_is_build_mipmaps_filter(shape):
    """`box_filter_matrix` along each axis gives `build_mipmaps`' next level (even, odd
    and size-1 axes)."""
    tex = np.random.default_rng(5).uniform(-1, 1, shape + (1,)).astype(np.float32)
    want = np.asarray(build_mipmaps(jnp.asarray(tex), levels=2)[1])[..., 0]
    got = (box_filter_matrix(shape[0]) @ tex[..., 0].astype(np.float64)
           @ box_filter_matrix(shape[1]).T)
    assert got.shape == mip_sizes(shape)[1]
    np.testing.assert_allclose(got, want, rtol=1e-6, atol=1e-6)
