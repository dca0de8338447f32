r"""Fit a tangent-space normal map to target shading.

Given a mesh with uvs, one or more views, lights, a material and target images,
find the normal map whose rendering matches the targets.

**Model.** The geometry is fixed, so each view's G-buffer — visibility, the
perspective-correct position, uv, normal, their screen derivatives, the
cotangent frame and the normal map's sample plan (texel indices, filter
weights, mip level of detail) — is computed **once** (`prepare`), and kept
only for the pixels the mesh covers, as a flat list. A step then only runs
the texel-dependent stages on those pixels: build the mip chain of the current
map (once, for all views), one gather and weighted sum per pixel (4 taps
where the fixed level of detail reads a single mip level, 8 elsewhere),
perturb, shade, subtract the target. Views and their lights are batched with
``vmap`` (views padded to a common pixel and target count; views whose lights
differ in kind or count form separate batches, see `ViewBatch`).

**Parameterisation.** Each texel holds two slopes ``(s_x, s_y)``; its normal is
``normalize(s_x, s_y, 1)``: always a unit vector with positive z, with no
constraint to enforce and no singular point.

**Solvers** (optimistix): ``"lm"`` Levenberg–Marquardt and ``"gn"``
Gauss–Newton, both matrix-free: the Jacobian is a linearised function
(forward-mode JVP, transposed for the VJP) and each step is solved by
lineax's iterative LSMR — no dense Jacobian is ever formed; ``"lbfgs"``:
the first-order baseline, L-BFGS on the sum of squares.

**Identifiability.** A normal has two degrees of freedom. One light gives one
equation per texel (a cone of possible normals); two lights leave a two-fold
ambiguity; three lights whose directions (as seen from the surface) are not
coplanar determine the normal under Lambertian shading (photometric stereo).
So a fit needs at least three non-coplanar lights per texel, in some view that
sees it lit; `check_identifiability` warns otherwise. Texels in attached
shadow for most lights, or seen only at grazing angles (only coarse mip
levels), are weakly determined; the optional smoothness term regularises them.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import math
import signal
import time
import warnings
from collections.abc import Sequence
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx
import numpy as np
import optimistix as optx
from jax import Array

from . import textures as _tex
from .camera import Camera
from .frames import perturb_normal
from .geometry import Mesh
from .numerics import angle_between, materialize, safe_normalize
from .render import GBuffer, RenderOptions, build_gbuffer, check_mesh
from .scene import NormalMapOptions, Scene
from .shading import DirectionalLight, Lights, Material, shade

__all__ = [
    "FitWarning",
    "default_problem",
    "default_light_directions",
    "directional_light",
    "view_relative",
    "psnr",
    "error_report",
    "texel_influence",
    "validate_problem",
    "FitTarget",
    "FitProblem",
    "FitOptions",
    "FitResult",
    "Prepared",
    "ViewBatch",
    "SOLVERS",
    "prepare",
    "fit_normal_map",
    "slopes_to_normals",
    "normals_to_slopes",
    "angular_error",
    "seen_texels",
    "check_identifiability",
    "render_with_map",
]

SOLVERS = ("lm", "gn", "lbfgs")


class FitWarning(UserWarning):
    """The fit input is suspicious (e.g. cannot determine the map)."""


@dataclasses.dataclass(frozen=True)
class FitTarget:
    """One target image: a view (camera + size), its lights, the image and an optional mask.

    ``image`` is **linear** RGB (H, W, 3), row 0 = top; ``mask`` (H, W) bool
    selects the pixels that count (default: all the mesh covers).
    """

    camera: Camera
    width: int
    height: int
    lights: Lights
    image: np.ndarray
    mask: np.ndarray | None = None
    name: str = ""


@dataclasses.dataclass(frozen=True)
class FitProblem:
    """The scene side of a fit: mesh, material, albedo, render options, targets, map size."""

    mesh: Mesh
    material: Material
    targets: tuple[FitTarget, ...]
    map_size: tuple[int, int] = (256, 256)
    albedo: np.ndarray = dataclasses.field(
        default_factory=lambda: np.array([0.8, 0.8, 0.8], np.float32))
    shading: str = "blinn_phong"
    frame: str = "cotangent"
    derivatives: str = "fine"
    double_sided: bool = True
    sampling: NormalMapOptions = NormalMapOptions(encoding="signed")
    source: str = "<fit problem>"


@dataclasses.dataclass(frozen=True)
class FitOptions:
    """How to fit.

    - `solver`: one of `SOLVERS`.
    - `max_steps`: outer iterations (per coarse-to-fine level).
    - `smoothness`: weight of the first-difference penalty on the slopes
      (residuals ``sqrt(w) * (s[i+1] - s[i])``), 0 to disable.
    - `coarse_to_fine`: number of extra coarser levels solved first (each half
      the resolution), then upsampled as the next level's start.
    - `lsmr_steps`: inner LSMR iterations per (Gauss-Newton/LM) step.
    - `rtol`, `atol`: convergence tolerances of the outer solver.
    - `seed`: initial-guess jitter seed (0 jitter by default: a flat start).
    - `init_noise`: standard deviation of the initial slopes.
    """

    solver: str = "lm"
    max_steps: int = 30
    smoothness: float = 0.0
    coarse_to_fine: int = 0
    lsmr_steps: int = 40
    rtol: float = 1e-6
    atol: float = 1e-8
    seed: int = 0
    init_noise: float = 0.0


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class ViewBatch:
    """Views whose lights have the same kinds and counts, stacked so one ``vmap`` shades them.

    Only the pixels a view's mesh covers take part, as a flat list; views with
    fewer pixels or targets are padded (copies of a real pixel or target with
    weight 0, so padding is NaN-free and changes nothing); views are batched
    only when padding at most doubles a view's pixels. ``V`` views, ``T``
    targets, ``K`` pixels each:

    - `gbuffer`: the G-buffer of those pixels, every field (V, K, ...) (the
      eye (V, 3)).
    - `pixels`: (V, K) int32 row-major pixel indices into the view's image,
      -1 for padding.
    - `images`: (V, T, K, 3) linear targets; `weights`: (V, T, K, 1), 0
      outside a target's mask and for padding.
    - `lights`: `Lights` with leaves (V, T, ...): one (stacked) light per target.
    - `views` (static): the view indices (into `Prepared.options`) of the rows;
      `targets` (static): each view's real number of targets.
    - `split` (static): the first ``split`` pixels of every view read a single
      mip level (4 non-zero filter taps: magnified texels, or the coarsest
      level), the rest two (8 taps); the step gathers each group with only the
      taps it needs.
    """

    gbuffer: GBuffer
    pixels: Array
    images: Array
    weights: Array
    lights: Lights
    views: tuple[int, ...] = dataclasses.field(metadata=dict(static=True))
    targets: tuple[int, ...] = dataclasses.field(metadata=dict(static=True))
    split: int = dataclasses.field(metadata=dict(static=True), default=0)


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Prepared:
    """Everything a fit step needs, computed once (see `prepare`).

    A view is one camera (with its image size); each of its targets is one
    image under one (stacked) light. ``batches`` group the views into
    `ViewBatch` stacks; ``options[v]`` are view ``v``'s render options (they
    differ only in image size). `target_images`, `target_mask` and `view`
    give per-view, image-layout access.
    """

    batches: tuple[ViewBatch, ...]
    material: Material
    options: tuple[RenderOptions, ...] = dataclasses.field(metadata=dict(static=True))

    @property
    def num_views(self) -> int:
        return len(self.options)

    def view(self, v: int) -> _View:
        """View ``v`` unpadded: its G-buffer (K_v, ...), pixels, targets and lights."""
        for b in self.batches:
            if v in b.views:
                i = b.views.index(v)
                keep = np.flatnonzero(np.asarray(b.pixels[i]) >= 0)
                t = b.targets[i]
                gb = _map_pixels(jax.tree_util.tree_map(lambda x: x[i], b.gbuffer),
                                 lambda x: x[keep])
                return _View(gb, b.pixels[i][keep], b.images[i, :t][:, keep],
                             b.weights[i, :t][:, keep],
                             jax.tree_util.tree_map(lambda x: x[i, :t], b.lights))
        raise IndexError(f"fit: no view {v} (the problem has {self.num_views})")

    def to_image(self, v: int, values: Array) -> Array:
        """Per-pixel ``values`` (..., K_v, C) of `view` ``v`` in image layout (..., H, W, C),
        0 off the mesh."""
        o = self.options[v]
        pix = self.view(v).pixels
        values = jnp.asarray(values)
        out = jnp.zeros(values.shape[:-2] + (o.height * o.width, values.shape[-1]), values.dtype)
        out = out.at[..., pix, :].set(values)
        return out.reshape(values.shape[:-2] + (o.height, o.width, values.shape[-1]))

    def target_images(self, v: int) -> np.ndarray:
        """(T_v, H, W, 3) linear targets of view ``v`` (0 where the mesh is not)."""
        return np.asarray(self.to_image(v, self.view(v).images))

    def target_mask(self, v: int, t: int = 0) -> np.ndarray:
        """(H, W) bool: the pixels that count for target ``t`` of view ``v``."""
        return np.asarray(self.to_image(v, self.view(v).weights[t]))[..., 0] > 0


@dataclasses.dataclass(frozen=True)
class _View:
    """One view, unpadded: ``gbuffer`` (K, ...), ``pixels`` (K,), ``images`` (T, K, 3),
    ``weights`` (T, K, 1), ``lights`` (leaves (T, ...))."""

    gbuffer: GBuffer
    pixels: Array
    images: Array
    weights: Array
    lights: Lights


@dataclasses.dataclass
class FitResult:
    """The fitted map and how the fit went.

    ``normals``: (h, w, 3) unit tangent-space normals (image layout, x along
    +u, y along +v, the decoded convention); ``slopes``: (h, w, 2);
    ``history``: one dict per step (step, loss, seconds, and the angular
    error when a ground truth was given); ``stopped``: why it ended.
    """

    normals: np.ndarray
    slopes: np.ndarray
    history: list
    seconds: float
    stopped: str
    best_loss: float


# --------------------------------------------------------------------------------------
# parameterisation
# --------------------------------------------------------------------------------------


def slopes_to_normals(slopes: Array) -> Array:
    """``normalize(s_x, s_y, 1)`` per texel: (h, w, 2) -> (h, w, 3) unit, z > 0."""
    one = jnp.ones(slopes.shape[:-1] + (1,), slopes.dtype)
    return safe_normalize(jnp.concatenate([slopes, one], -1))


def normals_to_slopes(normals: Array, max_slope: float = 1e3) -> Array:
    """Inverse of `slopes_to_normals` for normals with z > 0 (clamped to ``max_slope``)."""
    n = jnp.asarray(normals)
    z = jnp.maximum(n[..., 2:3], 1.0 / max_slope)
    return jnp.clip(n[..., :2] / z, -max_slope, max_slope)


# --------------------------------------------------------------------------------------
# preparation (once per fit)
# --------------------------------------------------------------------------------------


def _stack_lights(lights: Sequence[Lights]) -> Lights:
    structs = {jax.tree_util.tree_structure(light) for light in lights}
    shapes = {tuple(x.shape for x in jax.tree_util.tree_leaves(light)) for light in lights}
    if len(structs) != 1 or len(shapes) != 1:
        raise ValueError("fit: all targets of one view must have lights of the same kinds and "
                         "counts (e.g. each one directional light), so they can be batched")
    return jax.tree_util.tree_map(lambda *x: jnp.stack(x), *lights)


def _view_key(t: FitTarget):
    return (t.width, t.height, np.asarray(t.camera.view).tobytes(),
            np.asarray(t.camera.projection).tobytes())


def validate_problem(problem: FitProblem) -> None:
    """Raise a clear error for unusable input, before anything is compiled."""
    src = problem.source
    if problem.mesh.uv is None:
        raise ValueError(f"{src}: the mesh has no texture coordinates (uv); a normal map cannot "
                         "be fitted")
    if problem.mesh.normals is None:
        raise ValueError(f"{src}: the mesh has no vertex normals")
    if not problem.targets:
        raise ValueError(f"{src}: no target images")
    h, w = problem.map_size
    if not (isinstance(h, int) and isinstance(w, int) and h >= 2 and w >= 2):
        raise ValueError(f"{src}: the map size must be two integers >= 2, got {problem.map_size}")
    for i, t in enumerate(problem.targets):
        name = t.name or f"target {i}"
        img = np.asarray(t.image)
        if img.ndim != 3 or img.shape[2] != 3:
            raise ValueError(f"{src}: {name}: the target must be an RGB image (H, W, 3), got "
                             f"shape {img.shape}")
        if img.shape[:2] != (t.height, t.width):
            raise ValueError(f"{src}: {name}: the target is {img.shape[1]}x{img.shape[0]} but "
                             f"its camera renders {t.width}x{t.height}")
        if not np.all(np.isfinite(img)):
            raise ValueError(f"{src}: {name}: the target has NaN or infinite values")
        if t.lights is None or (t.lights.directional is None and t.lights.point is None):
            raise ValueError(f"{src}: {name}: no lights")
        if t.mask is not None:
            m = np.asarray(t.mask)
            if m.shape != (t.height, t.width):
                raise ValueError(f"{src}: {name}: the mask is {m.shape[::-1]}, expected "
                                 f"{(t.width, t.height)}")
            if not m.any():
                raise ValueError(f"{src}: {name}: the mask covers nothing")


def prepare(problem: FitProblem) -> Prepared:
    """Rasterize every view once and stack its targets (see `Prepared`)."""
    validate_problem(problem)
    groups: dict = {}
    for t in problem.targets:
        groups.setdefault(_view_key(t), []).append(t)
    views, opts_all = [], []
    nm = dataclasses.replace(problem.sampling, encoding="signed", channels=3)
    for ts in groups.values():
        t0 = ts[0]
        opts = RenderOptions(width=t0.width, height=t0.height, derivatives=problem.derivatives,
                             frame=problem.frame, shading=problem.shading,
                             double_sided=problem.double_sided, normal_map=nm,
                             normal_map_shape=tuple(problem.map_size),
                             albedo_shape=(tuple(np.asarray(problem.albedo).shape[:2])
                                           if np.asarray(problem.albedo).ndim == 3 else None),
                             outputs=("color",))
        check_mesh(problem.mesh, opts, problem.source)
        gb = build_gbuffer(problem.mesh, t0.camera, jnp.asarray(problem.albedo), opts=opts)
        cover = np.asarray(gb.mask)
        ws = []
        for i, t in enumerate(ts):
            m = cover if t.mask is None else (cover & np.asarray(t.mask, bool))
            if not m.any():
                raise ValueError(f"{problem.source}: {t.name or 'a target'}: the mask and the "
                                 "mesh's silhouette do not overlap")
            ws.append(m[..., None].astype(np.float32))
        pix = np.flatnonzero(cover).astype(np.int32)
        flat = lambda x: x.reshape((-1,) + x.shape[2:])[pix]  # noqa: E731
        views.append(_View(_map_pixels(gb, flat), jnp.asarray(pix),
                           jnp.asarray(np.stack([flat(np.asarray(t.image, np.float32))
                                                 for t in ts])),
                           jnp.asarray(np.stack([flat(w) for w in ws])),
                           _stack_lights([t.lights for t in ts])))
        opts_all.append(opts)
    return _assemble(views, tuple(opts_all), problem.material)


def _map_pixels(gb: GBuffer, fn) -> GBuffer:
    """Apply ``fn`` to every per-pixel field of ``gb`` (all but the eye position)."""
    out = jax.tree_util.tree_map(fn, dataclasses.replace(gb, eye=None))
    return dataclasses.replace(out, eye=gb.eye)


def _light_key(lights: Lights):
    leaves, tree = jax.tree_util.tree_flatten(lights)
    return tree, tuple(x.shape[1:] for x in leaves)


def _assemble(views: Sequence[_View], options: tuple[RenderOptions, ...],
              material: Material) -> Prepared:
    """Order each view's pixels by the taps they need, pad, and stack views into batches.

    A trilinear plan always has 8 taps, but where the level of detail is
    clamped (magnification, or the coarsest level) or integral, the second
    level's 4 weights are exactly 0. The geometry is fixed, so this is known
    once; gathering those pixels with 4 taps halves their gather and its
    transpose (the scatter-add that dominates the backward pass). Views whose
    lights have the same structure share one batch (see `ViewBatch`), unless
    padding a view to the batch's largest would more than double its pixels.
    """
    by_lights: dict = {}
    for v, view in enumerate(views):
        by_lights.setdefault(_light_key(view.lights), []).append(v)
    size = [view.pixels.shape[0] for view in views]
    groups = []  # by decreasing pixel count; a new batch where padding would double the work
    for members in by_lights.values():
        members = sorted(members, key=lambda v: -size[v])
        batch = [members[0]]
        for v in members[1:]:
            if 2 * size[v] >= size[batch[0]]:
                batch.append(v)
            else:
                groups.append(batch)
                batch = [v]
        groups.append(batch)
    batches = []
    for members in groups:
        eight = views[members[0]].gbuffer.plan.num_taps == 8
        parts = []  # per view: (indices of its one-level pixels, of the others)
        for v in members:
            w = np.asarray(views[v].gbuffer.plan.weight)
            one = np.all(w[:, 4:] == 0, axis=-1) if eight else np.zeros(len(w), bool)
            parts.append((np.flatnonzero(one), np.flatnonzero(~one)))
        ka = max(len(a) for a, _ in parts)
        kb = max(len(b) for _, b in parts)
        t_max = max(views[v].images.shape[0] for v in members)
        rows = []
        for v, (a, b) in zip(members, parts):
            view = views[v]
            fill = int(a[0] if len(a) else b[0])  # a real pixel, copied into the padding
            order = np.concatenate([a, np.full(ka - len(a), fill), b, np.full(kb - len(b), fill)])
            real = np.concatenate([np.ones(len(a), bool), np.zeros(ka - len(a), bool),
                                   np.ones(len(b), bool), np.zeros(kb - len(b), bool)])
            t = view.images.shape[0]
            tsel = np.minimum(np.arange(t_max), t - 1)  # padded targets repeat the last one
            weights = view.weights[tsel][:, order] * jnp.asarray(
                real[None, :, None] & (np.arange(t_max) < t)[:, None, None], jnp.float32)
            rows.append(dict(
                gbuffer=_map_pixels(view.gbuffer, lambda x: x[order]),
                pixels=jnp.where(jnp.asarray(real), view.pixels[order], -1),
                images=view.images[tsel][:, order], weights=weights,
                lights=jax.tree_util.tree_map(lambda x: x[tsel], view.lights)))
        stacked = jax.tree_util.tree_map(lambda *x: jnp.stack(x), *rows)
        batches.append(ViewBatch(**stacked, views=tuple(members),
                                 targets=tuple(views[v].images.shape[0] for v in members),
                                 split=ka if eight else 0))
    return Prepared(tuple(batches), material, options)


# --------------------------------------------------------------------------------------
# the per-step model
# --------------------------------------------------------------------------------------


def _mips(normals: Array, opts: RenderOptions) -> tuple[Array, ...]:
    return _tex.build_mipmaps(normals, levels=opts.levels) if opts.levels > 1 else (normals,)


def _pixel_colors(m: Array, gb: GBuffer, lights: Lights, material: Material, shading: str,
                  strength) -> Array:
    """(T, K, 3): each stacked light's shading of the per-pixel map vectors ``m`` (K, 3)."""
    m = m * jnp.stack([strength, strength, jnp.ones_like(strength)]).astype(m.dtype)[None]
    n = perturb_normal(gb.frame, m)
    return jax.vmap(lambda lt: shade(shading, n, gb.position, gb.eye, lt, material,
                                     albedo=gb.albedo))(lights)


