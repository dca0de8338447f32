"""`jax.grad` through the top-level `render(scene)`: the scene is a pytree whose arrays may be
traced. Each gradient is checked against central finite differences of the same function.

Visibility is piecewise constant (a pixel's triangle changes only when an edge crosses its
centre), so the derivative `render` returns is that of the shading with the visibility held
fixed. Perturbing vertex positions or the camera moves edges; the finite differences are
therefore taken over the pixels whose triangle is the same in the base and both perturbed
renders, where the function is smooth.
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.flatten_util import ravel_pytree

import jaxnm
from jaxnm import procedural
from jaxnm.render import render
from jaxnm.scene import Scene, validate_scene
from jaxnm.shading import DirectionalLight, Lights, Material, PointLight, stack_lights

SIZE = 32


@pytest.fixture(scope="module")
def scene() -> Scene:
    """A 32x32 torus patch with a normal map, an albedo texture and two kinds of light."""
    rng = np.random.default_rng(0)
    cam = jaxnm.Camera.look_at((0.0, -2.35, 1.75), (0.0, 0.0, -0.1), (0.0, 0.0, 1.0),
                               fov_y_deg=40.0)
    # (every array strongly typed float32, as the finite differences' arrays are, which
    # `ravel_pytree` gives back: a weakly typed scalar would compile each render again)
    f32 = functools.partial(jnp.asarray, dtype=jnp.float32)
    lights = Lights(
        directional=stack_lights([DirectionalLight(f32([-0.6, -0.5, 0.8]), f32([1.0, 0.9, 0.8]),
                                                   f32(0.9))]),
        point=stack_lights([PointLight(f32([1.8, -1.6, 1.4]), f32([0.5, 0.7, 1.0]),
                                       f32(4.0))]))
    albedo = rng.uniform(0.3, 0.9, (16, 16, 3)).astype(np.float32)
    return Scene(mesh=procedural.torus(1.0, 0.42, 24, 12, uv_scale=(3.0, 1.0)), camera=cam,
                 width=SIZE, height=SIZE, normal_map=procedural.default_normal_map_texels(32),
                 albedo=albedo, lights=lights,
                 material=Material(f32([1.0] * 3), f32([0.3] * 3), f32(16.0), f32([0.02] * 3)),
                 source="<grad test>").replace()


def _weights() -> jax.Array:
    rng = np.random.default_rng(1)
    return jnp.asarray(rng.uniform(0.5, 1.5, (SIZE, SIZE, 3)), jnp.float32)


def _field(name):
    """(get, set) of a scene field, or of the mesh positions for ``"positions"``."""
    if name == "positions":
        return (lambda s: s.mesh.positions,
                lambda s, x: dataclasses.replace(s, mesh=dataclasses.replace(s.mesh, positions=x)))
    return (lambda s: getattr(s, name), lambda s, x: dataclasses.replace(s, **{name: x}))


#: The fields the tests differentiate. Each test takes the gradient with respect to all of
#: them and checks its own field's part: one differentiated program for the whole module
#: instead of one per field (the part is the partial derivative all the same).
FIELDS = ("normal_map", "albedo", "lights", "material", "positions", "camera")


def _grad_of_every_field(scene, keep, w):
    """The gradient of ``sum(w * color)`` over ``keep`` with respect to every field in
    `FIELDS`, as a dict."""

    def loss(values):
        s = scene
        for name, x in values.items():
            s = _field(name)[1](s, x)
        color = render(s, outputs=("color",))["color"]
        return jnp.sum(jnp.where(keep, w * color, 0.0))

    return jax.grad(loss)({name: _field(name)[0](scene) for name in FIELDS})


_OUTPUTS = ("color", "triangle_id")


def _directional_check(scene, field: str, *, eps: float, moves_edges: bool, rtol: float,
                       seed: int = 0, scale=None):
    """Compare ``grad(L) . d`` with central differences of ``L`` along a random ``d``, where
    ``L(x) = sum(w * color)`` over the pixels whose triangle does not change. The gradient
    is ``field``'s part of the gradient with respect to every field (`FIELDS`)."""
    get, put = _field(field)
    flat0, unravel = ravel_pytree(get(scene))
    rng = np.random.default_rng(seed)
    d = rng.normal(size=flat0.shape).astype(np.float32)
    if scale is not None:
        d = d * np.asarray(ravel_pytree(scale)[0])
    d = jnp.asarray(d / np.linalg.norm(d))
    w = _weights()

    def with_flat(flat):
        return put(scene, unravel(flat))

    # (the ids and the colours from one program)
    def tri(flat):
        return np.asarray(render(with_flat(flat), outputs=_OUTPUTS)["triangle_id"])

    keep = np.ones((SIZE, SIZE, 1), bool)
    if moves_edges:
        base = tri(flat0)
        keep = (tri(flat0 + eps * d) == base) & (tri(flat0 - eps * d) == base) & (base >= 0)
        assert keep.mean() > 0.3, "too many pixels change triangle; use a smaller eps"
    keep = jnp.asarray(keep)

    def loss64(flat):  # the same sum in float64 on the host: no float32 cancellation in the FD
        color = np.asarray(render(with_flat(flat), outputs=_OUTPUTS)["color"], np.float64)
        return float(np.sum(np.where(np.asarray(keep), np.asarray(w, np.float64) * color, 0.0)))

    g = ravel_pytree(_grad_of_every_field(scene, keep, w)[field])[0]
    assert np.all(np.isfinite(np.asarray(g))), f"non-finite gradient w.r.t. {field}"
    assert keep.any()
    assert np.any(np.asarray(g) != 0), f"zero gradient w.r.t. {field}"
    fd = (loss64(flat0 + eps * d) - loss64(flat0 - eps * d)) / (2 * eps)
    ad = float(jnp.vdot(g, d))
    np.testing.assert_allclose(ad, fd, rtol=rtol, atol=1e-3 * abs(fd) + 1e-4,
                               err_msg=f"d/d {field}")
    return g


