"""Configuration at the edge: scene files and fit files (JSON) to `Scene` and `FitJob`.

Every field is checked here, before anything is rendered or compiled; an error
is one line, ``"<file>: <field>: <problem>"``, a `ValueError`. Files named by
a configuration (meshes, maps, images) are read through `jaxnm.io`. Paths are
relative to the JSON file.

A **scene file**::

    {
      "mesh": "torus.obj",   // or "builtin:torus", "builtin:plane", "builtin:sphere"
      "model": [[1,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]],   // optional, row-major, column vectors
      "camera": {"eye": [0,-2.4,1.7], "target": [0,0,0], "up": [0,0,1],
                 "fov_y_deg": 45, "near": 0.1, "far": 100},
                // or {"view": 4x4, "projection": 4x4} (OpenGL clip space, camera looks down -z)
      "width": 512, "height": 512,
      "normal_map": {"path": "rivets.png", "encoding": "unsigned", "channels": 3,
                     "green": "up", "strength": 1.0, "uv_origin": "bottom_left",
                     "wrap": "repeat", "filter": "trilinear", "space": "tangent"},
                // or a path string, or "builtin:rivets", or null
      "height_map": {"path": "bumps.png", "scale": 0.02},   // instead of a normal map
      "albedo": [0.8, 0.55, 0.35],          // or {"path": "albedo.png", "srgb": true}
      "lights": [{"type": "directional", "direction": [1,-1,2], "color": [1,1,1], "intensity": 1},
                 {"type": "point", "position": [2,-2,3], "color": [1,1,1], "intensity": 8,
                  "falloff": "inverse_square"}],
      "material": {"model": "blinn_phong", "diffuse": [1,1,1], "specular": [0.4,0.4,0.4],
                   "shininess": 48, "ambient": [0.03,0.03,0.03]},
      "frame": "cotangent", "derivatives": "fine", "double_sided": true, "cull_back": "auto",
      "precision": "float32", // the shader's arithmetic: "float16" models GLSL mediump
      "ddy": "up",            // "down": emulate HLSL's ddy (y down) in the screen-space frames
      "tangents": "auto"      // frame "vertex": the file's glTF TANGENT, else MikkTSpace;
                              // "mikktspace": always MikkTSpace
    }

Every key but ``mesh`` and ``camera`` is optional (defaults: 512 x 512, no
normal map, a grey albedo, one directional light from the camera's upper left,
Blinn-Phong). Lights and the camera are in world space.

A **fit file**::

    {
      "scene": "scene.json",                  // mesh, material, albedo, map sampling options
      "views": [{"camera": {"eye": [0,-2.4,1.7], "target": [0,0,0], "up": [0,0,1]},
                 "width": 512, "height": 512}],   // optional: default = the scene's camera
      "targets": [{"view": 0, "image": "t0.png", "color_space": "srgb",
                   "lights": [{"type": "directional", "direction": [0.3,-0.2,1]}],
                   "mask": "mask0.png"}],      // mask optional (white = use)
      "map": {"size": [256, 256], "encoding": "unsigned", "green": "up", "bits": 8},
      "ground_truth": {"path": "gt.png", "encoding": "unsigned", "green": "up"},   // optional
      "held_out": [{"view": 0, "image": "h0.png", "color_space": "srgb",
                    "lights": [...]}],          // optional: scored, never fitted
      "solver": {"method": "lm-texel", "max_steps": 30, "lsmr_steps": 10, "smoothness": 0,
                 "coarse_to_fine": 0, "seed": 0, "time_limit": null,
                 "ftol": 0.001, "patience": 3,   // converged: < 0.1 % loss drop in 3 steps
                 "texel_sums": "auto"}           // or "scatter", "tables" (FitOptions)
    }

Target images: PNG (8 or 16 bit), EXR, or ``.npy``/``.npz`` float arrays;
``color_space`` says whether their values are ``"srgb"``-encoded (default for
PNG/JPEG) or ``"linear"`` (default for EXR/npy/npz).
"""

from __future__ import annotations

import dataclasses
import difflib
import json
import math
import warnings
from pathlib import Path
from typing import Any

import jax.numpy as jnp
import numpy as np

from . import io
from .camera import Camera, look_at, perspective
from .fit import FitJob, FitOptions, FitTarget, problem_from_scene
from .frames import canonical_frame
from .maps import height_to_derivative_map
from .procedural import BUILTIN_MESHES, builtin_mesh, default_normal_map_texels
from .scene import (
    Scene,
    back_faces_hidden,
    check_scene_options,
    default_material,
    validate_scene,
)
from .shading import DirectionalLight, Lights, Material, PointLight, stack_lights
from .textures import NormalMapOptions, decode_normal_map, srgb_to_linear

__all__ = [
    "load_scene", "scene_from_dict", "load_fit", "fit_from_dict", "SCENE_KEYS", "FIT_KEYS",
    "TANGENT_MODES", "load_height_map", "OBJECT_SPACE_HINT"
]

