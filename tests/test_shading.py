"""Tests for jaxnm.shading: analytic values, invariants, batching, gradients, display encoding."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.test_util import check_grads

from jaxnm import shading
from jaxnm.shading import (
    SHADING_MODELS,
    DirectionalLight,
    Lights,
    Material,
    PointLight,
    stack_lights,
)

# jitted once per signature: eager dispatch compiles every primitive for every new shape
shade = jax.jit(shading.shade, static_argnums=0)
lambert = jax.jit(shading.lambert)
blinn_phong = jax.jit(shading.blinn_phong)
phong = jax.jit(shading.phong)
to_display = jax.jit(shading.to_display)

# --------------------------------------------------------------------------------------
# helpers
# --------------------------------------------------------------------------------------


def _unit(v):
    v = np.asarray(v, np.float64)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _rotation(rng):
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    if np.linalg.det(q) < 0:
        q[:, 0] = -q[:, 0]
    return q


def _material(diffuse=(0.6, 0.5, 0.4), specular=(0.3, 0.35, 0.4), shininess=12.0,
              ambient=(0.05, 0.04, 0.03)):
    return Material(jnp.asarray(diffuse), jnp.asarray(specular), jnp.asarray(shininess),
                    jnp.asarray(ambient))


def _dir_light(direction, color=(1.0, 0.9, 0.8), intensity=1.5):
    return DirectionalLight(jnp.asarray(direction), jnp.asarray(color), jnp.asarray(intensity))


def _point_light(position, color=(0.9, 1.0, 0.7), intensity=3.0, falloff="inverse_square"):
    return PointLight(jnp.asarray(position), jnp.asarray(color), jnp.asarray(intensity), falloff)


def _reference(model, N, p, eye, lights, mat, albedo=None):
    """Independent float64 NumPy implementation of the documented formulas."""
    N, p, eye = (np.asarray(x, np.float64) for x in (N, p, eye))
    a = np.ones_like(N) if albedo is None else np.asarray(albedo, np.float64)
    kd, ks, ka = (np.asarray(x, np.float64) for x in (mat.diffuse, mat.specular, mat.ambient))
    n = float(mat.shininess)
    V = _unit(eye - p)
    out = ka * a
    for light in lights:
        color = np.asarray(light.color, np.float64) * float(light.intensity)
        if isinstance(light, DirectionalLight):
            L = np.broadcast_to(_unit(light.direction), N.shape)
            E = np.broadcast_to(color, N.shape)
        else:
            d = np.asarray(light.position, np.float64) - p
            d2 = np.sum(d * d, -1, keepdims=True)
            L = d / np.sqrt(d2)
            E = color / d2 if light.falloff == "inverse_square" else color + 0 * d
        ndl = np.sum(N * L, -1, keepdims=True)
        out = out + kd * a * E * np.maximum(ndl, 0.0)
        if model == "lambert":
            continue
        if model == "blinn_phong":
            x = np.sum(N * _unit(L + V), -1, keepdims=True)
        else:
            R = -L - 2.0 * np.sum(N * -L, -1, keepdims=True) * N  # GLSL reflect(-L, N)
            x = np.sum(R * V, -1, keepdims=True)
        out = out + np.where(ndl > 0, ks * E * np.maximum(x, 0.0) ** n, 0.0)
    return out


def _random_scene(rng, shape=(5, 7)):
    """Per-pixel unit normals in the upper hemisphere of z and positions near the origin."""
    N = _unit(rng.normal(size=shape + (3,)) * [0.4, 0.4, 1.0] + [0.0, 0.0, 1.0])
    p = rng.uniform(-0.5, 0.5, size=shape + (3,)) * [1.0, 1.0, 0.1]
    eye = np.array([0.3, -0.2, 4.0])
    return N, p, eye


# --------------------------------------------------------------------------------------
# analytic values
# --------------------------------------------------------------------------------------


@pytest.mark.parametrize("model", SHADING_MODELS)
def test_lambert_cosine_law(model):
    mat = _material(specular=(0.0, 0.0, 0.0))
    N = jnp.array([0.0, 0.0, 1.0])
    for theta in (0.0, 0.3, 1.0, 1.5):
        direction = 3.0 * np.array([np.sin(theta), 0.0, np.cos(theta)])  # length is ignored
        light = _dir_light(direction)
        out = shade(model, N, jnp.zeros(3), jnp.array([0.0, 1.0, 5.0]), light, mat)
        expected = (np.asarray(mat.diffuse) * np.asarray(light.color) * 1.5 * np.cos(theta)
                    + np.asarray(mat.ambient))
        np.testing.assert_allclose(out, expected, rtol=1e-6, atol=1e-7)
    # below the horizon: ambient only
    out = shade(model, N, jnp.zeros(3), jnp.array([0.0, 0.0, 5.0]),
                _dir_light([0.0, 1.0, -0.2]), _material())
    np.testing.assert_allclose(out, np.asarray(_material().ambient), rtol=1e-6)


@pytest.mark.parametrize("fn", [blinn_phong, phong])
def test_specular_at_mirror_configuration(fn):
    """L and V mirrored about N: N.H = 1 and R.V = 1, so the lobe is ks * color * intensity."""
    mat = _material(diffuse=(0.0, 0.0, 0.0), ambient=(0.0, 0.0, 0.0), shininess=37.0)
    N = _unit([0.2, -0.3, 1.0])
    L = _unit([0.7, 0.1, 0.5])
    V = 2.0 * np.dot(N, L) * N - L
    p = np.array([0.1, 0.2, -0.3])
    light = _dir_light(L, color=(0.5, 1.0, 2.0), intensity=1.25)
    out = fn(jnp.asarray(N), jnp.asarray(p), jnp.asarray(p + 6.0 * V), light, mat)
    np.testing.assert_allclose(out, np.asarray(mat.specular) * [0.5, 1.0, 2.0] * 1.25, rtol=2e-5)


def test_specular_gated_by_lambert_term():
    """The GLSL Hacker demo's `if (lambertTerm > 0.0)` switches the highlight off."""
    mat = _material(shininess=1.0)
    N = jnp.array([0.0, 0.0, 1.0])
    L = _unit([1.0, 0.0, -0.05])  # just below the horizon
    eye = jnp.array([-5.0, 0.0, 1.0])  # N.H > 0 and R.V > 0 here
    H = _unit(L + _unit(np.asarray(eye)))
    assert H[2] > 0.05
    for fn in (blinn_phong, phong):
        out = fn(N, jnp.zeros(3), eye, _dir_light(L), mat)
        np.testing.assert_allclose(out, np.asarray(mat.ambient), rtol=1e-6)


