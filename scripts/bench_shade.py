"""Frame-method benchmark: render speed and perturbed-normal error for every frame method.

    python scripts/bench_shade.py [--size 512] [--repeats 5] [--derivatives fine [analytic]]
                                  [--frames cotangent exact ...] [--no-positions]

On the built-in default scene (`jaxnm.procedural.default_scene`: the rivet-mapped
torus, 16384 triangles, 256 x 256 trilinear normal map, one directional and one
point light, Blinn-Phong) at ``--size`` x ``--size``, for each frame method in
`jaxnm.frames.FRAMES` and each ``--derivatives`` mode it measures

- ``forward_ms``: the full render of ``color`` (`build_gbuffer` + `shade_gbuffer`
  jitted together into one program);
- ``shade_ms``: `shade_gbuffer` alone on a precomputed G-buffer (the forward
  pass of a normal-map fit, which builds the G-buffer once);
- ``grad_texels_ms``: forward + backward of a scalar loss of the colour image
  w.r.t. the normal-map texels, G-buffer fixed (one normal-map fit step);
- ``grad_positions_ms``: forward + backward of the same loss w.r.t. the mesh's
  vertex positions through the whole pipeline (visibility is piecewise
  constant, so this is the gradient of interpolation, derivatives, frame and
  shading);
- ``compile_s``: the XLA compile time of each of these programs (measured once,
  separately from the timings).

Timings are the median (and min) of ``--repeats`` runs after one warm-up run,
each ended with ``block_until_ready``. The loss is
``mean((color - 0.5)^2)`` over the image.

**Error.** The default torus (radii R = 1, r = 0.42) has ``u = 3 phi / 2 pi`` and
``v = theta / 2 pi``, so its exact per-point cotangent frame is known in closed form:

    grad u = 3 / (2 pi (R + r cos theta)) e_phi,   grad v = 1 / (2 pi r) e_theta,
    N = (cos theta cos phi, cos theta sin phi, sin theta),

with ``e_phi = (-sin phi, cos phi, 0)`` and ``e_theta = (-sin theta cos phi,
-sin theta sin phi, cos theta)``. Per pixel, (phi, theta) are taken from the
pixel's interpolated uv (where the map is sampled), and two reference perturbed
normals are built with the *same* sampled and decoded map value as the method
(the texture sample plan depends only on uv and its derivatives, not on the
frame):

- ``ref_cot``: ``T, B = (grad u, grad v) / max(|grad u|, |grad v|)``,
  Schüler's max-normalisation of the exact smooth-surface gradients: what
  ``cotangent`` converges to under refinement. ``|T| != |B|`` here
  (``|grad u| / |grad v|`` runs from 0.89 to 2.17 on this torus), so the
  map's bumps are stretched with the uv density.
- ``ref_unit``: ``T = normalize(grad u)``, ``B = normalize(grad v)``, the
  orthonormal frame a per-vertex (MikkTSpace-like) tangent frame converges to.

Reported per method: mean and 95th-percentile angle (degrees) between the
method's perturbed normal and each reference, over front-facing covered pixels
(``base_normal_*`` is the angle between the interpolated vertex normal and the
analytic N: the floor that tessellation alone gives). ``none`` (no map) shows
the size of the map's perturbation itself.

Prints one JSON line per (method, derivatives) and a final JSON summary with
the machine's CPU count, platform, JAX version and the load average at the start
and end (other processes on a small machine make the timings noisy: compare
methods within one run, and rerun when the load is not ~0).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import platform
import resource
import statistics
import time

import jax
import jax.numpy as jnp
import numpy as np

from jaxnm import frames as _frames
from jaxnm.frames import FRAMES
from jaxnm.geometry import Mesh
from jaxnm.interpolate import DERIVATIVE_MODES as DERIVATIVES
from jaxnm.numerics import angle_between
from jaxnm.procedural import default_scene
from jaxnm.render import RenderOptions, build_gbuffer, perturbed_normal, shade_gbuffer

#: The default torus's parametrisation (`jaxnm.procedural.default_torus`); checked at start-up.
MAJOR, MINOR, U_SCALE, V_SCALE = 1.0, 0.42, 3.0, 1.0


# --------------------------------------------------------------------------------------
# timing
# --------------------------------------------------------------------------------------


def _compile(fn, *args):
    t0 = time.perf_counter()
    compiled = jax.jit(fn).lower(*args).compile()
    return compiled, time.perf_counter() - t0


def _time(fn, args, repeats: int) -> tuple[float, float]:
    jax.block_until_ready(fn(*args))  # warm-up
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(fn(*args))
        times.append(time.perf_counter() - t0)
    return statistics.median(times) * 1e3, min(times) * 1e3


def bench_timing(scene, opts: RenderOptions, repeats: int, positions: bool) -> dict:
    """Forward, shade-only, and forward+backward (texels; positions) times, compile times."""
    nm = jnp.asarray(scene.normal_map)
    albedo = jnp.asarray(scene.albedo)
    mesh, cam, lights, mat = scene.mesh, scene.camera, scene.lights, scene.material

    def color(pos, texels):
        m = Mesh(pos, mesh.faces, mesh.uv, mesh.normals)
        gb = build_gbuffer(m, cam, albedo, opts=opts)
        return shade_gbuffer(gb, texels, lights, mat, opts=opts)["color"]

    def shade_only(gb, texels):
        return shade_gbuffer(gb, texels, lights, mat, opts=opts)["color"]

    def loss_texels(texels, gb):
        return jnp.mean(jnp.square(shade_only(gb, texels) - 0.5))

    def loss_positions(pos):
        return jnp.mean(jnp.square(color(pos, nm) - 0.5))

    out = {}
    fwd, out["compile_forward_s"] = _compile(color, mesh.positions, nm)
    out["forward_ms"], out["forward_ms_min"] = _time(fwd, (mesh.positions, nm), repeats)

    gb = jax.block_until_ready(build_gbuffer(mesh, cam, albedo, opts=opts))
    shd, out["compile_shade_s"] = _compile(shade_only, gb, nm)
    out["shade_ms"], out["shade_ms_min"] = _time(shd, (gb, nm), repeats)

    gt, out["compile_grad_texels_s"] = _compile(jax.value_and_grad(loss_texels), nm, gb)
    out["grad_texels_ms"], out["grad_texels_ms_min"] = _time(gt, (nm, gb), repeats)
    _, g = gt(nm, gb)
    out["grad_texels_finite"] = bool(jnp.all(jnp.isfinite(g)))
    out["grad_texels_nonzero"] = int(jnp.sum(g != 0))

    if positions:
        gp, out["compile_grad_positions_s"] = _compile(jax.value_and_grad(loss_positions),
                                                       mesh.positions)
        out["grad_positions_ms"], out["grad_positions_ms_min"] = _time(
            gp, (mesh.positions,), repeats)
        _, g = gp(mesh.positions)
        out["grad_positions_finite"] = bool(jnp.all(jnp.isfinite(g)))
    return {k: round(v, 3) if isinstance(v, float) else v for k, v in out.items()}


# --------------------------------------------------------------------------------------
# error against the analytic torus frame
# --------------------------------------------------------------------------------------


def check_torus(mesh: Mesh) -> float:
    """Max distance between the mesh's vertices and the analytic torus at their uvs."""
    uv = np.asarray(mesh.uv, np.float64)
    phi, theta = 2 * np.pi * uv[:, 0] / U_SCALE, 2 * np.pi * uv[:, 1] / V_SCALE
    ring = MAJOR + MINOR * np.cos(theta)
    p = np.stack([ring * np.cos(phi), ring * np.sin(phi), MINOR * np.sin(theta)], -1)
    return float(np.max(np.linalg.norm(p - np.asarray(mesh.positions, np.float64), axis=-1)))


