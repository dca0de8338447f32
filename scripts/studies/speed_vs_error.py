"""Speed against error: every frame method, derivative mode, shader precision, resolution and
texture filter, timed and measured in one run.

    python -m scripts.studies.speed_vs_error [--out speed_vs_error_out] [--reps 5] [--quick]
                                             [--full]

The scene is the built-in one (its camera, lights, material and 256x256 rivet map) with an
analytic torus (R = 1, r = 0.4, 64 x 128 segments, 16k triangles), so every pixel has a
float64 truth. Per configuration:

- ``compile_s``: the first `jaxnm.render` call (tracing and XLA compilation) minus one
  steady call; ``forward_ms``: the median of steady calls (image and AOVs), both by
  `scripts.benchmarks.timing.time_call`;
- ``grad_compile_s``, ``grad_ms``: the same for forward + backward of an image loss with
  respect to the normal-map texels (what a fit step runs, without the fit's reductions);
- ``normal_mean`` / ``normal_p95`` (degrees): the perturbed normal against the float64
  truth *of the method's own convention* (Schüler's gradient frame for the screen-space and
  per-triangle methods, MikkTSpace's orthonormal frame for ``vertex``/``vertex_area``; see
  ``docs/studies/frames.md``), built from the smooth torus's analytic frame and the map value the
  renderer sampled (decoded from the same filter at the rendered uv and uv derivatives, so
  only the frame and the arithmetic differ);
- ``image_rmse``: the RMS difference of the linear colour from the image shaded (by
  `jaxnm.shading.shade`, float32) with that truth normal, over covered pixels.

Precisions: float32, float16 (GLSL mediump), bfloat16, and float64 (the frame in double
precision from the float32 interpolants, with 64-bit JAX enabled for that configuration).
Configurations (`configurations`): around the base settings (cotangent, fine, float32,
256 px, trilinear), one axis at a time; ``--full`` runs the whole frame x derivative-mode x
precision grid. Writes
``speed_vs_error.json``, ``.csv``, a Markdown table and ``pareto.png`` into ``--out``.
Machines are noisy: compare the ratios within one run.
"""

from __future__ import annotations

import argparse
import csv
import json
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

import jaxnm
from jaxnm.frames import FRAMES
from jaxnm.interpolate import DERIVATIVE_MODES
from jaxnm.procedural import default_scene
from jaxnm.shading import shade
from jaxnm.textures import NormalMapOptions, decode_normal_map, sample
from scripts._cli import output, run_script
from scripts.benchmarks import timing
from scripts.studies.study_frames import GRADIENT_METHODS, Torus, angle, truth_frames

METHODS = [f for f in FRAMES if f != "none"]
BASE = dict(frame="cotangent", derivatives="fine", precision="float32", size=256,
            filter="trilinear")


def configurations(quick: bool = False, full: bool = False) -> list[dict]:
    """The default set: every frame with fine and gbuffer derivatives and cotangent with all
    four modes (fine, coarse and analytic build the same frame inside a triangle, so the
    full grid repeats itself: ``--full`` runs it anyway); cotangent, exact, vertex and
    nonperspective at float16, bfloat16 and float64; cotangent and vertex at 512 and 1024 px;
    cotangent with nearest and bilinear filtering."""
    methods = ("cotangent", "vertex", "nonperspective") if quick else METHODS
    out = []
    for frame in methods:
        modes = DERIVATIVE_MODES if full or frame == "cotangent" else ("fine", "gbuffer")
        for mode in (("fine", "gbuffer") if quick else modes):
            out.append({**BASE, "frame": frame, "derivatives": mode})
    for precision in ("float16", "bfloat16", "float64"):
        for frame in (methods if full or quick else
                      ("cotangent", "exact", "vertex", "nonperspective")):
            out.append({**BASE, "frame": frame, "precision": precision})
    for size in ((512,) if quick else (512, 1024)):
        for frame in ("cotangent", "vertex"):
            out.append({**BASE, "frame": frame, "size": size})
    for filt in ("nearest", "bilinear"):
        out.append({**BASE, "filter": filt})
    return out


def run_one(cfg: dict, surf: Torus, reps: int, *, grad: bool = True) -> dict:
    """Time and measure one configuration (``float64`` runs with 64-bit JAX enabled);
    ``grad=False`` leaves out the forward + backward timing (``grad_compile_s`` and
    ``grad_ms`` None)."""
    if cfg["precision"] == "float64":
        with jax.enable_x64(True):
            return _run_one(cfg, surf, reps, grad)
    return _run_one(cfg, surf, reps, grad)


