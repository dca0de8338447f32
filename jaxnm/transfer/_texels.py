"""Texels of a uv layout: which triangle holds each texel centre, and the margin around the
islands (shared by the bakers of `jaxnm.transfer`).

Maps are in image layout (row 0 on top, uv origin at the bottom left): texel (row r,
column c) of an h x w map sits at ``u = (c + 1/2) / w``, ``v = 1 - (r + 1/2) / h``.
"""

from __future__ import annotations

import dataclasses

import numpy as np

__all__ = ["TexelCover", "rasterize_uv", "extend_margin", "extend_margin_texels", "uv_box"]

#: Candidate (texel, triangle) pairs tested at once: bounds the memory of `rasterize_uv`.
_CANDIDATES = 1 << 18
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


def _affine(corners: np.ndarray, hw: tuple[int, int]):
    """Per triangle, in texel coordinates (texel column c, row j from the bottom, has its
    centre at ``(c, j)``): the corners ``(F, 3, 2)``, and the barycentrics of corners 1 and
    2 as affine functions ``l = a x + b y + c``, ``(F, 2, 3)``; zero-area triangles get
    none (their rows are skipped)."""
    h, w = hw
    q = np.stack([corners[..., 0] * w - 0.5, corners[..., 1] * h - 0.5], -1)
    e1, e2 = q[:, 1] - q[:, 0], q[:, 2] - q[:, 0]
    det = e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]
    ok = det != 0
    d = np.where(ok, det, 1.0)
    # l1 = ((p - q0) x e2) / det, l2 = (e1 x (p - q0)) / det
    a1, b1 = e2[:, 1] / d, -e2[:, 0] / d
    a2, b2 = -e1[:, 1] / d, e1[:, 0] / d
    c1 = -(a1 * q[:, 0, 0] + b1 * q[:, 0, 1])
    c2 = -(a2 * q[:, 0, 0] + b2 * q[:, 0, 1])
    return q, np.stack([np.stack([a1, b1, c1], -1), np.stack([a2, b2, c2], -1)], 1), ok


def _row_spans(q: np.ndarray, faces_idx: np.ndarray, h: int, w: int):
    """The (triangle, row, first column, count) spans of texel centres that a group of
    triangles may hold: per row through a triangle, the columns between the crossings of
    its edges with the row's centre line (widened by `_EDGE_TOLERANCE`)."""
    t = q[faces_idx]
    y0 = np.maximum(np.ceil(t[..., 1].min(1) - _EDGE_TOLERANCE), 0).astype(np.int64)
    y1 = np.minimum(np.floor(t[..., 1].max(1) + _EDGE_TOLERANCE), h - 1).astype(np.int64)
    rows = np.maximum(y1 - y0 + 1, 0)
    f = np.repeat(np.arange(len(faces_idx)), rows)
    j = y0[f] + np.arange(f.size) - np.repeat(np.cumsum(rows) - rows, rows)
    lo = np.full(f.size, np.inf)
    hi = np.full(f.size, -np.inf)
    for k in range(3):
        p, r = t[f, k], t[f, (k + 1) % 3]
        dy = r[:, 1] - p[:, 1]
        flat = dy == 0
        s = np.clip((j - p[:, 1]) / np.where(flat, 1.0, dy), 0.0, 1.0)
        x = p[:, 0] + s * (r[:, 0] - p[:, 0])
        lo = np.minimum(lo, np.where(flat, np.minimum(p[:, 0], r[:, 0]), x))
        hi = np.maximum(hi, np.where(flat, np.maximum(p[:, 0], r[:, 0]), x))
    c0 = np.maximum(np.ceil(lo - 1e-6), 0).astype(np.int64)
    c1 = np.minimum(np.floor(hi + 1e-6), w - 1).astype(np.int64)
    return faces_idx[f], j, c0, np.maximum(c1 - c0 + 1, 0)


def _candidates(faces_idx, q, coef, hw):
    """The (texel, triangle, barycentrics) pairs of a group of triangles whose centre lies
    in the triangle (closed, with `_EDGE_TOLERANCE`)."""
    h, w = hw
    f, j, c0, n = _row_spans(q, faces_idx, h, w)
    k = coef[f]  # per span: each barycentric's ``a c + b j + c``, ``b j`` once per span
    (a1, bj1, c1), (a2, bj2, c2) = ((k[:, i, 0], k[:, i, 1] * j, k[:, i, 2]) for i in (0, 1))
    f, j = np.repeat(f, n), np.repeat(j, n)
    c = np.repeat(c0, n) + np.arange(f.size) - np.repeat(np.cumsum(n) - n, n)
    l1 = np.repeat(a1, n) * c + np.repeat(bj1, n) + np.repeat(c1, n)
    l2 = np.repeat(a2, n) * c + np.repeat(bj2, n) + np.repeat(c2, n)
    l0 = 1.0 - l1 - l2
    ok = (l0 >= -_EDGE_TOLERANCE) & (l1 >= -_EDGE_TOLERANCE) & (l2 >= -_EDGE_TOLERANCE)
    l0, l1, l2 = (np.clip(x[ok], 0.0, 1.0) for x in (l0, l1, l2))
    total = l0 + l1 + l2
    bary = np.stack([l0 / total, l1 / total, l2 / total], -1)
    return (h - 1 - j[ok]) * w + c[ok], f[ok], bary  # image layout: row 0 on top


