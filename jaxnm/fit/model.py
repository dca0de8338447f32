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
from jax.custom_derivatives import SymbolicZero

from .. import textures as _tex
from .._exec.fusion import materialize
from ..frames import perturb_normal
from ..gbuffer import GBuffer, RenderOptions
from ..numerics import safe_normalize, safe_sqrt, tiny
from ..shading import Lights, Material, shade
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
    - `reduce` (static): return each pixel's residuals in the reduced form of
      `_reduced_pixel_residuals` (4 numbers per pixel instead of 3 per target);
      the loss and the Gauss-Newton model are the same.
    - `texel_sums`: the fixed-order texel sums of `jaxnm.fit.texel_lm._texel_sum_tables`
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


def _mip_chain(normals: Array, opts: RenderOptions) -> tuple[Array, ...]:
    """The mip chain a fit samples: ``normals`` (h, w, 3) box-filtered into ``opts.levels``
    levels, not renormalised (as `jaxnm.render` filters a normal map)."""
    return _tex.build_mipmaps(normals, levels=opts.levels)


def _pixel_colors(m: Array, gb: GBuffer, lights: Lights, material: Material, shading: str,
                  strength) -> Array:
    """(T, K, 3): each stacked light's shading of the per-pixel map vectors ``m`` (K, 3)."""
    m = m * jnp.stack([strength, strength, jnp.ones_like(strength)]).astype(m.dtype)[None]
    # at the frame's precision (``FitProblem.precision``), like `jaxnm.render`
    n = perturb_normal(gb.frame, m.astype(gb.frame.N.dtype)).astype(m.dtype)
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


def _is_zero(t) -> bool:
    return isinstance(t, SymbolicZero)


def _pixel_model_jvp(shading, primals, tangents):
    m, gb, lights, material, strength = primals
    dm, *rest_t = tangents
    f = lambda m_: _pixel_colors(m_, gb, lights, material, shading, strength)  # noqa: E731
    if _is_zero(dm):
        out = None
        y = f(m)
    else:
        y = f(m)
        basis = jnp.eye(3, dtype=m.dtype)
        blocks = jax.vmap(lambda e: jax.jvp(f, (m,), (jnp.broadcast_to(e, m.shape),))[1])(basis)
        # blocks: (3, T, K, 3) = d colour / d m_k
        out = jnp.einsum("kt...c,...k->t...c", blocks, dm, precision=jax.lax.Precision.HIGHEST)
    # the other inputs (G-buffer, lights, material, strength) are constants in a fit: their
    # tangents are symbolic zeros, and the JVP through them is skipped, not run on zeros
    if not all(_is_zero(t) for t in jax.tree_util.tree_leaves(rest_t, is_leaf=_is_zero)):
        rest_p = (gb, lights, material, strength)
        rest_t = jax.tree_util.tree_map(
            lambda t, p: jnp.zeros_like(p) if _is_zero(t) else t, tuple(rest_t), rest_p,
            is_leaf=_is_zero)
        rest = jax.jvp(lambda g, lt, mt, s: _pixel_colors(m, g, lt, mt, shading, s),
                       rest_p, rest_t)[1]
        out = rest if out is None else out + rest
    return y, jnp.zeros_like(y) if out is None else out


_pixel_model.defjvp(_pixel_model_jvp, symbolic_zeros=True)


#: Relative regularisation of the per-pixel Gram matrix in `_reduced_pixel_residuals`.
_GRAM_REGULARISATION = 1e-6


