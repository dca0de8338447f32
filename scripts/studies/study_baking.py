"""Baking study: a map must be decoded in the frame it was baked in. By how much is it off
otherwise?

    python -m scripts.studies.study_baking [--out baking_out] [--segments 12] [--map 128]
                                           [--size 128] [--fit-views 3] [--no-fit]

A high-poly surface (a torus displaced along its normal by a smooth bump pattern, whose
normal is known analytically in float64) is baked onto a low-poly torus (smooth normals)
into a tangent-space map, once per frame convention, two ways:

- **projection** (`jaxnm.bake.bake_normal_map`): per texel, the low-poly surface point with
  that uv, the high-poly normal there, expressed in the low-poly frame of the convention
  (``m = [T B N]^-1 n_high``: exactly what that frame decodes back to ``n_high``).
  Conventions: ``cotangent`` (Schüler's per-triangle gradient frame: what jaxnm's
  screen-space frame computes per triangle), ``vertex`` (MikkTSpace, what Blender,
  Substance, xNormal and glTF bake in) and ``vertex_area`` (plain per-vertex tangents).
  The high-poly surface is the low-poly's smooth parent displaced along its normal, so a
  baker's ray from a low-poly point along the smooth normal meets it at (nearly) the same
  surface parameters; the study uses that parametric correspondence exactly.
- **fit**: jaxnm's own fitter, from images of the high-poly mesh (``--fit-views`` views,
  six lights each) fitted on the low-poly mesh with the ``cotangent`` and the ``vertex``
  frame (``--no-fit`` skips it).

Then every bake is decoded by rendering the low-poly mesh with every frame method, and each
pixel's perturbed normal is compared with the high-poly normal at the pixel's uv. Writes
``baking.json``, ``baking.md`` (the matrix: bake x decode frame, mean / p95 degrees) and
``baking_matrix.png`` into ``--out``.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

import jaxnm
from jaxnm import frames as F
from jaxnm.bake import bake_normal_map
from jaxnm.camera import Camera, look_at, perspective
from jaxnm.fit import FitOptions, FitTarget, fit_normal_map, problem_from_scene
from jaxnm.procedural import default_light_directions, default_scene
from jaxnm.shading import DirectionalLight, Lights, stack_lights
from jaxnm.textures import NormalMapOptions
from scripts._cli import output, run_script

R, RT = 1.0, 0.4  # torus radii
AMP = 0.025  # displacement amplitude (world units)
DECODE_FRAMES = [f for f in F.FRAMES if f != "none"]
BAKE_FRAMES = ("cotangent", "vertex", "vertex_area")
EYES = ((0.0, -2.6, 1.9), (2.2, -1.2, 1.4), (-1.6, -1.9, -1.2))


def _unit(v):
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _angle(a, b):
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    return np.degrees(np.arctan2(np.linalg.norm(np.cross(a, b), axis=-1), np.sum(a * b, -1)))


# ---------------------------------------------------------------------- the high-poly surface


def _smooth(phi, th):
    ring = R + RT * np.cos(th)
    p = np.stack([ring * np.cos(phi), ring * np.sin(phi), RT * np.sin(th)], -1)
    n = np.stack([np.cos(th) * np.cos(phi), np.cos(th) * np.sin(phi), np.sin(th)], -1)
    return p, n


def _height(phi, th):
    return AMP * (np.sin(5 * phi) * np.sin(3 * th) + 0.5 * np.cos(9 * phi + 2 * th))


def high_point(phi, th):
    p, n = _smooth(phi, th)
    return p + _height(phi, th)[..., None] * n


def high_normal(u, v):
    """The displaced surface's unit normal at uv (float64, central differences)."""
    phi, th = 2 * np.pi * np.asarray(u, np.float64), 2 * np.pi * np.asarray(v, np.float64)
    h = 1e-6
    d_phi = (high_point(phi + h, th) - high_point(phi - h, th)) / (2 * h)
    d_th = (high_point(phi, th + h) - high_point(phi, th - h)) / (2 * h)
    return _unit(np.cross(d_phi, d_th))


def high_mesh(segments: int) -> jaxnm.Mesh:
    """The displaced torus as a fine mesh with its analytic normals (for the fitter's
    target images)."""
    m = jaxnm.procedural.torus(R, RT, 2 * segments, segments)
    uv = np.asarray(m.uv, np.float64)
    pos = high_point(2 * np.pi * uv[:, 0], 2 * np.pi * uv[:, 1])
    return jaxnm.Mesh(jnp.asarray(pos, jnp.float32), m.faces, m.uv,
                      jnp.asarray(high_normal(uv[:, 0], uv[:, 1]), jnp.float32))


# ---------------------------------------------------------------------- baking by projection


def bake_projection(mesh: jaxnm.Mesh, map_hw, convention: str) -> np.ndarray:
    """The tangent-space map (h, w, 3 signed unit vectors) of the high-poly normals in the
    low-poly ``convention`` frame (`jaxnm.bake.bake_normal_map`)."""
    return bake_normal_map(mesh, high_normal, map_hw, frame=convention)


# ---------------------------------------------------------------------- baking by fitting


def _camera(eye) -> Camera:
    return Camera.from_matrices(look_at(eye, (0.0, 0.0, 0.0), (0, 0, 1)),
                                perspective(45.0, 1.0, 0.1, 50.0))


