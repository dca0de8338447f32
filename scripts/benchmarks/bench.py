"""jaxnm beside Mitsuba 3 on the CPU, in one run: forward frames, gradients, the fit benchmark.

    python -m scripts.benchmarks.bench [--out bench_out] [--quick] [--no-mitsuba] [--budget 30]
        [--repeats 10] [--runs 1] [--no-cli] [--parts forward,fit,cli,views,raster,compiles]
        [--solver lm-texel] [--texel-sums auto] [--devices N]

(from the repository root). The problem is `scripts.benchmarks.bench_problem` (its docstring
defines it in full); Mitsuba's side is `scripts.benchmarks.bench_mitsuba` (``pip install -e
'.[bench]'`` and a system libLLVM; without them its columns say why). jaxnm is measured
as a user calls it: `jaxnm.render` and `jaxnm.fit` with JAX's defaults, no thread, allocator
or XLA setting changed by the benchmark. Every figure is a median of ``--repeats`` runs on
this machine (`scripts.benchmarks.timing`), and jaxnm's and Mitsuba's are measured in the
same process run, so their ratios hold on a noisy machine. Compilation is reported
separately *and* included:

- ``forward``: one frame (512 x 512 and 1024 x 1024; the 4k sphere, the 20k torus and a
  200k torus; one directional light, the 256 x 256 normal map, Lambert): `jaxnm.render`
  against ``mi.render``, and forward + backward w.r.t. the map (an image loss); and the
  frame after the mesh moved (its positions taking turns between two arrays), where
  Mitsuba rebuilds its acceleration structure.
- ``fit``: each renderer fits the map to its own four renders of the true map, from the
  flat map. jaxnm runs ``--solver`` in fresh processes: with an empty persistent
  compilation cache (``cold``), again with the cache it filled (``warm``), and a second
  fit in the warm process (``steady``: nothing left to compile). The clock starts when the
  fit starts, the one-off G-buffer preparation included. Reported: time until the mean
  error over the well-observed texels falls below 1 degree, the final errors over the
  seen and the well-observed texels, the held-out-light PSNR and XLA's compile time.
  Run it once per ``--solver`` (``lm-texel``, ``lm``, ``gn``, ``lbfgs``) to compare the
  solvers, and with ``--texel-sums scatter`` or ``tables`` to compare how a step sums into
  the texels.
- ``cli``: ``jaxnm fit`` (no arguments) as a user runs it: wall time and peak RSS, with an
  empty and with a warm compilation cache.
- ``views``: peak RSS and LM step time of fits from 4, 16 and 64 cameras (two lights
  each, 128 x 128 renders), each in a fresh process: memory against the number of views.
- ``raster``: the rasterizer alone on the forward frames' meshes, sizes and camera:
  `jaxnm.rasterize`'s triangle ids (visibility), with back-face culling, its fragments
  (ids, depth and facing), and the G-buffer a user composes from it (`jaxnm.interpolate`
  of position, uv and normal with fine derivatives, over the whole image); first call and
  steady median each.
- ``compiles``: in a fresh process with no persistent cache, every program the first
  `jaxnm.render` of the fit problem's scene and the cold fit (3 steps) compile, in order,
  with JAX's tracing, lowering and XLA compile times: where a first call's time goes.
- ``--devices N``: the built-in 2-view problem's steady LM step with its views on one and
  on N devices (`jaxnm.fit.shard_views`; on a CPU-only machine, N forced host devices).

Writes ``bench.json`` and ``bench.md`` (the tables) into ``--out`` and prints the JSON.
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import json
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

import jaxnm
from jaxnm import fit as F
from jaxnm import procedural
from jaxnm.textures import encode_normal_map
from scripts._cli import output, run_script
from scripts.benchmarks import bench_problem as B
from scripts.benchmarks import timing

#: The repository root: the benchmark's own worker processes run ``python -m
#: scripts.benchmarks.bench`` from there.
ROOT = Path(__file__).resolve().parents[2]
MODULE = "scripts.benchmarks.bench"

GOALS = {
    "time_to_1deg_cold_s": 5.0, "time_to_1deg_warm_s": 2.0, "cli_wall_s": 30.0,
    "cli_peak_rss_mb": 1024.0, "scaling_200k_over_20k": 2.0, "scaling_1024_over_512": 4.5,
}


# --------------------------------------------------------------------------------------
# forward frames
# --------------------------------------------------------------------------------------


def _meshes(quick: bool) -> dict:
    if quick:
        return {"4k sphere": procedural.uv_sphere(1.0, 64, 32),
                "20k torus": procedural.torus(1.0, 0.4, 128, 80)}
    return {"4k sphere": procedural.uv_sphere(1.0, 64, 32),
            "20k torus": procedural.torus(1.0, 0.4, 128, 80),
            "200k torus": procedural.torus(1.0, 0.4, 500, 200)}


#: Forward cells beyond the problem's own map size: the 20k torus at 512^2 with a map of
#: 512^2 texels (the same procedural map, `bench_problem.make_problem`), so that a change
#: tuned to the table's 256^2 map shows on another (a larger map's samples miss the caches
#: more often).
MAP_CELLS = (("20k torus", 512, 512),)


def _cells(p: B.BenchProblem, sizes, quick: bool):
    """``(row name, problem)`` for each forward cell: every mesh at every size with the
    problem's map, then `MAP_CELLS` (full runs only)."""
    meshes = _meshes(quick)
    for name, mesh in meshes.items():
        for size in sizes:
            yield name, _with_mesh(p, mesh, size)
    if quick:
        return
    for name, size, map_size in MAP_CELLS:
        if size in sizes:
            yield (f"{name}, {map_size}x{map_size} map",
                   _with_map(_with_mesh(p, meshes[name], size), map_size))


