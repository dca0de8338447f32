"""``jaxnm bake HIGH [LOW] -o OUT``: a high-poly mesh's detail baked into a low-poly mesh's
normal map by casting rays, by fitting the map to the high-poly mesh's shading, or both
(`jaxnm.transfer.bake_mesh_pair`), scored under held-out views and lights.

LOW is the mesh to bake onto; with ``--decimate N`` it is made from HIGH instead
(``fast-simplification``, N triangles) and given uvs by xatlas, and must then not be given:
``jaxnm bake sculpt.obj --decimate 2000`` turns a sculpt into a low-poly mesh and its map.
``--unwrap`` gives a LOW that was read new uvs the same way. Writes (each file atomically,
the maps first):

- ``OUT/raycast/`` and ``OUT/fit/``, per method run: ``normal_map.png`` (unsigned, green
  up, 8 or 16 bits), ``normal_map.npz`` (``normals``: unit tangent-space vectors, row 0 on
  top, as ``jaxnm fit`` writes them, with masks), ``error_map.png`` (the held-out angle per
  texel), ``normal_map.dds`` with ``--store bc5``; ray casting also ``missed.png`` where rays
  missed, the fit ``coverage.png`` (views per texel); ``low.glb``, LOW with the map as its
  normal texture for glTF viewers, where the map is for MikkTSpace (``--frame vertex``, the
  default, with tangents computed, not read from LOW);
- ``OUT/low.obj`` with ``--decimate`` or ``--unwrap``: the mesh the maps are for;
- ``OUT/report.json`` and ``OUT/figure.png`` (the held-out comparison).
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import sys
import time
from pathlib import Path

from ._flags import as_flags, output_path
from ._interrupt import CtrlC

__all__ = ["add_parser", "run", "STORES"]

#: ``--store``'s choices: an 8- or 16-bit PNG, or also a BC5 DDS.
STORES = ("png8", "png16", "bc5")


def add_parser(sub) -> None:
    """Add ``jaxnm bake`` and its options to the subcommands ``sub``."""
    from ._render import frame_name

    p = sub.add_parser(
        "bake", help="bake a high-poly mesh's detail into a low-poly mesh's normal map",
        description="Bake HIGH's detail into a tangent-space normal map on LOW's uv layout, by "
        "casting rays, by fitting the map to HIGH's shading, or both, and score the maps under "
        "views and lights the fit never saw.")
    p.add_argument("high", metavar="HIGH", help="the high-poly mesh (OBJ, PLY, glTF, STL, OFF)")
    p.add_argument("low", metavar="LOW", nargs="?",
                   help="the low-poly mesh with uvs (leave out with --decimate)")
    p.add_argument("-o", "--output", default="bake_out", help="output folder (default: "
                   "%(default)s)")
    p.add_argument("--method", choices=("raycast", "fit", "both"), default="both",
                   help="cast rays, fit the map to HIGH's shading from a flat start, or fit "
                   "from the ray-cast map (default: %(default)s)")
    p.add_argument("--size", type=_map_size, default=512, metavar="N|WxH",
                   help="the map's side, or its width and height, in texels (default: "
                   "%(default)s)")
    p.add_argument("--frame", type=frame_name, default="vertex", metavar="FRAME",
                   help="the tangent frame the map is for (default: vertex, i.e. MikkTSpace); "
                   "ray casting bakes for vertex or cotangent, --method fit for any")
    cage = p.add_mutually_exclusive_group()
    cage.add_argument("--cage", type=float, metavar="DIST",
                      help="rays start DIST along LOW's normals (default: chosen so that they "
                      "start outside HIGH)")
    cage.add_argument("--cage-mesh", dest="cage_mesh", metavar="FILE",
                      help="rays start on this mesh (LOW's triangles, moved) towards LOW")
    p.add_argument("--max-distance", dest="max_distance", type=float,
                   metavar="D", help="rays longer than D miss (default: 0, no limit)")
    p.add_argument("--margin", type=int, metavar="PX",
                   help="texels filled around the uv islands (default: 16)")
    p.add_argument("--samples", type=int, metavar="K",
                   help="ray-cast samples per texel (default: 1)")
    p.add_argument("--views", type=int, metavar="K",
                   help="views the fit plans (default: 12)")
    p.add_argument("--lights", type=int, metavar="L",
                   help="directional lights per view, at least 3 (default: 4)")
    p.add_argument("--render-size", dest="render_size", type=int, metavar="N",
                   help="the side of each view's image (default: the map's)")
    p.add_argument("--max-steps", dest="max_steps", type=int, metavar="N",
                   help="the fit's steps at most (default: 12)")
    p.add_argument("--eval-views", dest="eval_views", type=int, metavar="E",
                   help="held-out views that score the maps, 2 lights each (default: 4; 0: "
                   "no scores)")
    p.add_argument("--store", choices=STORES, default="png8",
                   help="how the maps are stored: 8- or 16-bit PNG, or also a BC5 DDS (the "
                   "storage extra; the map's side a multiple of 4) (default: %(default)s)")
    p.add_argument("--unwrap", action="store_true",
                   help="give LOW new uvs with xatlas (replacing any it has)")
    p.add_argument("--decimate", type=int, metavar="N",
                   help="make LOW from HIGH with N triangles, unwrapped with xatlas (then give "
                        "no LOW)")
    p.add_argument("--no-progress", action="store_true", dest="no_progress",
                   help="a line per fit step on stderr instead of a progress bar")


def _say(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


#: The options ``jaxnm bake`` passes on to `jaxnm.transfer.PairBakeOptions` where given
#: (their defaults are the dataclass's); each is set by its flag (``max_distance``:
#: ``--max-distance``).
_OPTIONS = ("method", "size", "frame", "cage", "max_distance", "samples", "margin", "views",
            "lights", "render_size", "eval_views")


def _map_size(text: str) -> int | tuple[int, int]:
    """``--size``: ``N`` (a square map) or ``WxH``, each side at least 4; a
    ``(height, width)`` pair for `PairBakeOptions.size`."""
    try:
        sides = [int(part) for part in text.lower().split("x")]
    except ValueError:
        sides = []
    if len(sides) not in (1, 2) or min(sides) < 4:
        raise argparse.ArgumentTypeError(f"give the map's side N or its width and height WxH, "
                                         f"each an integer >= 4, got {text!r}")
    return sides[0] if len(sides) == 1 else (sides[1], sides[0])


def _size_words(size: int | tuple[int, int]) -> str:
    """``--size`` as it was given: ``N`` or ``WxH``."""
    return str(size) if isinstance(size, int) else f"{size[1]}x{size[0]}"


def _check_shape(args) -> None:
    """One-line errors for the arguments' shape (which meshes, options the method uses) and
    plain ranges."""
    from ..transfer import RENDER_SIZES

    if args.low is not None and args.decimate is not None:
        raise ValueError("give LOW or --decimate N (LOW made from HIGH), not both")
    if args.low is None and args.decimate is None:
        raise ValueError("no LOW: give the low-poly mesh, or --decimate N to make one from "
                         "HIGH")
    if args.cage_mesh is not None and args.decimate is not None:
        raise ValueError("--cage-mesh: a cage has LOW's triangles, and --decimate makes new "
                         "ones; give LOW and its cage, or --cage DIST")
    for flag, v in (("--cage", args.cage), ("--max-distance", args.max_distance)):
        if v is not None and not (v >= 0 and v < float("inf")):
            raise ValueError(f"{flag} must be a finite distance >= 0, got {v}")
    if args.max_steps is not None and args.max_steps < 1:
        raise ValueError(f"--max-steps must be at least 1, got {args.max_steps}")
    sides = (args.size,) * 2 if isinstance(args.size, int) else args.size
    if args.store == "bc5" and any(side % 4 for side in sides):
        raise ValueError(f"--store bc5: a BC5 map's sides must be multiples of 4, got "
                         f"--size {_size_words(args.size)}")
    if sides[0] != sides[1] and (args.unwrap or args.decimate is not None):
        raise ValueError(f"--size {_size_words(args.size)}: xatlas packs a square atlas, so "
                         f"{'--unwrap' if args.unwrap else '--decimate'} takes one side")
    leaves_out = {"fit": ("ray casting", "casts no rays", (
                      ("--cage", args.cage), ("--cage-mesh", args.cage_mesh),
                      ("--max-distance", args.max_distance), ("--samples", args.samples))),
                  "raycast": ("the fit", "fits nothing", (
                      ("--views", args.views), ("--lights", args.lights),
                      ("--max-steps", args.max_steps)))}
    if args.method in leaves_out:
        what, why, flags = leaves_out[args.method]
        given = [flag for flag, v in flags if v is not None]
        if given:
            raise ValueError(f"{', '.join(given)}: {'options' if len(given) > 1 else 'an option'}"
                             f" of {what}, and --method {args.method} {why}")
    lo, hi = RENDER_SIZES
    if args.render_size is not None and not lo <= args.render_size <= hi:
        raise ValueError(f"--render-size must be {lo} to {hi} pixels, got {args.render_size}")
    if args.method != "raycast" and args.lights is not None and args.lights < 3:
        raise ValueError(f"--lights: a fit needs at least 3 lights per view (three "
                         f"non-coplanar directions determine a normal), got {args.lights}")


def _check_extra(args) -> None:
    """An ImportError naming the ``bake`` extra's packages that this bake needs and this
    environment lacks: before any mesh is read, not where each is first used."""
    import importlib.util

    needs = [("embreex", "embreex", args.method != "fit"),
             ("xatlas", "xatlas", args.unwrap or args.decimate is not None),
             ("fast_simplification", "fast-simplification", args.decimate is not None),
             ("flip_evaluator", "flip-evaluator", args.eval_views != 0)]
    missing = [package for module, package, needed in needs
               if needed and importlib.util.find_spec(module) is None]
    if missing:
        names = (", ".join(missing[:-1]) + " and " if len(missing) > 1 else "") + missing[-1]
        raise ImportError(f"this bake needs {names}, from the bake extra: "
                          'pip install -e ".[bake]"')


def _check_inputs(args) -> None:
    """A FileNotFoundError naming the first of HIGH, LOW and the cage mesh that is not a
    file: before any is read, so that a wrong name is not found after minutes of work."""
    for flag, path in (("", args.high), ("", args.low), ("--cage-mesh ", args.cage_mesh)):
        if path is not None and not Path(path).is_file():
            why = "a folder, not a mesh file" if Path(path).is_dir() else "no such file"
            raise FileNotFoundError(f"{flag}{path}: {why}")


def _options(args):
    """The `PairBakeOptions` of ``args``, or a one-line ValueError naming the option."""
    from ..transfer import PairBakeOptions

    _check_shape(args)
    given = {k: getattr(args, k) for k in _OPTIONS if getattr(args, k) is not None}
    if args.max_steps is not None:
        given["fit"] = dataclasses.replace(PairBakeOptions.fit, max_steps=args.max_steps)
    try:
        return PairBakeOptions(**given)
    except ValueError as e:
        said = str(e).removeprefix("PairBakeOptions: ")
        said = said.replace(f"size {args.size!r}", f"size {_size_words(args.size)}")
        raise ValueError(as_flags(said, _OPTIONS)) from None


def _meshes(args, say):
    """HIGH, LOW (read, or decimated and unwrapped) and the cage mesh of ``args``."""
    from .. import io
    from ..transfer import decimate, unwrap

    say(f"reading {args.high} ...")
    high = io.load_mesh(args.high)
    made = args.decimate is not None or args.unwrap
    if args.decimate is not None:
        say(f"decimating {args.high} to {args.decimate} triangles ...")
        low, low_name = decimate(high, args.decimate, name=args.high), f"LOW (from {args.high})"
    else:
        say(f"reading {args.low} ...")
        low, low_name = io.load_mesh(args.low), args.low
    if args.unwrap or args.decimate is not None:
        say(f"unwrapping {low_name} with xatlas ...")
        low = unwrap(low, size=args.size, name=low_name)
    elif low.uv is None:
        raise ValueError(f"{low_name}: the mesh has no texture coordinates (uv); a normal map "
                         "is baked into LOW's uv layout (--unwrap makes one with xatlas)")
    cage = None
    if args.cage_mesh:
        say(f"reading {args.cage_mesh} ...")
        cage = io.load_mesh(args.cage_mesh, normals="angle")  # (the rays use its points)
    return high, low, low_name, cage, made


def run(args, ctrl_c: CtrlC) -> int:
    """``jaxnm bake``: check the options, read (or make) the meshes, bake, write. Stage lines
    on stderr; Ctrl-C stops at the next stage boundary before the fit (exit 130, nothing
    written), after the current step during it, and leaves out the scores and figures
    after it (the maps and the report are written; exit 130)."""
    t0 = time.perf_counter()
    options = _options(args)
    if args.store == "bc5":
        import numpy as np

        from ..storage import encode_blocks

        encode_blocks(np.zeros((4, 4, 2), np.uint8), format="bc5")  # the storage extra
    out = output_path("-o", args.output, folder=True)
    _check_inputs(args)
    _check_extra(args)
    ctrl_c.output = out
    high, low, low_name, cage, made = _meshes(args, _say)
    ctrl_c.check()

    def stage(key: str, message: str) -> None:
        ctrl_c.check()
        _say(message)
        if key == "fit":
            ctrl_c.phase = "fit"
        elif key == "evaluate":
            ctrl_c.phase = "writing"

    from ..transfer import bake_mesh_pair

    bake = bake_mesh_pair(high, low, options, cage_mesh=cage, high_name=args.high,
                          low_name=low_name, cage_name=args.cage_mesh or "cage mesh",
                          on_stage=stage,
                          should_stop=lambda: ctrl_c.requested is not None,
                          progress="lines" if args.no_progress else True)
    ctrl_c.phase = "writing"
    _say(f"writing outputs to {out}/ ...")
    report = _write(out, bake, args, ctrl_c, low_written=made,
                    read_seconds=time.perf_counter() - t0 - bake.seconds)
    summary = _summary(report)
    if summary:  # (no scores and no fit: nothing to sum up)
        print(summary)
    print(f"outputs in {out}/ ({', '.join(report['files'])})")
    return 130 if report["interrupted"] else 0


def _summary(report: dict) -> str:
    """A line per method: how it went and its held-out scores."""
    lines = []
    evaluation = report.get("evaluation", {})
    scores = evaluation.get("methods", {})
    if scores and not sum(evaluation["scored_pixels_per_view"]):
        lines.append("held-out views: no pixel scored (LOW hidden or off-screen in every "
                     "view), so no scores")
        scores = {}
    for name in ("none", "raycast", "fit"):
        if name not in scores:
            continue
        # with pixels scored, a PSNR left out of the report is that of identical images
        s = {k: (math.inf if k == "psnr_db" else math.nan) if v is None else v
             for k, v in scores[name].items()}
        lines.append(f"{'no map' if name == 'none' else name:>8}: held-out PSNR "
                     f"{s['psnr_db']:.2f} dB, FLIP {s['flip']:.4f}, normal angle mean "
                     f"{s['angle_mean_deg']:.2f} deg")
    if "fit" in report:
        f = report["fit"]
        lines.append(f"fit {f['stopped_because']} after {f['steps']} "
                     f"step{'' if f['steps'] == 1 else 's'}; "
                     f"{f['unseen_texels']} of {f['chart_texels']} chart texels seen by fewer "
                     f"than 2 views")
    if "raycast" in report and report["raycast"]["texels_missed"]:
        r = report["raycast"]
        lines.append(f"rays of {r['texels_missed']} of {r['texels_inside']} texels missed HIGH "
                     f"(raycast/missed.png)")
    if report["interrupted"]:
        lines.append("interrupted: " + ", ".join(report.get("skipped", [])) + " left out")
    return "\n".join(lines)


# ----------------------------------------------------------------------------- outputs


def _map_files(folder: Path, normals, store: str, extra: dict) -> list[str]:
    """``normal_map.npz`` and ``normal_map.png`` (and ``normal_map.dds`` for bc5) of one
    method's map; returns the names written (relative to the output folder)."""
    import numpy as np

    from .. import io
    from ..textures import encode_normal_map, quantize

    bits = 16 if store == "png16" else 8
    io.save_normal_map_npz(folder / "normal_map.npz", normals, **extra)
    texels = np.asarray(quantize(encode_normal_map(np.asarray(normals), encoding="unsigned",
                                                   green="up", bits=bits), bits))
    io.save_png(folder / "normal_map.png", texels, bits=bits)
    names = ["normal_map.npz", "normal_map.png"]
    if store == "bc5":
        from ..storage import save_dds_normal_map

        n = np.asarray(normals, np.float64).copy()
        n[..., 2] = np.maximum(n[..., 2], 0.0)  # BC5 keeps x and y; z is rebuilt >= 0
        n /= np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-12)
        save_dds_normal_map(folder / "normal_map.dds", n.astype(np.float32))
        names.append("normal_map.dds")
    return [f"{folder.name}/{n}" for n in names]