@functools.partial(jax.custom_jvp, nondiff_argnums=(4,))
def _pixel_model(m, gb, lights, material, shading, strength):
    """`_pixel_colors` whose JVP in ``m`` is an explicit per-pixel (T, 3, 3) Jacobian.

    Every pixel's colours depend only on that pixel's sampled map vector, so the
    Jacobian w.r.t. ``m`` is block diagonal. Computing the blocks once per
    linearisation (three forward-mode passes) makes every later Jacobian
    product in the iterative solver a tiny einsum instead of a replay of the
    whole shading graph.
    """
    return _pixel_colors(m, gb, lights, material, shading, strength)


@_pixel_model.defjvp
def _pixel_model_jvp(shading, primals, tangents):
    m, gb, lights, material, strength = primals
    dm, dgb, dlights, dmaterial, dstrength = tangents
    f = lambda m_: _pixel_colors(m_, gb, lights, material, shading, strength)  # noqa: E731
    y = f(m)
    basis = jnp.eye(3, dtype=m.dtype)
    blocks = jax.vmap(lambda e: jax.jvp(f, (m,), (jnp.broadcast_to(e, m.shape),))[1])(basis)
    # blocks: (3, T, K, 3) = d colour / d m_k
    out = jnp.einsum("kt...c,...k->t...c", blocks, dm)
    rest = jax.jvp(lambda g, lt, mt, s: _pixel_colors(m, g, lt, mt, shading, s),
                   (gb, lights, material, strength), (dgb, dlights, dmaterial, dstrength))[1]
    return y, out + rest


