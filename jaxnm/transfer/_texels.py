"""Texels of a uv layout: which triangle holds each texel centre, and the margin around the
islands (shared by the bakers of `jaxnm.transfer`).

Maps are in image layout (row 0 on top, uv origin at the bottom left): texel (row r,
column c) of an h x w map sits at ``u = (c + 1/2) / w``, ``v = 1 - (r + 1/2) / h``.
"""

from __future__ import annotations

import dataclasses

import numpy as np

__all__ = ["TexelCover", "rasterize_uv", "extend_margin", "uv_box"]

#: Candidate (texel, triangle) pairs tested at once: bounds the memory of `rasterize_uv`.
_CANDIDATES = 1 << 22
#: A texel centre this close outside a triangle (in barycentric units) still belongs to it,
#: so that rounding never opens a crack along an edge two triangles share.
_EDGE_TOLERANCE = 1e-9
#: Barycentrics above this mark a texel as strictly inside a triangle (overlap counting).
_STRICT = 1e-6


@dataclasses.dataclass(frozen=True)
class TexelCover:
    """The triangles of a uv layout over a map's texel centres.

    **Fields:**
    - `face`: ``(h, w)`` int32 index of the triangle holding each texel centre (-1: none).
      Where triangles overlap the one with the highest index holds it (Blender draws the
      triangles in order, each over the last).
    - `bary`: ``(h, w, 3)`` float64 barycentrics of the texel centre in that triangle.
    - `overlapping`: ``(h, w)`` bool, texels strictly inside two or more triangles.
    - `overlap_faces`: for the first overlapping texel, the triangles that hold it (the
      last one wins), or an empty tuple.
    """

    face: np.ndarray
    bary: np.ndarray
    overlapping: np.ndarray
    overlap_faces: tuple[int, ...]


def _face_boxes(corners: np.ndarray, hw: tuple[int, int]):
    """Per triangle: the texel-centre box its uv bounding box spans (columns and rows
    counted from the bottom), and whether it has a uv area."""
    h, w = hw
    x = corners[..., 0] * w - 0.5  # texel column c has its centre at x = c
    y = corners[..., 1] * h - 0.5  # row j from the bottom has its centre at y = j
    c0 = np.maximum(np.ceil(x.min(1) - _EDGE_TOLERANCE), 0).astype(np.int64)
    c1 = np.minimum(np.floor(x.max(1) + _EDGE_TOLERANCE), w - 1).astype(np.int64)
    j0 = np.maximum(np.ceil(y.min(1) - _EDGE_TOLERANCE), 0).astype(np.int64)
    j1 = np.minimum(np.floor(y.max(1) + _EDGE_TOLERANCE), h - 1).astype(np.int64)
    e1, e2 = corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]
    area = e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]
    count = np.where((c1 >= c0) & (j1 >= j0) & (area != 0), (c1 - c0 + 1) * (j1 - j0 + 1), 0)
    return c0, j0, c1 - c0 + 1, count, area


def _candidates(faces_idx, c0, j0, bw, count, corners, area, hw):
    """The (texel, triangle, barycentrics) pairs of a group of triangles whose centre lies in
    the triangle (closed, with `_EDGE_TOLERANCE`)."""
    h, w = hw
    n = count[faces_idx]
    f = np.repeat(faces_idx, n)
    start = np.repeat(np.cumsum(n) - n, n)
    k = np.arange(f.size) - start
    c = c0[f] + k % bw[f]
    j = j0[f] + k // bw[f]
    u = (c + 0.5) / w
    v = (j + 0.5) / h
    a, b, cc = corners[f, 0], corners[f, 1], corners[f, 2]
    du, dv = u - a[:, 0], v - a[:, 1]
    l1 = (du * (cc[:, 1] - a[:, 1]) - (cc[:, 0] - a[:, 0]) * dv) / area[f]
    l2 = ((b[:, 0] - a[:, 0]) * dv - du * (b[:, 1] - a[:, 1])) / area[f]
    l0 = 1.0 - l1 - l2
    ok = (l0 >= -_EDGE_TOLERANCE) & (l1 >= -_EDGE_TOLERANCE) & (l2 >= -_EDGE_TOLERANCE)
    bary = np.clip(np.stack([l0, l1, l2], -1)[ok], 0.0, 1.0)
    bary /= bary.sum(-1, keepdims=True)
    texel = (h - 1 - j[ok]) * w + c[ok]  # image layout: row 0 on top
    return texel, f[ok], bary


