"""Fixed-order sparse sums: ``out[d] = sum of values[i] with dest[i] == d`` without atomics.

A scatter-add's order of additions is whatever the hardware's atomics make it (GPUs), or
costs a sort of the indices on every call where XLA makes it deterministic. The tables here
fix the order once, on the host, for destinations that are summed into many times.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array
from jax.typing import ArrayLike

__all__ = ["SumTables", "sum_by_tables", "sum_tables"]


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class SumTables:
    """A fixed sparse sum ``out[d] = sum of values[i] with dest[i] == d`` as fixed-order sums
    (`sum_tables` builds it, `sum_by_tables` applies it).

    - `tables`: per level, (..., R_k, W) int32 rows of indices into the previous level's
      rows (the first level's into the values); the entries of a row share one destination,
      in the values' order; an index past the end (`SumTables.PAD`) reads 0.
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
    """`sum_tables` for one destination array: its tables, and per level the destination
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
        table = np.full((int(rows.sum()), width), SumTables.PAD, np.int32)
        table[first[seg] + pos // width, pos % width] = ids
        tables.append(table)
        row_dest = np.repeat(d[starts], rows)
        done = np.repeat(rows == 1, rows)  # the destination's sum is complete
        targets.append(np.where(done, row_dest, -1))
        d, ids = row_dest[~done], np.flatnonzero(~done)  # the rest: summed again
    return tables, targets


def sum_tables(dests, size: int, width: int = 8) -> SumTables:
    """Host-side (NumPy) construction of the `SumTables` of destination arrays ``dests`` (one
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
            raise ValueError(f"sum_tables: destinations must be integers, got {d.dtype}")
        if d.size and (d.min() < 0 or d.max() >= size):
            raise ValueError(f"sum_tables: destinations must be in [0, {size}), found "
                             f"{d.min() if d.min() < 0 else d.max()}")
    if width < 2:
        raise ValueError(f"sum_tables: width must be at least 2, got {width}")
    built = [_table_levels(d, width) for d in dests]
    depth = max(len(tables) for tables, _ in built)
    empty = (np.zeros((0, width), np.int32), np.zeros(0, int))
    tables, targets = [], []
    for k in range(depth):  # each level padded to its largest row count
        level = [(b[0][k], b[1][k]) if k < len(b[0]) else empty for b in built]
        rows = max(t.shape[0] for t, _ in level)
        tables.append(np.stack([np.pad(t, ((0, rows - t.shape[0]), (0, 0)),
                                       constant_values=SumTables.PAD) for t, _ in level]))
        targets.append(np.stack([np.pad(g, (0, rows - g.size), constant_values=-1)
                                 for _, g in level]))
    targets = np.concatenate(targets, 1)
    # the rows that complete nothing: distinct destinations past `size`, dropped
    targets = np.where(targets < 0, size + np.arange(targets.shape[1]), targets).astype(np.int32)
    if not many:
        tables, targets = [t[0] for t in tables], targets[0]
    # cut and put on the device from the host: cutting device arrays, or `jnp.asarray` of
    # NumPy arrays, compiles a small program per shape
    return SumTables(tuple(jax.device_put(t) for t in tables), jax.device_put(targets), size)


def sum_by_tables(values: ArrayLike, tables: SumTables) -> Array:
    """``out[d] = sum of values[i] with dest[i] == d`` for the ``dest`` of ``tables``
    (`sum_tables`; unstacked): ``values`` (N, ...) -> (size, ...), in a fixed order.

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
