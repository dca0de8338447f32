"""Normal-map fit benchmark: angular error versus wall time for each solver.

    python scripts/bench_fit.py [--render 512] [--map 256] [--lights 6] [--views 2]
                                [--budget 60] [--solvers lm-texel lm gn lbfgs]
                                [--plot fit_bench.png]

On the built-in problem (the default torus and its rivet map, noise-free
targets) every solver starts from a flat map and runs until ``--budget``
seconds have passed (compile time included: the clock starts when
`fit_normal_map` is called; the one-off G-buffer preparation is reported
separately). Prints one JSON line per solver, then a JSON summary with the
time to reach 1 degree mean error and the per-step cost of the model
(forward + backward w.r.t. the map, one view and one light, on a 20k-triangle
torus at the render size) next to a full render of the same view.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import platform
import statistics
import time

import jax
import jax.numpy as jnp

from jaxnm import fit as F
from jaxnm import procedural
from jaxnm.procedural import default_problem
from jaxnm.render import render


def run_solver(problem, gt, prep, solver: str, budget: float, lsmr: int) -> dict:
    opts = F.FitOptions(solver=solver, max_steps=100000, lsmr_steps=lsmr, ftol=0.0)
    res = F.fit_normal_map(problem, opts, ground_truth=gt, prepared=prep, progress=False,
                           time_limit=budget)
    seen = F.seen_texels(prep, problem.map_size)
    hist = [{"step": h["step"], "seconds": round(h["seconds"], 2), "loss": h["loss"],
             "mean_deg": round(h["mean_angular_error_deg"], 4)} for h in res.history]
    below = [h["seconds"] for h in hist if h["mean_deg"] < 1.0]
    return {"solver": solver, "steps": len(hist), "seconds": round(res.seconds, 2),
            "seconds_to_1deg": below[0] if below else None,
            "final": F.error_report(res.normals, gt, seen), "history": hist}


def step_cost(render_size: int, repeats: int = 10) -> dict:
    """Forward+backward w.r.t. the map (1 view, 1 light) vs. a full render, 20k triangles."""
    problem, gt, scene = default_problem(render_size=render_size, map_size=256, n_lights=1,
                                           views=1)
    mesh = procedural.torus(1.0, 0.42, 160, 64, uv_scale=(3.0, 1.0))  # 20480 triangles
    problem = dataclasses.replace(problem, mesh=mesh)
    t0 = problem.targets[0]
    scene = scene.replace(mesh=mesh, camera=t0.camera, lights=t0.lights)

    def med(fn):
        jax.block_until_ready(fn())
        ts = []
        for _ in range(repeats):
            t = time.perf_counter()
            jax.block_until_ready(fn())
            ts.append(time.perf_counter() - t)
        return statistics.median(ts) * 1e3

    full = med(lambda: render(scene, outputs=("color",))["color"])
    prep = F.prepare(problem)
    args = F.ModelArgs.create(prep)
    z = jnp.zeros(problem.map_size + (2,))
    lf = jax.jit(F.loss)
    fw = med(lambda: lf(z, args))
    vg = jax.jit(jax.value_and_grad(F.loss))
    fb = med(lambda: vg(z, args))
    _, lin = jax.linearize(lambda y: F.residuals(y, args), z)
    lin = jax.jit(lin)
    lt = jax.jit(jax.linear_transpose(lin, z))
    r = lin(z)
    it = med(lambda: lt(lin(z)))
    del r
    return {"triangles": int(mesh.num_faces), "render_size": render_size,
            "full_render_ms": round(full, 2), "fit_forward_ms": round(fw, 2),
            "fit_forward_backward_ms": round(fb, 2),
            "lsmr_iteration_ms": round(it, 2),
            "ratio_forward_to_render": round(fw / full, 3),
            "ratio_forward_backward_to_render": round(fb / full, 3),
            "ratio_lsmr_iteration_to_render": round(it / full, 3)}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--render", type=int, default=512)
    ap.add_argument("--map", type=int, default=256)
    ap.add_argument("--lights", type=int, default=6)
    ap.add_argument("--views", type=int, default=2)
    ap.add_argument("--budget", type=float, default=60.0, help="seconds per solver")
    ap.add_argument("--lsmr", type=int, default=10, help="LSMR iterations per LM/GN step")
    ap.add_argument("--solvers", nargs="+", default=list(F.SOLVERS), choices=list(F.SOLVERS))
    ap.add_argument("--plot", default=None, help="write an error-vs-time plot (PNG)")
    ap.add_argument("--no-step-cost", action="store_true")
    args = ap.parse_args(argv)

    t = time.perf_counter()
    problem, gt, _ = default_problem(render_size=args.render, map_size=args.map,
                                       n_lights=args.lights, views=args.views)
    t_targets = time.perf_counter() - t
    t = time.perf_counter()
    prep = F.prepare(problem)
    jax.block_until_ready(prep)
    t_prep = time.perf_counter() - t
    results = []
    for s in args.solvers:
        r = run_solver(problem, gt, prep, s, args.budget, args.lsmr)
        print(json.dumps({k: v for k, v in r.items() if k != "history"}), flush=True)
        results.append(r)
    summary = {
        "problem": {"render": args.render, "map": args.map, "lights": args.lights,
                    "views": args.views, "targets": len(problem.targets),
                    "triangles": int(problem.mesh.num_faces)},
        "targets_seconds": round(t_targets, 2), "prepare_seconds": round(t_prep, 2),
        "budget_seconds": args.budget,
        "solvers": [{k: v for k, v in r.items() if k != "history"} for r in results],
        "machine": {"cpu_count": os.cpu_count(), "platform": platform.platform(),
                    "jax": jax.__version__},
    }
    if not args.no_step_cost:
        summary["step_cost"] = step_cost(args.render)
    if args.plot:
        _plot(args.plot, results)
        summary["plot"] = args.plot
    summary["histories"] = {r["solver"]: r["history"] for r in results}
    print(json.dumps(summary))


def _plot(path, results):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4), dpi=100)
    for r in results:
        h = r["history"]
        ax.semilogy([x["seconds"] for x in h], [x["mean_deg"] for x in h], label=r["solver"])
    ax.axhline(1.0, color="grey", lw=0.8, ls="--")
    ax.set_xlabel("wall time (s, compile included)")
    ax.set_ylabel("mean angular error over seen texels (deg)")
    ax.set_title("jaxnm fit: error vs time")
    ax.legend()
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


if __name__ == "__main__":
    main()
