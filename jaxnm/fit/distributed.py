"""A fit across processes: each process (one per host, started with ``jax.distributed``)
prepares only the views it owns, and the step runs as one SPMD program over every device.

`process_targets` deals the views out to the processes from the cameras and lights alone, so a
process reads the images of its own views only; `prepare_processes` rasterizes them and puts
them together with the other processes' rows as global arrays
(`jax.make_array_from_process_local_data`) split over the one-axis mesh ``"views"`` of every
device. `fit_normal_map` then runs it as it runs a `shard_views` problem: each device shades
its views and XLA sums the texel gradients across devices. The memory of the prepared views
per host falls with the number of hosts; the map, the solver state and the texel sums are
replicated.

**Batches.** Across processes, the views whose lights have the same kinds and counts form one
batch (on one process, `prepare` also splits a batch where padding would double a view's
pixels). Its views are dealt round-robin (in the fit's order) to the processes, and each
process pads its rows to the same count with copies of its first row that weigh nothing. A
process dealt no view of a batch (fewer views than processes) loads one view of it as such a
copy.

**Collectives.** `prepare_processes`, `fit_normal_map`, `seen_texels`, `texel_influence`,
`check_identifiability` and `compile_fit` of a problem spread over processes exchange small
host arrays with every other process (`jax.experimental.multihost_utils.process_allgather`):
every process must make the same calls in the same order. A fit agrees on every decision
that is not a function of the loss (the time limit, ``should_stop``, when to checkpoint)
across the processes after each step, so they all stop after the same step; a process that
has died makes the others' next collective fail at once.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import jax
import numpy as np

from ._batching import check_chunk, chunking, light_key, stack_lights, stack_rows, tap_groups
from ._processes import allgather_json
from .prepare import CHUNK, Prepared, ViewBatch, rasterize_views, view_key, view_options
from .problem import FitProblem, FitTarget

__all__ = ["process_targets", "prepare_processes", "spread_over_processes",
           "check_same_across_processes", "local_prepared"]


def spread_over_processes(prep: Prepared) -> bool:
    """Whether ``prep``'s views are spread over several processes (`prepare_processes`):
    then this process holds only some of its rows."""
    return not prep.batches[0].pixels.is_fully_addressable


def check_same_across_processes(values: dict, what: str = "this run") -> None:
    """Raise a one-line `ValueError` on every process when ``values`` (a JSON-able dict, e.g.
    the fit file's hash and the options) differ between processes, naming the first key that
    differs and its value on process 0 and on the first process that differs. A collective."""
    every = allgather_json(values)
    for p, other in enumerate(every[1:], 1):
        for key in sorted(set(every[0]) | set(other)):
            if every[0].get(key) != other.get(key):
                raise ValueError(f"{what}: process {p} has {key} {other.get(key)!r}, process 0 "
                                 f"{every[0].get(key)!r}: every process must run the same fit")


@dataclasses.dataclass(frozen=True)
class _Layout:
    """How a fit's views are dealt to the processes (see the module's "Batches").

    - `views`: each view's target indices (views in the order of their first target).
    - `batches`: each batch's views.
    - `rows`: ``rows[b][p]``: the views of batch ``b`` process ``p`` holds.
    - `fill`: ``fill[b][p]``: the view process ``p`` loads as a weightless copy where it
      holds no view of batch ``b``, else None.
    - `count`: each batch's rows per process.
    """

    views: list
    batches: list
    rows: list
    fill: list
    count: list

    def targets_of(self, p: int) -> tuple[int, ...]:
        """The target indices process ``p`` needs (its views and its weightless copies)."""
        vs = {v for b in range(len(self.batches)) for v in self.rows[b][p]}
        vs |= {f[p] for f in self.fill if f[p] is not None}
        return tuple(sorted(i for v in vs for i in self.views[v]))


def _layout(targets: Sequence[FitTarget], processes: int, local_devices: int = 1) -> _Layout:
    groups: dict = {}
    for i, t in enumerate(targets):
        groups.setdefault(view_key(t), []).append(i)
    views = list(groups.values())
    by_lights: dict = {}
    for v, ts in enumerate(views):
        key = light_key(stack_lights([targets[i].lights for i in ts]))
        by_lights.setdefault(key, []).append(v)
    batches = list(by_lights.values())
    rows, fill, count = [], [], []
    for members in batches:
        held = [members[p::processes] for p in range(processes)]
        rows.append(held)
        fill.append([None if held[p] else members[p % len(members)]
                     for p in range(processes)])
        m = -(-len(members) // processes)
        count.append(-(-m // local_devices) * local_devices)
    return _Layout(views, batches, rows, fill, count)


def process_targets(targets: Sequence[FitTarget], process_count: int) -> tuple[tuple[int, ...],
                                                                                ...]:
    """For each of ``process_count`` processes, the indices of ``targets`` whose images it
    needs for `prepare_processes` (read only the ``image`` and ``mask`` of these; the
    cameras, sizes and lights of every target decide who owns what)."""
    if isinstance(process_count, bool) or not isinstance(process_count, int) or process_count < 1:
        raise ValueError(f"process_targets: process_count must be an integer >= 1, got "
                         f"{process_count!r}")
    lay = _layout(targets, process_count)
    return tuple(lay.targets_of(p) for p in range(process_count))


def _devices() -> list:
    return sorted(jax.devices(), key=lambda d: (d.process_index, d.id))


def prepare_processes(problem: FitProblem, *, chunk: int | None = CHUNK) -> Prepared:
    """`prepare` for a fit across processes: call it on every process (after
    ``jax.distributed.initialize``) with the same ``problem``, whose targets are all of the
    fit's, in the same order. Only the targets this process needs (`process_targets` for
    ``jax.process_index()``) are read: the others may have ``image=None``.

    Returns a `Prepared` whose batch arrays span every process's devices (this process
    holds its own rows); `fit_normal_map` runs it as one SPMD program. With one process it
    is `prepare` with one batch per kind of lights. A collective (see the module)."""
    from jax.sharding import Mesh, NamedSharding, PartitionSpec

    check_chunk(chunk)
    n_proc, me = jax.process_count(), jax.process_index()
    devices = _devices()
    local = [d for d in devices if d.process_index == me]
    lay = _layout(problem.targets, n_proc, len(local))
    mine = lay.targets_of(me)
    sub = dataclasses.replace(problem, targets=tuple(problem.targets[i] for i in mine))
    raster, _, _ = rasterize_views(sub)
    # local view -> global view: each view's first target
    first = {tuple(lay.views[v]): v for v in range(len(lay.views))}
    order: dict = {}
    for i in mine:
        order.setdefault(view_key(problem.targets[i]), []).append(i)
    held = {first[tuple(ts)]: view for ts, view in zip(order.values(), raster, strict=True)}
    del raster
    # every process's largest one-level and two-level pixel counts per batch
    plan = []
    for b, members in enumerate(lay.batches):
        vs = lay.rows[b][me] or [lay.fill[b][me]]
        parts = [tap_groups(held[v]) for v in vs]
        plan.append((vs, parts, max(len(a) for a, _ in parts), max(len(c) for _, c in parts)))
    local_max = np.array([[p[2], p[3]] for p in plan], np.int64)
    every = allgather_json(local_max.tolist())
    sizes = np.max(np.asarray(every, np.int64), axis=0)
    mesh = Mesh(np.array(devices), ("views",))
    split = NamedSharding(mesh, PartitionSpec("views"))
    batches = []
    for b, members in enumerate(lay.batches):
        vs, parts, _, _ = plan[b]
        m = lay.count[b]
        targets = {v: len(lay.views[v]) for v in members}
        t_max = max(targets.values())
        rows = m * n_proc
        per_chunk = None if chunk is None else max(256, chunk // (rows * t_max))
        na, ka = chunking(int(sizes[b, 0]), per_chunk)
        nb, kb = chunking(int(sizes[b, 1]), per_chunk)
        eight = held[vs[0]].gbuffer.plan.num_taps == 8
        stacked = stack_rows(held, vs, parts, ka, kb, t_max)  # (each view in one batch)
        real = len(lay.rows[b][me])
        pick = np.concatenate([np.arange(len(vs)), np.zeros(m - len(vs), np.int64)])

        def rows_of(x, pick=pick):
            return x[pick]

        stacked = jax.tree_util.tree_map(rows_of, stacked)
        stacked["weights"][real:] = 0  # the copies weigh nothing
        stacked["pixels"][real:] = -1
        leaves, tree = jax.tree_util.tree_flatten(stacked)
        del stacked
        for j in range(len(leaves)):
            x = leaves[j]
            leaves[j] = jax.make_array_from_process_local_data(split, x,
                                                               (rows,) + x.shape[1:])
        stacked = jax.tree_util.tree_unflatten(tree, leaves)
        del leaves
        row_views = tuple(v for p in range(n_proc)
                          for v in lay.rows[b][p] + [-1] * (m - len(lay.rows[b][p])))
        batches.append(ViewBatch(**stacked, views=row_views,
                                 targets=tuple(targets.get(v, 0) for v in row_views),
                                 split=ka if eight else 0, chunks=(na, nb)))
    material = jax.device_put(jax.tree_util.tree_map(np.asarray, problem.material),
                              NamedSharding(mesh, PartitionSpec()))
    return Prepared(tuple(batches), material, tuple(view_options(problem)), chunk)


def local_prepared(prep: Prepared) -> tuple[Prepared, tuple[int, ...]]:
    """The views of ``prep`` this process holds, as a `Prepared` of their own on this
    process's devices, and their indices in ``prep`` (all of them where ``prep`` is not
    spread over processes: then ``prep`` itself). For what needs only some views' pixels on
    the host, e.g. `jaxnm.fit.fit_renders` on the process that writes the outputs."""
    if not spread_over_processes(prep):
        return prep, tuple(range(prep.num_views))
    from .prepare import assemble

    vs = prep.local_views()
    views = [prep.view(v) for v in vs]
    return assemble(views, tuple(prep.options[v] for v in vs), _local_material(prep),
                     prep.chunk), vs


def _local_material(prep: Prepared):
    return jax.tree_util.tree_map(lambda x: np.asarray(x.addressable_data(0)), prep.material)


