"""The execution layer (`jaxnm._exec`): the fusion barrier, running sums, compaction and
fixed-order sums, each against NumPy."""

import re

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxnm._exec.arrays import cumsum
from jaxnm._exec.compaction import flat_nonzero
from jaxnm._exec.fusion import materialize
from jaxnm._exec.sums import SumTables, sum_by_tables, sum_tables


def _while_carry_types(hlo: str) -> list[str]:
    """The element types of every array in the carried tuples of the compiled while loops."""
    out = []
    for m in re.finditer(r"= \(([^)]*)\) while\(", hlo):
        out += re.findall(r"(f32|s32|pred)\[\d", m.group(1))
    return out


def test_materialize_is_an_identity_that_keeps_every_leaf_in_its_own_buffer():
    x = jnp.linspace(-2.0, 3.0, 64)

    def f(x):
        a, i, b = x * 2.0, jnp.arange(64, dtype=jnp.int32) * 3, x > 0.5
        a, i, b = materialize((a, i, b))
        return a[:, None] + i[:, None] + b[:, None] * jnp.arange(4.0)[None, :]

    def g(x):
        return (x * 2.0)[:, None] + (jnp.arange(64) * 3)[:, None] + (x > 0.5)[:, None] \
            * jnp.arange(4.0)[None, :]

    np.testing.assert_array_equal(jax.jit(f)(x), g(x))
    np.testing.assert_array_equal(jax.grad(lambda x: f(x).sum())(x),
                                  jax.grad(lambda x: g(x).sum())(x))
    # Each kind of leaf (float, int, bool) goes through the loop: a leaf the loop leaves
    # untouched would be hoisted out of it and fused (recomputed) into every consumer.
    kinds = _while_carry_types(jax.jit(f).lower(x).compile().as_text())
    assert {"f32", "s32", "pred"} <= set(kinds), kinds


@pytest.mark.parametrize("n", [1, 7, 8, 9, 63, 64, 65, 513, 4097])
def test_cumsum_equals_the_sequential_running_sum_wrapping_included(n):
    rng = np.random.default_rng(n)
    small = rng.integers(-5, 6, n).astype(np.int32)
    # values near the int32 range: the running sum wraps, as integer adds (and NumPy's) do
    big = rng.integers(-(2**31), 2**31 - 1, n, dtype=np.int64).astype(np.int32)
    f = jax.jit(cumsum)
    for x in (small, big):
        with np.errstate(over="ignore"):
            want = np.cumsum(x, dtype=np.int32)
        got = f(jnp.asarray(x))
        assert got.dtype == jnp.int32
        np.testing.assert_array_equal(np.asarray(got), want)
    np.testing.assert_array_equal(np.asarray(cumsum(jnp.asarray(small), block=2)),
                                  np.cumsum(small))


@pytest.mark.parametrize("n", [1, 1000])
def test_flat_nonzero_equals_numpys_indices_cut_or_filled_to_size(n):
    rng = np.random.default_rng(n)
    f = jax.jit(flat_nonzero, static_argnums=(1, 2))
    for mask in (rng.random(n) < 0.3, np.zeros(n, bool), np.ones(n, bool)):
        count = int(mask.sum())
        for size in sorted({1, max(count - 1, 1), count + 5}):
            want = np.full(size, n)
            want[:min(size, count)] = np.flatnonzero(mask)[:size]
            got = f(jnp.asarray(mask), size, n)
            assert got.dtype == jnp.int32 and got.shape == (size,)
            np.testing.assert_array_equal(np.asarray(got), want)


