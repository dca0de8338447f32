"""Camera-relative rendering: the scene moved so that the camera sits at the origin.

A mesh far from the world origin keeps its precision when its float32 positions are small
numbers near the camera. `relative_inputs` composes the model matrix and the camera's
position in float64 on the host, where they are concrete, before anything is rounded to
float32 (what engines call camera-relative rendering); `place` moves the mesh inside the
frame's program. Point lights move with the mesh; directional lights, normals and the view
rotation do not change. Traced cameras or models (``jax.grad`` with respect to them) take
the same steps in float32 with JAX: NumPy cannot trace, and float32 cannot keep the
precision, so each computation serves where the other cannot.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from .camera import Camera
from .geometry import Mesh
from .numerics import safe_normalize
from .scene import Scene

__all__ = ["NO_SHIFT", "place", "relative_inputs"]


def relative_inputs(scene: Scene):
    """What a frame needs to render ``scene`` camera-relative: ``(camera, lights, origin,
    placement, affine)``, the camera at the origin (its view's rotation only), the point
    lights moved with everything else, the camera's world position ``origin``, the
    ``placement`` of the mesh and whether it is ``affine`` (`place`). In float64 on the host
    where the camera, the model and the point lights are concrete (then rounded to float32:
    a model's large translation and a large eye cancel before any rounding), in float32 with
    JAX where any is traced."""
    cam, model, lights = scene.camera, scene.model, scene.lights
    point = None if lights is None else lights.point
    if _concrete(cam.eye, cam.view, model, None if point is None else point.position):
        return _on_host(cam, model, lights, point)
    return _traced(cam, model, lights, point)


def _on_host(cam: Camera, model, lights, point):
    """`relative_inputs` in float64 NumPy, rounded to float32 at the end."""
    eye = np.asarray(cam.eye, np.float64)
    rel = np.eye(4) if model is None else np.array(model, np.float64)
    rel[:3, 3] -= eye
    view = np.array(cam.view, np.float64)
    view[:3, 3] = 0.0
    if point is not None:
        moved = np.asarray(point.position, np.float64) - eye
        lights = dataclasses.replace(lights, point=dataclasses.replace(
            point, position=moved.astype(np.float32)))
    camera = Camera(view=view.astype(np.float32), projection=cam.projection,
                    eye=np.zeros(3, np.float32))
    linear = rel[:3, :3]
    if np.array_equal(linear, np.eye(3)):
        return camera, lights, eye.astype(np.float32), rel[:3, 3].astype(np.float32), False
    placement = (rel.astype(np.float32), np.linalg.inv(linear).T.astype(np.float32))
    return camera, lights, eye.astype(np.float32), placement, True


def _traced(cam: Camera, model, lights, point):
    """`relative_inputs` in float32 JAX, for a traced camera, model or point light."""
    eye = jnp.asarray(cam.eye, jnp.float32)
    view = jnp.asarray(cam.view, jnp.float32).at[:3, 3].set(0.0)
    if point is not None:
        lights = dataclasses.replace(lights, point=dataclasses.replace(
            point, position=point.position - eye.reshape((1,) * (jnp.ndim(point.position) - 1)
                                                           + (3,))))
    camera = Camera(view=view, projection=cam.projection, eye=jnp.zeros(3, jnp.float32))
    if model is None:
        return camera, lights, eye, -eye, False
    rel = jnp.asarray(model, jnp.float32).at[:3, 3].add(-eye)
    return camera, lights, eye, (rel, jnp.linalg.inv(rel[:3, :3]).T), True


def place(mesh: Mesh, placement, affine: bool) -> Mesh:
    """``mesh`` moved by ``placement``: a translation (3,) (``affine`` False), or
    ``(rel, normal_matrix)``: positions by the 4x4 affine ``rel``, normals by
    ``normal_matrix`` (the inverse transpose of its linear part) and renormalised, tangents
    by the linear part; a mirroring ``rel`` reverses the faces' winding, so that
    counter-clockwise stays front."""
    if not affine:
        return dataclasses.replace(mesh, positions=mesh.positions
                                   + jnp.asarray(placement, jnp.float32)[None])
    rel, normal_matrix = (jnp.asarray(x, jnp.float32) for x in placement)
    linear = rel[:3, :3]
    highest = jax.lax.Precision.HIGHEST
    positions = jnp.matmul(mesh.positions, linear.T, precision=highest) + rel[None, :3, 3]
    normals, tangents, faces = mesh.normals, mesh.tangents, mesh.faces
    if normals is not None:
        normals = safe_normalize(jnp.matmul(normals, normal_matrix.T, precision=highest))
    mirrored = jnp.linalg.det(linear) < 0
    if tangents is not None:
        xyz = safe_normalize(jnp.matmul(tangents[..., :3], linear.T, precision=highest))
        moved = jnp.concatenate([xyz, tangents[..., 3:]], -1)
        # a mirror flips the winding: the corners reversed, and cross(N, T) with them
        flipped = moved[:, ::-1] * jnp.asarray([1.0, 1.0, 1.0, -1.0], moved.dtype)
        tangents = jnp.where(mirrored, flipped, moved)
    faces = jnp.where(mirrored, faces[:, ::-1], faces)
    return dataclasses.replace(mesh, positions=positions, normals=normals, faces=faces,
                               tangents=tangents)


def _concrete(*xs) -> bool:
    return all(not isinstance(x, jax.core.Tracer)
               for x in jax.tree_util.tree_leaves(xs))


#: The placement of a mesh already where it belongs (`place`): zero shift.
NO_SHIFT = np.zeros(3, np.float32)