@pytest.mark.parametrize("model", SHADING_MODELS)
def test_point_light_inverse_square(model):
    mat = _material()
    N = jnp.array([0.0, 0.0, 1.0])
    eye = jnp.array([0.0, 0.0, 20.0])
    ka = np.asarray(mat.ambient)
    direct = []
    for d in (0.5, 1.0, 2.0, 4.0):
        out = shade(model, N, jnp.zeros(3), eye, _point_light([0.0, 0.0, d]), mat)
        direct.append(np.asarray(out) - ka)
    for d, value in zip((0.5, 1.0, 2.0, 4.0), direct):
        np.testing.assert_allclose(value * d * d, direct[1], rtol=1e-5)
    # no falloff: constant
    outs = [shade(model, N, jnp.zeros(3), eye, _point_light([0.0, 0.0, d], falloff="none"), mat)
            for d in (0.5, 3.0)]
    np.testing.assert_allclose(outs[0], outs[1], rtol=1e-6)


@pytest.mark.parametrize("model", SHADING_MODELS)
def test_matches_numpy_reference(model):
    rng = np.random.default_rng(0)
    N, p, eye = _random_scene(rng)
    albedo = rng.uniform(0.2, 1.0, size=N.shape)
    lights = [_dir_light([0.3, 0.4, 1.0]), _dir_light([-0.8, 0.1, 0.3], color=(0.2, 0.3, 1.0)),
              _point_light([0.5, -0.4, 1.5]), _point_light([-1.0, 0.2, 0.8], falloff="none")]
    mat = _material()
    out = shade(model, jnp.asarray(N, jnp.float32), jnp.asarray(p, jnp.float32), eye, lights,
                mat, albedo=jnp.asarray(albedo, jnp.float32))
    assert out.shape == N.shape and out.dtype == jnp.float32
    ref = _reference(model, N, p, eye, lights, mat, albedo)
    np.testing.assert_allclose(out, ref, rtol=2e-5, atol=1e-6)


