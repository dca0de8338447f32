"""Baking a tangent-space normal map from a normal field, in a chosen frame convention.

A tangent-space map only means something together with the frame it is decoded in
(`jaxnm.frames.FRAMES`): the renderer decodes ``normalize(T m.x + B m.y + N m.z)``. To bake
is to invert that per texel: find the mesh point whose uv is the texel centre, build the
frame there exactly as the renderer would, and store ``m = [T B N]^-1 n`` (normalised) for
the target normal ``n``, so that decoding in the same frame returns ``n`` at texel centres.

`bake_normal_map` does it for the texture-space conventions, the ones a baker can
evaluate without a camera:

- ``"cotangent"`` (also ``"exact"``): Schüler's frame of the texel's triangle (the uv
  gradients on the plane normal to the interpolated normal, scaled so the longer is unit),
  which is what the screen-space cotangent frame computes for every pixel of that triangle;
- ``"vertex"``: MikkTSpace (the mesh's per-corner tangents, `jaxnm.tangents`), the frame of
  Blender, Substance, xNormal and glTF;
- ``"vertex_area"``: area-weighted per-vertex tangents.

The target normals come from a function of uv (for example a high-poly surface evaluated at
the same surface parameters, or an analytic bump). Everything here runs once, in NumPy
float64 on the host, with the frames built by `jaxnm.frames` (float32).
"""

from __future__ import annotations

import functools
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np

from . import frames as _frames
from .geometry import Mesh

__all__ = ["BAKE_FRAMES", "texel_uv", "locate_texels", "world_to_tangent", "bake_normal_map"]

#: The frame conventions `bake_normal_map` can bake for (``"exact"`` is ``"cotangent"``).
BAKE_FRAMES = ("cotangent", "exact", "vertex", "vertex_area")