def _reduce_pixels(m, gb, lights, material, shading, strength, images, weights):
    """(rho, e, L) of one view's pixels: see `_reduced_pixel_residuals`; ``L`` (K, 6) as the
    lower triangle (l00, l10, l20, l11, l21, l22) of each pixel's Gram factor."""
    def r_of(m_):  # (T, K, 3) weighted residuals of every target at every pixel
        return (_pixel_colors(m_, gb, lights, material, shading, strength) - images) * weights

    r = r_of(m)
    basis = jnp.eye(3, dtype=m.dtype)
    B = jax.vmap(lambda e: jax.jvp(r_of, (m,), (jnp.broadcast_to(e, m.shape),))[1])(basis)
    # B: (3, T, K, 3), d r / d m_a. The Gram matrix G = B^T B and g = B^T r per pixel:
    def gram(a, b):
        return jnp.sum(B[a] * B[b], axis=(0, 2))  # sum over targets and colour channels

    g00, g11, g22 = gram(0, 0), gram(1, 1), gram(2, 2)
    g10, g20, g21 = gram(1, 0), gram(2, 0), gram(2, 1)
    g = jnp.stack([jnp.sum(B[a] * r, axis=(0, 2)) for a in range(3)], -1)  # (K, 3)
    # Cholesky of G + delta I, written out for 3 x 3 (delta keeps it positive definite
    # where fewer than three independent directions are observed, e.g. in shadow)
    tiny_ = tiny(m.dtype)
    delta = _GRAM_REGULARISATION * (g00 + g11 + g22) + tiny_
    l00 = jnp.sqrt(g00 + delta)
    l10, l20 = g10 / l00, g20 / l00
    l11 = jnp.sqrt(jnp.maximum(g11 + delta - l10 * l10, delta))
    l21 = (g21 - l20 * l10) / l11
    l22 = jnp.sqrt(jnp.maximum(g22 + delta - l20 * l20 - l21 * l21, delta))
    rho0 = g[:, 0] / l00
    rho1 = (g[:, 1] - l10 * rho0) / l11
    rho2 = (g[:, 2] - l20 * rho0 - l21 * rho1) / l22
    rho = jnp.stack([rho0, rho1, rho2], -1)
    e = safe_sqrt(jnp.maximum(jnp.sum(r * r, axis=(0, 2)) - jnp.sum(rho * rho, -1), 0.0))
    return rho, e, jnp.stack([l00, l10, l20, l11, l21, l22], -1)


@functools.partial(jax.custom_jvp, nondiff_argnums=(4,))
def _reduced_pixel_residuals(m, gb, lights, material, shading, strength, images, weights):
    r"""The residuals of one view's pixels in reduced form: 4 numbers per pixel, whatever the
    number of targets, with the same sum of squares and the same Gauss-Newton model.

    A pixel's weighted residuals ``r = (colour(m) - target) * weight`` over its ``T``
    targets (``3T`` numbers) depend only on its sampled map vector ``m`` (3 numbers).
    With the Jacobian ``B = dr/dm`` (``3T x 3``) and ``G = B^T B = L L^T`` (Cholesky of
    ``G + delta I``, ``delta`` = `_GRAM_REGULARISATION` times its trace), the reduced
    residuals are

    .. math:: 
ho = L^{-1} B^T r, \qquad e = \sqrt{|r|^2 - |
ho|^2},

    so ``|rho|^2 + e^2 = |r|^2`` (the loss is unchanged), and their Jacobian is
    ``[L^T; 0]``, whose Gram matrix ``L L^T = G + delta I`` and gradient
    ``L rho = B^T r`` are those of the full residuals: a Gauss-Newton or LM step on the
    reduced residuals is the step on the full ones (up to ``delta``). Per iteration of the
    inner solver, a pixel then costs a 3 x 3 triangular product instead of ``3T`` rows.

    **Returns:** ``(rho, e)``, (K, 3) and (K,). Differentiable w.r.t. ``m`` only (the
    JVP is the Gauss-Newton Jacobian above, which is also the exact gradient of the loss).
    """
    rho, e, _ = _reduce_pixels(m, gb, lights, material, shading, strength, images, weights)
    return rho, e


def _reduced_jvp(shading, primals, tangents):
    dm = tangents[0]
    others = jax.tree_util.tree_leaves(tangents[1:], is_leaf=_is_zero)
    if not all(_is_zero(t) for t in others):
        raise NotImplementedError("_reduced_pixel_residuals is differentiable w.r.t. the map "
                                  "only; use ModelArgs(reduce=False) for other derivatives")
    rho, e, L = _reduce_pixels(*primals[:4], shading, *primals[4:])
    if _is_zero(dm):
        return (rho, e), (jnp.zeros_like(rho), jnp.zeros_like(e))
    l00, l10, l20, l11, l21, l22 = (L[:, i] for i in range(6))
    d0, d1, d2 = dm[:, 0], dm[:, 1], dm[:, 2]
    drho = jnp.stack([l00 * d0 + l10 * d1 + l20 * d2, l11 * d1 + l21 * d2, l22 * d2], -1)
    return (rho, e), (drho, jnp.zeros_like(e))