@pytest.mark.parametrize("n", [32, 4099])
def test_both_ways_of_flat_nonzero_give_numpys_indices(n):
    """The word-packed way (each output slot finds its entry) and the running-sum way
    (each entry is scattered into its slot), whichever `flat_nonzero` picks: runs of true
    entries across word boundaries, words with every bit set or none, a tail word, and
    sizes below and above the count."""
    from jaxnm._exec.compaction import _nonzero_by_scatter, _nonzero_by_words

    rng = np.random.default_rng(n)
    runs = np.zeros(n, bool)
    runs[5:n // 2] = True  # a run spanning whole words
    masks = [rng.random(n) < 0.3, rng.random(n) < 0.97, runs, np.zeros(n, bool)]
    ways = [jax.jit(fn, static_argnums=(1, 2)) for fn in (_nonzero_by_words,
                                                           _nonzero_by_scatter)]
    sizes = (n // 8, n // 2 + 3, n + 7)  # one program per size, below and above each count
    for mask in masks:
        count = int(mask.sum())
        assert any(size < count for size in sizes) or count == 0
        for size in sizes:
            want = np.full(size, -1)
            want[:min(size, count)] = np.flatnonzero(mask)[:size]
            for way in ways:
                got = way(jnp.asarray(mask), size, -1)
                assert got.dtype == jnp.int32 and got.shape == (size,)
                np.testing.assert_array_equal(np.asarray(got), want)


@pytest.mark.parametrize("n", [32, 4099])
def test_ranked_nonzero_windows_are_numpys_indices(n):
    """`ranked_nonzero`'s windows are the slices of NumPy's indices from any first rank
    (traced, so one compiled program serves them all): at word boundaries, inside runs
    that span words, at and past the last entry, and filled past it."""
    from jaxnm._exec.compaction import ranked_nonzero

    rng = np.random.default_rng(n + 1)
    runs = np.zeros(n, bool)
    runs[5:n // 2] = True
    size = 37
    window = jax.jit(lambda m, first: ranked_nonzero(m)[1](first, size, -1))
    total = jax.jit(lambda m: ranked_nonzero(m)[0])
    for mask in (rng.random(n) < 0.3, rng.random(n) < 0.97, runs, np.zeros(n, bool)):
        ref = np.flatnonzero(mask)
        assert int(total(jnp.asarray(mask))) == len(ref)
        for first in sorted({0, 1, 31, 32, 33, 64, len(ref) // 2, max(len(ref) - 3, 0),
                             len(ref), len(ref) + 40}):
            want = np.full(size, -1)
            part = ref[first:first + size]
            want[:len(part)] = part
            np.testing.assert_array_equal(np.asarray(window(jnp.asarray(mask), first)), want)
    with pytest.raises(ValueError, match="1-D boolean"):
        ranked_nonzero(jnp.ones((3,), jnp.int32))


def test_cumsum_and_flat_nonzero_reject_what_they_do_not_handle():
    with pytest.raises(ValueError, match="1-D integer"):
        cumsum(jnp.ones((3,), jnp.float32))
    with pytest.raises(ValueError, match="1-D integer"):
        cumsum(jnp.ones((2, 3), jnp.int32))
    with pytest.raises(ValueError, match="1-D boolean"):
        flat_nonzero(jnp.ones((3,), jnp.int32), 3, 0)


def _sums_in_float64(dest, values, size):
    ref = np.zeros((size,) + values.shape[1:])
    np.add.at(ref, dest, values.astype(np.float64))
    return ref


@pytest.mark.parametrize("width", [2, 8])
def test_sum_tables_sum_each_destination_once_in_a_fixed_order(width):
    """`sum_by_tables` equals the float64 sums per destination (within float32 rounding of
    each term's partial sums), for destinations with no entries, one, a row's worth, and
    700 (several levels); the same tables give the same bits every call; stacked tables
    (common shapes, different depths) equal each array's own; the final scatter writes
    distinct destinations, so XLA needs no sorting to make it deterministic."""
    rng = np.random.default_rng(0)
    size = 60
    dest = np.r_[rng.integers(0, 40, 300), np.full(700, 7), [45] * width, [50]]
    rng.shuffle(dest)
    values = rng.normal(size=(dest.size, 3)).astype(np.float32)
    tables = sum_tables(dest, size, width)
    most, levels = np.bincount(dest).max(), 1  # dest 7's entries: ceil(log_width) levels
    while width ** levels < most:
        levels += 1
    assert len(tables.tables) == levels
    sums = jax.jit(sum_by_tables)
    got = np.asarray(sums(values, tables))
    ref = _sums_in_float64(dest, values, size)
    bound = 8 * np.finfo(np.float32).eps * _sums_in_float64(dest, np.abs(values), size)
    assert np.all(np.abs(got - ref) <= bound + 1e-30)
    assert np.all(got[ref == 0] == 0) and not got[np.setdiff1d(np.arange(size), dest)].any()
    np.testing.assert_array_equal(np.asarray(sums(values, tables)), got)
    # a 1-D value array too; the transpose is gathers: d sum(c * out) / d values = c[dest]
    c = rng.normal(size=size).astype(np.float32)
    grad = jax.jit(jax.grad(lambda v: jnp.sum(jnp.asarray(c) * sum_by_tables(v, tables))))(
        jnp.asarray(values[:, 0]))
    np.testing.assert_array_equal(np.asarray(grad), c[dest])
    hlo = jax.jit(sum_by_tables).lower(values, tables).as_text()
    assert re.search(r"scatter.*unique_indices = true", hlo), "the final scatter is not unique"
    # stacked: one short array (one level) and an empty one beside the deep one
    parts = [dest, dest[:5], np.zeros(0, np.int64)]
    stacked = sum_tables(parts, size, width)
    assert stacked.tables[0].shape[0] == 3 and len(stacked.tables) == len(tables.tables)
    for k, d in enumerate(parts):
        one = jax.tree_util.tree_map(lambda x, k=k: x[k], stacked)
        out = np.asarray(sums(values[:d.size], one))
        np.testing.assert_allclose(out, _sums_in_float64(d, values[:d.size], size),
                                   rtol=1e-5, atol=1e-5)
    assert SumTables.PAD > dest.size


def test_sum_tables_refuse_what_they_cannot_sum():
    with pytest.raises(ValueError, match="integers"):
        sum_tables(np.zeros(3), 4)
    with pytest.raises(ValueError, match=r"in \[0, 4\), found 4"):
        sum_tables(np.array([0, 4]), 4)
    with pytest.raises(ValueError, match="found -1"):
        sum_tables([np.array([0]), np.array([-1])], 4)
    with pytest.raises(ValueError, match="width"):
        sum_tables(np.array([0, 1]), 4, width=1)
