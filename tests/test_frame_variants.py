"""The frames engines ship (`gram_schmidt`, `separate`, `cross`, `surface_gradient`) against
float64 closed forms on planes: the uv's gradients and dp/du, dp/dv from the inverse of the
plane's uv matrix, with screen derivatives that are any front-facing pixel footprint."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import compute_frame_kw

from jaxnm import frames as F


def _angle(a, b):
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    return np.degrees(np.arctan2(np.linalg.norm(np.cross(a, b), axis=-1), np.sum(a * b, -1)))


def _unit(v):
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _planes(n=64, mirrored=False, seed=0):
    """Random planes z = 0 with uv = A (x, y): screen derivatives (dp1, dp2) of a
    front-facing footprint (N . dp1 x dp2 > 0, GL's y up), their uv derivatives, and the
    truths: grad u, grad v (rows of A), dp/du, dp/dv (columns of A^-1), the handedness."""
    rng = np.random.default_rng(seed)
    a = rng.normal(size=(n, 2, 2)) + 2 * np.eye(2)
    det = np.linalg.det(a)
    a[det < 0, 0] *= -1  # unmirrored ...
    if mirrored:
        a[:, 0] *= -1  # ... or mirrored in u
    j = rng.normal(size=(n, 2, 2)) + 2 * np.eye(2)
    j[np.linalg.det(j) < 0, :, 1] *= -1  # front-facing: dp1 x dp2 along +z
    dp = np.concatenate([j, np.zeros((n, 1, 2))], 1)  # (n, 3, 2): columns dp1, dp2
    duv = a @ j  # (n, 2, 2): columns duv1, duv2
    inv = np.linalg.inv(a)
    z = np.zeros((n, 1))
    N = np.tile([0.0, 0.0, 1.0], (n, 1))
    grad_u, grad_v = np.concatenate([a[:, 0], z], 1), np.concatenate([a[:, 1], z], 1)
    dpdu, dpdv = np.concatenate([inv[:, :, 0], z], 1), np.concatenate([inv[:, :, 1], z], 1)
    hand = np.sign(np.cross(dpdu, dpdv)[:, 2])
    args = tuple(jnp.asarray(x) for x in (N, dp[:, :, 0], dp[:, :, 1], duv[:, :, 0],
                                           duv[:, :, 1]))
    return args, dict(grad_u=grad_u, grad_v=grad_v, dpdu=dpdu, dpdv=dpdv, hand=hand, N=N)


@pytest.fixture(autouse=True, scope="module")
def _x64():
    with jax.enable_x64(True):
        yield


@pytest.mark.parametrize("mirrored", [False, True])
def test_surface_gradient_frame_is_mikktspace_orthonormal_frame(mirrored):
    args, t = _planes(mirrored=mirrored)
    f = F.surface_gradient_frame(*args)
    T0 = _unit(t["dpdu"])
    B0 = t["hand"][:, None] * np.cross(t["N"], T0)
    assert np.max(_angle(f.T, T0)) < 1e-9 and np.max(_angle(f.B, B0)) < 1e-9
    # resolving the surface gradient N - g, g = -(m.x T + m.y B) / m.z, is perturb_normal
    m = _unit(np.random.default_rng(1).normal(size=(len(T0), 3)) * [1, 1, 0.3] + [0, 0, 1])
    g = -(m[:, :1] * T0 + m[:, 1:2] * B0) / m[:, 2:]
    resolved = _unit(t["N"] - g)
    assert np.max(_angle(F.perturb_normal(f, jnp.asarray(m)), resolved)) < 1e-9


def test_cross_frame_sign_under_gl_y_up():
    """devsh's expression as written, on GL's y-up derivatives, is ``-D_uv dp/du``: for an
    unmirrored uv on a front face it reverses T and B (the map turned by 180 degrees);
    jaxnm's `cross_frame` is the GL-correct sign, and feeding it HLSL's ddy reproduces the
    expression as written."""
    args, t = _planes()
    N, dp1, dp2, duv1, duv2 = (np.asarray(x) for x in args)
    written = duv1[:, 1:] * dp2 - dp1 * duv2[:, 1:]  # dFdx(v) dFdy(p) - dFdx(p) dFdy(v)
    assert np.min(_angle(written, t["dpdu"])) > 179.999
    f = F.cross_frame(*args)
    assert np.max(_angle(f.T, t["dpdu"])) < 1e-9
    assert np.max(_angle(f.B, np.cross(t["N"], t["dpdu"]))) < 1e-9
    hlsl = F.cross_frame(*args, ddy_sign=-1)
    assert np.min(_angle(hlsl.T, t["dpdu"])) > 179.999
    assert np.min(_angle(hlsl.B, np.cross(t["N"], t["dpdu"]))) > 179.999


def test_cross_frame_reverses_t_on_mirrored_uv():
    args, t = _planes(mirrored=True)
    f = F.cross_frame(*args)
    assert np.min(_angle(f.T, t["dpdu"])) > 179.999  # B = N x T has no handedness
    B0 = t["hand"][:, None] * np.cross(t["N"], _unit(t["dpdu"]))
    assert np.max(_angle(f.B, B0)) < 1e-9


@pytest.mark.parametrize("mirrored", [False, True])
def test_gram_schmidt_and_separate_frames(mirrored):
    args, t = _planes(mirrored=mirrored)
    gs = F.gram_schmidt_frame(*args)
    # T along grad u, B along dp/dv (orthogonal to grad u): orthonormal, right-handed by D
    assert np.max(_angle(gs.T, t["grad_u"])) < 1e-9
    assert np.max(_angle(gs.B, t["dpdv"])) < 1e-9
    np.testing.assert_allclose(np.einsum("pi,pi->p", gs.T, gs.B), 0, atol=1e-12)
    sep = F.separate_frame(*args)
    assert np.max(_angle(sep.T, t["grad_u"])) < 1e-9
    assert np.max(_angle(sep.B, t["grad_v"])) < 1e-9
    np.testing.assert_allclose(np.linalg.norm(sep.T, axis=-1), 1, atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(sep.B, axis=-1), 1, atol=1e-12)


def test_compute_frame_dispatches_the_variants_and_degenerate_input_is_finite():
    args, _ = _planes(n=8)
    N, dp1, dp2, duv1, duv2 = args
    from jaxnm.interpolate import Attribute

    kw = dict(N=N, p_attr=Attribute(dp1, dp1, dp2), uv_attr=Attribute(duv1, duv1, duv2))
    for name, fn in (("gram_schmidt", F.gram_schmidt_frame), ("separate", F.separate_frame),
                     ("cross", F.cross_frame), ("surface_gradient", F.surface_gradient_frame)):
        assert name in F.FRAMES and name in F.SCREEN_FRAMES
        a, b = compute_frame_kw(name, **kw), fn(*args)
        np.testing.assert_allclose(np.asarray(a.T), np.asarray(b.T), atol=1e-12)
        zero = fn(N, dp1, dp2, 0 * duv1, 0 * duv2)
        assert not np.any(np.asarray(zero.T)) and np.all(np.isfinite(np.asarray(zero.B)))
    # the uv determinant's guard (a double where): a finite gradient at a zero uv footprint
    g = jax.grad(lambda d: jnp.sum(F.surface_gradient_frame(N, dp1, dp2, d, 0 * duv2).T))(
        0 * duv1)
    assert np.all(np.isfinite(np.asarray(g)))