def _sample_split(plan: _tex.SamplePlan, mips, split: int) -> Array:
    """`apply_plan`, with the first ``split`` pixels gathered from their 4 non-zero taps."""
    if split == 0:
        return _tex.apply_plan(plan, mips)
    head = dataclasses.replace(plan, index=plan.index[:split, :4], weight=plan.weight[:split, :4])
    tail = dataclasses.replace(plan, index=plan.index[split:], weight=plan.weight[split:])
    return jnp.concatenate([_tex.apply_plan(head, mips), _tex.apply_plan(tail, mips)], 0)


def _shade_view(gb: GBuffer, mips, lights: Lights, material: Material, opts: RenderOptions,
                strength, split: int = 0) -> Array:
    """(T, K, 3): the pixels of ``gb`` under each stacked light, with the map's mip chain
    ``mips``."""
    # materialised: fused into the shading, the 8-tap gather would be recomputed per use
    m = materialize(_sample_split(gb.plan, mips, split))
    return _pixel_model(m, gb, lights, material, opts.shading, jnp.asarray(strength, m.dtype))


def _shade_batch(batch: ViewBatch, mips, material: Material, opts: RenderOptions,
                 strength) -> Array:
    """(V, T, K, 3): every view of ``batch`` under each of its lights (``vmap`` over views)."""
    return jax.vmap(lambda gb, lt: _shade_view(gb, mips, lt, material, opts, strength,
                                               batch.split))(batch.gbuffer, batch.lights)


