"""Hard cases: worst-pixel error against an exact reference, and finite gradients.

    python -m scripts.studies.hard_cases [--out hard_cases_out] [--size 64]

Every case renders a plane (or a closed mesh) whose uv mapping is affine, with a constant,
clearly tilted normal map value ``m``. On a plane the per-pixel cotangent frame is exact
whatever the view (its screen-space derivatives are scaled alike), so the perturbed normal
has a closed form: ``normalize(T m.x + B m.y + N m.z)`` with ``T, B`` the world gradients
of ``u`` and ``v`` scaled so that the longer is unit (Schüler's normalisation), computed
here in float64. Each case reports the worst pixel's angle to it, the tolerance it must
meet, and whether the image, the gradients with respect to the map, the vertex positions,
the camera and the lights, and every output are finite. Writes ``hard_cases.json``,
``hard_cases.md``, one PNG per case (the shaded image) and ``cases.png`` (every case's image,
labelled, in one figure; needs matplotlib) into ``--out``.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

import jaxnm
from jaxnm.camera import Camera, look_at, perspective
from jaxnm.scene import Scene
from jaxnm.shading import DirectionalLight, Lights, PointLight, stack_lights
from jaxnm.textures import NormalMapOptions
from scripts._cli import output, run_script

MAP_VALUE = np.array([0.35, -0.25, 0.9])  # decoded tangent-space vector (clearly tilted)
#: Worst-pixel angle to the exact perturbed normal every plane case must meet (degrees).
TOLERANCE = 1e-3


def _texels(n: int = 8) -> np.ndarray:
    """A constant unsigned map storing `MAP_VALUE` (normalised)."""
    m = MAP_VALUE / np.linalg.norm(MAP_VALUE)
    return np.broadcast_to(((m + 1) / 2).astype(np.float32), (n, n, 3)).copy()


def plane(segments: int = 2, size: float = 2.0, uv_matrix=((0.5, 0.0), (0.0, 0.5)),
          uv_offset=(0.5, 0.5), z: float = 0.0) -> tuple[jaxnm.Mesh, np.ndarray]:
    """A square in the plane z = ``z`` facing +z, uv = uv_matrix @ (x, y) + uv_offset."""
    t = np.linspace(-size / 2, size / 2, segments + 1)
    x, y = np.meshgrid(t, t, indexing="xy")
    pos = np.stack([x.ravel(), y.ravel(), np.full(x.size, z)], 1)
    a = np.asarray(uv_matrix, np.float64)
    uv = pos[:, :2] @ a.T + np.asarray(uv_offset)
    n = segments + 1
    i, j = np.meshgrid(np.arange(segments), np.arange(segments), indexing="xy")
    k = (j * n + i).ravel()
    faces = np.concatenate([np.stack([k, k + 1, k + n + 1], 1),
                            np.stack([k, k + n + 1, k + n], 1)])
    mesh = jaxnm.Mesh(jnp.asarray(pos, jnp.float32), jnp.asarray(faces, jnp.int32),
                      jnp.asarray(uv, jnp.float32),
                      jnp.asarray(np.tile([0.0, 0.0, 1.0], (len(pos), 1)), jnp.float32))
    return mesh, a


def chart_plane(uv_matrices, segments: int = 4, size: float = 2.0):
    """The plane z = 0 as separate triangles (no shared vertices), face ``f`` mapped by
    ``uv_matrices[f]`` (uv = A (x, y) + 0.5; None: a constant uv, zero uv area). Returns the
    mesh and the exact perturbed normal per face (the unperturbed +z where uv is constant,
    the renderer's documented fallback)."""
    shared, _ = plane(segments=segments, size=size)
    pos = np.asarray(shared.positions, np.float64)[np.asarray(shared.faces)]  # (F, 3, 3)
    uv, ref = [], []
    for f, a in enumerate(uv_matrices):
        if a is None:
            uv.append(np.full((3, 2), 0.37))
            ref.append(np.array([0.0, 0.0, 1.0]))
        else:
            uv.append(pos[f, :, :2] @ np.asarray(a, np.float64).T + 0.5)
            ref.append(plane_reference(np.asarray(a, np.float64)))
    n = len(uv_matrices)
    mesh = jaxnm.Mesh(jnp.asarray(pos.reshape(-1, 3), jnp.float32),
                      jnp.arange(3 * n, dtype=jnp.int32).reshape(n, 3),
                      jnp.asarray(np.concatenate(uv), jnp.float32),
                      jnp.asarray(np.tile([0.0, 0.0, 1.0], (3 * n, 1)), jnp.float32))
    return mesh, np.stack(ref)


def plane_reference(uv_matrix: np.ndarray) -> np.ndarray:
    """The exact perturbed normal on a z-plane with the affine uv ``uv_matrix`` (float64)."""
    gu = np.array([uv_matrix[0, 0], uv_matrix[0, 1], 0.0])
    gv = np.array([uv_matrix[1, 0], uv_matrix[1, 1], 0.0])
    s = math.sqrt(max(gu @ gu, gv @ gv))
    m = MAP_VALUE / np.linalg.norm(MAP_VALUE)
    v = gu / s * m[0] + gv / s * m[1] + np.array([0.0, 0.0, 1.0]) * m[2]
    return v / np.linalg.norm(v)


@dataclasses.dataclass
class Case:
    name: str
    scene: Scene
    # (3,) the exact perturbed normal, or (F, 3) one per face, or None: finite only
    reference: np.ndarray | None
    tolerance_deg: float | None
    note: str = ""


#: A directional and a point light (each case differentiates with respect to both).
LIGHTS = Lights(
    directional=stack_lights([DirectionalLight(jnp.array([-0.5, -0.4, 0.8]),
                                               jnp.array([1.0, 0.95, 0.9]), jnp.asarray(0.8))]),
    point=stack_lights([PointLight(jnp.array([0.6, -0.8, 1.5]), jnp.array([0.6, 0.7, 1.0]),
                                   jnp.asarray(2.0))]))


def _scene(mesh, cam, size, **kw) -> Scene:
    return Scene(mesh=mesh, camera=cam, width=size, height=size,
                 normal_map=jnp.asarray(_texels()),
                 normal_map_options=NormalMapOptions(filter="nearest"),
                 albedo=np.array([0.8, 0.7, 0.6], np.float32), lights=LIGHTS,
                 source="<hard case>", **kw).replace()


def _look(eye, target, up=(0, 1, 0), fov=50.0, near=0.1, far=100.0) -> Camera:
    return Camera.from_matrices(look_at(eye, target, up), perspective(fov, 1.0, near, far))


def cases(size: int = 64) -> list[Case]:
    out = []
    mesh, a = plane()
    ref = plane_reference(a)
    for deg in (85.0, 89.0, 89.9, 89.99):  # angle between the view and the normal
        r = math.radians(deg)
        eye = (0.0, -3.0 * math.sin(r), 3.0 * math.cos(r))
        big, _ = plane(size=200.0, uv_matrix=a, uv_offset=(0.5, 0.5))
        out.append(Case(f"grazing view {deg} deg", _scene(big, _look(eye, (0, 0, 0), (0, 0, 1),
                                                                       fov=20.0), size),
                        ref, TOLERANCE))
    for h in (1e-2, 1e-4):  # extreme close-up: the camera h above the surface
        cam = _look((0.1, 0.05, h), (0.1, 0.05, 0.0), fov=60.0, near=h * 0.1, far=10.0)
        out.append(Case(f"close-up {h:g} above the surface", _scene(mesh, cam, size), ref,
                        TOLERANCE))
    # quads straddling uv charts: the right half mirrored and shifted, every triangle its own
    # chart boundary; and one triangle of zero uv area amid regular ones
    grid, _ = plane(segments=4)
    right = np.asarray(grid.positions)[np.asarray(grid.faces)].mean(1)[:, 0] > 0
    nf = len(right)
    charts = [np.array([[-0.5, 0.0], [0.0, 0.5]]) if r else a for r in right]
    m5, ref5 = chart_plane(charts)
    out.append(Case("quads straddling uv charts (mirrored half)",
                    _scene(m5, _look((0.3, -0.2, 2.5), (0, 0, 0)), size), ref5, TOLERANCE))
    degenerate = [a] * nf
    degenerate[nf // 2 + 1] = None
    m6, ref6 = chart_plane(degenerate)
    out.append(Case("one triangle of zero uv area", _scene(m6, _look((0.3, -0.2, 2.5), (0, 0, 0)),
                                                           size),
                    ref6, TOLERANCE, "that triangle falls back to the unperturbed normal"))
    # half precision (GLSL mediump) close up: fine differences of rounded uv values are the
    # noise Schüler's readers report (test_shader_precision.py measures it); his advice,
    # derivatives of full-precision values (here: the exact ones, rounded), removes it
    cam = _look((0.1, 0.05, 1e-2), (0.1, 0.05, 0.0), fov=60.0, near=1e-3, far=10.0)
    out.append(Case("close-up 1e-2 in float16, derivatives rounded, not differenced",
                    _scene(mesh, cam, size, precision="float16", derivatives="analytic"),
                    ref, 0.1, "float16 fine differences: 21 deg mean here"))
    sheared = np.array([[0.5, 0.5 * math.tan(math.radians(80))], [0.0, 0.5]])
    m2, _ = plane(uv_matrix=sheared, uv_offset=(0.0, 0.0))
    out.append(Case("uv sheared 80 deg", _scene(m2, _look((0.3, -0.2, 2.5), (0, 0, 0)), size),
                    plane_reference(sheared), TOLERANCE))
    mirrored = np.array([[-0.5, 0.0], [0.0, 0.5]])
    m3, _ = plane(uv_matrix=mirrored)
    out.append(Case("uv mirrored", _scene(m3, _look((0.3, -0.2, 2.5), (0, 0, 0)), size),
                    plane_reference(mirrored), TOLERANCE))
    stretched = np.array([[0.5, 0.0], [0.0, 0.5e-3]])  # 1000:1
    m4, _ = plane(uv_matrix=stretched)
    out.append(Case("uv stretched 1000:1", _scene(m4, _look((0.3, -0.2, 2.5), (0, 0, 0)), size),
                    plane_reference(stretched), TOLERANCE))
    tiny, _ = plane(segments=160, uv_matrix=a)  # triangles of about 0.1 pixel
    out.append(Case("sub-pixel triangles", _scene(tiny, _look((0.0, 0.0, 30.0), (0, 0, 0),
                                                               fov=8.0), size), ref, TOLERANCE))
    cross, _ = plane(size=40.0, uv_matrix=a)  # reaches behind the camera
    out.append(Case("triangles crossing the near plane",
                    _scene(cross, _look((0.0, -0.5, 0.3), (0.0, 3.0, 0.0), (0, 0, 1)), size),
                    ref, TOLERANCE))
    # finite only: degenerate uvs, silhouettes, a camera inside a closed mesh
    deg, _ = plane(uv_matrix=np.zeros((2, 2)), uv_offset=(0.3, 0.6))
    out.append(Case("constant uv (no frame)", _scene(deg, _look((0.3, -0.2, 2.5), (0, 0, 0)),
                                                     size),
                    np.array([0.0, 0.0, 1.0]), 1e-3, "falls back to the unperturbed normal"))
    sphere = jaxnm.procedural.uv_sphere(1.0, 24, 12)
    out.append(Case("silhouettes (sphere)", _scene(sphere, _look((0.0, -3.0, 0.5), (0, 0, 0),
                                                                   (0, 0, 1)), size),
                    None, None, "finite values and gradients"))
    # the silhouettes' tessellation: the same program shapes, compiled once (a test runs
    # every case)
    box = jaxnm.procedural.uv_sphere(3.0, 24, 12)
    out.append(Case("camera inside a closed mesh", _scene(box, _look((0.2, 0.1, 0.0),
                                                                      (1.0, 0.5, 0.3)), size,
                                                          double_sided=True),
                    None, None, "finite values and gradients"))
    return out


def run_case(case: Case) -> dict:
    scene = case.scene
    out = jaxnm.render(scene, outputs=("color", "perturbed_normal", "mask", "tangent",
                                       "bitangent", "dpdx", "duvdy", "triangle_id"))
    mask = np.asarray(out["mask"])[..., 0] > 0
    finite = all(bool(np.isfinite(np.asarray(v)).all()) for v in out.values())
    rec = {"case": case.name, "covered_pixels": int(mask.sum()), "finite_outputs": finite,
           "note": case.note}
    if case.reference is not None and mask.any():
        n = np.asarray(out["perturbed_normal"], np.float64)[mask]
        ref = np.asarray(case.reference, np.float64)
        if ref.ndim == 2:  # one reference per face
            ref = ref[np.asarray(out["triangle_id"])[..., 0][mask].astype(int)]
        ref = np.broadcast_to(ref, n.shape)
        ang = np.degrees(np.arctan2(np.linalg.norm(np.cross(n, ref), axis=-1),
                                    np.sum(n * ref, -1)))
        rec.update(worst_deg=float(ang.max()), mean_deg=float(ang.mean()),
                   tolerance_deg=case.tolerance_deg)

    def loss(nm, positions, cam, lights):
        sc = scene.replace(normal_map=nm, mesh=dataclasses.replace(scene.mesh,
                                                                   positions=positions),
                           camera=cam, lights=lights)
        return jnp.sum(jaxnm.render(sc)["color"] * jnp.linspace(0.5, 1.5, 3)[None, None])

    grads = jax.grad(loss, argnums=(0, 1, 2, 3))(jnp.asarray(scene.normal_map),
                                                 scene.mesh.positions, scene.camera,
                                                 scene.lights)
    rec["finite_gradients"] = all(bool(np.isfinite(np.asarray(g)).all())
                                  for g in jax.tree_util.tree_leaves(grads))
    ok = finite and rec["finite_gradients"] and rec["covered_pixels"] > 0
    if "worst_deg" in rec:
        ok &= rec["worst_deg"] <= case.tolerance_deg
    rec["pass"] = bool(ok)
    rec["image"] = np.asarray(jaxnm.shading.to_display(out["color"]))
    return rec


def _contact_sheet(rows: list[dict], images: list[np.ndarray], path: Path) -> None:
    """Every case's shaded image with its name and worst error, in one figure."""
    try:
        from matplotlib.figure import Figure
    except ImportError:
        print("matplotlib missing: no cases.png (pip install '.[notebook]')")
        return
    cols = 6
    rows_n = -(-len(images) // cols)
    fig = Figure(figsize=(1.9 * cols, 2.25 * rows_n), dpi=100)
    for k, ax in enumerate(fig.subplots(rows_n, cols).ravel()):
        ax.set_axis_off()
        if k >= len(images):
            continue
        ax.imshow(images[k], interpolation="nearest")
        r = rows[k]
        worst = f"worst {r['worst_deg']:.1g} deg" if "worst_deg" in r else "finite"
        name = r["case"] if len(r["case"]) <= 30 else r["case"][:28] + "..."
        ax.set_title(f"{name}\n{worst}", fontsize=6.5)
    fig.tight_layout()
    fig.savefig(path)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="hard_cases_out")
    ap.add_argument("--size", type=int, default=64)
    args = ap.parse_args(argv)
    output("--out", args.out, folder=True)  # before the work
    if args.size < 1:
        raise ValueError(f"--size must be a positive number of pixels, got {args.size}")
    from jaxnm.io import save_png

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    rows, images = [], []
    for k, case in enumerate(cases(args.size)):
        rec = run_case(case)
        images.append(rec["image"])
        save_png(out / f"case_{k:02d}.png", rec.pop("image"))
        rec["image"] = f"case_{k:02d}.png"
        rows.append(rec)
        print(json.dumps(rec), flush=True)
    (out / "hard_cases.json").write_text(json.dumps(rows, indent=1) + "\n")
    md = ["| case | worst error (deg) | tolerance (deg) | finite values / gradients | pass | "
          "image |", "|---|---|---|---|---|---|"]
    for r in rows:
        worst = f"{r['worst_deg']:.4f}" if "worst_deg" in r else "-"
        tol = f"{r['tolerance_deg']:g}" if r.get("tolerance_deg") is not None else "-"
        md.append(f"| {r['case']} | {worst} | {tol} | {r['finite_outputs']} / "
                  f"{r['finite_gradients']} | {'yes' if r['pass'] else 'NO'} | {r['image']} |")
    (out / "hard_cases.md").write_text("\n".join(md) + "\n")
    _contact_sheet(rows, images, out / "cases.png")
    print("\n".join(md))
    return 0 if all(r["pass"] for r in rows) else 1


if __name__ == "__main__":
    sys.exit(run_script(main))