_reduced_pixel_residuals.defjvp(_reduced_jvp, symbolic_zeros=True)


def _first_taps(plan: _tex.SamplePlan, taps: int | None) -> _tex.SamplePlan:
    """``plan`` with only its first ``taps`` filter taps (None: all of them)."""
    if taps is None:
        return plan
    return dataclasses.replace(plan, index=plan.index[..., :taps], weight=plan.weight[..., :taps])


def sample_split(plan: _tex.SamplePlan, mips, split: int) -> Array:
    """`jaxnm.textures.apply_plan` of the texels of ``mips``, with the first ``split`` pixels
    gathered from their 4 non-zero taps (see `ViewBatch.split`)."""
    head = jax.tree_util.tree_map(lambda x: x[:split], _first_taps(plan, 4))
    tail = jax.tree_util.tree_map(lambda x: x[split:], plan)
    parts = [_tex.apply_plan(p, mips) for p in (head, tail) if p.index.shape[0]]
    return parts[0] if len(parts) == 1 else jnp.concatenate(parts, 0)


def _shade_view(gb: GBuffer, mips, lights: Lights, material: Material, opts: RenderOptions,
                strength, taps: int | None = None) -> Array:
    """(T, K, 3): the pixels of ``gb`` under each stacked light, with the map's mip chain
    ``mips`` read through the first ``taps`` taps of the sample plan (None: all)."""
    m = _sample(gb.plan, mips, taps)
    return _pixel_model(m, gb, lights, material, opts.shading, jnp.asarray(strength, m.dtype))


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
    return materialize(_tex.apply_plan(_first_taps(plan, taps), mips))


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
    opts = prep.options[0]
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
    return _shade_view(gb, _mip_chain(normals, opts), lights, material, opts, strength)


def _reduced_batch(batch: ViewBatch, mips, material: Material, opts: RenderOptions,
                   strength) -> Array:
    """Every view of ``batch`` as `_reduced_pixel_residuals`, flat."""
    def one(gb, lights, images, weights, taps):
        m = _sample(gb.plan, mips, taps)
        rho, e = _reduced_pixel_residuals(m, gb, lights, material, opts.shading,
                                         jnp.asarray(strength, m.dtype), images, weights)
        return jnp.concatenate([rho, e[:, None]], -1)

    return _over_chunks(batch, one, 1).reshape(-1)


@jax.jit  # one program per problem shape: op by op, the reduced form took ~10 s a call
def residuals(z: Array, args: ModelArgs) -> tuple[Array, ...]:
    """The weighted differences between the renders and the targets, one flat array per
    `ViewBatch`, and the smoothness residuals (if any); ``z`` (h, w, 2) are the
    preconditioned slopes (``slopes = z * args.scale``). With ``args.reduce``, a batch
    whose views have more than one target returns `_reduced_pixel_residuals` instead
    (same sum of squares, same Gauss-Newton model, 4 numbers per pixel)."""
    slopes = z * args.scale
    res = _map_residuals(slopes_to_normals(slopes), args)
    if args.smoothness is not None:
        res = res + (_smoothness_residuals(slopes, args.smoothness),)
    return res


def _map_residuals(normals: Array, args: ModelArgs) -> tuple[Array, ...]:
    prep, strength = args.prepared, args.strength
    opts = prep.options[0]
    mips = _mip_chain(normals, opts)  # shared by every view
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


def _smoothness_residuals(slopes: Array, weight: Array) -> Array:
    """The first-difference penalty's residuals: ``sqrt(weight)`` times the differences of
    horizontally and vertically adjacent slopes, flat."""
    dx = slopes[:, 1:] - slopes[:, :-1]
    dy = slopes[1:] - slopes[:-1]
    return jnp.sqrt(weight) * jnp.concatenate([dx.reshape(-1), dy.reshape(-1)])


@jax.jit
def loss(z: Array, args: ModelArgs) -> Array:
    """``0.5 * sum(residuals(z, args)^2)``, the objective every solver minimises (one
    compiled program per problem shape)."""
    return 0.5 * sum(jnp.sum(r * r) for r in residuals(z, args))