def render_with_map(prep: Prepared, normals: Array, *, strength: float = 1.0,
                    lights: Sequence[Lights] | None = None) -> list[Array]:
    """Render every view of ``prep`` with the map ``normals`` (h, w, 3); one (T, H, W, 3) per view.

    ``lights`` (one stacked `Lights` per view, leaves (T, ...)) replaces the
    prepared lights, e.g. to render from held-out light directions.
    """
    opts = prep.options[0]
    mips = _mips(jnp.asarray(normals), opts)
    out = []
    for v in range(prep.num_views):
        view = prep.view(v)
        lt = view.lights if lights is None else lights[v]
        img = _shade_view(view.gbuffer, mips, lt, prep.material, opts, strength)
        out.append(prep.to_image(v, img))
    return out


def _residuals(z: Array, args) -> tuple[Array, ...]:
    prep, smooth, strength, scale = args
    slopes = z * scale
    opts = prep.options[0]
    mips = _mips(slopes_to_normals(slopes), opts)  # shared by every view
    res = []
    for batch in prep.batches:
        img = _shade_batch(batch, mips, prep.material, opts, strength)
        res.append(((img - batch.images) * batch.weights).reshape(-1))
    if smooth is not None:
        dx = slopes[:, 1:] - slopes[:, :-1]
        dy = slopes[1:] - slopes[:-1]
        res.append(jnp.sqrt(smooth) * jnp.concatenate([dx.reshape(-1), dy.reshape(-1)]))
    return tuple(res)


