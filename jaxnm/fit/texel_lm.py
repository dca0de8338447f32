r"""Levenberg–Marquardt on the normal equations in texel space, streamed over pixel chunks.

optimistix's ``"lm"`` linearises the residual function and solves each step by
LSMR on it: the linearisation it keeps between steps, and LSMR's vectors, live
in *residual* space — a few numbers per pixel and target, for every pixel of
every view. A fit of many views then holds several copies of its pixels.

This solver (``FitOptions(solver="lm-texel")``) keeps the Gauss–Newton model in
the space of the *texels*. A pixel's residuals depend on its sampled map vector
``m`` only (3 numbers), so with ``B = dr/dm`` and ``G = B^T B = L L^T`` (the
factor of the reduced residuals, `jaxnm.fit.model.ModelArgs`), the Gauss–Newton matrix and
gradient are

.. math:: H = \sum_\text{pixels} A^T L L^T A, \qquad g = \sum_\text{pixels} A^T B^T r,

with ``A = dm/dz`` the sampling (a weighted gather of the mip chain built from
the slopes ``z``). Each step makes **one pass** over the pixels — chunk by
chunk (`ViewBatch.chunks`), every view of a chunk at once — that shades them,
forms ``L`` (6 numbers per pixel, kept) and sums the loss and ``g`` in texel
space; the damped system ``(H + lambda I) dz = -g`` is then solved by conjugate
gradients (`conjugate_gradient`), each product ``H v`` one more gather and scatter per
pixel from the stored factors. Nothing else per pixel outlives a chunk: the solver's
memory is the prepared problem, 24 bytes per pixel and a few texel-sized
vectors, whatever the number of views.

The damping ``lambda`` follows the classical trust-region rule optimistix's
Levenberg–Marquardt uses (the ratio of the actual to the predicted decrease sets it).
Like optimistix's solvers, a step evaluates the point the previous step proposed, accepts
or rejects it, and proposes the next; the first step evaluates the start.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from jax import Array

from .. import textures as _tex
from .._exec.device import choose, resident
from .._exec.sums import SumTables
from ._pixels import first_taps, mip_chain, reduce_pixels, smoothness_residuals
from .model import ModelArgs, slopes_to_normals
from .prepare import Prepared, ViewBatch

__all__ = ["TexelLM", "TexelLMState", "conjugate_gradient", "texel_sum_tables"]


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class TexelLMState:
    """What `TexelLM` carries between steps (a pytree).

    - `f`: () the loss ``0.5 |r|^2`` at the accepted point (inf before the first step).
    - `g`: (h, w, 2) its gradient in the solver's variables.
    - `factors`: per `ViewBatch`, the lower triangles of each pixel's ``L``, chunk-major:
      a (count, V, size, 6) array per pixel group (its chunks, in order).
    - `delta`: (h, w, 2) the move proposed for the next step; `predicted`: () the decrease
      the model predicts for it.
    - `lam`: () the damping.
    """

    f: Array
    g: Array
    factors: tuple[tuple[Array, ...], ...]
    delta: Array
    predicted: Array
    lam: Array


def _fold(batch: ViewBatch, body, carry, per_pixel: tuple[Array, ...] | None = None,
          sums: tuple[SumTables, ...] | None = None):
    """Run ``body(carry, gbuffer, lights, images, weights, taps, per_pixel_chunk, sums_chunk)``
    over every chunk of every view of ``batch`` (one chunk of all views at a time), threading
    ``carry``.

    Per-pixel arrays stay **chunk-major**: ``per_pixel`` holds one (count, V, size, ...) array
    per pixel group (`ViewBatch.pixel_groups`), read a chunk at a time, and ``body``'s
    second outputs come back the same way (or None) — no reordering into (V, K, ...),
    which would copy them. ``sums``: the texel sums of each group's chunks
    (`texel_sum_tables`), or None.
    Returns the final carry and that tuple."""
    outs = []
    for g, (start, size, n, taps) in enumerate(batch.pixel_groups()):
        def chunk(carry, xs, start=start, size=size, taps=taps):
            c, extra, tables = xs
            return body(carry, *batch.chunk(start, size, c), taps, extra, tables)

        extra = None if per_pixel is None else per_pixel[g]
        tables = None if sums is None else sums[g]
        if n == 1:
            first = jax.tree_util.tree_map(lambda x: x[0], (extra, tables))
            carry, out = chunk(carry, (0, *first))
            out = None if out is None else out[None]
        else:
            carry, out = jax.lax.scan(chunk, carry, (jnp.arange(n), extra, tables))
        outs.append(out)
    return carry, None if outs[0] is None else tuple(outs)


def texel_sum_tables(prepared: Prepared) -> tuple[tuple[SumTables, ...], ...]:
    """For each `ViewBatch` of ``prepared`` and each of its pixel groups, the fixed-order
    texel sums (`jaxnm.textures.plan_sum_tables`) of every chunk's taps, stacked by chunk:
    what a step's texel-space sums use in place of scatter-adds (`FitOptions.texel_sums`).
    Built on the host, once per fit (the taps do not change between steps). The indices
    are copied to the host whole and cut there (cutting them on a GPU would compile a
    program per cut)."""
    out = []
    for batch in prepared.batches:
        plan = batch.gbuffer.plan
        index = np.asarray(plan.index)
        groups = []
        for start, size, n, taps in batch.pixel_groups():
            chunks = [index[:, start + c * size:start + (c + 1) * size, :taps]
                      for c in range(n)]
            groups.append(_tex.plan_sum_tables(plan, chunks))
        out.append(tuple(groups))
    return tuple(out)


def _sampler(plan: _tex.SamplePlan, mips, tables: SumTables | None):
    """``apply_plan(plan, mips)`` and its transpose w.r.t. ``mips`` (a function of the
    output's cotangent): a scatter-add (``jax.vjp``), or the fixed-order sums of
    ``tables``."""
    if tables is None:
        m, pull = jax.vjp(lambda mp: _tex.apply_plan(plan, mp), mips)
        return m, lambda y: pull(y)[0]
    return (_tex.apply_plan(plan, mips),
            lambda y: _tex.transpose_plan(plan, tables, y, mips))


def _factor_shapes(batch: ViewBatch) -> tuple[tuple[int, ...], ...]:
    """The shapes of a batch's kept factors: (count, V, size, 6) per pixel group."""
    views = batch.pixels.shape[0]
    return tuple((n, views, size, 6) for _, size, n, _ in batch.pixel_groups())


def _lower_times(f: Array, d: Array) -> Array:
    """``L d`` per pixel for ``L``'s lower triangle ``f`` (..., 6) (l00, l10, l20, l11, l21,
    l22) and ``d`` (..., 3)."""
    l00, l10, l20, l11, l21, l22 = (f[..., i] for i in range(6))
    d0, d1, d2 = d[..., 0], d[..., 1], d[..., 2]
    return jnp.stack([l00 * d0, l10 * d0 + l11 * d1, l20 * d0 + l21 * d1 + l22 * d2], -1)


def _lower_transpose_times(f: Array, d: Array) -> Array:
    """``L^T d`` per pixel (see `_lower_times`)."""
    l00, l10, l20, l11, l21, l22 = (f[..., i] for i in range(6))
    d0, d1, d2 = d[..., 0], d[..., 1], d[..., 2]
    return jnp.stack([l00 * d0 + l10 * d1 + l20 * d2, l11 * d1 + l21 * d2, l22 * d2], -1)


def _mip_fn(args: ModelArgs):
    """The mip chain of the map as a function of the solver's variables ``z``."""
    opts = args.prepared.options[0]
    return lambda z: mip_chain(slopes_to_normals(z * args.scale), opts)


def _smooth_fn(args: ModelArgs):
    return lambda z: smoothness_residuals(z * args.scale, args.smoothness)


def _batch_sums(args: ModelArgs, b: int):
    """The texel sums of batch ``b`` (`texel_sum_tables`), or None (scatter-adds)."""
    return None if args.texel_sums is None else args.texel_sums[b]


def _add(a, b):
    return jax.tree_util.tree_map(jnp.add, a, b)


def _gauss_newton_parts(z: Array, args: ModelArgs) -> tuple[Array, Array, tuple[Array, ...]]:
    """One pass over every pixel of ``args.prepared``: the loss ``0.5 |r|^2``, its gradient
    w.r.t. ``z`` (h, w, 2), and each pixel's Gram factor ``L`` per `ViewBatch` (as
    `TexelLMState.factors`).

    The gradient is ``A^T (L rho)`` (``L rho = B^T r``) summed in the mip chain, then
    pulled back to ``z`` through the (texel-space) mip chain; the smoothness penalty's
    share is added exactly."""
    prep = args.prepared
    opts = prep.options[0]
    mips, mips_vjp = jax.vjp(_mip_fn(args), z)
    f = jnp.zeros((), z.dtype)
    cot = jax.tree_util.tree_map(jnp.zeros_like, mips)

    def reduce(m, gb, lights, images, weights):
        return reduce_pixels(m, gb, lights, prep.material, opts.shading,
                       jnp.asarray(args.strength, m.dtype), images, weights)

    factors = []
    for b, batch in enumerate(prep.batches):
        def body(carry, gb, lights, images, weights, taps, _, tables):
            f, cot = carry
            m, pull = _sampler(first_taps(gb.plan, taps), mips, tables)
            rho, e, lower = jax.vmap(reduce)(m, gb, lights, images, weights)
            f = f + 0.5 * (jnp.sum(rho * rho) + jnp.sum(e * e))
            return (f, _add(cot, pull(_lower_times(lower, rho)))), lower

        (f, cot), lower = _fold(batch, body, (f, cot), sums=_batch_sums(args, b))
        factors.append(lower)
    g = mips_vjp(cot)[0]
    if args.smoothness is not None:
        s, s_vjp = jax.vjp(_smooth_fn(args), z)
        f = f + 0.5 * jnp.sum(s * s)
        g = g + s_vjp(s)[0]
    return f, g, tuple(factors)


def _gauss_newton_product(z: Array, args: ModelArgs, factors):
    """``v -> H v`` at ``z``: the Gauss-Newton matrix from the stored ``factors`` (one gather
    and one scatter per pixel), plus the smoothness penalty's (exact) share."""
    prep = args.prepared
    _, mips_jvp = jax.linearize(_mip_fn(args), z)
    mips_t = jax.linear_transpose(mips_jvp, z)
    smooth_jvp = smooth_t = None
    if args.smoothness is not None:
        _, smooth_jvp = jax.linearize(_smooth_fn(args), z)
        smooth_t = jax.linear_transpose(smooth_jvp, z)

    def product(v):
        dmips = mips_jvp(v)
        cot = jax.tree_util.tree_map(jnp.zeros_like, dmips)
        for b, (batch, lower) in enumerate(zip(prep.batches, factors)):
            def body(cot, gb, lights, images, weights, taps, lower_c, tables, dmips=dmips):
                dm, pull = _sampler(first_taps(gb.plan, taps), dmips, tables)
                y = _lower_times(lower_c, _lower_transpose_times(lower_c, dm))
                return _add(cot, pull(y)), None

            cot, _ = _fold(batch, body, cot, lower, _batch_sums(args, b))
        out = mips_t(cot)[0]
        if smooth_t is not None:
            out = out + smooth_t(smooth_jvp(v))[0]
        return out

    return product


def conjugate_gradient(operator, b: Array, max_steps: int, rtol: float = 1e-4) -> Array:
    """Conjugate gradients for ``operator(x) = b`` (symmetric positive definite), from
    ``x = 0``, for at most ``max_steps`` products or until ``|r| <= rtol |b|``.

    Written out rather than lineax's ``CG``: that one spends a product on the residual of
    its zero start and another every ten steps to re-stabilise it, and it reports a
    breakdown (NaN) wherever ``p.Ap <= 100 eps n |r|^2`` — a test in absolute units that
    a Gauss-Newton matrix with weakly observed texels (curvature ~ the damping) fails.
    On accelerators (programs that must not wait for the host), always ``max_steps``
    iterations, the iterate frozen once the test ends it (the same result)."""
    gamma0 = jnp.sum(b * b)
    stop = (rtol * rtol) * gamma0

    def more(state):
        _, _, _, gamma, k = state
        return (k < max_steps) & (gamma > stop)

    def body(state):
        x, r, p, gamma, k = state
        ap = operator(p)
        pap = jnp.sum(p * ap)
        alpha = jnp.where(pap > 0, gamma / jnp.where(pap > 0, pap, 1), 0)
        x = x + alpha * p
        r = r - alpha * ap
        gamma_new = jnp.sum(r * r)
        p = r + (gamma_new / jnp.maximum(gamma, jnp.finfo(b.dtype).tiny)) * p
        # a breakdown (p.Ap <= 0) ends the loop with the iterate so far
        return x, r, p, jnp.where(pap > 0, gamma_new, 0), k + 1

    state = (jnp.zeros_like(b), b, b, gamma0, jnp.zeros((), jnp.int32))
    if not resident():
        return jax.lax.while_loop(more, body, state)[0]

    # where programs are resident (`jaxnm._exec.device`): ``max_steps`` iterations, a loop
    # of known trip count (a GPU reads no condition back), the state kept as it is once the
    # test ends it: the same iterate, for the products a converged solve would have skipped
    def step(_, state):
        go = more(state)
        return jax.tree_util.tree_map(lambda new, old: jnp.where(go, new, old), body(state),
                                      state)

    return jax.lax.fori_loop(0, max_steps, step, state)[0]


def _damping(lam, ratio, accepted):
    """The damping after a step of gain ``ratio`` (actual over predicted decrease), by the
    rule of `optimistix.ClassicalTrustRegion` (its defaults; ``lambda`` is the inverse of
    its step size): a rejected step (ratio < 0.01) multiplies it by 4, a step the model
    predicted well (ratio > 0.99) divides it by 3.5, any other keeps it."""
    good = accepted & (ratio > 0.99)
    return jnp.where(accepted, jnp.where(good, lam / 3.5, lam), 4.0 * lam)


@dataclasses.dataclass(frozen=True)
class TexelLM:
    """Levenberg–Marquardt on the texel-space normal equations (see the module).

    - `cg_steps`: conjugate-gradient iterations per step (``FitOptions.lsmr_steps``).
    - `rtol`, `atol`: the step's termination test, as optimistix's: the accepted move and
      loss change are both below ``atol + rtol * |value|``.
    - `lam0`: the first damping, relative to the Gauss-Newton curvature along the first
      gradient (0.1: with 1e-3, on test_fit's small problem, the damping fell so low that
      six steps in a row were rejected before it had grown back).
    """

    cg_steps: int = 20
    rtol: float = 1e-6
    atol: float = 1e-9
    lam0: float = 0.1

    def init(self, z: Array, args: ModelArgs) -> TexelLMState:
        """The state before the first step (which evaluates ``z``): zeros made on the host
        and put on the device in buffers of their own (as an XLA program it would be one
        more compilation)."""
        dt = np.dtype(z.dtype)
        factors = tuple(tuple(np.zeros(shape, dt) for shape in _factor_shapes(b))
                        for b in args.prepared.batches)
        zero = np.zeros((), dt)
        return jax.device_put(TexelLMState(
            f=np.full((), np.inf, dt), g=np.zeros(z.shape, dt), factors=factors,
            delta=np.zeros(z.shape, dt), predicted=zero, lam=zero.copy()), may_alias=False)

    def step(self, z: Array, state: TexelLMState, args: ModelArgs):
        """Evaluate the proposed point, accept or reject it, propose the next move.

        Returns ``(z, state, done, result, loss)`` with ``z`` the accepted point and
        ``loss`` its loss."""
        tiny = jnp.finfo(z.dtype).tiny
        first = ~jnp.isfinite(state.f)
        trial = z + state.delta
        f_t, g_t, factors_t = _gauss_newton_parts(trial, args)
        ratio = (state.f - f_t) / jnp.maximum(state.predicted, tiny)
        accepted = first | ((f_t < state.f) & (ratio >= 0.01))
        pick = lambda new, old: jnp.where(accepted, new, old)  # noqa: E731
        z_new = pick(trial, z)
        f, g = pick(f_t, state.f), pick(g_t, state.g)
        factors = jax.tree_util.tree_map(pick, factors_t, state.factors)
        product = _gauss_newton_product(z_new, args, factors)

        def start_damping():  # lam0 times the curvature along the gradient (first step only)
            return self.lam0 * jnp.sum(g * product(g)) / jnp.maximum(jnp.sum(g * g), tiny)

        # (`choose`: on accelerators both, and a select; the first costs one product)
        lam = choose(first, start_damping, lambda: _damping(state.lam, ratio, accepted))
        lam = jnp.maximum(lam, tiny)
        delta = conjugate_gradient(lambda v: product(v) + lam * v, -g, self.cg_steps)
        # the decrease the model predicts, -(g.d + d.H d / 2): a CG iterate d from 0 has
        # d.(H + lam I) d = -g.d (its residual is orthogonal to the Krylov space it lies in),
        # which saves a product
        predicted = 0.5 * (lam * jnp.sum(delta * delta) - jnp.sum(g * delta))
        moved = jnp.max(jnp.abs(z_new - z)) <= self.atol + self.rtol * jnp.max(jnp.abs(z_new))
        flat = jnp.abs(state.f - f) <= self.atol + self.rtol * jnp.abs(f)
        done = ~first & accepted & moved & flat
        new_state = TexelLMState(f=f, g=g, factors=factors, delta=delta, predicted=predicted,
                                 lam=lam)
        return z_new, new_state, done, optx.RESULTS.successful, f
