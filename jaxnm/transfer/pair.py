"""A high-poly mesh's detail baked into a low-poly mesh's normal map, by casting rays, by
fitting the map to HIGH's shading, or both (`bake_mesh_pair`, what ``jaxnm bake`` runs).

**Ray casting** (``"raycast"``) is `jaxnm.transfer.raycast_normal_map`: per texel, HIGH's
normal where a ray from LOW meets it, Blender's selected-to-active bake.

**Fitting** (``"fit"``) asks instead for the map whose *shading* on LOW looks like HIGH's:

1. **Views.** `jaxnm.transfer.views.plan_views` chooses ``views`` views of LOW and
   ``lights`` directional lights for each, so that every texel of LOW's uv chart is seen by
   two views within ``max_angle_deg`` of its normal and lit from three non-coplanar
   directions; the texels seen fewer than twice are reported (`PairBake.unseen_texels`).
2. **Targets.** HIGH is rendered by jaxnm itself from each view (its own interpolated
   normals, no map) and shaded under each light with the material and albedo the map is
   fitted with (`jaxnm.shading.shade`, as `jaxnm.render` shades). A pixel counts where
   both meshes cover it, LOW faces the camera within ``max_angle_deg`` (as the plan
   counted), and the points HIGH and LOW show there are close (within three times the 95th
   percentile of that distance over such pixels: `PairBake.tolerance`), which leaves out
   silhouettes and occlusions a map cannot reproduce.
3. **The fit.** `jaxnm.fit.fit_normal_map` fits LOW's map to those targets in ``frame``
   (MikkTSpace for ``"vertex"``: LOW's tangents are computed once and carried by the
   problem), from the flat map (``"fit"``) or from the ray-cast map (``"both"``, but for
   texels whose rays went astray: `fit_start`). Texels neither in the chart nor sampled by
   any view then get the margin, as the ray-cast map does.

**Scoring** (`jaxnm.transfer.evaluate`) renders every map, and LOW with no map, from views
and under lights the fit never used, against HIGH's render: PSNR, FLIP and the angle between
HIGH's normal and LOW's perturbed normal per pixel (`PairBake.evaluation`).

The library changes no process state; `should_stop` and `on_stage` let a caller (the
command line's Ctrl-C) stop between stages and between fit steps.
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable

import numpy as np

from ..fit import (
    FitOptions,
    FitProblem,
    FitResult,
    FitTarget,
    fit_normal_map,
    prepare,
    seen_texels,
)
from ..frames import FRAMES
from ..geometry import Mesh, bounding_sphere
from ..shading import Material
from ..textures import NormalMapOptions
from ._meshes import check_mesh, inside_out, prepare_low, warn_overlap, with_normals
from ._surfaces import directional_lights, facing, pair_mask, pair_tolerance, shade_lights, surface
from ._texels import extend_margin, rasterize_uv
from .evaluate import PairEvaluation, evaluate_maps
from .raycast import RAYCAST_FRAMES, RaycastBake, raycast_normal_map
from .views import ViewPlan, held_out_views, plan_views

__all__ = ["METHODS", "PairBakeOptions", "PairBake", "bake_mesh_pair", "bake_material",
           "pair_fit_problem", "fit_pair_map", "fit_start", "START_MAX_TILT_DEG",
           "RENDER_SIZES"]

#: What `bake_mesh_pair` can run: ray casting, fitting, or a fit that starts from the rays.
METHODS = ("raycast", "fit", "both")

#: The sides a view's image may have, in pixels (`PairBakeOptions.render_size`, or the map's
#: larger side when that is None), smallest and largest.
RENDER_SIZES = (16, 8192)


def bake_material() -> Material:
    """The material maps are fitted and scored with: a white diffuse surface with a weak,
    broad highlight (specular 0.15, shininess 24) and no ambient term, under the albedo
    `PairBakeOptions.albedo`."""
    import jax.numpy as jnp

    return Material(diffuse=jnp.ones(3), specular=jnp.full(3, 0.15),
                    shininess=jnp.asarray(24.0), ambient=jnp.zeros(3))


@dataclasses.dataclass(frozen=True)
class PairBakeOptions:
    """How `bake_mesh_pair` bakes (validated when constructed).

    - `method`: one of `METHODS` (default ``"both"``).
    - `size`: the map's side, or ``(height, width)``.
    - `frame`: the tangent frame the map is for, one of `jaxnm.frames.FRAMES` but
      ``"none"`` (``"vertex"``: MikkTSpace); ray casting bakes for `RAYCAST_FRAMES` only.
    - `cage`, `max_distance`, `samples`, `margin`: ray casting's
      (`jaxnm.transfer.raycast_normal_map`); `margin` also fills the fitted map around the
      islands.
    - `views`, `lights`, `render_size`, `candidates`, `max_angle_deg`: the fit's views
      (`jaxnm.transfer.views.plan_views`); `render_size` None is the map's larger side.
    - `fit`: the solver's `jaxnm.fit.FitOptions`.
    - `shading`, `albedo`: the shading model and the constant albedo targets are rendered
      and maps fitted and scored with (the material is `bake_material`).
    - `eval_views`, `eval_lights`: held-out views and lights per view that score every map
      (`jaxnm.transfer.evaluate`); 0 views: no scores.
    """

    method: str = "both"
    size: int | tuple[int, int] = 512
    frame: str = "vertex"
    cage: float | None = None
    max_distance: float = 0.0
    samples: int = 1
    margin: int = 16
    views: int = 12
    lights: int = 4
    render_size: int | None = None
    candidates: int = 48
    max_angle_deg: float = 60.0
    fit: FitOptions = FitOptions(max_steps=12, lsmr_steps=10)
    shading: str = "blinn_phong"
    albedo: float = 0.8
    eval_views: int = 4
    eval_lights: int = 2

    def __post_init__(self):
        if self.method not in METHODS:
            raise ValueError(f"PairBakeOptions: method must be one of {', '.join(METHODS)}, "
                             f"got {self.method!r}")
        if self.frame not in FRAMES or self.frame == "none":
            raise ValueError(f"PairBakeOptions: frame must be one of "
                             f"{', '.join(f for f in FRAMES if f != 'none')}, got {self.frame!r}")
        if self.method != "fit" and self.frame not in RAYCAST_FRAMES:
            raise ValueError(f"PairBakeOptions: frame {self.frame!r}: ray casting bakes for "
                             f"the frames {', '.join(RAYCAST_FRAMES)} only (method 'fit' fits "
                             "a map for any frame)")
        hw = self.map_size
        if len(hw) != 2 or not all(isinstance(s, (int, np.integer)) and s >= 4 for s in hw):
            raise ValueError(f"PairBakeOptions: size must be an integer >= 4 or a pair of "
                             f"them, got {self.size!r}")
        for name, lo in (("views", 0 if self.method == "raycast" else 1),
                         ("lights", 1), ("candidates", 1), ("eval_views", 0),
                         ("eval_lights", 1), ("samples", 1), ("margin", 0)):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < lo:
                raise ValueError(f"PairBakeOptions: {name} must be an integer >= {lo}, got "
                                 f"{v!r}")
        rs, (lo, hi) = self.render_size, RENDER_SIZES
        if rs is not None and (isinstance(rs, bool) or not isinstance(rs, (int, np.integer))
                               or not lo <= rs <= hi):
            raise ValueError(f"PairBakeOptions: render_size must be an integer in [{lo}, {hi}] "
                             f"or None, got {rs!r}")
        renders = self.eval_views or (self.method != "raycast" and self.views)
        if rs is None and renders and not lo <= max(hw) <= hi:
            raise ValueError(f"PairBakeOptions: size {self.size!r}: without a render_size, "
                             f"each view's image takes the map's larger side, which must then "
                             f"be {lo} to {hi} pixels")
        if not 0 < self.max_angle_deg < 90:
            raise ValueError(f"PairBakeOptions: max_angle_deg must be in (0, 90), got "
                             f"{self.max_angle_deg!r}")
        if not (math.isfinite(self.albedo) and 0 < self.albedo <= 1):
            raise ValueError(f"PairBakeOptions: albedo must be in (0, 1], got {self.albedo!r}")

    @property
    def map_size(self) -> tuple[int, int]:
        """``(h, w)`` of the map."""
        s = self.size
        return (s, s) if np.ndim(s) == 0 else tuple(s)

    @property
    def views_render_size(self) -> int:
        """The side of every view's image: `render_size`, or the map's larger side."""
        return int(self.render_size or max(self.map_size))


@dataclasses.dataclass
class PairBake:
    """What `bake_mesh_pair` made. Maps are ``(h, w, 3)`` float32 unit tangent-space normals
    in image layout (row 0 on top, uv origin at the bottom left), signed, for `frame`.

    - `maps`: by method, ``"raycast"`` and/or ``"fit"``.
    - `raycast`: the `RaycastBake` (None without ray casting).
    - `fit`: the `jaxnm.fit.FitResult` (None without a fit); `plan`: its `ViewPlan`.
    - `unseen_texels`: chart texels seen by fewer than two views (None without a fit).
    - `fit_seen`: ``(h, w)`` bool, the texels the fit's views sample (None without a fit).
    - `evaluation`: the held-out scores (`jaxnm.transfer.evaluate.PairEvaluation`), or
      None when skipped.
    - `low`: LOW as baked for (normals, and MikkTSpace tangents for ``"vertex"``).
    - `options`, `frame`; `timings`: seconds per stage; `seconds`: in all.
    - `tolerance`: the distance within which HIGH's and LOW's points count as the same
      pixel in the fit's targets (None without a fit).
    - `interrupted`: `should_stop` ended the bake early; `skipped`: what was left out.
    """

    maps: dict
    raycast: RaycastBake | None
    fit: FitResult | None
    plan: ViewPlan | None
    unseen_texels: int | None
    fit_seen: np.ndarray | None
    evaluation: PairEvaluation | None
    low: Mesh
    options: PairBakeOptions
    frame: str
    timings: dict
    seconds: float
    tolerance: float | None = None
    interrupted: bool = False
    skipped: list = dataclasses.field(default_factory=list)


class _Clock:
    """Seconds per stage, and the caller's stage callback."""

    def __init__(self, on_stage):
        self.timings: dict[str, float] = {}
        self.on_stage = on_stage
        self.stage = None
        self.t = time.perf_counter()

    def start(self, stage: str, message: str) -> None:
        self.stop()
        if self.on_stage is not None:
            self.on_stage(stage, message)
        self.stage, self.t = stage, time.perf_counter()

    def stop(self) -> None:
        if self.stage is not None:
            self.timings[self.stage] = round(self.timings.get(self.stage, 0.0)
                                             + time.perf_counter() - self.t, 3)
        self.stage = None


