"""Scenes: everything a render needs, from a JSON file or built in.

A scene JSON file (paths are relative to the file) looks like::

    {
      "mesh": "torus.obj",   // or "builtin:torus" (the default scene's), "builtin:plane",
                             // "builtin:sphere"
      "model": [[1,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]],   // optional, row-major, column vectors
      "camera": {"eye": [0,-2.4,1.7], "target": [0,0,0], "up": [0,0,1],
                 "fov_y_deg": 45, "near": 0.1, "far": 100},
                // or {"view": 4x4, "projection": 4x4} (OpenGL clip space, camera looks down -z)
      "width": 512, "height": 512,
      "normal_map": {"path": "rivets.png", "encoding": "unsigned", "channels": 3,
                     "green": "up", "strength": 1.0, "uv_origin": "bottom_left",
                     "wrap": "repeat", "filter": "trilinear", "space": "tangent"},
                // or a path string, or "builtin:rivets", or null
      "albedo": [0.8, 0.55, 0.35],          // or {"path": "albedo.png", "srgb": true}
      "lights": [{"type": "directional", "direction": [1,-1,2], "color": [1,1,1], "intensity": 1},
                 {"type": "point", "position": [2,-2,3], "color": [1,1,1], "intensity": 8,
                  "falloff": "inverse_square"}],
      "material": {"model": "blinn_phong", "diffuse": [1,1,1], "specular": [0.4,0.4,0.4],
                   "shininess": 48, "ambient": [0.03,0.03,0.03]},
      "frame": "cotangent", "derivatives": "fine", "double_sided": true, "cull_back": false,
      "ddy": "up"             // "down": emulate HLSL's ddy (y down) in the screen-space frames
    }

Every key but ``mesh`` and ``camera`` is optional (defaults: 512 x 512, no
normal map, a grey albedo, one directional light from the camera's upper left,
Blinn-Phong). Lights and the camera are in world space.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import jax.numpy as jnp
import numpy as np

from . import procedural
from .camera import Camera, look_at, perspective
from .geometry import Mesh, validate_arrays
from .shading import SHADING_MODELS, DirectionalLight, Lights, Material, PointLight, stack_lights

__all__ = [
    "NormalMapOptions",
    "Scene",
    "load_scene",
    "default_scene",
    "scene_from_dict",
    "FRAMES",
    "DERIVATIVES",
]

FRAMES = ("cotangent", "cotangent_unnormalized", "nonperspective", "exact", "exact_face",
          "vertex", "axis", "none")
DERIVATIVES = ("fine", "coarse", "analytic", "gbuffer")
_BUILTIN_MESHES = ("torus", "plane", "sphere")


@dataclasses.dataclass(frozen=True)
class NormalMapOptions:
    """How the normal map's texels are decoded and sampled (all static).

    - `encoding`: ``"unsigned"`` (``2x - 1``), ``"unsigned_exact"`` (Schüler's
      exact expansion ``x*255/127 - 128/127`` for 8 bits), or ``"signed"``.
    - `channels`: 3, or 2 (``z = sqrt(max(0, 1 - x^2 - y^2))``).
    - `green`: ``"up"`` (OpenGL: +green points to the top of the image as
      displayed) or ``"down"`` (DirectX). With ``uv_origin="bottom_left"``,
      "up" means the map's +y is along +v.
    - `strength`: scales the map's x and y.
    - `uv_origin`: ``"bottom_left"`` (OpenGL/OBJ) or ``"top_left"`` (glTF/D3D images).
    - `wrap`, `filter`: texture sampling (``"repeat"|"clamp"|"mirror"``,
      ``"nearest"|"bilinear"|"trilinear"``).
    - `space`: ``"tangent"``, ``"object"`` (an object-space normal map), or
      ``"derivative"`` (a derivative map ``(dh/du, dh/dv)`` in world units per
      unit of uv, Mikkelsen's surface-gradient bump mapping; scene files give a
      ``height_map`` instead, converted on load).
    - `bits`: bit depth of the stored values (for ``"unsigned_exact"``).
    """

    encoding: str = "unsigned"
    channels: int = 3
    green: str = "up"
    strength: float = 1.0
    uv_origin: str = "bottom_left"
    wrap: str = "repeat"
    filter: str = "trilinear"
    space: str = "tangent"
    bits: int = 8


@dataclasses.dataclass(frozen=True)
class Scene:
    """A mesh, a camera, maps, lights, a material and the render options.

    ``normal_map`` holds the *stored* texel values (H, W, C) in image layout,
    before decoding (e.g. in [0, 1] for unsigned encodings); decoding follows
    ``normal_map_options``. ``albedo`` is a linear RGB texture (H, W, 3) or a
    constant (3,).
    """

    mesh: Mesh
    camera: Camera
    width: int = 512
    height: int = 512
    normal_map: np.ndarray | None = None
    normal_map_options: NormalMapOptions = NormalMapOptions()
    albedo: np.ndarray = dataclasses.field(
        default_factory=lambda: np.array([0.8, 0.8, 0.8], np.float32))
    lights: Lights = None  # type: ignore[assignment]
    material: Material = None  # type: ignore[assignment]
    shading: str = "blinn_phong"
    frame: str = "cotangent"
    derivatives: str = "fine"
    double_sided: bool = True
    cull_back: bool = False
    ddy: str = "up"
    source: str = "<built-in>"

    def replace(self, **changes) -> Scene:
        """A copy with some fields changed (validated again)."""
        return _validated(dataclasses.replace(self, **changes))


def _validated(scene: Scene) -> Scene:
    src = scene.source
    for name in ("width", "height"):
        v = getattr(scene, name)
        if not isinstance(v, (int, np.integer)) or v <= 0:
            raise ValueError(f"{src}: `{name}` must be a positive integer, got {v!r}")
        if v > 16384:
            raise ValueError(f"{src}: `{name}` = {v} is larger than the supported 16384")
    if scene.frame not in FRAMES:
        raise ValueError(f"{src}: unknown frame {scene.frame!r}; expected one of {FRAMES}")
    if scene.derivatives not in DERIVATIVES:
        raise ValueError(f"{src}: unknown derivatives {scene.derivatives!r}; expected one of "
                         f"{DERIVATIVES}")
    if scene.ddy not in ("up", "down"):
        raise ValueError(f"{src}: 'ddy' must be 'up' (GLSL dFdy) or 'down' (HLSL ddy), got "
                         f"{scene.ddy!r}")
    if scene.shading not in SHADING_MODELS:
        raise ValueError(f"{src}: unknown shading model {scene.shading!r}; expected one of "
                         f"{SHADING_MODELS}")
    m = scene.mesh
    validate_arrays(np.asarray(m.positions), np.asarray(m.faces),
                    None if m.uv is None else np.asarray(m.uv),
                    None if m.normals is None else np.asarray(m.normals), source=src)
    needs_uv = scene.normal_map_options.space in ("tangent", "derivative")
    if scene.normal_map is not None and m.uv is None and needs_uv:
        raise ValueError(f"{src}: the scene has a tangent-space normal map but the mesh has no "
                         "texture coordinates (uv)")
    lights, material = scene.lights, scene.material
    if lights is None or material is None:
        scene = dataclasses.replace(
            scene, lights=lights if lights is not None else _default_lights(scene.camera),
            material=material if material is not None else default_material())
    if scene.lights.directional is None and scene.lights.point is None:
        raise ValueError(f"{src}: the scene has no lights")
    _check_near_plane(scene)
    return scene


def _check_near_plane(scene: Scene) -> None:
    """Refuse a camera that cannot see the mesh: every vertex behind the near plane."""
    from .camera import to_clip

    clip = np.asarray(to_clip(scene.mesh.positions, scene.camera))
    if not np.any(clip[:, 2] >= -clip[:, 3]):
        raise ValueError(f"{scene.source}: every vertex of the mesh is behind the camera's near "
                         "plane (is the camera inside the object, or looking away from it?)")


def default_material() -> Material:
    return Material(diffuse=jnp.array([1.0, 1.0, 1.0]), specular=jnp.array([0.35, 0.35, 0.35]),
                    shininess=jnp.asarray(48.0), ambient=jnp.array([0.04, 0.04, 0.04]))


def _default_lights(camera: Camera) -> Lights:
    """One directional light from the camera's upper left."""
    inv = np.linalg.inv(np.asarray(camera.view, np.float64))
    d = inv[:3, :3] @ np.array([-0.5, 0.6, 1.0])
    return Lights(directional=stack_lights([DirectionalLight(
        jnp.asarray(d / np.linalg.norm(d), jnp.float32), jnp.ones(3), jnp.asarray(1.0))]))


