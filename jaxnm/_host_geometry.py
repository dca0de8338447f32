"""Host-side float64 geometry, for decisions made before a frame's programs run.

Whether a camera sees any of a mesh (`jaxnm.scene.validate_scene`) and whether it can see
none of its back faces (`jaxnm.scene.back_faces_hidden`, a fit's views) are decided once, on
concrete arrays, in float64 NumPy: no XLA program is compiled for them, and nothing is
rounded before the decision.
"""

from __future__ import annotations

import jax
import numpy as np

from .camera import Camera

__all__ = ["box_in_front", "clip_float64", "closed_shape", "enclosed_volume"]


def _is_concrete(x) -> bool:
    return not isinstance(x, jax.core.Tracer)


def clip_float64(points, camera: Camera, model=None) -> np.ndarray:
    """`jaxnm.camera.to_clip` on the host in float64: clip-space coordinates (N, 4) of object-space
    ``points`` (N, 3) moved by ``model`` (an affine 4x4 object-to-world matrix, or None)
    and seen by a concrete ``camera``. For decisions made before a frame's programs run
    (the near-plane check, back-face culling)."""
    p = np.asarray(points, np.float64)
    if model is not None:
        m = np.asarray(model, np.float64)
        p = p @ m[:3, :3].T + m[:3, 3]
    rot = np.asarray(camera.view, np.float64)[:3, :3]
    proj = np.asarray(camera.projection, np.float64)
    return ((p - np.asarray(camera.eye, np.float64)) @ rot.T) @ proj[:, :3].T + proj[:, 3]


def closed_shape(positions, faces) -> np.ndarray | None:
    """The bounding box (2, 3) float64 (min, max) of a mesh that encloses a volume with its
    counter-clockwise (front) faces outside, else None (also for traced arrays): such a
    mesh, seen from outside, shows only front faces (`jaxnm.scene.back_faces_hidden`).

    Enclosing: after welding vertices at equal positions (to 1e-6 of the mesh's extent: a uv
    seam's copies), every edge is used by exactly two faces, once in each direction (closed,
    manifold, consistently oriented; faces with two welded corners equal are dropped);
    outside: the enclosed volume (the sum of the faces' signed tetrahedra) is positive. On
    the host, in float64/int64 (a few passes over the faces)."""
    if not (_is_concrete(positions) and _is_concrete(faces)):
        return None
    p = np.asarray(positions, np.float64)
    volume = enclosed_volume(p, np.asarray(faces, np.int64))
    if volume is None or not volume > 0:
        return None
    return np.stack([p.min(axis=0), p.max(axis=0)])


def enclosed_volume(p: np.ndarray, f: np.ndarray) -> float | None:
    """The signed volume that host float64 positions ``p`` and int64 faces ``f`` enclose
    (positive where the counter-clockwise faces look outside), or None where they enclose
    none: not closed, not manifold or not consistently oriented, after welding (as
    `closed_shape` says)."""
    if p.shape[0] == 0 or f.shape[0] == 0 or not np.all(np.isfinite(p)):
        return None
    # positions equal up to rounding (a seam's copies: cos 2pi vs cos 0) weld together
    step = 1e-6 * max(float(np.max(np.abs(p))), np.finfo(np.float64).tiny)
    _, weld = np.unique(np.round(p / step).astype(np.int64), axis=0, return_inverse=True)
    t = weld.reshape(-1)[f]
    t = t[(t[:, 0] != t[:, 1]) & (t[:, 1] != t[:, 2]) & (t[:, 2] != t[:, 0])]
    if t.shape[0] == 0:
        return None
    n = int(t.max()) + 1
    a = t.reshape(-1)
    b = np.roll(t, -1, axis=1).reshape(-1)
    edges = np.sort(a * n + b)
    if np.any(edges[1:] == edges[:-1]):  # an edge twice in one direction
        return None
    if not np.array_equal(edges, np.sort(b * n + a)):  # an edge without its reverse
        return None
    q = p[f]
    return float(np.sum(q[:, 0] * np.cross(q[:, 1], q[:, 2]))) / 6


def box_in_front(box: np.ndarray, camera: Camera, model=None) -> bool:
    """Whether the (2, 3) (min, max) box, moved by ``model`` (None: identity; it must not
    mirror), lies wholly in front of ``camera``'s near plane (host, float64)."""
    if model is not None and not np.linalg.det(np.asarray(model, np.float64)[:3, :3]) > 0:
        return False
    corners = [[box[i, 0], box[j, 1], box[k, 2]] for i in (0, 1) for j in (0, 1) for k in (0, 1)]
    clip = clip_float64(corners, camera, model)
    w = clip[:, 3]
    return bool(np.all(w > 0) and np.all(clip[:, 2] + w > 1e-6 * w))
