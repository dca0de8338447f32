"""A fit across processes on one machine: step time, peak memory and the share of a step that
is communication, for one process and for several (`jaxnm.fit.prepare_processes`).

    python -m scripts.benchmarks.bench_distributed [--processes 1,2] [--views 8] [--size 128]
        [--map 128] [--lights 4] [--steps 8] [--out bench_distributed.json]

(from the repository root). The problem is the built-in torus and rivet map
(`jaxnm.default_problem`'s scene) seen from ``--views`` cameras spread over the upper
hemisphere, ``--size`` x ``--size`` pixels each, under ``--lights`` directional lights per view,
fitted as a fit file (`jaxnm.config.load_fit`) with a ``--map`` x ``--map`` map: ``--steps``
texel-space LM steps of 10 conjugate-gradient iterations from the flat map, no stopping test.

- **1 process**: the ordinary fit (`jaxnm.fit.prepare`, `jaxnm.fit.fit_normal_map`).
- **N processes**: N processes on this machine joined by ``jax.distributed`` through a
  coordinator on 127.0.0.1, gloo for the CPU's collectives, each reading and preparing only
  its own views (`jaxnm.fit.process_targets`, `jaxnm.fit.prepare_processes`).

Per process: the step time (the median of the steps after the second: compilation left out),
the peak RSS (Linux's VmHWM, the process's own high-water mark, read after the fit) and the
prepared views' bytes it holds. **Communication**: after the fit across processes, each
process fits its own views alone (`jaxnm.fit.local_prepared`: the same views, the same
replicated solve, no cross-process reduction), all processes at once so that they share the
cores as before; the fraction of a step that is communication is ``1 - alone / across``:
the all-reduces of the texel sums and the loss, and the wait for the slowest process.

Each configuration runs in fresh processes (each with JAX's defaults: every process's XLA
uses all the cores, so N processes on one machine share them); nothing is cached between
them. Prints the JSON (and writes it to ``--out`` if given).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import socket
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from scripts._cli import output, run_script

ROOT = Path(__file__).resolve().parents[2]
MODULE = "scripts.benchmarks.bench_distributed"
#: Seconds one configuration's processes may take before the benchmark gives up on them.
TIMEOUT = 1800
CG_STEPS = 10


def ring_eyes(n: int, radius: float = 3.0) -> list[list[float]]:
    """``n`` eyes spread over the upper hemisphere around the origin (a Fibonacci spiral)."""
    import math

    eyes = []
    for i in range(n):
        z = 0.25 + 0.7 * (i + 0.5) / n
        phi = i * math.pi * (3.0 - math.sqrt(5.0))
        r = math.sqrt(1.0 - z * z)
        eyes.append([radius * r * math.cos(phi), radius * r * math.sin(phi), radius * z])
    return eyes


def make_fit_file(folder: Path, *, views: int, size: int, map_size: int, lights: int,
                  steps: int) -> Path:
    """The benchmark's fit file and its target images (``.npy``) in ``folder``."""
    import jax.numpy as jnp
    import numpy as np

    import jaxnm
    from jaxnm.camera import eye_to_world
    from jaxnm.procedural import default_light_directions
    from jaxnm.scene import back_faces_hidden

    _, _, scene = jaxnm.default_problem(render_size=size, map_size=map_size, n_lights=lights,
                                        views=1)
    cam_spec = {"target": [0, 0, 0], "up": [0, 0, 1], "fov_y_deg": 45, "near": 0.1, "far": 50}
    (folder / "scene.json").write_text(json.dumps({
        "mesh": "builtin:torus", "width": size, "height": size,
        "camera": {"eye": ring_eyes(views)[0], **cam_spec},
        "albedo": np.asarray(scene.albedo).tolist(),
        "material": {"model": "blinn_phong", "specular": [0.15, 0.15, 0.15], "shininess": 24,
                     "ambient": [0, 0, 0]}}))
    entries, view_specs = [], []
    for v, eye in enumerate(ring_eyes(views)):
        view_specs.append({"camera": {"eye": eye, **cam_spec}, "width": size, "height": size})
        cam = jaxnm.Camera.from_matrices(jaxnm.look_at(eye, (0.0, 0.0, 0.0), (0.0, 0.0, 1.0)),
                                         jaxnm.perspective(45.0, 1.0, 0.1, 50.0))
        for k, d in enumerate(default_light_directions(lights)):
            light = jaxnm.directional_light(eye_to_world(cam, jnp.asarray(d)))
            img = jaxnm.render(scene.replace(camera=cam, lights=light,
                                             cull_back=back_faces_hidden(scene.mesh, cam)))
            name = f"v{v:03d}_l{k}.npy"
            np.save(folder / name, np.asarray(img["color"], np.float32))
            direction = np.asarray(light.directional.direction)[0].tolist()
            entries.append({"image": name, "view": v,
                            "lights": [{"type": "directional", "direction": direction}]})
    fit = {"scene": "scene.json", "views": view_specs, "targets": entries,
           "map": {"size": map_size},
           "solver": {"method": "lm-texel", "max_steps": steps, "lsmr_steps": CG_STEPS,
                      "ftol": 0, "rtol": 0, "atol": 0}}
    path = folder / "fit.json"
    path.write_text(json.dumps(fit))
    return path