def default_scene(*, width: int = 512, height: int = 512) -> Scene:
    """The built-in scene: a rivet-mapped torus under two lights (no files needed)."""
    mesh = procedural.default_torus()
    cam = Camera.from_matrices(look_at((0.0, -2.35, 1.75), (0.0, 0.0, -0.1), (0.0, 0.0, 1.0)),
                               perspective(45.0, width / height, 0.1, 50.0))
    nm = procedural.encode_unsigned(procedural.default_normal_map(256))
    lights = Lights(
        directional=stack_lights([DirectionalLight(jnp.array([-0.6, -0.5, 0.8]),
                                                   jnp.array([1.0, 0.96, 0.9]),
                                                   jnp.asarray(0.9))]),
        point=stack_lights([PointLight(jnp.array([1.8, -1.6, 1.4]), jnp.array([0.5, 0.7, 1.0]),
                                       jnp.asarray(4.0))]),
    )
    return _validated(Scene(
        mesh=mesh, camera=cam, width=width, height=height, normal_map=nm,
        albedo=np.array([0.85, 0.6, 0.38], np.float32), lights=lights,
        material=default_material(), source="<built-in default scene>"))


# --------------------------------------------------------------------------------------
# JSON
# --------------------------------------------------------------------------------------


def load_scene(path) -> Scene:
    """Read a scene JSON file (see the module docstring); errors name the file and the key."""
    from .io import load_json

    path = Path(path)
    data = load_json(path)
    return scene_from_dict(data, base_dir=path.parent, source=str(path))


