"""Small array operations in the forms XLA's CPU backend runs well.

Each computes what its NumPy counterpart does, exactly; the form differs: slices instead of
the gathers that tuple indexing lowers to, C division instead of floor division's sign
fix-ups, and a running sum by shifted adds instead of ``jnp.cumsum``'s reduce-windows.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jax import Array
from jax.typing import ArrayLike

__all__ = ["cumsum", "div", "xyw"]


def xyw(h: ArrayLike) -> Array:
    """The x, y and w components of homogeneous ``(..., 4)`` points, as slices."""
    h = jnp.asarray(h)
    return jnp.concatenate([h[..., 0:2], h[..., 3:4]], -1)


def cumsum(x: ArrayLike, block: int = 8) -> Array:
    """Inclusive running sum of a 1-D integer array: `jnp.cumsum`, faster on XLA's CPU.

    Exact (integer adds in the array's dtype, wrapping as they do). ``jnp.cumsum``
    lowers to a tree of reduce-windows and a gather-like combine. Here: running sums within
    blocks of ``block`` by ``log2(block)`` shifted adds, the blocks' totals summed the same
    way, one level down (until a level fits in one block), then added back: a fraction of
    the time on XLA's CPU (docs/guides/design.md).
    """
    x = jnp.asarray(x)
    if x.ndim != 1 or not jnp.issubdtype(x.dtype, jnp.integer):
        raise ValueError(f"cumsum: expected a 1-D integer array, got {x.dtype}{x.shape}")
    n = x.shape[0]
    if n <= block:
        return jnp.cumsum(x)  # (a reduce-window: also the fusion boundary for the levels above)
    m = -(-n // block)
    run = jnp.pad(x, (0, m * block - n)).reshape(m, block)
    k = 1
    while k < block:
        run = run + jnp.pad(run[:, :-k], ((0, 0), (k, 0)))
        k *= 2
    total = run[:, -1]
    before = cumsum(total, block) - total  # the blocks ahead of each block
    return (run + before[:, None]).reshape(-1)[:n]


def div(a: Array, b) -> Array:
    """``a // b`` for non-negative integers ``a`` and positive ``b``, as C division: jnp's
    floor division adds sign fix-ups to every loop it is in (the rasterizer's tile and
    pixel index arithmetic)."""
    return jax.lax.div(a, jnp.asarray(b, a.dtype))
