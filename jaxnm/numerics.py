"""Numerically safe primitives, forward *and* backward.

Every normalisation, division and square root in jaxnm goes through this
module. Each function is finite in value and gradient for every finite input,
including the singular points (zero vectors, zero denominators), where it
returns a documented fallback whose gradient is zero.

The pattern is the "double where": the unsafe branch is fed a harmless
substitute input where it would be singular, so that neither its value nor its
(discarded) gradient can be NaN, and the outer ``where`` selects the fallback.
A single ``where`` is not enough for reverse-mode AD: the cotangent of the
unselected branch is multiplied by zero, and ``0 * inf`` is NaN.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array
from jax.typing import ArrayLike

__all__ = [
    "sum_last", "dot", "spread", "cross", "eps", "tiny", "safe_div", "safe_sqrt", "safe_rsqrt",
    "safe_norm", "safe_normalize", "angle_between"
]


def sum_last(x: ArrayLike, keepdims: bool = False) -> Array:
    """Sum over a short last axis (e.g. 3 vector components), written out term by term.

    XLA's CPU reduction over a minor axis of length 3 is an order of magnitude
    slower than the equivalent chain of elementwise adds, which fuse with their
    producers; every small dot product in jaxnm goes through here.
    """
    x = jnp.asarray(x)
    out = x[..., 0]
    for i in range(1, x.shape[-1]):
        out = out + x[..., i]
    return out[..., None] if keepdims else out


def dot(a: ArrayLike, b: ArrayLike, keepdims: bool = False) -> Array:
    """Dot product over the (short) last axis, see `sum_last`."""
    a, b = jnp.asarray(a), jnp.asarray(b)
    if a.ndim != b.ndim:  # explicit rank alignment (rank promotion may be disabled)
        n = max(a.ndim, b.ndim)
        a = a.reshape((1,) * (n - a.ndim) + a.shape)
        b = b.reshape((1,) * (n - b.ndim) + b.shape)
    return sum_last(a * b, keepdims=keepdims)


def spread(x: ArrayLike, n: int = 3) -> Array:
    """``x`` (..., 1) repeated to (..., n) along its last axis, as a concatenation.

    For a per-pixel scalar that scales a vector (a normalisation, a cosine times a
    colour): broadcasting it is free in the forward pass, but reverse mode transposes a
    broadcast into a reduction over the minor axis of ``n``, which XLA's CPU runs
    through a library call an order of magnitude slower than it should be (one such
    reduction over 65536 pixels took a fifth of a whole frame's gradient). The
    transpose of a concatenation is slices and elementwise adds, which fuse. The values
    are the same either way.
    """
    x = jnp.asarray(x)
    if x.shape[-1:] != (1,):
        raise ValueError(f"spread: expected a last axis of 1, got shape {x.shape}")
    return jnp.concatenate([x] * n, axis=-1)


def _roll_last(x: ArrayLike, shift: int) -> Array:
    """``x[..., (i + shift) % n]`` for a short last axis, as slices (tuple indexing is a gather)."""
    x = jnp.asarray(x)
    k = shift % x.shape[-1]
    return x if k == 0 else jnp.concatenate([x[..., k:], x[..., :k]], -1)


def _xyw(h: ArrayLike) -> Array:
    """The x, y and w components of homogeneous ``(..., 4)`` points, as slices."""
    h = jnp.asarray(h)
    return jnp.concatenate([h[..., 0:2], h[..., 3:4]], -1)


def cross(a: ArrayLike, b: ArrayLike) -> Array:
    """``a x b`` over the last axis (length 3), written out (fuses better than ``jnp.cross``)."""
    a, b = jnp.asarray(a), jnp.asarray(b)
    a0, a1, a2 = a[..., 0:1], a[..., 1:2], a[..., 2:3]
    b0, b1, b2 = b[..., 0:1], b[..., 1:2], b[..., 2:3]
    return jnp.concatenate([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0], -1)


def _cumsum(x: ArrayLike, block: int = 8) -> Array:
    """Inclusive running sum of a 1-D integer array: `jnp.cumsum`, faster on XLA's CPU.

    Exact (integer adds in the array's dtype, wrapping as they do). ``jnp.cumsum``
    lowers to a tree of reduce-windows and a gather-like combine. Here: running sums within
    blocks of ``block`` by ``log2(block)`` shifted adds, the blocks' totals summed the same
    way, one level down (until a level fits in one block), then added back: about a quarter
    of the time on XLA's CPU.
    """
    x = jnp.asarray(x)
    if x.ndim != 1 or not jnp.issubdtype(x.dtype, jnp.integer):
        raise ValueError(f"_cumsum: expected a 1-D integer array, got {x.dtype}{x.shape}")
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
    before = _cumsum(total, block) - total  # the blocks ahead of each block
    return (run + before[:, None]).reshape(-1)[:n]


def _flat_nonzero(mask: ArrayLike, size: int, fill_value: int) -> Array:
    """The indices (int32, ascending) of the true entries of a 1-D boolean ``mask``, the
    first ``size`` of them, then ``fill_value``: ``jnp.nonzero(mask, size=size,
    fill_value=fill_value)[0]``.

    Two ways, by the work each costs on XLA's CPU. A mask of 2^16 entries or more (an
    image's pixels, a large mesh's triangles) is packed into 32-bit words, and each *output*
    slot finds its entry: which word by a running count of the words' set bits, which bit
    from the word's bytes and a table; the mask is read once, and the running sum is over a
    32nd of it. A smaller one takes one running sum (`_cumsum`) and one scatter."""
    mask = jnp.asarray(mask)
    if mask.ndim != 1 or mask.dtype != jnp.bool_:
        raise ValueError(f"_flat_nonzero: expected a 1-D boolean mask, got "
                         f"{mask.dtype}{mask.shape}")
    if mask.shape[0] >= _WORDS_FROM:
        return _nonzero_by_words(mask, size, fill_value)
    return _nonzero_by_scatter(mask, size, fill_value)


#: `_flat_nonzero` packs masks of at least this many entries into words.
_WORDS_FROM = 1 << 16


def _nonzero_by_scatter(mask: Array, size: int, fill_value: int) -> Array:
    """`_flat_nonzero` by a running sum over the entries and a scatter of each into place."""
    n = mask.shape[0]
    slot = _cumsum(mask.astype(jnp.int32)) - 1  # each true entry's place in the output
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
    """`_flat_nonzero` from the output side (`_ranked_nonzero`)."""
    return _ranked_nonzero(mask)[1](0, size, fill_value)


def _ranked_nonzero(mask: ArrayLike) -> tuple[Array, Callable[[ArrayLike, int, int], Array]]:
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
        raise ValueError(f"_ranked_nonzero: expected a 1-D boolean mask, got "
                         f"{mask.dtype}{mask.shape}")
    n = mask.shape[0]
    n_words = -(-n // 32)
    bits = jnp.pad(mask, (0, n_words * 32 - n)).reshape(n_words, 32)
    words = bits[:, 0].astype(jnp.uint32)
    for i in range(1, 32):  # (slices and ors: one loop over the words)
        words = words | (bits[:, i].astype(jnp.uint32) << i)
    # computed once (fused into the slots' gather, XLA would pack a word again per slot)
    words = _materialize(words)
    counts = jax.lax.population_count(words).astype(jnp.int32)
    ends = _cumsum(counts)
    starts = ends - counts
    total = ends[-1]
    # the words with a true entry, in order
    busy = _nonzero_by_scatter(counts > 0, n_words, 0)

    def window(first, size: int, fill_value: int) -> Array:
        if isinstance(first, int) and first == 0:
            # from the first entry (`_flat_nonzero`): each busy word's first slot marked,
            # the running count of marks up to slot s is the rank of the word holding s
            s = jnp.arange(size, dtype=jnp.int32)
            marks = jnp.zeros((size,), jnp.int32).at[jnp.where(counts > 0, starts, size)].add(
                1, mode="drop")
            w = busy[jnp.clip(_cumsum(marks) - 1, 0, n_words - 1)]
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
            w = busy[jnp.clip(passed + _cumsum(marks), 0, n_words - 1)]
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


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class _SumTables:
    """A fixed sparse sum ``out[d] = sum of values[i] with dest[i] == d`` as fixed-order sums
    (`_sum_tables` builds it, `_sum_by_tables` applies it).

    - `tables`: per level, (..., R_k, W) int32 rows of indices into the previous level's
      rows (the first level's into the values); the entries of a row share one destination,
      in the values' order; an index past the end (`_SumTables.PAD`) reads 0.
    - `targets`: (..., R_1 + R_2 + ...) int32, each row's destination where the row is its
      destination's last (complete) sum, else past ``size`` (each such row its own index,
      so that the targets stay distinct), and dropped.
    - `size` (static): the number of destinations.

    Leading axes (``...``) stack several sums of the same shapes (e.g. one per chunk of a
    loop), to be indexed before use."""

    tables: tuple[Array, ...]
    targets: Array
    size: int = dataclasses.field(metadata=dict(static=True))

    #: The index of an empty entry.
    PAD = np.iinfo(np.int32).max


def _table_levels(dest: np.ndarray, width: int) -> tuple[list, list]:
    """`_sum_tables` for one destination array: its tables, and per level the destination
    of each row that completes one (-1 for the rest)."""
    d = dest.ravel()
    ids = np.argsort(d, kind="stable")  # each destination's entries in the values' order
    d = d[ids]
    tables, targets = [], []
    while d.size or not tables:
        starts = np.flatnonzero(np.r_[True, d[1:] != d[:-1]]) if d.size else np.zeros(0, int)
        lengths = np.diff(np.r_[starts, d.size])
        rows = -(-lengths // width)  # a destination's entries cut into rows of `width`
        first = np.cumsum(rows) - rows
        seg = np.repeat(np.arange(starts.size), lengths)
        pos = np.arange(d.size) - starts[seg]
        table = np.full((int(rows.sum()), width), _SumTables.PAD, np.int32)
        table[first[seg] + pos // width, pos % width] = ids
        tables.append(table)
        row_dest = np.repeat(d[starts], rows)
        done = np.repeat(rows == 1, rows)  # the destination's sum is complete
        targets.append(np.where(done, row_dest, -1))
        d, ids = row_dest[~done], np.flatnonzero(~done)  # the rest: summed again
    return tables, targets


def _sum_tables(dests, size: int, width: int = 8) -> _SumTables:
    """Host-side (NumPy) construction of the `_SumTables` of destination arrays ``dests`` (one
    integer array, or a list of them to stack: their sums get common shapes), each entry in
    ``[0, size)``.

    Each level sums rows of ``width`` entries of one destination, term by term in a fixed
    order; a destination with more than ``width`` entries has its rows summed again at the
    next level (``ceil(log_width(n))`` levels for ``n`` entries). The result is therefore the
    same on every run and every device, unlike a scatter-add, whose order of additions is
    whatever the hardware's atomics make it (GPUs), or which costs a sort of the indices on
    every call where XLA makes it deterministic. Worth it where the same ``dests`` are summed
    into many times (a fit's texel sums: built once, used in every conjugate-gradient
    iteration)."""
    many = isinstance(dests, (list, tuple))
    dests = [np.asarray(d) for d in (dests if many else [dests])]
    for d in dests:
        if not np.issubdtype(d.dtype, np.integer):
            raise ValueError(f"_sum_tables: destinations must be integers, got {d.dtype}")
        if d.size and (d.min() < 0 or d.max() >= size):
            raise ValueError(f"_sum_tables: destinations must be in [0, {size}), found "
                             f"{d.min() if d.min() < 0 else d.max()}")
    if width < 2:
        raise ValueError(f"_sum_tables: width must be at least 2, got {width}")
    built = [_table_levels(d, width) for d in dests]
    depth = max(len(tables) for tables, _ in built)
    empty = (np.zeros((0, width), np.int32), np.zeros(0, int))
    tables, targets = [], []
    for k in range(depth):  # each level padded to its largest row count
        level = [(b[0][k], b[1][k]) if k < len(b[0]) else empty for b in built]
        rows = max(t.shape[0] for t, _ in level)
        tables.append(np.stack([np.pad(t, ((0, rows - t.shape[0]), (0, 0)),
                                       constant_values=_SumTables.PAD) for t, _ in level]))
        targets.append(np.stack([np.pad(g, (0, rows - g.size), constant_values=-1)
                                 for _, g in level]))
    targets = np.concatenate(targets, 1)
    # the rows that complete nothing: distinct destinations past `size`, dropped
    targets = np.where(targets < 0, size + np.arange(targets.shape[1]), targets).astype(np.int32)
    if not many:
        tables, targets = [t[0] for t in tables], targets[0]
    # cut and put on the device from the host: cutting device arrays, or `jnp.asarray` of
    # NumPy arrays, compiles a small program per shape
    return _SumTables(tuple(jax.device_put(t) for t in tables), jax.device_put(targets), size)


def _sum_by_tables(values: ArrayLike, tables: _SumTables) -> Array:
    """``out[d] = sum of values[i] with dest[i] == d`` for the ``dest`` of ``tables``
    (`_sum_tables`; unstacked): ``values`` (N, ...) -> (size, ...), in a fixed order.

    Gathers and adds only, then one scatter to distinct destinations (which XLA need not make
    deterministic: it is). Differentiable in ``values`` (the transpose is gathers)."""
    v = jnp.asarray(values)
    if v.shape[0] == 0:  # nothing to sum (every index is a pad); a gather needs an operand
        v = jnp.zeros((1,) + v.shape[1:], v.dtype)
    sums = []
    for table in tables.tables:
        rows = v.at[table].get(mode="fill", fill_value=0)  # (R, W, ...)
        v = rows[:, 0]
        for j in range(1, rows.shape[1]):
            v = v + rows[:, j]
        sums.append(v)
    out = jnp.zeros((tables.size,) + v.shape[1:], v.dtype)
    return out.at[tables.targets].set(jnp.concatenate(sums, 0), mode="drop",
                                      unique_indices=True)


@jax.custom_jvp
def _materialize(x):
    """``x`` (an array or a pytree of arrays), computed once into its own buffer.

    A fusion barrier that XLA keeps: XLA CPU may fuse a producer (a texture
    gather, barycentric setup) into *every* consumer and recompute it per use,
    which can cost 5-10x; `jax.lax.optimization_barrier` is dropped on CPU. The
    value goes through a while loop whose trip count (0 or 1; the body is an
    identity) depends on the data, so the compiler can neither delete the loop
    nor fuse across it. An identity for values and (forward and reverse)
    derivatives; use it where profiling shows recomputation.
    """
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


@_materialize.defjvp
def _materialize_jvp(primals, tangents):
    (x,), (dx,) = primals, tangents
    return _materialize(x), dx


def eps(dtype) -> float:
    """Relative tolerance used for "numerically zero" tests, about 8 units of rounding:
    1e-6 (f32), 1e-12 (f64), 1e-3 (f16), 1e-2 (bf16)."""
    dtype = jnp.dtype(dtype)
    if dtype == jnp.float64:
        return 1e-12
    if dtype == jnp.bfloat16:
        return 1e-2
    if dtype == jnp.float16:
        return 1e-3
    return 1e-6


def tiny(dtype) -> float:
    """Smallest magnitude treated as non-zero in a denominator (well above the subnormals)."""
    dtype = jnp.dtype(dtype)
    if dtype == jnp.float64:
        return 1e-200
    if dtype in (jnp.float16, jnp.bfloat16):
        return 1e-4
    return 1e-30


def safe_div(num: ArrayLike, den: ArrayLike, fallback: ArrayLike = 0.0) -> Array:
    """``num / den`` where ``|den| > tiny``; ``fallback`` (zero gradient) elsewhere."""
    num = jnp.asarray(num)
    den = jnp.asarray(den)
    ok = jnp.abs(den) > tiny(jnp.result_type(num, den))
    den_safe = jnp.where(ok, den, jnp.ones_like(den))
    return jnp.where(ok, num / den_safe, fallback)


def safe_sqrt(x: ArrayLike) -> Array:
    """``sqrt(max(x, 0))`` with a zero (not infinite) gradient at and below zero."""
    x = jnp.asarray(x)
    ok = x > tiny(x.dtype)
    return jnp.where(ok, jnp.sqrt(jnp.where(ok, x, jnp.ones_like(x))), 0.0)


def safe_rsqrt(x: ArrayLike, fallback: ArrayLike = 0.0) -> Array:
    """``1/sqrt(x)`` for ``x > tiny``; ``fallback`` elsewhere (where GLSL's ``inversesqrt`` is
    undefined)."""
    x = jnp.asarray(x)
    ok = x > tiny(x.dtype)
    return jnp.where(ok, jnp.reciprocal(jnp.sqrt(jnp.where(ok, x, jnp.ones_like(x)))), fallback)


def safe_norm(v: ArrayLike, axis: int = -1, keepdims: bool = False) -> Array:
    """Euclidean norm along ``axis``; gradient zero (not NaN) at the zero vector."""
    v = jnp.moveaxis(jnp.asarray(v), axis, -1)
    out = safe_sqrt(dot(v, v, keepdims=keepdims))
    return jnp.moveaxis(out, -1, axis) if keepdims else out


def safe_normalize(v: ArrayLike, axis: int = -1, fallback: ArrayLike | None = None) -> Array:
    """``v / |v|``; where ``|v|`` is (numerically) zero, returns ``fallback``.

    ``fallback`` broadcasts against ``v`` and defaults to the zero vector. Pass,
    for example, the unperturbed normal so that a degenerate input degrades
    gracefully instead of producing NaN.
    """
    v = jnp.asarray(v)
    if axis in (-1, v.ndim - 1):
        sq = dot(v, v, keepdims=True)
    else:
        sq = jnp.sum(v * v, axis=axis, keepdims=True)
    ok = sq > tiny(v.dtype)
    inv = jnp.reciprocal(jnp.sqrt(jnp.where(ok, sq, jnp.ones_like(sq))))
    if fallback is None:
        fallback = jnp.zeros_like(v)
    if axis in (-1, v.ndim - 1):
        inv = spread(inv, v.shape[-1])
    return jnp.where(ok, v * inv, jnp.asarray(fallback, v.dtype))


def angle_between(a: ArrayLike, b: ArrayLike, axis: int = -1) -> Array:
    """Angle in radians between vectors ``a`` and ``b`` along ``axis``.

    Uses ``atan2(|a x b|, a . b)``, accurate for tiny and near-pi angles (where
    ``arccos`` of a dot product loses half the digits) and finite in gradient
    for parallel or zero vectors. Only 3-vectors are supported.
    """
    a = jnp.asarray(a)
    b = jnp.asarray(b)
    a, b = jnp.moveaxis(a, axis, -1), jnp.moveaxis(b, axis, -1)
    y = safe_norm(cross(a, b))
    x = dot(a, b)
    ok = (y * y + x * x) > tiny(x.dtype)  # atan2's gradient is 0/0 at the origin
    return jnp.where(ok, jnp.arctan2(jnp.where(ok, y, 0.0), jnp.where(ok, x, 1.0)), 0.0)
