"""Write an example fit folder for `jaxnm fit FIT.json`: the built-in problem as files.

    python -m scripts.examples.make_example_fit [OUTDIR] [--render 256] [--map 128] [--noise 0]
    jaxnm fit OUTDIR/fit.json -o OUTDIR/out

OUTDIR (default ``example_fit``) receives ``scene.json`` (the built-in torus and
material), one 16-bit sRGB PNG target per view and light (2 views x 6
lights), a held-out target under a light the fit does not see, the
ground-truth map ``gt.png`` (8-bit unsigned, as the targets were rendered
with) and ``fit.json`` tying them together. The files are generated, not
stored in the repository; edit them as a template for your own data.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from jaxnm.camera import eye_to_world
from jaxnm.fit import view_key
from jaxnm.io import save_png
from jaxnm.procedural import HELD_OUT_LIGHT, default_problem
from jaxnm.render import render
from jaxnm.shading import directional_light
from jaxnm.textures import linear_to_srgb
from scripts._cli import output, run_script


def _list(x) -> list:
    """A float array as nested lists of float32-exact, shortest-repr numbers."""
    return np.asarray(x, np.float32).astype(np.float64).round(9).tolist()


def _camera(cam) -> dict:
    return {"view": _list(cam.view), "projection": _list(cam.projection)}


def _dumps(obj: dict) -> str:
    """JSON with one line per top-level key (and per list item): readable, not sprawling."""
    def value(v):
        if isinstance(v, list) and v and isinstance(v[0], dict):
            return "[\n  " + ",\n  ".join(json.dumps(x) for x in v) + "\n ]"
        return json.dumps(v)
    return "{\n" + ",\n".join(f" {json.dumps(k)}: {value(v)}" for k, v in obj.items()) + "\n}\n"


def _srgb_png(path: Path, linear: np.ndarray) -> None:
    save_png(path, np.asarray(linear_to_srgb(np.clip(linear, 0.0, 1.0))), bits=16)


def write_example(outdir: Path, render_size: int = 256, map_size: int = 128,
                  noise: float = 0.0) -> Path:
    """Write the example into ``outdir``; returns the path of ``fit.json``."""
    outdir = Path(outdir)
    outdir.mkdir(parents=True, exist_ok=True)
    problem, _, scene = default_problem(render_size=render_size, map_size=map_size,
                                        noise=noise)
    m, nm = scene.material, scene.normal_map_options
    (outdir / "scene.json").write_text(_dumps({
        "mesh": "builtin:torus",
        "width": render_size, "height": render_size,
        "camera": _camera(problem.targets[0].camera),
        "normal_map": {"path": "gt.png", "filter": nm.filter, "wrap": nm.wrap,
                       "uv_origin": nm.uv_origin},
        "albedo": _list(scene.albedo),
        "material": {"model": scene.shading, "diffuse": _list(m.diffuse),
                     "specular": _list(m.specular), "shininess": float(m.shininess),
                     "ambient": _list(m.ambient)},
    }))
    save_png(outdir / "gt.png", np.asarray(scene.normal_map, np.float32))  # 8-bit codes / 255

    views, targets = [], []
    keys = {}
    for i, t in enumerate(problem.targets):
        key = view_key(t)
        if key not in keys:
            keys[key] = len(views)
            views.append({"camera": _camera(t.camera), "width": t.width, "height": t.height})
        _srgb_png(outdir / f"target_{i:02d}.png", np.asarray(t.image))
        d = np.asarray(t.lights.directional.direction).reshape(-1, 3)[0]
        targets.append({"view": keys[key], "image": f"target_{i:02d}.png",
                        "color_space": "srgb",
                        "lights": [{"type": "directional", "direction": _list(d)}]})

    cam = problem.targets[0].camera
    held_dir = eye_to_world(cam, HELD_OUT_LIGHT)
    held = render(scene.replace(camera=cam, lights=directional_light(held_dir)))["color"]
    _srgb_png(outdir / "held_out.png", np.asarray(held))

    fit = {
        "scene": "scene.json",
        "views": views,
        "targets": targets,
        "map": {"size": [map_size, map_size], "encoding": "unsigned", "green": "up", "bits": 8},
        "ground_truth": {"path": "gt.png", "encoding": "unsigned", "green": "up"},
        "held_out": [{"view": 0, "image": "held_out.png", "color_space": "srgb",
                      "lights": [{"type": "directional", "direction": _list(held_dir)}]}],
        "solver": {"method": "lm-texel", "max_steps": 15, "lsmr_steps": 20},
    }
    path = outdir / "fit.json"
    path.write_text(_dumps(fit))
    return path


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("outdir", nargs="?", default="example_fit")
    ap.add_argument("--render", type=int, default=256, help="render size (square)")
    ap.add_argument("--map", type=int, default=128, help="normal map size (square)")
    ap.add_argument("--noise", type=float, default=0.0,
                    help="Gaussian noise on the targets, relative to each target's maximum")
    args = ap.parse_args(argv)
    output("OUTDIR", args.outdir, folder=True)  # before the work
    path = write_example(Path(args.outdir), args.render, args.map, args.noise)
    print(f"wrote {path}; run: jaxnm fit {path} -o {Path(args.outdir) / 'out'}")


if __name__ == "__main__":
    sys.exit(run_script(main))