_KNOWN_KEYS = {"mesh", "model", "camera", "width", "height", "normal_map", "height_map",
               "albedo", "lights", "material", "frame", "derivatives", "double_sided",
               "cull_back", "shading", "ddy"}


def scene_from_dict(data: dict, *, base_dir=".", source: str = "<dict>") -> Scene:
    """Build a `Scene` from a parsed scene JSON object."""
    from . import io

    if not isinstance(data, dict):
        raise ValueError(f"{source}: a scene must be a JSON object, got {type(data).__name__}")
    unknown = set(data) - _KNOWN_KEYS
    if unknown:
        raise ValueError(f"{source}: unknown keys {sorted(unknown)}; known keys are "
                         f"{sorted(_KNOWN_KEYS)}")
    base = Path(base_dir)
    if "mesh" not in data:
        raise ValueError(f"{source}: missing required key 'mesh'")
    mesh_ref = data["mesh"]
    if not isinstance(mesh_ref, str):
        raise ValueError(f"{source}: 'mesh' must be a file path or 'builtin:<name>'")
    if mesh_ref.startswith("builtin:"):
        name = mesh_ref.split(":", 1)[1]
        if name not in _BUILTIN_MESHES:
            raise ValueError(f"{source}: unknown built-in mesh {name!r}; expected one of "
                             f"{_BUILTIN_MESHES}")
        mesh = {"torus": procedural.default_torus,
                "plane": lambda: procedural.plane(2.0, 8),
                "sphere": lambda: procedural.uv_sphere(1.0, 96, 48)}[name]()
    else:
        mesh = io.load_mesh(base / mesh_ref)
    if "model" in data:
        try:
            mesh = mesh.transformed(_matrix(data["model"], "model", source))
        except ValueError as e:
            raise ValueError(f"{source}: 'model': {e}") from None

    width = _get(data, "width", int, 512, source)
    height = _get(data, "height", int, 512, source)
    if width <= 0 or height <= 0:
        raise ValueError(f"{source}: 'width' and 'height' must be positive, got {width}x{height}")
    camera = _camera(data.get("camera"), width / height if height else 1.0, source)

    nm, nm_opts = None, NormalMapOptions()
    spec = data.get("normal_map")
    if spec is not None:
        nm, nm_opts = _normal_map(spec, base, source)
    if data.get("height_map") is not None:
        if nm is not None:
            raise ValueError(f"{source}: give either 'normal_map' or 'height_map', not both")
        nm, nm_opts = _height_map(data["height_map"], base, source)

    albedo = _albedo(data.get("albedo", [0.8, 0.8, 0.8]), base, source)
    lights = _lights(data["lights"], source) if "lights" in data else None
    mat_spec = dict(data.get("material", {}))
    shading = mat_spec.pop("model", data.get("shading", "blinn_phong"))
    material = _material(mat_spec, source)
    return _validated(Scene(
        mesh=mesh, camera=camera, width=width, height=height, normal_map=nm,
        normal_map_options=nm_opts, albedo=albedo, lights=lights, material=material,
        shading=shading, frame=_get(data, "frame", str, "cotangent", source),
        derivatives=_get(data, "derivatives", str, "fine", source),
        double_sided=_get(data, "double_sided", bool, True, source),
        cull_back=_get(data, "cull_back", bool, False, source),
        ddy=_get(data, "ddy", str, "up", source), source=source))


