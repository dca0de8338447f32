"""A fusion barrier that XLA keeps (`materialize`).

XLA's CPU backend fuses a producer into every consumer that reads it and recomputes it
there; where several consumers read one per-pixel value (a texture gather, the barycentric
set-up of a pixel), that recomputation can cost several times the value itself.
`jax.lax.optimization_barrier` does not stop it on the CPU; `materialize` does.

On the other backends (`jaxnm._exec.device.resident`) `materialize` is an
`jax.lax.optimization_barrier`: XLA's GPU compiler removes the barriers only after fusion
and scheduling, so they keep their values out of the fusions that follow, and a GPU would
read a data-dependent loop's condition on the host.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from .device import resident

__all__ = ["materialize"]


@jax.custom_jvp
def materialize(x):
    """``x`` (an array or a pytree of arrays), computed once into its own buffer.

    A fusion barrier that XLA keeps: XLA CPU may fuse a producer (a texture
    gather, barycentric setup) into *every* consumer and recompute it per use,
    which can cost several times the value itself; `jax.lax.optimization_barrier` is
    dropped on CPU. The
    value goes through a while loop whose trip count (0 or 1; the body is an
    identity) depends on the data, so the compiler can neither delete the loop
    nor fuse across it. An identity for values and (forward and reverse)
    derivatives; use it where profiling shows recomputation. Where programs are
    `jaxnm._exec.device.resident` (every backend but the CPU), a
    `jax.lax.optimization_barrier` instead, which those compilers keep until after fusion.
    """
    if resident():
        return jax.lax.optimization_barrier(x)
    leaves = jax.tree_util.tree_leaves(x)
    probe = leaves[0].reshape(-1)[0]
    one = jax.lax.bitcast_convert_type(probe.astype(jnp.float32), jnp.int32) & 1

    def keep(a, k):
        # Make ``a`` loop-variant (an untouched value would be hoisted out of the loop and
        # fused into its consumers): XLA does not fold float "0 * k" (it could be NaN), nor
        # a select on the counter's sign (it never is negative, which XLA does not prove).
        if jnp.issubdtype(a.dtype, jnp.floating):
            return a + 0.0 * k.astype(a.dtype)
        return jnp.where(k < 0, jnp.zeros_like(a), a)

    def body(c):
        k, v = c
        return k + 1, jax.tree_util.tree_map(lambda a: keep(a, k), v)

    return jax.lax.while_loop(lambda c: c[0] < one, body, (jnp.int32(0), x))[1]


@materialize.defjvp
def _materialize_jvp(primals, tangents):
    (x,), (dx,) = primals, tangents
    return materialize(x), dx
