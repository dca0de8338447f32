"""What this process holds of arrays spread over processes, and the small host exchanges
between processes that a fit across them makes (`jaxnm.fit.distributed`).

Each exchange is a collective: every process must make the same calls in the same order.
With one process each returns what the process has.
"""

from __future__ import annotations

import hashlib
import json

import jax
import numpy as np

__all__ = ["allgather_json", "fingerprint_across_processes", "held_rows", "host_row", "local_rows",
           "sum_over_processes", "to_host"]


def allgather_json(value) -> list:
    """``value`` (anything `json` writes) of every process, in process order. A collective:
    every process must call it. One process: ``[value]``."""
    if jax.process_count() == 1:
        return [json.loads(json.dumps(value))]
    from jax.experimental import multihost_utils

    data = np.frombuffer(json.dumps(value, sort_keys=True).encode(), np.uint8)
    sizes = np.asarray(multihost_utils.process_allgather(np.array([data.size], np.int64)))
    buf = np.zeros(int(sizes.max()), np.uint8)
    buf[:data.size] = data
    every = np.asarray(multihost_utils.process_allgather(buf))
    return [json.loads(every[p, :int(sizes[p, 0])].tobytes().decode())
            for p in range(every.shape[0])]


def sum_over_processes(x: np.ndarray) -> np.ndarray:
    """The sum of a host array ``x`` over every process (added in process order; ``x`` itself
    with one process). A collective."""
    if jax.process_count() == 1:
        return x
    from jax.experimental import multihost_utils

    every = np.asarray(multihost_utils.process_allgather(np.asarray(x)))
    out = every[0].copy()
    for part in every[1:]:
        out += part
    return out


def to_host(x) -> np.ndarray:
    """A host copy of the whole of ``x``, also where other processes hold parts of it (a
    collective then)."""
    if not isinstance(x, jax.Array) or x.is_fully_addressable:
        return np.asarray(x)
    if x.is_fully_replicated:
        return np.asarray(x.addressable_data(0))
    from jax.experimental import multihost_utils

    return np.asarray(multihost_utils.process_allgather(x, tiled=True))


def fingerprint_across_processes(local: dict) -> dict:
    """A fit's `jaxnm.fit.checkpoint.fit_fingerprint` made on every process (each hashing its
    own targets' images) combined into one, the same on every process. A collective."""
    every = allgather_json(local["problem"])
    h = hashlib.sha256(json.dumps(every, sort_keys=True).encode()).hexdigest()[:16]
    return {**local, "problem": {"across_processes": h}}


def held_rows(x) -> dict:
    """``{row: (shard data, row within it)}`` of the leading-axis rows of ``x`` held here."""
    out = {}
    for shard in x.addressable_shards:
        start = (shard.index[0].start or 0) if shard.index else 0
        for j in range(shard.data.shape[0] if shard.index else 0):
            out.setdefault(start + j, (shard.data, j))
    return out


def host_row(x, i: int) -> np.ndarray:
    """Row ``i`` (leading axis) of ``x`` on the host, also of an array spread over
    processes whose row is held here."""
    if not isinstance(x, jax.Array) or x.is_fully_addressable:
        return np.asarray(x)[i]
    data, j = held_rows(x)[i]
    return np.asarray(data)[j]


def local_rows(x) -> tuple[np.ndarray, np.ndarray]:
    """``(rows, data)``: the indices of the leading-axis rows of ``x`` held by this process
    and their host copy (every row where ``x`` is not spread over processes)."""
    if not isinstance(x, jax.Array) or x.is_fully_addressable:
        x = np.asarray(x)
        return np.arange(x.shape[0]), x
    held = held_rows(x)
    rows = np.array(sorted(held), np.int64)
    if not len(rows):
        return rows, np.zeros((0,) + x.shape[1:], x.dtype)
    return rows, np.stack([np.asarray(held[i][0])[held[i][1]] for i in rows])
