"""The benchmark problem that jaxnm and Mitsuba 3 both solve, as arrays: fitting a normal map
by differentiable rendering on the CPU (`scripts.benchmarks.bench` runs it).

This docstring is the problem's definition; both renderers build their scenes from the same
`BenchProblem` (`make_problem`; jaxnm's side here, Mitsuba's in
`scripts.benchmarks.bench_mitsuba`), and both run in one process run, so that their ratios
hold on a noisy machine.

**Mesh.** A torus of major radius 1 and minor radius 0.4 in the xy-plane: a (128 + 1) x
(80 + 1) vertex grid over (major angle, minor angle), seam vertices duplicated, two
triangles per cell (20,480 triangles); per-vertex normals; u = major angle / 2 pi,
v = minor angle / 2 pi.

**Camera.** A pinhole at eye (0, -4.614418608, 3.231050694) looking at the origin, up +z,
vertical field of view 45 deg, 512 x 512 pixels.

**Map.** A 256 x 256 tangent-space normal map, +x along +u, +y along +v, image row 0 at
v = 1; sampled bilinearly with repeat wrapping. The ground truth is a 512 x 512 procedural
map box-filtered 2 x 2 in its encoded values (the mean of the four texels' ``0.5 n + 0.5``).
Its heights (`procedural_height`, at texel centres) are round bumps on an 8 x 8 grid of uv
cells, ``(1 - r^2)^2`` where ``r^2 = |(8u, 8v) mod 1 - 0.5|^2 / 0.35^2 < 1``, plus a
shallow diagonal groove every quarter of the uv square, ``-0.3 exp(-(d / 0.02)^2)`` with
``d = (u - v) mod 0.25 - 0.125``; `jaxnm.maps.height_to_normal_map` turns them into
normals with scale 6 (any similar procedural map will do). The fit starts from the flat
map (0.5, 0.5, 1) everywhere.

**Lights.** Four renders, one directional light each, irradiance pi: radiance
``0.8 max(0, n' . l)`` with ``n'`` the perturbed normal (Lambert, albedo 0.8). The
direction towards light k is ``d = sin(el) (-f) + cos(el) (cos(az) r + sin(az) u)``, with
``f`` the camera's forward axis, ``r = normalize(f x up)``, ``u = r x f``, elevation
``el = 45 deg`` and azimuths ``az = 0, 90, 180, 270 deg``. A fifth, held-out light,
towards ``normalize(0.4, -0.6, 0.7)``, is used only to judge the fitted map.

**Mitsuba's side.** Variant ``llvm_ad_rgb``; the ``direct`` integrator with 1 emitter
sample and 0 BSDF samples; 1 sample per pixel at the pixel centre (``stratified`` sampler,
``sample_count`` 1, no jitter); a ``normalmap`` BSDF (raw bitmap, bilinear) over
``diffuse``. Loss: the sum over the four renders of the mean squared error to the
targets; Adam with learning rate 0.01; after each step the texels are clipped to [0, 1]
and renormalised (``c <- 0.5 normalize(2c - 1) + 0.5``). A trap in Mitsuba 3.9 /
Dr.Jit 1.5: with ``direct``, one ``dr.backward`` on a loss summed over several
``mi.render`` calls delivers only the last render's gradient; take one backward per
render on a fresh leaf copy of the map and sum the gradients (or use the ``prb``
integrator, correct and slower). Mitsuba's LLVM backend needs the system's LLVM shared
library (Debian: ``libllvm19``; ``DRJIT_LIBLLVM_PATH``).

**jaxnm's side.** The same scene (`jaxnm_scene`, Lambert shading, the bilinear repeat-wrapped
map) fitted with `jaxnm.fit.fit_normal_map` (`jaxnm_fit_problem`).

**Metric.** The angle between the fitted and the true unit normals (`angle_deg`), averaged
over two sets of texels (`texel_masks`):

- *seen*: the gradient of ``sum(render_k)`` with respect to the texel is non-zero, at the
  true map, for at least one light k;
- *well-observed*: seen by at least two lights, with the bilinear weights of the pixel
  hits summing to at least 1;

and the held-out light's PSNR (`psnr`: peak 1, the full linear image) of the render with
the fitted map against the render with the true map.

**Clock.** Wall time from the start of the fit, each renderer fitting its own renders of
the true map (target rendering excluded); compilation is reported separately *and*
included. The headline figure is the time until the mean error over the well-observed
texels falls below 1 degree.
"""

from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np

import jaxnm
from jaxnm import fit as F
from jaxnm import procedural
from jaxnm.maps import height_to_normal_map
from jaxnm.scene import Scene, back_faces_hidden
from jaxnm.shading import Material, directional_light
from jaxnm.textures import NormalMapOptions, encode_normal_map