def _get(data: dict, key: str, kind, default, source: str):
    v = data.get(key, default)
    if kind is int and isinstance(v, bool) or not isinstance(v, kind):
        if kind is float and isinstance(v, int) and not isinstance(v, bool):
            return float(v)
        raise ValueError(f"{source}: '{key}' must be {kind.__name__}, got {v!r}")
    return v


def _vector(v: Any, n: int, key: str, source: str) -> np.ndarray:
    try:
        a = np.asarray(v, np.float64)
    except (TypeError, ValueError):
        a = np.zeros(0)
    if a.shape != (n,) or not np.all(np.isfinite(a)):
        raise ValueError(f"{source}: '{key}' must be a list of {n} finite numbers, got {v!r}")
    return a


def _matrix(v: Any, key: str, source: str) -> np.ndarray:
    try:
        a = np.asarray(v, np.float64)
    except (TypeError, ValueError):
        a = np.zeros(0)
    if a.shape != (4, 4) or not np.all(np.isfinite(a)):
        raise ValueError(f"{source}: '{key}' must be a 4x4 matrix (row-major nested lists), "
                         f"got {v!r}")
    return a


def _camera(spec: Any, aspect: float, source: str) -> Camera:
    if not isinstance(spec, dict):
        raise ValueError(f"{source}: missing or invalid 'camera' (an object with eye/target or "
                         "view/projection)")
    try:
        if "view" in spec or "projection" in spec:
            extra = set(spec) - {"view", "projection"}
            if extra or "view" not in spec or "projection" not in spec:
                raise ValueError("an explicit camera needs exactly 'view' and 'projection'")
            return Camera.from_matrices(_matrix(spec["view"], "camera.view", source),
                                        _matrix(spec["projection"], "camera.projection", source))
        extra = set(spec) - {"eye", "target", "up", "fov_y_deg", "near", "far"}
        if extra:
            raise ValueError(f"unknown camera keys {sorted(extra)}")
        if "eye" not in spec or "target" not in spec:
            raise ValueError("needs 'eye' and 'target' (or 'view' and 'projection')")
        eye = _vector(spec["eye"], 3, "camera.eye", source)
        target = _vector(spec["target"], 3, "camera.target", source)
        up = _vector(spec.get("up", [0, 1, 0]), 3, "camera.up", source)
        return Camera.from_matrices(
            look_at(eye, target, up),
            perspective(float(spec.get("fov_y_deg", 45.0)), aspect, float(spec.get("near", 0.1)),
                        float(spec.get("far", 100.0))))
    except ValueError as e:
        msg = str(e).removeprefix("camera: ")
        raise ValueError(f"{source}: 'camera': {msg}") from None