def _fit_targets(high: Mesh, low: Mesh, plan: ViewPlan,
                 options: PairBakeOptions) -> tuple[list[FitTarget], float]:
    """The fit's targets (step 2 of the module) and the distance tolerance of their masks."""
    r = plan.render_size
    material, albedo = bake_material(), np.full(3, options.albedo, np.float32)
    pairs = []
    for cam in plan.cameras:
        pairs.append((surface(high, cam, r, source="HIGH"),
                      surface(low, cam, r, uv=True, source="LOW")))
    tolerance = pair_tolerance(pairs, options.max_angle_deg)
    targets = []
    for k, (hi, lo) in enumerate(pairs):
        mask = pair_mask(hi, lo, tolerance) & facing(lo, options.max_angle_deg)
        if not mask.any():
            continue
        images = shade_lights(hi, plan.lights[k], material, albedo, options.shading)
        for j, d in enumerate(plan.lights[k]):
            targets.append(FitTarget(plan.cameras[k], r, r, directional_lights(d[None]),
                                     images[j], mask=mask, name=f"view{k}_light{j}"))
    return targets, tolerance


def pair_fit_problem(low: Mesh, targets, options: PairBakeOptions, *,
                     source: str = "LOW") -> FitProblem:
    """The `jaxnm.fit.FitProblem` of fitting LOW's map to ``targets`` for ``options`` (its
    frame, map size, material, albedo and shading). The map is sampled bilinearly, without
    mip levels: a pixel then moves only the four texels around its uv, so texels that no
    pixel samples at full resolution keep their start (through a trilinear filter's coarse
    levels, a fit moves texels no view shows, in ways other views see)."""
    return FitProblem(mesh=low, material=bake_material(), targets=tuple(targets),
                      map_size=options.map_size, albedo=np.full(3, options.albedo, np.float32),
                      shading=options.shading, frame=options.frame, derivatives="fine",
                      sampling=NormalMapOptions(encoding="signed", filter="bilinear"),
                      source=source)