EYE = (0.0, -4.614418608, 3.231050694)
FOV_Y_DEG = 45.0
ELEVATION_DEG = 45.0
AZIMUTHS_DEG = (0.0, 90.0, 180.0, 270.0)
HELD_OUT = (0.4, -0.6, 0.7)
ALBEDO = 0.8
#: How far the benchmark's moved-mesh frames move the mesh along x, in world units.
MOVED_OFFSET = 1e-3


@dataclasses.dataclass(frozen=True)
class BenchProblem:
    """Everything both renderers need (NumPy, float64 where it is geometry).

    - `positions` (V, 3), `faces` (F, 3), `uv` (V, 2), `normals` (V, 3): the torus.
    - `eye`, `target`, `up`, `fov_y_deg`, `width`, `height`: the pinhole camera.
    - `gt_texels` (h, w, 3): the true map's encoded values in [0, 1] (row 0 = v = 1);
      `gt_normals` (h, w, 3) its unit normals; `flat_texels` the start.
    - `light_dirs` (4, 3) unit directions towards the lights; `held_out_dir` (3,).
    - `albedo`: the Lambert albedo (radiance = albedo * max(0, n . l)).
    """

    positions: np.ndarray
    faces: np.ndarray
    uv: np.ndarray
    normals: np.ndarray
    eye: tuple
    target: tuple
    up: tuple
    fov_y_deg: float
    width: int
    height: int
    gt_texels: np.ndarray
    gt_normals: np.ndarray
    flat_texels: np.ndarray
    light_dirs: np.ndarray
    held_out_dir: np.ndarray
    albedo: float = ALBEDO


def procedural_height(size: int) -> np.ndarray:
    """(size, size) heights, image layout (row 0 = v near 1): round bumps on an 8 x 8 grid of
    uv cells plus a shallow diagonal groove; periodic in u and v."""
    t = (np.arange(size) + 0.5) / size
    u, v = np.meshgrid(t, 1.0 - t, indexing="xy")
    fu, fv = (u * 8) % 1.0 - 0.5, (v * 8) % 1.0 - 0.5
    r2 = (fu * fu + fv * fv) / 0.35**2
    bumps = np.where(r2 < 1, (1 - r2) ** 2, 0.0)
    d = (u - v) % 0.25 - 0.125  # a diagonal groove every quarter of the uv square
    groove = -0.3 * np.exp(-(d / 0.02) ** 2)
    return (bumps + groove).astype(np.float32)


