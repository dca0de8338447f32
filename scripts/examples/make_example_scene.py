"""Regenerate the example scene in scripts/examples/scenes/torus/ (an OBJ, a normal-map PNG,
scene.json).

    python -m scripts.examples.make_example_scene
    jaxnm render scripts/examples/scenes/torus/scene.json -o torus.png
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from jaxnm import procedural
from jaxnm.io import save_png

HERE = Path(__file__).resolve().parent / "scenes" / "torus"


def write_obj(path: Path, mesh) -> None:
    pos, uv, nrm = (np.asarray(a, np.float64) for a in (mesh.positions, mesh.uv, mesh.normals))
    faces = np.asarray(mesh.faces) + 1
    lines = ["# torus with angle uvs, written by scripts/examples/make_example_scene.py"]
    lines += [f"v {x:.6f} {y:.6f} {z:.6f}" for x, y, z in pos]
    lines += [f"vt {u:.6f} {v:.6f}" for u, v in uv]
    lines += [f"vn {x:.6f} {y:.6f} {z:.6f}" for x, y, z in nrm]
    lines += [f"f {a}/{a}/{a} {b}/{b}/{b} {c}/{c}/{c}" for a, b, c in faces]
    path.write_text("\n".join(lines) + "\n")


def main() -> None:
    HERE.mkdir(parents=True, exist_ok=True)
    mesh = procedural.torus(1.0, 0.42, 48, 24, uv_scale=(3.0, 1.0))
    write_obj(HERE / "torus.obj", mesh)
    nm = procedural.default_normal_map_texels(128)
    save_png(HERE / "rivets.png", nm)
    scene = {
        "mesh": "torus.obj",
        "camera": {"eye": [0.0, -2.35, 1.75], "target": [0.0, 0.0, -0.1], "up": [0, 0, 1],
                   "fov_y_deg": 45, "near": 0.1, "far": 50},
        "width": 384, "height": 288,
        "normal_map": {"path": "rivets.png", "encoding": "unsigned", "green": "up",
                       "strength": 1.0, "filter": "trilinear", "wrap": "repeat"},
        "albedo": [0.85, 0.6, 0.38],
        "lights": [
            {"type": "directional", "direction": [-0.6, -0.5, 0.8], "color": [1, 0.96, 0.9],
             "intensity": 0.9},
            {"type": "point", "position": [1.8, -1.6, 1.4], "color": [0.5, 0.7, 1.0],
             "intensity": 4.0},
        ],
        "material": {"model": "blinn_phong", "diffuse": [1, 1, 1], "specular": [0.35, 0.35, 0.35],
                     "shininess": 48, "ambient": [0.04, 0.04, 0.04]},
        "frame": "cotangent",
        "derivatives": "fine",
        "double_sided": True,
    }
    (HERE / "scene.json").write_text(json.dumps(scene, indent=2) + "\n")
    print(f"wrote {HERE}")


if __name__ == "__main__":
    main()