def _with_mesh(p: B.BenchProblem, mesh, size: int) -> B.BenchProblem:
    return dataclasses.replace(
        p, positions=np.asarray(mesh.positions, np.float64), faces=np.asarray(mesh.faces),
        uv=np.asarray(mesh.uv, np.float64), normals=np.asarray(mesh.normals, np.float64),
        width=size, height=size)


def _with_map(p: B.BenchProblem, map_size: int) -> B.BenchProblem:
    """``p`` with the benchmark's map made at ``map_size`` texels a side."""
    m = B.make_problem(render_size=8, map_size=map_size, major=3, minor=3)
    return dataclasses.replace(p, gt_texels=m.gt_texels, gt_normals=m.gt_normals,
                               flat_texels=m.flat_texels)


def jaxnm_calls(p: B.BenchProblem) -> dict:
    """jaxnm's timed calls, each forced to completion: ``"forward"`` (`render`),
    ``"forward_moved"`` (`render` of the mesh taking turns between two positions), and the
    loss's value and gradient w.r.t. the map under one jit (``"forward_backward"``); and the
    first render's time in s (``"first_forward_s"``, compilation included: it made the
    target)."""
    scene = B.jaxnm_scene(p, p.light_dirs[0])
    t = time.perf_counter()
    target = jax.block_until_ready(jaxnm.render(scene)["color"])
    first_forward = time.perf_counter() - t

    # the scene is an argument, not a closure: closed-over arrays are compile-time constants,
    # and XLA would constant-fold the rasterizer over them (47 s compiles at 200k triangles)
    @jax.jit
    def loss_and_grad(scene, texels, target):
        def loss(t):
            return jnp.mean((jaxnm.render(scene.replace(normal_map=t))["color"] - target) ** 2)
        return jax.value_and_grad(loss)(texels)

    # the same frame with the mesh taking turns between two positions, as Mitsuba's
    # "forward_moved" (`bench_mitsuba.forward_calls`); jaxnm keeps nothing of a mesh
    # between frames, so this only checks that nothing depends on it staying put
    moved = [scene, scene.replace(mesh=dataclasses.replace(
        scene.mesh, positions=scene.mesh.positions + jnp.asarray([B.MOVED_OFFSET, 0, 0],
                                                                 scene.mesh.positions.dtype)))]
    turn = [0]

    def forward_moved():
        turn[0] ^= 1
        return jax.block_until_ready(jaxnm.render(moved[turn[0]])["color"])

    flat = jnp.asarray(p.flat_texels)
    return {"forward": lambda: jax.block_until_ready(jaxnm.render(scene)["color"]),
            "forward_moved": forward_moved,
            "forward_backward": lambda: jax.block_until_ready(
                loss_and_grad(scene, flat, target)),
            "first_forward_s": first_forward}


#: The timed calls of `bench_forward`: jaxnm's (`jaxnm_calls`) and Mitsuba's
#: (`bench_mitsuba.forward_calls`).
JAXNM_CALLS = ("forward", "forward_moved", "forward_backward")
MITSUBA_CALLS = ("forward", "forward_moved", "forward_backward")


def bench_forward(p: B.BenchProblem, mitsuba, sizes, repeats: int, quick: bool,
                  runs: int = 1, only: str | None = None) -> list[dict]:
    """Per cell (`_cells`; with ``only``, those whose "mesh size" contains it): jaxnm's and
    Mitsuba's forward and forward+backward calls, taking
    turns in blocks (`timing.side_by_side`: the ratios compare the same phases of a noisy
    machine), one cell after the other; ``runs`` times over, where each figure is the
    median of the runs' (and each ratio the median of the runs' ratios, each side by side
    in its run), and the runs' forward ratios are listed (``"forward_ratio_runs"``). A slow
    stretch of a shared machine (seconds to half a minute on a small one) that catches one
    cell in one run then decides none of its figures.

    Each run sets every cell up again (the first run's first calls are the compile times)
    and lets it go before the next: with all six cells' Mitsuba scenes alive at once,
    Mitsuba's frames were up to 1.5x slower (4k sphere 3.7 -> 5.5 ms at 512^2)."""
    cells, timed = {}, {}
    for r in range(runs):
        for name, q in _cells(p, sizes, quick):
            size = q.width
            if only is not None and only not in f"{name} {size}x{size}":
                continue
            jc = jaxnm_calls(q)
            calls = {f"jaxnm {k}": jc[k] for k in JAXNM_CALLS}
            mi = None
            if mitsuba is not None:
                mi = mitsuba.forward_calls(q)
                calls.update({f"mitsuba {k}": mi[k] for k in MITSUBA_CALLS})
            first, ms, faults = timing.side_by_side(calls, repeats, seed=r,
                                                  first_calls=r == 0)
            if r == 0:  # what the rows keep of the cell: its first calls
                mi = None if mi is None else {
                    k: mi[k] for k in ("first_s", "kernel_cache_files_at_start")}
                cells[name, size] = (name, q, jc["first_forward_s"], mi, first)
            timed.setdefault((name, size), []).append((ms, faults))
            del calls, jc, mi
            if runs == 1:  # the cell's row now
                _forward_rows([cells[name, size]], [timed[name, size]])
            else:
                print(f"bench forward: {name} at {size}^2, run {r + 1} of {runs}",
                      file=sys.stderr, flush=True)
    return _forward_rows(list(cells.values()), list(timed.values()), echo=runs > 1)