def analytic_frames(uv: jax.Array) -> tuple[_frames.Frame, _frames.Frame]:
    """(max-normalised, unit) analytic torus frames at the points with these uvs, (H, W, 3)."""
    phi = 2 * jnp.pi * uv[..., 0:1] / U_SCALE
    theta = 2 * jnp.pi * uv[..., 1:2] / V_SCALE
    cp, sp, ct, st = jnp.cos(phi), jnp.sin(phi), jnp.cos(theta), jnp.sin(theta)
    zero = jnp.zeros_like(phi)
    e_phi = jnp.concatenate([-sp, cp, zero], -1)
    e_theta = jnp.concatenate([-st * cp, -st * sp, ct], -1)
    n = jnp.concatenate([ct * cp, ct * sp, st], -1)
    gu = U_SCALE / (2 * jnp.pi * (MAJOR + MINOR * ct))  # |grad u|, (H, W, 1)
    gv = jnp.full_like(gu, V_SCALE / (2 * jnp.pi * MINOR))  # |grad v|
    s = jnp.maximum(gu, gv)
    cot = _frames.Frame(e_phi * (gu / s), e_theta * (gv / s), n)
    unit = _frames.Frame(e_phi, e_theta, n)
    return cot, unit


def _stats(deg: np.ndarray) -> tuple[float, float]:
    return round(float(np.mean(deg)), 4), round(float(np.percentile(deg, 95)), 4)


