"""The Mitsuba 3 side of the side-by-side benchmark (the problem is defined in
`scripts.benchmarks.bench_problem`'s docstring).

    python -m scripts.benchmarks.bench_mitsuba   # is Mitsuba usable here? a small render and fit

Plain functions, NumPy in and out, on the `bench_problem.BenchProblem` that jaxnm's side
uses too. Mitsuba is imported lazily, so this module imports without it:

- `available()`: whether Mitsuba 3 (``llvm_ad_rgb``) runs here, and why not.
- `render(problem, texels, light_dir)`: one image.
- `forward_calls(problem)`: the forward, forward + backward and moved-mesh forward calls
  to time;
  `forward_times(problem)`: their timings.
- `fit(problem, budget_s=...)`: the benchmark's Adam fit of the map.

**Setup** (``pip install -e '.[bench]'``, i.e. ``mitsuba==3.9.1 drjit==1.5.0``): Dr.Jit's
LLVM backend loads the system's LLVM shared library (>= 15) from ``DRJIT_LIBLLVM_PATH``.
If that is unset, this module sets it, before Mitsuba is imported, to the newest
``libLLVM`` it finds in the usual places (Debian: ``apt-get install libllvm19``). LLVM 15
aborted the process here ("LLVM ERROR: Cannot select ... fminimum", or fmaximum) on the
first render kernel, so `available()` tries a tiny render in a subprocess before saying yes.

**The scene** (matching jaxnm's conventions, checked against ``jaxnm.render``):

- the mesh is a ``mi.Mesh`` built from the problem's arrays (positions, faces, vertex
  normals, uv as ``vertex_texcoords``). Mitsuba's bitmap lookup puts image row 0 at
  uv ``v = 0``, while the problem's texel row 0 is at ``v = 1``: the mesh gets the
  texture coordinates ``(u, 1 - v)``, so the texel array is used as is. This leaves
  ``dp/du`` (hence Mitsuba's tangent frame) unchanged;
- ``normalmap`` BSDF (raw bitmap, bilinear, repeat) over ``diffuse`` (albedo 0.8). Its
  tangent frame is ``s = normalize(dp/du - n (n . dp/du))`` (``dp/du`` per triangle,
  ``n`` the interpolated vertex normal), ``t = n x s``: orthonormal, +x along +u, +y
  along +v on a right-handed parameterisation (the torus is one). jaxnm's default
  per-pixel cotangent frame is not orthonormal: its ``T, B`` are the gradients of
  ``u, v`` scaled together so the longer has unit length; on the torus that is
  ``B`` (``|dp/dv| = 2 pi r`` is the shorter), so jaxnm tilts the normal less along u
  than Mitsuba does, by ``|dp/dv| / |dp/du| = r / (R + r cos v)`` (0.29 to 0.67);
- ``flip_invalid_normals=False`` and ``use_shadowing_function=False`` (Mitsuba's defaults
  are ``True``: the shadowing term dims tilted normals, by 1 % at a 30 deg tilt under a
  45 deg light and more at grazing light, and perturbed normals that face away from
  the viewer get their x, y mirrored). Radiance is then the benchmark's
  ``0.8 max(0, n' . l)``, except that Mitsuba returns 0 where the light is below the
  interpolated normal or the perturbed normal faces away from the viewer (jaxnm shades
  those pixels);
- one ``directional`` emitter with ``direction = -light_dir`` (the direction the light
  travels) and irradiance pi;
- ``direct`` integrator, 1 emitter sample, 0 BSDF samples: unlike jaxnm it traces
  shadow rays, so the torus shadows itself under grazing lights (the fourth
  benchmark light, from below the view, darkens a fifth of the torus's pixels);
- pinhole ``perspective`` sensor (``look_at``, vertical fov), ``hdrfilm`` with a
  ``box`` filter, ``stratified`` sampler with 1 sample and no jitter: one sample at
  each pixel centre; image row 0 is the top.

**The trap** (Mitsuba 3.9 / Dr.Jit 1.5, measured with this module's scenes): with the
``direct`` integrator, one ``dr.backward`` on a loss summed over several ``mi.render``
calls delivers only the last render's gradient; the others' are exactly zero, whether
the renders share one scene (light changed in between) or use four scenes, one leaf or
one leaf per scene. `fit` and `forward_times` take one ``dr.backward`` per render, right
after it, on a fresh leaf copy of the map, and sum the copies' gradients.
"""

