"""The built-in scene and fitting problem, generated in code (no files needed).

- `default_scene`: the rivet-mapped torus under a directional and a point light
  (``jaxnm render`` with no scene file).
- `default_problem`: that torus rendered from ``views`` cameras under
  ``n_lights`` directional lights with the ground-truth map — the targets of
  ``jaxnm fit`` with no fit file (`default_fit_job` adds a held-out light).
"""

from __future__ import annotations

import math

import jax.numpy as jnp
import numpy as np

from ..camera import Camera, eye_to_world, look_at, perspective
from ..fit import FitJob, FitOptions, FitProblem, FitTarget, problem_from_scene
from ..render import render
from ..scene import (
    MAX_IMAGE_SIZE,
    Scene,
    back_faces_hidden,
    check_scene_options,
    default_material,
    validate_scene,
)
from ..shading import (
    DirectionalLight,
    Lights,
    Material,
    PointLight,
    directional_light,
    stack_lights,
)
from ..textures import decode_normal_map
from .assets import default_normal_map_texels, default_torus

__all__ = ["default_scene", "default_light_directions", "default_problem", "default_fit_job",
           "DEFAULT_FIT_EYES", "HELD_OUT_LIGHT"]

#: The cameras of the built-in fitting problem (looking at the origin, z up).
DEFAULT_FIT_EYES = ((0.0, -2.35, 1.75), (1.6, 1.5, 1.9), (-2.1, 0.6, -1.2))
#: The held-out light of `default_fit_job`, in the first camera's frame: elevation ~55 deg,
#: azimuth ~38 deg, between fitted lights 0 and 1.
HELD_OUT_LIGHT = (0.45, 0.35, 0.82)


def default_scene(*, width: int = 512, height: int = 512) -> Scene:
    """The built-in scene: a rivet-mapped torus under two lights (no files needed)."""
    check_scene_options(width=width, height=height, source="default_scene")
    cam = Camera.from_matrices(look_at((0.0, -2.35, 1.75), (0.0, 0.0, -0.1), (0.0, 0.0, 1.0)),
                               perspective(45.0, width / height, 0.1, 50.0))
    lights = Lights(
        directional=stack_lights([DirectionalLight(jnp.array([-0.6, -0.5, 0.8]),
                                                   jnp.array([1.0, 0.96, 0.9]),
                                                   jnp.asarray(0.9))]),
        point=stack_lights([PointLight(jnp.array([1.8, -1.6, 1.4]), jnp.array([0.5, 0.7, 1.0]),
                                       jnp.asarray(4.0))]),
    )
    mesh = default_torus()
    return validate_scene(Scene(
        mesh=mesh, camera=cam, width=width, height=height,
        normal_map=default_normal_map_texels(256), albedo=np.array([0.85, 0.6, 0.38], np.float32),
        lights=lights, material=default_material(), cull_back=back_faces_hidden(mesh, cam),
        source="<built-in default scene>"))


def default_light_directions(n: int = 6, elevation_deg: float = 50.0, seed: int = 0) -> np.ndarray:
    """``n`` unit directions on a cone around +z (azimuths evenly spread, fixed jitter)."""
    rng = np.random.default_rng(seed)
    az = 2 * np.pi * (np.arange(n) / n) + rng.uniform(-0.15, 0.15, n)
    el = np.radians(elevation_deg + rng.uniform(-8, 8, n))
    return np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], -1)


def _fit_scene(render_size: int, map_size: int) -> Scene:
    """The default scene with a ``map_size`` rivet map and a duller, ambient-free material."""
    sc = default_scene(width=render_size, height=render_size)
    return sc.replace(normal_map=default_normal_map_texels(map_size), material=Material(
        diffuse=jnp.ones(3), specular=jnp.asarray([0.15, 0.15, 0.15]),
        shininess=jnp.asarray(24.0), ambient=jnp.zeros(3)))


def _fit_camera(eye) -> Camera:
    return Camera.from_matrices(look_at(eye, (0.0, 0.0, 0.0), (0.0, 0.0, 1.0)),
                                perspective(45.0, 1.0, 0.1, 50.0))


