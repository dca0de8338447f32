r"""The per-step model of a fit: slopes -> map -> sampled texels -> shading -> residuals.

**Parameterisation.** Each texel holds two slopes ``(s_x, s_y)``; its normal is
``normalize(s_x, s_y, 1)``: always a unit vector with positive z, with no
constraint to enforce and no singular point. The solver works on
preconditioned variables ``z = slopes / scale`` (`ModelArgs.scale`).

**A step** runs only the texel-dependent stages on the covered pixels of a
`Prepared` problem: build the mip chain of the current map (once, for all
views), one gather and weighted sum per pixel (4 taps where the fixed level of
detail reads a single mip level, 8 elsewhere), perturb, shade, subtract the
target. Views and their lights are batched with ``vmap``; a big problem is evaluated in
chunks of every view's pixels, one after another (`ViewBatch.chunks`), so the step's
working memory stays bounded.
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Sequence

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array

from .. import textures as _tex
from .._exec.fusion import materialize
from ..gbuffer import GBuffer, RenderOptions
from ..numerics import safe_normalize
from ..shading import Lights, Material
from ._pixels import (
    first_taps,
    mip_chain,
    pixel_model,
    reduced_pixel_residuals,
    smoothness_residuals,
)
from .prepare import Prepared, ViewBatch

__all__ = [
    "ModelArgs", "slopes_to_normals", "normals_to_slopes", "residuals", "map_residuals", "loss",
    "render_with_map", "sample_split"
]


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class ModelArgs:
    """Everything `residuals` and `loss` need besides the variables.

    **Fields** (a pytree; arrays may be traced):
    - `prepared`: the `Prepared` problem.
    - `smoothness`: () weight of the first-difference penalty on the slopes, or
      None for no penalty.
    - `strength`: () scale of the map's x and y (1 for the map as fitted).
    - `scale`: (h, w, 1) per-texel preconditioner: the slopes are ``z * scale``.
    - `reduce` (static): return each pixel's residuals in a reduced form (4 numbers per
      pixel instead of 3 per target, ``rho = L^-1 B^T r`` and ``e = sqrt(|r|^2 - |rho|^2)``
      with ``B = dr/dm``, ``B^T B = L L^T``); the loss and the Gauss-Newton model are the
      same.
    - `texel_sums`: the fixed-order texel sums of `jaxnm.fit.texel_lm.texel_sum_tables`
      (per batch, per pixel group), or None: the ``"lm-texel"`` solver then sums into the
      texels by scatter-adds (see `FitOptions.texel_sums`).
    """

    prepared: Prepared
    smoothness: Array | None
    strength: Array
    scale: Array
    reduce: bool = dataclasses.field(default=False, metadata=dict(static=True))
    texel_sums: tuple | None = None

    @staticmethod
    def create(prepared: Prepared, *, smoothness: float = 0.0, strength: float = 1.0,
               scale: Array | None = None, reduce: bool = False,
               texel_sums: tuple | None = None) -> ModelArgs:
        """Arguments for ``prepared`` (no preconditioning unless ``scale`` is given; see
        `residuals` for ``reduce``)."""
        h, w = prepared.options[0].normal_map_shape

        def put(x):  # from the host: `jnp.asarray` of a number compiles a conversion
            return jax.device_put(np.asarray(x, np.float32))

        return ModelArgs(prepared, None if smoothness <= 0 else put(smoothness), put(strength),
                         put(np.ones((h, w, 1))) if scale is None else scale,
                         reduce=bool(reduce), texel_sums=texel_sums)


def slopes_to_normals(slopes: Array) -> Array:
    """``normalize(s_x, s_y, 1)`` per texel: (h, w, 2) -> (h, w, 3) unit, z > 0."""
    one = jnp.ones(slopes.shape[:-1] + (1,), slopes.dtype)
    return safe_normalize(jnp.concatenate([slopes, one], -1))


def normals_to_slopes(normals: Array, max_slope: float = 1e3) -> Array:
    """Inverse of `slopes_to_normals` for normals with z > 0 (clamped to ``max_slope``)."""
    n = jnp.asarray(normals)
    z = jnp.maximum(n[..., 2:3], 1.0 / max_slope)
    return jnp.clip(n[..., :2] / z, -max_slope, max_slope)


def sample_split(plan: _tex.SamplePlan, mips, split: int) -> Array:
    """`jaxnm.textures.apply_plan` of the texels of ``mips``, with the first ``split`` pixels
    gathered from their 4 non-zero taps (see `ViewBatch.split`)."""
    head = jax.tree_util.tree_map(lambda x: x[:split], first_taps(plan, 4))
    tail = jax.tree_util.tree_map(lambda x: x[split:], plan)
    parts = [_tex.apply_plan(p, mips) for p in (head, tail) if p.index.shape[0]]
    return parts[0] if len(parts) == 1 else jnp.concatenate(parts, 0)


def _shade_view(gb: GBuffer, mips, lights: Lights, material: Material, opts: RenderOptions,
                strength, taps: int | None = None) -> Array:
    """(T, K, 3): the pixels of ``gb`` under each stacked light, with the map's mip chain
    ``mips`` read through the first ``taps`` taps of the sample plan (None: all)."""
    m = _sample(gb.plan, mips, taps)
    return pixel_model(m, gb, lights, material, opts.shading, jnp.asarray(strength, m.dtype))


def _over_chunks(batch: ViewBatch, fn, pixel_axis: int) -> Array:
    """``fn(gbuffer, lights, images, weights, taps)`` of one view's pixel chunk, run over every
    chunk of every view of ``batch`` (``vmap`` over views, a loop over the chunks of
    `ViewBatch.chunks`), and put together along its output's ``pixel_axis`` in the batch's
    pixel order: (V, ..., K, ...).

    ``taps`` is 4 for the pixels that read one mip level (the first `ViewBatch.split`), None
    (the plan's own) for the rest. A loop iteration holds one chunk's intermediates, so
    the working memory of a step stays bounded however many views and pixels there are."""
    parts = []
    for start, size, n, taps in batch.pixel_groups():
        def chunk(c, start=start, size=size, taps=taps):
            return jax.vmap(lambda *a: fn(*a, taps))(*batch.chunk(start, size, c))

        if n == 1:
            parts.append(chunk(0))
            continue
        out = jnp.moveaxis(jax.lax.map(chunk, jnp.arange(n)), 0, pixel_axis)  # n, size adjacent
        parts.append(out.reshape(out.shape[:pixel_axis] + (n * size,)
                                 + out.shape[pixel_axis + 2:]))
    return parts[0] if len(parts) == 1 else jnp.concatenate(parts, pixel_axis)


def _sample(plan: _tex.SamplePlan, mips, taps: int | None) -> Array:
    """The pixels' map vectors (K, 3) from the first ``taps`` taps of ``plan`` (None: all),
    materialised: fused into the shading, the gather would be recomputed per use."""
    return materialize(_tex.apply_plan(first_taps(plan, taps), mips))


def _shade_batch(batch: ViewBatch, mips, material: Material, opts: RenderOptions,
                 strength) -> Array:
    """(V, T, K, 3): every view of ``batch`` under each of its lights."""
    def one(gb, lights, images, weights, taps):
        return _shade_view(gb, mips, lights, material, opts, strength, taps)

    return _over_chunks(batch, one, 2)


def render_with_map(prep: Prepared, normals: Array, *, strength: float = 1.0,
                    lights: Sequence[Lights] | None = None) -> list[np.ndarray]:
    """Render every view of ``prep`` with the map ``normals`` (h, w, 3); one (T, H, W, 3) NumPy
    array per view.

    ``lights`` (one stacked `Lights` per view, leaves (T, ...)) replaces the
    prepared lights, e.g. to render from held-out light directions.
    """
    if not isinstance(prep, Prepared):
        raise TypeError(f"render_with_map: prep must be a Prepared (jaxnm.fit.prepare), got "
                        f"{type(prep).__name__}")
    opts = prep.options[0]
    want = (*opts.normal_map_shape, 3)
    if jnp.shape(normals) != want:
        raise ValueError(f"render_with_map: normals must be {want}, the prepared problem's map, "
                         f"got {jnp.shape(normals)}")
    if lights is not None and len(lights) != prep.num_views:
        raise ValueError(f"render_with_map: lights must hold one Lights per view "
                         f"({prep.num_views}), got {len(lights)}")
    out = []
    for v in range(prep.num_views):
        view = prep.view(v)
        lt = view.lights if lights is None else lights[v]
        img = _render_view(view.gbuffer, jnp.asarray(normals), lt, prep.material,
                           jnp.asarray(strength, jnp.float32), opts=opts)
        out.append(prep.to_image(v, img))
    return out


@functools.partial(jax.jit, static_argnames=("opts",))
def _render_view(gb, normals, lights, material, strength, *, opts):
    return _shade_view(gb, mip_chain(normals, opts), lights, material, opts, strength)


def _reduced_batch(batch: ViewBatch, mips, material: Material, opts: RenderOptions,
                   strength) -> Array:
    """Every view of ``batch`` as `reduced_pixel_residuals`, flat."""
    def one(gb, lights, images, weights, taps):
        m = _sample(gb.plan, mips, taps)
        rho, e = reduced_pixel_residuals(m, gb, lights, material, opts.shading,
                                         jnp.asarray(strength, m.dtype), images, weights)
        return jnp.concatenate([rho, e[:, None]], -1)

    return _over_chunks(batch, one, 1).reshape(-1)


@jax.jit  # one program per problem shape (op by op, the reduced form is far slower)
def residuals(z: Array, args: ModelArgs) -> tuple[Array, ...]:
    """The weighted differences between the renders and the targets, one flat array per
    `ViewBatch`, and the smoothness residuals (if any); ``z`` (h, w, 2) are the
    preconditioned slopes (``slopes = z * args.scale``). With ``args.reduce``, a batch
    whose views have more than one target returns its reduced residuals instead (see
    `ModelArgs`: same sum of squares, same Gauss-Newton model, 4 numbers per pixel)."""
    slopes = z * args.scale
    res = _map_residuals(slopes_to_normals(slopes), args)
    if args.smoothness is not None:
        res = res + (smoothness_residuals(slopes, args.smoothness),)
    return res


def _map_residuals(normals: Array, args: ModelArgs) -> tuple[Array, ...]:
    prep, strength = args.prepared, args.strength
    opts = prep.options[0]
    mips = mip_chain(normals, opts)  # shared by every view
    res = []
    for batch in prep.batches:
        if args.reduce and 3 * batch.images.shape[1] > 4:
            res.append(_reduced_batch(batch, mips, prep.material, opts, strength))
            continue
        img = _shade_batch(batch, mips, prep.material, opts, strength)
        res.append(((img - batch.images) * batch.weights).reshape(-1))
    return tuple(res)


@jax.jit
def map_residuals(normals: Array, args: ModelArgs) -> tuple[Array, ...]:
    """The image residuals of `residuals` for a map given as its texels' vectors ``normals``
    (h, w, 3), not necessarily unit (e.g. a stored map's decoded codes): mip-mapped,
    sampled and shaded as the fit does, one flat array per `ViewBatch`; no smoothness
    term. Differentiable in ``normals`` (a fit through a map's storage,
    `jaxnm.fit.stored`)."""
    return _map_residuals(normals, args)


@jax.jit
def loss(z: Array, args: ModelArgs) -> Array:
    """``0.5 * sum(residuals(z, args)^2)``, the objective every solver minimises (one
    compiled program per problem shape)."""
    return 0.5 * sum(jnp.sum(r * r) for r in residuals(z, args))