from __future__ import annotations

import glob
import importlib.util
import json
import math
import os
import re
import statistics
import subprocess
import sys
import time
import types
from pathlib import Path

import numpy as np

from scripts.benchmarks import timing
from scripts.benchmarks.bench_problem import MOVED_OFFSET

MITSUBA_VERSION = "3.9.1"
DRJIT_VERSION = "1.5.0"
VARIANT = "llvm_ad_rgb"
#: Mitsuba's defaults are True; off, the radiance is the benchmark's 0.8 max(0, n'.l)
FLIP_INVALID_NORMALS = False
USE_SHADOWING_FUNCTION = False
INSTALL_HINT = ("pip install -e '.[bench]' (mitsuba==3.9.1 drjit==1.5.0) and a system libLLVM "
                ">= 15 (Debian: apt-get install libllvm19), found via DRJIT_LIBLLVM_PATH")

_LLVM_GLOBS = (
    "/usr/lib/x86_64-linux-gnu/libLLVM*.so*", "/usr/lib/aarch64-linux-gnu/libLLVM*.so*",
    "/usr/lib/llvm-*/lib/libLLVM*.so*", "/usr/lib64/libLLVM*.so*", "/usr/lib/libLLVM*.so*",
    "/usr/local/lib/libLLVM*.so*", "/opt/homebrew/opt/llvm/lib/libLLVM.dylib",
    "/usr/local/opt/llvm/lib/libLLVM.dylib",
)
_state: dict = {}


# --------------------------------------------------------------------------------------
# setup
# --------------------------------------------------------------------------------------


def _llvm_major(path: str) -> int | None:
    m = re.search(r"libLLVM[-.](?:so\.)?(\d+)", os.path.basename(path))
    if m is None:
        m = re.search(r"llvm-(\d+)", path)
    return int(m.group(1)) if m else None


def llvm_candidates() -> list[str]:
    """Existing ``libLLVM`` shared libraries, newest major version first (>= 15, which
    Dr.Jit needs; unversioned names last)."""
    seen, found = set(), []
    for pattern in _LLVM_GLOBS:
        for path in sorted(glob.glob(pattern)):
            real = os.path.realpath(path)
            major = _llvm_major(path)
            if real in seen or not os.path.isfile(real) or (major is not None and major < 15):
                continue
            seen.add(real)
            found.append((-(major or 0), path))
    return [path for _, path in sorted(found, key=lambda x: x[0])]


def configure_llvm() -> str | None:
    """Set ``DRJIT_LIBLLVM_PATH`` (if unset) to the first candidate; return the path used."""
    path = os.environ.get("DRJIT_LIBLLVM_PATH")
    if not path:
        candidates = llvm_candidates()
        if candidates:
            path = os.environ["DRJIT_LIBLLVM_PATH"] = candidates[0]
    return path or None


def _mitsuba():
    """``(mi, dr)`` with the ``llvm_ad_rgb`` variant set (imported on first use)."""
    if "mi" not in _state:
        configure_llvm()
        import drjit as dr
        import mitsuba as mi

        mi.set_variant(VARIANT)
        _state.update(mi=mi, dr=dr)
    return _state["mi"], _state["dr"]


def _versions() -> str:
    mi, dr = _mitsuba()
    return (f"mitsuba {mi.__version__}, drjit {dr.__version__}, "
            f"LLVM {os.environ.get('DRJIT_LIBLLVM_PATH')}")