#: How a scene file names an object-space map (the end of the warning that a map given as a
#: tangent-space one looks like one, `jaxnm.io.check_tangent_normal_map`).
OBJECT_SPACE_HINT = "a scene file's normal_map takes \"space\": \"object\""

SCENE_KEYS = ("mesh", "model", "camera", "width", "height", "normal_map", "height_map",
              "albedo", "lights", "material", "frame", "derivatives", "precision", "double_sided",
              "cull_back", "shading", "ddy", "tangents")
#: The scene key ``tangents``: ``"auto"`` uses a glTF file's TANGENT attribute where there is
#: one (the glTF rule) and MikkTSpace otherwise; ``"mikktspace"`` always computes them.
TANGENT_MODES = ("auto", "mikktspace")
FIT_KEYS = ("scene", "views", "targets", "map", "ground_truth", "held_out", "solver")
_SOLVER_KEYS = {"method": "solver", "max_steps": "max_steps", "lsmr_steps": "lsmr_steps",
                "smoothness": "smoothness", "coarse_to_fine": "coarse_to_fine", "seed": "seed",
                "rtol": "rtol", "atol": "atol", "init_noise": "init_noise", "ftol": "ftol",
                "patience": "patience", "texel_sums": "texel_sums"}
_KINDS = {
    int: "an integer",
    float: "a number",
    bool: "true or false",
    str: "a string",
    list: "a list",
    dict: "an object",
}


# --------------------------------------------------------------------------------------
# typed fields
# --------------------------------------------------------------------------------------


def _field(data: dict, key: str, kind, default, where: str):
    """``data[key]`` (or ``default``) checked to be of ``kind`` (JSON's types: an int is a
    valid float, a bool is not a number)."""
    v = data.get(key, default)
    if v is None and default is None:
        return None
    ok = isinstance(v, kind) and not (kind in (int, float) and isinstance(v, bool))
    if kind is float and isinstance(v, int) and not isinstance(v, bool):
        v, ok = float(v), True
    if kind is float and ok and not math.isfinite(v):
        ok = False
    if not ok:
        raise ValueError(f"{where}'{key}' must be {_KINDS[kind]}, got {v!r}")
    return v


def _keys(data: dict, known, where: str) -> None:
    """Refuse keys of ``data`` outside ``known``, naming the known key each may be a typo of."""
    unknown = sorted(set(data) - set(known))
    if unknown:
        meant = {k: difflib.get_close_matches(str(k), known, n=1, cutoff=0.75) for k in unknown}
        hints = [f"{k!r} for {m[0]!r}" for k, m in meant.items() if m]
        hint = f" (a typo? {', '.join(hints)})" if hints else ""
        raise ValueError(f"{where}unknown keys {unknown}{hint}; known keys are {sorted(known)}")


def _vector(v: Any, n: int, key: str, where: str) -> np.ndarray:
    try:
        a = np.asarray(v, np.float64)
    except (TypeError, ValueError):
        a = np.zeros(0)
    if a.shape != (n,) or not np.all(np.isfinite(a)):
        raise ValueError(f"{where}'{key}' must be a list of {n} finite numbers, got {v!r}")
    return a


def _colour(v: Any, key: str, where: str) -> np.ndarray:
    """An RGB list of finite numbers >= 0 (a colour, a reflectance or an albedo)."""
    a = _vector(v, 3, key, where)
    if np.any(a < 0):
        raise ValueError(f"{where}'{key}' must not be negative (light and reflectance are "
                         f">= 0), got {v!r}")
    return a


def _matrix(v: Any, key: str, where: str) -> np.ndarray:
    try:
        a = np.asarray(v, np.float64)
    except (TypeError, ValueError):
        a = np.zeros(0)
    if a.shape != (4, 4) or not np.all(np.isfinite(a)):
        raise ValueError(f"{where}'{key}' must be a 4x4 matrix of finite numbers (row-major "
                         f"nested lists), got {v!r}")
    return a


def _object(v: Any, key: str, where: str) -> dict:
    if isinstance(v, str):
        return {"path": v}
    if not isinstance(v, dict) or "path" not in v:
        raise ValueError(f"{where}'{key}' must be a path or an object with 'path'")
    if not isinstance(v["path"], str):
        raise ValueError(f"{where}'{key}.path' must be a string, got {v['path']!r}")
    return dict(v)


def _rewrap(e: ValueError, where: str) -> ValueError:
    return ValueError(f"{where}{e}")


# --------------------------------------------------------------------------------------
# parts shared by scene and fit files
# --------------------------------------------------------------------------------------