def default_problem(*, render_size: int = 512, map_size: int = 256, n_lights: int = 6,
                    noise: float = 0.0, seed: int = 0, views: int = 2
                    ) -> tuple[FitProblem, np.ndarray, Scene]:
    """The built-in fitting problem: the default scene's torus and rivet map.

    Renders the torus from ``views`` cameras (at most 3, `DEFAULT_FIT_EYES`)
    under ``n_lights`` directional lights given relative to each view (so each
    view sees its lit side) with the ground-truth map (an 8-bit unsigned map
    of ``map_size``), adds Gaussian noise of standard deviation ``noise``
    (relative to each target's maximum), and returns ``(problem,
    ground_truth_normals, scene)``.
    """
    _check_problem_args(render_size=render_size, map_size=map_size, n_lights=n_lights,
                        noise=noise, seed=seed, views=views)
    scene = _fit_scene(render_size, map_size)
    gt = np.asarray(decode_normal_map(jnp.asarray(scene.normal_map), encoding="unsigned"),
                    np.float64)
    gt = (gt / np.linalg.norm(gt, axis=-1, keepdims=True)).astype(np.float32)
    rng = np.random.default_rng(seed)
    targets = []
    for vi, eye in enumerate(DEFAULT_FIT_EYES[:views]):
        cam = _fit_camera(eye)
        for li, d in enumerate(default_light_directions(n_lights, seed=seed)):
            lights = directional_light(eye_to_world(cam, d))
            img = np.asarray(render(scene.replace(
                camera=cam, lights=lights, cull_back=back_faces_hidden(scene.mesh, cam)))["color"])
            if noise > 0:
                img = img + rng.normal(0.0, noise * img.max(), img.shape).astype(np.float32)
            targets.append(FitTarget(cam, render_size, render_size, lights, img,
                                     name=f"view{vi}_light{li}"))
    problem = problem_from_scene(scene, targets, (map_size, map_size),
                                 source="<built-in fit problem>")
    return problem, gt, scene


def _check_problem_args(*, render_size, map_size, n_lights, noise, seed, views) -> None:
    """`default_problem`'s arguments, each refused in one line naming it."""
    def integer(v):
        return not isinstance(v, bool) and isinstance(v, (int, np.integer))

    for name, v, lo, hi in (("render_size", render_size, 1, MAX_IMAGE_SIZE),
                            ("map_size", map_size, 2, None), ("n_lights", n_lights, 1, None),
                            ("views", views, 1, len(DEFAULT_FIT_EYES)),
                            ("seed", seed, 0, None)):
        if not integer(v) or v < lo or (hi is not None and v > hi):
            bound = f"{lo} to {hi}" if hi is not None else f">= {lo}"
            raise ValueError(f"default_problem: {name} must be an integer {bound}, got {v!r}")
    if isinstance(noise, bool) or not isinstance(noise, (int, float, np.floating)) \
            or not math.isfinite(noise) or noise < 0:
        raise ValueError(f"default_problem: noise must be a finite number >= 0, got {noise!r}")


def default_fit_job(*, quick: bool = False) -> FitJob:
    """``jaxnm fit`` with no fit file: `default_problem` (512x512 renders and a 256x256 map,
    or 128x128 and 64x64 with ``quick``), 15 texel-space LM steps of 20 conjugate-gradient
    iterations, scored against the ground truth and a held-out light (`HELD_OUT_LIGHT`)."""
    if not isinstance(quick, bool):
        raise ValueError(f"default_fit_job: quick must be True or False, got {quick!r}")
    size, msize = (128, 64) if quick else (512, 256)
    problem, gt, scene = default_problem(render_size=size, map_size=msize, n_lights=6, views=2)
    cam = problem.targets[0].camera
    lights = directional_light(eye_to_world(cam, HELD_OUT_LIGHT))
    img = np.asarray(render(scene.replace(
        camera=cam, lights=lights, cull_back=back_faces_hidden(scene.mesh, cam)))["color"])
    held = (FitTarget(cam, size, size, lights, img, name="held-out light"),)
    # Levenberg-Marquardt in texel space (the default solver), 20 conjugate-gradient
    # iterations a step: a step's pass over the pixels (shading 12 targets and forming their
    # Gauss-Newton blocks) costs about as much as 20 iterations, so more of them per step
    # reach each accuracy sooner
    options = FitOptions(solver="lm-texel", max_steps=15, lsmr_steps=20)
    return FitJob(problem=problem, options=options,
                  ground_truth=gt, held_out=held)

