"""jaxnm.blend: each detail-blending method against its published formula on hand-worked
cases, reoriented normal mapping's rotation property, the exactness of partial derivatives,
surface gradients and derivative maps against the float64 normal of summed height fields,
and finite gradients."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxnm
from jaxnm.blend import BLEND_METHODS, blend_normal_maps, height_gradient, normal_from_gradient

BASE = np.array([0.6, 0.0, 0.8])
DETAIL = np.array([0.0, 0.6, 0.8])


def _unit(v):
    v = np.asarray(v, np.float64)
    return v / np.linalg.norm(v)


# worked by hand from the listings of Barré-Brisebois & Hill (2012), base (0.6, 0, 0.8),
# detail (0, 0.6, 0.8)
HAND = {
    "linear": _unit([0.6, 0.6, 1.6]),  # n1 + n2
    "udn": _unit([0.6, 0.6, 0.8]),  # (n1.xy + n2.xy, n1.z)
    "whiteout": _unit([0.6, 0.6, 0.64]),  # (n1.xy + n2.xy, n1.z n2.z)
    "partial_derivative": _unit([0.75, 0.75, 1.0]),  # (n1.xy / n1.z + n2.xy / n2.z, 1)
    "surface_gradient": _unit([0.75, 0.75, 1.0]),  # e_z - (grad h1 + grad h2, 0)
    # t = (0.6, 0, 1.8), u = (0, -0.6, 0.8), t.u = 1.44: t * 1.44 / 1.8 - u
    "reoriented": np.array([0.48, 0.6, 0.64]),
}


@pytest.mark.parametrize("method", BLEND_METHODS)
def test_each_method_matches_its_published_formula_on_a_worked_case(method):
    got = np.asarray(blend_normal_maps(BASE, DETAIL, method=method), np.float64)
    np.testing.assert_allclose(got, HAND[method], atol=2e-7)


def test_the_worked_reoriented_case_is_unit_before_normalising():
    t = BASE + [0, 0, 1]
    u = DETAIL * [-1, -1, 1]
    r = t * (t @ u) / t[2] - u
    assert abs(np.linalg.norm(r) - 1) < 1e-12 and np.allclose(r, HAND["reoriented"])


def _random_normals(rng, n, max_tilt_deg):
    theta = np.radians(rng.uniform(0, max_tilt_deg, n))
    phi = rng.uniform(0, 2 * np.pi, n)
    return np.stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi),
                     np.cos(theta)], -1)


def test_reoriented_rotates_the_detail_onto_the_base():
    rng = np.random.default_rng(0)
    n1, n2 = _random_normals(rng, 200, 80), _random_normals(rng, 200, 80)
    with jax.enable_x64(True):
        r = np.asarray(blend_normal_maps(n1, n2, method="reoriented"))
        flat = np.tile([0.0, 0.0, 1.0], (200, 1))
        np.testing.assert_allclose(blend_normal_maps(n1, flat, method="reoriented"), n1,
                                   atol=1e-12)
        np.testing.assert_allclose(blend_normal_maps(flat, n2, method="reoriented"), n2,
                                   atol=1e-12)
    # a rotation taking e_z to n1: the angle to the base is the detail's angle to e_z,
    # and the unnormalised published form is already unit
    np.testing.assert_allclose(np.sum(r * n1, -1), n2[:, 2], atol=1e-12)
    t = n1 + [0, 0, 1]
    u = n2 * [-1, -1, 1]
    pub = t * np.sum(t * u, -1, keepdims=True) / t[:, 2:] - u
    np.testing.assert_allclose(np.linalg.norm(pub, axis=-1), 1.0, atol=1e-12)
    np.testing.assert_allclose(r, pub, atol=1e-12)


def test_a_flat_detail_leaves_the_base_for_the_exact_methods():
    rng = np.random.default_rng(1)
    n1 = _random_normals(rng, 50, 70).astype(np.float32)
    flat = np.tile(np.float32([0, 0, 1]), (50, 1))
    for method in ("reoriented", "partial_derivative", "surface_gradient", "whiteout", "udn"):
        np.testing.assert_allclose(blend_normal_maps(n1, flat, method=method), n1, atol=2e-6)
    # the linear blend halves the tilt instead: not the base
    lin = np.asarray(blend_normal_maps(n1, flat, method="linear"))
    assert np.degrees(np.arccos(np.clip(np.sum(lin * n1, -1), -1, 1))).max() > 10


# ------------------------------------------------------------------ summed height fields


def _heights(x, y):
    """Two height fields with analytic gradients: a broad base and a fine detail."""
    tau = 2 * np.pi
    h1 = 0.08 * np.sin(tau * x) * np.cos(tau * y)
    g1 = np.stack([0.08 * tau * np.cos(tau * x) * np.cos(tau * y),
                   -0.08 * tau * np.sin(tau * x) * np.sin(tau * y)], -1)
    h2 = 0.01 * np.sin(tau * 7 * x + 1.0) * np.sin(tau * 5 * y)
    g2 = np.stack([0.01 * tau * 7 * np.cos(tau * 7 * x + 1.0) * np.sin(tau * 5 * y),
                   0.01 * tau * 5 * np.sin(tau * 7 * x + 1.0) * np.cos(tau * 5 * y)], -1)
    return h1, g1, h2, g2


def _normal(g):
    n = np.concatenate([-g, np.ones_like(g[..., :1])], -1)
    return n / np.linalg.norm(n, axis=-1, keepdims=True)


def _degrees(a, b):
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    return np.degrees(np.arctan2(np.linalg.norm(np.cross(a, b), axis=-1), np.sum(a * b, -1)))


def test_the_height_gradient_round_trips_and_is_the_analytic_one():
    x, y = np.meshgrid(np.linspace(0, 1, 33), np.linspace(0, 1, 33))
    _, g1, _, g2 = _heights(x, y)
    with jax.enable_x64(True):
        n = _normal(g1 + g2)
        np.testing.assert_allclose(height_gradient(n), g1 + g2, atol=1e-12)
        np.testing.assert_allclose(normal_from_gradient(g1 + g2), n, atol=1e-15)
        # a finite-difference check of the fields' analytic gradients themselves
        e = 1e-6
        h = lambda x, y: sum(_heights(x, y)[::2])  # noqa: E731
        fd = np.stack([(h(x + e, y) - h(x - e, y)), (h(x, y + e) - h(x, y - e))], -1) / (2 * e)
        np.testing.assert_allclose(fd, g1 + g2, atol=1e-7)
    # a normal below the tangent plane stands for no height field: zero gradient
    np.testing.assert_array_equal(height_gradient(np.float32([[0.6, 0.0, -0.8]])), [[0, 0]])


def test_partial_derivatives_and_surface_gradients_equal_the_summed_heights():
    """The exact answer for detail added as height; the other methods are measurably off."""
    x, y = np.meshgrid(np.linspace(0, 1, 64), np.linspace(0, 1, 64))
    _, g1, _, g2 = _heights(x, y)
    truth = _normal(g1 + g2)
    errs = {}
    with jax.enable_x64(True):
        for method in BLEND_METHODS:
            errs[method] = _degrees(blend_normal_maps(_normal(g1), _normal(g2), method=method),
                                    truth).max()
        # a derivative map blends by addition: exactly the summed heights' map
        d = np.asarray(height_gradient(_normal(g1))) + np.asarray(height_gradient(_normal(g2)))
        assert _degrees(normal_from_gradient(d), truth).max() < 1e-12
    assert errs["partial_derivative"] < 1e-12 and errs["surface_gradient"] < 1e-12
    assert errs["linear"] > 5 and errs["udn"] > 0.1 and errs["whiteout"] > 0.1
    assert errs["reoriented"] > 0.1
    # float32 (the library's working precision): the exact ones to float rounding
    e32 = _degrees(blend_normal_maps(_normal(g1).astype(np.float32),
                                     _normal(g2).astype(np.float32),
                                     method="partial_derivative"), truth).max()
    assert e32 < 1e-3


def test_derivative_maps_blend_exactly_through_filtering():
    """Filtering is linear, so the mip chain of a summed derivative map is the sum of the
    chains: blending and mip-mapping commute for derivative maps, not for normal maps."""
    n = 32
    c = (np.arange(n) + 0.5) / n
    x, y = np.meshgrid(c, c)
    _, g1, _, g2 = _heights(x, y)
    with jax.enable_x64(True):
        m1 = jaxnm.build_mipmaps(g1)
        m2 = jaxnm.build_mipmaps(g2)
        m12 = jaxnm.build_mipmaps(g1 + g2)
        for a, b, s in zip(m1, m2, m12):
            np.testing.assert_allclose(np.asarray(a) + np.asarray(b), s, atol=1e-15)
        # normals: blending the filtered maps is not filtering the blended map
        n1 = jaxnm.build_mipmaps(_normal(g1), renormalize=True)
        n2 = jaxnm.build_mipmaps(_normal(g2), renormalize=True)
        n12 = jaxnm.build_mipmaps(_normal(g1 + g2), renormalize=True)
        err = _degrees(blend_normal_maps(n1[2], n2[2], method="partial_derivative"), n12[2])
    assert err.max() > 0.1


@pytest.mark.parametrize("method", BLEND_METHODS)
def test_gradients_are_finite_even_at_degenerate_inputs(method):
    rng = np.random.default_rng(2)
    n1 = _random_normals(rng, 20, 89).astype(np.float32)
    n2 = _random_normals(rng, 20, 89).astype(np.float32)
    # degenerate rows: the base pointing down (RNM's t = 0), both in the tangent plane,
    # opposite normals (the linear sum vanishes), zero vectors
    n1[:4] = [[0, 0, -1], [1, 0, 0], [0.6, 0, 0.8], [0, 0, 0]]
    n2[:4] = [[0.3, 0.4, np.sqrt(0.75)], [-1, 0, 0], [-0.6, 0, -0.8], [0, 0, 0]]

    def loss(a, b):
        r = blend_normal_maps(a, b, method=method)
        return jnp.sum(r * jnp.float32([[0.2, -0.3, 0.9]]))

    val = blend_normal_maps(n1, n2, method=method)
    ga, gb = jax.grad(loss, argnums=(0, 1))(jnp.asarray(n1), jnp.asarray(n2))
    assert np.isfinite(np.asarray(val)).all()
    assert np.isfinite(np.asarray(ga)).all() and np.isfinite(np.asarray(gb)).all()
    # and the non-degenerate rows are unit
    np.testing.assert_allclose(np.linalg.norm(np.asarray(val)[4:], axis=-1), 1.0, atol=1e-5)


def test_broadcasting_and_bad_input():
    r = blend_normal_maps(np.tile(BASE, (4, 5, 1)), DETAIL, method="whiteout")
    assert r.shape == (4, 5, 3)
    with pytest.raises(ValueError, match="unknown method='rnm'"):
        blend_normal_maps(BASE, DETAIL, method="rnm")
    with pytest.raises(ValueError, match=r"`detail` must have shape \(\.\.\., 3\)"):
        blend_normal_maps(BASE, DETAIL[:2])
    assert jaxnm.blend_normal_maps is blend_normal_maps
