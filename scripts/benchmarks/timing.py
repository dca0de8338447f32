"""The timer of every script that times something: medians of steady calls, each forced to
completion, with the first call (compilation included) counted apart.

- `time_call`: a first call (``first_s``: tracing and XLA compilation included), ``warmup``
  untimed calls, then ``repeats`` timed ones; `Timing` holds the times and gives the median,
  the minimum and ``compile_s``, the first call less a steady one.
- `side_by_side`: several calls (jaxnm's and Mitsuba's) timed taking turns in blocks, so that
  a slow phase of a noisy machine falls on all of them alike and their ratios hold.
- `CompileLog`: JAX's own compile events while it is open (tracing, lowering and XLA
  compilation, per program): which programs a call compiled, and what each cost.

Every timed call is finished with `jax.block_until_ready` before the clock stops: JAX
dispatches its work asynchronously, and a clock around the call alone would time the
dispatch. Non-JAX results (NumPy arrays, Python numbers) pass through it unchanged.
"""

from __future__ import annotations

import dataclasses
import resource
import statistics
import time
from collections.abc import Callable

import jax
import numpy as np


def finish(x):
    """``x`` once every JAX array in it has been computed (`jax.block_until_ready`)."""
    return jax.block_until_ready(x)


@dataclasses.dataclass(frozen=True)
class Timing:
    """The timed calls of `time_call`: ``first_s`` (the first call, compilation included;
    None if it was not timed) and ``times_s`` (the steady calls, in order)."""

    first_s: float | None
    times_s: tuple[float, ...]

    @property
    def median_ms(self) -> float:
        return 1e3 * statistics.median(self.times_s)

    @property
    def min_ms(self) -> float:
        return 1e3 * min(self.times_s)

    @property
    def compile_s(self) -> float | None:
        """The first call less a steady one (the median): tracing, lowering and compiling,
        and whatever else a first call does once."""
        return None if self.first_s is None else self.first_s - self.median_ms / 1e3


def time_call(fn: Callable[[], object], *, repeats: int = 10, warmup: int = 0,
              first: bool = True) -> Timing:
    """Time ``fn()``: with ``first``, one call timed apart (compilation included), then
    ``warmup`` untimed calls and ``repeats`` timed ones, each finished with
    `jax.block_until_ready`."""
    first_s = None
    if first:
        t = time.perf_counter()
        finish(fn())
        first_s = time.perf_counter() - t
    for _ in range(warmup):
        finish(fn())
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        finish(fn())
        times.append(time.perf_counter() - t)
    return Timing(first_s, tuple(times))


def side_by_side(calls: dict[str, Callable[[], object]], repeats: int, *, block: int = 5,
                 warm: int = 5, warm_s: float = 0.25, seed: int = 0,
                 first_calls: bool = True) -> tuple[dict, dict, dict]:
    """(first call s, median ms of the next ``repeats``, the process's minor page faults per
    timed call: a call that faults its buffers in afresh each time shows here) of each of
    ``calls``.

    With ``first_calls``, each call is first run once, timed apart (its compilation). Then
    the calls take turns in blocks of ``block`` timed runs, each block after at least
    ``warm`` untimed ones and at least ``warm_s`` seconds of them: a slow phase of the
    machine falls on all of them alike, and each is timed in its own steady state, as a
    user who renders frame after frame sees it. A call that follows another's is slower
    for a while: on a 2-core x86-64 machine, jaxnm's 4k sphere at 512^2 (3.4 ms a frame
    back to back) took 4.3-6.8 ms a frame for its first 60-80 ms of frames after 0.2-1 s
    without XLA work, whoever ran meanwhile (a frame is a hundred-odd small kernels, each
    split over XLA's worker threads, which the system wakes and places slowly after an
    idle spell); Mitsuba's frames changed little. The order of the turns is shuffled in
    every cycle (``seed``), so that no call always follows the same one."""
    first, times, faults = {}, {k: [] for k in calls}, {k: 0 for k in calls}
    for k, fn in (calls.items() if first_calls else ()):
        t = time.perf_counter()
        finish(fn())
        first[k] = time.perf_counter() - t
    rng = np.random.default_rng(seed)
    for _ in range(-(-repeats // block)):
        for k in rng.permutation(list(calls)):
            fn = calls[k]
            t_warm = time.perf_counter()
            n = 0
            while n < warm or time.perf_counter() - t_warm < warm_s:
                finish(fn())
                n += 1
            for _ in range(block):
                f0 = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
                t = time.perf_counter()
                finish(fn())
                times[k].append(time.perf_counter() - t)
                faults[k] += resource.getrusage(resource.RUSAGE_SELF).ru_minflt - f0
    return (first, {k: 1e3 * statistics.median(v) for k, v in times.items()},
            {k: round(n / len(times[k])) for k, n in faults.items()})


# --------------------------------------------------------------------------------------
# compilation
# --------------------------------------------------------------------------------------

_EVENTS = {"/jax/core/compile/jaxpr_trace_duration": "trace_s",
           "/jax/core/compile/jaxpr_to_mlir_module_duration": "lower_s",
           "/jax/core/compile/backend_compile_duration": "compile_s"}
_open_logs: list[CompileLog] = []
_listening = False


def _listen(event, secs, **kw):
    if event in _EVENTS:
        for log in _open_logs:
            log.events.append((_EVENTS[event], kw.get("fun_name", "?"), secs))


class CompileLog:
    """JAX's compile events while open (``with CompileLog() as log: ...``): ``events``, a
    list of (``"trace_s"``, ``"lower_s"`` or ``"compile_s"``, program name, seconds).

    A program is traced, lowered to MLIR, then compiled by XLA; tracing alone happens for
    every `jax.jit` call that misses JAX's tracing cache, and an inner jit inlined into its
    caller is traced but never compiled on its own. A program read from JAX's persistent
    compilation cache is traced and lowered, not compiled."""

    def __init__(self):
        self.events: list[tuple[str, str, float]] = []

    def __enter__(self) -> CompileLog:
        global _listening
        if not _listening:
            jax.monitoring.register_event_duration_secs_listener(_listen)
            _listening = True
        _open_logs.append(self)
        return self

    def __exit__(self, *exc) -> None:
        _open_logs.remove(self)

    @property
    def compile_s(self) -> float:
        """XLA's compilation, in s, summed over the programs."""
        return sum(s for kind, _, s in self.events if kind == "compile_s")

    def summary(self) -> dict:
        """The totals of tracing, lowering and compiling, and each program XLA compiled, in
        order, with the tracing and lowering that led to it (``program`` as JAX names it)."""
        programs, pending = [], {}
        totals = dict.fromkeys(_EVENTS.values(), 0.0)
        for kind, name, secs in self.events:
            totals[kind] += secs
            name = name if name.startswith("jit(") else f"jit({name})"  # tracing: bare
            rec = pending.setdefault(name, {"program": name, "trace_s": 0.0, "lower_s": 0.0})
            if kind == "compile_s":
                rec["compile_s"] = secs
                programs.append({k: round(v, 4) if isinstance(v, float) else v
                                 for k, v in pending.pop(name).items()})
            else:
                rec[kind] += secs
        return {"programs_compiled": len(programs),
                **{f"total_{k}": round(v, 3) for k, v in totals.items()},
                "programs": programs}
