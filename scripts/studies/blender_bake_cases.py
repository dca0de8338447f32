"""Maps baked by Blender, decoded by jaxnm: which frame a real baker's map needs, in degrees.

    python -m scripts.studies.blender_bake_cases [--out DIR] [--size 128]

Blender (``bpy``, Cycles, "selected to active", tangent space) bakes a normal map from an
analytically displaced high-poly surface onto a low-poly one (`tests/blender_ref.py`, run in
its own environment: ``JAXNM_BLENDER_PYTHON`` or ``.venv-blender/bin/python``). jaxnm then
renders the low-poly mesh with that map and every frame, and each pixel's decoded normal is
compared with the *high-poly surface's* normal at the point the baker's ray hits: the ray
leaves the low-poly surface point along its interpolated normal, and the hit is solved on
the analytic surface (so no view parallax and no tessellation error enter the reference).

Cases (low-poly, uv layout): a flat grid and a curved cylinder patch with smooth normals,
each with plain, mirrored (the two halves share the vertices of the mirror line), stretched
(1:3) and sheared uvs; a box with hard edges (split normals, one uv island per face); the
patch with two columns of zero-area uv triangles (their own pixels carry no map information
and are left out; their neighbours must not suffer). Prints JSON and a markdown table.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import jax.numpy as jnp
import numpy as np

import jaxnm
from jaxnm.frames import FRAMES
from jaxnm.scene import Scene
from jaxnm.textures import NormalMapOptions
from scripts._cli import output, run_script

ROOT = Path(__file__).resolve().parents[2]  # the repository
AMPLITUDE = 0.04
MAP_SIZE = 512


def blender_python() -> str | None:
    """The Python with bpy: $JAXNM_BLENDER_PYTHON, or .venv-blender/bin/python."""
    cand = os.environ.get("JAXNM_BLENDER_PYTHON") or str(ROOT / ".venv-blender" / "bin" /
                                                         "python")
    return cand if Path(cand).exists() else None


# --------------------------------------------------------------------------------------
# the detail: a smooth height field, symmetric in its first coordinate (for mirroring)
# --------------------------------------------------------------------------------------


def height(s, t):
    return AMPLITUDE * (np.cos(4 * s) * np.cos(2.5 * t) + 0.5 * np.sin(2 * t + 0.5))


def height_grad(s, t):
    return (AMPLITUDE * -4 * np.sin(4 * s) * np.cos(2.5 * t),
            AMPLITUDE * (-2.5 * np.cos(4 * s) * np.sin(2.5 * t) + np.cos(2 * t + 0.5)))


def _grid_faces(n: int, m: int, offset: int = 0) -> np.ndarray:
    j, i = np.meshgrid(np.arange(m), np.arange(n), indexing="ij")
    k = (j * (n + 1) + i).reshape(-1) + offset
    return np.concatenate([np.stack([k, k + 1, k + n + 2], 1),
                           np.stack([k, k + n + 2, k + n + 1], 1)])


def _uv(kind: str, s01, t01):
    """uv of the layout ``kind`` from grid coordinates in [0, 1]."""
    return {"plain": np.stack([s01, t01], -1),
            "mirrored": np.stack([1 - np.abs(2 * s01 - 1), t01], -1),
            "stretched": np.stack([s01, t01 / 3 + 0.3], -1),
            "sheared": np.stack([0.6 * s01 + 0.35 * t01, t01], -1)}[kind]


# --------------------------------------------------------------------------------------
# cases: low-poly, high-poly, and the analytic reference along the baker's rays
# --------------------------------------------------------------------------------------


class Plane:
    """z = 0 over [-1, 1]^2 (low: 8 x 8 quads), high: z = height(x, y)."""

    def __init__(self, uv_kind: str):
        self.name = f"flat, {uv_kind} uv"
        s = np.linspace(-1, 1, 9)
        X, Y = np.meshgrid(s, s, indexing="xy")
        self.lo_pos = np.stack([X, Y, 0 * X], -1).reshape(-1, 3)
        self.lo_faces = _grid_faces(8, 8)
        self.lo_uv = _uv(uv_kind, (X.reshape(-1) + 1) / 2, (Y.reshape(-1) + 1) / 2)
        self.lo_n = np.tile([0.0, 0.0, 1.0], (len(self.lo_pos), 1))
        s = np.linspace(-1, 1, 301)
        X, Y = np.meshgrid(s, s, indexing="xy")
        self.hi_pos = np.stack([X, Y, height(X, Y)], -1).reshape(-1, 3)
        self.hi_faces = _grid_faces(300, 300)
        self.camera = jaxnm.Camera.look_at((0.3, -0.4, 2.6), (0, 0, 0), (0, 1, 0),
                                           fov_y_deg=45)

    def reference(self, p, d):
        gx, gy = height_grad(p[:, 0], p[:, 1])
        n = np.stack([-gx, -gy, np.ones_like(gx)], -1)
        return n / np.linalg.norm(n, axis=-1, keepdims=True), np.ones(len(p), bool)


class Patch:
    """A cylinder patch (radius 1 about y, angle -0.75..0.75) with smooth radial normals
    (low: 10 x 10 quads); high: radius 1 + height(angle, y)."""

    def __init__(self, uv_kind: str, degenerate: bool = False):
        self.name = f"curved, {uv_kind} uv" + (", zero-area uv triangles" if degenerate else "")
        a = np.linspace(-0.75, 0.75, 11)
        y = np.linspace(-1, 1, 11)
        A, Y = np.meshgrid(a, y, indexing="xy")
        self.lo_pos = self._surface(A, Y, np.ones_like(A)).reshape(-1, 3)
        self.lo_n = np.stack([np.sin(A), 0 * A, np.cos(A)], -1).reshape(-1, 3)
        self.lo_faces = _grid_faces(10, 10)
        s01 = ((A + 0.75) / 1.5).reshape(-1)
        self.lo_uv = _uv(uv_kind, s01, ((Y + 1) / 2).reshape(-1))
        self.zero_area = np.zeros(len(self.lo_faces), bool)
        if degenerate:  # columns 3 and 6 collapse onto columns 2 and 5
            col = np.arange(len(self.lo_uv)) % 11
            self.lo_uv[col == 3, 0] = self.lo_uv[col == 2, 0]
            self.lo_uv[col == 6] = self.lo_uv[col == 5]
            t = self.lo_uv[self.lo_faces]
            e1, e2 = t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]
            self.zero_area = np.abs(e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]) < 1e-12
        a = np.linspace(-0.75, 0.75, 301)
        y = np.linspace(-1, 1, 301)
        A, Y = np.meshgrid(a, y, indexing="xy")
        self.hi_pos = self._surface(A, Y, 1 + height(A, Y)).reshape(-1, 3)
        self.hi_faces = _grid_faces(300, 300)
        self.camera = jaxnm.Camera.look_at((0.2, 0.3, 3.4), (0, 0, 0.9), (0, 1, 0),
                                           fov_y_deg=40)

    @staticmethod
    def _surface(a, y, r):
        return np.stack([r * np.sin(a), y, r * np.cos(a)], -1)

    def reference(self, p, d):
        t = np.zeros(len(p))
        for _ in range(30):  # Newton on the ray parameter, numerical derivative
            def f(t_):
                q = p + t_[:, None] * d
                return np.hypot(q[:, 0], q[:, 2]) - 1 - height(np.arctan2(q[:, 0], q[:, 2]),
                                                               q[:, 1])
            f0 = f(t)
            t = t - f0 / ((f(t + 1e-6) - f0) / 1e-6)
        q = p + t[:, None] * d
        a, y = np.arctan2(q[:, 0], q[:, 2]), q[:, 1]
        r = 1 + height(a, y)
        ha, hy = height_grad(a, y)
        sa = np.stack([ha * np.sin(a) + r * np.cos(a), 0 * a, ha * np.cos(a) - r * np.sin(a)],
                      -1)
        sy = np.stack([hy * np.sin(a), np.ones_like(a), hy * np.cos(a)], -1)
        n = np.cross(sa, sy)
        n = n / np.linalg.norm(n, axis=-1, keepdims=True) * np.sign(np.sum(n * d, -1))[:, None]
        return n, np.abs(f(t)) < 1e-9


class Box:
    """A cube with hard edges (split normals, an island per face); high: each face displaced
    by ``height`` along its normal. Pixels within 0.1 of an edge are left out (there a ray can
    meet the neighbouring face's detail)."""

    def __init__(self):
        self.name = "box, hard edges"
        lo_pos, lo_n, lo_uv, lo_faces, hi_pos, hi_faces = [], [], [], [], [], []
        self.axes = []
        k = 0
        for axis in range(3):
            for sgn in (-1.0, 1.0):
                n = np.zeros(3)
                n[axis] = sgn
                e1 = np.eye(3)[(axis + 1) % 3]
                e2 = np.cross(n, e1)
                self.axes.append((n, e1, e2))
                s = np.linspace(-1, 1, 3)
                S, T = np.meshgrid(s, s, indexing="xy")
                pts = n + S[..., None] * e1 + T[..., None] * e2
                lo_pos.append(pts.reshape(-1, 3))
                lo_n.append(np.tile(n, (9, 1)))
                u0, v0 = 0.05 + 0.32 * (k % 3), 0.05 + 0.48 * (k // 3)
                lo_uv.append(np.stack([u0 + 0.28 * (S + 1) / 2, v0 + 0.42 * (T + 1) / 2],
                                      -1).reshape(-1, 2))
                lo_faces.append(_grid_faces(2, 2, 9 * k))
                s = np.linspace(-1, 1, 121)
                S, T = np.meshgrid(s, s, indexing="xy")
                hp = n + S[..., None] * e1 + T[..., None] * e2 + height(S, T)[..., None] * n
                hi_faces.append(_grid_faces(120, 120, 121 * 121 * k))
                hi_pos.append(hp.reshape(-1, 3))
                k += 1
        self.lo_pos, self.lo_n = np.concatenate(lo_pos), np.concatenate(lo_n)
        self.lo_uv, self.lo_faces = np.concatenate(lo_uv), np.concatenate(lo_faces)
        self.hi_pos, self.hi_faces = np.concatenate(hi_pos), np.concatenate(hi_faces)
        self.camera = jaxnm.Camera.look_at((2.6, -3.2, 2.9), (0, 0, 0), (0, 0, 1), fov_y_deg=40)

    def reference(self, p, d):
        ref = np.zeros_like(p)
        ok = np.zeros(len(p), bool)
        for n, e1, e2 in self.axes:
            on = np.abs(p @ n - 1) < 1e-4
            s, t = p[on] @ e1, p[on] @ e2
            hs, ht = height_grad(s, t)
            v = n[None] - hs[:, None] * e1[None] - ht[:, None] * e2[None]
            ref[on] = v / np.linalg.norm(v, axis=-1, keepdims=True)
            ok[on] = (np.abs(s) < 0.9) & (np.abs(t) < 0.9)
        return ref, ok


def cases():
    return ([Plane(k) for k in ("plain", "mirrored", "stretched", "sheared")]
            + [Patch(k) for k in ("plain", "mirrored", "stretched", "sheared")]
            + [Box(), Patch("plain", degenerate=True)])


# --------------------------------------------------------------------------------------
# bake, decode, compare
# --------------------------------------------------------------------------------------


def bake(case, workdir: Path, blender: str) -> np.ndarray:
    """Blender's tangent-space bake of ``case`` (a MAP_SIZE^2 float map, row 0 = v = 1)."""
    spec, out = workdir / "spec.npz", workdir / "out.npz"
    np.savez(spec, hi_positions=case.hi_pos, hi_faces=case.hi_faces, lo_positions=case.lo_pos,
             lo_faces=case.lo_faces, lo_uv=case.lo_uv, lo_normals=case.lo_n, size=MAP_SIZE,
             cage_extrusion=0.2)
    run = subprocess.run([blender, str(ROOT / "tests" / "blender_ref.py"), "bake", str(spec),
                          str(out)], capture_output=True, text=True, timeout=900)
    if run.returncode != 0:
        raise RuntimeError(f"Blender bake failed: {run.stderr[-2000:]}")
    return np.load(out)["image"]


def decode_errors(case, image: np.ndarray, frame: str, size: int = 128) -> np.ndarray:
    """Per covered pixel (that the reference keeps): the angle (deg) between jaxnm's decoded
    normal with ``frame`` and the high-poly normal where the baker's ray hits."""
    mesh = jaxnm.Mesh(jnp.asarray(case.lo_pos, jnp.float32), jnp.asarray(case.lo_faces),
                      jnp.asarray(case.lo_uv, jnp.float32), jnp.asarray(case.lo_n, jnp.float32))
    if frame == "vertex":
        mesh = mesh.with_tangents()  # MikkTSpace, as Blender's baker
    scene = Scene(mesh=mesh, camera=case.camera, width=size, height=size,
                  normal_map=jnp.asarray(image, jnp.float32),
                  normal_map_options=NormalMapOptions(filter="bilinear", wrap="clamp"),
                  frame=frame, source=case.name)
    out = jaxnm.render(scene, outputs=("perturbed_normal", "position", "normal", "mask",
                                       "triangle_id"))
    m = np.asarray(out["mask"])[..., 0] > 0
    tri = np.asarray(out["triangle_id"])[..., 0].astype(int)[m]
    p = np.asarray(out["position"], np.float64)[m]
    d = np.asarray(out["normal"], np.float64)[m]
    ref, ok = case.reference(p, d)
    ok &= ~getattr(case, "zero_area", np.zeros(len(case.lo_faces), bool))[tri]
    n = np.asarray(out["perturbed_normal"], np.float64)[m]
    ang = np.degrees(np.arctan2(np.linalg.norm(np.cross(n, ref), axis=-1), np.sum(n * ref, -1)))
    return ang[ok]


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default=None, help="also write table.json and table.md here")
    ap.add_argument("--size", type=int, default=128, help="render size")
    args = ap.parse_args(argv)
    output("--out", args.out, folder=True)  # before the work
    blender = blender_python()
    if blender is None:
        sys.exit("no Blender Python: set JAXNM_BLENDER_PYTHON or make .venv-blender with "
                 "pip install bpy==5.0.1")
    frames = [f for f in FRAMES if f != "none"]
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for case in cases():
            image = bake(case, Path(tmp), blender)
            row = {"case": case.name}
            for frame in frames:
                err = decode_errors(case, image, frame, args.size)
                row[frame] = {"mean_deg": round(float(err.mean()), 4),
                              "p99_deg": round(float(np.percentile(err, 99)), 3),
                              "pixels": int(err.size)}
            rows.append(row)
            print(json.dumps(row), flush=True)
    md = ["| case | " + " | ".join(frames) + " |", "|---|" + "---|" * len(frames)]
    for r in rows:
        md.append(f"| {r['case']} | " + " | ".join(
            f"{r[f]['mean_deg']:.3f} / {r[f]['p99_deg']:.2f}" for f in frames) + " |")
    print("\n".join(md))
    if args.out:
        out = Path(args.out)
        out.mkdir(parents=True, exist_ok=True)
        (out / "table.json").write_text(json.dumps(rows, indent=1) + "\n")
        (out / "table.md").write_text("\n".join(md) + "\n")


if __name__ == "__main__":
    sys.exit(run_script(main))