def _grey(values, vmax: float, fill: float = 0.25):
    """A PNG-ready grey image: ``values / vmax`` clipped to [0, 1], ``fill`` where NaN."""
    import numpy as np

    v = np.asarray(values, np.float64)
    return np.where(np.isfinite(v), np.clip(v / vmax, 0, 1), fill).astype(np.float32)


def _write_maps(out: Path, bake, store: str) -> list[str]:
    """Each method's map files, and the mesh the maps are for; the names written."""
    import numpy as np

    from .. import io

    files = []
    # glTF viewers decode a normal texture in MikkTSpace over the file's normals and uvs
    viewable = bake.frame == "vertex" and (bake.low.tangent_source or "mikktspace") == "mikktspace"
    if bake.raycast is not None:
        r = bake.raycast
        files += _map_files(out / "raycast", r.normals, store,
                            {"inside": r.inside, "filled": r.filled, "missed": r.missed})
        if viewable:
            io.save_glb(out / "raycast" / "low.glb", bake.low, r.normals)
            files.append("raycast/low.glb")
        if r.texels_missed:
            io.save_png(out / "raycast" / "missed.png", r.missed.astype(np.float32))
            files.append("raycast/missed.png")
    if "fit" in bake.maps:
        n = bake.maps["fit"]
        files += _map_files(out / "fit", n, store, {
            "slopes": (n[..., :2] / np.maximum(n[..., 2:], 1e-3)).astype(np.float32),
            "seen": bake.fit_seen, "views_per_texel": bake.plan.counts.astype(np.int16),
            "chart": bake.plan.chart})
        if viewable:
            io.save_glb(out / "fit" / "low.glb", bake.low, n)
            files.append("fit/low.glb")
    return files


