"""Where `render` and the fit's LM step spend their time, on whatever backend JAX runs on.

    python scripts/profile_render.py [--out profile_out] [--trace] [--fit] [--repeats 50]

For the bench scenes (20k torus at 512x512, 200k torus at 1024x1024, the fit benchmark's
camera) it times, medians of ``--repeats`` runs, each forced to completion:

- ``render``: `jaxnm.render` as a user calls it (the default packing for this backend),
  then with ``pack=False`` and ``pack=True``, and the host's part of a call (until the
  outputs are dispatched);
- ``whole_jit``: the whole frame as one program, the scene an argument of the caller's jit;
- ``visibility``: `jaxnm.rasterize`'s triangle ids alone.

``--slots 15,17,19`` also times visibility and the whole-frame program with rounds of
2^k (triangle, tile) slots instead of `jaxnm.raster.default_slots` (its cap was chosen on
the CPU), with each variant's compile time. ``--host`` breaks `render`'s host part
(before its program is dispatched) into its steps.

``--fit`` also times steps of the fit benchmark (``--solver``, default lm-texel), with
the first run's time (compilation included), for each of ``--texel-sums`` (e.g.
``scatter,tables``: how the step sums into the texels, `FitOptions.texel_sums`), and
says whether two runs gave the same map bit for bit.
``--trace`` also records a profiler trace of the whole-frame program (and, with ``--fit``,
of the fit's steps) and prints the kernels that take the most device time per frame (per
step): on a GPU, its kernels and copies; on the CPU, XLA's thunks, which nest (an
executor's span holds its kernels'). JSON on stdout, one object per line; the traces
(``perfetto_trace.json.gz``, for https://ui.perfetto.dev) stay in ``--out``.
"""

from __future__ import annotations

import argparse
import collections
import gzip
import importlib
import json
import os
import statistics
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

import bench_problem as B  # noqa: E402
import jax  # noqa: E402
import numpy as np  # noqa: E402

import jaxnm  # noqa: E402
from jaxnm import fit as F  # noqa: E402
from jaxnm import procedural  # noqa: E402

SCENES = {"20k torus 512": ((128, 80), 512), "200k torus 1024": ((500, 200), 1024)}


def median_ms(fn, repeats: int) -> float:
    jax.block_until_ready(fn())
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        jax.block_until_ready(fn())
        times.append(time.perf_counter() - t)
    return round(statistics.median(times) * 1e3, 3)


def host_ms(fn, repeats: int) -> float:
    """Median time until ``fn`` returns (its device work dispatched, not finished)."""
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t)
        jax.block_until_ready(out)
    return round(statistics.median(times) * 1e3, 3)


def scene_for(grid, size) -> jaxnm.Scene:
    p = B.make_problem(render_size=size)
    torus = procedural.torus(1.0, 0.4, *grid)
    mesh = jaxnm.Mesh(torus.positions, torus.faces, torus.uv, torus.normals)
    # on the device, as a user's scene after its first use (NumPy leaves would be copied in
    # on every call)
    return jax.device_put(B.jaxnm_scene(p, p.light_dirs[0]).replace(mesh=mesh))