def _probe() -> None:
    """Render a tiny normal-mapped quad and differentiate it (run in a subprocess by
    `available`: a bad LLVM aborts the process rather than raising)."""
    mi, dr = _mitsuba()
    quad = types.SimpleNamespace(
        positions=np.array([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]], np.float64),
        faces=np.array([[0, 1, 2], [0, 2, 3]]), uv=np.array([[0, 0], [1, 0], [1, 1], [0, 1]],
                                                              np.float64),
        normals=np.tile([0.0, 0.0, 1.0], (4, 1)), eye=(0.0, -1.0, 3.0), target=(0.0, 0.0, 0.0),
        up=(0.0, 0.0, 1.0), fov_y_deg=45.0, width=8, height=8, albedo=0.8)
    texels = np.full((4, 4, 3), 0.5, np.float32)
    texels[..., 2] = 1.0
    sc, params, key = _scene(quad, texels, (0.3, -0.2, 0.9))
    leaf = _leaf(params[key])
    params[key] = leaf
    params.update()
    img = mi.render(sc, params, spp=1)
    dr.backward(dr.mean(img, axis=None))
    g = np.asarray(dr.grad(leaf))
    assert np.isfinite(np.asarray(img)).all() and np.any(g != 0)
    print(_versions())


def available() -> tuple[bool, str]:
    """``(True, "mitsuba 3.9.1, drjit 1.5.0, LLVM <path>")``, or ``(False, reason)`` where
    the reason says how to install. Runs a tiny render in a subprocess (a second or two,
    once per process)."""
    if "available" in _state:
        return _state["available"]
    missing = [m for m in ("mitsuba", "drjit") if importlib.util.find_spec(m) is None]
    path = configure_llvm()
    if missing:
        res = (False, f"{' and '.join(missing)} not installed: {INSTALL_HINT}")
    elif path is None:
        res = (False, f"no libLLVM >= 15 found and DRJIT_LIBLLVM_PATH unset: {INSTALL_HINT}")
    else:
        code = "from scripts.benchmarks import bench_mitsuba as b; b._probe()"
        try:
            r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                               timeout=300, cwd=Path(__file__).resolve().parents[2],
                               env=dict(os.environ, DRJIT_LIBLLVM_PATH=path))
            ok, out = r.returncode == 0, (r.stdout + r.stderr).strip()
        except subprocess.TimeoutExpired:
            ok, out = False, "timed out"
        if ok:
            res = (True, out.splitlines()[-1])
        else:
            lines = [ln for ln in out.splitlines() if ln.strip()]
            # Dr.Jit's own diagnosis comes first; the Python error is the last line
            why = next((ln for ln in lines if re.match(r"(LLVM ERROR|jitc?_\w+\(\))", ln)),
                       lines[-1] if lines else "")
            res = (False, f"a test render with LLVM {path} failed (exit {r.returncode}: "
                          f"{why.strip()[:200]}): {INSTALL_HINT}")
    _state["available"] = res
    return res


# --------------------------------------------------------------------------------------
# the scene
# --------------------------------------------------------------------------------------


def _mesh(p, bsdf):
    mi, _ = _mitsuba()
    props = mi.Properties()
    props["bsdf"] = bsdf
    mesh = mi.Mesh("torus", len(p.positions), len(p.faces), props=props,
                   has_vertex_normals=True, has_vertex_texcoords=True)
    uv = np.stack([p.uv[:, 0], 1.0 - p.uv[:, 1]], 1)  # Mitsuba's row 0 is at v = 0
    params = mi.traverse(mesh)
    params["vertex_positions"] = mi.Float(np.asarray(p.positions, np.float32).ravel())
    params["faces"] = mi.UInt32(np.asarray(p.faces, np.uint32).ravel())
    params["vertex_normals"] = mi.Float(np.asarray(p.normals, np.float32).ravel())
    params["vertex_texcoords"] = mi.Float(np.asarray(uv, np.float32).ravel())
    params.update()
    return mesh