def _parse_camera(spec: Any, *, aspect: float, where: str = "") -> Camera:
    """A camera from ``{"eye", "target", "up", "fov_y_deg", "near", "far"}`` or
    ``{"view", "projection"}``; ``where`` prefixes error messages (e.g. ``"fit.json: "``)."""
    w = f"{where}camera: "
    if not isinstance(spec, dict):
        raise ValueError(f"{where}missing or invalid 'camera' (an object with eye/target or "
                         "view/projection)")
    if "view" in spec or "projection" in spec:
        _keys(spec, ("view", "projection"), w)
        if "view" not in spec or "projection" not in spec:
            raise ValueError(f"{w}an explicit camera needs both 'view' and 'projection'")
        view, proj = _matrix(spec["view"], "view", w), _matrix(spec["projection"], "projection",
                                                                  w)
        make = lambda: Camera.from_matrices(view, proj)  # noqa: E731
    else:
        _keys(spec, ("eye", "target", "up", "fov_y_deg", "near", "far"), w)
        if "eye" not in spec or "target" not in spec:
            raise ValueError(f"{w}needs 'eye' and 'target' (or 'view' and 'projection')")
        eye = _vector(spec["eye"], 3, "eye", w)
        target = _vector(spec["target"], 3, "target", w)
        up = _vector(spec.get("up", [0, 1, 0]), 3, "up", w)
        fov = _field(spec, "fov_y_deg", float, 45.0, w)
        near = _field(spec, "near", float, 0.1, w)
        far = _field(spec, "far", float, 100.0, w)
        make = lambda: Camera.from_matrices(look_at(eye, target, up),  # noqa: E731
                                            perspective(fov, aspect, near, far))
    try:
        return make()
    except ValueError as e:
        raise ValueError(f"{w}{str(e).removeprefix('camera: ')}") from None


def _parse_lights(spec: Any, *, where: str = "") -> Lights:
    """`Lights` from a non-empty list of ``{"type": "directional"|"point", ...}`` objects."""
    if not isinstance(spec, list) or not spec:
        raise ValueError(f"{where}'lights' must be a non-empty list of light objects")
    directional, point = [], []
    for i, light in enumerate(spec):
        w = f"{where}lights[{i}]: "
        if not isinstance(light, dict) or light.get("type") not in ("directional", "point"):
            raise ValueError(f"{w}must be an object with type 'directional' or 'point'")
        color = jnp.asarray(_colour(light.get("color", [1, 1, 1]), "color", w), jnp.float32)
        intensity = _field(light, "intensity", float, 1.0, w)
        if intensity < 0:
            raise ValueError(f"{w}'intensity' must be >= 0, got {intensity!r}")
        intensity = jnp.asarray(intensity, jnp.float32)
        if light["type"] == "directional":
            _keys(light, ("type", "direction", "color", "intensity"), w)
            d = _vector(light.get("direction"), 3, "direction", w)
            if np.linalg.norm(d) == 0:
                raise ValueError(f"{w}'direction' must not be zero")
            directional.append(DirectionalLight(jnp.asarray(d, jnp.float32), color, intensity))
        else:
            _keys(light, ("type", "position", "color", "intensity", "falloff"), w)
            pos = _vector(light.get("position"), 3, "position", w)
            falloff = _field(light, "falloff", str, "inverse_square", w)
            try:
                point.append(PointLight(jnp.asarray(pos, jnp.float32), color, intensity,
                                        falloff=falloff))
            except ValueError as e:
                raise _rewrap(e, w) from None
    try:
        return Lights(directional=stack_lights(directional) if directional else None,
                      point=stack_lights(point) if point else None)
    except ValueError as e:
        raise ValueError(f"{where}'lights': {e}") from None


def _parse_material(spec: Any, *, where: str = "") -> tuple[Material, str]:
    """``(material, shading model)`` from ``{"model", "diffuse", "specular", "shininess",
    "ambient"}`` (defaults: `jaxnm.scene.default_material`, Blinn-Phong)."""
    w = f"{where}material: "
    if not isinstance(spec, dict):
        raise ValueError(f"{where}'material' must be an object")
    _keys(spec, ("model", "diffuse", "specular", "shininess", "ambient"), w)
    base = default_material()
    vals = {k: (jnp.asarray(_colour(spec[k], k, w), jnp.float32) if k in spec
                else getattr(base, k)) for k in ("diffuse", "specular", "ambient")}
    shin = _field(spec, "shininess", float, float(base.shininess), w)
    if shin < 0:
        raise ValueError(f"{w}'shininess' must be >= 0, got {shin!r}")
    model = _field(spec, "model", str, "blinn_phong", w)
    return Material(shininess=jnp.asarray(shin, jnp.float32), **vals), model


def _map_options(spec: dict, known, where: str, **fixed) -> NormalMapOptions:
    fields = {f.name for f in dataclasses.fields(NormalMapOptions)}
    kinds = {f.name: (int if f.type == "int" else float if f.type == "float" else str)
             for f in dataclasses.fields(NormalMapOptions)}
    _keys(spec, known, where)
    values = {k: _field(spec, k, kinds[k], None, where) for k in spec if k in fields}
    try:
        return NormalMapOptions(**{**values, **fixed})
    except ValueError as e:
        raise ValueError(f"{where}{str(e).removeprefix('NormalMapOptions: ')}") from None


