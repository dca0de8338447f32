"""What a view sees of a mesh, and its shading under several lights: the pieces the fitting
baker (`jaxnm.transfer.pair`) and its scoring (`jaxnm.transfer.evaluate`) share, so that
targets, fitted renders and scores all come from one path through `jaxnm.render` and
`jaxnm.shading.shade`."""

from __future__ import annotations

import dataclasses
import functools
import math

import jax
import jax.numpy as jnp
import numpy as np

from ..camera import Camera
from ..geometry import Mesh
from ..render import render
from ..scene import Scene
from ..shading import DirectionalLight, Lights, Material, shade, stack_lights
from ..textures import NormalMapOptions

__all__ = ["Surface", "surface", "shade_lights", "directional_lights", "pair_mask",
           "pair_tolerance", "facing", "angles_deg", "TRIANGLE_CHUNK"]


@dataclasses.dataclass(frozen=True)
class Surface:
    """One view of a mesh, host arrays in image layout (row 0 on top): `mask` and
    `front_facing` ``(H, W)`` bool, `position` and `normal` ``(H, W, 3)`` (the normal the
    shading uses: the interpolated one, face-forwarded, perturbed by the map where there is
    one), `uv` ``(H, W, 2)`` or None, and the camera's `eye`."""

    mask: np.ndarray
    front_facing: np.ndarray
    position: np.ndarray
    normal: np.ndarray
    uv: np.ndarray | None
    eye: np.ndarray


#: Triangles `surface` renders at once: a mesh with more is rendered in equal pieces of at
#: most this many, merged by depth, so that a view of HIGH needs the memory of one piece
#: (`jaxnm.render`'s grows with the triangles: about 0.45 GB for a million at 512x512).
TRIANGLE_CHUNK = 1 << 20


def surface(mesh: Mesh, camera: Camera, size: int, *, frame: str = "none",
            normal_map: np.ndarray | None = None,
            sampling: NormalMapOptions | None = None, uv: bool = False,
            source: str = "mesh", chunk: int = TRIANGLE_CHUNK) -> Surface:
    """`Surface` of ``mesh`` from ``camera`` at ``size`` x ``size`` pixels, by `jaxnm.render`:
    with ``normal_map`` ((h, w, 3) signed unit normals sampled as ``sampling`` says) the
    normal is the perturbed one in ``frame``; without, the interpolated normal. A mesh of
    more than ``chunk`` triangles is rendered in pieces (the last padded with triangles of
    no area, so that every piece has one shape and one compiled program), each pixel taking
    the nearest piece's fragment."""
    scene = Scene(mesh=mesh, camera=camera, width=size, height=size, frame=frame,
                  normal_map=None if normal_map is None else jnp.asarray(normal_map,
                                                                          jnp.float32),
                  normal_map_options=sampling or NormalMapOptions(encoding="signed"),
                  source=source)
    outputs = ("mask", "front_facing", "position", "perturbed_normal") + (
        ("uv",) if uv else ())
    faces = np.asarray(mesh.faces)
    if len(faces) <= chunk:
        out = {k: np.asarray(v) for k, v in render(scene, outputs=outputs).items()}
    else:
        out = _render_in_pieces(scene, faces, outputs, chunk)
    return Surface(mask=out["mask"][..., 0] > 0, front_facing=out["front_facing"][..., 0] > 0,
                   position=out["position"].astype(np.float32),
                   normal=out["perturbed_normal"].astype(np.float32),
                   uv=out["uv"].astype(np.float32) if uv else None,
                   eye=np.asarray(camera.eye, np.float64))


