"""Checks of the meshes a bake starts from, shared by the bakers of `jaxnm.transfer`: arrays
that make a mesh, normals where it has none, LOW's uvs and tangents, and warnings about
degenerate and non-manifold triangles and overlapping uv islands."""

from __future__ import annotations

import dataclasses
import warnings

import numpy as np

from .._host_geometry import enclosed_volume
from ..geometry import Mesh, vertex_normals
from ..io import JaxnmWarning

__all__ = ["BakeWarning", "check_mesh", "with_normals", "prepare_low", "warn_bad_triangles",
           "warn_overlap", "warn_outside_unit_square", "inside_out"]


class BakeWarning(JaxnmWarning):
    """Something in a bake's input deserves attention but the bake went on: rays that hit
    nothing, overlapping uv islands, degenerate or non-manifold triangles."""


def check_mesh(mesh: Mesh, name: str) -> tuple[np.ndarray, np.ndarray]:
    """Host float64 positions and int64 faces, or ValueError naming the mesh (TypeError for
    anything but a `Mesh`)."""
    if not isinstance(mesh, Mesh):
        raise TypeError(f"{name}: expected a jaxnm Mesh (jaxnm.io.load_mesh), got "
                        f"{type(mesh).__name__}")
    p = np.asarray(mesh.positions, np.float64)
    f = np.asarray(mesh.faces)
    if p.ndim != 2 or p.shape[1] != 3 or len(p) == 0:
        raise ValueError(f"{name}: positions must have shape (V, 3), got {p.shape}")
    if f.ndim != 2 or f.shape[1] != 3 or len(f) == 0 or not np.issubdtype(f.dtype, np.integer):
        raise ValueError(f"{name}: faces must be integer triangles (F, 3), got {f.shape} "
                         f"{f.dtype}")
    if not np.all(np.isfinite(p)):
        raise ValueError(f"{name}: vertex positions are NaN or infinite")
    if f.min() < 0 or f.max() >= len(p):
        raise ValueError(f"{name}: face indices must be in [0, {len(p) - 1}]")
    return p, f.astype(np.int64)


def _count_bad(rows: np.ndarray) -> int:
    """How many rows of ``rows`` hold a NaN or an infinity."""
    return int(np.sum(~np.all(np.isfinite(rows), axis=-1)))


def with_normals(mesh: Mesh, name: str) -> Mesh:
    """``mesh`` with its normals checked, or angle-weighted ones where it has none (as
    Blender computes them), or ValueError naming the mesh."""
    if mesh.normals is not None:
        n = np.asarray(mesh.normals)
        if n.shape != np.shape(mesh.positions):
            raise ValueError(f"{name}: normals must have the positions' shape "
                             f"{np.shape(mesh.positions)}, got {n.shape}")
        if not np.all(np.isfinite(n)):
            raise ValueError(f"{name}: {_count_bad(n)} of {len(n)} vertex normals are NaN or "
                             f"infinite")
        return mesh
    return dataclasses.replace(mesh, normals=vertex_normals(mesh.positions, mesh.faces))


def prepare_low(low: Mesh, frame: str, name: str) -> Mesh:
    """LOW with uvs checked, normals (angle-weighted where it has none) and, for
    ``"vertex"``, MikkTSpace tangents; warns about degenerate and non-manifold triangles,
    uvs outside the unit square, and a closed mesh turned inside out."""
    p, f = check_mesh(low, name)
    if low.uv is None:
        raise ValueError(f"{name}: the mesh has no texture coordinates (uv); a normal map is "
                         "baked into the low-poly mesh's uv layout")
    uv = np.asarray(low.uv)
    if uv.shape != (len(p), 2):
        raise ValueError(f"{name}: uv must have shape ({len(p)}, 2), got {uv.shape}")
    if not np.all(np.isfinite(uv)):
        raise ValueError(f"{name}: {_count_bad(uv)} of {len(uv)} vertex uvs are NaN or infinite")
    low = with_normals(low, name)
    if frame == "vertex" and low.tangents is None:
        low = low.with_tangents()
    warn_bad_triangles(p, f, name)
    warn_outside_unit_square(uv, f, name)
    if inside_out(p, f):
        warnings.warn(f"{name}: a closed mesh whose faces wind inwards (the volume they "
                      "enclose is negative), so its front faces look inside; reverse their "
                      "winding", BakeWarning, stacklevel=3)
    return low