def _forward_rows(cells, timed, echo: bool = True) -> list[dict]:
    """`bench_forward`'s rows of ``cells`` from each cell's runs ``timed`` ((ms, faults) per
    run): medians over the runs (page faults per call: the runs' most)."""
    rows = []
    for (name, q, first_forward_s, mi, first), t in zip(cells, timed):
        def med(k, t=t):
            return statistics.median(ms[k] for ms, _ in t)

        j = {f"{k}_ms": round(med(f"jaxnm {k}"), 2) for k in JAXNM_CALLS}
        j["page_faults_per_call"] = {k: max(f[f"jaxnm {k}"] for _, f in t) for k in JAXNM_CALLS}
        j.update({"first_forward_s": round(first_forward_s, 2),
                  "first_backward_s": round(first["jaxnm forward_backward"], 2),
                  "triangles": int(q.faces.shape[0]), "size": f"{q.width}x{q.height}"})
        row = {"mesh": name, "jaxnm": j}
        if mi is not None:
            row["mitsuba"] = {
                "forward_ms": round(med("mitsuba forward"), 2),
                "forward_moved_ms": round(med("mitsuba forward_moved"), 2),
                "forward_backward_ms": round(med("mitsuba forward_backward"), 2),
                "first_forward_s": round(mi["first_s"]["forward"], 2),
                "first_backward_s": round(mi["first_s"]["forward_backward"], 2),
                "kernel_cache_files_at_start": mi["kernel_cache_files_at_start"],
                "page_faults_per_call": {k: max(f[f"mitsuba {k}"] for _, f in t)
                                         for k in MITSUBA_CALLS}}

            def ratio(ours, theirs, t=t):
                return round(statistics.median(ms[f"jaxnm {ours}"] / ms[f"mitsuba {theirs}"]
                                               for ms, _ in t), 2)

            row["forward_ratio"] = ratio("forward", "forward")
            row["forward_moved_ratio"] = ratio("forward_moved", "forward_moved")
            row["forward_backward_ratio"] = ratio("forward_backward", "forward_backward")
            if len(t) > 1:
                row["forward_ratio_runs"] = [
                    round(ms["jaxnm forward"] / ms["mitsuba forward"], 2) for ms, _ in t]
        if len(t) > 1:
            j["forward_ms_runs"] = [round(ms["jaxnm forward"], 2) for ms, _ in t]
        rows.append(row)
        if echo:
            print(json.dumps(row), file=sys.stderr, flush=True)
    return rows


# --------------------------------------------------------------------------------------
# the rasterizer alone
# --------------------------------------------------------------------------------------


def bench_raster(p: B.BenchProblem, sizes, repeats: int, quick: bool) -> list[dict]:
    """Per mesh and size of the forward frames (the problem's camera): `jaxnm.rasterize`'s
    triangle ids (visibility), the same with back-face culling, its whole `Fragments`
    (ids, depth and facing), and the G-buffer a user composes from them
    (`jaxnm.interpolate` of position, uv and normal with fine derivatives, over the whole
    image); each under one jit, the mesh an argument, its first call (compilation included)
    and the median of ``repeats`` steady calls."""
    rows = []
    for name, mesh in _meshes(quick).items():
        for size in sizes:
            q = _with_mesh(p, mesh, size)
            m = B.jaxnm_scene(q, q.light_dirs[0]).mesh
            clip = jax.block_until_ready(jaxnm.to_clip(m.positions, B.jaxnm_camera(q)))
            attrs = {"p": m.positions, "uv": m.uv, "n": m.normals}

            @functools.partial(jax.jit, static_argnames="cull_back")
            def visibility(clip, faces, cull_back=False, size=size):
                return jaxnm.rasterize(clip, faces, width=size, height=size,
                                       cull_back=cull_back).triangle_id

            @jax.jit
            def fragments(clip, faces, size=size):
                return jaxnm.rasterize(clip, faces, width=size, height=size)

            @jax.jit
            def gbuffer(clip, faces, attrs, size=size):
                frags = jaxnm.rasterize(clip, faces, width=size, height=size)
                return jaxnm.interpolate(attrs, frags, derivatives="fine")

            t = {"visibility": timing.time_call(lambda: visibility(clip, m.faces),
                                                repeats=repeats),
                 "visibility_cull_back": timing.time_call(
                     lambda: visibility(clip, m.faces, cull_back=True), repeats=repeats),
                 "fragments": timing.time_call(lambda: fragments(clip, m.faces),
                                               repeats=repeats),
                 "gbuffer": timing.time_call(lambda: gbuffer(clip, m.faces, attrs),
                                             repeats=repeats)}
            covered = jnp.mean(jaxnm.rasterize(clip, m.faces, width=size, height=size).mask)
            row = {"mesh": name, "triangles": int(m.faces.shape[0]), "size": f"{size}x{size}",
                   "covered_fraction": round(float(covered), 3)}
            for k, tk in t.items():
                row[f"{k}_ms"] = round(tk.median_ms, 2)
                row[f"{k}_first_s"] = round(tk.first_s, 2)
            row["visibility_mpix_per_s"] = round(size * size / t["visibility"].median_ms / 1e3, 1)
            rows.append(row)
            print(json.dumps(row), file=sys.stderr, flush=True)
    return rows