def _reading(where: str, read, *args, **kwargs):
    """``read(*args, **kwargs)``, a file reader whose ValueError (a file that is not what it
    should be) then also names the scene or fit file and the field, ``where``."""
    try:
        return read(*args, **kwargs)
    except ValueError as e:
        raise ValueError(f"{where}{e}") from None


#: The file formats each kind of input is read in (by its name's extension).
_FORMATS = {"mesh": io.MESH_EXTENSIONS, "texture": io.TEXTURE_EXTENSIONS,
            "normal map": (*io.TEXTURE_EXTENSIONS, ".dds"), "image": io.IMAGE_EXTENSIONS}


def _input_file(base: Path, ref: Any, key: str, where: str, kind: str | None = None) -> Path:
    """``base / ref``, checked to name an existing file (and, for a ``kind`` of `_FORMATS`,
    one read in that kind's formats): else a one-line error naming the field
    (``"scene.json: normal_map: maps/rivet.png: no such file"``)."""
    if not isinstance(ref, str) or not ref:
        raise ValueError(f"{where}'{key}' must be a file path, got {ref!r}")
    p = base / ref
    if not p.exists():
        raise FileNotFoundError(f"{where}{key}: {p}: no such file")
    if not p.is_file():
        raise ValueError(f"{where}{key}: {p}: not a regular file")
    formats = _FORMATS.get(kind, ())
    if formats and p.suffix.lower() not in formats:
        a = "an" if kind[0] in "aeiou" else "a"
        raise ValueError(f"{where}{key}: {p}: not {a} {kind} format that jaxnm reads "
                         f"({p.suffix.lower() or 'no extension'}); it reads "
                         f"{', '.join(formats)}")
    return p


#: Image formats that store unsigned 8- or 16-bit values (``encoding: "signed"`` needs float).
_INTEGER_IMAGES = (".png", ".jpg", ".jpeg", ".bmp", ".tga", ".tif", ".tiff")


def _normal_map_loader(spec: Any, *, base_dir=".", where: str = ""):
    """Check a scene's ``normal_map`` entry (a path, ``"builtin:rivets"``, or an object with
    ``path`` and the `NormalMapOptions` fields) and that its file exists; returns a function
    that reads it: ``() -> (stored texels, NormalMapOptions)``."""
    spec = _object(spec, "normal_map", where)
    w = f"{where}normal_map: "
    fields = [f.name for f in dataclasses.fields(NormalMapOptions) if f.name != "bits"]
    _keys(spec, ["path", *fields], w)
    ref = spec.pop("path")
    opts = _map_options(spec, fields, w)
    if ref == "builtin:rivets":
        if opts.encoding != "unsigned" or opts.channels != 3:
            raise ValueError(f"{w}'builtin:rivets' is stored as a 3-channel unsigned map")
        return lambda: (default_normal_map_texels(256), dataclasses.replace(opts, bits=8))
    path = _input_file(Path(base_dir), ref, "normal_map", where, "normal map")
    if path.suffix.lower() == ".dds":  # BC5 or DXT5nm: two 8-bit channels
        if opts.encoding != "unsigned" or opts.space != "tangent":
            raise ValueError(f"{w}{ref!r}: a DDS map is an unsigned tangent-space map")

        def dds():
            from .storage import load_dds_normal_map

            m = _reading(w, load_dds_normal_map, path)
            return m.texels.astype(np.float32), m.options(opts)
        return dds
    if opts.encoding == "signed" and path.suffix.lower() in _INTEGER_IMAGES:
        raise ValueError(f"{w}{ref!r}: encoding 'signed' needs float data (.npy/.npz); an "
                         "8/16-bit image stores unsigned values")

    def image():
        raw, bits = _reading(w, io.load_texture, path, channels=opts.channels)
        if opts.encoding == "signed" and bits in (8, 16):
            raise ValueError(f"{w}{ref!r}: encoding 'signed' needs float data (.npy/.npz); an "
                             "8/16-bit image stores unsigned values")
        if opts.space == "tangent":
            io.check_tangent_normal_map(raw, encoding=opts.encoding, channels=opts.channels,
                                        source=f"{w}{ref}", hint=OBJECT_SPACE_HINT)
        return raw.astype(np.float32), dataclasses.replace(
            opts, bits=bits if bits in (8, 16) else opts.bits)
    return image