def bench_error(scene, opts: RenderOptions) -> dict:
    """Angles (degrees) between the method's perturbed normal and the analytic references."""
    eopts = dataclasses.replace(opts, outputs=("perturbed_normal",))
    nm = jnp.asarray(scene.normal_map)
    gb = build_gbuffer(scene.mesh, scene.camera, jnp.asarray(scene.albedo), opts=eopts)
    # the same G-buffer's uv (hence the same sample plan and decoded map value) for references;
    # for frame "none" no plan is built, so take it from a cotangent G-buffer
    gb_uv = gb if gb.plan is not None else build_gbuffer(
        scene.mesh, scene.camera, jnp.asarray(scene.albedo),
        opts=dataclasses.replace(eopts, frame="cotangent"))
    n_method = perturbed_normal(gb, nm, eopts)
    cot, unit = analytic_frames(gb_uv.uv.value)
    n_cot = perturbed_normal(dataclasses.replace(gb_uv, frame=cot), nm, eopts)
    n_unit = perturbed_normal(dataclasses.replace(gb_uv, frame=unit), nm, eopts)
    m = np.asarray(gb.mask & gb.front_facing)
    deg = {k: np.degrees(np.asarray(angle_between(n_method, r)))[m]
           for k, r in (("cot", n_cot), ("unit", n_unit))}
    base = np.degrees(np.asarray(angle_between(gb.normal, cot.N)))[m]
    out = {"pixels": int(m.sum()),
           "back_facing_pixels_skipped": int(np.sum(np.asarray(gb.mask & ~gb.front_facing)))}
    out["angle_vs_ref_cot_mean_deg"], out["angle_vs_ref_cot_p95_deg"] = _stats(deg["cot"])
    out["angle_vs_ref_unit_mean_deg"], out["angle_vs_ref_unit_p95_deg"] = _stats(deg["unit"])
    out["base_normal_mean_deg"], out["base_normal_p95_deg"] = _stats(base)
    return out


# --------------------------------------------------------------------------------------


def _machine() -> dict:
    return {"cpu_count": os.cpu_count(), "platform": platform.platform(),
            "python": platform.python_version(), "jax": jax.__version__,
            "jaxlib": _jaxlib_version(),
            "backend": jax.default_backend()}


def _jaxlib_version():
    try:
        import jaxlib

        return jaxlib.__version__
    except Exception:  # pragma: no cover
        return None


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=512, help="image width and height (512)")
    ap.add_argument("--repeats", type=int, default=5, help="timed runs per measurement (5)")
    ap.add_argument("--derivatives", nargs="+", default=["fine"], choices=DERIVATIVES)
    ap.add_argument("--frames", nargs="+", default=list(FRAMES), choices=FRAMES)
    ap.add_argument("--no-positions", action="store_true",
                    help="skip the gradient w.r.t. vertex positions (the slowest to compile)")
    ap.add_argument("--no-timing", action="store_true", help="errors only")
    args = ap.parse_args(argv)

    scene = default_scene(width=args.size, height=args.size)
    dev = check_torus(scene.mesh)
    if dev > 1e-5:
        raise SystemExit(f"bench_shade: the default torus no longer matches the analytic "
                         f"parametrisation (max deviation {dev:.3g}); update MAJOR/MINOR/U_SCALE")
    t_start = time.perf_counter()
    load_start = os.getloadavg()
    results = []
    for deriv in args.derivatives:
        for frame in args.frames:
            opts = RenderOptions.of(scene, outputs=("color",), derivatives=deriv, frame=frame)
            r = {"frame": frame, "derivatives": deriv, "size": args.size}
            r.update(bench_error(scene, opts))
            if not args.no_timing:
                r.update(bench_timing(scene, opts, args.repeats, not args.no_positions))
            r["peak_rss_mb"] = round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1)
            print(json.dumps(r), flush=True)
            results.append(r)
    keys = ("forward_ms", "shade_ms", "grad_texels_ms", "grad_positions_ms",
            "compile_forward_s", "compile_grad_texels_s", "compile_grad_positions_s",
            "angle_vs_ref_cot_mean_deg", "angle_vs_ref_cot_p95_deg",
            "angle_vs_ref_unit_mean_deg", "angle_vs_ref_unit_p95_deg")
    table = [{"frame": r["frame"], "derivatives": r["derivatives"],
              **{k: r[k] for k in keys if k in r}} for r in results]
    print(json.dumps({
        "machine": _machine(), "scene": "default_scene (torus, 16384 triangles, 256^2 map)",
        "size": args.size, "repeats": args.repeats, "statistic": "median after 1 warm-up",
        "triangles": int(scene.mesh.num_faces), "wall_s": round(time.perf_counter() - t_start, 1),
        "load_avg_1_5_15_start": [round(x, 2) for x in load_start],
        "load_avg_1_5_15_end": [round(x, 2) for x in os.getloadavg()],
        "table": table}))


if __name__ == "__main__":
    main()