def test_grad_wrt_normal_map(scene):
    _directional_check(scene, "normal_map", eps=1e-2, moves_edges=False, rtol=2e-3)


def test_grad_wrt_albedo_texture(scene):
    _directional_check(scene, "albedo", eps=1e-2, moves_edges=False, rtol=2e-3)


def test_grad_wrt_lights(scene):
    _directional_check(scene, "lights", eps=1e-2, moves_edges=False, rtol=2e-3)


def test_grad_wrt_material(scene):
    _directional_check(scene, "material", eps=1e-2, moves_edges=False, rtol=2e-3)


def test_grad_wrt_vertex_positions(scene):
    # 0.4 % apart as measured: pixels whose texel, mip level or frame normalisation switches
    # between the perturbed renders contribute kinks that central differences average
    _directional_check(scene, "positions", eps=2e-4, moves_edges=True, rtol=2e-2)


def test_grad_wrt_camera(scene):
    # move the eye and turn the view; the projection's focal lengths change too
    scale = jaxnm.Camera(view=jnp.full((4, 4), 0.1).at[3].set(0.0),
                         projection=jnp.zeros((4, 4)).at[0, 0].set(1.0).at[1, 1].set(1.0),
                         eye=jnp.ones(3))
    _directional_check(scene, "camera", eps=3e-4, moves_edges=True, rtol=2e-2, scale=scale)


def test_grad_under_jit_and_of_every_output_is_finite(scene):
    """`render` traces: jit of a loss of every floating output, gradient w.r.t. the map."""
    outputs = ("color", "perturbed_normal", "tangent", "bitangent", "normal", "position",
               "dpdx", "duvdy")

    @jax.jit
    def loss(nm):
        out = render(scene.replace(normal_map=nm), outputs=outputs)
        return sum(jnp.sum(v) for v in out.values())

    g = jax.grad(loss)(jnp.asarray(scene.normal_map))
    assert np.isfinite(np.asarray(g)).all() and np.any(np.asarray(g) != 0)


def test_validation_never_converts_a_tracer(scene):
    """`validate_scene`'s shape checks run on traced arrays; value checks wait for concrete
    ones."""
    with pytest.raises(ValueError, match="normal map must have shape"):
        jax.grad(lambda nm: jnp.sum(render(validate_scene(scene.replace(normal_map=nm)))[
            "color"]))(jnp.zeros((8, 8, 2)))
    bad = np.array(scene.mesh.positions)
    bad[0, 0] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        validate_scene(scene.replace(mesh=dataclasses.replace(scene.mesh,
                                                              positions=jnp.asarray(bad))))


def test_a_packed_frames_gradient_keeps_one_copy_of_the_inputs():
    """Differentiated, a packed frame's loop over passes of covered pixels (`render` on the
    CPU from 256x256 up) keeps the normal map and the mesh once: no loop of the traced
    gradient stacks a copy of them per pass (writing a map-sized buffer every pass, and
    more memory than the threshold where the C library reuses freed memory)."""
    from jax._src import core

    scene = procedural.default_scene(width=256, height=256)
    texels = jnp.asarray(scene.normal_map)
    positions = jnp.asarray(scene.mesh.positions)

    def loss(t, p):
        sc = scene.replace(normal_map=t, mesh=dataclasses.replace(scene.mesh, positions=p))
        return jnp.mean(render(sc)["color"] ** 2)

    jaxpr = jax.make_jaxpr(jax.grad(loss, argnums=(0, 1)))(texels, positions)
    loops = []

    def walk(j):
        for e in j.eqns:
            if e.primitive.name == "scan":
                loops.append((e.params["length"], [v.aval.shape for v in e.outvars]))
            for sub in core.jaxprs_in_params(e.params):
                walk(sub)

    walk(jaxpr.jaxpr)
    assert any(n > 1 for n, _ in loops)  # the passes' loop is there (else this tests nothing)
    inputs = {tuple(jnp.shape(x)) for x in (texels, positions, scene.mesh.uv,
                                            scene.mesh.normals)}
    stacked = [(n, s) for n, shapes in loops for s in shapes if len(s) > 1 and s[1:] in inputs]
    assert not stacked, stacked