def _height_map_loader(spec: Any, *, base_dir=".", where: str = ""):
    """Check a ``height_map`` entry (a path or an object with ``path``, ``scale`` in world
    units, ``uv_origin``, ``wrap``, ``filter``) and that its file exists; returns a function
    that reads it: ``() -> (derivative map, NormalMapOptions)``. The height map is rendered
    by surface-gradient bump mapping through its derivative map."""
    spec = _object(spec, "height_map", where)
    w = f"{where}height_map: "
    _keys(spec, ("path", "scale", "uv_origin", "wrap", "filter"), w)
    ref = spec.pop("path")
    scale = _field(spec, "scale", float, 0.02, w)
    spec.pop("scale", None)
    opts = _map_options(spec, ("uv_origin", "wrap", "filter"), w, encoding="signed",
                        channels=2, space="derivative")
    if opts.wrap == "mirror":
        raise ValueError(f"{w}'wrap' must be 'repeat' or 'clamp'")
    path = _input_file(Path(base_dir), ref, "height_map", where, "texture")

    def load():
        raw, _ = _reading(w, io.load_texture, path, channels=1)
        d = np.array(height_to_derivative_map(raw[..., 0], scale=scale, wrap=opts.wrap))
        if opts.uv_origin == "top_left":  # v grows down the image: dh/dv changes sign
            d[..., 1] = -d[..., 1]
        return d.astype(np.float32), opts
    return load


def load_height_map(spec: Any, *, base_dir=".", where: str = ""):
    """``(derivative map, NormalMapOptions)`` from a scene file's ``height_map`` entry
    ``spec`` (paths relative to ``base_dir``; ``where`` names the entry in errors), read at
    once."""
    return _height_map_loader(spec, base_dir=base_dir, where=where)()


def _albedo_loader(spec: Any, base: Path, where: str):
    """Check a scene's ``albedo`` (an RGB list, a path or ``{"path", "srgb"}``); returns a
    function giving the linear albedo (RGB, or an (h, w, 3) texture)."""
    if isinstance(spec, (list, tuple)):
        rgb = _colour(spec, "albedo", where).astype(np.float32)
        return lambda: rgb
    if not isinstance(spec, (str, dict)):
        raise ValueError(f"{where}'albedo' must be an RGB list, a path or {{'path', 'srgb'}}")
    spec = _object(spec, "albedo", where)
    _keys(spec, ("path", "srgb"), f"{where}albedo: ")
    srgb = _field(spec, "srgb", bool, True, f"{where}albedo: ")
    path = _input_file(base, spec["path"], "albedo", where, "texture")

    def load():
        tex, _ = _reading(f"{where}albedo: ", io.load_texture, path, channels=3)
        return np.asarray(srgb_to_linear(tex) if srgb else tex, np.float32)
    return load


def _mesh_loader(ref: Any, base: Path, where: str):
    """Check a scene's ``mesh`` (a file path or ``"builtin:<name>"``); returns a function
    that reads it."""
    if not isinstance(ref, str):
        raise ValueError(f"{where}'mesh' must be a file path or 'builtin:<name>'")
    if ref.startswith("builtin:"):
        name = ref.split(":", 1)[1]
        if name not in BUILTIN_MESHES:
            raise ValueError(f"{where}'mesh': unknown built-in mesh {name!r}; expected one of "
                             f"{', '.join(BUILTIN_MESHES)}")
        return lambda: builtin_mesh(name)
    path = _input_file(base, ref, "mesh", where, "mesh")
    return lambda: _reading(f"{where}mesh: ", io.load_mesh, path)


# --------------------------------------------------------------------------------------
# scene files
# --------------------------------------------------------------------------------------


def load_scene(path) -> Scene:
    """Read a scene JSON file (see the module docstring); errors name the file and the key."""
    path = Path(path)
    return scene_from_dict(io.load_json(path), base_dir=path.parent, source=str(path))


def scene_from_dict(data: dict, *, base_dir=".", source: str = "<dict>") -> Scene:
    """Build a `Scene` from a parsed scene JSON object; errors start with ``source``. Every
    field is checked, and every file it names found, before any file is read."""
    return _scene_loader(data, base_dir=base_dir, source=source)()


