"""``jaxnm fit``: fit configuration files, the built-in default problem, and the outputs.

A fit file (JSON, paths relative to it)::

    {
      "scene": "scene.json",                  // mesh, material, albedo, map sampling options
      "views": [{"camera": {"eye": [0,-2.4,1.7], "target": [0,0,0], "up": [0,0,1]},
                 "width": 512, "height": 512}],   // optional: default = the scene's camera
      "targets": [{"view": 0, "image": "t0.png", "color_space": "srgb",
                   "lights": [{"type": "directional", "direction": [0.3,-0.2,1]}],
                   "mask": "mask0.png"}],      // mask optional (white = use)
      "map": {"size": [256, 256], "encoding": "unsigned", "green": "up", "bits": 8},
      "ground_truth": {"path": "gt.png", "encoding": "unsigned", "green": "up"},   // optional
      "held_out": [{"view": 0, "image": "h0.png", "color_space": "srgb",
                    "lights": [...]}],          // optional: scored, never fitted
      "solver": {"method": "lm", "max_steps": 30, "lsmr_steps": 10, "smoothness": 0,
                 "coarse_to_fine": 0, "seed": 0, "time_limit": null}
    }

Target images: PNG (8 or 16 bit), EXR, or ``.npy``/``.npz`` float arrays;
``color_space`` says whether their values are ``"srgb"``-encoded (default for
PNG/JPEG) or ``"linear"`` (default for EXR/npy/npz).
"""

from __future__ import annotations

import dataclasses
import json
import time
from pathlib import Path

import jax.numpy as jnp
import numpy as np

from . import fit as F
from . import io
from . import textures as _tex
from .scene import _camera, _lights, load_scene

__all__ = ["load_fit", "run", "cli_main", "write_outputs"]


def _image(path: Path, color_space: str | None, source: str) -> np.ndarray:
    img, bits = io.load_image_float(path)
    if img.ndim == 3 and img.shape[2] == 4:
        img = img[..., :3]
    if img.ndim != 3 or img.shape[2] != 3:
        raise ValueError(f"{path}: a target must be an RGB image, got shape {img.shape}")
    if color_space is None:
        color_space = "srgb" if bits in (8, 16) else "linear"
    if color_space not in ("srgb", "linear"):
        raise ValueError(f"{source}: color_space must be 'srgb' or 'linear', got {color_space!r}")
    if not np.all(np.isfinite(img)):
        raise ValueError(f"{path}: the target has NaN or infinite values")
    return np.asarray(_tex.srgb_to_linear(img)) if color_space == "srgb" else img