def bake_fit(low: jaxnm.Mesh, map_hw, frame: str, size: int, views: int, steps: int):
    """Fit the low-poly map with ``frame`` to renders of the high-poly mesh."""
    base = default_scene(width=size, height=size)
    high = base.replace(mesh=high_mesh(128), normal_map=None)
    targets = []
    for vi, eye in enumerate(EYES[:views]):
        cam = _camera(eye)
        for li, d in enumerate(default_light_directions(6)):
            inv = np.linalg.inv(np.asarray(cam.view, np.float64))[:3, :3]
            lights = Lights(directional=stack_lights([DirectionalLight(
                jnp.asarray(inv @ d, jnp.float32), jnp.ones(3), jnp.asarray(1.0))]))
            img = np.asarray(jaxnm.render(high.replace(camera=cam, lights=lights))["color"])
            targets.append(FitTarget(cam, size, size, lights, img, name=f"v{vi}l{li}"))
    scene = base.replace(mesh=low, frame=frame, normal_map=None,
                         normal_map_options=NormalMapOptions(encoding="signed",
                                                             filter="bilinear"))
    problem = problem_from_scene(scene, targets, map_hw, source=f"<bake fit {frame}>")
    res = fit_normal_map(problem, FitOptions(max_steps=steps), progress=False)
    return np.asarray(res.normals, np.float32)


# ---------------------------------------------------------------------- decoding


def decode_errors(low: jaxnm.Mesh, baked: np.ndarray, frame: str, size: int, views) -> dict:
    errs = []
    for eye in views:
        sc = default_scene(width=size, height=size).replace(
            mesh=low, camera=_camera(eye), normal_map=jnp.asarray(baked),
            normal_map_options=NormalMapOptions(encoding="signed", filter="bilinear"),
            frame=frame)
        out = jaxnm.render(sc, outputs=("perturbed_normal", "uv", "mask", "front_facing"))
        m = (np.asarray(out["mask"])[..., 0] > 0) & (np.asarray(out["front_facing"])[..., 0] > 0)
        uv = np.asarray(out["uv"], np.float64)[m]
        errs.append(_angle(np.asarray(out["perturbed_normal"])[m],
                           high_normal(uv[:, 0], uv[:, 1])))
    e = np.concatenate(errs)
    return {"mean": float(e.mean()), "p95": float(np.percentile(e, 95)), "pixels": int(e.size)}


def _table(rows) -> str:
    bakes = list(dict.fromkeys(r["bake"] for r in rows))
    head = "| baked by \\ decoded with | " + " | ".join(DECODE_FRAMES) + " |"
    lines = [head, "|---" * (len(DECODE_FRAMES) + 1) + "|"]
    for b in bakes:
        cells = []
        for f in DECODE_FRAMES:
            r = next(r for r in rows if r["bake"] == b and r["decode"] == f)
            cells.append(f"{r['mean']:.2f} / {r['p95']:.1f}")
        lines.append(f"| {b} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def _plot(rows, path: Path) -> None:
    try:
        from matplotlib.figure import Figure
    except ImportError:
        print("matplotlib missing: no plot (pip install '.[notebook]')")
        return
    bakes = list(dict.fromkeys(r["bake"] for r in rows))
    mat = np.array([[next(r["mean"] for r in rows if r["bake"] == b and r["decode"] == f)
                     for f in DECODE_FRAMES] for b in bakes])
    fig = Figure(figsize=(9, 0.6 * len(bakes) + 2), dpi=100)
    ax = fig.add_subplot()
    im = ax.imshow(np.log10(np.maximum(mat, 1e-3)), cmap="viridis")
    for i in range(mat.shape[0]):
        for j in range(mat.shape[1]):
            ax.text(j, i, f"{mat[i, j]:.2f}", ha="center", va="center", fontsize=7, color="w")
    ax.set_xticks(range(len(DECODE_FRAMES)), DECODE_FRAMES, rotation=30, fontsize=7)
    ax.set_yticks(range(len(bakes)), bakes, fontsize=7)
    ax.set(title="mean error (deg) of the decoded normal against the high-poly normal")
    fig.colorbar(im, ax=ax, label="log10 deg")
    fig.tight_layout()
    fig.savefig(path)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="baking_out")
    ap.add_argument("--segments", type=int, default=12, help="low-poly tube segments")
    ap.add_argument("--map", type=int, default=128, help="map width (height: half)")
    ap.add_argument("--size", type=int, default=128, help="render size for decoding/fitting")
    ap.add_argument("--fit-views", type=int, default=3)
    ap.add_argument("--fit-steps", type=int, default=40)
    ap.add_argument("--no-fit", action="store_true", help="projection bakes only")
    args = ap.parse_args(argv)
    output("--out", args.out, folder=True)  # before the work
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    low = jaxnm.procedural.torus(R, RT, 2 * args.segments, args.segments).with_tangents()
    hw = (args.map // 2, args.map)
    bakes = {f"projection, {c}": bake_projection(low, hw, c) for c in BAKE_FRAMES}
    if not args.no_fit:
        for frame in ("cotangent", "vertex"):
            bakes[f"jaxnm fit, {frame}"] = bake_fit(low, hw, frame, args.size, args.fit_views,
                                                    args.fit_steps)
            jax.clear_caches()
    rows = []
    for name, baked in bakes.items():
        for frame in DECODE_FRAMES:
            r = {"bake": name, "decode": frame,
                 **decode_errors(low, baked, frame, args.size, EYES[:args.fit_views])}
            rows.append(r)
            print(json.dumps(r), flush=True)
    meta = {"segments": args.segments, "map": list(hw), "size": args.size,
            "amplitude": AMP, "seconds": time.perf_counter() - t0,
            "jax": jax.__version__, "date": time.strftime("%Y-%m-%d")}
    (out / "baking.json").write_text(json.dumps({"meta": meta, "rows": rows}, indent=1) + "\n")
    (out / "baking.md").write_text(_table(rows))
    _plot(rows, out / "baking_matrix.png")
    print(_table(rows))
    print(json.dumps(meta))


if __name__ == "__main__":
    sys.exit(run_script(main))
