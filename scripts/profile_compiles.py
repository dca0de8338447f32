"""Which programs a first call compiles, and what each costs: tracing, lowering, XLA.

    python scripts/profile_compiles.py [--phases render,fit] [--steps 3]

Time to answer is mostly compilation (issue 9), and a first call can hide many small
programs (``jnp.asarray`` of a NumPy array, a stack, a division on the device: each its
own compilation, ~10-30 ms on the CPU, more on a GPU, where every program goes through
ptxas). For each phase, in one fresh process (JAX's persistent compilation cache left off,
as a library user has it):

- ``render``: the first `jaxnm.render` of the fit benchmark's scene (the 20k torus at
  512x512, one light, the map);
- ``fit``: the fit benchmark's fit as ``bench.py`` times it cold (its four targets
  rendered, every compiled program dropped, then `prepare` and ``--steps`` LM steps).

it prints one JSON object per line: the phase's wall time, the sum of tracing, lowering
and XLA compilation, and every program compiled in it, in order, with the three times
(``fun_name`` as JAX reports it). Runs on whatever backend JAX picks.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

import bench_problem as B  # noqa: E402
import jax  # noqa: E402

import jaxnm  # noqa: E402
from jaxnm import fit as F  # noqa: E402

_EVENTS = {"/jax/core/compile/jaxpr_trace_duration": "trace_s",
           "/jax/core/compile/jaxpr_to_mlir_module_duration": "lower_s",
           "/jax/core/compile/backend_compile_duration": "compile_s"}


class CompileLog:
    """Collects JAX's per-program compile events (a `jax.monitoring` listener) while on.

    A program is traced, lowered, then compiled; tracing alone happens for every
    `jax.jit` call that misses the tracing cache. The records are grouped by ``fun_name``
    in the order the programs reached XLA; traces that never reached XLA (an inner jit
    inlined into its caller) count in the phase's tracing total only."""

    def __init__(self):
        self.on = False
        self.events: list[tuple[str, str, float]] = []
        jax.monitoring.register_event_duration_secs_listener(self._listen)

    def _listen(self, event, secs, **kw):
        if self.on and event in _EVENTS:
            name = kw.get("fun_name", "?")
            if not name.startswith("jit("):  # tracing names the function bare
                name = f"jit({name})"
            self.events.append((_EVENTS[event], name, secs))

    def summary(self) -> dict:
        programs, pending = [], {}
        totals = dict.fromkeys(_EVENTS.values(), 0.0)
        for kind, name, secs in self.events:
            totals[kind] += secs
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


def render_phase(p, log: CompileLog) -> dict:
    scene = B.jaxnm_scene(p, p.light_dirs[0])
    log.on = True
    t = time.perf_counter()
    jax.block_until_ready(jaxnm.render(scene)["color"])
    wall = time.perf_counter() - t
    log.on = False
    return {"phase": "render", "scene": "20k torus 512", "wall_s": round(wall, 3)}


def fit_phase(p, log: CompileLog, steps: int) -> dict:
    problem = B.jaxnm_fit_problem(p)
    jax.clear_caches()  # as bench.py: the fit compiles everything it runs
    opts = F.FitOptions(max_steps=steps, lsmr_steps=10, ftol=0.0)
    log.on = True
    t = time.perf_counter()
    prep = F.prepare(problem)
    t_prep = time.perf_counter() - t
    res = F.fit_normal_map(problem, opts, prepared=prep, progress=False)
    wall = time.perf_counter() - t
    log.on = False
    return {"phase": "fit", "steps": len(res.history) - 1, "wall_s": round(wall, 3),
            "prepare_s": round(t_prep, 3),
            "texel_sums": F.texel_sums_for(prep, opts)}


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--phases", default="render,fit")
    ap.add_argument("--steps", type=int, default=3, help="LM steps of the fit phase")
    args = ap.parse_args(argv)
    log = CompileLog()
    p = B.make_problem()
    for phase in args.phases.split(","):
        log.events.clear()
        if phase == "render":
            row = render_phase(p, log)
        elif phase == "fit":
            row = fit_phase(p, log, args.steps)
        else:
            raise SystemExit(f"unknown phase {phase!r}; expected render or fit")
        row["backend"] = jax.default_backend()
        row.update(log.summary())
        print(json.dumps(row), flush=True)


if __name__ == "__main__":
    main()