def _peak_rss_mb() -> float | None:
    """This process's peak RSS (VmHWM) in MB; None off Linux."""
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) / 1024
    except OSError:
        return None
    return None


def _step_s(history: list) -> float:
    """The median seconds per step after the second (the first two compile)."""
    t = [rec["seconds"] for rec in history]
    gaps = [b - a for a, b in zip(t[2:], t[3:])] or [t[-1] - t[-2]]
    return statistics.median(gaps)


def _held_mb(prep) -> float:
    """The prepared views' bytes this process holds, in MB."""
    import jax

    total = 0
    for x in jax.tree_util.tree_leaves(prep):
        if isinstance(x, jax.Array):
            total += sum(s.data.nbytes for s in x.addressable_shards)
    return total / 2**20


def run_one(fit_path: str) -> dict:
    """One process: the ordinary fit of the fit file."""
    import warnings

    from jaxnm import fit as F
    from jaxnm.config import load_fit

    warnings.simplefilter("ignore")
    job = load_fit(fit_path)
    t0 = time.perf_counter()
    prep = F.prepare(job.problem)
    prepare_s = time.perf_counter() - t0
    res = F.fit_normal_map(job.problem, job.options, prepared=prep, progress=False)
    return {"process": 0, "views": prep.num_views, "prepare_s": prepare_s,
            "step_s": _step_s(res.history), "first_steps_s": res.history[1]["seconds"],
            "peak_rss_mb": _peak_rss_mb(), "prepared_mb": _held_mb(prep),
            "final_loss": res.history[-1]["loss"]}


def run_member(fit_path: str, port: int, count: int, me: int) -> dict:
    """Process ``me`` of ``count``: the fit across processes, then its own views alone."""
    import warnings

    import jax

    warnings.simplefilter("ignore")
    jax.config.update("jax_cpu_collectives_implementation", "gloo")
    jax.distributed.initialize(f"127.0.0.1:{port}", count, me, initialization_timeout=300)
    from jax.experimental import multihost_utils

    from jaxnm import fit as F
    from jaxnm.config import load_fit

    job = load_fit(fit_path, images=lambda key, ts: F.process_targets(ts, count)[me])
    t0 = time.perf_counter()
    prep = F.prepare_processes(job.problem)
    prepare_s = time.perf_counter() - t0
    res = F.fit_normal_map(job.problem, job.options, prepared=prep, progress=False)
    peak = _peak_rss_mb()
    out = {"process": me, "views": len(prep.local_views()), "prepare_s": prepare_s,
           "step_s": _step_s(res.history), "first_steps_s": res.history[1]["seconds"],
           "peak_rss_mb": peak, "prepared_mb": _held_mb(prep),
           "final_loss": res.history[-1]["loss"]}
    local, _ = F.local_prepared(prep)
    del prep
    multihost_utils.sync_global_devices("alone")  # every process starts its own fit at once
    alone = F.fit_normal_map(job.problem, job.options, prepared=local, progress=False)
    out["alone_step_s"] = _step_s(alone.history)
    multihost_utils.sync_global_devices("done")
    return out