def inside_out(p: np.ndarray, f: np.ndarray) -> bool:
    """Whether host positions ``p`` and faces ``f`` are a closed mesh whose faces wind
    inwards (a negative enclosed volume): its front faces look inside."""
    volume = enclosed_volume(p, f)
    return volume is not None and volume < 0


#: How far (in uv units) a triangle's corner may lie outside [0, 1] unremarked: exporters
#: write 1.0000001, and a thousandth is a texel of a 1024 map, within the bake's margin.
_UV_SLACK = 1e-3


def warn_outside_unit_square(uv: np.ndarray, f: np.ndarray, name: str) -> None:
    """A `BakeWarning` where triangles reach outside the unit uv square: the map holds
    [0, 1]² only, so their texels outside it are never baked, while a render repeats the
    map there (tiled or UDIM layouts)."""
    t = uv[f]
    out = ((t < -_UV_SLACK) | (t > 1 + _UV_SLACK)).any(axis=(1, 2))
    if out.any():
        corners = t[out].reshape(-1, 2)
        lo, hi = corners.min(0), corners.max(0)
        warnings.warn(f"{name}: {int(out.sum())} of {len(f)} triangles reach outside the unit "
                      f"uv square (u {lo[0]:.3g} to {hi[0]:.3g}, v {lo[1]:.3g} to "
                      f"{hi[1]:.3g}; first: face {int(np.argmax(out))}); the map covers [0, 1] "
                      "only, so no texel is baked for them there, and a render repeats the "
                      "map over them: unwrap LOW anew (xatlas)", BakeWarning,
                      stacklevel=4)


def warn_bad_triangles(p: np.ndarray, f: np.ndarray, name: str) -> None:
    """`BakeWarning`s for zero-area triangles and for edges that more than two triangles
    share (after welding equal positions)."""
    q = p[f]
    area2 = np.linalg.norm(np.cross(q[:, 1] - q[:, 0], q[:, 2] - q[:, 0]), axis=-1)
    scale = max(float(np.abs(p).max()), np.finfo(np.float64).tiny)
    bad = np.flatnonzero(area2 <= (1e-12 * scale) ** 2)
    if bad.size:
        warnings.warn(f"{name}: {bad.size} degenerate (zero-area) triangles (first: face "
                      f"{bad[0]}); their texels have no tangent frame and keep (0, 0, 1)",
                      BakeWarning, stacklevel=4)
    _, weld = np.unique(p, axis=0, return_inverse=True)
    t = weld.reshape(-1)[f]
    e = np.sort(np.stack([t, np.roll(t, -1, axis=1)], -1).reshape(-1, 2), axis=1)
    e = e[e[:, 0] != e[:, 1]]
    edges, counts = np.unique(e, axis=0, return_counts=True)
    many = counts > 2
    if many.any():
        a, b = edges[np.argmax(many)]
        warnings.warn(f"{name}: {int(many.sum())} edges are shared by more than two triangles "
                      f"(non-manifold; first: the edge at {p[np.argmax(weld == a)].round(4)} - "
                      f"{p[np.argmax(weld == b)].round(4)}); rays near them leave from every "
                      "sheet", BakeWarning, stacklevel=4)


def warn_overlap(cover, name: str) -> None:
    """A `BakeWarning` where texels lie inside more than one uv triangle of ``cover`` (a
    `jaxnm.transfer._texels.TexelCover`)."""
    k = int(cover.overlapping.sum())
    if k:
        faces = " and ".join(str(i) for i in cover.overlap_faces)
        warnings.warn(f"{name}: {k} texels lie inside more than one uv triangle (overlapping "
                      f"uv islands; first: faces {faces}); each such texel is baked from the "
                      "triangle with the highest index, as Blender does", BakeWarning,
                      stacklevel=4)
