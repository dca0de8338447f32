"""Rasterizer benchmark: visibility and full G-buffer time for 4k/20k/200k triangles.

Prints one JSON object per (mesh, resolution) line and a final JSON summary:

    python scripts/bench_raster.py [--repeats 15] [--sizes 512 1024] [--tris 4k 20k 200k]
    python scripts/bench_raster.py --scans   # jaxnm.numerics' running sums against jnp's

Reported per case: median and min wall time (ms) of ``rasterize`` (visibility:
triangle ids + depth; also with back-face culling), of the G-buffer (rasterize +
interpolate p, uv, N with fine derivatives), Mpix/s, compile time (s), XLA temp buffer size of the
visibility program (MB), and the process's peak RSS (MB) after the case.
"""

from __future__ import annotations

import argparse
import json
import resource
import statistics
import time

import jax
import jax.numpy as jnp

import jaxnm
from jaxnm import procedural

MESHES = {"4k": (64, 32), "20k": (160, 64), "200k": (500, 200)}


def _time(fn, repeats):
    out = fn()
    jax.block_until_ready(out)
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(fn())
        times.append(time.perf_counter() - t0)
    return statistics.median(times) * 1e3, min(times) * 1e3


def bench_case(tris: str, size: int, repeats: int) -> dict:
    major, minor = MESHES[tris]
    mesh = procedural.torus(1.0, 0.4, major, minor)
    cam = jaxnm.Camera.look_at((0.0, -2.2, 1.6), (0.0, 0.0, 0.0), (0.0, 0.0, 1.0),
                               fov_y_deg=50.0)
    clip = jax.block_until_ready(jaxnm.to_clip(mesh.positions, cam))
    faces = mesh.faces
    kw = dict(width=size, height=size)

    t0 = time.perf_counter()
    compiled = jax.jit(lambda c, f: jaxnm.rasterize(c, f, **kw).triangle_id).lower(
        clip, faces).compile()
    compile_s = time.perf_counter() - t0
    mem = compiled.memory_analysis()
    temp_mb = getattr(mem, "temp_size_in_bytes", 0) / 2**20 if mem is not None else None

    def vis():
        return jaxnm.rasterize(clip, faces, **kw).triangle_id

    def vis_culled():
        return jaxnm.rasterize(clip, faces, cull_back=True, **kw).triangle_id

    attrs = {"p": mesh.positions, "uv": mesh.uv, "n": mesh.normals}

    @jax.jit
    def gbuffer(clip, faces):
        fr = jaxnm.rasterize(clip, faces, **kw)
        return jaxnm.interpolate(attrs, fr, derivatives="fine")

    vis_med, vis_min = _time(vis, repeats)
    cull_med, _ = _time(vis_culled, repeats)
    gb_med, gb_min = _time(lambda: gbuffer(clip, faces), repeats)
    fr = jaxnm.rasterize(clip, faces, **kw)
    return {
        "mesh": tris,
        "triangles": int(faces.shape[0]),
        "size": size,
        "covered_fraction": round(float(jnp.mean(fr.mask)), 3),
        "visibility_ms_median": round(vis_med, 2),
        "visibility_ms_min": round(vis_min, 2),
        "visibility_cull_back_ms_median": round(cull_med, 2),
        "gbuffer_ms_median": round(gb_med, 2),
        "gbuffer_ms_min": round(gb_min, 2),
        "visibility_mpix_per_s": round(size * size / vis_med / 1e3, 1),
        "compile_s": round(compile_s, 2),
        "xla_temp_mb": None if temp_mb is None else round(temp_mb, 1),
        "peak_rss_mb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1),
    }


def bench_scans(repeats: int) -> list[dict]:
    """`jaxnm.numerics.cumsum` / `flat_nonzero` against `jnp.cumsum` / `jnp.nonzero` on the
    sizes the rasterizer scans: an image's pixels (512^2, 1024^2), a mesh's triangles (200k), a
    round of slots (2^15); a fifth of the entries set."""
    import numpy as np

    from jaxnm.numerics import cumsum, flat_nonzero

    rows = []
    for n in (512 * 512, 1024 * 1024, 200_000, 1 << 15):
        mask = jnp.asarray(np.random.default_rng(n).random(n) < 0.2)
        x = mask.astype(jnp.int32)
        size = n // 4
        pairs = {
            "cumsum": (jax.jit(jnp.cumsum), jax.jit(cumsum), (x,)),
            "nonzero": (jax.jit(lambda m: jnp.nonzero(m, size=size, fill_value=n)[0]),
                        jax.jit(lambda m: flat_nonzero(m, size, n)), (mask,)),
        }
        for name, (ref, ours, a) in pairs.items():
            assert bool((ref(*a) == ours(*a)).all()), name
            t_ref, t_ours = _time(lambda: ref(*a), repeats)[0], _time(lambda: ours(*a), repeats)[0]
            rows.append({"scan": name, "n": n, "jnp_ms": round(t_ref, 3),
                         "jaxnm_ms": round(t_ours, 3), "ratio": round(t_ref / t_ours, 2)})
    return rows


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=15)
    ap.add_argument("--sizes", type=int, nargs="+", default=[512, 1024])
    ap.add_argument("--tris", nargs="+", default=list(MESHES), choices=list(MESHES))
    ap.add_argument("--scans", action="store_true",
                    help="time the running sums (cumsum, nonzero) instead")
    args = ap.parse_args(argv)
    if args.scans:
        rows = bench_scans(max(args.repeats, 50))
        for r in rows:
            print(json.dumps(r))
        print(json.dumps({"machine": _machine(), "results": rows}))
        return
    results = []
    for tris in args.tris:
        for size in args.sizes:
            r = bench_case(tris, size, args.repeats)
            print(json.dumps(r), flush=True)
            results.append(r)
    print(json.dumps({"machine": _machine(), "results": results}))


def _machine() -> dict:
    import os
    import platform

    return {"cpu_count": os.cpu_count(), "platform": platform.platform(),
            "jax": jax.__version__, "backend": jax.default_backend()}


if __name__ == "__main__":
    main()
