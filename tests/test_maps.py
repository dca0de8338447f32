"""Tests for jaxnm.maps: bump (surface gradient), derivative and object-space normal maps."""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.test_util import check_grads

import jaxnm
from jaxnm import maps
from jaxnm.camera import Camera, look_at, orthographic, perspective

# jitted: eager dispatch would compile every primitive for every new shape
bump_normal = jax.jit(maps.bump_normal)
derivative_map_normal = jax.jit(maps.derivative_map_normal)
height_to_normal_map = jax.jit(maps.height_to_normal_map, static_argnames="wrap")
height_to_derivative_map = jax.jit(maps.height_to_derivative_map, static_argnames="wrap")
object_space_normal = jax.jit(maps.object_space_normal)
normal_matrix = jax.jit(maps.normal_matrix)

# --------------------------------------------------------------------------------------
# an analytic height field on a tilted plane
# --------------------------------------------------------------------------------------

ORIGIN = np.array([0.3, -0.2, 0.1])
_T = np.array([0.8, 0.0, 0.6])
_B = np.cross(np.array([-0.6, 0.28, 0.8]) / np.linalg.norm([-0.6, 0.28, 0.8]), _T)
_B = _B / np.linalg.norm(_B)
TX, TY = _T, _B  # orthonormal tangents of the plane
NORMAL = np.cross(TX, TY)  # unit plane normal
UV_A = np.array([[0.7, 0.25], [-0.15, 0.9]])  # uv = UV_A @ (s, t) + UV_C: sheared, scaled
UV_C = np.array([0.5, 0.5])


def _height(st):
    s, t = st[..., 0], st[..., 1]
    return 0.05 * jnp.sin(3 * s + 0.4) + 0.03 * jnp.cos(5 * t - 0.2) + 0.02 * jnp.sin(2 * s + 4 * t)


def _height_grad(st):
    s, t = st[..., 0], st[..., 1]
    hs = 0.15 * jnp.cos(3 * s + 0.4) + 0.04 * jnp.cos(2 * s + 4 * t)
    ht = -0.15 * jnp.sin(5 * t - 0.2) + 0.08 * jnp.cos(2 * s + 4 * t)
    return jnp.stack([hs, ht], -1)


def _like(v, x):
    """Constant vector ``v`` with leading unit axes to the rank of ``x`` (explicit broadcast)."""
    v = jnp.asarray(v, x.dtype)
    return v.reshape((1,) * (x.ndim - v.ndim) + v.shape)


def _mm(a, b):
    """The references' products at full float32 precision (a GPU's default is TF32: 1e-3)."""
    return jnp.matmul(a, jnp.asarray(b, jnp.result_type(a)), precision=jax.lax.Precision.HIGHEST)


def _plane_coords(p):
    d = p - _like(ORIGIN, p)
    return jnp.stack([_mm(d, TX), _mm(d, TY)], -1)


def _analytic_normal(st, scale):
    g = _height_grad(st)
    g3 = g[..., :1] * _like(TX, g) + g[..., 1:] * _like(TY, g)
    n = _like(NORMAL, g3) - scale * g3
    return n / jnp.linalg.norm(n, axis=-1, keepdims=True)


def _camera_matrices(kind):
    view = look_at([1.5, -2.0, 3.0], ORIGIN + 0.1 * TX, up=[0.0, 0.0, 1.0])
    if kind == "perspective":
        proj = perspective(50.0, 1.0, 0.1, 50.0)
    else:
        proj = orthographic(-1.5, 1.5, -1.5, 1.5, 0.1, 50.0)
    return view, proj


@functools.cache
def _screen_samples(kind, size=32):
    """Window positions -> plane points, with exact screen derivatives (jacfwd, float64)."""
    view, proj = _camera_matrices(kind)
    inv = jnp.asarray(np.linalg.inv(proj @ view))

    def world(xy):  # window (x, y up) -> intersection of the pixel's ray with the plane
        ndc = 2.0 * xy / size - 1.0
        a = inv @ jnp.concatenate([ndc, jnp.array([-1.0, 1.0])])
        b = inv @ jnp.concatenate([ndc, jnp.array([1.0, 1.0])])
        a, b = a[:3] / a[3], b[:3] / b[3]
        t = jnp.dot(ORIGIN - a, NORMAL) / jnp.dot(b - a, NORMAL)
        return a + t * (b - a)

    @jax.jit
    def samples(xy):
        p = jax.vmap(world)(xy)
        jac = jax.vmap(jax.jacfwd(world))(xy)  # (n, 3, 2)
        dh = jax.vmap(jax.grad(lambda q: _height(_plane_coords(world(q)))))(xy)
        uv_jac = jax.vmap(jax.jacfwd(lambda q: _plane_coords(world(q)) @ UV_A.T))(xy)
        return p, jac, dh, uv_jac

    g = np.linspace(2.5, size - 2.5, 6)
    p, jac, dh, uv_jac = samples(jnp.asarray(np.stack(np.meshgrid(g, g), -1).reshape(-1, 2)))
    return dict(p=p, dp_dx=jac[..., 0], dp_dy=jac[..., 1], dh_dx=dh[:, 0], dh_dy=dh[:, 1],
                duv_dx=uv_jac[..., 0], duv_dy=uv_jac[..., 1])


