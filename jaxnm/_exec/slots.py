"""Triangle-parallel work in bounded memory: slots, rounds and passes.

The rasterizer's work is one *slot* per (triangle, tile) pair, for every tile of the image's
grid that a triangle's box touches (`jaxnm._exec.triangles`). Slots are numbered triangle
after triangle, and evaluated a fixed number at a time, a *round*, until all are done: the
memory of a frame is bounded, nothing is dropped, and the number of rounds adapts at run
time (on the CPU: a while loop; where programs are `jaxnm._exec.device.resident`, a fixed
number of rounds and a conditional overflow, `round_limits`). A frame that could count more
slots than int32 holds is split into *passes* over its
triangles. How the work is split is a `RasterStrategy`, which changes the time and memory
of a frame, never its result; `default_strategy` chooses one per backend and scene size.
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array

from .arrays import cumsum
from .compaction import flat_nonzero
from .device import resident

__all__ = ["MAX_SLOTS", "MAX_SLOTS_ACCELERATOR", "RESIDENT_SLOTS", "RasterStrategy", "SlotList",
           "default_strategy", "each_pass", "over_rounds", "round_limits", "slot_list",
           "slot_owners", "slot_passes"]


@dataclasses.dataclass(frozen=True)
class RasterStrategy:
    """How the rasterizer spends its work: the time and memory of a frame, never its result
    (every strategy gives the same triangle ids, depth and facing). Static (a `jax.jit`
    argument); `default_strategy` chooses one per backend and scene size.

    **Fields:**
    - `block`: the side of the square pixel tiles. A *slot* is one (triangle, tile) pair,
      for every tile a triangle's clipped bounding box touches; the depth buffer is stored
      tile by tile, and each slot's depth test is one scatter of a whole tile.
    - `slots`: the slots depth-tested together, a round (a fixed buffer); rounds repeat
      until every slot is done. A CPU wants rounds whose buffers stay in its caches, a GPU
      few large ones (its loop waits on the host for every round's condition).
    - `pass_slots`: a frame's slots are counted in int32; a frame that could have more
      than this many is depth-tested in passes over its triangles, each counting at most
      this many (a power of two; only huge images with tens of thousands of large
      triangles need more than one).
    """

    block: int = 4
    slots: int = 1 << 15
    pass_slots: int = 1 << 30

    def __post_init__(self):
        for name in ("block", "slots", "pass_slots"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < 1:
                raise ValueError(f"RasterStrategy: `{name}` must be a positive int, got {v!r}")
        if self.pass_slots & (self.pass_slots - 1):
            raise ValueError(f"RasterStrategy: `pass_slots` must be a power of two, got "
                             f"{self.pass_slots}")


#: The most slots per round, by backend (others: `MAX_SLOTS_ACCELERATOR`): on the CPU, rounds
#: whose buffers stay in the caches; a GPU's loop waits on the host for its condition every
#: round, so it wants few large rounds. docs/guides/design.md has the measurements
#: (``python -m scripts.benchmarks.bench --parts raster``).
MAX_SLOTS = {"cpu": 1 << 15}
#: The most slots per round on a backend `MAX_SLOTS` does not name (GPUs).
MAX_SLOTS_ACCELERATOR = 1 << 19


def default_strategy(num_faces: int, width: int, height: int, *, block: int = 4,
                     backend: str | None = None) -> RasterStrategy:
    """The `RasterStrategy` for ``num_faces`` triangles in a ``width`` x ``height`` image on
    ``backend`` (JAX's default if None): about one round for small scenes, at most
    `MAX_SLOTS` slots a round."""
    backend = jax.default_backend() if backend is None else backend
    cap = MAX_SLOTS.get(backend, MAX_SLOTS_ACCELERATOR)
    tiles = (-(-width // block)) * (-(-height // block))
    want = max(4 * num_faces, tiles, 256)
    return RasterStrategy(block=block, slots=int(min(cap, 1 << (want - 1).bit_length())))


class SlotList(NamedTuple):
    """The slots of the triangles that have any, numbered triangle after triangle
    (`slot_list`); every field but `size` is an array.

    - `order`: (F,) the triangles with slots, in order (padded with triangle 0).
    - `starts`, `ends`: (F,) each listed triangle's first slot and one past its last.
    - `starts_ahead`: `starts` padded with `total`, so that any `size` of them after one
      triangle can be sliced.
    - `total`: () the number of slots.
    - `size`: the slots of a round (static).
    """

    order: Array
    starts: Array
    ends: Array
    starts_ahead: Array
    total: Array
    size: int


def slot_list(counts: Array, size: int) -> SlotList:
    """The `SlotList` of triangles with ``counts`` (F,) slots each, taken ``size`` a round.

    The bookkeeping runs over the triangles that have slots, listed first: a dense mesh has
    far fewer of them than triangles."""
    n = counts.shape[0]
    order = flat_nonzero(counts > 0, n, 0)
    live = jnp.arange(n) < jnp.sum(counts > 0)
    counts = jnp.where(live, counts[order], 0)
    ends = cumsum(counts)
    starts = ends - counts
    total = ends[-1]
    starts_ahead = jnp.concatenate([starts, jnp.full((size + 1,), total, jnp.int32)])
    return SlotList(order, starts, ends, starts_ahead, total, size)


def slot_owners(slots: SlotList, slot0: Array) -> tuple[Array, Array, Array]:
    """For the round of slots ``slot0`` to ``slot0 + size - 1``: each slot's triangle and its
    index among that triangle's slots, each (size,) int32, and whether the slot exists
    (below the total).

    The round starts inside listed triangle ``k0``; each of the next ``size`` triangles
    starts at most once in the round, so counting the starts up to each slot (a scatter and
    a running sum over the round) replaces a binary search per slot."""
    size = slots.size
    s = slot0 + jnp.arange(size, dtype=jnp.int32)
    live = s < slots.total
    k0 = jnp.searchsorted(slots.ends, slot0, side="right").astype(jnp.int32)
    ahead = jax.lax.dynamic_slice_in_dim(slots.starts_ahead, k0 + 1, size)
    marks = jnp.zeros((size,), jnp.int32).at[ahead - slot0].add(1, mode="drop")
    k = jnp.minimum(k0 + cumsum(marks), slots.order.shape[0] - 1)
    t = slots.order[k]
    local = s - slots.starts[k]
    return t, local, live


#: Where programs are resident, the slots their rounds hold without a conditional: this many
#: per triangle and per tile of the image, whichever is more. Frames of the benchmark scene
#: (scripts/benchmarks/bench_problem.py, block 4) have 2.9 slots per triangle with the 20k
#: torus at 512x512, 1.7 with the 200k torus at 1024x1024, and 1.7 per tile with the 4k
#: sphere at 512x512 (the sum of `jaxnm._exec.triangles.triangle_setup`'s counts).
RESIDENT_SLOTS = (4, 2)


def round_limits(num_faces: int, tiles: int, size: int, pass_slots: int) -> tuple[int, int]:
    """``(first, most)`` for `over_rounds` where programs are resident: the rounds of
    ``size`` slots always run (enough for `RESIDENT_SLOTS` of ``num_faces`` triangles on an
    image of ``tiles`` tiles), and the most a pass of at most ``pass_slots`` slots can need
    (every triangle on every tile). Static."""
    most = max(1, -(-min(num_faces * tiles, pass_slots) // size))
    want = max(RESIDENT_SLOTS[0] * num_faces, RESIDENT_SLOTS[1] * tiles, 1)
    return min(most, -(-want // size)), most


def over_rounds(evaluate, update, carry, *, total: Array, size: int,
                limits: tuple[int, int] | None = None):
    """``carry = update(carry, *evaluate(slot0))`` for the rounds ``slot0 = 0, size, 2 size,
    ...`` below ``total`` slots. ``evaluate`` runs under the caller's ``jax_enable_x64``; the
    loop keeps a carry of 64-bit integers (depth keys) 64-bit whatever it is.

    On the CPU a while loop: the number of rounds is known at run time only, and reading the
    condition costs nothing. Where programs are `jaxnm._exec.device.resident`, ``limits =
    (first, most)`` (`round_limits`, static) bound it instead: the first ``first`` rounds
    always run (a loop of known trip count; a round past ``total`` evaluates only dead
    slots, which write nothing), and only a frame with more slots takes the rest, up to
    ``most`` rounds, behind one conditional (each further round behind its own): the same
    result, without a condition read back for the usual frame."""
    x64 = bool(jax.config.jax_enable_x64)  # the caller's

    def round_(c):
        q, carry = c
        with jax.enable_x64(x64):
            out = evaluate(q * size)
        return q + 1, update(carry, *out)

    def one(q, carry):  # (a loop index under the carry's x64 may be int64)
        return round_((jnp.asarray(q, jnp.int32), carry))[1]

    with _carry_x64(x64, carry):
        if not resident():
            return jax.lax.while_loop(lambda c: c[0] * size < total, round_,
                                      (jnp.int32(0), carry))[1]
        if limits is None:
            raise ValueError("over_rounds: a resident program needs `limits` (round_limits)")
        first, most = limits
        carry = jax.lax.fori_loop(0, first, one, carry)
        if most <= first:
            return carry

        def rest(carry):
            def more(q, carry):
                return jax.lax.cond(q * size < total, one, lambda q, c: c, q, carry)
            return jax.lax.fori_loop(first, most, more, carry)

        return jax.lax.cond(first * size < total, rest, lambda c: c, carry)


def _carry_x64(x64: bool, carry):
    """``jax.enable_x64`` for a loop over ``carry``: the caller's setting ``x64``, or on where
    the carry holds 64-bit depth keys, so that they stay 64-bit whatever the caller's."""
    return jax.enable_x64(x64 or any(x.dtype == np.uint64 for x in jax.tree.leaves(carry)))


def slot_passes(counts: Array, pass_slots: int) -> tuple[Array, Array]:
    """The pass of each triangle (F,) int32 and the number of passes, for triangles with
    ``counts`` slots each (each at most ``pass_slots``): triangle i is in pass
    ``floor(start_i / pass_slots)`` where ``start_i`` is its first slot in the frame, counted
    exactly (mod 2**32 plus the number of wrap-arounds) though it may exceed int32."""
    ends = jnp.cumsum(counts.astype(jnp.uint32))  # exact mod 2**32
    wrapped = jnp.concatenate([jnp.zeros((1,), bool), ends[1:] < ends[:-1]])
    laps = jnp.cumsum(wrapped.astype(jnp.int32))  # 2**32 wrap-arounds up to each end
    starts = ends - counts.astype(jnp.uint32)
    # the start's wrap-arounds are the previous end's (an end that wrapped, starts before)
    laps = jnp.concatenate([jnp.zeros((1,), jnp.int32), laps[:-1]])
    shift = pass_slots.bit_length() - 1
    passes = laps * (1 << (32 - shift)) + (starts >> shift).astype(jnp.int32)
    return passes, passes[-1] + 1


def each_pass(fn, counts, carry, *, tiles: int, pass_slots: int):
    """``carry = fn(counts_p, carry)`` for the triangles of each pass in turn
    (`slot_passes`), ``counts_p`` (F,) being ``counts`` (each triangle's slots: its box's
    tiles) for that pass's triangles and 0 for the others; a single call with ``counts``
    itself where the frame cannot have more than ``pass_slots`` slots (faces x tiles;
    static). A while loop, not a ``lax.cond`` between it and one pass: XLA's CPU
    conditional around the depth test made the whole frame slower for large meshes
    (the ``lax.cond`` below only chooses how the passes are counted). Where programs are
    `jaxnm._exec.device.resident`, `_resident_passes`."""
    n = counts.shape[0]
    if n * tiles <= pass_slots:
        return fn(counts, carry)
    if resident():
        return _resident_passes(fn, counts, carry, most=-(-n * tiles // pass_slots),
                                pass_slots=pass_slots)
    # Most frames fit in one pass, and a float32 sum of the counts (each < 2**28) says so
    # for far less than `slot_passes`' exact running sums:
    # its rounding error is below F * 2**-24 of the sum
    fits = jnp.sum(counts.astype(jnp.float32)) * (1.0 + n * 2.0**-24) < pass_slots
    passes, n_passes = jax.lax.cond(
        fits, lambda c: (jnp.zeros_like(c), jnp.int32(1)),
        lambda c: slot_passes(c, pass_slots), counts)

    x64 = bool(jax.config.jax_enable_x64)  # the caller's

    def one_pass(c):
        p, carry = c
        with jax.enable_x64(x64):
            return p + 1, fn(jnp.where(passes == p, counts, 0), carry)

    with _carry_x64(x64, carry):
        return jax.lax.while_loop(lambda c: c[0] < n_passes, one_pass,
                                  (jnp.int32(0), carry))[1]


def _resident_passes(fn, counts, carry, *, most: int, pass_slots: int):
    """`each_pass` where programs are resident: the passes counted exactly (`slot_passes`,
    a few running sums over the triangles, cheaper on an accelerator than a conditional
    read back), the first pass always run, and the others, up to ``most`` (static), only in
    a frame that has them: behind one conditional, each behind its own."""
    passes, n_passes = slot_passes(counts, pass_slots)
    x64 = bool(jax.config.jax_enable_x64)  # the caller's

    def one_pass(p, carry):
        p = jnp.asarray(p, jnp.int32)  # (a loop index under the carry's x64 may be int64)
        with jax.enable_x64(x64):
            return fn(jnp.where(passes == p, counts, 0), carry)

    with _carry_x64(x64, carry):
        carry = one_pass(0, carry)

        def rest(carry):
            def more(p, carry):
                return jax.lax.cond(p < n_passes, one_pass, lambda p, c: c, p, carry)
            return jax.lax.fori_loop(1, most, more, carry)

        return jax.lax.cond(n_passes > 1, rest, lambda c: c, carry)
