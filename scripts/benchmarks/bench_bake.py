"""Baking: jaxnm's `raycast_normal_map` against Blender's Cycles bake of the same pair, and
the time `bake_mesh_pair` takes to answer with a fitted map.

    python -m scripts.benchmarks.bench_bake [--size 1024] [--samples 4] [--repeats 3]
                                            [--parts raycast,blender,fit] [--fit-size 512]

The pair is `bake_pairs.torus_pair`: a displaced torus of ``--hi`` quads (two triangles each;
1000 x 500 = 1,000,000 triangles) over a plain one of ``--lo`` quads (64 x 40 = 5,120
triangles) with a mirrored uv layout. Both bake a tangent-space normal map of ``--size``
squared with ``--samples`` samples per texel, the same cage extrusion, no max ray distance
and a 16-texel margin, on this machine, one after the other in one run of this script:

- **jaxnm** in this process: the first call (Embree's scene and JAX's compilation of the
  frame included) and the median of ``--repeats`` more; the process's RSS before them (the
  pair's arrays, Python, JAX) and its peak during them (Linux's VmHWM, restarted before);
- **Blender** (``tests/blender_ref.py transfer`` in Blender's Python, ``JAXNM_BLENDER_PYTHON``
  or ``.venv-blender``): the ``bpy.ops.object.bake`` call itself, first and median of the
  same repeats in one Blender process, the whole process's wall time (start, scene set-up,
  every bake) and its peak RSS.

- **the fit** (``--parts fit``): `bake_mesh_pair` with ``method="both"`` (the rays, then the
  fit from them; ``--fit-method fit``: from flat) at ``--fit-size`` squared, its default
  views, lights and steps, no scoring (``eval_views=0``): the time to answer (from the meshes
  to the fitted map) of the first call (XLA's compilation included, as a first ``jaxnm
  bake`` without a compilation cache) and of a second one, the seconds per stage, and the
  process's peak RSS during them, restarted before (HIGH's renders and the fit's prepared
  views dominate it).

Prints JSON: the settings, the machine (with its load average before and after: run it on a
quiet machine), both sides' figures and the ratio of the medians.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np

from jaxnm.transfer import BakeWarning, raycast_normal_map
from scripts._cli import run_script
from scripts.benchmarks import bake_pairs
from scripts.studies.blender_bake_cases import blender_python

ROOT = Path(__file__).resolve().parents[2]


def _status_mib(field: str) -> float | None:
    """A memory figure of this process from Linux's /proc/self/status (VmRSS, VmHWM)."""
    try:
        with open("/proc/self/status") as f:
            kib = next(int(line.split()[1]) for line in f if line.startswith(field + ":"))
    except (OSError, StopIteration):
        return None
    return round(kib / 1024, 1)


def _reset_peak() -> bool:
    """Restart the peak-RSS count (VmHWM) from the current RSS (Linux; the benchmark's own
    process, so that the peak is the bakes', not the pair's construction)."""
    try:
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")
        return True
    except OSError:
        return False


def run_jaxnm(pair: dict, args) -> dict:
    low, high = bake_pairs.low_mesh(pair), bake_pairs.high_mesh(pair)
    times, result = [], None
    rss_before = _status_mib("VmRSS")
    reset = _reset_peak()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", BakeWarning)  # the mirrored halves share texels
        for _ in range(args.repeats + 1):
            t = time.perf_counter()
            result = raycast_normal_map(high, low, args.size, samples=args.samples,
                                        cage=args.cage, margin=16)
            times.append(time.perf_counter() - t)
    return dict(first_s=round(times[0], 3), median_s=round(statistics.median(times[1:]), 3),
                runs_s=[round(x, 3) for x in times[1:]],
                stages_s={k: round(v, 3) for k, v in result.timings.items()},
                texels_inside=result.texels_inside, texels_missed=result.texels_missed,
                rss_before_mib=rss_before,
                peak_rss_mib=_status_mib("VmHWM") if reset else None)