def test_albedo_scales_diffuse_and_ambient_not_specular():
    rng = np.random.default_rng(1)
    N, p, eye = _random_scene(rng, (4,))
    light = _dir_light([0.2, 0.1, 1.0])
    mat = _material()
    spec = blinn_phong(N, p, eye, light, mat) - lambert(N, p, eye, light, mat)
    albedo = np.array([0.5, 0.25, 2.0])
    spec_a = (blinn_phong(N, p, eye, light, mat, albedo=albedo)
              - lambert(N, p, eye, light, mat, albedo=albedo))
    np.testing.assert_allclose(spec_a, spec, rtol=1e-5, atol=1e-7)
    np.testing.assert_allclose(lambert(N, p, eye, light, mat, albedo=albedo),
                               lambert(N, p, eye, light, mat) * albedo[None], rtol=1e-6)


def test_safe_pow():
    f = shading._pos_pow
    x = jnp.array([-0.5, 0.0, 1e-35, 0.25, 1.0])
    np.testing.assert_allclose(f(x, jnp.asarray(0.0)), [1.0, 1.0, 1.0, 1.0, 1.0])
    np.testing.assert_allclose(f(x, jnp.asarray(3.0)), [0.0, 0.0, 0.0, 0.25**3, 1.0], rtol=1e-6)
    for n in (0.0, 0.5, 1.0, 8.0):
        gx, gn = jax.vmap(jax.grad(f, argnums=(0, 1)), in_axes=(0, None))(x, jnp.asarray(n))
        assert np.all(np.isfinite(gx)) and np.all(np.isfinite(gn))
        np.testing.assert_allclose(gn[3], np.log(0.25) * 0.25**n, rtol=1e-5)


# --------------------------------------------------------------------------------------
# invariants
# --------------------------------------------------------------------------------------


@pytest.mark.parametrize("model", SHADING_MODELS)
def test_rigid_motion_invariance(model):
    """Rotating (and translating) N, p, the eye and the lights together changes nothing."""
    rng = np.random.default_rng(2)
    N, p, eye = _random_scene(rng, (6,))
    mat = _material()
    d, q = np.array([0.3, -0.5, 1.0]), np.array([0.4, 0.3, 1.2])
    base = shade(model, N, p, eye, [_dir_light(d), _point_light(q)], mat)
    for _ in range(3):
        R, t = _rotation(rng), rng.normal(size=3)
        moved = shade(model, N @ R.T, p @ R.T + t, R @ eye + t,
                      [_dir_light(R @ d), _point_light(R @ q + t)], mat)
        np.testing.assert_allclose(moved, base, rtol=1e-4, atol=1e-6)


# --------------------------------------------------------------------------------------
# batching
# --------------------------------------------------------------------------------------


def test_stacked_lights_equal_sum_of_single_lights():
    # the light loop is model-independent; phong exercises the most code
    model = "phong"
    rng = np.random.default_rng(3)
    N, p, eye = _random_scene(rng, (4, 6))
    mat = _material(ambient=(0.0, 0.0, 0.0))
    dirs = [_dir_light(rng.normal(size=3) + [0, 0, 1.5], color=rng.uniform(size=3),
                       intensity=rng.uniform(0.5, 2.0)) for _ in range(4)]
    points = [_point_light(rng.normal(size=3) + [0, 0, 2.0], intensity=rng.uniform(1.0, 3.0))
              for _ in range(3)]
    singles = sum(shade(model, N, p, eye, light, mat) for light in dirs + points)
    stacked_dir, stacked_pt = stack_lights(dirs), stack_lights(points)
    assert stacked_dir.direction.shape == (4, 3) and stacked_dir.intensity.shape == (4,)
    for lights in (Lights(stacked_dir, stacked_pt), [Lights(directional=stacked_dir), stacked_pt],
                   dirs + points):
        np.testing.assert_allclose(shade(model, N, p, eye, lights, mat), singles, rtol=1e-5,
                                   atol=1e-6)
    # a (2, 2) stack of directional lights is summed over both axes
    grid = jax.tree_util.tree_map(lambda x: x.reshape((2, 2) + x.shape[1:]), stacked_dir)
    np.testing.assert_allclose(shade(model, N, p, eye, grid, mat),
                               shade(model, N, p, eye, stacked_dir, mat), rtol=1e-6, atol=1e-7)
    # vmap over the stack renders one image per light
    per_light = jax.vmap(lambda light: shade(model, N, p, eye, light, mat))(stacked_dir)
    assert per_light.shape == (4,) + N.shape
    for i, light in enumerate(dirs):
        np.testing.assert_allclose(per_light[i], shade(model, N, p, eye, light, mat), rtol=1e-6,
                                   atol=1e-7)