def _error_maps(out: Path, bake) -> list[str]:
    """Per method, the held-out angle per texel, 0 to 10 degrees from black to white (texels
    no held-out view shows: grey); and the fit's views per texel (0 to 4)."""
    from .. import io

    files = []
    if bake.evaluation is not None:
        for name, s in bake.evaluation.methods.items():
            if name in bake.maps:
                io.save_png(out / name / "error_map.png", _grey(s.texel_error_deg, 10.0))
                files.append(f"{name}/error_map.png")
    if bake.plan is not None and "fit" in bake.maps:
        import numpy as np

        cover = np.where(bake.plan.chart, bake.plan.counts, np.nan)
        io.save_png(out / "fit" / "coverage.png", _grey(cover, 4.0, 0.0))
        files.append("fit/coverage.png")
    return files


def _figure(out: Path, bake) -> str | None:
    """``figure.png``: the first held-out view and light, HIGH beside LOW with no map and
    with each map, their FLIP maps and normal angles; None without matplotlib or scores."""
    from .. import io

    ev = bake.evaluation
    if ev is None or not sum(ev.pixels):
        return None
    names = ["none"] + [n for n in ("raycast", "fit") if n in ev.example]
    ex = ev.example
    s = ev.methods
    titles = ["HIGH"] + [f"{'no map' if n == 'none' else n}: {s[n].psnr_db:.1f} dB, "
                         f"FLIP {s[n].flip:.3f}" for n in names]
    rows = [[ex["high"]] + [ex[n]["image"] for n in names],
            [None] + [(ex[n]["flip"], 1.0, "FLIP") for n in names],
            [None] + [(ex[n]["angle"], 20.0, "degrees") for n in names]]
    ok = io.save_figure_grid(out / "figure.png", rows, titles=titles,
                             row_labels=["render (sRGB)", "FLIP", "normal angle"],
                             note="a held-out view and light (scores over all held-out "
                                  "images)")
    return "figure.png" if ok else None