def _loss(slopes, args):
    return 0.5 * sum(jnp.sum(r * r) for r in _residuals(slopes, args))


# --------------------------------------------------------------------------------------
# diagnostics
# --------------------------------------------------------------------------------------


def seen_texels(prep: Prepared, map_size: tuple[int, int], *,
                min_weight: float = 0.25) -> np.ndarray:
    """(h, w) bool: texels that some view samples at the finest mip level with total filter
    weight >= ``min_weight`` (i.e. that directly influence at least part of a pixel)."""
    h, w = map_size
    acc = jnp.zeros(h * w, jnp.float32)
    for b in prep.batches:
        wmask = (b.weights.max(1)[..., 0] > 0)[..., None]  # (V, K, 1): used pixels
        idx, wt = b.gbuffer.plan.index, b.gbuffer.plan.weight
        wt = jnp.where((idx < h * w) & wmask, wt, 0.0)  # level 0 texels come first
        acc = acc.at[jnp.minimum(idx, h * w - 1).reshape(-1)].add(wt.reshape(-1))
    return np.asarray(acc.reshape(h, w) >= min_weight)


def texel_influence(prep: Prepared) -> Array:
    """(h, w): each texel's total filter weight over all used pixels, views and targets.

    The column sums of the (fixed) texel-to-pixel sampling operator, mip
    levels included; used to precondition the solve (see `fit_normal_map`).
    """
    h, w = prep.options[0].normal_map_shape

    def sampled(t):
        mips = _mips(t, prep.options[0])
        return [_tex.apply_plan(b.gbuffer.plan, mips)[..., 0] * b.weights.sum(1)[..., 0]
                for b in prep.batches]

    zeros = jnp.zeros((h, w, 1), jnp.float32)
    _, vjp = jax.vjp(sampled, zeros)
    ones = [jnp.ones(b.pixels.shape, jnp.float32) for b in prep.batches]  # (V, K)
    return vjp(ones)[0][..., 0]