def test_batch_shapes_and_jit():
    rng = np.random.default_rng(4)
    N, p, eye = _random_scene(rng, (2, 3, 4))
    mat, light = _material(), _dir_light([0.1, 0.2, 1.0])
    out = shading.shade("phong", N, p, eye, light, mat)  # eager
    np.testing.assert_allclose(out, shade("phong", N, p, eye, light, mat), rtol=1e-5)
    assert out.shape == (2, 3, 4, 3)
    np.testing.assert_allclose(out[1, 2], shade("phong", N[1, 2], p[1, 2], eye, light, mat),
                               rtol=1e-6)
    # a single position broadcasts against per-pixel normals
    assert shade("lambert", N, p[0, 0, 0], eye, light, mat).shape == (2, 3, 4, 3)
    # a single pixel
    assert shade("blinn_phong", N[0, 0, 0], p[0, 0, 0], eye, light, mat).shape == (3,)


def test_errors():
    mat, light = _material(), _dir_light([0.0, 0.0, 1.0])
    with pytest.raises(ValueError, match="unknown shading model"):
        shading.shade("cook_torrance", jnp.zeros(3), jnp.zeros(3), jnp.ones(3), light, mat)
    with pytest.raises(ValueError, match="one type"):
        stack_lights([light, _point_light([0.0, 0.0, 1.0])])
    with pytest.raises(ValueError, match="falloff"):
        shading.shade("lambert", jnp.zeros(3), jnp.zeros(3), jnp.ones(3),
              _point_light([0.0, 0.0, 1.0], falloff="linear"), mat)
    with pytest.raises(TypeError):
        shading.shade("lambert", jnp.zeros(3), jnp.zeros(3), jnp.ones(3), {"sun": light}, mat)


# --------------------------------------------------------------------------------------
# gradients
# --------------------------------------------------------------------------------------


def _scene_fn(f_albedo=True):
    """f(params) -> (3,): a weighted sum of the shaded image per model (SHADING_MODELS order).

    All models in one function, so that each gradient test compiles once.
    """

    def f(N, p, eye, direction, position, color, intensity, kd, ks, n, ka):
        lights = [DirectionalLight(direction, color, intensity),
                  PointLight(position, color[::-1], intensity)]
        mat = Material(kd, ks, n, ka)
        a = jnp.linspace(0.5, 1.0, N.size, dtype=N.dtype).reshape(N.shape) if f_albedo else None
        outs = []
        for model in SHADING_MODELS:
            out = shading.shade(model, N, p, eye, lights, mat, albedo=a)
            w = jnp.linspace(0.3, 1.7, out.size, dtype=out.dtype).reshape(out.shape)
            outs.append(jnp.sum(w * out))
        return jnp.stack(outs)

    return f


def _generic_args(rng):
    N, p, eye = _random_scene(rng, (3,))
    return [jnp.asarray(x) for x in (
        N, p, eye, [0.3, 0.2, 1.0], [0.2, -0.1, 1.5], [0.9, 0.8, 0.7], 1.3,
        [0.6, 0.5, 0.4], [0.3, 0.35, 0.4], 7.5, [0.05, 0.04, 0.03])]


def test_check_grads_generic():
    """Gradients w.r.t. N, p, eye, light direction/position, colour, intensity and material."""
    with jax.enable_x64(True):
        rng = np.random.default_rng(5)
        args = _generic_args(rng)
        assert args[0].dtype == jnp.float64
        f = jax.jit(_scene_fn())
        values = f(*args)
        assert np.all(values > 0.1)  # generic: lit, with highlights, away from the kinks
        check_grads(f, args, order=1, modes=("fwd", "rev"), atol=1e-6, rtol=1e-6)