def _raycast_report(r) -> dict:
    faces = [int(i) for i in r.missed_faces[:20]]
    return {"cage": r.cage, "cage_source": r.cage_source, "max_distance": r.max_distance,
            "samples": r.samples, "margin": r.margin, "texels_inside": r.texels_inside,
            "texels_missed": r.texels_missed,
            "missed_mask": "raycast/missed.png" if r.texels_missed else None,
            "missed_uv_box": None if r.missed_uv_box is None else
            [round(float(x), 5) for x in r.missed_uv_box],
            "missed_faces_first": faces, "missed_faces": int(r.missed_faces.size),
            "overlapping_texels": r.overlapping, "seconds": round(r.seconds, 3),
            "stages_seconds": {k: round(v, 3) for k, v in r.timings.items()}}


def _fit_report(bake) -> dict:
    import numpy as np

    from ..fit.report import stopped_in_words

    f, plan, o = bake.fit, bake.plan, bake.options
    counts = plan.counts[plan.chart]
    return {"start": "raycast" if o.method == "both" else "flat",
            "views": len(plan.cameras), "lights_per_view": int(plan.lights.shape[1]),
            "render_size": plan.render_size, "candidates": plan.candidates,
            "max_angle_deg": plan.max_angle_deg, "chart_texels": int(plan.chart.sum()),
            "unseen_texels": bake.unseen_texels,
            "unseen_means": f"chart texels seen by fewer than {plan.min_views} planned views "
                            f"within {plan.max_angle_deg:g} degrees of their normal",
            "views_per_texel": np.bincount(counts).tolist(),
            "texels_sampled_by_the_fit": int(bake.fit_seen.sum()),
            "view_directions": np.round(plan.directions, 6).tolist(),
            "light_directions": np.round(plan.lights, 6).tolist(),
            "mask_tolerance": bake.tolerance, "sampling": "bilinear, no mip levels",
            "stopped": f.stopped, "stopped_because": stopped_in_words(f, o.fit),
            "stop_test": f.stop_test,
            "steps": sum(1 for h in f.history if h["step"] > 0),
            "start_loss": f.history[0]["loss"] if f.history else None,
            "final_loss": f.best_loss, "fit_seconds": round(f.seconds, 3),
            "identifiable": f.identifiability.get("identifiable"),
            "solver": dataclasses.asdict(o.fit)}