def light_directions(eye, target=(0.0, 0.0, 0.0), up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """d = sin(el)(-f) + cos(el)(cos(az) r + sin(az) u) for the four azimuths."""
    f = np.asarray(target, np.float64) - np.asarray(eye, np.float64)
    f /= np.linalg.norm(f)
    r = np.cross(f, up)
    r /= np.linalg.norm(r)
    u = np.cross(r, f)
    el = math.radians(ELEVATION_DEG)
    return np.stack([math.sin(el) * -f + math.cos(el) * (math.cos(math.radians(a)) * r
                                                        + math.sin(math.radians(a)) * u)
                     for a in AZIMUTHS_DEG])


def make_problem(*, render_size: int = 512, map_size: int = 256, major: int = 128,
                 minor: int = 80, bump: float = 6.0) -> BenchProblem:
    """The benchmark problem (the defaults are the benchmark's sizes)."""
    mesh = procedural.torus(1.0, 0.4, major, minor)
    h = procedural_height(2 * map_size)
    n2 = height_to_normal_map(jnp.asarray(h), scale=bump)  # green up: +y along +v
    enc2 = np.asarray(encode_normal_map(n2), np.float64)
    enc = enc2.reshape(map_size, 2, map_size, 2, 3).mean(axis=(1, 3))  # box filter, encoded
    n = enc * 2 - 1
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    flat = np.zeros((map_size, map_size, 3), np.float32) + np.float32([0.5, 0.5, 1.0])
    held = np.asarray(HELD_OUT, np.float64) / np.linalg.norm(HELD_OUT)
    return BenchProblem(
        positions=np.asarray(mesh.positions, np.float64), faces=np.asarray(mesh.faces),
        uv=np.asarray(mesh.uv, np.float64), normals=np.asarray(mesh.normals, np.float64),
        eye=EYE, target=(0.0, 0.0, 0.0), up=(0.0, 0.0, 1.0), fov_y_deg=FOV_Y_DEG,
        width=render_size, height=render_size, gt_texels=enc.astype(np.float32),
        gt_normals=n.astype(np.float32), flat_texels=flat, light_dirs=light_directions(EYE),
        held_out_dir=held)


# --------------------------------------------------------------------------------------
# jaxnm's side
# --------------------------------------------------------------------------------------


def jaxnm_camera(p: BenchProblem) -> jaxnm.Camera:
    return jaxnm.Camera.look_at(p.eye, p.target, p.up, fov_y_deg=p.fov_y_deg,
                                aspect=p.width / p.height, near=0.05, far=50.0)


def jaxnm_scene(p: BenchProblem, light_dir, texels=None) -> Scene:
    """The problem as a jaxnm scene under one light, with ``texels`` (default: the truth)."""
    mesh = jaxnm.Mesh(jnp.asarray(p.positions, jnp.float32), jnp.asarray(p.faces, jnp.int32),
                      jnp.asarray(p.uv, jnp.float32), jnp.asarray(p.normals, jnp.float32))
    camera = jaxnm_camera(p)
    # a closed mesh seen from outside: its back faces are skipped (the same image)
    return Scene(mesh=mesh, camera=camera, width=p.width, height=p.height,
                 cull_back=back_faces_hidden(mesh, camera),
                 normal_map=jnp.asarray(p.gt_texels if texels is None else texels),
                 normal_map_options=NormalMapOptions(filter="bilinear", wrap="repeat"),
                 albedo=np.full(3, p.albedo, np.float32),
                 lights=directional_light(np.asarray(light_dir, np.float32)),
                 material=Material(jnp.ones(3), jnp.zeros(3), jnp.asarray(1.0), jnp.zeros(3)),
                 shading="lambert", source="<benchmark problem>")


def jaxnm_fit_problem(p: BenchProblem, targets=None) -> F.FitProblem:
    """The fit benchmark as a jaxnm `FitProblem`: the map fitted to ``targets``, by default
    jaxnm's renders of the true map under each of the four lights."""
    if targets is None:
        targets = [F.FitTarget(jaxnm_camera(p), p.width, p.height, sc.lights,
                               np.asarray(jaxnm.render(sc)["color"]))
                   for sc in (jaxnm_scene(p, d) for d in p.light_dirs)]
    return F.problem_from_scene(jaxnm_scene(p, p.light_dirs[0]), targets,
                                p.gt_texels.shape[:2], source="<benchmark>")


def texel_masks(p: BenchProblem) -> tuple[np.ndarray, np.ndarray]:
    """(seen, well_observed) (h, w) bool masks, from jaxnm's renders of the true map."""
    texels = jnp.asarray(p.gt_texels)
    hits = []
    for d in p.light_dirs:
        sc = jaxnm_scene(p, d)
        g = jax.grad(lambda t, sc=sc: jnp.sum(render_color(sc, t)))(texels)
        hits.append(np.any(np.asarray(g) != 0, axis=-1))
    hits = np.stack(hits)
    # bilinear weight of the pixel hits per texel: the gradient of the sum of a linear
    # read-out of a constant texture (the map's red channel) at every covered pixel
    sc = jaxnm_scene(p, p.light_dirs[0])
    uv_opts = ("uv", "mask")
    out = jaxnm.render(sc, outputs=uv_opts)
    w = _bilinear_weight_sums(np.asarray(out["uv"]), np.asarray(out["mask"])[..., 0] > 0,
                              p.gt_texels.shape[:2])
    seen = hits.any(0)
    well = (hits.sum(0) >= 2) & (w >= 1.0)
    return seen, well


def _bilinear_weight_sums(uv: np.ndarray, mask: np.ndarray, size) -> np.ndarray:
    """Per texel, the sum over covered pixels of its bilinear weight (repeat wrap, GL texel
    centres, uv origin bottom-left)."""
    h, w = size
    u, v = uv[mask, 0], uv[mask, 1]
    x = u * w - 0.5
    y = (1.0 - v) * h - 0.5  # image rows go down
    x0, y0 = np.floor(x), np.floor(y)
    fx, fy = x - x0, y - y0
    acc = np.zeros((h, w))
    for dx, dy, wt in ((0, 0, (1 - fx) * (1 - fy)), (1, 0, fx * (1 - fy)),
                       (0, 1, (1 - fx) * fy), (1, 1, fx * fy)):
        np.add.at(acc, (((y0 + dy).astype(int)) % h, ((x0 + dx).astype(int)) % w), wt)
    return acc


def render_color(sc: Scene, texels) -> jax.Array:
    return jaxnm.render(sc.replace(normal_map=texels))["color"]


def angle_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Per-texel angle in degrees (float64 atan2, `jaxnm.fit.angular_error`)."""
    return F.angular_error(a, b)


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    """Full-image PSNR with peak 1 (linear values), `jaxnm.fit.psnr`."""
    return F.psnr(np.asarray(a), np.asarray(b), peak=1.0)
