"""The true entries of a boolean mask, as indices: ``jnp.nonzero`` with a size, and by rank.

The covered pixels of an image and the triangles that have slots are listed this way. Both
functions give what ``jnp.nonzero(mask, size=..., fill_value=...)`` gives; they differ in the
work XLA's CPU backend does for it (see each function).
"""

from __future__ import annotations

from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array
from jax.typing import ArrayLike

from .arrays import cumsum
from .fusion import materialize

__all__ = ["flat_nonzero", "ranked_nonzero"]


def flat_nonzero(mask: ArrayLike, size: int, fill_value: int) -> Array:
    """The indices (int32, ascending) of the true entries of a 1-D boolean ``mask``, the
    first ``size`` of them, then ``fill_value``: ``jnp.nonzero(mask, size=size,
    fill_value=fill_value)[0]``.

    Two ways, by the work each costs on XLA's CPU. A mask of 2^16 entries or more (an
    image's pixels, a large mesh's triangles) is packed into 32-bit words, and each *output*
    slot finds its entry: which word by a running count of the words' set bits, which bit
    from the word's bytes and a table; the mask is read once, and the running sum is over a
    32nd of it. A smaller one takes one running sum (`cumsum`) and one scatter."""
    mask = jnp.asarray(mask)
    if mask.ndim != 1 or mask.dtype != jnp.bool_:
        raise ValueError(f"flat_nonzero: expected a 1-D boolean mask, got "
                         f"{mask.dtype}{mask.shape}")
    if mask.shape[0] >= _WORDS_FROM:
        return _nonzero_by_words(mask, size, fill_value)
    return _nonzero_by_scatter(mask, size, fill_value)


#: `flat_nonzero` packs masks of at least this many entries into words.
_WORDS_FROM = 1 << 16


def _nonzero_by_scatter(mask: Array, size: int, fill_value: int) -> Array:
    """`flat_nonzero` by a running sum over the entries and a scatter of each into place."""
    n = mask.shape[0]
    slot = cumsum(mask.astype(jnp.int32)) - 1  # each true entry's place in the output
    # the false entries go to distinct places past the end (dropped), so the scatter's
    # indices are unique, as XLA is told: deterministic GPU ops then leave it alone
    # (a set with repeated indices they sort or serialise)
    past = max(size, n) + jnp.arange(n, dtype=jnp.int32)
    return jnp.full((size,), fill_value, jnp.int32).at[jnp.where(mask, slot, past)].set(
        jnp.arange(n, dtype=jnp.int32), mode="drop", unique_indices=True)


def _nth_bit_table() -> np.ndarray:
    """``t[v * 8 + j]``: the position of the ``j``-th set bit (0-based) of the byte ``v``
    (0 where it has fewer)."""
    t = np.zeros((256, 8), np.int32)
    for v in range(256):
        ones = [b for b in range(8) if v >> b & 1]
        t[v, :len(ones)] = ones
    return t.reshape(-1)


_NTH_BIT = _nth_bit_table()


def _nonzero_by_words(mask: Array, size: int, fill_value: int) -> Array:
    """`flat_nonzero` from the output side (`ranked_nonzero`)."""
    return ranked_nonzero(mask)[1](0, size, fill_value)


def ranked_nonzero(mask: ArrayLike) -> tuple[Array, Callable[[ArrayLike, int, int], Array]]:
    """The true entries of a 1-D boolean ``mask`` by rank: ``(total, window)``, where
    ``total`` is their number and ``window(first, size, fill_value)`` the indices (int32,
    ascending) of those ranked ``first`` to ``first + size - 1`` (``first`` may be traced),
    then ``fill_value``: ``jnp.nonzero(mask, size=first + size, fill_value=fill_value)[0][
    first:]``. Each window costs work in its ``size`` and a 32nd of the mask's length, not
    the mask's length: a long mask's entries can be taken a window at a time.

    The mask is packed into 32-bit words once, with a running count of their set bits; each
    *output* slot then finds its entry: which word by the running count of the words that
    start in the window, which bit from the word's bytes and a table."""
    mask = jnp.asarray(mask)
    if mask.ndim != 1 or mask.dtype != jnp.bool_:
        raise ValueError(f"ranked_nonzero: expected a 1-D boolean mask, got "
                         f"{mask.dtype}{mask.shape}")
    n = mask.shape[0]
    n_words = -(-n // 32)
    bits = jnp.pad(mask, (0, n_words * 32 - n)).reshape(n_words, 32)
    words = bits[:, 0].astype(jnp.uint32)
    for i in range(1, 32):  # (slices and ors: one loop over the words)
        words = words | (bits[:, i].astype(jnp.uint32) << i)
    # computed once (fused into the slots' gather, XLA would pack a word again per slot)
    words = materialize(words)
    counts = jax.lax.population_count(words).astype(jnp.int32)
    ends = cumsum(counts)
    starts = ends - counts
    total = ends[-1]
    # the words with a true entry, in order
    busy = _nonzero_by_scatter(counts > 0, n_words, 0)

    def window(first, size: int, fill_value: int) -> Array:
        if isinstance(first, int) and first == 0:
            # from the first entry (`flat_nonzero`): each busy word's first slot marked,
            # the running count of marks up to slot s is the rank of the word holding s
            s = jnp.arange(size, dtype=jnp.int32)
            marks = jnp.zeros((size,), jnp.int32).at[jnp.where(counts > 0, starts, size)].add(
                1, mode="drop")
            w = busy[jnp.clip(cumsum(marks) - 1, 0, n_words - 1)]
        else:
            first = jnp.asarray(first, jnp.int32)
            s = first + jnp.arange(size, dtype=jnp.int32)
            # the busy words ending at or before `first` are passed; the running count of
            # the busy words starting after it, up to slot s, is the rank of the one
            # holding s (past the busy words: above every rank)
            some = jnp.arange(n_words) < jnp.sum(counts > 0)
            big = np.iinfo(np.int32).max
            passed = jnp.searchsorted(jnp.where(some, ends[busy], big), first,
                                      side="right").astype(jnp.int32)
            after = jnp.where(some, starts[busy], big) - first
            marks = jnp.zeros((size,), jnp.int32).at[
                jnp.where((after > 0) & (after < size), after, size)].add(1, mode="drop")
            w = busy[jnp.clip(passed + cumsum(marks), 0, n_words - 1)]
        word, j = words[w], s - starts[w]  # the j-th set bit of `word` (0-based)
        # which byte: the first whose end has more than j set bits below it
        below = [jax.lax.population_count(word & jnp.uint32((1 << (8 * k)) - 1)).astype(
            jnp.int32) for k in (1, 2, 3)]
        byte = sum((j >= b).astype(jnp.int32) for b in below)
        skipped = jax.lax.population_count(
            word & ((jnp.uint32(1) << (8 * byte).astype(jnp.uint32)) - 1)).astype(jnp.int32)
        value = ((word >> (8 * byte).astype(jnp.uint32)) & jnp.uint32(0xFF)).astype(jnp.int32)
        bit = 8 * byte + jnp.asarray(_NTH_BIT)[value * 8 + (j - skipped)]
        return jnp.where(s < total, w * 32 + bit, fill_value)

    return total, window