def _scene(p, texels, light_dir):
    """``(scene, params, key)``: the problem's scene under one light, and the key of the
    map's texels (an ``(h, w, 3)`` tensor) in ``params``."""
    mi, _ = _mitsuba()
    bsdf = mi.load_dict({
        "type": "normalmap",
        "flip_invalid_normals": FLIP_INVALID_NORMALS,
        "use_shadowing_function": USE_SHADOWING_FUNCTION,
        "normalmap": {"type": "bitmap", "raw": True, "filter_type": "bilinear",
                      "wrap_mode": "repeat",
                      "bitmap": mi.Bitmap(np.ascontiguousarray(texels, np.float32))},
        "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": [p.albedo] * 3}},
    })
    d = np.asarray(light_dir, np.float64)
    d = d / np.linalg.norm(d)
    scene = mi.load_dict({
        "type": "scene",
        "integrator": {"type": "direct", "emitter_samples": 1, "bsdf_samples": 0},
        "sensor": {
            "type": "perspective", "fov": float(p.fov_y_deg), "fov_axis": "y",
            "near_clip": 0.05, "far_clip": 50.0,
            "to_world": mi.ScalarTransform4f().look_at(
                origin=[float(x) for x in p.eye], target=[float(x) for x in p.target],
                up=[float(x) for x in p.up]),
            "sampler": {"type": "stratified", "sample_count": 1, "jitter": False},
            "film": {"type": "hdrfilm", "width": int(p.width), "height": int(p.height),
                     "rfilter": {"type": "box"}, "pixel_format": "rgb"},
        },
        "light": {"type": "directional", "direction": [float(x) for x in -d],
                  "irradiance": {"type": "rgb", "value": [math.pi] * 3}},
        "torus": _mesh(p, bsdf),
    })
    params = mi.traverse(scene)
    key = next(k for k in params.keys() if k.endswith("normalmap.data"))
    return scene, params, key


def _leaf(x):
    """A fresh, detached, evaluated copy of tensor ``x`` with gradients enabled."""
    mi, dr = _mitsuba()
    leaf = mi.TensorXf(dr.detach(x))
    dr.make_opaque(leaf)
    dr.enable_grad(leaf)
    return leaf


def _decode(texels: np.ndarray) -> np.ndarray:
    n = 2.0 * np.asarray(texels, np.float64) - 1.0
    n /= np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-12)
    return n.astype(np.float32)


def _kernel_cache_files() -> int:
    """Files in Dr.Jit's on-disk kernel cache (~/.drjit): first calls are much faster
    when a previous process compiled the same kernels."""
    return len(glob.glob(os.path.join(os.path.expanduser("~"), ".drjit", "*")))


def render(problem, texels: np.ndarray, light_dir) -> np.ndarray:
    """``(H, W, 3)`` float32 linear image of the problem's mesh with the tangent-space map
    ``texels`` (``(h, w, 3)`` encoded in [0, 1], row 0 at v = 1) under one directional
    light towards ``light_dir`` (irradiance pi, albedo ``problem.albedo``: radiance
    ``0.8 max(0, n' . l)``), 1 spp at pixel centres, ``direct`` integrator; row 0 = top."""
    mi, _ = _mitsuba()
    scene, _, _ = _scene(problem, texels, light_dir)
    return np.asarray(mi.render(scene, spp=1), np.float32)


# --------------------------------------------------------------------------------------
# timings and the fit
# --------------------------------------------------------------------------------------


def _loss_and_grad(scene, params, key, value, target):
    """One render with a fresh leaf copy of ``value`` as the map, its MSE to ``target``
    and one backward: ``(loss, d loss / d value)`` as Dr.Jit values."""
    mi, dr = _mitsuba()
    leaf = _leaf(value)
    params[key] = leaf
    params.update()
    img = mi.render(scene, params, spp=1)
    loss = dr.mean(dr.square(img - target), axis=None)
    dr.backward(loss)
    return dr.detach(loss), dr.grad(leaf)


