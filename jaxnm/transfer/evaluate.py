"""Scores of baked maps against the high-poly mesh they stand for, from views and under
lights a fit never used (`evaluate_maps`).

Per held-out view, HIGH and LOW are rendered by jaxnm (`jaxnm.render`), LOW once per map and
once with no map (the floor every map should beat), and shaded under each of the view's
lights with the bake's material (`jaxnm.shading.shade`). A pixel is scored where both meshes
cover it and the points they show lie within the tolerance of each other (by default three
times the 95th percentile of that distance over the held-out views' pixels, as the bake's
targets count it). Per method:

- **PSNR** of the linear colour against HIGH's over every scored pixel and channel of every
  held-out image together, the peak being 1 (white): ``10 log10(1 / MSE)``.
- **FLIP** (NVIDIA's FLIP, the ``flip-evaluator`` package, LDR, 67 pixels per degree) of the
  sRGB images (`jaxnm.shading.to_display`), the test image taking the reference's pixels
  where it is not scored, averaged over the scored pixels of every image.
- **The normal's angle** between HIGH's shading normal (interpolated, face-forwarded) and
  LOW's perturbed normal per scored pixel, ``atan2(|a x b|, a . b)`` in float64: mean,
  median and 95th percentile, and per texel (the texel LOW's uv falls in) the mean over the
  pixels that show it, NaN where none does.
"""

from __future__ import annotations

import dataclasses
import math
import time

import numpy as np

from ..geometry import Mesh
from ..shading import Material, to_display
from ..textures import NormalMapOptions
from ._surfaces import angles_deg, pair_mask, pair_tolerance, shade_lights, surface

__all__ = ["MethodScores", "PairEvaluation", "evaluate_maps", "flip_error", "pooled_psnr",
           "texel_means", "NO_MAP"]

#: The name of LOW rendered with no map in the scores.
NO_MAP = "none"


def flip_error(reference: np.ndarray, test: np.ndarray) -> np.ndarray:
    """``(H, W)`` FLIP error of the sRGB image ``test`` against ``reference`` (both
    ``(H, W, 3)`` in [0, 1]): NVIDIA's FLIP for LDR images at its default 67 pixels per
    degree (``flip-evaluator``, the ``bake`` extra)."""
    try:
        import flip_evaluator
    except ImportError:
        raise ImportError('FLIP scores need flip-evaluator: pip install -e ".[bake]"') from None
    err, _, _ = flip_evaluator.evaluate(np.array(reference, np.float32, order="C"),
                                        np.array(test, np.float32, order="C"), "LDR",
                                        inputsRGB=True, applyMagma=False,
                                        computeMeanError=False)
    return np.asarray(err, np.float32).reshape(reference.shape[:2])


def pooled_psnr(sq_error_sum: float, count: int) -> float:
    """``10 log10(1 / MSE)`` for a sum of squared errors over ``count`` values (peak 1)."""
    if count == 0:
        return math.nan
    mse = sq_error_sum / count
    return math.inf if mse == 0 else -10.0 * math.log10(mse)


def texel_means(values: np.ndarray, uv: np.ndarray, map_size: tuple[int, int]):
    """Per texel of a ``map_size`` map (image layout), the sum and count of ``values`` (N,)
    at the points of uv ``uv`` (N, 2) (each the texel its uv falls in, wrapped)."""
    h, w = map_size
    u, v = np.mod(uv[:, 0], 1.0), np.mod(uv[:, 1], 1.0)
    idx = (np.minimum(((1.0 - v) * h).astype(np.int64), h - 1) * w
           + np.minimum((u * w).astype(np.int64), w - 1))
    return (np.bincount(idx, weights=values, minlength=h * w),
            np.bincount(idx, minlength=h * w))


def _finite(x: float, digits: int) -> float | None:
    """``x`` rounded, or None where it is not finite (JSON has no NaN or infinity)."""
    return round(float(x), digits) if math.isfinite(x) else None