def kernel_table(trace_dir: Path, per: int, top: int = 15) -> list[dict]:
    """The device kernels of the newest trace under ``trace_dir``, by total time / ``per``
    (the first row: all device events, their time and count); then the host's events
    (Python's frames left out) by total time / ``per``, rows marked ``"host"``: on a GPU,
    where the host's time goes between the kernels (launches, waits, copies)."""
    path = sorted(trace_dir.rglob("perfetto_trace.json.gz"), key=lambda q: q.stat().st_mtime)[-1]
    with gzip.open(path) as f:
        events = json.load(f)["traceEvents"]
    names = {e["pid"]: e["args"]["name"] for e in events
             if e.get("ph") == "M" and e.get("name") == "process_name"}
    threads = {(e["pid"], e["tid"]): e["args"]["name"] for e in events
               if e.get("ph") == "M" and e.get("name") == "thread_name"}
    device = {pid for pid, n in names.items() if "GPU" in n or "TPU" in n}
    on_gpu = bool(device)
    if not device:  # the CPU backend: XLA's thunks on the host threads
        device = {pid for pid, n in names.items() if "Host" in n or "CPU" in n}
    total, count = collections.Counter(), collections.Counter()
    host_total, host_count = collections.Counter(), collections.Counter()
    for e in events:
        # (Python frames, "$file:line name", are the host's: not device work)
        if e.get("ph") != "X" or e["name"].startswith("$"):
            continue
        key = f'{e["name"]} @ {threads.get((e["pid"], e.get("tid")), "?")}'
        if e.get("pid") in device:
            total[key] += e.get("dur", 0.0)
            count[key] += 1
        elif on_gpu:
            host_total[key] += e.get("dur", 0.0)
            host_count[key] += 1
    allk = sum(total.values())
    rows = [{"kernel": k[:120], "us": round(us / per, 1), "calls": count[k] // per,
             "share": round(us / allk, 3)} for k, us in total.most_common(top)]
    rows += [{"host": k[:120], "us": round(us / per, 1), "calls": host_count[k] // per}
             for k, us in host_total.most_common(top)]
    return [{"kernel": "(all device events)", "us": round(allk / per, 1),
             "calls": sum(count.values()) // per}] + rows


def profile_render(name, grid, size, args) -> dict:
    scene = scene_for(grid, size)
    row = {"scene": name, "backend": jax.default_backend()}
    row["render_ms"] = median_ms(lambda: jaxnm.render(scene)["color"], args.repeats)
    row["render_host_ms"] = host_ms(lambda: jaxnm.render(scene)["color"], args.repeats)
    for pack in (False, True):
        row[f"render_pack_{pack}_ms"] = median_ms(
            lambda pack=pack: jaxnm.render(scene, pack=pack)["color"], args.repeats)

    whole = jax.jit(lambda s: jaxnm.render(s)["color"])
    row["whole_jit_ms"] = median_ms(lambda: whole(scene), args.repeats)
    row["whole_jit_host_ms"] = host_ms(lambda: whole(scene), args.repeats)

    cam = scene.camera
    clip = jaxnm.to_clip(scene.mesh.positions, cam)

    @jax.jit
    def ids(clip, faces):
        return jaxnm.rasterize(clip, faces, width=size, height=size).triangle_id

    row["visibility_ms"] = median_ms(lambda: ids(clip, scene.mesh.faces), args.repeats)
    if args.trace:
        d = Path(args.out) / f"trace_{name.replace(' ', '_')}"
        frames = 20
        with jax.profiler.trace(str(d), create_perfetto_trace=True):
            for _ in range(frames):
                jax.block_until_ready(whole(scene))
        row["kernels"] = kernel_table(d, frames)
    return row


def compile_s(fn, *args) -> float:
    t = time.perf_counter()
    fn.lower(*args).compile()
    return round(time.perf_counter() - t, 3)


def profile_slots(name, grid, size, args) -> list[dict]:
    """Visibility and the whole frame with rounds of 2^k slots (see the module docstring)."""
    raster = importlib.import_module("jaxnm.raster")

    scene = scene_for(grid, size)
    clip = jaxnm.to_clip(scene.mesh.positions, scene.camera)
    faces = scene.mesh.faces
    default = raster.default_slots(faces.shape[0], size, size, 4)
    rows = []
    for k in [int(k) for k in args.slots.split(",")]:
        slots = 1 << k

        @jax.jit
        def ids(clip, faces, slots=slots):
            return jaxnm.rasterize(clip, faces, width=size, height=size,
                                   slots=slots).triangle_id

        original = raster.default_slots
        raster.default_slots = lambda *a, slots=slots: slots
        try:
            jax.clear_caches()
            whole = jax.jit(lambda s: jaxnm.render(s)["color"])
            row = {"scene": name, "backend": jax.default_backend(), "slots_log2": k,
                   "default_slots_log2": default.bit_length() - 1,
                   "visibility_compile_s": compile_s(ids, clip, faces),
                   "visibility_ms": median_ms(lambda: ids(clip, faces), args.repeats),
                   "whole_jit_compile_s": compile_s(whole, scene),
                   "whole_jit_ms": median_ms(lambda: whole(scene), args.repeats)}
        finally:
            raster.default_slots = original
        rows.append(row)
    jax.clear_caches()
    return rows


def profile_host(name, grid, size, args) -> dict:
    """`render`'s host steps before its program runs, each timed alone (medians)."""
    R = importlib.import_module("jaxnm.render")
    from jaxnm.scene import validate_scene

    scene = scene_for(grid, size)
    jax.block_until_ready(jaxnm.render(scene)["color"])
    v = validate_scene(scene)
    opts = R.RenderOptions.of(v)

    steps = {
        "validate_scene": lambda: validate_scene(scene),
        "RenderOptions.of": lambda: R.RenderOptions.of(v),
        "with_tangents+check_mesh": lambda: (R.with_tangents_if_needed(v, opts),
                                             R.check_mesh(v.mesh, opts, v.source)),
        "back_faces_hidden": lambda: R.back_faces_hidden(v.mesh, v.camera, v.model),
        # the public function shifts the mesh eagerly; `render` leaves that to its programs
        "camera_relative (eager shift)": lambda: R.camera_relative(v),
        "whole render (host part)": lambda: jaxnm.render(scene)["color"],
    }
    row = {"scene": name, "backend": jax.default_backend()}
    for label, fn in steps.items():
        row[f"{label}_ms"] = host_ms(fn, args.repeats)
    return row


def profile_fit(args) -> list[dict]:
    """The fit benchmark's steps, for each of ``--texel-sums``: the first run (compilation
    included), the time per step of the next, and whether two runs gave the same map bit
    for bit (scatter-adds on a GPU need not, without deterministic ops)."""
    problem = B.jaxnm_fit_problem(B.make_problem())
    prep = F.prepare(problem)
    steps = 10
    rows, first_map = [], None
    for sums in args.texel_sums.split(","):
        opts = F.FitOptions(solver=args.solver, max_steps=steps, lsmr_steps=10, ftol=0.0,
                            texel_sums=sums)

        def run(opts=opts):
            return F.fit_normal_map(problem, opts, prepared=prep, progress=False)

        t = time.perf_counter()
        res0 = run()  # compiles
        first = time.perf_counter() - t
        t = time.perf_counter()
        res = run()
        row = {"fit": f"benchmark {args.solver}", "backend": jax.default_backend(),
               "texel_sums": F.texel_sums_for(prep, opts), "first_run_s": round(first, 2),
               "xla_flags": os.environ.get("XLA_FLAGS", ""),
               "s_per_step": round((time.perf_counter() - t) / steps, 4),
               "history_steps": len(res.history) - 1,
               "runs_identical": bool(np.array_equal(res0.slopes, res.slopes)),
               "runs_max_diff": float(np.abs(res0.slopes - res.slopes).max())}
        if first_map is None:
            first_map = res.slopes
        else:
            row["max_diff_vs_first_mode"] = float(np.abs(res.slopes - first_map).max())
        if args.trace:
            d = Path(args.out) / f"trace_fit_{sums}"
            with jax.profiler.trace(str(d), create_perfetto_trace=True):
                run()
            row["kernels"] = kernel_table(d, steps)
        rows.append(row)
    return rows


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="profile_out")
    ap.add_argument("--repeats", type=int, default=50)
    ap.add_argument("--trace", action="store_true")
    ap.add_argument("--fit", action="store_true", help="also the fit benchmark's LM steps")
    ap.add_argument("--solver", choices=F.SOLVERS, default=F.FitOptions().solver,
                    help="the solver --fit times (default: FitOptions')")
    ap.add_argument("--texel-sums", dest="texel_sums", default="auto",
                    help="--fit: FitOptions.texel_sums to time, e.g. scatter,tables")
    ap.add_argument("--scenes", default=",".join(SCENES))
    ap.add_argument("--slots", default="", help="e.g. 15,17,19: rounds of 2^k slots")
    ap.add_argument("--host", action="store_true", help="render's host steps, one by one")
    args = ap.parse_args(argv)
    Path(args.out).mkdir(parents=True, exist_ok=True)
    for name in args.scenes.split(","):
        if name:
            print(json.dumps(profile_render(name, *SCENES[name], args)), flush=True)
            if args.host:
                print(json.dumps(profile_host(name, *SCENES[name], args)), flush=True)
            if args.slots:
                for row in profile_slots(name, *SCENES[name], args):
                    print(json.dumps(row), flush=True)
    if args.fit:
        for row in profile_fit(args):
            print(json.dumps(row), flush=True)


if __name__ == "__main__":
    main()