def _run_one(cfg: dict, surf: Torus, reps: int, with_grad: bool) -> dict:
    base = default_scene(width=cfg["size"], height=cfg["size"])
    mesh = jaxnm.Mesh(jnp.asarray(surf.pos, jnp.float32), jnp.asarray(surf.faces, jnp.int32),
                      jnp.asarray(surf.uv, jnp.float32), jnp.asarray(surf.nrm, jnp.float32))
    if cfg["frame"] == "vertex":
        mesh = mesh.with_tangents()
    opts = NormalMapOptions(filter=cfg["filter"], wrap="repeat")
    scene = base.replace(mesh=mesh, normal_map_options=opts, frame=cfg["frame"],
                         derivatives=cfg["derivatives"], precision=cfg["precision"])
    outputs = ("color", "perturbed_normal", "position", "uv", "duvdx", "duvdy", "mask",
               "front_facing")

    def forward():
        return jaxnm.render(scene, outputs=outputs)

    fwd = timing.time_call(forward, repeats=reps)
    out = forward()  # the outputs measured below
    weights = jnp.linspace(0.5, 1.5, 3)

    def loss(texels):
        color = jaxnm.render(scene.replace(normal_map=texels))["color"]
        return jnp.sum(color * weights[None, None])

    texels = jnp.asarray(scene.normal_map)
    g = None
    if with_grad:
        grad = jax.jit(jax.grad(loss))
        g = timing.time_call(lambda: grad(texels), repeats=max(2, reps // 2))

    m = (np.asarray(out["mask"])[..., 0] > 0) & (np.asarray(out["front_facing"])[..., 0] > 0)
    p = np.asarray(out["position"], np.float64)[m]
    dp_du, dp_dv, n = surf.frame_at(p)
    (tg, bg), (tu, bu), (to, bo) = truth_frames(dp_du, dp_dv, n)
    t_true, b_true = (tg, bg) if cfg["frame"] in GRADIENT_METHODS else (to, bo)
    if cfg["frame"] == "cotangent_unnormalized":  # the true, unscaled gradients
        t_true, b_true = tu, bu
    raw = sample(texels, out["uv"], out["duvdx"], out["duvdy"], filter=cfg["filter"],
                 wrap="repeat")
    mv = np.asarray(decode_normal_map(raw), np.float64)[m]
    truth = t_true * mv[:, :1] + b_true * mv[:, 1:2] + n * mv[:, 2:3]
    truth /= np.linalg.norm(truth, axis=-1, keepdims=True)
    err = angle(np.asarray(out["perturbed_normal"], np.float64)[m], truth)
    c_true = shade(scene.shading, jnp.asarray(truth, jnp.float32),
                   jnp.asarray(p, jnp.float32), jnp.asarray(scene.camera.eye, jnp.float32),
                   scene.lights, scene.material,
                   albedo=jnp.broadcast_to(jnp.asarray(scene.albedo, jnp.float32), p.shape))
    diff = np.asarray(out["color"], np.float64)[m] - np.asarray(c_true, np.float64)
    return {**cfg, "pixels": int(m.sum()), "compile_s": fwd.compile_s,
            "forward_ms": fwd.median_ms,
            "grad_compile_s": None if g is None else g.compile_s,
            "grad_ms": None if g is None else g.median_ms,
            "normal_mean": float(err.mean()), "normal_p95": float(np.percentile(err, 95)),
            "normal_max": float(err.max()), "image_rmse": float(np.sqrt(np.mean(diff ** 2))),
            "finite": bool(np.isfinite(err).all())}


def _pareto(rows) -> set[int]:
    """Indices of the configurations no other one beats in both forward time and error."""
    keep = set()
    for i, r in enumerate(rows):
        if not any(o["forward_ms"] <= r["forward_ms"] and o["normal_mean"] < r["normal_mean"]
                   or o["forward_ms"] < r["forward_ms"] and o["normal_mean"] <= r["normal_mean"]
                   for o in rows if o["size"] == r["size"]):
            keep.add(i)
    return keep


def _label(r) -> str:
    parts = [r["frame"], r["derivatives"]]
    parts += [r["precision"]] if r["precision"] != "float32" else []
    parts += [f"{r['size']}px"] if r["size"] != BASE["size"] else []
    parts += [r["filter"]] if r["filter"] != BASE["filter"] else []
    return " ".join(parts)


def _table(rows, front) -> str:
    lines = ["| configuration | forward ms | fwd+bwd ms | compile s (fwd / grad) | normal "
             "error mean / p95 (deg) | image RMSE |", "|---|---|---|---|---|---|"]
    for i, r in sorted(enumerate(rows), key=lambda ir: (ir[1]["size"], ir[1]["normal_mean"])):
        star = " **(Pareto)**" if i in front else ""
        g, gc = (("-", "-") if r["grad_ms"] is None else
                 (f"{r['grad_ms']:.1f}", f"{r['grad_compile_s']:.1f}"))
        lines.append(f"| {_label(r)}{star} | {r['forward_ms']:.1f} | {g} | "
                     f"{r['compile_s']:.1f} / {gc} | "
                     f"{r['normal_mean']:.3g} / {r['normal_p95']:.3g} | "
                     f"{r['image_rmse']:.2e} |")
    return "\n".join(lines) + "\n"


def _plot(rows, front, path: Path) -> None:
    try:
        from matplotlib.figure import Figure
    except ImportError:
        print("matplotlib missing: no plot (pip install '.[notebook]')")
        return
    fig = Figure(figsize=(8, 5), dpi=110)
    ax = fig.add_subplot()
    colors = {"float32": "C0", "float16": "C1", "bfloat16": "C3", "float64": "C2"}
    markers = {"fine": "o", "coarse": "s", "analytic": "^", "gbuffer": "x"}
    for i, r in enumerate(rows):
        ax.scatter(r["forward_ms"], max(r["normal_mean"], 1e-6), c=colors[r["precision"]],
                   marker=markers[r["derivatives"]], s=20 + 10 * (r["size"] // 256))
    seen = set()  # one label per frame (its fastest configuration), and the Pareto front
    for i, r in sorted(enumerate(rows), key=lambda ir: ir[1]["forward_ms"]):
        if i in front or r["frame"] not in seen:
            seen.add(r["frame"])
            ax.annotate(_label(r), (r["forward_ms"], max(r["normal_mean"], 1e-6)), fontsize=6,
                        xytext=(4, 2), textcoords="offset points")
    from matplotlib.lines import Line2D

    handles = [Line2D([], [], ls="", marker="o", color=c, label=p) for p, c in colors.items()]
    handles += [Line2D([], [], ls="", marker=m, color="k", label=d)
                for d, m in markers.items()]
    ax.legend(handles=handles, fontsize=7, loc="center right")
    for size in sorted({r["size"] for r in rows}):
        pts = sorted((rows[i]["forward_ms"], rows[i]["normal_mean"]) for i in front
                     if rows[i]["size"] == size)
        if len(pts) > 1:
            ax.plot(*zip(*pts), "k:", lw=0.8)
    ax.set(xscale="log", yscale="log", xlabel="forward ms per frame (median)",
           ylabel="perturbed-normal error, mean deg (own convention)",
           title="speed against error (colour: precision; marker: derivatives; size: px)")
    fig.tight_layout()
    fig.savefig(path)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="speed_vs_error_out")
    ap.add_argument("--reps", type=int, default=5, help="steady-state calls per timing")
    ap.add_argument("--quick", action="store_true", help="a few configurations (smoke test)")
    ap.add_argument("--full", action="store_true",
                    help="the whole frame x derivative-mode x precision grid (about 3x longer)")
    args = ap.parse_args(argv)
    output("--out", args.out, folder=True)  # before the work
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    surf = Torus(64)
    t0 = time.perf_counter()
    rows = []
    for cfg in configurations(args.quick, args.full):
        rows.append(run_one(cfg, surf, args.reps))
        print(json.dumps(rows[-1]), flush=True)
        jax.clear_caches()  # each configuration compiles anew; keep memory flat
    front = _pareto(rows)
    for i, r in enumerate(rows):
        r["pareto"] = i in front
    meta = {"jax": jax.__version__, "backend": jax.default_backend(),
            "device": str(jax.devices()[0]), "date": time.strftime("%Y-%m-%d"),
            "seconds": time.perf_counter() - t0}
    (out / "speed_vs_error.json").write_text(json.dumps({"meta": meta, "rows": rows},
                                                        indent=1) + "\n")
    with open(out / "speed_vs_error.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    (out / "speed_vs_error.md").write_text(_table(rows, front))
    _plot(rows, front, out / "pareto.png")
    print(json.dumps(meta))


if __name__ == "__main__":
    sys.exit(run_script(main))