def _child(args: list[str]) -> subprocess.Popen:
    env = dict(os.environ, JAX_PLATFORMS="cpu", PYTHONWARNINGS="ignore")
    return subprocess.Popen([sys.executable, "-m", MODULE, *args], cwd=ROOT, env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def _results(procs: list[subprocess.Popen]) -> list[dict]:
    out = []
    try:
        for p in procs:
            stdout, stderr = p.communicate(timeout=TIMEOUT)
            if p.returncode != 0:
                raise RuntimeError(f"a benchmark process failed ({p.returncode}): "
                                   f"{stderr.strip().splitlines()[-1:]}")
            out.append(json.loads(stdout.strip().splitlines()[-1]))
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
                p.wait()
    return out


def _port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _machine() -> dict:
    cpu = platform.processor()
    try:
        with open("/proc/cpuinfo") as f:
            cpu = next((ln.split(":", 1)[1].strip() for ln in f if ln.startswith("model name")),
                       cpu)
    except OSError:
        pass
    return {"cpu": cpu, "cores": os.cpu_count(), "machine": platform.machine(),
            "python": platform.python_version()}


def summarize(count: int, per_process: list[dict]) -> dict:
    """One configuration's row: the slowest process's step, the largest peak RSS, and the
    communication fraction of the step (0 for one process)."""
    step = max(p["step_s"] for p in per_process)
    row = {"processes": count, "step_s": step,
           "peak_rss_mb": max(p["peak_rss_mb"] or 0 for p in per_process),
           "prepared_mb": max(p["prepared_mb"] for p in per_process),
           "per_process": per_process}
    if count > 1:
        alone = max(p["alone_step_s"] for p in per_process)
        row["alone_step_s"] = alone
        row["communication_fraction"] = max(0.0, 1.0 - alone / step)
    else:
        row["communication_fraction"] = 0.0
    return row


def markdown(res: dict) -> str:
    """The table of a result (rows: process counts)."""
    lines = ["| processes | views per process | step (s, median) | of which communication | "
             "peak RSS per process (MB) | prepared views per process (MB) |",
             "|---|---|---|---|---|---|"]
    for row in res["runs"]:
        views = "/".join(str(p["views"]) for p in row["per_process"])
        rss = "/".join(f"{p['peak_rss_mb']:.0f}" for p in row["per_process"])
        held = "/".join(f"{p['prepared_mb']:.1f}" for p in row["per_process"])
        comm = ("—" if row["processes"] == 1
                else f"{100 * row['communication_fraction']:.0f}% "
                     f"(alone {row['alone_step_s']:.2f} s)")
        lines.append(f"| {row['processes']} | {views} | {row['step_s']:.2f} | {comm} | {rss} | "
                     f"{held} |")
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--processes", default="1,2", help="process counts, comma-separated")
    ap.add_argument("--views", type=int, default=8)
    ap.add_argument("--size", type=int, default=128)
    ap.add_argument("--map", type=int, default=128)
    ap.add_argument("--lights", type=int, default=4)
    ap.add_argument("--steps", type=int, default=8)
    ap.add_argument("--out", type=Path)
    ap.add_argument("--worker", nargs="+", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    output("--out", args.out, folder=False)  # before the work
    if args.worker:  # one benchmark process: prints its JSON line
        kind, rest = args.worker[0], args.worker[1:]
        if kind == "make":
            out = {"fit": str(make_fit_file(Path(rest[0]), views=args.views, size=args.size,
                                            map_size=args.map, lights=args.lights,
                                            steps=args.steps))}
        elif kind == "one":
            out = run_one(rest[0])
        else:
            out = run_member(rest[0], int(rest[1]), int(rest[2]), int(rest[3]))
        print(json.dumps(out), flush=True)
        return 0
    counts = [int(c) for c in args.processes.split(",")]
    size_args = ["--views", str(args.views), "--size", str(args.size), "--map", str(args.map),
                 "--lights", str(args.lights), "--steps", str(args.steps)]
    with tempfile.TemporaryDirectory() as tmp:
        fit = _results([_child([*size_args, "--worker", "make", tmp])])[0]["fit"]
        runs = []
        for n in counts:
            if n == 1:
                per = _results([_child(["--worker", "one", fit])])
            else:
                port = _port()
                per = _results([_child(["--worker", "member", fit, str(port), str(n), str(i)])
                                for i in range(n)])
            runs.append(summarize(n, per))
    from importlib.metadata import version

    res = {"machine": _machine(), "jax": version("jax"), "backend": "cpu",
           "problem": {"views": args.views, "size": args.size, "map": args.map,
                       "lights_per_view": args.lights, "steps": args.steps,
                       "solver": "lm-texel", "cg_steps": CG_STEPS},
           "command": "python -m " + MODULE + " " + " ".join(
               argv if argv is not None else sys.argv[1:]),
           "runs": runs}
    res["table"] = markdown(res)
    text = json.dumps(res, indent=1)
    if args.out:
        args.out.write_text(text)
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(run_script(main))