def _scene_loader(data: Any, *, base_dir=".", source: str = "<dict>"):
    """Check a parsed scene JSON object, every field and that every file it names exists,
    without reading any; returns a function that reads them and builds the `Scene`. The
    function has ``width``, ``height`` and ``camera`` attributes (a fit file's default
    view)."""
    where = f"{source}: "
    if not isinstance(data, dict):
        raise ValueError(f"{where}a scene must be a JSON object, got {type(data).__name__}")
    if "targets" in data and not set(data) & {"mesh", "camera"}:
        raise ValueError(f"{where}a fit file (it has 'targets'), not a scene file: run it "
                         f"with `jaxnm fit`; the scene to render is the one its 'scene' names")
    _keys(data, SCENE_KEYS, where)
    base = Path(base_dir)
    width = _field(data, "width", int, 512, where)
    height = _field(data, "height", int, 512, where)
    if width <= 0 or height <= 0:
        raise ValueError(f"{where}'width' and 'height' must be positive, got {width}x{height}")
    frame = _field(data, "frame", str, "cotangent", where)
    try:
        frame = canonical_frame(frame)
    except ValueError as e:
        raise _rewrap(e, where) from None
    options = dict(frame=frame,
                   derivatives=_field(data, "derivatives", str, "fine", where),
                   precision=_field(data, "precision", str, "float32", where),
                   double_sided=_field(data, "double_sided", bool, True, where),
                   ddy=_field(data, "ddy", str, "up", where))
    cull = data.get("cull_back", "auto")  # auto: where no back face can be seen
    if cull != "auto" and not isinstance(cull, bool):
        raise ValueError(f"{where}'cull_back' must be true, false or \"auto\", got {cull!r}")
    camera = _parse_camera(data.get("camera"), aspect=width / height, where=where)
    lights = _parse_lights(data["lights"], where=where) if "lights" in data else None
    material, shading = _parse_material(data.get("material", {}), where=where)
    if "shading" in data:
        if "model" in data.get("material", {}):
            raise ValueError(f"{where}give the shading model as 'material.model' or 'shading', "
                             "not both")
        shading = _field(data, "shading", str, "blinn_phong", where)
    model = _matrix(data["model"], "model", where) if "model" in data else None
    tangent_mode = _field(data, "tangents", str, "auto", where)
    if tangent_mode not in TANGENT_MODES:
        raise ValueError(f"{where}'tangents' must be one of {', '.join(TANGENT_MODES)}, got "
                         f"{tangent_mode!r}")
    if data.get("normal_map") is not None and data.get("height_map") is not None:
        raise ValueError(f"{where}give either 'normal_map' or 'height_map', not both")
    check_scene_options(width=width, height=height, shading=shading, source=source, **options)
    if "mesh" not in data:
        raise ValueError(f"{where}missing required key 'mesh'")
    # the files: each found now, read below
    mesh_of = _mesh_loader(data["mesh"], base, where)
    map_of = None
    if data.get("normal_map") is not None:
        map_of = _normal_map_loader(data["normal_map"], base_dir=base, where=where)
    elif data.get("height_map") is not None:
        map_of = _height_map_loader(data["height_map"], base_dir=base, where=where)
    albedo_of = _albedo_loader(data.get("albedo", [0.8, 0.8, 0.8]), base, where)

    def load() -> Scene:
        mesh = mesh_of()
        if options["frame"] == "vertex" or tangent_mode == "mikktspace":
            if tangent_mode == "mikktspace" or mesh.tangents is None:
                if mesh.uv is None or mesh.normals is None:
                    raise ValueError(f"{where}frame 'vertex' needs a mesh with uvs and normals")
                mesh = mesh.with_tangents()  # MikkTSpace, once, at load
        nm, nm_opts = map_of() if map_of is not None else (None, NormalMapOptions())
        cull_back = back_faces_hidden(mesh, camera, model) if cull == "auto" else cull
        # the model stays a float64 matrix: render composes it with the camera in float64
        return validate_scene(Scene(
            mesh=mesh, camera=camera, width=width, height=height, normal_map=nm,
            normal_map_options=nm_opts, albedo=albedo_of(), lights=lights, material=material,
            model=model, shading=shading, source=source, cull_back=cull_back, **options))

    load.width, load.height, load.camera = width, height, camera
    return load


# --------------------------------------------------------------------------------------
# fit files
# --------------------------------------------------------------------------------------


def _image(path: Path, color_space: str | None, where: str) -> np.ndarray:
    img, bits = _reading(where, io.load_image_float, path)
    if img.ndim == 3 and img.shape[2] == 4:
        img = img[..., :3]
    if img.ndim != 3 or img.shape[2] != 3:
        raise ValueError(f"{where}{path}: a target must be an RGB image, got shape {img.shape}")
    if color_space is None:
        color_space = "srgb" if bits in (8, 16) else "linear"
    if not np.all(np.isfinite(img)):
        raise ValueError(f"{where}{path}: the target has NaN or infinite values")
    return np.asarray(srgb_to_linear(img)) if color_space == "srgb" else img


def _check_size(a: np.ndarray, width: int, height: int, what: str, where: str) -> None:
    if a.shape[:2] != (height, width):
        raise ValueError(f"{where}{what} is {a.shape[1]}x{a.shape[0]}, but its view renders "
                         f"{width}x{height}")


def _solver_options(spec: Any, where: str) -> tuple[FitOptions, float | None]:
    w = f"{where}solver: "
    if not isinstance(spec, dict):
        raise ValueError(f"{where}'solver' must be an object")
    _keys(spec, list(_SOLVER_KEYS) + ["time_limit"], w)
    kinds = {"method": str, "max_steps": int, "lsmr_steps": int, "coarse_to_fine": int,
             "seed": int, "patience": int, "texel_sums": str}
    values = {_SOLVER_KEYS[k]: _field(spec, k, kinds.get(k, float), None, w)
              for k in spec if k in _SOLVER_KEYS}
    time_limit = _field(spec, "time_limit", float, None, w)
    if time_limit is not None and not time_limit > 0:
        raise ValueError(f"{w}'time_limit' must be a positive number of seconds, got "
                         f"{time_limit}")
    try:
        return FitOptions(**values), time_limit
    except ValueError as e:
        raise ValueError(f"{w}{str(e).removeprefix('FitOptions: ')}") from None