@dataclasses.dataclass
class MethodScores:
    """One map's held-out scores (see the module docstring).

    - `psnr_db`, `flip`: over every held-out image; `per_image`: ``{"view", "light",
      "psnr_db", "flip"}`` each.
    - `angle_mean_deg`, `angle_median_deg`, `angle_p95_deg`: over every scored pixel of
      every view.
    - `texel_error_deg`: ``(h, w)`` float32 mean angle per texel, NaN where no pixel shows it.
    """

    psnr_db: float
    flip: float
    angle_mean_deg: float
    angle_median_deg: float
    angle_p95_deg: float
    texel_error_deg: np.ndarray
    per_image: list

    def summary(self) -> dict:
        """The scores as a JSON-ready dict (no per-texel map; a score that is not finite,
        e.g. where no pixel was scored, or the PSNR of identical images, is None)."""
        return {"psnr_db": _finite(self.psnr_db, 3), "flip": _finite(self.flip, 5),
                "angle_mean_deg": _finite(self.angle_mean_deg, 4),
                "angle_median_deg": _finite(self.angle_median_deg, 4),
                "angle_p95_deg": _finite(self.angle_p95_deg, 4),
                "texels_scored": int(np.isfinite(self.texel_error_deg).sum()),
                "per_image": self.per_image}


@dataclasses.dataclass
class PairEvaluation:
    """`evaluate_maps`' result.

    - `methods`: `MethodScores` by name: `NO_MAP` and each map's.
    - `views`: ``(E, 3)`` camera positions; `lights`: ``(E, L, 3)`` light directions;
      `size`: the images' side; `tolerance`: the mask's distance; `pixels`: scored pixels
      per view.
    - `example`: for the first view and light, sRGB images by name (``"high"`` and each
      method), each method's FLIP map and angle map (degrees), and the mask.
    - `seconds`: the time it took.
    """

    methods: dict
    views: np.ndarray
    lights: np.ndarray
    size: int
    tolerance: float
    pixels: list
    example: dict
    seconds: float

    def summary(self) -> dict:
        """A JSON-ready dict of everything but the arrays."""
        return {"views": np.round(self.views, 6).tolist(),
                "lights": np.round(self.lights, 6).tolist(), "image_size": self.size,
                "tolerance": self.tolerance, "scored_pixels_per_view": self.pixels,
                "seconds": round(self.seconds, 3),
                "methods": {k: v.summary() for k, v in self.methods.items()}}


class _Tally:
    """Running sums of one method's scores over the views."""

    def __init__(self, map_size):
        self.sq, self.count, self.flip_sum, self.flip_count = 0.0, 0, 0.0, 0
        self.angles: list[np.ndarray] = []
        self.tex_sum = np.zeros(map_size[0] * map_size[1])
        self.tex_count = np.zeros(map_size[0] * map_size[1])
        self.per_image: list[dict] = []
        self.map_size = map_size

    def add(self, k, ref, test, ref_srgb, mask, angles, uv, example) -> None:
        for j in range(ref.shape[0]):
            diff = (test[j] - ref[j])[mask].astype(np.float64)
            sq = float(np.sum(diff * diff))
            test_srgb = np.asarray(to_display(np.where(mask[..., None], test[j], ref[j])))
            f = flip_error(ref_srgb[j], test_srgb)
            self.sq += sq
            self.count += diff.size
            self.flip_sum += float(f[mask].sum(dtype=np.float64))
            self.flip_count += int(mask.sum())
            self.per_image.append({
                "view": k, "light": j, "psnr_db": _finite(pooled_psnr(sq, diff.size), 3),
                "flip": _finite(float(f[mask].mean()) if mask.any() else math.nan, 5)})
            if example is not None and j == 0:
                example["image"], example["flip"] = test_srgb, f
        self.angles.append(angles[mask])
        s, c = texel_means(angles[mask], uv[mask].astype(np.float64), self.map_size)
        self.tex_sum += s
        self.tex_count += c

    def scores(self) -> MethodScores:
        a = np.concatenate(self.angles) if self.angles else np.zeros(0)
        with np.errstate(invalid="ignore", divide="ignore"):
            tex = np.where(self.tex_count > 0, self.tex_sum / self.tex_count, np.nan)
        return MethodScores(
            psnr_db=pooled_psnr(self.sq, self.count),
            flip=self.flip_sum / self.flip_count if self.flip_count else math.nan,
            angle_mean_deg=float(a.mean()) if a.size else math.nan,
            angle_median_deg=float(np.median(a)) if a.size else math.nan,
            angle_p95_deg=float(np.percentile(a, 95)) if a.size else math.nan,
            texel_error_deg=tex.reshape(self.map_size).astype(np.float32),
            per_image=self.per_image)