def run_fit(pair: dict, args) -> dict:
    """`bake_mesh_pair`'s time to answer and peak memory (see the module docstring)."""
    from jaxnm.transfer import PairBakeOptions, bake_mesh_pair

    low, high = bake_pairs.low_mesh(pair), bake_pairs.high_mesh(pair)
    options = PairBakeOptions(method=args.fit_method, size=args.fit_size, eval_views=0,
                              cage=args.cage)
    rss_before = _status_mib("VmRSS")
    reset = _reset_peak()
    calls = []
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", BakeWarning)
        for _ in range(2):
            t = time.perf_counter()
            bake = bake_mesh_pair(high, low, options)
            calls.append(dict(seconds=round(time.perf_counter() - t, 3),
                              stages_s={k: round(v, 3) for k, v in bake.timings.items()},
                              steps=sum(1 for h in bake.fit.history if h["step"] > 0),
                              stopped=bake.fit.stopped))
    return dict(method=args.fit_method, map_size=args.fit_size,
                render_size=options.views_render_size, views=options.views,
                lights=options.lights, targets=options.views * options.lights,
                fit_options=repr(options.fit), first=calls[0], second=calls[1],
                unseen_texels=bake.unseen_texels, chart_texels=int(bake.plan.chart.sum()),
                rss_before_mib=rss_before,
                peak_rss_mib=_status_mib("VmHWM") if reset else None)


def run_blender(pair: dict, args, blender: str) -> dict:
    with tempfile.TemporaryDirectory() as tmp:
        spec, out = Path(tmp) / "spec.npz", Path(tmp) / "out.npz"
        np.savez(spec, **pair, size=args.size, samples=args.samples,
                 margins=np.full(args.repeats + 1, 16), cage_extrusion=args.cage,
                 max_ray_distance=0.0)
        t = time.perf_counter()
        run = subprocess.run([blender, str(ROOT / "tests" / "blender_ref.py"), "transfer",
                              str(spec), str(out)], capture_output=True, text=True)
        wall = time.perf_counter() - t
        if run.returncode != 0:
            sys.exit(f"Blender failed: {run.stderr[-2000:]}")
        res = np.load(out)
        sec, peak = res["bake_seconds"], int(res["peak_rss_kib"])
    return dict(bake_first_s=round(float(sec[0]), 3),
                bake_median_s=round(float(np.median(sec[1:])), 3),
                bake_runs_s=[round(float(x), 3) for x in sec[1:]], process_s=round(wall, 3),
                process_bakes=int(sec.size),
                peak_rss_mib=round(peak / 1024, 1) if peak >= 0 else None)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=1024)
    ap.add_argument("--samples", type=int, default=4)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--hi", type=int, nargs=2, default=(1000, 500))
    ap.add_argument("--lo", type=int, nargs=2, default=(64, 40))
    ap.add_argument("--cage", type=float, default=0.08)
    ap.add_argument("--no-blender", action="store_true")
    ap.add_argument("--parts", default="raycast,blender,fit",
                    help="what to time: raycast, blender, fit (default: %(default)s)")
    ap.add_argument("--fit-size", type=int, default=512, dest="fit_size")
    ap.add_argument("--fit-method", choices=("both", "fit"), default="both", dest="fit_method")
    args = ap.parse_args(argv)
    parts = set(args.parts.split(","))
    pair = bake_pairs.torus_pair(tuple(args.lo), tuple(args.hi))
    out = dict(settings=dict(size=args.size, samples=args.samples, repeats=args.repeats,
                             hi_triangles=len(pair["hi_faces"]),
                             lo_triangles=len(pair["lo_faces"]), cage=args.cage, margin=16),
               machine=dict(cpus=os.cpu_count(), processor=platform.processor() or
                            platform.machine(), python=platform.python_version()))
    out["machine"]["load_average_before"] = [round(x, 2) for x in os.getloadavg()]
    if "raycast" in parts:
        out["jaxnm"] = run_jaxnm(pair, args)
    blender = None if args.no_blender or "blender" not in parts else blender_python()
    if blender is not None:
        out["blender"] = run_blender(pair, args, blender)
        if "jaxnm" in out:
            out["blender_bake_over_jaxnm"] = round(out["blender"]["bake_median_s"]
                                                   / out["jaxnm"]["median_s"], 2)
    if "fit" in parts:
        out["fit"] = run_fit(pair, args)
    out["machine"]["load_average_after"] = [round(x, 2) for x in os.getloadavg()]
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    sys.exit(run_script(main))