#: A ray-cast normal tilted further than this from its texel's normal does not start a fit.
START_MAX_TILT_DEG = 75.0


def fit_start(normals: np.ndarray) -> np.ndarray:
    """The map a fit starts from, made from a ray-cast one: each texel's normal, or the
    flat ``(0, 0, 1)`` where it is tilted more than `START_MAX_TILT_DEG` from it. Such
    normals come from rays that hit HIGH's far side or another part (an ear in front of the
    head: facing into LOW's surface, ``z < 0``); as slopes ``(x, y) / z`` they are huge,
    where the shading's derivatives vanish, and a fit from them stays there (on the
    Stanford Bunny, 843 such texels kept a fit from the rays at three times the loss the fit
    from flat reached)."""
    n = np.asarray(normals, np.float32)
    steep = n[..., 2] < math.cos(math.radians(START_MAX_TILT_DEG))
    return np.where(steep[..., None], np.float32([0.0, 0.0, 1.0]), n)


def fit_pair_map(problem: FitProblem, options: PairBakeOptions, start: np.ndarray | None,
                 chart: np.ndarray, *, should_stop=None, progress: bool | str = False,
                 on_compiled: Callable[[], None] | None = None):
    """Fit ``problem``'s map from ``start`` (None: flat); returns the `FitResult`, the map
    with the margin around what the views sample (``chart`` or `seen_texels`) and those
    texels."""
    from ..fit import compile_fit

    prep = prepare(problem)
    compile_fit(problem, options.fit, prepared=prep)
    if on_compiled is not None:
        on_compiled()
    result = fit_normal_map(problem, options.fit, prepared=prep, progress=progress,
                            start=start, should_stop=(None if should_stop is None else
                                                      lambda rec: bool(should_stop())))
    seen = seen_texels(prep, options.map_size)
    vals, filled = extend_margin(result.normals, chart | seen, options.margin)
    n = np.where(filled[..., None], vals, [0.0, 0.0, 1.0])
    n = n / np.linalg.norm(n, axis=-1, keepdims=True)
    return result, n.astype(np.float32), seen