def evaluate_maps(high: Mesh, low: Mesh, maps: dict, cameras, lights: np.ndarray, *,
                  frame: str, size: int, map_size: tuple[int, int], material: Material,
                  albedo, shading: str,
                  tolerance: float | None = None,
                  sampling: NormalMapOptions = NormalMapOptions(encoding="signed"),
                  should_stop=None) -> PairEvaluation | None:
    """Score each map of ``maps`` (name -> ``(h, w, 3)`` signed unit tangent-space normals
    for ``frame``), and LOW with no map (`NO_MAP`), against HIGH (the module docstring says
    how).

    **Arguments:**
    - `high`, `low`: the meshes, with normals (LOW with uvs, and tangents for ``"vertex"``).
    - `cameras`: the held-out views (square images of `size`); `lights`: ``(E, L, 3)``
      directions towards each view's lights.
    - `map_size`: ``(h, w)`` of the per-texel error maps.
    - `material`, `albedo`, `shading`: as the targets were shaded.
    - `tolerance`: the mask's distance (None: measured, see the module docstring).
    - `sampling`: how the maps are sampled (signed, trilinear by default).
    - `should_stop`: polled between views; True ends the scoring (returns None).

    **Returns:** a `PairEvaluation`, or None when stopped.
    """
    t0 = time.perf_counter()
    map_size = tuple(int(s) for s in map_size)
    base = [(surface(high, cam, size, source="HIGH"),
             surface(low, cam, size, uv=True, source="LOW")) for cam in cameras]
    tol = pair_tolerance(base) if tolerance is None else float(tolerance)
    names = [NO_MAP] + list(maps)
    tallies = {name: _Tally(map_size) for name in names}
    example: dict = {}
    pixels = []
    for k, (cam, (hi, plain)) in enumerate(zip(cameras, base, strict=True)):
        if should_stop is not None and should_stop():
            return None
        mask = pair_mask(hi, plain, tol)
        pixels.append(int(mask.sum()))
        ref = shade_lights(hi, lights[k], material, albedo, shading)
        ref_srgb = np.asarray(to_display(ref))
        if k == 0:
            example.update(high=ref_srgb[0], mask=mask)
        for name in names:
            lo = plain if name == NO_MAP else surface(
                low, cam, size, frame=frame, normal_map=maps[name], sampling=sampling,
                source="LOW")
            test = shade_lights(lo, lights[k], material, albedo, shading)
            ang = angles_deg(hi.normal, lo.normal)
            ex = {} if k == 0 else None
            tallies[name].add(k, ref, test, ref_srgb, mask, ang, plain.uv, ex)
            if ex is not None:
                example[name] = {"image": ex["image"], "flip": ex["flip"],
                                 "angle": np.where(mask, ang, np.nan).astype(np.float32)}
    return PairEvaluation(methods={n: t.scores() for n, t in tallies.items()},
                          views=np.array([np.asarray(c.eye, np.float64) for c in cameras]),
                          lights=np.asarray(lights, np.float64), size=int(size),
                          tolerance=tol, pixels=pixels, example=example,
                          seconds=time.perf_counter() - t0)