def rasterize_uv(uv: np.ndarray, faces: np.ndarray, hw: tuple[int, int]) -> TexelCover:
    """Find, for every texel centre of an ``hw = (h, w)`` map, the triangle of the uv layout
    ``(uv[faces])`` that holds it and its barycentrics there (see `TexelCover`).

    Vectorised over the spans of texel centres each triangle crosses row by row, in groups
    of triangles that hold about `_CANDIDATES` texels; zero-area uv triangles hold none.
    """
    h, w = hw
    corners = np.asarray(uv, np.float64)[np.asarray(faces)]
    q, coef, ok = _affine(corners, hw)
    e1, e2 = q[:, 1] - q[:, 0], q[:, 2] - q[:, 0]
    texels = np.abs(e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]) / 2 + 2 * np.ptp(q[..., 1], 1)
    order = np.flatnonzero(ok)
    cum = np.cumsum(texels[order] + 2)  # about the texels (and rows) each triangle holds
    face = np.full(h * w, -1, np.int64)
    bary = np.zeros((h * w, 3))
    strict = np.zeros(h * w, np.int32)
    start = 0
    while start < len(order):  # groups of triangles in index order: the highest index wins
        base = cum[start - 1] if start else 0
        stop = max(start + 1, int(np.searchsorted(cum, base + _CANDIDATES, side="right")))
        texel, f, b = _candidates(order[start:stop], q, coef, hw)
        start = stop
        np.maximum.at(face, texel, f)  # texels of several triangles: the highest index
        win = f == face[texel]  # one per texel: a triangle holds a texel once
        bary[texel[win]] = b[win]
        inner = (b[:, 0] > _STRICT) & (b[:, 1] > _STRICT) & (b[:, 2] > _STRICT)
        np.add.at(strict, texel[inner], np.int32(1))
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

    Each pass visits only the texels next to the last pass's (a band around the islands).

    **Returns:** the values ``(h, w, C)`` and the mask of assigned texels after the passes.
    """
    h, w = mask.shape
    index = np.flatnonzero(mask)
    out = np.array(values, np.float64).reshape(h * w, -1)  # unassigned texels keep theirs
    filled, filled_vals = extend_margin_texels(index, out[index], (h, w), margin)
    out[filled] = filled_vals
    done = np.zeros(h * w, bool)
    done[filled] = True
    return out.reshape(h, w, -1), done.reshape(h, w)


def extend_margin_texels(index: np.ndarray, values: np.ndarray, hw: tuple[int, int],
                         margin: int) -> tuple[np.ndarray, np.ndarray]:
    """`extend_margin` of the texels ``index`` (flat image indices) holding ``values``
    ``(n, C)``, the others unassigned: the assigned texels after the passes (flat image
    indices, ascending) and their values, without maps of the whole image's values."""
    h, w = hw
    stride = w + 2  # a padded grid: the border's neighbours exist and are never assigned
    in_map = np.zeros((h + 2, stride), bool)
    in_map[1:-1, 1:-1] = True
    in_map = in_map.ravel()
    index = np.asarray(index, np.int64)
    padded = index + 2 * (index // w) + stride + 1
    done = np.zeros((h + 2) * stride, bool)
    done[padded] = True
    vals = np.zeros(((h + 2) * stride, values.shape[-1]))
    vals[padded] = values
    edges = np.array([-1, 1, -stride, stride])
    corners = np.array([-stride - 1, -stride + 1, stride - 1, stride + 1])
    near = np.zeros_like(done)
    for o in edges:  # the padding keeps np.roll from wrapping an assigned texel in
        near |= np.roll(done, o)
    cand = np.flatnonzero(near & in_map & ~done)
    for _ in range(int(margin)):
        if cand.size == 0:
            break
        acc = np.zeros((cand.size, vals.shape[-1]))
        wsum = np.zeros(cand.size)
        for offsets, weight in ((edges, 2.0), (corners, 1.0)):
            for o in offsets:
                m = done[cand + o]
                acc += np.where(m[:, None], weight * vals[cand + o], 0.0)
                wsum += weight * m
        vals[cand] = acc / wsum[:, None]
        done[cand] = True
        cand = np.unique((cand[:, None] + edges[None]).ravel())
        cand = cand[in_map[cand] & ~done[cand]]
    padded = np.flatnonzero(done)
    r, c = np.divmod(padded, stride)
    return (r - 1) * w + (c - 1), vals[padded]


def uv_box(mask: np.ndarray) -> tuple[float, float, float, float] | None:
    """The uv bounding box ``(u0, v0, u1, v1)`` of the texel centres in ``mask`` (image
    layout), or None when it is empty."""
    r, c = np.nonzero(mask)
    if r.size == 0:
        return None
    h, w = mask.shape
    return ((c.min() + 0.5) / w, 1.0 - (r.max() + 0.5) / h, (c.max() + 0.5) / w,
            1.0 - (r.min() + 0.5) / h)
