"""Diagnostics of a fit: which texels the views see, how strongly, whether the lights can
determine a normal (identifiability), and the error measures."""

from __future__ import annotations

import math
import warnings

import numpy as np

from .. import textures as _tex
from ._processes import local_rows
from .prepare import Prepared
from .problem import FitWarning

__all__ = ["seen_texels", "texel_influence", "angular_error", "check_identifiability",
           "error_report", "psnr"]


def seen_texels(prep: Prepared, map_size: tuple[int, int], *,
                min_weight: float = 0.25) -> np.ndarray:
    """(h, w) bool: texels that some view samples at the finest mip level with total filter
    weight >= ``min_weight`` (i.e. that directly influence at least part of a pixel)."""
    h, w = map_size
    acc = np.zeros(h * w)
    for b in prep.batches:
        used = (local_rows(b.weights)[1].max(1)[..., 0] > 0)[..., None]  # (V, K, 1)
        idx, wt = local_rows(b.gbuffer.plan.index)[1], local_rows(b.gbuffer.plan.weight)[1]
        keep = (idx < h * w) & used  # level 0 texels come first in the flat index
        acc += np.bincount(idx[keep], weights=wt[keep], minlength=h * w)
    return _summed(prep, acc).reshape(h, w) >= min_weight


def _summed(prep: Prepared, acc: np.ndarray) -> np.ndarray:
    """``acc`` summed over the processes ``prep``'s views are spread over (itself if none)."""
    from ._processes import sum_over_processes
    from .distributed import spread_over_processes

    return sum_over_processes(acc) if spread_over_processes(prep) else acc


#: Pixels per piece of `texel_influence`'s sums.
_INFLUENCE_ROWS = 1 << 16


def texel_influence(prep: Prepared) -> np.ndarray:
    """(h, w) float32: each texel's total filter weight over all used pixels, views and
    targets.

    The column sums of the (fixed) texel-to-pixel sampling operator, mip levels included
    (a coarser level's texel passes its weight down through the transpose of
    `jaxnm.textures.build_mipmaps`' box filter); used to precondition the solve (see
    `fit_normal_map`). Computed on the host in float64: as an XLA program (the sampling's
    VJP) it would cost a compilation per problem shape, long on a GPU with deterministic
    ops.
    """
    h, w = prep.options[0].normal_map_shape
    shapes = _tex.mip_sizes((h, w), prep.options[0].levels)
    sizes = [a * b for a, b in shapes]
    acc = np.zeros(sum(sizes))
    for b in prep.batches:
        used = local_rows(b.weights)[1].sum(1, dtype=np.float64)[..., 0].reshape(-1)
        idx = local_rows(b.gbuffer.plan.index)[1]
        idx = idx.reshape(-1, idx.shape[-1])  # (pixels of every view, taps)
        weight = local_rows(b.gbuffer.plan.weight)[1].reshape(idx.shape)
        # in pieces: float64 copies of a large batch's taps at once would be the fit's peak
        # memory. Each piece's count is as long as the levels, so a piece is never much
        # shorter
        rows = max(_INFLUENCE_ROWS, acc.size // idx.shape[1])
        for k in range(0, idx.shape[0], rows):
            wt = weight[k:k + rows].astype(np.float64) * used[k:k + rows, None]
            acc += np.bincount(idx[k:k + rows].ravel(), weights=wt.ravel(),
                               minlength=acc.size)
    levels = np.split(_summed(prep, acc), np.cumsum(sizes)[:-1])
    grad = levels[-1].reshape(shapes[-1])
    for k in range(len(shapes) - 2, -1, -1):  # coarse to fine: through each filter
        hk, wk = shapes[k]
        grad = (_tex.box_filter_matrix(hk).T @ grad @ _tex.box_filter_matrix(wk)
                + levels[k].reshape(hk, wk))
    return grad.astype(np.float32)


def angular_error(a, b) -> np.ndarray:
    """Per-texel angle in degrees between two normal maps (..., 3), computed in float64 as
    ``atan2(|a x b|, a . b)`` (accurate for small angles, unlike ``arccos``)."""
    a = np.asarray(a, np.float64)
    b = np.asarray(b, np.float64)
    return np.degrees(np.arctan2(np.linalg.norm(np.cross(a, b), axis=-1), np.sum(a * b, -1)))


def check_identifiability(prep: Prepared, *, warn: bool = True,
                          source: str = "fit") -> dict:
    """How well the targets can determine a normal map; warns (`FitWarning`, the message
    starting with ``source``, the fit file's name) when they cannot.

    Counts, per view, the lights and the rank of their directions as seen from
    the object (a point light's direction is taken towards the centroid of the
    visible surface). Returns a dict with the counts and the verdict.
    """
    report = {"views": []}
    ok_any = False
    per_view = {}
    for v in prep.local_views():
        view = prep.view(v)
        centre = np.asarray(view.gbuffer.position).mean(0)
        dirs = []
        lt = view.lights
        if lt.directional is not None:
            d = np.asarray(lt.directional.direction).reshape(-1, 3)
            dirs += list(d / np.linalg.norm(d, axis=-1, keepdims=True))
        if lt.point is not None:
            p = np.asarray(lt.point.position).reshape(-1, 3) - centre
            dirs += list(p / np.maximum(np.linalg.norm(p, axis=-1, keepdims=True), 1e-12))
        dirs = np.asarray(dirs)
        unique = np.unique(np.round(dirs, 6), axis=0) if len(dirs) else dirs
        rank = int(np.linalg.matrix_rank(unique, tol=1e-3)) if len(unique) else 0
        per_view[v] = {"targets": int(view.images.shape[0]),
                       "distinct_light_directions": int(len(unique)), "direction_rank": rank}
    from ._processes import allgather_json
    from .distributed import spread_over_processes

    if spread_over_processes(prep):  # every process's views
        for part in allgather_json({str(v): rec for v, rec in per_view.items()}):
            per_view.update({int(v): rec for v, rec in part.items()})
    for v in sorted(per_view):
        report["views"].append(per_view[v])
        ok_any |= per_view[v]["direction_rank"] >= 3
    report["identifiable"] = bool(ok_any)
    if warn and not ok_any:
        warnings.warn(
            f"{source}: no view has at least three lights with non-coplanar directions; one light "
            "cannot determine a normal (it only fixes the angle to the light) and two leave a "
            "two-fold ambiguity: the fitted map is not determined by these targets",
            FitWarning, stacklevel=2)
    return report


def psnr(a: np.ndarray, b: np.ndarray, mask: np.ndarray | None = None, peak: float | None = None
         ) -> float:
    """Peak signal-to-noise ratio in dB (peak = max of ``b`` by default) over ``mask``."""
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    if mask is not None:
        a, b = a[mask], b[mask]
    peak = float(b.max()) if peak is None else peak
    mse = float(np.mean((a - b) ** 2))
    return math.inf if mse == 0 else 10 * math.log10(peak * peak / mse)


def error_report(fitted: np.ndarray, gt: np.ndarray, seen: np.ndarray) -> dict:
    """Mean / median / 95th percentile angular error (degrees) over the seen texels."""
    err = angular_error(fitted, gt)
    e = err[seen]
    return {"seen_texels": int(seen.sum()), "total_texels": int(seen.size),
            "mean_deg": float(e.mean()), "median_deg": float(np.median(e)),
            "p95_deg": float(np.percentile(e, 95)), "max_deg": float(e.max())}