def _render_in_pieces(scene: Scene, faces: np.ndarray, outputs, chunk: int) -> dict:
    """`jaxnm.render`'s ``outputs`` of ``scene``, its triangles rendered in equal pieces of at
    most ``chunk`` and merged by window depth (host arrays)."""
    pieces = -(-len(faces) // chunk)
    each = -(-len(faces) // pieces)
    tangents = None if scene.mesh.tangents is None else np.asarray(scene.mesh.tangents)
    best = None
    for k in range(pieces):
        part = np.zeros((each, 3), faces.dtype)  # padding: triangles (0, 0, 0) cover nothing
        f = faces[k * each:(k + 1) * each]
        part[:len(f)] = f
        mesh = dataclasses.replace(scene.mesh, faces=jnp.asarray(part))
        if tangents is not None:
            t = np.zeros((each,) + tangents.shape[1:], tangents.dtype)
            t[:len(f)] = tangents[k * each:(k + 1) * each]
            mesh = dataclasses.replace(mesh, tangents=jnp.asarray(t))
        got = {n: np.asarray(v) for n, v in render(scene.replace(mesh=mesh),
                                                  outputs=outputs + ("depth",)).items()}
        if best is None:
            best = got
            continue
        nearer = (got["mask"][..., 0] > 0) & ((best["mask"][..., 0] == 0)
                                              | (got["depth"][..., 0] < best["depth"][..., 0]))
        for n in best:
            best[n] = np.where(nearer[..., None], got[n], best[n])
    return best


def directional_lights(directions: np.ndarray) -> Lights:
    """White directional lights of unit intensity towards ``directions`` ``(L, 3)``,
    stacked."""
    return Lights(directional=stack_lights([
        DirectionalLight(jnp.asarray(d, jnp.float32), jnp.ones(3), jnp.asarray(1.0))
        for d in np.asarray(directions, np.float64)]))


@functools.partial(jax.jit, static_argnames="shading")
def _shade_each(normal, position, eye, lights: Lights, material, albedo, *, shading):
    def one(light):
        return shade(shading, normal, position, eye, Lights(directional=light), material,
                     albedo=albedo)

    return jax.vmap(one)(lights.directional)


def shade_lights(s: Surface, directions: np.ndarray, material: Material, albedo,
                 shading: str) -> np.ndarray:
    """``(L, H, W, 3)`` float32 linear colour of `Surface` ``s`` under each of the directional
    lights towards ``directions`` ``(L, 3)`` on its own (`jaxnm.shading.shade`, as
    `jaxnm.render` shades), 0 off the mesh."""
    lights = directional_lights(directions)
    c = _shade_each(jax.device_put(s.normal), jax.device_put(s.position),
                    jnp.asarray(s.eye, jnp.float32), lights, material,
                    jnp.broadcast_to(jnp.asarray(albedo, jnp.float32), (3,)), shading=shading)
    return np.where(s.mask[None, ..., None], np.asarray(c, np.float32), np.float32(0.0))


def pair_mask(high: Surface, low: Surface, tolerance: float) -> np.ndarray:
    """``(H, W)`` bool: the pixels both meshes cover where the points they show are at most
    ``tolerance`` apart (elsewhere one mesh's silhouette or an occlusion shows a surface
    the other does not have there)."""
    d = np.linalg.norm(high.position - low.position, axis=-1)
    return high.mask & low.mask & (d <= tolerance)


def facing(s: Surface, max_angle_deg: float) -> np.ndarray:
    """``(H, W)`` bool: the front-facing pixels of ``s`` whose normal is within
    ``max_angle_deg`` of the direction to the camera."""
    to_eye = s.eye[None, None] - s.position
    cos = np.einsum("hwi,hwi->hw", s.normal, to_eye) / np.maximum(
        np.linalg.norm(to_eye, axis=-1), 1e-30)
    return s.mask & s.front_facing & (cos >= math.cos(math.radians(max_angle_deg)))


def pair_tolerance(pairs, max_angle_deg: float = 60.0) -> float:
    """The distance `pair_mask` allows between the points HIGH and LOW show at a pixel, from
    ``pairs`` of their `Surface`s (one per view): three times the 95th percentile of that
    distance over the pixels both cover where LOW faces the camera within ``max_angle_deg``
    (0 where there are none). The 95th percentile measures how far the surfaces lie apart
    where they face the views (a point seen at 60 degrees lies up to twice as far along the
    ray); the few pixels past it that show another surface altogether (an ear in front of
    the head, a hole in a scan: on the Stanford Bunny the 98th percentile is 2.6 mm, the
    99th 49 mm) do not move it."""
    d = [np.linalg.norm(hi.position - lo.position, axis=-1)[hi.mask & facing(lo, max_angle_deg)]
         for hi, lo in pairs]
    d = np.concatenate(d) if d else np.zeros(0)
    return 3.0 * float(np.percentile(d, 95)) if d.size else 0.0


def angles_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The angle in degrees between the vectors ``a`` and ``b`` (..., 3), as ``atan2(|a x b|,
    a . b)`` in float64."""
    a = np.asarray(a, np.float64)
    b = np.asarray(b, np.float64)
    return np.degrees(np.arctan2(np.linalg.norm(np.cross(a, b), axis=-1),
                                 np.einsum("...i,...i->...", a, b)))