def _report(bake, args, files: list, low_written: bool) -> dict:
    """``report.json``: the inputs, the options, each method's account, the scores, the
    seconds per stage and what was written."""
    o = bake.options
    rep = {"high": args.high,
           "low": args.low if args.low else f"{args.high} decimated to {args.decimate} "
                                           "triangles",
           "low_file": "low.obj" if low_written else args.low,
           "low_triangles": int(bake.low.faces.shape[0]),
           "unwrapped": bool(args.unwrap or args.decimate is not None),
           "method": o.method, "map_size": list(o.map_size), "frame": bake.frame,
           "tangents": (bake.low.tangent_source or "mikktspace") if bake.frame == "vertex"
           else None,
           "map_encoding": {"encoding": "unsigned", "green": "up", "uv_origin": "bottom_left",
                            "bits": 16 if args.store == "png16" else 8,
                            "npz": "normals: unit tangent-space vectors, row 0 on top"},
           "store": args.store, "material": {"shading": o.shading, "albedo": o.albedo,
                                             "diffuse": 1.0, "specular": 0.15,
                                             "shininess": 24.0, "ambient": 0.0}}
    if bake.raycast is not None:
        rep["raycast"] = _raycast_report(bake.raycast)
    if bake.fit is not None:
        rep["fit"] = _fit_report(bake)
    if bake.evaluation is not None:
        rep["evaluation"] = bake.evaluation.summary()
        rep["evaluation"]["what"] = ("held-out views and lights the fit never used; PSNR of "
                                     "linear colour (peak 1), FLIP (LDR, sRGB), the angle "
                                     "between HIGH's and LOW's shading normals per pixel")
    rep["seconds"] = dict(bake.timings)
    rep["bake_seconds"] = round(bake.seconds, 3)
    rep["interrupted"] = bake.interrupted
    rep["skipped"] = list(bake.skipped)
    rep["files"] = files
    return rep


def _write(out: Path, bake, args, ctrl_c: CtrlC, *, low_written: bool,
           read_seconds: float) -> dict:
    """Write the maps and a report first, then the optional files (error maps, coverage,
    figure) unless Ctrl-C was pressed, then the final report; returns it."""
    from .. import io

    files = _write_maps(out, bake, args.store)
    if low_written:
        io.save_obj(out / "low.obj", bake.low)
        files.append("low.obj")
    report = _report(bake, args, files + ["report.json"], low_written)
    report["seconds"]["read"] = round(max(read_seconds, 0.0), 3)
    report["pending"] = ["error_maps", "figure"]
    io.save_json(out / "report.json", report)
    skipped = []
    for part in ("error_maps", "figure"):
        if ctrl_c.requested is not None:
            skipped.append(part)
        elif part == "error_maps":
            report["files"] += _error_maps(out, bake)
        else:
            name = _figure(out, bake)
            if name is not None:
                report["files"].append(name)
            elif bake.evaluation is not None:
                report["figure"] = "not drawn: matplotlib is not installed (the cli extra)"
    del report["pending"]
    report["skipped"] += skipped
    report["interrupted"] = bool(bake.interrupted or ctrl_c.requested is not None)
    io.save_json(out / "report.json", report)
    return report
