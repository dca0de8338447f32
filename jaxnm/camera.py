"""Cameras: OpenGL view and projection matrices, and the clip-space transform.

Conventions (OpenGL): right-handed world and eye space, the camera looks down
its local ``-z`` axis with ``+y`` up; matrices are 4x4, row-major nested
lists/arrays that act on *column* vectors, ``clip = projection @ view @ model @
[p, 1]``; NDC is ``clip.xyz / clip.w`` with ``z`` in ``[-1, 1]`` (near to far).
"""

from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array
from jaxtyping import ArrayLike, Float

#: Matrix products of geometry are computed in full float32 on every backend.
_HIGHEST = jax.lax.Precision.HIGHEST

__all__ = ["Camera", "look_at", "perspective", "orthographic", "to_clip", "to_window",
           "eye_to_world"]


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Camera:
    """A pinhole (or orthographic) camera.

    **Fields:**
    - `view`: (4, 4) world-to-eye matrix.
    - `projection`: (4, 4) eye-to-clip matrix (OpenGL clip space).
    - `eye`: (3,) camera position in world space, ``inverse(view) @ [0, 0, 0, 1]``,
      kept separately so that camera-relative positions stay accurate for
      geometry far from the origin: `from_matrices` stores it as a float64
      NumPy array (JAX reads it as float32; `jaxnm.render` subtracts it from
      the model's positions in float64 on the host).
    """

    view: Float[ArrayLike, "*batch 4 4"]
    projection: Float[ArrayLike, "*batch 4 4"]
    eye: Float[ArrayLike, "*batch 3"]

    @staticmethod
    def from_matrices(view, projection) -> Camera:
        """A camera from explicit 4x4 ``view`` and ``projection`` matrices (column vectors)."""
        view64 = _as_matrix(view, "view")
        proj64 = _as_matrix(projection, "projection")
        if not np.allclose(view64[3], [0.0, 0.0, 0.0, 1.0]):
            raise ValueError("camera: the view matrix must be affine (last row 0, 0, 0, 1), got "
                             f"{view64[3].tolist()}")
        if abs(np.linalg.det(view64[:3, :3])) < 1e-12:
            raise ValueError("camera: the view matrix is singular")
        eye = np.linalg.inv(view64)[:3, 3]
        return Camera(
            view=jnp.asarray(view64, jnp.float32),
            projection=jnp.asarray(proj64, jnp.float32),
            eye=np.asarray(eye, np.float64),
        )

    @staticmethod
    def look_at(eye, target, up=(0.0, 1.0, 0.0), *, fov_y_deg=45.0, aspect=1.0, near=0.1,
                far=100.0) -> Camera:
        """A perspective camera at ``eye`` looking at ``target`` (see `look_at`, `perspective`).
        ``aspect`` is the image's width / height: the default, 1, suits a square image, and
        a scene of another shape renders stretched unless it is given (scene files set it
        from their width and height)."""
        return Camera.from_matrices(look_at(eye, target, up),
                                    perspective(fov_y_deg, aspect, near, far))

    @staticmethod
    def framing(centre, radius: float, direction, *, up=None, fov_y_deg: float = 30.0,
                aspect: float = 1.0, margin: float = 1.02) -> Camera:
        """A perspective camera that sees the whole sphere of ``radius`` about ``centre``:
        on the ray from ``centre`` along ``direction``, looking at ``centre``, at the
        distance where the sphere, enlarged by ``margin``, touches the narrower side of the
        view (``aspect`` is the image's width / height); its near and far planes enclose
        the sphere. ``up`` None takes the world axis least along the view.
        `jaxnm.geometry.bounding_sphere` gives a mesh's centre and radius."""
        _concrete({"centre": centre, "radius": radius, "direction": direction}, "framing")
        c = np.asarray(centre, np.float64)
        d = np.asarray(direction, np.float64)
        if c.shape != (3,) or d.shape != (3,) or not np.all(np.isfinite(np.r_[c, d])):
            raise ValueError(f"camera: framing takes a finite centre and direction of 3 "
                             f"numbers each, got {centre!r} and {direction!r}")
        if not (radius > 0 and math.isfinite(radius)) or not margin >= 1:
            raise ValueError(f"camera: framing needs a radius > 0 and a margin >= 1, got "
                             f"{radius!r} and {margin!r}")
        if not np.linalg.norm(d) > 0:
            raise ValueError("camera: framing's direction must not be zero")
        d = d / np.linalg.norm(d)
        half = math.radians(fov_y_deg) / 2
        if aspect < 1:  # the horizontal side is the narrower
            half = math.atan(aspect * math.tan(half))
        dist = margin * radius / math.sin(half)
        if up is None:
            up = np.eye(3)[int(np.argmin(np.abs(d)))]
        return Camera.look_at(c + dist * d, c, up, fov_y_deg=fov_y_deg, aspect=aspect,
                              near=max(dist - 1.1 * radius, 1e-3 * radius),
                              far=dist + 1.1 * radius)

    @property
    def view_projection(self) -> Array:
        """``projection @ view``."""
        return jnp.matmul(self.projection, self.view, precision=_HIGHEST)