# --------------------------------------------------------------------------------------
# the fit benchmark
# --------------------------------------------------------------------------------------


def _problem(quick: bool) -> B.BenchProblem:
    return (B.make_problem(render_size=256, map_size=128, major=64, minor=40) if quick
            else B.make_problem())


def _error_summary(normals, p: B.BenchProblem, seen, well) -> dict:
    err = B.angle_deg(normals, p.gt_normals)
    return {"seen_mean_deg": round(float(err[seen].mean()), 4),
            "well_mean_deg": round(float(err[well].mean()), 4),
            "well_p95_deg": round(float(np.percentile(err[well], 95)), 4)}


def _jaxnm_fit_once(p: B.BenchProblem, targets, well, budget: float, solver: str,
                    texel_sums: str = "auto") -> dict:
    """One LM fit; the clock includes `prepare` (the G-buffer) and every compilation."""
    problem = B.jaxnm_fit_problem(p, targets)
    with timing.CompileLog() as log:
        t0 = time.perf_counter()
        prep = F.prepare(problem)
        t_prep = time.perf_counter() - t0
        opts = F.FitOptions(solver=solver, max_steps=40, lsmr_steps=10, texel_sums=texel_sums)
        res = F.fit_normal_map(problem, opts,
                               ground_truth=p.gt_normals, prepared=prep, progress=False,
                               time_limit=budget, error_texels=well)
    below = [t_prep + h["seconds"] for h in res.history if h["mean_angular_error_deg"] < 1.0]
    steps = [b - a for a, b in zip([h["seconds"] for h in res.history][1:-1],
                                   [h["seconds"] for h in res.history][2:])]
    return {"time_to_1deg_s": round(below[0], 2) if below else None,
            "prepare_s": round(t_prep, 2),
            "first_loss_s": round(t_prep + res.history[0]["seconds"], 2),
            "s_per_step": round(statistics.median(steps), 3) if steps else None,
            "steps": len(res.history) - 1, "backend_compile_s": round(log.compile_s, 2),
            "normals": res.normals}


def fit_worker(args) -> None:
    """In a fresh process: the jaxnm fit (then again, steady), JSON on stdout."""
    jax.config.update("jax_compilation_cache_dir", args.cache)
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.05)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
    p = _problem(args.quick)
    seen, well = B.texel_masks(p)
    targets = B.jaxnm_fit_problem(p).targets
    # as if the targets came from files: the fit compiles everything it runs, including
    # the visibility program its `prepare` shares with `render` (1 s cold)
    jax.clear_caches()
    out = {}
    for run in ("first", "steady"):
        r = _jaxnm_fit_once(p, targets, well, args.budget, args.solver, args.texel_sums)
        normals = r.pop("normals")
        r.update(_error_summary(normals, p, seen, well))
        held = B.jaxnm_scene(p, p.held_out_dir)
        texels = encode_normal_map(jnp.asarray(normals))
        r["held_out_psnr_db"] = round(B.psnr(jaxnm.render(held.replace(normal_map=texels))
                                             ["color"], jaxnm.render(held)["color"]), 2)
        out[run] = r
    print("RESULT " + json.dumps(out))