def _check_call(options, cage_mesh, progress, on_stage, should_stop) -> None:
    """`bake_mesh_pair`'s arguments, checked before any work."""
    if not isinstance(options, PairBakeOptions):
        raise TypeError(f"bake_mesh_pair: options must be a PairBakeOptions, got "
                        f"{type(options).__name__}")
    if cage_mesh is not None and options.method == "fit":
        raise ValueError("bake_mesh_pair: cage_mesh is for ray casting, and options.method "
                         "'fit' casts no rays")
    if progress not in (True, False, "lines"):
        raise ValueError(f"bake_mesh_pair: progress must be True, False or 'lines', got "
                         f"{progress!r}")
    for what, f in (("on_stage", on_stage), ("should_stop", should_stop)):
        if f is not None and not callable(f):
            raise TypeError(f"bake_mesh_pair: {what} must be a function or None, got "
                            f"{type(f).__name__}")


def bake_mesh_pair(high: Mesh, low: Mesh, options: PairBakeOptions = PairBakeOptions(), *,
                   cage_mesh: Mesh | None = None, high_name: str = "HIGH",
                   low_name: str = "LOW", cage_name: str = "cage mesh",
                   on_stage: Callable[[str, str], None] | None = None,
                   should_stop: Callable[[], bool] | None = None,
                   progress: bool | str = False) -> PairBake:
    """Bake HIGH's detail into a tangent-space normal map on LOW's uv layout, by
    `options.method` (the module docstring says how), and score the maps under held-out
    views and lights.

    **Arguments:**
    - `high`, `low`: the meshes (LOW with uvs; normals are computed where missing).
    - `options`: a `PairBakeOptions`.
    - `cage_mesh`: a cage with LOW's triangles, in LOW's order, for the rays (instead of
      `options.cage`; `raycast_normal_map`'s).
    - `high_name`, `low_name`, `cage_name`: for messages (the files).
    - `on_stage`: called as ``on_stage(stage, message)`` before each stage (``"inputs"``,
      ``"raycast"``, ``"plan"``, ``"targets"``, ``"prepare"``, ``"fit"``,
      ``"evaluate"``); an exception it raises ends the bake.
    - `should_stop`: polled after every fit step and between the scoring's views; once it
      returns True the fit ends after its step and the scoring is left out
      (`PairBake.interrupted`).
    - `progress`: the fit's progress on stderr (`jaxnm.fit.fit_normal_map`'s).

    **Returns:** a `PairBake`. Raises ValueError for unusable input (naming the mesh) and
    when the meshes do not overlap; warns (`BakeWarning`) about missed rays, overlapping uv
    islands, uvs outside the unit square and degenerate or non-manifold triangles.
    """
    _check_call(options, cage_mesh, progress, on_stage, should_stop)
    t0 = time.perf_counter()
    clock = _Clock(on_stage)
    o = options
    stop = should_stop or (lambda: False)
    clock.start("inputs", f"checking {high_name} and {low_name} ...")
    check_mesh(high, high_name)
    high = with_normals(high, high_name)
    raycast = None
    if o.method == "fit":  # (ray casting checks LOW itself, with the same messages)
        low = prepare_low(low, o.frame, low_name)
        warn_overlap(rasterize_uv(np.asarray(low.uv), np.asarray(low.faces), o.map_size),
                     low_name)
    else:
        clock.start("raycast", f"casting rays from {low_name}'s {o.map_size[1]}x"
                               f"{o.map_size[0]} texels to {high_name} ...")
        raycast = raycast_normal_map(high, low, o.map_size, frame=o.frame, cage=o.cage,
                                     cage_mesh=cage_mesh, max_distance=o.max_distance,
                                     samples=o.samples, margin=o.margin,
                                     high_name=high_name, low_name=low_name,
                                     cage_name=cage_name)
        low = with_normals(low, low_name)
        if o.frame == "vertex" and low.tangents is None:
            low = low.with_tangents()
    result = PairBake(maps={}, raycast=raycast, fit=None, plan=None, unseen_texels=None,
                      fit_seen=None, evaluation=None, low=low, options=o, frame=o.frame,
                      timings=clock.timings, seconds=0.0)
    if raycast is not None:
        result.maps["raycast"] = raycast.normals
    try:
        if o.method != "raycast":
            _fit_stage(result, high, low, clock, stop, progress, (high_name, low_name))
        if stop():
            result.interrupted = True
            result.skipped.append("evaluation")
        elif o.eval_views > 0:
            clock.start("evaluate", f"scoring the maps under {o.eval_views} held-out views x "
                                    f"{o.eval_lights} lights ...")
            result.evaluation = _evaluate(result, high, low, stop)
            if result.evaluation is None:
                result.interrupted = True
                result.skipped.append("evaluation")
    finally:
        clock.stop()
    result.seconds = time.perf_counter() - t0
    return result