def _dhduv(st):
    """Gradient of H(uv) = h(st(uv)) with uv = UV_A st + UV_C: UV_A^-T grad h."""
    return _mm(_height_grad(st), np.linalg.inv(UV_A))


# --------------------------------------------------------------------------------------
# bump and derivative maps against the analytic normal
# --------------------------------------------------------------------------------------


@pytest.mark.parametrize("kind", ["orthographic", "perspective"])
def test_bump_normal_matches_analytic_height_field(kind):
    with jax.enable_x64(True):
        sc = _screen_samples(kind)
        N = jnp.broadcast_to(jnp.asarray(NORMAL), sc["p"].shape)
        st = _plane_coords(sc["p"])
        for scale in (1.0, 2.5):
            got = bump_normal(N, sc["dp_dx"], sc["dp_dy"], sc["dh_dx"], sc["dh_dy"],
                              scale=scale)
            np.testing.assert_allclose(got, _analytic_normal(st, scale), atol=1e-10)
        # the normals really are perturbed
        assert float(jnp.min(got @ NORMAL)) < 0.99
        # HLSL's downward ddy: flip every y derivative, same normal
        flipped = bump_normal(N, sc["dp_dx"], -sc["dp_dy"], sc["dh_dx"], -sc["dh_dy"],
                              scale=scale)
        np.testing.assert_allclose(flipped, got, atol=1e-12)
        # (..., 1) heights are accepted too
        got1 = bump_normal(N, sc["dp_dx"], sc["dp_dy"], sc["dh_dx"][:, None],
                           sc["dh_dy"][:, None], scale=scale)
        np.testing.assert_allclose(got1, got, atol=1e-12)


@pytest.mark.parametrize("kind", ["orthographic", "perspective"])
def test_derivative_map_equals_bump_map(kind):
    with jax.enable_x64(True):
        sc = _screen_samples(kind)
        N = jnp.broadcast_to(jnp.asarray(NORMAL), sc["p"].shape)
        st = _plane_coords(sc["p"])
        dmap = derivative_map_normal(N, sc["dp_dx"], sc["dp_dy"], sc["duv_dx"], sc["duv_dy"],
                                     _dhduv(st), scale=1.7)
        bump = bump_normal(N, sc["dp_dx"], sc["dp_dy"], sc["dh_dx"], sc["dh_dy"], scale=1.7)
        np.testing.assert_allclose(dmap, bump, atol=1e-10)
        np.testing.assert_allclose(dmap, _analytic_normal(st, 1.7), atol=1e-10)


def test_surface_gradient_identity_random():
    """dh = g . dp for a tangent g gives normalize(N - s g) for ANY non-degenerate dp_dx, dp_dy.

    Hence derivative maps are exact under every derivative mode (fine, coarse, analytic): the
    screen derivatives only have to be consistent between position and uv.
    """
    rng = np.random.default_rng(0)
    n = 64
    N = rng.normal(size=(n, 3))
    N /= np.linalg.norm(N, axis=-1, keepdims=True)

    def tangent(v):
        return v - np.sum(v * N, -1, keepdims=True) * N

    sx, sy, g = (tangent(rng.normal(size=(n, 3))) for _ in range(3))
    sx *= rng.uniform(1e-3, 1e2, size=(n, 1))  # wildly different screen scales
    hx, hy = np.sum(g * sx, -1), np.sum(g * sy, -1)
    expected = N - 0.8 * g
    expected /= np.linalg.norm(expected, axis=-1, keepdims=True)
    got = bump_normal(*(jnp.asarray(x, jnp.float32) for x in (N, sx, sy, hx, hy)), scale=0.8)
    np.testing.assert_allclose(got, expected, atol=2e-5)


