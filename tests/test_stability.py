"""Hard cases: the renderer stays accurate and finite where float32 usually gives up.

Far from the origin: a scene's model matrix and camera are composed in float64 and the
scene is rendered camera-relative (`jaxnm.render.render`), so a mesh a million
units out renders like the same mesh at the origin; baking the model into float32 world
positions (what the renderer did before) turns its normals by tens of degrees there.
"""

import dataclasses

import jax.numpy as jnp
import numpy as np
import pytest
from _scenes import OUTPUTS, WHOLE, builtin_scene

import jaxnm
from jaxnm.camera import Camera, look_at, perspective
from scripts.studies import hard_cases as H


def _angle(a, b):
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    return np.degrees(np.arctan2(np.linalg.norm(np.cross(a, b), axis=-1), np.sum(a * b, -1)))


def _translated(scene, t, *, bake: bool):
    """``scene`` moved by ``t``: the mesh through the model matrix (or baked into float32
    world positions), the camera and the point light with it."""
    model = np.eye(4)
    model[:3, 3] = t
    cam = Camera.from_matrices(look_at(np.array([0.0, -2.35, 1.75]) + t, t + [0.0, 0.0, -0.1],
                                       (0, 0, 1)), perspective(45.0, 1.0, 0.1, 50.0))
    p = scene.lights.point
    lights = dataclasses.replace(scene.lights, point=dataclasses.replace(
        p, position=np.asarray(p.position, np.float64) + t))
    if bake:
        return scene.replace(mesh=scene.mesh.transformed(model), camera=cam, lights=lights)
    return scene.replace(model=model, camera=cam, lights=lights)


@pytest.fixture(scope="module")
def at_origin():
    """The built-in scene and its outputs. Every render of this module but the mirrored
    model's asks for the same outputs (`_scenes.OUTPUTS`, as the scene's renders in other
    modules): one program, the scene's mesh placed by a translation or baked."""
    scene = builtin_scene(WHOLE)
    return scene, jaxnm.render(scene, outputs=OUTPUTS)


@pytest.mark.parametrize("offset", [1e3, 1e6, 1e7])
def test_far_from_the_origin_renders_like_the_origin(at_origin, offset):
    scene, ref = at_origin
    t = np.array([1.0, -0.5, 0.25]) * offset
    out = jaxnm.render(_translated(scene, t, bake=False), outputs=OUTPUTS)
    np.testing.assert_array_equal(np.asarray(out["mask"]), np.asarray(ref["mask"]))
    m = np.asarray(ref["mask"])[..., 0] > 0
    err = _angle(out["perturbed_normal"], ref["perturbed_normal"])[m]
    assert err.max() < 0.01, (offset, float(err.max()))
    np.testing.assert_allclose(np.asarray(out["color"]), np.asarray(ref["color"]), atol=1e-5)
    # world positions come back in world space (float32 at that magnitude)
    np.testing.assert_allclose(np.asarray(out["position"])[m], np.asarray(ref["position"])[m]
                               + t, rtol=1e-6, atol=1e-6 * offset)


def test_float32_world_positions_lose_the_normal_far_out(at_origin):
    """What camera-relative rendering avoids: the same scene with the model baked into
    float32 world positions a million units out (float32 spacing there: 0.06)."""
    scene, ref = at_origin
    out = jaxnm.render(_translated(scene, np.array([1e6, -5e5, 2.5e5]), bake=True),
                       outputs=OUTPUTS)
    m = (np.asarray(ref["mask"])[..., 0] > 0) & (np.asarray(out["mask"])[..., 0] > 0)
    assert _angle(out["perturbed_normal"], ref["perturbed_normal"])[m].mean() > 5.0


def test_a_rotating_mirroring_model_far_out(at_origin):
    """A model that rotates, scales and mirrors as well as translates by 1e6: equal to the
    same linear map applied at the origin (the winding and the tangent frame follow the
    mirror)."""
    scene, _ = at_origin
    c, s = np.cos(0.5), np.sin(0.5)
    lin = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]) @ np.diag([-1.2, 1.0, 0.9])
    near = np.eye(4)
    near[:3, :3] = lin
    ref = jaxnm.render(scene.replace(mesh=scene.mesh.transformed(near)), outputs=OUTPUTS)
    t = np.array([1e6, -5e5, 2.5e5])
    far = _translated(scene, t, bake=False)
    model = np.asarray(far.model).copy()
    model[:3, :3] = lin
    out = jaxnm.render(far.replace(model=model), outputs=("perturbed_normal", "mask"))
    np.testing.assert_array_equal(np.asarray(out["mask"]), np.asarray(ref["mask"]))
    m = np.asarray(ref["mask"])[..., 0] > 0
    assert m.sum() > 1000
    assert _angle(out["perturbed_normal"], ref["perturbed_normal"])[m].max() < 0.01


def _padded(case, vertices=325, faces=528):
    """``case`` with its mesh padded to (``vertices``, ``faces``), the silhouette cases' sphere
    (`hard_cases.cases`), so that the planes, the uv charts and the spheres render and
    differentiate with one program: copies of the first vertex, and faces that each use one
    of them three times (zero area: they cover no pixel and change no gradient) appended
    after the mesh's own faces (whose ids and references do not change). The sub-pixel
    triangles' plane is larger: kept as it is."""
    mesh = case.scene.mesh
    nv, nf = vertices - mesh.positions.shape[0], faces - mesh.faces.shape[0]
    if nv < 0 or nf < 0:
        return case
    extra = np.full((nf, 3), mesh.positions.shape[0], np.int32)

    def more(a):
        return np.concatenate([np.asarray(a), np.repeat(np.asarray(a)[:1], nv, 0)])

    padded = dataclasses.replace(
        mesh, positions=jnp.asarray(more(mesh.positions)), uv=jnp.asarray(more(mesh.uv)),
        normals=jnp.asarray(more(mesh.normals)),
        faces=jnp.asarray(np.concatenate([np.asarray(mesh.faces), extra])))
    return dataclasses.replace(case, scene=case.scene.replace(mesh=padded))


HARD = {c.name: _padded(c) for c in H.cases(48)}


@pytest.mark.parametrize("name", list(HARD))
def test_hard_case(name):
    """Grazing views to 89.99 deg, close-ups 1e-4 above the surface, sheared (80 deg),
    mirrored and 1000:1 stretched uvs, sub-pixel triangles and triangles crossing the near
    plane: the perturbed normal within 1e-3 deg of the exact one at every pixel; a constant
    uv falls back to the unperturbed normal; silhouettes and a camera inside a closed mesh:
    finite. Every case: finite outputs and finite gradients w.r.t. the map, the vertex
    positions and the camera."""
    rec = H.run_case(HARD[name])
    assert rec["covered_pixels"] > 0 and rec["finite_outputs"] and rec["finite_gradients"]
    if "worst_deg" in rec:
        assert rec["worst_deg"] <= rec["tolerance_deg"], rec
    assert rec["pass"]