def forward_calls(problem) -> dict:
    """The timed calls, each forcing its result to the host: ``"forward"``, one render
    (the true map, light 0); ``"forward_backward"``, forward + backward w.r.t. the map's
    texels (the flat map, loss = MSE to the render of the true map); ``"forward_moved"``,
    one render after the mesh moved (its positions alternate between two arrays, the
    second moved by ``bench_problem.MOVED_OFFSET``). All are run once here (kernel
    compilation, or a load from Dr.Jit's disk cache): their times are in ``"first_s"``,
    with the number of cached kernel files found at the start."""
    mi, dr = _mitsuba()
    cache_files = _kernel_cache_files()
    scene, params, key = _scene(problem, problem.gt_texels, problem.light_dirs[0])

    def forward():
        return np.asarray(mi.render(scene, spp=1))

    t = time.perf_counter()
    target = mi.TensorXf(forward())
    first_forward = time.perf_counter() - t
    flat = mi.TensorXf(np.asarray(problem.flat_texels, np.float32))

    def forward_backward():
        loss, g = _loss_and_grad(scene, params, key, flat, target)
        return float(loss.array[0]), np.asarray(g)

    t = time.perf_counter()
    forward_backward()
    first_backward = time.perf_counter() - t

    # A scene of its own whose mesh takes turns between two positions (the second moved by
    # bench_problem.MOVED_OFFSET along x): each frame pays for what a new mesh costs Mitsuba (its
    # acceleration structure rebuilt in `params.update()`). Both position arrays are made
    # up front, so the call times the update and the render, not a copy from NumPy.
    moved_scene, moved_params, _ = _scene(problem, problem.gt_texels, problem.light_dirs[0])
    vk = next(k for k in moved_params.keys() if k.endswith("vertex_positions"))
    xyz = np.asarray(problem.positions, np.float32)
    positions = [mi.Float(xyz.ravel()), mi.Float((xyz + [MOVED_OFFSET, 0, 0]).astype(
        np.float32).ravel())]
    turn = [0]

    def forward_moved():
        turn[0] ^= 1
        moved_params[vk] = positions[turn[0]]
        moved_params.update()
        return np.asarray(mi.render(moved_scene, spp=1))

    t = time.perf_counter()
    forward_moved()
    first_moved = time.perf_counter() - t
    return {"forward": forward, "forward_backward": forward_backward,
            "forward_moved": forward_moved,
            "first_s": {"forward": first_forward, "forward_backward": first_backward,
                        "forward_moved": first_moved},
            "kernel_cache_files_at_start": cache_files}


def forward_times(problem, *, repeats: int = 10) -> dict:
    """Median wall ms of `forward_calls`' two calls (``repeats`` each, one after the
    other, `timing.time_call`), and their first calls in s."""
    calls = forward_calls(problem)
    out = {}
    for name in ("forward", "forward_backward"):
        out[f"{name}_ms"] = timing.time_call(calls[name], repeats=repeats, first=False).median_ms
        out[f"first_{'backward' if name != 'forward' else 'forward'}_s"] = calls["first_s"][name]
    return {**out, "triangles": int(len(problem.faces)),
            "size": f"{problem.width}x{problem.height}",
            "kernel_cache_files_at_start": calls["kernel_cache_files_at_start"]}


def _project(mi, dr, texels):
    """Clip to [0, 1] and renormalise: ``c <- 0.5 normalize(2c - 1) + 0.5`` per texel."""
    c = dr.clip(dr.detach(texels), 0.0, 1.0)
    n = dr.unravel(mi.Vector3f, c.array * 2.0 - 1.0)
    n = n * dr.rsqrt(dr.maximum(dr.squared_norm(n), 1e-24))
    return mi.TensorXf(dr.ravel(n) * 0.5 + 0.5, c.shape)