def texel_uv(map_hw: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """The uv of each texel centre, two ``(h, w)`` arrays (float64), for a map stored with
    its uv origin at the bottom left (row 0 holds v near 1: image layout)."""
    h, w = map_hw
    u = (np.arange(w) + 0.5) / w
    v = 1.0 - (np.arange(h) + 0.5) / h
    return np.meshgrid(u, v)


def locate_texels(mesh: Mesh, u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per point ``(u, v)`` (any shape, flattened): the index of a face whose uv triangle
    contains it (-1 where none does) and its barycentrics ``(N, 3)`` in that face."""
    if mesh.uv is None:
        raise ValueError("locate_texels: the mesh has no texture coordinates (uv)")
    uv = np.asarray(mesh.uv, np.float64)[np.asarray(mesh.faces)]  # (F, 3, 2)
    q = np.stack([np.ravel(u), np.ravel(v)], -1)
    tri = np.full(len(q), -1)
    bary = np.zeros((len(q), 3))
    a, b, c = uv[:, 0], uv[:, 1], uv[:, 2]
    det = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (c[:, 0] - a[:, 0]) * (b[:, 1] - a[:, 1])
    for f in np.nonzero(np.abs(det) > 0)[0]:  # zero-area uv triangles hold no texel
        lo, hi = uv[f].min(0) - 1e-12, uv[f].max(0) + 1e-12
        idx = np.nonzero(np.all((q >= lo) & (q <= hi), -1) & (tri < 0))[0]
        if idx.size == 0:
            continue
        d = q[idx] - a[f]
        b1 = (d[:, 0] * (c[f, 1] - a[f, 1]) - (c[f, 0] - a[f, 0]) * d[:, 1]) / det[f]
        b2 = ((b[f, 0] - a[f, 0]) * d[:, 1] - d[:, 0] * (b[f, 1] - a[f, 1])) / det[f]
        inside = (b1 >= -1e-12) & (b2 >= -1e-12) & (b1 + b2 <= 1 + 1e-12)
        tri[idx[inside]] = f
        bary[idx[inside]] = np.stack([1 - b1 - b2, b1, b2], -1)[inside]
    return tri, bary


def _check_bakeable(mesh: Mesh, frame: str, caller: str) -> None:
    if frame not in BAKE_FRAMES:
        raise ValueError(f"{caller}: cannot bake for frame {frame!r}; expected one of "
                         f"{', '.join(BAKE_FRAMES)} (the others depend on the camera)")
    if mesh.normals is None:
        raise ValueError(f"{caller}: the mesh has no vertex normals")
    if frame == "vertex" and mesh.tangents is None:
        raise ValueError(f"{caller}: frame 'vertex' needs the mesh's MikkTSpace "
                         "tangents (Mesh.with_tangents())")


@functools.partial(jax.jit, static_argnames="frame")
def _frame_of(frame: str, *args) -> _frames.Frame:
    """The renderer's frame at points, from `world_to_tangent`'s interpolated attributes."""
    if frame in ("cotangent", "exact"):
        return _frames.exact_frame(*args)
    if frame == "vertex":
        return _frames.compute_frame("vertex", args[0],
                                     inputs=_frames.FrameInputs(tangent=args[1]))
    return _frames.compute_frame("vertex_area", args[0],
                                 inputs=_frames.FrameInputs(tangent=args[1]))


def world_to_tangent(mesh: Mesh, tri: np.ndarray, bary: np.ndarray, normals: np.ndarray, *,
                     frame: str = "vertex",
                     fill: tuple[float, float, float] = (0.0, 0.0, 1.0)) -> np.ndarray:
    """The tangent-space vectors that decode to the world-space ``normals`` at the mesh
    points ``(tri, bary)`` in ``frame`` (one of `BAKE_FRAMES`): per point the frame is
    built exactly as the renderer builds it there (`jaxnm.frames`, float32) and inverted,
    ``m = normalize([T B N]^-1 n)``.

    **Arguments:**
    - `mesh`: the mesh with uv and vertex normals; ``"vertex"`` needs its MikkTSpace
      tangents (`Mesh.with_tangents`).
    - `tri`: ``(N,)`` face index of each point; `bary`: ``(N, 3)`` its barycentrics.
    - `normals`: ``(N, 3)`` world-space target normals (any length but zero).
    - `fill`: the result where the frame is degenerate (or the target is zero).

    **Returns:** ``(N, 3)`` float64 unit vectors.
    """
    _check_bakeable(mesh, frame, "world_to_tangent")
    tri = np.asarray(tri)
    bary = np.asarray(bary, np.float64)
    n_points = len(tri)
    # pad to a power of two (>= 1024) so that the frame is compiled for few shapes
    size = max(1024, 1 << max(0, n_points - 1).bit_length())
    tri = np.concatenate([tri, np.zeros(size - n_points, tri.dtype)])
    bary = np.concatenate([bary, np.full((size - n_points, 3), 1.0 / 3.0)])
    faces = np.asarray(mesh.faces)[tri]

    def corners(a):
        return np.asarray(a, np.float64)[faces]

    def interp(c):
        return np.einsum("tk,tkc->tc", bary, c)

    n = interp(corners(mesh.normals))
    if frame in ("cotangent", "exact"):
        args = (corners(mesh.positions), corners(mesh.uv), _unit_rows(n))
    elif frame == "vertex":  # per face corner, reconstructed as the renderer does
        args = (n, interp(np.asarray(mesh.tangents, np.float64)[tri]))
    else:
        vt = _frames.vertex_tangents(mesh.positions, mesh.normals, mesh.uv, mesh.faces)
        args = (_unit_rows(n), interp(corners(vt)))
    fr = _frame_of(frame, *(jnp.asarray(a, jnp.float32) for a in args))
    t_, b_, n_ = (np.asarray(np.asarray(x)[:n_points].T, np.float64) for x in (fr.T, fr.B, fr.N))
    target = np.asarray(normals, np.float64).T
    # [T B N] m = target by Cramer's rule: det times the inverse has the rows B x N, N x T,
    # T x B; components along the first axis
    rows = [_cross(b_, n_), _cross(n_, t_), _cross(t_, b_)]
    det = _dot(t_, rows[0])
    ok = np.abs(det) > 1e-12  # a degenerate frame stores the fill value
    m = np.stack([_dot(r, target) for r in rows], -1) / np.where(ok, det, 1.0)[:, None]
    m[~ok] = fill
    m[~(np.einsum("ti,ti->t", m, m) > 0)] = fill
    return m / np.sqrt(np.einsum("ti,ti->t", m, m))[:, None]


def _unit_rows(a: np.ndarray) -> np.ndarray:
    return a / np.linalg.norm(a, axis=-1, keepdims=True)


def _cross(a: np.ndarray, b: np.ndarray) -> list[np.ndarray]:
    """``a x b`` of vectors given by their components ``a[0], a[1], a[2]`` (as np.cross
    computes it)."""
    return [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]


def _dot(a, b) -> np.ndarray:
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def bake_normal_map(mesh: Mesh, normal_at_uv: Callable[[np.ndarray, np.ndarray], np.ndarray],
                    map_hw: tuple[int, int], *, frame: str = "vertex",
                    fill: tuple[float, float, float] = (0.0, 0.0, 1.0)) -> np.ndarray:
    """Bake the normals ``normal_at_uv(u, v) -> (N, 3)`` into a tangent-space map for
    ``frame`` (one of `BAKE_FRAMES`).

    **Arguments:**
    - `mesh`: the (low-poly) mesh with uv and vertex normals; ``"vertex"`` needs its
      MikkTSpace tangents (`Mesh.with_tangents`).
    - `normal_at_uv`: the target unit normals (world space) at flat arrays of u and v.
    - `map_hw`: ``(height, width)`` of the map.
    - `fill`: the value of texels no uv triangle covers.

    **Returns:** ``(h, w, 3)`` float32 signed unit vectors (decode them with
    ``NormalMapOptions(encoding="signed")``; `jaxnm.textures.encode_normal_map` makes an
    8-bit image), uv origin at the bottom left.
    """
    _check_bakeable(mesh, frame, "bake_normal_map")
    u, v = texel_uv(map_hw)
    tri, bary = locate_texels(mesh, u, v)
    hit = tri >= 0
    target = np.asarray(normal_at_uv(u.ravel()[hit], v.ravel()[hit]), np.float64)
    m = world_to_tangent(mesh, tri[hit], bary[hit], target, frame=frame, fill=fill)
    out = np.tile(np.asarray(fill, np.float32), (u.size, 1))
    out[hit] = m
    return out.reshape(*map_hw, 3)