def load_fit(path) -> tuple[F.FitProblem, F.FitOptions, dict]:
    """Read a fit file; returns ``(problem, options, extras)`` where extras holds the
    ground truth, the held-out targets and the output map encoding."""
    path = Path(path)
    data = io.load_json(path)
    src = str(path)
    base = path.parent
    if not isinstance(data, dict):
        raise ValueError(f"{src}: a fit file must be a JSON object")
    known = {"scene", "views", "targets", "map", "ground_truth", "held_out", "solver"}
    if set(data) - known:
        raise ValueError(f"{src}: unknown keys {sorted(set(data) - known)}; known: {sorted(known)}")
    if "scene" not in data:
        raise ValueError(f"{src}: missing 'scene' (a scene JSON file with the mesh and material)")
    scene = load_scene(base / data["scene"])
    views = []
    for i, v in enumerate(data.get("views", [])):
        w, h = int(v.get("width", scene.width)), int(v.get("height", scene.height))
        views.append((_camera(v.get("camera"), w / h, f"{src}: views[{i}]"), w, h))
    if not views:
        views = [(scene.camera, scene.width, scene.height)]

    def target(t, i, key):
        name = f"{key}[{i}]"
        if not isinstance(t, dict) or "image" not in t or "lights" not in t:
            raise ValueError(f"{src}: {name} needs 'image' and 'lights'")
        vi = int(t.get("view", 0))
        if not 0 <= vi < len(views):
            raise ValueError(f"{src}: {name}.view = {vi} but there are {len(views)} views")
        cam, w, h = views[vi]
        img = _image(base / t["image"], t.get("color_space"), src)
        mask = None
        if "mask" in t:
            m, _ = io.load_texture(base / t["mask"])
            mask = m[..., 0] > 0.5
        return F.FitTarget(cam, w, h, _lights(t["lights"], f"{src}: {name}"), img, mask,
                           name=f"{name} ({t['image']})")

    if not isinstance(data.get("targets"), list) or not data["targets"]:
        raise ValueError(f"{src}: 'targets' must be a non-empty list")
    targets = tuple(target(t, i, "targets") for i, t in enumerate(data["targets"]))
    held = tuple(target(t, i, "held_out") for i, t in enumerate(data.get("held_out", [])))
    mp = dict(data.get("map", {}))
    size = mp.pop("size", [256, 256])
    if isinstance(size, int):
        size = [size, size]
    enc = {"encoding": mp.pop("encoding", "unsigned"), "green": mp.pop("green", "up"),
           "bits": int(mp.pop("bits", 8))}
    if mp:
        raise ValueError(f"{src}: unknown map keys {sorted(mp)}")
    nm_opts = dataclasses.replace(scene.normal_map_options, encoding="signed", channels=3)
    problem = F.FitProblem(
        mesh=scene.mesh, material=scene.material, targets=targets,
        map_size=(int(size[0]), int(size[1])), albedo=np.asarray(scene.albedo),
        shading=scene.shading, frame=scene.frame, derivatives=scene.derivatives,
        double_sided=scene.double_sided, sampling=nm_opts, source=src)
    sv = dict(data.get("solver", {}))
    method = sv.pop("method", "lm")
    time_limit = sv.pop("time_limit", None)
    try:
        options = F.FitOptions(solver=method, **sv)
    except TypeError as e:
        raise ValueError(f"{src}: solver: {e}") from None
    gt = None
    if "ground_truth" in data:
        g = data["ground_truth"]
        g = {"path": g} if isinstance(g, str) else dict(g)
        raw, bits = io.load_texture(base / g["path"], channels=3)
        gt = np.asarray(_tex.decode_normal_map(
            jnp.asarray(raw), encoding=g.get("encoding", "unsigned"),
            green=g.get("green", "up"), bits=bits if bits in (8, 16) else 8))
        gt = gt / np.linalg.norm(gt, axis=-1, keepdims=True)
        if gt.shape[:2] != problem.map_size:
            raise ValueError(f"{src}: the ground truth is {gt.shape[:2]} but the map size is "
                             f"{problem.map_size}")
    return problem, options, {"ground_truth": gt, "held_out": held, "encoding": enc,
                              "time_limit": time_limit}


def default_fit(quick: bool = False):
    """The built-in problem (see `jaxnm.fit.default_problem`) with a held-out light."""
    size, msize = (128, 64) if quick else (512, 256)
    problem, gt, scene = F.default_problem(render_size=size, map_size=msize, n_lights=6, views=2)
    # held out: a direction not among the fitted ones (elevation ~55 deg, azimuth ~38 deg,
    # between fitted lights 0 and 1 in the view's frame)
    d = F.view_relative(problem.targets[0].camera, [0.45, 0.35, 0.82])
    from .render import render

    sc = scene.replace(camera=problem.targets[0].camera, lights=F.directional_light(d))
    img = render(sc, outputs=("color",))["color"]
    held = (F.FitTarget(problem.targets[0].camera, size, size, F.directional_light(d), img,
                        name="held-out light"),)
    options = F.FitOptions(solver="lm", max_steps=30, lsmr_steps=10)
    return problem, options, {"ground_truth": gt, "held_out": held,
                              "encoding": {"encoding": "unsigned", "green": "up", "bits": 8},
                              "time_limit": None}


def run(problem, options, extras, outdir, *, progress=True) -> dict:
    """Fit, then write every output into ``outdir``; returns the summary dict."""
    outdir = Path(outdir)
    outdir.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    prep = F.prepare(problem)
    t_prep = time.perf_counter() - t0
    ident = F.check_identifiability(prep)
    gt = extras.get("ground_truth")
    result = F.fit_normal_map(problem, options, ground_truth=gt, progress=progress,
                              prepared=prep, time_limit=extras.get("time_limit"))
    summary = {"stopped": result.stopped, "steps": len(result.history),
               "fit_seconds": round(result.seconds, 2), "prepare_seconds": round(t_prep, 2),
               "final_loss": result.best_loss, "identifiability": ident,
               "solver": dataclasses.asdict(options), "map_size": list(problem.map_size)}
    write_outputs(outdir, problem, prep, result, extras, summary)
    return summary