def angular_error(a: Array, b: Array) -> np.ndarray:
    """Per-texel angle in degrees between two normal maps (..., 3)."""
    return np.degrees(np.asarray(angle_between(jnp.asarray(a), jnp.asarray(b))))


def check_identifiability(prep: Prepared, *, warn: bool = True) -> dict:
    """How well the targets can determine a normal map; warns when they cannot.

    Counts, per view, the lights and the rank of their directions as seen from
    the object (a point light's direction is taken towards the centroid of the
    visible surface). Returns a dict with the counts and the verdict.
    """
    report = {"views": []}
    ok_any = False
    for v in range(prep.num_views):
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
        report["views"].append({"targets": int(view.images.shape[0]),
                                "distinct_light_directions": int(len(unique)),
                                "direction_rank": rank})
        ok_any |= rank >= 3
    report["identifiable"] = bool(ok_any)
    if warn and not ok_any:
        warnings.warn(
            "fit: no view has at least three lights with non-coplanar directions; one light "
            "cannot determine a normal (it only fixes the angle to the light) and two leave a "
            "two-fold ambiguity: the fitted map is not determined by these targets",
            FitWarning, stacklevel=2)
    return report


# --------------------------------------------------------------------------------------
# solving
# --------------------------------------------------------------------------------------


def _solver(opts: FitOptions):
    lsmr = lx.LSMR(rtol=1e-4, atol=1e-6, max_steps=opts.lsmr_steps)
    if opts.solver == "lm":
        return optx.LevenbergMarquardt(rtol=opts.rtol, atol=opts.atol, linear_solver=lsmr)
    if opts.solver == "gn":
        return optx.GaussNewton(rtol=opts.rtol, atol=opts.atol, linear_solver=lsmr)
    if opts.solver == "lbfgs":
        return optx.LBFGS(rtol=opts.rtol, atol=opts.atol)
    raise ValueError(f"fit: unknown solver {opts.solver!r}; expected one of {SOLVERS}")


class _Stepper:
    """Drives an optimistix solver one step at a time (progress, Ctrl-C, best-so-far)."""

    def __init__(self, solver, args, y0, least_squares: bool):
        self.solver = solver
        self.args = args
        if least_squares:
            fn = lambda y, a: (_residuals(y, a), None)  # noqa: E731
        else:
            fn = lambda y, a: (_loss(y, a), None)  # noqa: E731
        self.fn = fn
        f_struct, aux_struct = jax.eval_shape(fn, y0, args)
        self.state = solver.init(fn, y0, args, {}, f_struct, aux_struct, frozenset())
        self._step = eqx.filter_jit(self._step_impl)

    def _step_impl(self, y, state, args):
        y, state, _ = self.solver.step(self.fn, y, args, {}, state, frozenset())
        done, result = self.solver.terminate(self.fn, y, args, {}, state, frozenset())
        return y, state, done, result

    def step(self, y):
        y, self.state, done, result = self._step(y, self.state, self.args)
        return y, bool(done), result


@functools.partial(jax.jit, static_argnames=())
def _loss_jit(slopes, args):
    return _loss(slopes, args)


def _upsample(slopes: Array, size: tuple[int, int]) -> Array:
    return jax.image.resize(slopes, size + (slopes.shape[-1],), "linear")


