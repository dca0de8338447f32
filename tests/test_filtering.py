"""jaxnm.filtering: renormalised and shortened mip chains, Toksvig's factor on analytic cases
(a single normal, two normals at a known angle, the lobe's integral), LEAN's moments and
lobe against the slopes' sample statistics and a Monte Carlo average, finite gradients."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxnm.filtering import (
    blinn_phong_lobe,
    lean_moments,
    lean_specular,
    normal_mipmaps,
    toksvig_factor,
    toksvig_specular,
)
from jaxnm.textures import build_mipmaps


def _tilted(theta, phi=0.0):
    return np.array([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)])


def _bumpy(n=16, seed=0):
    rng = np.random.default_rng(seed)
    v = rng.normal(size=(n, n, 3)) * [0.3, 0.3, 0.0] + [0, 0, 1]
    return (v / np.linalg.norm(v, axis=-1, keepdims=True)).astype(np.float32)


def test_renormalised_levels_are_unit_and_shortened_ones_are_the_average():
    tex = _bumpy()
    ren = normal_mipmaps(tex, mode="renormalize")
    short = normal_mipmaps(tex, mode="shortened")
    assert len(ren) == len(short) == 5
    for k in range(1, 5):
        np.testing.assert_allclose(np.linalg.norm(ren[k], axis=-1), 1.0, atol=1e-6)
        assert np.linalg.norm(short[k], axis=-1).max() < 1.0
    # the shortened chain is the plain box average: its last level is the map's mean
    np.testing.assert_allclose(short[-1][0, 0], tex.reshape(-1, 3).mean(0), atol=1e-6)
    np.testing.assert_array_equal(ren[0], tex)
    with pytest.raises(ValueError, match="unknown mode='cry'"):
        normal_mipmaps(tex, mode="cry")


@pytest.mark.parametrize("s", [1.0, 16.0, 256.0])
def test_toksvig_factor_of_a_single_normal_is_one(s):
    n = _tilted(0.4, 1.0)
    tol = 1e-6 + 2e-7 * s  # float32: a unit vector's length is 1 to an ulp or two
    assert float(toksvig_factor(n, s)) == pytest.approx(1.0, abs=tol)
    # a constant map's mips stay unit: no gloss lost at any level
    flat = np.broadcast_to(n.astype(np.float32), (8, 8, 3))
    for level in normal_mipmaps(flat, mode="shortened"):
        np.testing.assert_allclose(toksvig_factor(level, s), 1.0, atol=tol)


@pytest.mark.parametrize("angle_deg", [10.0, 40.0, 90.0])
def test_toksvig_factor_of_two_normals_at_a_known_angle(angle_deg):
    """The average of two unit normals at angle a has length cos(a / 2); a 2x2 texel
    block of them filters to that average."""
    a = np.radians(angle_deg)
    n1, n2 = _tilted(a / 2, 0.3), _tilted(-a / 2, 0.3)
    tex = np.array([[n1, n2], [n2, n1]], np.float32)
    avg = np.asarray(normal_mipmaps(tex, mode="shortened")[1])[0, 0]
    length = np.cos(a / 2)
    assert np.linalg.norm(avg) == pytest.approx(length, rel=1e-6)
    s = 32.0
    want = length / (length + s * (1 - length))
    assert float(toksvig_factor(avg, s)) == pytest.approx(want, rel=1e-5)
    # and the shortened normal's direction is the bisector
    np.testing.assert_allclose(avg / np.linalg.norm(avg), _tilted(0.0), atol=1e-6)


def test_toksvig_keeps_the_lobe_integral():
    """(1 + s') / (1 + s) is the ratio of the integrals of cos^s over the hemisphere."""
    mu = np.linspace(0, 1, 200001)
    for s, ft in ((16.0, 0.5), (64.0, 0.1), (8.0, 1.0)):
        integral = lambda p: 2 * np.pi * np.trapezoid(mu**p, mu)  # noqa: E731
        ratio = integral(ft * s) / integral(s)
        assert (1 + ft * s) / (1 + s) == pytest.approx(1 / ratio, rel=1e-4)
    # a shortened normal: toksvig_specular is that scale times the lower-exponent lobe
    n_avg = 0.9 * _tilted(0.2)
    h = _tilted(0.25)
    ft = float(toksvig_factor(n_avg, 64.0))
    want = (1 + 64 * ft) / 65 * np.dot(_tilted(0.2), h) ** (64 * ft)
    assert float(toksvig_specular(n_avg, h, 64.0)) == pytest.approx(want, rel=1e-5)


def test_lean_moments_give_the_slopes_mean_and_covariance():
    tex = _bumpy(16, seed=3).astype(np.float64)
    with jax.enable_x64(True):
        chain = build_mipmaps(lean_moments(tex))
    b = tex[..., :2] / tex[..., 2:]
    m = np.asarray(chain[-1])[0, 0]
    np.testing.assert_allclose(m[:2], b.reshape(-1, 2).mean(0), atol=1e-12)
    cov = np.cov(b.reshape(-1, 2).T, bias=True)
    np.testing.assert_allclose([m[2] - m[0] ** 2, m[3] - m[1] ** 2, m[4] - m[0] * m[1]],
                               [cov[0, 0], cov[1, 1], cov[0, 1]], atol=1e-12)


def test_lean_lobe_is_the_gaussian_average_of_the_slope_lobe():
    """Monte Carlo: slopes drawn from a Gaussian, exp(-s/2 |h~ - b|^2) averaged, against
    lean_specular of their moments."""
    rng = np.random.default_rng(4)
    mean = np.array([0.05, -0.03])
    cov = np.array([[0.010, 0.004], [0.004, 0.006]])
    b = rng.multivariate_normal(mean, cov, size=400000)
    s = 48.0
    h = _tilted(0.12, 0.7)
    ht = h[:2] / h[2]
    mc = np.mean(np.exp(-0.5 * s * np.sum((ht - b) ** 2, -1)))
    mom = np.array([mean[0], mean[1], cov[0, 0] + mean[0] ** 2, cov[1, 1] + mean[1] ** 2,
                    cov[0, 1] + mean[0] * mean[1]])
    with jax.enable_x64(True):
        got = float(lean_specular(mom, h, s))
    assert got == pytest.approx(mc, rel=5e-3)
    # a single normal (no spread): exp(-s/2 |h~ - b|^2), close to Blinn-Phong near its peak
    n = _tilted(0.1)
    single = float(lean_specular(lean_moments(n), h, s))
    bn = n[:2] / n[2]
    assert single == pytest.approx(np.exp(-0.5 * s * np.sum((ht - bn) ** 2)), rel=1e-5)
    assert single == pytest.approx(float(blinn_phong_lobe(n, h, s)), rel=0.05)


def test_gradients_are_finite_at_degenerate_inputs():
    n = jnp.asarray([[0.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.6, 0.0, 0.8], [1.0, 0.0, 0.0],
                     [0.0, 0.0, -1.0]], jnp.float32)
    h = jnp.asarray([[0.0, 0.0, 1.0]], jnp.float32)

    def loss(n):
        return (jnp.sum(toksvig_specular(n, h, 32.0)) + jnp.sum(toksvig_factor(n, 32.0))
                + jnp.sum(lean_specular(lean_moments(n), h, 32.0))
                + jnp.sum(blinn_phong_lobe(n, h, 0.0)))

    assert np.isfinite(float(loss(n)))
    assert np.isfinite(np.asarray(jax.grad(loss)(n))).all()
    # values: a vanishing average has factor 0; a unit normal along h peaks at 1
    np.testing.assert_allclose(toksvig_factor(n, 32.0)[:2], [0.0, 1.0], atol=1e-6)
    np.testing.assert_allclose(lean_specular(lean_moments(n[1]), h[0], 32.0), 1.0, atol=1e-6)
