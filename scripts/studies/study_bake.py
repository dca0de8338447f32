"""Fitting a map to a high-poly mesh's shading against casting rays, under views and lights
the fit never used.

    python -m scripts.studies.study_bake --bunny PATH [--out DIR] [--size 512]
                                         [--pairs suzanne,torus,bunny]

Each pair is baked by `jaxnm.transfer.bake_mesh_pair` twice in one process: ``method="fit"``
(the map fitted from flat) and ``method="both"`` (the ray-cast map, then the fit from it),
with the same options (`PairBakeOptions`' defaults: 12 planned views x 4 lights at the
map's size, 12 texel-space Levenberg-Marquardt steps, MikkTSpace frame), and every map is
scored under the same 4 held-out views x 2 lights (`jaxnm.transfer.evaluate`: PSNR of the
linear colour, FLIP, the angle between HIGH's and LOW's shading normals). Seconds are the
bake's own stages (the first bake in the process includes XLA's compilation; the second
reuses it). Then the maps of ``method="both"`` are scored again at the fit's own views,
and at those views turned by 10 and 25 degrees, under lights the fit did not use: how far
from its views a fit's gain carries. The pairs:

- **suzanne**: Blender's Suzanne onto the same head subdivided three times and displaced
  (`scripts.benchmarks.bake_pairs.suzanne_pair`: needs Blender's Python,
  ``JAXNM_BLENDER_PYTHON`` or ``.venv-blender``), rays from an extrusion of 0.1 with a max
  distance of 0.4, as ``tests/test_transfer_raycast.py`` compares with Cycles;
- **torus**: a displaced torus onto a plain one with mirrored uvs (`torus_pair`), the
  automatic cage;
- **bunny**: the Stanford Bunny (Stanford 3D Scanning Repository, Turk and Levoy 1994;
  ``data/stanford-bunny.obj`` of github.com/alecjacobson/common-3d-test-models, 69,451
  triangles, sha256 ``1eb35d1e...39b32205``), given by ``--bunny``: LOW is HIGH decimated
  to ``--bunny-triangles`` and unwrapped by xatlas (`jaxnm.transfer.decimate`, `unwrap`).

Prints a markdown table and JSON (written to ``DIR/study_bake.json`` with ``--out``), with
the machine and its load average before and after (the figures are only comparable on a
quiet machine).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
import warnings
from pathlib import Path

import numpy as np

from jaxnm import io
from jaxnm.transfer import (
    BakeWarning,
    PairBakeOptions,
    bake_mesh_pair,
    decimate,
    evaluate_maps,
    unwrap,
)
from jaxnm.transfer.pair import bake_material
from jaxnm.transfer.views import framing_camera, held_out_views
from scripts._cli import output, run_script
from scripts.benchmarks import bake_pairs
from scripts.studies.blender_bake_cases import blender_python

#: The fit's stages, whose seconds add up to a fit's time.
_FIT_STAGES = ("plan", "targets", "prepare", "fit")


def load_pair(name: str, args):
    """``(HIGH, LOW, extra options)`` of pair ``name``."""
    if name == "suzanne":
        blender = blender_python()
        if blender is None:
            raise SystemExit("suzanne needs Blender's Python: set JAXNM_BLENDER_PYTHON")
        pair = bake_pairs.suzanne_pair(blender)
        return (bake_pairs.high_mesh(pair), bake_pairs.low_mesh(pair),
                dict(cage=0.1, max_distance=0.4))
    if name == "torus":
        pair = bake_pairs.torus_pair()
        return bake_pairs.high_mesh(pair), bake_pairs.low_mesh(pair), {}
    if args.bunny is None:
        raise SystemExit("bunny needs --bunny PATH (data/stanford-bunny.obj of "
                         "github.com/alecjacobson/common-3d-test-models)")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # (the file has no normals: computed)
        high = io.load_mesh(args.bunny)
    t = time.perf_counter()
    low = unwrap(decimate(high, args.bunny_triangles), size=args.size)
    print(f"bunny: LOW decimated and unwrapped in {time.perf_counter() - t:.1f} s",
          flush=True)
    return high, low, {}


def _row(bake, method: str, name: str) -> dict:
    s = bake.evaluation.methods[name]
    t = bake.timings
    seconds = {"raycast": t.get("raycast", 0.0),
               "fit": sum(t.get(k, 0.0) for k in _FIT_STAGES),
               "both": t.get("raycast", 0.0) + sum(t.get(k, 0.0) for k in _FIT_STAGES),
               "none": 0.0}[method]
    return {"method": method, "psnr_db": round(s.psnr_db, 3), "flip": round(s.flip, 5),
            "angle_mean_deg": round(s.angle_mean_deg, 3),
            "angle_median_deg": round(s.angle_median_deg, 3), "seconds": round(seconds, 2)}


def _turned(d: np.ndarray, degrees: float) -> np.ndarray:
    """The unit direction ``d`` turned by ``degrees`` about an axis perpendicular to it."""
    axis = np.cross(d, np.eye(3)[int(np.argmin(np.abs(d)))])
    axis /= np.linalg.norm(axis)
    a = np.radians(degrees)
    return d * np.cos(a) + np.cross(axis, d) * np.sin(a)


def near_the_fit(bake, high, turns=(0.0, 10.0, 25.0)) -> dict:
    """Held-out PSNR, FLIP and normal angle of each map at the fit's own views (turned by
    ``turns`` degrees) under lights the fit did not use: how far from its views a fit
    carries."""
    plan, o = bake.plan, bake.options
    _, lights = held_out_views(plan.centre, plan.radius, plan.directions, len(plan.cameras),
                               o.eval_lights)
    out = {}
    for turn in turns:
        cams = [framing_camera(plan.centre, plan.radius, _turned(d, turn))
                for d in plan.directions]
        ev = evaluate_maps(high, bake.low, bake.maps, cams, lights, frame=o.frame,
                           size=o.views_render_size, map_size=o.map_size,
                           material=bake_material(), albedo=np.full(3, o.albedo, np.float32),
                           shading=o.shading)
        out[f"{turn:g} deg"] = {k: [round(v.psnr_db, 3), round(v.flip, 5),
                                    round(v.angle_mean_deg, 3)]
                                for k, v in ev.methods.items()}
    return out


def study_pair(name: str, args) -> dict:
    high, low, extra = load_pair(name, args)
    runs = {}
    for method in ("fit", "both"):
        options = PairBakeOptions(method=method, size=args.size, **extra)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", BakeWarning)  # e.g. the torus' mirrored uvs
            runs[method] = bake_mesh_pair(high, low, options)
        print(f"{name} {method}: {runs[method].seconds:.1f} s {runs[method].timings}",
              flush=True)
    flat, both = runs["fit"], runs["both"]
    rows = [_row(both, "none", "none"), _row(both, "raycast", "raycast"),
            _row(flat, "fit", "fit"), _row(both, "both", "fit")]
    out = {"pair": name, "high_triangles": int(high.num_faces),
           "low_triangles": int(low.num_faces), "map_size": args.size, "rows": rows,
           "unseen_texels": flat.unseen_texels, "chart_texels": int(flat.plan.chart.sum()),
           "stages_seconds": {m: r.timings for m, r in runs.items()},
           "fit_steps": {m: sum(1 for h in r.fit.history if h["step"] > 0)
                         for m, r in runs.items()},
           "fit_stopped": {m: r.fit.stopped for m, r in runs.items()},
           "raycast": {"cage": both.raycast.cage, "cage_source": both.raycast.cage_source,
                       "texels_missed": both.raycast.texels_missed,
                       "texels_inside": both.raycast.texels_inside},
           "held_out_pixels": both.evaluation.pixels,
           "held_out_texel_error_deg": {
               k: float(np.nanmean(v.texel_error_deg))
               for k, v in both.evaluation.methods.items()}}
    out["held_out_texel_error_deg"]["fit (from flat)"] = float(
        np.nanmean(flat.evaluation.methods["fit"].texel_error_deg))
    out["near_the_fit_views"] = {
        "what": "[PSNR dB, FLIP, normal angle deg] at the fit's own views turned by this much, "
                "under lights the fit did not use; 'fit' is the fit from the ray cast",
        **near_the_fit(both, high)}
    return out


def table(results: list[dict]) -> str:
    lines = ["| pair | method | held-out PSNR (dB) | FLIP | normal angle mean (deg) | seconds |",
             "|---|---|---|---|---|---|"]
    names = {"none": "no map", "raycast": "ray cast", "fit": "fit (from flat)",
             "both": "fit from the ray cast"}
    for r in results:
        for row in r["rows"]:
            lines.append(f"| {r['pair']} | {names[row['method']]} | {row['psnr_db']:.2f} | "
                         f"{row['flip']:.4f} | {row['angle_mean_deg']:.2f} | "
                         f"{row['seconds']:.1f} |")
    return "\n".join(lines)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default=None, help="also write study_bake.json here")
    ap.add_argument("--size", type=int, default=512, help="map size (default: %(default)s)")
    ap.add_argument("--pairs", default="suzanne,torus,bunny")
    ap.add_argument("--bunny", default=None, help="the Stanford Bunny's OBJ")
    ap.add_argument("--bunny-triangles", type=int, default=3000, dest="bunny_triangles")
    args = ap.parse_args(argv)
    output("--out", args.out, folder=True)  # before the work
    machine = {"cpus": os.cpu_count(), "processor": platform.processor() or platform.machine(),
               "python": platform.python_version(),
               "load_average_before": [round(x, 2) for x in os.getloadavg()]}
    results = [study_pair(name, args) for name in args.pairs.split(",")]
    machine["load_average_after"] = [round(x, 2) for x in os.getloadavg()]
    report = {"settings": {"size": args.size, "options": repr(PairBakeOptions()),
                           "bunny_triangles": args.bunny_triangles},
              "machine": machine, "pairs": results}
    print(table(results))
    print(json.dumps(report, indent=1, default=float))
    if args.out:
        path = Path(args.out)
        path.mkdir(parents=True, exist_ok=True)
        (path / "study_bake.json").write_text(json.dumps(report, indent=1, default=float)
                                              + "\n")
        (path / "study_bake.md").write_text(table(results) + "\n")


if __name__ == "__main__":
    sys.exit(run_script(main))