def fit_normal_map(problem: FitProblem, options: FitOptions = FitOptions(), *,
                   ground_truth: np.ndarray | None = None, progress: bool = True,
                   prepared: Prepared | None = None, strength: float = 1.0,
                   time_limit: float | None = None) -> FitResult:
    """Fit the normal map of ``problem`` (see the module docstring).

    **Arguments:**
    - `problem`, `options`: what to fit and how.
    - `ground_truth`: optional (h, w, 3) decoded unit normals: the history then
      records the mean angular error over `seen_texels` at every step.
    - `progress`: show a progress bar (loss, step, elapsed, ETA).
    - `prepared`: reuse a `prepare(problem)` result.
    - `time_limit`: stop (keeping the best map) after this many seconds.

    Ctrl-C stops cleanly after the current step and returns the best map so far.
    Deterministic for a given `options.seed`.
    """
    if options.solver not in SOLVERS:
        raise ValueError(f"fit: unknown solver {options.solver!r}; expected one of {SOLVERS}")
    t_start = time.perf_counter()
    prep = prepared if prepared is not None else prepare(problem)
    check_identifiability(prep)
    h, w = problem.map_size
    sizes = [(max(2, h >> k), max(2, w >> k)) for k in range(options.coarse_to_fine, -1, -1)]
    key = jax.random.PRNGKey(options.seed)
    slopes = options.init_noise * jax.random.normal(key, sizes[0] + (2,), jnp.float32)
    seen = gt = None
    if ground_truth is not None:
        gt = jnp.asarray(ground_truth, jnp.float32)
        seen = seen_texels(prep, (h, w))
    history: list = []
    stopped = "max_steps"
    best = (math.inf, slopes)
    interrupted = {"flag": False}

    def on_sigint(signum, frame):  # finish the current step, then stop
        interrupted["flag"] = True

    old_handler = None
    try:
        old_handler = signal.signal(signal.SIGINT, on_sigint)
    except ValueError:  # not in the main thread
        pass
    bar = _progress(options.max_steps * len(sizes), progress)
    try:
        for level, size in enumerate(sizes):
            if level > 0:
                slopes = _upsample(best[1], size)
                best = (math.inf, slopes)
            lp = prep if size == (h, w) else _with_map_size(problem, prep, size)
            smooth = None if options.smoothness <= 0 else jnp.asarray(options.smoothness,
                                                                        jnp.float32)
            # Jacobi-like preconditioning: solve for z = slopes / scale, where scale evens
            # out how strongly each texel is observed (texels seen by many pixels vs. few)
            c = texel_influence(lp)
            c_ref = jnp.median(jnp.where(c > 0, c, jnp.nan)[~jnp.isnan(jnp.where(c > 0, c,
                                                                                  jnp.nan))])
            scale = jnp.sqrt(c_ref / (c + 0.01 * c_ref))[..., None]
            args = (lp, smooth, jnp.asarray(strength, jnp.float32), scale)
            z = slopes / scale
            stepper = _Stepper(_solver(options), args, z, options.solver != "lbfgs")
            loss0 = float(_loss_jit(z, args))
            if loss0 < best[0]:
                best = (loss0, slopes)
            rec0 = {"level": level, "size": list(size), "step": 0, "loss": loss0,
                    "seconds": time.perf_counter() - t_start}
            if gt is not None and size == (h, w):
                rec0["mean_angular_error_deg"] = float(
                    angular_error(slopes_to_normals(slopes), gt)[seen].mean())
            history.append(rec0)
            for k in range(options.max_steps):
                z, done, result = stepper.step(z)
                slopes = z * scale
                loss = float(_loss_jit(z, args))
                rec = {"level": level, "size": list(size), "step": k + 1, "loss": loss,
                       "seconds": time.perf_counter() - t_start}
                if np.isfinite(loss) and loss < best[0]:
                    best = (loss, slopes)
                if gt is not None and size == (h, w):
                    err = angular_error(slopes_to_normals(best[1]), gt)[seen]
                    rec["mean_angular_error_deg"] = float(err.mean())
                history.append(rec)
                bar.update(rec)
                if interrupted["flag"]:
                    stopped = "interrupted"
                    break
                if time_limit is not None and rec["seconds"] > time_limit:
                    stopped = "time_limit"
                    break
                if done:
                    stopped = "converged" if result == optx.RESULTS.successful else str(result)
                    break
            if stopped in ("interrupted", "time_limit"):
                break
    finally:
        bar.close()
        if old_handler is not None:
            signal.signal(signal.SIGINT, old_handler)
    final = best[1]
    if final.shape[:2] != (h, w):  # stopped during a coarse level
        final = _upsample(final, (h, w))
    return FitResult(normals=np.asarray(slopes_to_normals(final)), slopes=np.asarray(final),
                     history=history, seconds=time.perf_counter() - t_start, stopped=stopped,
                     best_loss=float(best[0]))


def _with_map_size(problem: FitProblem, prep: Prepared, size) -> Prepared:
    """The prepared problem re-planned for a coarser map (same G-buffers, new sample plans)."""
    views, opts_all = [], []
    for v, opts in enumerate(prep.options):
        view = prep.view(v)
        o = dataclasses.replace(opts, normal_map_shape=tuple(size))
        nm = o.normal_map
        plan = _tex.plan_sample(view.gbuffer.uv, size_hw=tuple(size), levels=o.levels,
                                filter=nm.filter, wrap=nm.wrap, uv_origin=nm.uv_origin)
        views.append(dataclasses.replace(view, gbuffer=dataclasses.replace(view.gbuffer,
                                                                           plan=plan)))
        opts_all.append(o)
    return _assemble(views, tuple(opts_all), prep.material)


