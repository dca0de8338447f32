"""Command line: ``jaxnm render`` and ``jaxnm fit``.

    jaxnm render [SCENE.json] [-o out.png] [--aovs out.npz] [--derivatives MODE]
                 [--frame FRAME] [--normal-map PATH] [--width W --height H]
    jaxnm fit [FIT.json] [-o OUTDIR] ...

Options override the scene file; with no scene file the built-in default scene
(a rivet-mapped torus, generated in code) is used.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

__all__ = ["main"]


def _add_render(sub) -> None:
    from .render import OUTPUTS
    from .scene import DERIVATIVES, FRAMES

    p = sub.add_parser("render", help="render a scene to a PNG (and optional AOVs)",
                       description="Render SCENE.json (or the built-in default scene) to a PNG.")
    p.add_argument("scene", nargs="?", help="scene JSON file (default: the built-in scene)")
    p.add_argument("-o", "--output", default="render.png", help="output PNG (default: %(default)s)")
    p.add_argument("--aovs", metavar="OUT.npz",
                   help="also write these arrays to an .npz: " + ", ".join(OUTPUTS[:-1])
                   + " and color (linear); see --aov-list")
    p.add_argument("--aov-list", default=",".join(OUTPUTS), metavar="NAMES",
                   help="comma-separated AOV names to write with --aovs (default: all)")
    p.add_argument("--derivatives", choices=DERIVATIVES, help="screen-space derivative mode")
    p.add_argument("--frame", choices=FRAMES, help="tangent frame method")
    p.add_argument("--normal-map", metavar="PATH",
                   help="use this tangent-space normal map (8/16-bit PNG, unsigned, green up)")
    p.add_argument("--height-map", metavar="PATH", dest="height_map",
                   help="bump the surface with this height map instead (grayscale image)")
    p.add_argument("--height-scale", type=float, default=0.02, dest="height_scale",
                   help="world units per unit of the height map (default: %(default)s)")
    p.add_argument("--width", type=int)
    p.add_argument("--height", type=int)
    p.add_argument("--exposure", type=float, default=1.0, help="linear scale before sRGB")
    p.add_argument("--bits", type=int, choices=(8, 16), default=8, help="PNG bit depth")


def _render(args) -> int:
    import numpy as np

    from . import io
    from .render import OUTPUTS, render
    from .scene import default_scene, load_scene
    from .shading import to_display

    t0 = time.perf_counter()
    if args.scene:
        scene = load_scene(args.scene)
    else:
        scene = default_scene(width=args.width or 512, height=args.height or 512)
    changes = {}
    if args.width or args.height:
        w, h = args.width or scene.width, args.height or scene.height
        if (w, h) != (scene.width, scene.height):
            changes.update(width=w, height=h, camera=_rescaled_camera(scene, w, h))
    if args.normal_map:
        raw, bits = io.load_texture(args.normal_map, channels=3)
        changes.update(normal_map=raw, normal_map_options=_replace(
            scene.normal_map_options, bits=bits if bits in (8, 16) else 8))
    if args.height_map:
        from .scene import _height_map

        d, opts = _height_map({"path": args.height_map, "scale": args.height_scale}, Path("."),
                              "--height-map")
        changes.update(normal_map=d, normal_map_options=opts)
    if changes:
        scene = scene.replace(**changes)
    outputs = ["color"]
    if args.aovs:
        names = [n.strip() for n in args.aov_list.split(",") if n.strip()]
        bad = [n for n in names if n not in OUTPUTS]
        if bad:
            raise ValueError(f"--aov-list: unknown AOV names {bad}; known: {', '.join(OUTPUTS)}")
        outputs += [n for n in names if n != "color"]
    result = render(scene, outputs=tuple(outputs), derivatives=args.derivatives,
                    frame=args.frame)
    io.save_png(args.output, np.asarray(to_display(result["color"], exposure=args.exposure)),
                bits=args.bits)
    msg = f"wrote {args.output} ({scene.width}x{scene.height})"
    if args.aovs:
        io.save_aovs(args.aovs, result)
        msg += f" and {args.aovs} ({', '.join(result)})"
    print(f"{msg} in {time.perf_counter() - t0:.2f} s")
    return 0


def _replace(obj, **kw):
    import dataclasses

    return dataclasses.replace(obj, **kw)


def _rescaled_camera(scene, width: int, height: int):
    """The scene's camera with the projection's aspect ratio adapted to a new image size."""
    import numpy as np

    from .camera import Camera

    proj = np.array(scene.camera.projection, np.float64)
    old = scene.width / scene.height
    new = width / height
    proj[0, :] *= old / new  # x scale ~ 1 / aspect (perspective and orthographic alike)
    return Camera.from_matrices(np.asarray(scene.camera.view, np.float64), proj)


def _add_fit(sub) -> None:
    p = sub.add_parser("fit", help="fit a normal map to target shading",
                       description="Fit a tangent-space normal map to target images.")
    p.add_argument("config", nargs="?", help="fit JSON file (default: the built-in problem)")
    p.add_argument("-o", "--output", default="fit_out", help="output folder (default: %(default)s)")
    p.add_argument("--solver", choices=("lm", "gn", "lbfgs"), help="optimiser (default: lm)")
    p.add_argument("--max-steps", type=int, dest="max_steps", help="outer iterations")
    p.add_argument("--lsmr-steps", type=int, dest="lsmr_steps",
                   help="inner LSMR iterations per Gauss-Newton/LM step")
    p.add_argument("--smoothness", type=float, help="slope smoothness weight (default 0)")
    p.add_argument("--coarse-to-fine", type=int, dest="coarse_to_fine",
                   help="number of coarser levels solved first")
    p.add_argument("--seed", type=int)
    p.add_argument("--time-limit", type=float, dest="time_limit", metavar="SECONDS")
    p.add_argument("--quick", action="store_true",
                   help="built-in problem at 128x128 renders and a 64x64 map (a smoke test)")
    p.add_argument("--no-progress", action="store_true", dest="no_progress")


def _fit(args) -> int:
    from .fit_cli import cli_main

    return cli_main(args)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="jaxnm", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)
    _add_render(sub)
    _add_fit(sub)
    args = parser.parse_args(argv)
    try:
        if args.command == "render":
            return _render(args)
        return _fit(args)
    except (ValueError, FileNotFoundError, ImportError) as e:
        print(f"jaxnm {args.command}: error: {e}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