_interpolate = jax.jit(jaxnm.interpolate, static_argnames="derivatives")


@pytest.mark.parametrize("mode", ["analytic", "fine", "coarse"])
def test_derivative_map_on_rasterized_plane(mode):
    """jaxnm.rasterize + interpolate on a 2-triangle plane at 32x32, float32."""
    corners = np.array([[-1.5, -1.5], [1.5, -1.5], [1.5, 1.5], [-1.5, 1.5]])
    positions = ORIGIN + corners[:, :1] * TX + corners[:, 1:] * TY
    uv = corners @ UV_A.T + UV_C
    faces = np.array([[0, 1, 2], [0, 2, 3]])
    view, proj = _camera_matrices("perspective")
    cam = Camera.from_matrices(view, proj)
    clip = jaxnm.to_clip(jnp.asarray(positions, jnp.float32), cam)
    frags = jaxnm.rasterize(clip, jnp.asarray(faces), width=32, height=32)
    attrs = _interpolate({"p": jnp.asarray(positions, jnp.float32),
                          "uv": jnp.asarray(uv, jnp.float32)}, frags, derivatives=mode)
    mask = np.asarray(frags.mask)
    assert mask.sum() > 300
    p = attrs["p"].value
    uv0 = attrs["uv"].value - _like(UV_C, attrs["uv"].value)
    st = _mm(uv0, np.linalg.inv(UV_A).T)
    N = jnp.broadcast_to(jnp.asarray(NORMAL, jnp.float32), p.shape)
    got = derivative_map_normal(N, attrs["p"].ddx, attrs["p"].ddy, attrs["uv"].ddx,
                                attrs["uv"].ddy, _dhduv(st).astype(jnp.float32), scale=2.0)
    expected = _analytic_normal(_plane_coords(p), 2.0)
    assert np.all(np.isfinite(got))
    np.testing.assert_allclose(np.asarray(got)[mask], np.asarray(expected)[mask], atol=2e-4)
    # background pixels: zero derivatives and N = 0 in, zero normal out, no NaN
    zero = derivative_map_normal(jnp.zeros_like(N), attrs["p"].ddx, attrs["p"].ddy,
                                 attrs["uv"].ddx, attrs["uv"].ddy, jnp.zeros_like(st))
    assert np.all(np.asarray(zero)[~mask] == 0.0)


# --------------------------------------------------------------------------------------
# degenerate inputs
# --------------------------------------------------------------------------------------


def test_degenerate_footprint_returns_N_without_nan():
    N = jnp.asarray([0.0, 0.6, 0.8])
    ex, ey = jnp.array([1.0, 0.0, 0.0]), jnp.array([0.0, 0.8, -0.6])
    cases = {
        "zero dp_dx": (jnp.zeros(3), ey, 0.3, -0.2),
        "zero footprint": (jnp.zeros(3), jnp.zeros(3), 0.3, -0.2),
        "edge-on (dp_dx || dp_dy)": (ex, 2.0 * ex, 0.3, -0.2),
        "zero height derivatives": (ex, ey, 0.0, 0.0),
    }

    def f(N, sx, sy, hx, hy):
        return jnp.sum(maps.bump_normal(N, sx, sy, hx, hy, scale=1.5) * jnp.array([0.3, 1.0, 2.0]))

    grad = jax.jit(jax.grad(f, argnums=(0, 1, 2, 3, 4)))
    for name, (sx, sy, hx, hy) in cases.items():
        out = bump_normal(N, sx, sy, jnp.asarray(hx), jnp.asarray(hy), scale=1.5)
        np.testing.assert_allclose(out, N, atol=1e-7, err_msg=name)
        for g in grad(N, sx, sy, jnp.asarray(hx), jnp.asarray(hy)):
            assert np.all(np.isfinite(g)), name
    # a zero normal stays zero, finitely
    out = bump_normal(jnp.zeros(3), ex, ey, jnp.asarray(0.3), jnp.asarray(0.1))
    assert np.all(out == 0.0)
    for g in grad(jnp.zeros(3), ex, ey, jnp.asarray(0.3), jnp.asarray(0.1)):
        assert np.all(np.isfinite(g))
    # derivative map with zero uv derivatives: N unchanged
    out = derivative_map_normal(N, ex, ey, jnp.zeros(2), jnp.zeros(2), jnp.array([3.0, -1.0]))
    np.testing.assert_allclose(out, N, atol=1e-7)
    g = jax.jit(jax.grad(lambda d: jnp.sum(maps.derivative_map_normal(N, ex, ey, d, d, d))))(
        jnp.zeros(2))
    assert np.all(np.isfinite(g))