class _progress:
    """A tqdm progress bar showing the loss (or nothing when disabled)."""

    def __init__(self, total: int, enabled: bool):
        self.bar = None
        if enabled:
            from tqdm import tqdm

            self.bar = tqdm(total=total, desc="fit", unit="step", dynamic_ncols=True)

    def update(self, rec: dict) -> None:
        if self.bar is None:
            return
        post = {"loss": f"{rec['loss']:.4g}"}
        if "mean_angular_error_deg" in rec:
            post["err"] = f"{rec['mean_angular_error_deg']:.2f}deg"
        self.bar.set_postfix(post, refresh=False)
        self.bar.update(1)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()


# --------------------------------------------------------------------------------------
# the built-in problem
# --------------------------------------------------------------------------------------


def default_light_directions(n: int = 6, elevation_deg: float = 50.0, seed: int = 0) -> np.ndarray:
    """``n`` unit directions on a cone around +z (azimuths evenly spread, fixed jitter)."""
    rng = np.random.default_rng(seed)
    az = 2 * np.pi * (np.arange(n) / n) + rng.uniform(-0.15, 0.15, n)
    el = np.radians(elevation_deg + rng.uniform(-8, 8, n))
    return np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], -1)


def directional_light(direction, color=(1.0, 1.0, 1.0), intensity: float = 1.0) -> Lights:
    """A `Lights` holding one directional light (``direction`` points towards the light)."""
    return Lights(directional=DirectionalLight(jnp.asarray(direction, jnp.float32)[None],
                                               jnp.asarray(color, jnp.float32)[None],
                                               jnp.full((1,), intensity, jnp.float32)))


def default_problem(*, render_size: int = 512, map_size: int = 256, n_lights: int = 6,
                    noise: float = 0.0, seed: int = 0, views: int = 2
                    ) -> tuple[FitProblem, np.ndarray, Scene]:
    """The built-in fitting problem: the default scene's torus and rivet map.

    Renders the torus from ``views`` cameras under ``n_lights`` directional
    lights with the ground-truth map (an 8-bit unsigned PNG-like map of
    ``map_size``), adds Gaussian noise of standard deviation ``noise`` (relative
    to each target's maximum), and returns ``(problem, ground_truth_normals,
    scene)``.
    """
    from . import procedural
    from .camera import look_at, perspective
    from .render import render

    scene = _default_fit_scene(render_size, map_size)
    gt_raw = scene.normal_map
    gt = np.asarray(_tex.decode_normal_map(jnp.asarray(gt_raw), encoding="unsigned"))
    gt = gt / np.linalg.norm(gt, axis=-1, keepdims=True)
    eyes = [(0.0, -2.35, 1.75), (1.6, 1.5, 1.9), (-2.1, 0.6, -1.2)][:views]
    rng = np.random.default_rng(seed)
    targets = []
    dirs = default_light_directions(n_lights, seed=seed)
    for vi, eye in enumerate(eyes):
        cam = Camera.from_matrices(look_at(eye, (0.0, 0.0, 0.0), (0.0, 0.0, 1.0)),
                                   perspective(45.0, 1.0, 0.1, 50.0))
        for li, d in enumerate(dirs):
            # light directions are given relative to the view, so each view sees its lit side
            d_world = view_relative(cam, d)
            sc = scene.replace(camera=cam, lights=directional_light(d_world))
            img = render(sc, outputs=("color",))["color"]
            if noise > 0:
                img = img + rng.normal(0.0, noise * img.max(), img.shape).astype(np.float32)
            targets.append(FitTarget(cam, render_size, render_size, directional_light(d_world), img,
                                     name=f"view{vi}_light{li}"))
    problem = FitProblem(mesh=scene.mesh, material=scene.material, targets=tuple(targets),
                         map_size=(map_size, map_size), albedo=np.asarray(scene.albedo),
                         shading=scene.shading, frame=scene.frame,
                         derivatives=scene.derivatives, double_sided=scene.double_sided,
                         sampling=dataclasses.replace(scene.normal_map_options,
                                                      encoding="signed"),
                         source="<built-in fit problem>")
    del procedural
    return problem, gt, scene


def view_relative(cam: Camera, d) -> np.ndarray:
    """World direction of ``d`` given in the camera's frame (x right, y up, z towards the eye)."""
    inv = np.linalg.inv(np.asarray(cam.view, np.float64))
    v = inv[:3, :3] @ np.asarray(d, np.float64)
    return v / np.linalg.norm(v)


def _default_fit_scene(render_size: int, map_size: int) -> Scene:
    from . import procedural
    from .scene import default_scene

    sc = default_scene(width=render_size, height=render_size)
    nm = procedural.encode_unsigned(procedural.default_normal_map(map_size))
    return sc.replace(normal_map=nm, material=Material(
        diffuse=jnp.ones(3), specular=jnp.asarray([0.15, 0.15, 0.15]),
        shininess=jnp.asarray(24.0), ambient=jnp.zeros(3)))


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


def _json_default(o):
    if isinstance(o, (np.floating, np.integer)):
        return o.item()
    raise TypeError(type(o))


def save_json(path, obj) -> None:
    Path(path).write_text(json.dumps(obj, indent=2, default=_json_default) + "\n")