def test_gradients_finite_at_edge_cases():
    f = _scene_fn()
    jac_fn = jax.jit(jax.jacrev(f, argnums=tuple(range(11))))
    jvp_fn = jax.jit(lambda args: jax.jvp(f, args, [jnp.ones_like(a) for a in args]))
    n_up = jnp.array([[0.0, 0.0, 1.0]])
    base = dict(N=n_up, p=jnp.zeros((1, 3)), eye=jnp.array([0.0, 0.0, 3.0]),
                direction=jnp.array([0.3, 0.0, 1.0]), position=jnp.array([0.0, 0.5, 2.0]),
                color=jnp.array([1.0, 0.9, 0.8]), intensity=jnp.asarray(1.0),
                kd=jnp.array([0.5, 0.5, 0.5]), ks=jnp.array([0.3, 0.3, 0.3]),
                n=jnp.asarray(8.0), ka=jnp.array([0.1, 0.1, 0.1]))
    cases = {
        "generic": {},
        "terminator N.L = 0": dict(direction=jnp.array([1.0, 0.0, 0.0]),
                                   position=jnp.array([0.0, 2.0, 0.0])),
        "zero normal": dict(N=jnp.zeros((1, 3))),
        "zero light direction": dict(direction=jnp.zeros(3)),
        "shininess 0": dict(n=jnp.asarray(0.0)),
        "shininess 0.5": dict(n=jnp.asarray(0.5)),
        # N = x, L ~ (1, 0, 1), V ~ (-1, 0, 1): H = z is perpendicular to N while N . L > 0
        "N.H = 0": dict(N=jnp.array([[1.0, 0.0, 0.0]]), direction=jnp.array([1.0, 0.0, 1.0]),
                        eye=jnp.array([-3.0, 0.0, 3.0])),
        "H = 0 (L = -V)": dict(direction=jnp.array([0.0, 0.0, -1.0]),
                               eye=jnp.array([0.0, 0.0, 3.0])),
        "R.V = 0": dict(direction=jnp.array([0.0, 0.0, 1.0]), eye=jnp.array([3.0, 0.0, 0.0])),
        "point light on the surface": dict(position=jnp.zeros(3)),
        "eye on the surface": dict(eye=jnp.zeros(3)),
    }
    for name, change in cases.items():
        args = list(dict(base, **change).values())
        value, tangent = jvp_fn(args)
        assert np.all(np.isfinite(value)) and np.all(np.isfinite(tangent)), (name, tangent)
        for i, jac in enumerate(jac_fn(*args)):  # (models, *arg.shape)
            for model, g in zip(SHADING_MODELS, jac):
                assert np.all(np.isfinite(g)), f"{model}, case {name!r}, argument {i}: {g}"


# --------------------------------------------------------------------------------------
# display
# --------------------------------------------------------------------------------------


def _srgb_reference(x):
    x = np.clip(np.asarray(x, np.float64), 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * x ** (1 / 2.4) - 0.055)


def test_to_display_values():
    x = np.array([-1.0, 0.0, 0.001, 0.0031308, 0.01, 0.18, 0.5, 0.9, 1.0, 7.0])
    np.testing.assert_allclose(to_display(jnp.asarray(x, jnp.float32)), _srgb_reference(x),
                               atol=2e-7)
    np.testing.assert_allclose(to_display(jnp.float32(0.18)), 0.46135612950044164, rtol=1e-6)
    np.testing.assert_allclose(to_display(jnp.float32(0.0031308)), 0.04045, rtol=1e-4)
    np.testing.assert_allclose(to_display(jnp.float32(0.25), exposure=2.0),
                               to_display(jnp.float32(0.5)))
    out = to_display(jnp.asarray(np.linspace(-0.5, 2.0, 1001), jnp.float32))
    assert float(out.min()) == 0.0 and float(out.max()) <= 1.0
    assert np.all(np.diff(np.asarray(out)) >= 0.0)
    assert to_display(jnp.ones((4, 5, 3))).shape == (4, 5, 3)


def test_to_display_gradient_finite():
    x = jnp.array([-1.0, 0.0, 1e-12, 0.0031308, 0.5, 1.0, 2.0])
    g = jax.vmap(jax.grad(lambda v: to_display(v)))(x)
    assert np.all(np.isfinite(g))
    np.testing.assert_allclose(g[1], 12.92)
    assert g[0] == 0.0 and g[-1] == 0.0