def _normal_map(spec: Any, base: Path, source: str):
    from . import io

    if isinstance(spec, str):
        spec = {"path": spec}
    if not isinstance(spec, dict) or "path" not in spec:
        raise ValueError(f"{source}: 'normal_map' must be a path or an object with 'path'")
    spec = dict(spec)
    ref = spec.pop("path")
    fields = {f.name for f in dataclasses.fields(NormalMapOptions)}
    unknown = set(spec) - fields
    if unknown:
        raise ValueError(f"{source}: unknown normal_map keys {sorted(unknown)}; known: "
                         f"{sorted(fields | {'path'})}")
    opts = NormalMapOptions(**spec)
    _check_options(opts, source)
    if ref == "builtin:rivets":
        raw = procedural.encode_unsigned(procedural.default_normal_map(256))
        bits = 8
        if opts.encoding != "unsigned" or opts.channels != 3:
            raise ValueError(f"{source}: 'builtin:rivets' is stored as a 3-channel unsigned map")
    else:
        raw, bits = io.load_texture(base / ref, channels=opts.channels)
        if opts.encoding == "signed" and bits in (8, 16):
            raise ValueError(f"{source}: normal_map {ref!r}: encoding 'signed' needs float data "
                             "(.npy/.npz); an 8/16-bit image stores unsigned values")
    return raw.astype(np.float32), dataclasses.replace(opts, bits=bits if bits in (8, 16)
                                                      else opts.bits)


def _height_map(spec: Any, base: Path, source: str):
    """A height (bump) map file -> its derivative map, rendered by surface-gradient bump mapping."""
    from . import io
    from .maps import height_to_derivative_map

    if isinstance(spec, str):
        spec = {"path": spec}
    if not isinstance(spec, dict) or "path" not in spec:
        raise ValueError(f"{source}: 'height_map' must be a path or an object with 'path'")
    spec = dict(spec)
    known = {"path", "scale", "uv_origin", "wrap", "filter"}
    if set(spec) - known:
        raise ValueError(f"{source}: unknown height_map keys {sorted(set(spec) - known)}; known: "
                         f"{sorted(known)}")
    scale = spec.get("scale", 0.02)
    if not isinstance(scale, (int, float)) or not np.isfinite(scale):
        raise ValueError(f"{source}: height_map.scale must be a finite number (world units)")
    opts = NormalMapOptions(encoding="signed", channels=2, space="derivative",
                            uv_origin=spec.get("uv_origin", "bottom_left"),
                            wrap=spec.get("wrap", "repeat"), filter=spec.get("filter", "trilinear"))
    _check_options(opts, source)
    if opts.wrap == "mirror":
        raise ValueError(f"{source}: height_map.wrap must be 'repeat' or 'clamp'")
    raw, _ = io.load_texture(base / spec["path"], channels=1)
    d = np.array(height_to_derivative_map(raw[..., 0], scale=float(scale), wrap=opts.wrap))
    if opts.uv_origin == "top_left":  # v grows down the image: dh/dv changes sign
        d[..., 1] = -d[..., 1]
    return d.astype(np.float32), opts