def _output_map(spec: Any, where: str) -> tuple[tuple[int, int], NormalMapOptions]:
    w = f"{where}map: "
    if not isinstance(spec, dict):
        raise ValueError(f"{where}'map' must be an object")
    _keys(spec, ("size", "encoding", "green", "bits"), w)
    size = spec.get("size", [256, 256])
    if isinstance(size, int) and not isinstance(size, bool):
        size = [size, size]
    if (not isinstance(size, list) or len(size) != 2
            or any(isinstance(s, bool) or not isinstance(s, int) or s < 2 for s in size)):
        raise ValueError(f"{w}'size' must be an integer or two integers >= 2 (height, width), "
                         f"got {spec.get('size')!r}")
    opts = _map_options({k: spec[k] for k in ("encoding", "green", "bits") if k in spec},
                        ("encoding", "green", "bits"), w)
    if opts.bits not in (8, 16):
        raise ValueError(f"{w}'bits' must be 8 or 16, got {opts.bits!r}")
    if opts.encoding == "signed":
        raise ValueError(f"{w}'encoding' must be 'unsigned' or 'unsigned_exact' (a PNG stores "
                         "unsigned values)")
    return (size[0], size[1]), opts


def load_fit(path, *, images=None) -> FitJob:
    """Read a fit file (see the module docstring) into a `FitJob`; every field is checked
    before anything is rendered or compiled. ``images``: see `fit_from_dict`."""
    path = Path(path)
    return fit_from_dict(io.load_json(path), base_dir=path.parent, source=str(path),
                         images=images)


def fit_from_dict(data: dict, *, base_dir=".", source: str = "<dict>",
                  images=None) -> FitJob:
    """Build a `FitJob` from a parsed fit JSON object; errors start with ``source``. Every
    field, of the fit file and of its scene file, is checked and every file they name found
    before any is read; then the images (each checked against its view's size), the ground
    truth and the scene's files are read.

    ``images``: None (read every image), or a function ``images(key, targets)`` given
    ``"targets"`` or ``"held_out"`` and those targets without their images (``image`` and
    ``mask`` None), returning the indices of the ones whose image and mask to read (the
    others keep None): a process of a fit across processes reads its own views only
    (`jaxnm.fit.process_targets`)."""
    where = f"{source}: "
    base = Path(base_dir)
    if not isinstance(data, dict):
        raise ValueError(f"{where}a fit file must be a JSON object")
    if "mesh" in data and "targets" not in data:
        name = "scene.json" if source.startswith("<") else Path(source).name
        raise ValueError(f"{where}a scene file (it has 'mesh'), not a fit file: a fit file "
                         f"names its scene (\"scene\": \"{name}\") and lists its 'targets'")
    _keys(data, FIT_KEYS, where)
    options, time_limit = _solver_options(data.get("solver", {}), where)
    map_size, output = _output_map(data.get("map", {}), where)
    for key in ("targets", "held_out", "views"):
        if key in data and not isinstance(data[key], list):
            raise ValueError(f"{where}'{key}' must be a list")
    if not data.get("targets"):
        raise ValueError(f"{where}'targets' must be a non-empty list")
    if "scene" not in data or not isinstance(data["scene"], str):
        raise ValueError(f"{where}'scene' must name a scene JSON file (the mesh and material)")
    scene_path = _input_file(base, data["scene"], "scene", where)
    scene_of = _scene_loader(io.load_json(scene_path), base_dir=scene_path.parent,
                             source=str(scene_path))
    views = _views(data.get("views", []), scene_of, where)
    specs = {key: [_target_spec(t, i, key, views, base, where)
                   for i, t in enumerate(data.get(key, []))] for key in ("targets", "held_out")}
    _warn_repeats(data, base, where)
    truth_of = (_ground_truth_loader(data["ground_truth"], base, map_size, where)
                if "ground_truth" in data else None)

    def read(key):  # the images, each checked against its view
        bare = tuple(spec[0] for spec in specs[key])
        wanted = range(len(bare)) if images is None else set(images(key, bare))
        return tuple(_read_target(*spec) if i in wanted else spec[0]
                     for i, spec in enumerate(specs[key]))

    targets, held = read("targets"), read("held_out")
    gt = truth_of() if truth_of is not None else None
    problem = problem_from_scene(scene_of(), targets, map_size, source=source)
    try:
        return FitJob(problem=problem, options=options, ground_truth=gt, held_out=held,
                      output=output, time_limit=time_limit)
    except ValueError as e:
        raise ValueError(str(e)) from None