def _concrete(values: dict, where: str) -> None:
    """Refuse traced values in a constructor that computes on the host in float64."""
    for name, v in values.items():
        if isinstance(v, jax.core.Tracer):
            raise TypeError(f"camera: {where} builds a camera on the host in float64 and "
                            f"takes concrete values, but `{name}` is traced (jax.jit, grad or "
                            "vmap); to trace a camera, trace the arrays of a Camera(view=..., "
                            "projection=..., eye=...) made outside the traced function")


def _as_matrix(m, name: str) -> np.ndarray:
    _concrete({name: m}, "from_matrices")
    m = np.asarray(m, dtype=np.float64)
    if m.shape != (4, 4):
        raise ValueError(f"camera: `{name}` must be a 4x4 matrix, got shape {m.shape}")
    if not np.all(np.isfinite(m)):
        raise ValueError(f"camera: `{name}` contains NaN or inf")
    return m


def look_at(eye, target, up=(0.0, 1.0, 0.0)) -> np.ndarray:
    """World-to-eye matrix (float64) of a camera at ``eye`` looking at ``target`` (gluLookAt)."""
    _concrete({"eye": eye, "target": target, "up": up}, "look_at")
    eye, target, up = (np.asarray(v, np.float64).reshape(3) for v in (eye, target, up))
    for name, v in (("eye", eye), ("target", target), ("up", up)):
        if not np.all(np.isfinite(v)):
            raise ValueError(f"camera: `{name}` must be finite, got {v.tolist()}")
    f = target - eye
    if np.linalg.norm(f) <= 1e-12 * max(1.0, np.linalg.norm(eye)):
        raise ValueError("camera: `eye` and `target` coincide")
    f = f / np.linalg.norm(f)
    s = np.cross(f, up)
    if np.linalg.norm(s) <= 1e-9 * max(np.linalg.norm(up), 1e-300):
        raise ValueError("camera: `up` is parallel to the viewing direction (or zero)")
    s = s / np.linalg.norm(s)
    u = np.cross(s, f)
    m = np.eye(4)
    m[0, :3], m[1, :3], m[2, :3] = s, u, -f
    m[:3, 3] = -m[:3, :3] @ eye
    return m