def test_check_grads_bump_and_derivative_map():
    with jax.enable_x64(True):
        rng = np.random.default_rng(1)
        # O(1) magnitudes: check_grads' finite differences use a fixed step
        N = jnp.asarray([0.1, 0.2, 0.97]) / np.linalg.norm([0.1, 0.2, 0.97])
        sx = jnp.asarray([1.0, 0.2, -0.1])
        sy = jnp.asarray([-0.1, 1.2, -0.2])
        hx, hy = jnp.asarray(0.4), jnp.asarray(-0.3)
        check_grads(jax.jit(lambda *a: maps.bump_normal(*a, scale=1.3)), (N, sx, sy, hx, hy),
                    order=1, modes=("fwd", "rev"))
        duv_dx, duv_dy, d = (jnp.asarray(rng.normal(size=2)) for _ in range(3))
        check_grads(jax.jit(lambda *a: maps.derivative_map_normal(*a, scale=0.7)),
                    (N, sx, sy, duv_dx, duv_dy, d), order=1, modes=("fwd", "rev"))


# --------------------------------------------------------------------------------------
# height-map conversions
# --------------------------------------------------------------------------------------


def _ramp(a, b, rows=6, cols=7):
    """h = a * column + b * (rows - 1 - row): slope a per texel along u, b along v (v up)."""
    r, c = np.meshgrid(np.arange(rows), np.arange(cols), indexing="ij")
    return jnp.asarray(a * c + b * (rows - 1 - r), jnp.float32)


def test_height_to_normal_map_linear_ramp():
    a, b, s = 0.3, -0.5, 2.0
    expected = np.array([-s * a, -s * b, 1.0]) / np.linalg.norm([-s * a, -s * b, 1.0])
    nmap = height_to_normal_map(_ramp(a, b), scale=s, wrap="clamp")
    assert nmap.shape == (6, 7, 3)
    np.testing.assert_allclose(nmap, np.broadcast_to(expected, nmap.shape), atol=1e-6)
    nmap = height_to_normal_map(_ramp(a, b), scale=s, wrap="repeat")
    np.testing.assert_allclose(nmap[1:-1, 1:-1], np.broadcast_to(expected, (4, 5, 3)), atol=1e-6)
    # v is up: a bump in the top row slopes the surface up towards +v, tilting n to -v
    h = jnp.zeros((5, 5)).at[0].set(1.0)
    assert float(height_to_normal_map(h, wrap="clamp")[1, 2, 1]) < -0.1


def test_height_to_normal_map_periodic_sine_exact():
    """Central differences of sin(k c) are sin(k) cos(k c): exact, with wrap-around."""
    cols, k, amp = 16, 2 * np.pi / 16, 0.7
    c = np.arange(cols)
    h = jnp.asarray(np.broadcast_to(amp * np.sin(k * c + 0.3), (4, cols)), jnp.float32)
    du = amp * np.sin(k) * np.cos(k * c + 0.3)
    n = np.stack([-du, np.zeros_like(du), np.ones_like(du)], -1)
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    got = height_to_normal_map(h, wrap="repeat")
    np.testing.assert_allclose(got, np.broadcast_to(n, got.shape), atol=1e-6)


def test_height_to_derivative_map_units():
    a, b, s = 0.3, -0.5, 2.0
    d = height_to_derivative_map(_ramp(a, b), scale=s, wrap="clamp")
    assert d.shape == (6, 7, 2)
    np.testing.assert_allclose(d[..., 0], s * 7 * a, rtol=1e-6)  # per unit u (7 columns)
    np.testing.assert_allclose(d[..., 1], s * 6 * b, rtol=1e-6)  # per unit v (6 rows)


