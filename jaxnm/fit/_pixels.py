"""The per-pixel model of a fit: a pixel's colours under its lights as a function of its
sampled map vector, with the Jacobian blocks and reduced residuals the solvers use.

Every pixel's colours depend only on that pixel's sampled map vector ``m`` (3 numbers), so
the Jacobian with respect to ``m`` is block diagonal: `pixel_model` gives it as explicit
per-pixel blocks, and `reduced_pixel_residuals` folds a pixel's ``3T`` residuals (``T``
targets) into 4 numbers with the same sum of squares and Gauss-Newton model.
`jaxnm.fit.model` and `jaxnm.fit.texel_lm` build their steps from these.
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
from jax import Array
from jax.custom_derivatives import SymbolicZero

from .. import textures as _tex
from ..frames import perturb_normal
from ..gbuffer import GBuffer, RenderOptions
from ..numerics import safe_sqrt, tiny
from ..shading import Lights, Material, shade

__all__ = ["first_taps", "mip_chain", "pixel_model", "reduce_pixels", "reduced_pixel_residuals",
           "smoothness_residuals"]


def mip_chain(normals: Array, opts: RenderOptions) -> tuple[Array, ...]:
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
def pixel_model(m, gb, lights, material, shading, strength):
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


pixel_model.defjvp(_pixel_model_jvp, symbolic_zeros=True)


#: Relative regularisation of the per-pixel Gram matrix in `reduced_pixel_residuals`.
_GRAM_REGULARISATION = 1e-6


def reduce_pixels(m, gb, lights, material, shading, strength, images, weights):
    """(rho, e, L) of one view's pixels: see `reduced_pixel_residuals`; ``L`` (K, 6) as the
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
def reduced_pixel_residuals(m, gb, lights, material, shading, strength, images, weights):
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
    rho, e, _ = reduce_pixels(m, gb, lights, material, shading, strength, images, weights)
    return rho, e


def _reduced_jvp(shading, primals, tangents):
    dm = tangents[0]
    others = jax.tree_util.tree_leaves(tangents[1:], is_leaf=_is_zero)
    if not all(_is_zero(t) for t in others):
        raise NotImplementedError("reduced_pixel_residuals is differentiable w.r.t. the map "
                                  "only; use ModelArgs(reduce=False) for other derivatives")
    rho, e, L = reduce_pixels(*primals[:4], shading, *primals[4:])
    if _is_zero(dm):
        return (rho, e), (jnp.zeros_like(rho), jnp.zeros_like(e))
    l00, l10, l20, l11, l21, l22 = (L[:, i] for i in range(6))
    d0, d1, d2 = dm[:, 0], dm[:, 1], dm[:, 2]
    drho = jnp.stack([l00 * d0 + l10 * d1 + l20 * d2, l11 * d1 + l21 * d2, l22 * d2], -1)
    return (rho, e), (drho, jnp.zeros_like(e))


reduced_pixel_residuals.defjvp(_reduced_jvp, symbolic_zeros=True)


def first_taps(plan: _tex.SamplePlan, taps: int | None) -> _tex.SamplePlan:
    """``plan`` with only its first ``taps`` filter taps (None: all of them)."""
    if taps is None:
        return plan
    return dataclasses.replace(plan, index=plan.index[..., :taps], weight=plan.weight[..., :taps])


def smoothness_residuals(slopes: Array, weight: Array) -> Array:
    """The first-difference penalty's residuals: ``sqrt(weight)`` times the differences of
    horizontally and vertically adjacent slopes, flat."""
    dx = slopes[:, 1:] - slopes[:, :-1]
    dy = slopes[1:] - slopes[:-1]
    return jnp.sqrt(weight) * jnp.concatenate([dx.reshape(-1), dy.reshape(-1)])