def _fit_stage(result: PairBake, high, low, clock: _Clock, stop, progress, names) -> None:
    """Steps 1 to 3 of the module: plan, targets, fit; the results go into ``result``."""
    o = result.options
    r = o.views_render_size
    clock.start("plan", f"planning {o.views} views of {names[1]} ({o.candidates} candidates "
                        f"at {r}x{r}) ...")
    plan = plan_views(low, o.map_size, views=o.views, lights=o.lights, render_size=r,
                      candidates=o.candidates, max_angle_deg=o.max_angle_deg, high=high)
    result.plan, result.unseen_texels = plan, plan.unseen
    clock.start("targets", f"rendering {names[0]} from {len(plan.cameras)} views under "
                           f"{o.lights} lights ...")
    targets, result.tolerance = _fit_targets(high, low, plan, o)
    if not targets and inside_out(*check_mesh(low, names[1])):
        raise ValueError(f"{names[1]}: no view shows its front faces over {names[0]}: they "
                         "wind inwards (a closed mesh of negative volume); reverse their "
                         "winding")
    if not targets:
        raise ValueError(f"{names[0]} and {names[1]} do not overlap: no view shows both at "
                         "the same place; are both in the same space and units?")
    clock.start("prepare", f"preparing the fit ({len(targets)} targets) ...")
    problem = pair_fit_problem(low, targets, o, source=names[1])
    start = fit_start(result.maps["raycast"]) if o.method == "both" else None

    def compiled():
        clock.start("fit", f"fitting the {o.map_size[1]}x{o.map_size[0]} map "
                           f"({'from the ray-cast map' if start is not None else 'from flat'})"
                           " ...")

    fit, n, seen = fit_pair_map(problem, o, start, plan.chart, should_stop=stop,
                                progress=progress, on_compiled=compiled)
    result.fit, result.fit_seen = fit, seen
    result.maps["fit"] = n
    if fit.stopped == "interrupted":
        result.interrupted = True


def _evaluate(result: PairBake, high, low, stop) -> PairEvaluation | None:
    """The held-out scores of ``result``'s maps (None when stopped)."""
    o = result.options
    if result.plan is not None:
        centre, radius, used = result.plan.centre, result.plan.radius, result.plan.directions
    else:
        (centre, radius), used = bounding_sphere(low, high), np.zeros((0, 3))
    cams, lights = held_out_views(centre, radius, used, o.eval_views, o.eval_lights, low=low)
    return evaluate_maps(high, low, result.maps, cams, lights, frame=o.frame,
                         size=o.views_render_size, map_size=o.map_size,
                         material=bake_material(), albedo=np.full(3, o.albedo, np.float32),
                         shading=o.shading, should_stop=stop)