def test_derivative_map_consistent_with_normal_map():
    """A plane with one world unit per texel, seen one pixel per texel: both conversions agree."""
    rng = np.random.default_rng(2)
    rows, cols, s = 8, 10, 0.7
    h = jnp.asarray(rng.normal(size=(rows, cols)), jnp.float32)
    nmap = height_to_normal_map(h, scale=s)
    dmap = height_to_derivative_map(h, scale=s)
    shape = (rows, cols, 3)
    N = jnp.broadcast_to(jnp.array([0.0, 0.0, 1.0]), shape)
    dp_dx = jnp.broadcast_to(jnp.array([1.0, 0.0, 0.0]), shape)  # x = u direction (T)
    dp_dy = jnp.broadcast_to(jnp.array([0.0, 1.0, 0.0]), shape)  # window y up = v (B)
    duv_dx = jnp.broadcast_to(jnp.array([1.0 / cols, 0.0]), (rows, cols, 2))
    duv_dy = jnp.broadcast_to(jnp.array([0.0, 1.0 / rows]), (rows, cols, 2))
    got = derivative_map_normal(N, dp_dx, dp_dy, duv_dx, duv_dy, dmap)
    np.testing.assert_allclose(got, nmap, atol=1e-6)


def test_height_map_errors():
    with pytest.raises(ValueError, match="wrap"):
        height_to_normal_map(jnp.zeros((4, 4)), wrap="mirror")
    with pytest.raises(ValueError, match=r"\(H, W\)"):
        height_to_derivative_map(jnp.zeros((4, 4, 1)))
    # tiny maps do not crash
    assert height_to_normal_map(jnp.zeros((1, 3)), wrap="clamp").shape == (1, 3, 3)


# --------------------------------------------------------------------------------------
# object-space normal maps
# --------------------------------------------------------------------------------------


def _rotation(rng):
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    return q if np.linalg.det(q) > 0 else -q


def test_object_space_normal_rotation():
    rng = np.random.default_rng(3)
    R = _rotation(rng)
    m = rng.normal(size=(4, 5, 3))
    unit = m / np.linalg.norm(m, axis=-1, keepdims=True)
    np.testing.assert_allclose(normal_matrix(jnp.asarray(R, jnp.float32)), R, atol=1e-6)
    got = object_space_normal(jnp.asarray(m, jnp.float32),
                                   model_normal_matrix=normal_matrix(jnp.asarray(R)))
    np.testing.assert_allclose(got, unit @ R.T, atol=1e-6)
    # no matrix: object space is world space, just normalised
    np.testing.assert_allclose(object_space_normal(jnp.asarray(m, jnp.float32)), unit,
                               atol=1e-6)


def test_object_space_normal_nonuniform_scale_and_mirror():
    """On an ellipsoid x = A q (q on the unit sphere, object normal q) the world normal is
    perpendicular to the transformed tangents and points outwards, also when A mirrors."""
    rng = np.random.default_rng(4)
    q = rng.normal(size=(32, 3))
    q /= np.linalg.norm(q, axis=-1, keepdims=True)
    t1 = np.cross(q, rng.normal(size=3))
    t2 = np.cross(q, t1)
    for A in (np.diag([2.0, 0.5, 1.0]) @ _rotation(rng), np.diag([-1.0, 2.0, 3.0])):
        model = np.eye(4)
        model[:3, :3], model[:3, 3] = A, [1.0, 2.0, 3.0]
        n = object_space_normal(jnp.asarray(q, jnp.float32),
                                     model_normal_matrix=normal_matrix(jnp.asarray(model)))
        n = np.asarray(n, np.float64)
        np.testing.assert_allclose(np.linalg.norm(n, axis=-1), 1.0, atol=1e-6)
        np.testing.assert_allclose(np.sum(n * (t1 @ A.T), -1), 0.0, atol=1e-5)
        np.testing.assert_allclose(np.sum(n * (t2 @ A.T), -1), 0.0, atol=1e-5)
        assert np.all(np.sum(n * (q @ A.T), -1) > 0)  # outwards


def test_object_space_normal_degenerate():
    flat = normal_matrix(jnp.diag(jnp.array([1.0, 1.0, 0.0])))  # singular: cofactor
    assert np.all(np.isfinite(flat))
    m = jnp.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 0.0, 0.0]])
    fallback = jnp.array([0.0, 1.0, 0.0])
    out = object_space_normal(m, model_normal_matrix=flat,
                                   fallback=jnp.broadcast_to(fallback, m.shape))
    np.testing.assert_allclose(out, [[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [0.0, 1.0, 0.0]],
                               atol=1e-7)
    g = jax.jit(jax.grad(lambda x: jnp.sum(object_space_normal(
        x, model_normal_matrix=flat))))(m)
    assert np.all(np.isfinite(g))
    g = jax.jit(jax.grad(lambda a: jnp.sum(normal_matrix(a))))(
        jnp.diag(jnp.array([1.0, 1.0, 0.0])))
    assert np.all(np.isfinite(g))