def _views(specs: list, scene_of, where: str) -> list:
    """``(camera, width, height)`` of each of a fit file's ``views`` (default: the scene's
    camera)."""
    views = []
    for i, v in enumerate(specs):
        w = f"{where}views[{i}]: "
        if not isinstance(v, dict):
            raise ValueError(f"{w}must be an object with 'camera', 'width', 'height'")
        _keys(v, ("camera", "width", "height"), w)
        width = _field(v, "width", int, scene_of.width, w)
        height = _field(v, "height", int, scene_of.height, w)
        if width <= 0 or height <= 0:
            raise ValueError(f"{w}'width' and 'height' must be positive")
        views.append((_parse_camera(v.get("camera"), aspect=width / height, where=w), width,
                      height))
    return views or [(scene_of.camera, scene_of.width, scene_of.height)]


def _target_spec(t: Any, i: int, key: str, views: list, base: Path, where: str):
    """A fit file's ``targets[i]`` (or ``held_out[i]``) checked, its files found: ``(the
    target without its image, image path, colour space, mask path or None, where)``."""
    w = f"{where}{key}[{i}]: "
    if not isinstance(t, dict) or "image" not in t or "lights" not in t:
        raise ValueError(f"{w}needs 'image' and 'lights'")
    _keys(t, ("view", "image", "lights", "mask", "color_space"), w)
    vi = _field(t, "view", int, 0, w)
    if not 0 <= vi < len(views):
        there = "there is 1 view" if len(views) == 1 else f"there are {len(views)} views"
        raise ValueError(f"{w}'view' = {vi} but {there}")
    color_space = _field(t, "color_space", str, None, w)
    if color_space not in (None, "srgb", "linear"):
        raise ValueError(f"{w}'color_space' must be 'srgb' or 'linear', got {color_space!r}")
    image = _input_file(base, t["image"], "image", w, "image")
    mask = _input_file(base, t["mask"], "mask", w, "texture") if "mask" in t else None
    lights = _parse_lights(t["lights"], where=w)
    cam, width, height = views[vi]
    bare = FitTarget(cam, width, height, lights, None, None, name=f"{key}[{i}] ({t['image']})")
    return bare, image, color_space, mask, w


def _warn_repeats(data: dict, base: Path, where: str) -> None:
    """Warn for a target listed twice (the same view, image, mask, colour space and lights:
    it counts twice in the fit), or held out and fitted both (its score is no held-out one)."""
    seen = {}
    for key in ("targets", "held_out"):
        for i, t in enumerate(data.get(key, [])):
            same = {k: v for k, v in t.items() if k not in ("image", "mask", "view")}
            same.update(view=t.get("view", 0), image=str((base / t["image"]).resolve()),
                        mask=str((base / t["mask"]).resolve()) if "mask" in t else None)
            first = seen.setdefault(json.dumps(same, sort_keys=True), f"{key}[{i}]")
            if first != f"{key}[{i}]":
                why = ("so it counts twice in the fit" if key == "targets" else
                       "so its score is not a held-out one" if first.startswith("targets")
                       else "so it is scored twice")
                warnings.warn(f"{where}{key}[{i}] repeats {first} (the same view, image and "
                              f"lights), {why}", io.JaxnmWarning, stacklevel=2)


def _read_target(bare: FitTarget, image: Path, color_space, mask: Path | None,
                 where: str) -> FitTarget:
    """``bare`` with its image (linear RGB) and mask read, each the size of its view."""
    img = _image(image, color_space, f"{where}image: ")
    _check_size(img, bare.width, bare.height, f"image: {image}", where)
    m = None
    if mask is not None:
        m = _reading(f"{where}mask: ", io.load_texture, mask)[0][..., 0] > 0.5
        _check_size(m, bare.width, bare.height, f"mask: {mask}", where)
    return dataclasses.replace(bare, image=img, mask=m)


def _ground_truth_loader(spec: Any, base: Path, map_size: tuple[int, int], where: str):
    """Check a fit file's ``ground_truth`` and that its file exists; returns a function that
    reads it: unit normals (h, w, 3), float32, the map's size."""
    spec = _object(spec, "ground_truth", where)
    w = f"{where}ground_truth: "
    _keys(spec, ("path", "encoding", "green"), w)
    opts = _map_options({k: v for k, v in spec.items() if k != "path"}, ("encoding", "green"),
                        w)
    path = _input_file(base, spec["path"], "ground_truth", where, "texture")

    def load():
        raw, bits = _reading(w, io.load_texture, path, channels=3)
        if raw.shape[:2] != tuple(map_size):
            raise ValueError(f"{w}{path} is {raw.shape[1]}x{raw.shape[0]}, but the map is "
                             f"{map_size[1]}x{map_size[0]}")
        io.check_tangent_normal_map(raw, encoding=opts.encoding, source=f"{w}{spec['path']}",
                                    hint="a fit's ground truth is a tangent-space map")
        gt = np.asarray(decode_normal_map(jnp.asarray(raw), encoding=opts.encoding,
                                          green=opts.green, bits=bits if bits in (8, 16)
                                          else 8), np.float64)
        return (gt / np.linalg.norm(gt, axis=-1, keepdims=True)).astype(np.float32)
    return load