def perspective(fov_y_deg: float, aspect: float, near: float, far: float) -> np.ndarray:
    """OpenGL perspective projection (gluPerspective), float64; NDC z in [-1, 1].
    ``fov_y_deg`` is the vertical field of view; ``aspect`` the image's width / height."""
    if not (0.0 < fov_y_deg < 180.0):
        raise ValueError(f"camera: `fov_y_deg` must be in (0, 180), got {fov_y_deg}")
    if not (aspect > 0.0 and math.isfinite(aspect)):
        raise ValueError(f"camera: `aspect` must be positive, got {aspect}")
    if not (near > 0.0):
        raise ValueError(f"camera: `near` must be > 0 for a perspective camera, got {near}")
    if not (far > near and math.isfinite(far)):
        raise ValueError(f"camera: `far` must be finite and > near ({near}), got {far}")
    f = 1.0 / math.tan(math.radians(fov_y_deg) / 2.0)
    m = np.zeros((4, 4))
    m[0, 0] = f / aspect
    m[1, 1] = f
    m[2, 2] = (far + near) / (near - far)
    m[2, 3] = 2.0 * far * near / (near - far)
    m[3, 2] = -1.0
    return m


def orthographic(left, right, bottom, top, near, far) -> np.ndarray:
    """OpenGL orthographic projection (glOrtho), float64."""
    if not (right != left and top != bottom and far != near):
        raise ValueError("camera: orthographic extents must be non-empty")
    m = np.eye(4)
    m[0, 0] = 2.0 / (right - left)
    m[1, 1] = 2.0 / (top - bottom)
    m[2, 2] = -2.0 / (far - near)
    m[0, 3] = -(right + left) / (right - left)
    m[1, 3] = -(top + bottom) / (top - bottom)
    m[2, 3] = -(far + near) / (far - near)
    return m


def to_clip(positions: Float[ArrayLike, "V 3"], camera: Camera) -> Float[Array, "V 4"]:
    """Clip-space coordinates ``(V, 4)`` of world-space ``positions`` ``(V, 3)``.

    Computed as ``projection @ A @ (p - eye)``, where ``A`` is the linear part of
    the view matrix (``view @ p = A (p - eye)`` for any affine view matrix), so
    that geometry far from the world origin but near the camera keeps its
    precision.
    """
    p = jnp.asarray(positions)
    # Written out term by term rather than as matmuls: float32 products on any backend (a
    # GPU's default matmul precision, TF32, would round positions to 1e-4), and on the CPU
    # less time than two matmuls with an inner axis of 3. Each term is a column of positions
    # times a row of the matrix, broadcast to (V, 3) then (V, 4): XLA's CPU loop over the
    # (V, 4) result reads its inputs once (docs/guides/design.md, "Numerics")
    a, proj = camera.view[None, :3, :3], camera.projection[None]  # (1, 3, 3), (1, 4, 4)
    d = p - jnp.asarray(camera.eye)[None, :]
    e = d[:, 0:1] * a[:, :, 0] + d[:, 1:2] * a[:, :, 1] + d[:, 2:3] * a[:, :, 2]
    return (e[:, 0:1] * proj[:, :, 0] + e[:, 1:2] * proj[:, :, 1] + e[:, 2:3] * proj[:, :, 2]
            + proj[:, :, 3])


def to_window(clip: Float[ArrayLike, "*batch 4"], width: int,
              height: int) -> Float[Array, "*batch 4"]:
    """Homogeneous window coordinates ``((X + W) w/2, (Y + W) h/2, (Z + W)/2, W)`` of clip
    points ``(X, Y, Z, W)`` in a ``width`` x ``height`` image: dividing the first three by
    the last gives window x, y (pixels, y up) and the window depth in [0, 1]."""
    x, y, z, w = jnp.moveaxis(clip, -1, 0)
    return jnp.stack([(x + w) * (0.5 * width), (y + w) * (0.5 * height), (z + w) * 0.5, w], -1)


def eye_to_world(camera: Camera, direction) -> np.ndarray:
    """The unit world-space direction (float64) of ``direction`` given in the camera's eye
    frame (x right, y up, z towards the viewer), e.g. a light placed relative to the view."""
    rot = np.asarray(camera.view, np.float64)[:3, :3]
    v = np.linalg.solve(rot, np.asarray(direction, np.float64))
    return v / np.linalg.norm(v)