def write_outputs(outdir: Path, problem, prep, result, extras, summary) -> None:
    """The fitted map (PNG + npz), re-renders beside the targets, loss curve, error report."""
    enc = extras["encoding"]
    n = result.normals
    stored = np.asarray(_tex.encode_normal_map(jnp.asarray(n), encoding=enc["encoding"],
                                               green=enc["green"], bits=enc["bits"]))
    io.save_png(outdir / "normal_map.png", stored, bits=enc["bits"])
    np.savez_compressed(outdir / "normal_map.npz", normals=n.astype(np.float32),
                        slopes=result.slopes.astype(np.float32))
    # re-renders beside the targets: target | fit | 4 x |difference|
    renders = F.render_with_map(prep, jnp.asarray(n))
    k = 0
    for v, imgs in enumerate(renders):
        imgs = np.asarray(imgs)
        targets = prep.target_images(v)
        for t in range(imgs.shape[0]):
            row = np.concatenate([targets[t], imgs[t], np.abs(imgs[t] - targets[t]) * 4], 1)
            io.save_png(outdir / f"render_{k:02d}.png",
                        np.asarray(_tex.linear_to_srgb(np.clip(row, 0, 1))))
            k += 1
    (outdir / "loss.json").write_text(json.dumps(result.history, indent=1) + "\n")
    _plot_loss(outdir / "loss.png", result.history)
    gt = extras.get("ground_truth")
    if gt is not None:
        seen = F.seen_texels(prep, problem.map_size)
        summary["error"] = F.error_report(n, gt, seen)
        err = F.angular_error(n, gt)
        img = np.clip(err / 10.0, 0, 1)  # 0..10 degrees -> black..white
        img = np.where(seen, img, 0.25)  # unseen texels in dark grey
        io.save_png(outdir / "error_map.png", img.astype(np.float32))
    held = extras.get("held_out") or ()
    if held:
        summary["held_out"] = _score_held_out(problem, held, n, gt)
    F.save_json(outdir / "report.json", summary)


def _score_held_out(problem, held, n, gt) -> list:
    out = []
    for t in held:
        hp = dataclasses.replace(problem, targets=(t,))
        prep = F.prepare(hp)
        fitted = np.asarray(F.render_with_map(prep, jnp.asarray(n))[0][0])
        m = prep.target_mask(0)
        rec = {"name": t.name, "psnr_db_vs_target": round(F.psnr(fitted, t.image, m), 2)}
        if gt is not None:
            truth = np.asarray(F.render_with_map(prep, jnp.asarray(gt))[0][0])
            rec["psnr_db_vs_ground_truth_render"] = round(F.psnr(fitted, truth, m), 2)
        out.append(rec)
    return out


def _plot_loss(path: Path, history: list) -> None:
    from matplotlib.figure import Figure  # no pyplot: leaves the caller's backend alone

    fig = Figure(figsize=(6, 3.5), dpi=100)
    ax = fig.add_subplot()
    steps = np.arange(len(history))  # iterations, across coarse-to-fine levels
    ax.semilogy(steps, [max(h["loss"], 1e-30) for h in history], label="loss")
    ax.set_xlabel("iteration")
    ax.set_ylabel("0.5 * sum of squared residuals")
    if history and "mean_angular_error_deg" in history[-1]:
        ax2 = ax.twinx()
        ax2.plot(steps, [h.get("mean_angular_error_deg", np.nan) for h in history], "C1",
                 label="mean angular error")
        ax2.set_ylabel("mean angular error (deg)", color="C1")
    ax.set_title("jaxnm fit")
    fig.tight_layout()
    fig.savefig(path)


def cli_main(args) -> int:
    if args.config:
        problem, options, extras = load_fit(args.config)
    else:
        problem, options, extras = default_fit(quick=getattr(args, "quick", False))
    overrides = {k: getattr(args, k) for k in ("solver", "max_steps", "smoothness", "seed",
                                                "lsmr_steps", "coarse_to_fine")
                 if getattr(args, k, None) is not None}
    if overrides:
        options = dataclasses.replace(options, **overrides)
    if getattr(args, "time_limit", None) is not None:
        extras = dict(extras, time_limit=args.time_limit)
    summary = run(problem, options, extras, args.output, progress=not args.no_progress)
    line = f"fit {summary['stopped']} after {summary['steps']} steps in " \
           f"{summary['fit_seconds']:.1f} s"
    if "error" in summary:
        e = summary["error"]
        line += (f"; angular error over {e['seen_texels']} seen texels: mean {e['mean_deg']:.3f}"
                 f", median {e['median_deg']:.3f}, p95 {e['p95_deg']:.3f} deg")
    for h in summary.get("held_out", []):
        line += f"; held-out PSNR {h['psnr_db_vs_target']:.1f} dB"
    print(line)
    print(f"outputs in {args.output}/ (normal_map.png, normal_map.npz, render_*.png, loss.png, "
          "loss.json, report.json" + (", error_map.png)" if "error" in summary else ")"))
    return 0
