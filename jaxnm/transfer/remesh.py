"""A low-poly mesh made from a high-poly one: fewer triangles (`decimate`, with
``fast-simplification``) and a uv layout (`unwrap`, with ``xatlas``), both from the ``bake``
extra; together they turn a sculpt into a mesh to bake its map onto."""

from __future__ import annotations

import numpy as np

from ..geometry import Mesh
from ._meshes import check_mesh

__all__ = ["weld", "decimate", "unwrap", "angle_weighted_normals"]


def weld(positions: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(positions, faces)`` with vertices at equal positions merged (a mesh split at uv
    or normal seams becomes one surface) and unused vertices dropped."""
    p = np.asarray(positions, np.float64)
    f = np.asarray(faces, np.int64)
    unique, inverse = np.unique(p, axis=0, return_inverse=True)
    f = inverse.reshape(-1)[f]
    used, f = np.unique(f, return_inverse=True)
    return unique[used], f.reshape(-1, 3)


def angle_weighted_normals(positions: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Unit vertex normals, each face's normal weighted by its angle at the vertex, in
    float64 (`jaxnm.geometry.vertex_normals`' ``"angle"`` weighting, on the host)."""
    p = np.asarray(positions, np.float64)[faces]
    n = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    n /= np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-300)
    acc = np.zeros((len(positions), 3))
    for k in range(3):
        e1 = p[:, (k + 1) % 3] - p[:, k]
        e2 = p[:, (k + 2) % 3] - p[:, k]
        cos = np.einsum("ij,ij->i", e1, e2) / np.maximum(
            np.linalg.norm(e1, axis=-1) * np.linalg.norm(e2, axis=-1), 1e-300)
        w = np.arccos(np.clip(cos, -1.0, 1.0))
        for c in range(3):
            acc[:, c] += np.bincount(faces[:, k], weights=n[:, c] * w, minlength=len(acc))
    length = np.linalg.norm(acc, axis=-1, keepdims=True)
    return np.where(length > 0, acc / np.where(length > 0, length, 1.0), [0.0, 0.0, 1.0])


def _mesh(positions, faces, uv=None, normals=None) -> Mesh:
    import jax.numpy as jnp

    if normals is None:
        normals = angle_weighted_normals(positions, faces)
    return Mesh(jnp.asarray(positions, jnp.float32), jnp.asarray(faces, jnp.int32),
                None if uv is None else jnp.asarray(uv, jnp.float32),
                jnp.asarray(normals, jnp.float32))


def decimate(mesh: Mesh, triangles: int, *, name: str = "HIGH") -> Mesh:
    """``mesh`` welded (`weld`) and simplified to about ``triangles`` triangles by quadric
    edge collapses (``fast_simplification.simplify``), without the slivers the collapses
    leave (triangles of three nearly collinear vertices), with angle-weighted normals and
    no uvs (`unwrap` makes them).

    Raises ValueError (naming ``name``) when ``triangles`` is not below the welded mesh's
    count or is under 4; ImportError without the ``bake`` extra."""
    try:
        import fast_simplification
    except ImportError:
        raise ImportError('decimating needs fast-simplification: pip install -e ".[bake]"'
                          ) from None
    p, f = check_mesh(mesh, name)
    p, f = weld(p, f)
    if isinstance(triangles, bool) or int(triangles) != triangles:
        raise ValueError(f"{name}: decimate's triangles must be an integer, got {triangles!r}")
    if triangles < 4:
        raise ValueError(f"{name}: the decimated mesh needs at least 4 triangles, got "
                         f"{triangles!r}")
    if triangles >= len(f):
        raise ValueError(f"{name}: has {len(f)} triangles (welded), not more than the "
                         f"{int(triangles)} asked for; nothing to decimate")
    q, g = fast_simplification.simplify(p, f.astype(np.int32), target_count=int(triangles))
    q, g = weld(q, np.asarray(g, np.int64))  # (drops any vertex no triangle uses)
    # collapses along a border leave slivers of three collinear vertices: no area in space,
    # some in the uv layout, and rays from them graze HIGH's border edge
    area2 = np.linalg.norm(np.cross(q[g[:, 1]] - q[g[:, 0]], q[g[:, 2]] - q[g[:, 0]]), axis=-1)
    diag = float(np.linalg.norm(np.ptp(q, axis=0)))
    g = g[area2 > 1e-10 * diag * diag]
    q, g = weld(q, g)
    return _mesh(q, g)


def unwrap(mesh: Mesh, *, size: int = 1024, padding: int = 2, name: str = "LOW") -> Mesh:
    """``mesh`` with a uv layout made by xatlas: the welded surface cut into charts and
    packed into one square atlas for a ``size`` map, ``padding`` texels apart (bilinear
    filtering reads no texel of another chart). The charts are scaled to fill 60% of the
    map, less (by 15% at a time) until xatlas packs them into a single atlas: left to
    itself, xatlas sizes the charts for a smaller atlas, and a small mesh's charts then
    cover a fifth of the map. Vertices are split where charts meet; each copy keeps the
    welded surface's angle-weighted normal, so the shading is as smooth as before. Any uvs
    ``mesh`` had are replaced.

    Raises ImportError without the ``bake`` extra."""
    try:
        import xatlas
    except ImportError:
        raise ImportError('unwrapping needs xatlas: pip install -e ".[bake]"') from None
    for what, v, lo in (("size", size, 4), ("padding", padding, 0)):
        if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < lo:
            raise ValueError(f"{name}: unwrap's {what} must be an integer >= {lo}, got {v!r}")
    p, f = check_mesh(mesh, name)
    p, f = weld(p, f)
    normals = angle_weighted_normals(p, f)
    area = 0.5 * float(np.linalg.norm(np.cross(p[f[:, 1]] - p[f[:, 0]], p[f[:, 2]] - p[f[:, 0]]),
                                      axis=-1).sum())
    if not area > 0:
        raise ValueError(f"{name}: every triangle has zero area; nothing to unwrap")
    fill = 0.6
    for _ in range(12):
        atlas = xatlas.Atlas()
        atlas.add_mesh(p.astype(np.float32), f.astype(np.uint32), normals.astype(np.float32))
        pack = xatlas.PackOptions()
        pack.resolution, pack.padding, pack.bilinear = int(size), int(padding), True
        pack.texels_per_unit = float(size * np.sqrt(fill / area))
        atlas.generate(pack_options=pack)
        if atlas.atlas_count == 1:
            break
        fill *= 0.85
    else:
        raise ValueError(f"{name}: xatlas could not pack the charts into one {size}x{size} "
                         "atlas")
    vmap, faces, uv = atlas[0]
    vmap = np.asarray(vmap, np.int64)
    return _mesh(p[vmap], np.asarray(faces, np.int64), np.asarray(uv, np.float64),
                 normals[vmap])