def devices_worker(args) -> None:
    """In a fresh process with ``--devices`` devices: the built-in 2-view problem, 10 LM
    steps, views spread over the devices (`jaxnm.fit.shard_views`); JSON on stdout."""
    from jaxnm.procedural import default_problem

    problem, gt, _ = default_problem(render_size=256 if args.quick else 512,
                                     map_size=128 if args.quick else 256, views=2)
    prep = F.shard_views(F.prepare(problem))
    opts = F.FitOptions(max_steps=10, lsmr_steps=10, ftol=0.0)
    F.fit_normal_map(problem, opts, prepared=prep, progress=False)  # compile
    res = F.fit_normal_map(problem, opts, prepared=prep, progress=False)
    secs = [h["seconds"] for h in res.history]
    print("RESULT " + json.dumps({
        "devices": len(jax.devices()), "platform": jax.devices()[0].platform,
        "s_per_step": round(statistics.median(np.diff(secs[1:])), 4),
        "views_per_device": [len(b.views) // len(jax.devices()) for b in prep.batches]}))


def bench_devices(args) -> dict:
    """Steady LM step time with the views on 1 and on ``--devices`` devices (on a CPU-only
    machine the devices are forced host devices sharing the same cores)."""
    out = {}
    for n in sorted({1, args.devices}):
        env = _worker_env()
        if jax.devices()[0].platform == "cpu":
            env["XLA_FLAGS"] = (env.get("XLA_FLAGS", "")
                                + f" --xla_force_host_platform_device_count={n}").strip()
        out[str(n)] = _run_worker(["--devices-worker"] + (["--quick"] if args.quick else []),
                                  env)
    return out


def compiles_worker(args) -> None:
    """In a fresh process (no persistent compilation cache): the programs that the first
    `jaxnm.render` of the fit problem's scene (light 0) compiles, then those of the cold fit
    as the ``fit`` part times it (its targets rendered, every compiled program dropped, then
    `prepare` and 3 steps of ``--solver``); JSON rows on stdout (`timing.CompileLog`)."""
    p = _problem(args.quick)
    scene = B.jaxnm_scene(p, p.light_dirs[0])
    with timing.CompileLog() as log:
        t = time.perf_counter()
        jax.block_until_ready(jaxnm.render(scene)["color"])
        wall = time.perf_counter() - t
    rows = [{"phase": "render", "wall_s": round(wall, 3), **log.summary()}]
    problem = B.jaxnm_fit_problem(p)
    jax.clear_caches()
    opts = F.FitOptions(solver=args.solver, max_steps=3, lsmr_steps=10, ftol=0.0,
                        texel_sums=args.texel_sums)
    with timing.CompileLog() as log:
        t = time.perf_counter()
        prep = F.prepare(problem)
        t_prep = time.perf_counter() - t
        res = F.fit_normal_map(problem, opts, prepared=prep, progress=False)
        wall = time.perf_counter() - t
    rows.append({"phase": f"fit ({args.solver}, {len(res.history) - 1} steps)",
                 "wall_s": round(wall, 3), "prepare_s": round(t_prep, 3), **log.summary()})
    for r in rows:
        r["backend"] = jax.default_backend()
    print("RESULT " + json.dumps(rows))


def bench_compiles(args) -> list[dict]:
    """`compiles_worker`'s rows."""
    rows = _run_worker(["--compiles-worker", "--solver", args.solver, "--texel-sums",
                        args.texel_sums] + (["--quick"] if args.quick else []))
    for r in rows:
        print(json.dumps(r), file=sys.stderr, flush=True)
    return rows


def _ring_eyes(n: int, radius: float = 3.0) -> list[tuple[float, float, float]]:
    """``n`` eyes spread over the upper hemisphere around the origin (a Fibonacci spiral)."""
    eyes = []
    for i in range(n):
        z = 0.25 + 0.7 * (i + 0.5) / n
        phi = i * np.pi * (3.0 - np.sqrt(5.0))
        r = np.sqrt(1.0 - z * z)
        eyes.append((radius * r * np.cos(phi), radius * r * np.sin(phi), radius * z))
    return eyes


def _status_mb(key: str) -> float | None:
    """``key`` (VmRSS, VmHWM) of this process from /proc, in MB (None off Linux)."""
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith(key + ":"):
                    return int(line.split()[1]) / 1024
    except OSError:
        return None
    return None


def _reset_peak() -> float | None:
    """Hand freed memory back, reset this process's peak RSS to its current RSS (Linux's
    /proc/self/clear_refs) and return that RSS in MB (None where it cannot)."""
    import gc

    gc.collect()
    try:
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")
    except OSError:
        return None
    return _status_mb("VmRSS")


def _peak_mb() -> float:
    return _status_mb("VmHWM")


def views_worker(args) -> None:
    """In a fresh process: an LM fit of the built-in torus and rivet map from ``--views``
    cameras (two lights each, ``--view-size`` square renders, a 128 x 128 map, 3 steps),
    prepared with ``--chunk`` pixel-targets per piece of a step ("none": whole); JSON on
    stdout. The parent reads this process's peak RSS; ``fit_working_mb`` is the fit's own
    peak above the memory held when it starts (the targets and the prepared problem),
    ``steps_working_mb`` the same for the same fit run again (nothing left to compile),
    ``prepare_working_mb`` the peak of `prepare` above the memory before it; the step time
    is the second fit's."""
    from jaxnm.camera import Camera, eye_to_world, look_at, perspective
    from jaxnm.procedural import default_problem
    from jaxnm.shading import directional_light

    size = args.view_size
    scene = default_problem(render_size=size, map_size=128, n_lights=1, views=1)[2]
    targets = []
    for eye in _ring_eyes(args.views):
        cam = Camera.from_matrices(look_at(eye, (0.0, 0.0, 0.0), (0.0, 0.0, 1.0)),
                                   perspective(45.0, 1.0, 0.1, 50.0))
        for d in ((-0.4, 0.5, 1.0), (0.6, -0.2, 1.0)):
            lights = directional_light(eye_to_world(cam, np.array(d)))
            sc = scene.replace(camera=cam, lights=lights)
            targets.append(F.FitTarget(cam, size, size, lights,
                                       np.asarray(jaxnm.render(sc)["color"])))
    problem = F.problem_from_scene(scene, targets, (128, 128), source="<views>")
    chunk = None if args.chunk == "none" else int(args.chunk)
    before_mb = _reset_peak()
    t = time.perf_counter()
    prep = F.prepare(problem, chunk=chunk)
    prepare_mb = None if before_mb is None else round(_peak_mb() - before_mb)
    opts = F.FitOptions(solver=args.solver, max_steps=3, lsmr_steps=10, ftol=0.0)
    working = []
    for run in range(2):  # the second fit compiles nothing: the steps' own memory
        start_mb = _reset_peak()
        res = F.fit_normal_map(problem, opts, prepared=prep, progress=False)
        working.append(None if start_mb is None else round(_peak_mb() - start_mb))
        if run == 0:
            fit_s = time.perf_counter() - t
    secs = [h["seconds"] for h in res.history]
    print("RESULT " + json.dumps({
        "views": args.views, "size": size, "chunk": args.chunk, "solver": args.solver,
        "targets": len(targets),
        "prepared_mb": round(sum(x.nbytes for x in jax.tree_util.tree_leaves(prep)) / 2**20, 1),
        "pixels": int(sum(int(np.prod(b.images.shape[:1] + b.images.shape[2:3]))
                          for b in prep.batches)),
        "fit_s": round(fit_s, 2), "prepare_working_mb": prepare_mb,
        "fit_working_mb": working[0], "steps_working_mb": working[1],
        "s_per_step": round(statistics.median(np.diff(secs[1:])), 3)}))


def bench_views(args) -> list[dict]:
    """Peak RSS and LM step time of a fit against its number of views and their size (fresh
    processes), by optimistix's LM and by the texel-space LM (``lm-texel``): 4, 16, 64
    views of 128 x 128 and 16 of 256 x 256 with `prepare`'s default chunking, and 64 views
    evaluated whole and in chunks of 2^17 pixel-targets."""
    rows = []
    runs = ([(4, 128, "default"), (16, 128, "default"), (64, 128, "default"),
             (64, 128, "none"), (64, 128, str(1 << 17)), (16, 256, "default")]
            if not args.quick else [(2, 128, "default"), (8, 128, str(1 << 12))])
    runs = [run + (solver,) for solver in ("lm", "lm-texel") for run in runs]
    for n, size, chunk, solver in runs:
        chunk = str(F.CHUNK) if chunk == "default" else chunk
        cmd = _worker_cmd("--views-worker", "--views", str(n), "--view-size", str(size),
                          "--chunk", chunk, "--solver", solver)
        child = _timed_child(cmd, _worker_env(), keep_output=True)
        row = json.loads(child["output"].split("RESULT ", 1)[1])
        row.update(wall_s=child["wall_s"], peak_rss_mb=child["peak_rss_mb"])
        rows.append(row)
        print(json.dumps(row), file=sys.stderr, flush=True)
    return rows


def _worker_cmd(*args: str) -> list[str]:
    """The command of one of this benchmark's worker processes (run from `ROOT`)."""
    return [sys.executable, "-m", MODULE, *args]


def _worker_env() -> dict:
    """A worker's environment: this process's, without ``JAX_COMPILATION_CACHE_DIR`` (a
    worker measures its own compilation; the fit worker turns the cache on itself)."""
    return {k: v for k, v in os.environ.items() if k != "JAX_COMPILATION_CACHE_DIR"}


def _run_worker(args: list[str], env: dict | None = None) -> dict:
    """Run a worker (`_worker_cmd`) and return the JSON it printed after ``RESULT``."""
    out = subprocess.run(_worker_cmd(*args), env=_worker_env() if env is None else env,
                         cwd=ROOT, capture_output=True, text=True, check=True).stdout
    return json.loads(out.split("RESULT ", 1)[1])


def _fit_worker_args(cache: str, args) -> list[str]:
    return ["--fit-worker", "--cache", cache, "--budget", str(args.budget), "--solver",
            args.solver, "--texel-sums", args.texel_sums] + (["--quick"] if args.quick else [])


def bench_fit(args, mitsuba) -> dict:
    result = {}
    with tempfile.TemporaryDirectory() as cache:
        cold = _run_worker(_fit_worker_args(cache, args))
        warm = _run_worker(_fit_worker_args(cache, args))
    result["jaxnm"] = {"cold": cold["first"], "warm": warm["first"], "steady": warm["steady"],
                       "solver": args.solver, "texel_sums": args.texel_sums}
    if mitsuba is not None:
        p = _problem(args.quick)
        seen, well = B.texel_masks(p)
        fit = mitsuba.fit(p, budget_s=args.budget, snapshot_every=5)
        errs = [(s["seconds"], B.angle_deg(s["normals"], p.gt_normals)[well].mean())
                for s in fit["snapshots"]]
        below = [t for t, e in errs if e < 1.0]
        final = fit["snapshots"][-1]["normals"]
        texels = np.array(encode_normal_map(jnp.asarray(final)))  # writable, for Mitsuba
        held = mitsuba.render(p, texels, p.held_out_dir)
        truth = mitsuba.render(p, p.gt_texels, p.held_out_dir)
        result["mitsuba"] = {
            "time_to_1deg_s": round(below[0], 2) if below else None,
            "first_step_s": round(fit["first_step_s"], 2), "s_per_step": fit["s_per_step"],
            "steps": fit["history"][-1]["step"], **_error_summary(final, p, seen, well),
            "held_out_psnr_db": round(B.psnr(held, truth), 2)}
    return result


# --------------------------------------------------------------------------------------
# the command a user runs
# --------------------------------------------------------------------------------------


# Runs a command, waits for it and writes "exit-code peak-RSS-KiB" to the file named first.
# The peak is read with wait4 *from this small process*: Linux carries the memory high-water
# mark of the process image that exec replaces into the child's ru_maxrss, and a child
# spawned straight from the benchmark (vfork + exec) would report the benchmark's own peak.
_RUNNER = """
import os, subprocess, sys
proc = subprocess.Popen(sys.argv[2:], stderr=subprocess.DEVNULL)
_, status, usage = os.wait4(proc.pid, 0)
with open(sys.argv[1], "w") as f:
    f.write(f"{os.waitstatus_to_exitcode(status)} {usage.ru_maxrss}")
"""


def _timed_child(cmd, env, keep_output: bool = False) -> dict:
    """Run ``cmd``; its wall time, its own peak RSS and its first output line (all of it
    with ``keep_output``)."""
    with tempfile.TemporaryFile() as out, tempfile.NamedTemporaryFile("r") as stat:
        t = time.perf_counter()
        subprocess.run([sys.executable, "-c", _RUNNER, stat.name, *cmd], env=env, stdout=out,
                       cwd=ROOT, check=True)
        wall = time.perf_counter() - t
        code, maxrss_kib = (int(v) for v in stat.read().split())
        out.seek(0)
        text = out.read().decode().strip()
    if code != 0:
        raise RuntimeError(f"{' '.join(cmd)} exited with {code}")
    res = {"wall_s": round(wall, 1), "peak_rss_mb": round(maxrss_kib / 1024),
           "summary": text.splitlines()[0] if text else ""}
    if keep_output:
        res["output"] = text
    return res


def bench_cli(args) -> dict:
    jaxnm_bin = str(Path(sys.executable).parent / "jaxnm")
    with tempfile.TemporaryDirectory() as tmp:
        env = dict(_worker_env(), JAXNM_COMPILATION_CACHE=str(Path(tmp) / "cache"))
        cmd = [jaxnm_bin, "fit", "-o", str(Path(tmp) / "out"), "--no-progress"]
        if args.quick:
            cmd.append("--quick")
        return {"cold": _timed_child(cmd, env), "warm": _timed_child(cmd, env)}


# --------------------------------------------------------------------------------------
# report
# --------------------------------------------------------------------------------------


def _r(x, nd: int = 2):
    return "-" if x is None else (round(x, nd) if isinstance(x, float) else x)


def markdown(res: dict) -> str:
    lines = [f"Machine: {res['machine']}; JAX {res['jax']}; {res['mitsuba']}; {res['date']}."]
    if res.get("forward"):
        lines += ["", "| frame | size | jaxnm forward ms | Mitsuba forward ms | ratio | jaxnm "
                  "fwd+bwd ms | Mitsuba fwd+bwd ms | ratio | jaxnm first call s (compile): "
                  "forward, fwd+bwd | mesh moved: jaxnm / Mitsuba forward ms (ratio) |",
                  "|---|---|---|---|---|---|---|---|---|---|"]
    for r in res.get("forward", []):
        j, m = r["jaxnm"], r.get("mitsuba", {})
        lines.append(f"| {r['mesh']} ({j['triangles']} tris) | {j['size']} | {j['forward_ms']} | "
                     f"{_r(m.get('forward_ms'))} | {r.get('forward_ratio', '-')} | "
                     f"{j['forward_backward_ms']} | {_r(m.get('forward_backward_ms'))} | "
                     f"{r.get('forward_backward_ratio', '-')} | {j['first_forward_s']}, "
                     f"{j['first_backward_s']} | "
                     f"{_r(j.get('forward_moved_ms'))} / {_r(m.get('forward_moved_ms'))} "
                     f"({r.get('forward_moved_ratio', '-')}) |")
    f = res.get("fit", {})
    if f:
        lines += ["", "| fit | time to well-observed < 1 deg (s) | prepare (s) | "
                  "first loss after (s) | s / step | XLA compile (s) | steps | "
                  "final seen / well mean (deg) | held-out PSNR (dB) |",
                  "|---|---|---|---|---|---|---|---|---|"]
        for k in ("cold", "warm", "steady"):
            j = f["jaxnm"][k]
            lines.append(f"| jaxnm {f['jaxnm'].get('solver', 'LM')}, {k} | "
                         f"{_r(j['time_to_1deg_s'])} | {j['prepare_s']} | "
                         f"{j['first_loss_s']} | "
                         f"{j['s_per_step']} | {j['backend_compile_s']} | {j['steps']} | "
                         f"{j['seen_mean_deg']} / {j['well_mean_deg']} | "
                         f"{j['held_out_psnr_db']} |")
        if "mitsuba" in f:
            m = f["mitsuba"]
            lines.append(f"| Mitsuba 3 + Adam | {_r(m['time_to_1deg_s'])} | - | "
                         f"{m['first_step_s']} | "
                         f"{_r(m['s_per_step'], 3)} | - | {m['steps']} | {m['seen_mean_deg']} / "
                         f"{m['well_mean_deg']} | {m['held_out_psnr_db']} |")
    c = res.get("cli")
    if c:
        lines += ["", "| `jaxnm fit` | wall s | peak RSS MiB | result |", "|---|---|---|---|"]
        for k in ("cold", "warm"):
            lines.append(f"| {k} cache | {c[k]['wall_s']} | {c[k]['peak_rss_mb']} | "
                         f"{c[k]['summary']} |")
    v = res.get("views")
    if v:
        lines += ["", "| solver | views (x2 lights) | size | chunk (pixel-targets) | "
                  "pixels (all views) | prepared MB | LM s / step | "
                  "fit s (3 steps, compile included) | peak RSS MB | prepare's own MB | "
                  "fit's own MB: first fit / again |",
                  "|---|---|---|---|---|---|---|---|---|---|---|"]
        for r in v:
            lines.append(f"| {r.get('solver', 'lm')} | {r['views']} | {r.get('size', 128)} | "
                         f"{r.get('chunk', '-')} | "
                         f"{r['pixels']} | {r.get('prepared_mb', '-')} | {r['s_per_step']} | "
                         f"{r['fit_s']} | {r['peak_rss_mb']} | "
                         f"{r.get('prepare_working_mb', '-')} | {r.get('fit_working_mb', '-')} / "
                         f"{r.get('steps_working_mb', '-')} |")
    ra = res.get("raster")
    if ra:
        lines += ["", "| rasterizer | size | covered | visibility ms | with back-face culling ms | "
                  "fragments ms (ids, depth, facing) | "
                  "G-buffer ms (p, uv, N + fine derivatives) | visibility Mpix/s | "
                  "first call s (compile): visibility, G-buffer |",
                  "|---|---|---|---|---|---|---|---|---|"]
        for r in ra:
            lines.append(f"| {r['mesh']} ({r['triangles']} tris) | {r['size']} | "
                         f"{r['covered_fraction']} | {r['visibility_ms']} | "
                         f"{r['visibility_cull_back_ms']} | {r['fragments_ms']} | "
                         f"{r['gbuffer_ms']} | "
                         f"{r['visibility_mpix_per_s']} | {r['visibility_first_s']}, "
                         f"{r['gbuffer_first_s']} |")
    co = res.get("compiles")
    if co:
        lines += ["", "| first call | program | tracing s | lowering s | XLA compile s |",
                  "|---|---|---|---|---|"]
        for r in co:
            lines.append(f"| {r['phase']}: {r['wall_s']} s in all, {r['programs_compiled']} "
                         f"programs | (all) | {r['total_trace_s']} | {r['total_lower_s']} | "
                         f"{r['total_compile_s']} |")
            for g in r["programs"]:
                lines.append(f"| | {g['program']} | {g['trace_s']} | {g['lower_s']} | "
                             f"{g['compile_s']} |")
    d = res.get("devices")
    if d:
        lines += ["", "| devices | platform | views per device | LM s / step |",
                  "|---|---|---|---|"]
        for n, r in d.items():
            lines.append(f"| {n} | {r['platform']} | {r['views_per_device']} | "
                         f"{r['s_per_step']} |")
    lines += ["", "Goals: " + ", ".join(f"{k} <= {v}" for k, v in GOALS.items())]
    return "\n".join(lines) + "\n"


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="bench_out")
    ap.add_argument("--quick", action="store_true", help="small sizes (a smoke test)")
    ap.add_argument("--no-mitsuba", action="store_true")
    ap.add_argument("--no-cli", action="store_true")
    ap.add_argument("--parts", default="forward,fit,cli",
                    help="comma-separated parts to run, of forward, fit, cli, views, raster, "
                         "compiles (default: %(default)s)")
    ap.add_argument("--only", help="forward: only the cells whose 'mesh size' contains this, "
                                   "e.g. '512x512 map' or '200k torus 1024x1024'")
    ap.add_argument("--budget", type=float, default=30.0, help="seconds per fit")
    ap.add_argument("--repeats", type=int, default=10)
    ap.add_argument("--runs", type=int, default=1,
                    help="time the forward cells this many times over, one cell after the "
                         "other each time, and report the medians (default: %(default)s)")
    ap.add_argument("--devices", type=int, default=1,
                    help="also time LM steps with the views over this many devices")
    ap.add_argument("--fit-worker", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--devices-worker", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--compiles-worker", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--cache", help=argparse.SUPPRESS)
    ap.add_argument("--views-worker", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--views", type=int, default=4, help=argparse.SUPPRESS)
    ap.add_argument("--view-size", type=int, default=128, help=argparse.SUPPRESS)
    ap.add_argument("--chunk", default=str(F.CHUNK), help=argparse.SUPPRESS)
    ap.add_argument("--solver", default=F.FitOptions().solver, choices=F.SOLVERS,
                    help="the fit benchmark's solver (default: FitOptions', "
                         f"{F.FitOptions().solver}; --parts views runs lm and lm-texel)")
    ap.add_argument("--texel-sums", dest="texel_sums", default="auto", choices=F.TEXEL_SUMS,
                    help="the fit benchmark's FitOptions.texel_sums (default auto)")
    args = ap.parse_args(argv)
    output("--out", args.out, folder=True)  # before the work
    if args.fit_worker:
        return fit_worker(args)
    if args.views_worker:
        return views_worker(args)
    if args.devices_worker:
        return devices_worker(args)
    if args.compiles_worker:
        return compiles_worker(args)
    mitsuba, why = None, "Mitsuba not run (--no-mitsuba)"
    if not args.no_mitsuba:
        from scripts.benchmarks import bench_mitsuba

        ok, why = bench_mitsuba.available()
        mitsuba = bench_mitsuba if ok else None
        if not ok:
            print(f"Mitsuba 3 unavailable, its columns are empty: {why}", file=sys.stderr)
    res = {"machine": f"{platform.machine()}, {os.cpu_count()} cores, {platform.system()}",
           "jax": jax.__version__, "jaxnm": jaxnm.__version__, "mitsuba": why,
           "date": time.strftime("%Y-%m-%d")}
    parts = set(args.parts.split(","))
    p = _problem(args.quick)
    sizes = (256,) if args.quick else (512, 1024)
    if "forward" in parts:
        res["forward"] = bench_forward(p, mitsuba, sizes, args.repeats, args.quick,
                                       runs=args.runs, only=args.only)
    if "fit" in parts:
        res["fit"] = bench_fit(args, mitsuba)
    if "cli" in parts and not args.no_cli:
        res["cli"] = bench_cli(args)
    if "views" in parts:
        res["views"] = bench_views(args)
    if "raster" in parts:
        res["raster"] = bench_raster(p, sizes, args.repeats, args.quick)
    if "compiles" in parts:
        res["compiles"] = bench_compiles(args)
    if args.devices > 1:
        res["devices"] = bench_devices(args)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "bench.json").write_text(json.dumps(res, indent=1) + "\n")
    (out / "bench.md").write_text(markdown(res))
    print(json.dumps(res))
    print(markdown(res), file=sys.stderr)


if __name__ == "__main__":
    sys.exit(run_script(main))