def rasterize_uv(uv: np.ndarray, faces: np.ndarray, hw: tuple[int, int]) -> TexelCover:
    """Find, for every texel centre of an ``hw = (h, w)`` map, the triangle of the uv layout
    ``(uv[faces])`` that holds it and its barycentrics there (see `TexelCover`).

    Vectorised over the texels of each triangle's bounding box, in groups of at most
    `_CANDIDATES` pairs; zero-area uv triangles hold no texel.
    """
    h, w = hw
    corners = np.asarray(uv, np.float64)[np.asarray(faces)]
    c0, j0, bw, count, area = _face_boxes(corners, hw)
    face = np.full(h * w, -1, np.int64)
    bary = np.zeros((h * w, 3))
    strict = np.zeros(h * w, np.int32)
    order = np.flatnonzero(count)
    cum = np.cumsum(count[order])
    start = 0
    while start < len(order):  # groups of triangles in index order: the highest index wins
        base = cum[start - 1] if start else 0
        stop = max(start + 1, int(np.searchsorted(cum, base + _CANDIDATES, side="right")))
        texel, f, b = _candidates(order[start:stop], c0, j0, bw, count, corners, area, hw)
        start = stop
        np.maximum.at(face, texel, f)
        win = f == face[texel]
        bary[texel[win]] = b[win]
        np.add.at(strict, texel[np.all(b > _STRICT, -1)], 1)
    overlap_faces: tuple[int, ...] = ()
    if np.any(strict > 1):
        hold = _holders(int(np.argmax(strict > 1)), corners, hw)
        overlap_faces = tuple(int(i) for i in hold)
    return TexelCover(face.reshape(h, w).astype(np.int32), bary.reshape(h, w, 3),
                      (strict > 1).reshape(h, w), overlap_faces)


def _holders(texel: int, corners: np.ndarray, hw: tuple[int, int]) -> np.ndarray:
    """The triangles whose interior holds texel ``texel`` (image-layout index)."""
    h, w = hw
    r, c = divmod(int(texel), w)
    p = np.array([(c + 0.5) / w, 1.0 - (r + 0.5) / h])
    a, b, cc = corners[:, 0], corners[:, 1], corners[:, 2]

    def side(p0, p1):
        return (p1[:, 0] - p0[:, 0]) * (p[1] - p0[:, 1]) - (p1[:, 1] - p0[:, 1]) * (p[0] - p0[:, 0])

    s = np.stack([side(a, b), side(b, cc), side(cc, a)], -1)
    return np.flatnonzero(np.all(s > 0, -1) | np.all(s < 0, -1))


def extend_margin(values: np.ndarray, mask: np.ndarray, margin: int) -> tuple[np.ndarray,
                                                                             np.ndarray]:
    """Blender's "extend" margin (``IMB_filter_extend``, the margin type Blender forces for
    tangent-space normal bakes): ``margin`` passes, in each of which every texel outside
    ``mask`` with an assigned texel among its four edge neighbours takes the weighted mean
    of the assigned texels among its eight neighbours (weight 2 across an edge, 1 across a
    corner), and counts as assigned from the next pass on. Texels beyond the map's border
    do not count.

    **Returns:** the values ``(h, w, C)`` and the mask of assigned texels after the passes.
    """
    vals = np.array(values, np.float64, copy=True)
    done = np.array(mask, bool, copy=True)
    h, w = done.shape
    for _ in range(int(margin)):
        pad_m = np.pad(done, 1)
        pad_v = np.pad(vals * done[..., None], ((1, 1), (1, 1), (0, 0)))
        edge = (pad_m[:-2, 1:-1] | pad_m[2:, 1:-1] | pad_m[1:-1, :-2] | pad_m[1:-1, 2:])
        todo = ~done & edge
        if not todo.any():
            break
        acc = np.zeros_like(vals)
        wsum = np.zeros((h, w))
        for di in (-1, 0, 1):
            for dj in (-1, 0, 1):
                if di == dj == 0:
                    continue
                wt = 2.0 if di == 0 or dj == 0 else 1.0
                sl = (slice(1 + di, h + 1 + di), slice(1 + dj, w + 1 + dj))
                acc += wt * pad_v[sl]
                wsum += wt * pad_m[sl]
        vals[todo] = acc[todo] / wsum[todo][:, None]
        done = done | todo
    return vals, done


def uv_box(mask: np.ndarray) -> tuple[float, float, float, float] | None:
    """The uv bounding box ``(u0, v0, u1, v1)`` of the texel centres in ``mask`` (image
    layout), or None when it is empty."""
    r, c = np.nonzero(mask)
    if r.size == 0:
        return None
    h, w = mask.shape
    return ((c.min() + 0.5) / w, 1.0 - (r.max() + 0.5) / h, (c.max() + 0.5) / w,
            1.0 - (r.min() + 0.5) / h)