def fit(problem, *, budget_s: float, lr: float = 0.01, max_steps: int = 100000,
        snapshot_every: int = 1) -> dict:
    """The benchmark's Mitsuba fit: targets are Mitsuba's renders of ``problem.gt_texels``
    under each of ``problem.light_dirs``; start from ``problem.flat_texels``; loss = sum
    over the renders of the MSE; Adam(``lr``); after each step clip to [0, 1] and
    renormalise. Steps start while less than ``budget_s`` seconds have passed since the
    start of the fit (target rendering excluded, reported as ``target_render_s``).

    **Returns:** ``history`` (``step``, ``seconds`` at the end of the step, ``loss`` as
    evaluated in that step, i.e. at the map after ``step - 1`` updates), ``snapshots``
    (``step``, ``seconds``, ``normals``: ``(h, w, 3)`` unit normals) at step 0 and every
    ``snapshot_every`` steps, ``first_step_s`` (to the end of step 1, compilation
    included), ``s_per_step`` (median of the later steps), ``target_render_s``,
    ``final_texels`` and ``kernel_cache_files_at_start``.
    """
    mi, dr = _mitsuba()
    cache_files = _kernel_cache_files()
    t = time.perf_counter()
    renders = []
    for d in problem.light_dirs:
        scene, params, key = _scene(problem, problem.gt_texels, d)
        target = mi.render(scene, spp=1)
        dr.eval(target)
        renders.append((scene, params, key, target))
    target_render_s = time.perf_counter() - t

    start = time.perf_counter()
    opt = mi.ad.Adam(lr=lr)
    opt["texels"] = mi.TensorXf(np.asarray(problem.flat_texels, np.float32))
    snapshots = [{"step": 0, "seconds": 0.0, "normals": _decode(problem.flat_texels)}]
    history, durations = [], []
    step, t_prev = 0, start
    while step < max_steps and time.perf_counter() - start < budget_s:
        step += 1
        total, grad = 0.0, None
        for scene, params, key, target in renders:  # one backward per render (the trap)
            loss, g = _loss_and_grad(scene, params, key, opt["texels"], target)
            total += float(loss.array[0])
            grad = g if grad is None else grad + g
        dr.set_grad(opt["texels"], grad)
        opt.step()
        opt["texels"] = _project(mi, dr, opt["texels"])  # keeps Adam's moments
        if step % snapshot_every == 0:
            normals = _decode(np.asarray(opt["texels"]))
        else:
            dr.eval(opt["texels"])
        now = time.perf_counter()
        durations.append(now - t_prev)
        t_prev = now
        history.append({"step": step, "seconds": now - start, "loss": total})
        if step % snapshot_every == 0:
            snapshots.append({"step": step, "seconds": now - start, "normals": normals})
    return {"history": history, "snapshots": snapshots,
            "first_step_s": durations[0] if durations else None,
            "s_per_step": statistics.median(durations[1:]) if len(durations) > 1 else None,
            "target_render_s": target_render_s,
            "final_texels": np.asarray(opt["texels"], np.float32),
            "kernel_cache_files_at_start": cache_files}


# --------------------------------------------------------------------------------------
# smoke run
# --------------------------------------------------------------------------------------


def _main() -> None:
    ok, msg = available()
    out = {"available": ok, "message": msg,
           "DRJIT_LIBLLVM_PATH": os.environ.get("DRJIT_LIBLLVM_PATH")}
    if not ok:
        print(json.dumps(out, indent=1))
        return
    from scripts.benchmarks import bench_problem as bp

    p = bp.make_problem(render_size=128, map_size=64, major=64, minor=40)
    t = time.perf_counter()
    img = render(p, p.gt_texels, p.light_dirs[0])
    out["render_128"] = {"seconds": time.perf_counter() - t, "shape": list(img.shape),
                         "mean": float(img.mean()), "lit_pixels": int((img.max(-1) > 0).sum())}
    out["forward_times_128"] = forward_times(p, repeats=5)
    res = fit(p, budget_s=5.0, snapshot_every=10)
    last = res["snapshots"][-1]
    err = bp.angle_deg(last["normals"], p.gt_normals)
    out["fit_5s"] = {
        "steps": len(res["history"]), "first_step_s": res["first_step_s"],
        "s_per_step": res["s_per_step"], "target_render_s": res["target_render_s"],
        "loss_first": res["history"][0]["loss"] if res["history"] else None,
        "loss_last": res["history"][-1]["loss"] if res["history"] else None,
        "last_snapshot": {"step": last["step"], "seconds": last["seconds"],
                          "mean_angle_deg_all_texels": float(err.mean()),
                          "median_angle_deg_all_texels": float(np.median(err))},
        "kernel_cache_files_at_start": res["kernel_cache_files_at_start"]}
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    _main()