def _check_options(opts: NormalMapOptions, source: str) -> None:
    choices = {"encoding": ("unsigned", "unsigned_exact", "signed"), "channels": (2, 3),
               "green": ("up", "down"), "uv_origin": ("bottom_left", "top_left"),
               "wrap": ("repeat", "clamp", "mirror"),
               "filter": ("nearest", "bilinear", "trilinear"),
               "space": ("tangent", "object", "derivative")}
    for key, valid in choices.items():
        if getattr(opts, key) not in valid:
            raise ValueError(f"{source}: normal_map.{key} must be one of {valid}, got "
                             f"{getattr(opts, key)!r}")
    if not (isinstance(opts.strength, (int, float)) and np.isfinite(opts.strength)):
        raise ValueError(f"{source}: normal_map.strength must be a finite number")


def _albedo(spec: Any, base: Path, source: str) -> np.ndarray:
    from . import io
    from .textures import srgb_to_linear

    if isinstance(spec, (list, tuple)):
        return _vector(spec, 3, "albedo", source).astype(np.float32)
    if isinstance(spec, str):
        spec = {"path": spec}
    if not isinstance(spec, dict) or "path" not in spec:
        raise ValueError(f"{source}: 'albedo' must be an RGB list, a path or {{'path', 'srgb'}}")
    tex, _ = io.load_texture(base / spec["path"], channels=3)
    if spec.get("srgb", True):
        tex = np.asarray(srgb_to_linear(tex))
    return tex.astype(np.float32)


def _lights(spec: Any, source: str) -> Lights:
    if not isinstance(spec, list) or not spec:
        raise ValueError(f"{source}: 'lights' must be a non-empty list of light objects")
    directional, point = [], []
    for i, light in enumerate(spec):
        key = f"lights[{i}]"
        if not isinstance(light, dict) or light.get("type") not in ("directional", "point"):
            raise ValueError(f"{source}: {key} must be an object with type 'directional' or "
                             "'point'")
        color = _vector(light.get("color", [1, 1, 1]), 3, f"{key}.color", source)
        intensity = float(light.get("intensity", 1.0))
        if light["type"] == "directional":
            extra = set(light) - {"type", "direction", "color", "intensity"}
            d = _vector(light.get("direction"), 3, f"{key}.direction", source)
            if np.linalg.norm(d) == 0:
                raise ValueError(f"{source}: {key}.direction must not be zero")
            directional.append(DirectionalLight(jnp.asarray(d, jnp.float32),
                                                jnp.asarray(color, jnp.float32),
                                                jnp.asarray(intensity, jnp.float32)))
        else:
            extra = set(light) - {"type", "position", "color", "intensity", "falloff"}
            pos = _vector(light.get("position"), 3, f"{key}.position", source)
            point.append(PointLight(jnp.asarray(pos, jnp.float32),
                                    jnp.asarray(color, jnp.float32),
                                    jnp.asarray(intensity, jnp.float32),
                                    falloff=light.get("falloff", "inverse_square")))
        if extra:
            raise ValueError(f"{source}: {key} has unknown keys {sorted(extra)}")
    try:
        return Lights(directional=stack_lights(directional) if directional else None,
                      point=stack_lights(point) if point else None)
    except ValueError as e:
        raise ValueError(f"{source}: 'lights': {e}") from None


def _material(spec: dict, source: str) -> Material:
    base = default_material()
    unknown = set(spec) - {"diffuse", "specular", "shininess", "ambient"}
    if unknown:
        raise ValueError(f"{source}: unknown material keys {sorted(unknown)}")
    vals = {}
    for k in ("diffuse", "specular", "ambient"):
        vals[k] = (jnp.asarray(_vector(spec[k], 3, f"material.{k}", source), jnp.float32)
                   if k in spec else getattr(base, k))
    shin = spec.get("shininess", float(base.shininess))
    if not isinstance(shin, (int, float)) or not np.isfinite(shin) or shin < 0:
        raise ValueError(f"{source}: material.shininess must be a number >= 0, got {shin!r}")
    return Material(shininess=jnp.asarray(float(shin), jnp.float32), **vals)
