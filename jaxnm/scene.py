"""Scenes: everything a render needs, as one pytree.

A `Scene` holds arrays (the mesh, the camera, the normal map, the albedo, the
lights, the material), which may be traced — ``jax.grad`` of a loss of
``render(scene.replace(normal_map=x))`` differentiates through the whole
renderer — and static options (image size, frame method, derivative mode, ...),
each validated by the stage that owns its vocabulary. Scene files are read by
`jaxnm.config.load_scene`; the built-in scene is `jaxnm.procedural.default_scene`.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array

from ._host_geometry import box_in_front, clip_float64, closed_shape
from .camera import Camera
from .frames import check_frame
from .geometry import Mesh, check_mesh_arrays
from .interpolate import check_derivatives, check_precision
from .numerics import safe_normalize
from .shading import DirectionalLight, Lights, Material, check_shading_model, stack_lights
from .textures import NormalMapOptions

__all__ = [
    "Scene", "validate_scene", "check_scene_shapes", "default_lights", "default_material",
    "back_faces_hidden", "MAX_IMAGE_SIZE", "DDY_CONVENTIONS", "check_scene_options"
]

#: The largest image width or height a scene may ask for.
MAX_IMAGE_SIZE = 16384
#: ``ddy="up"``: GLSL's dFdy (window y up); ``"down"``: emulate HLSL's ddy.
DDY_CONVENTIONS = ("up", "down")


def _static(default):
    return dataclasses.field(default=default, metadata=dict(static=True))


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Scene:
    """A mesh, a camera, maps, lights, a material and the render options.

    **Arrays** (pytree leaves, may be traced):
    - `mesh`: a `Mesh` (world space).
    - `camera`: a `Camera`.
    - `normal_map`: the *stored* texel values (H, W, C) in image layout, before
      decoding (e.g. in [0, 1] for unsigned encodings), or None; decoded
      following `normal_map_options`.
    - `albedo`: linear RGB, a constant (3,) or a texture (H, W, 3).
    - `lights`: `Lights`; `material`: a `Material`. None means the defaults
      (`default_lights`, `default_material`).
    - `model`: (4, 4) affine object-to-world matrix of the mesh (column vectors),
      or None for the identity. Keep it float64 (a NumPy array) for geometry far
      from the origin: `jaxnm.render` composes it with the camera in float64
      and renders camera-relative, so a mesh a million units out renders like
      one at the origin.

    **Options** (static, checked when the scene is constructed):
    - `width`, `height`: image size in pixels.
    - `normal_map_options`: a `jaxnm.textures.NormalMapOptions`.
    - `shading`: one of `jaxnm.shading.SHADING_MODELS`.
    - `frame`: one of `jaxnm.frames.FRAMES`.
    - `derivatives`: one of `jaxnm.interpolate.DERIVATIVE_MODES`.
    - `precision`: the fragment shader's arithmetic, one of `jaxnm.interpolate.PRECISIONS`
      (``"float16"`` models GLSL ``mediump``: the frame and the perturbation are computed
      in it from rounded inputs; see `jaxnm.interpolate.at_precision`).
    - `double_sided`: flip N, T and B on back faces; `cull_back`: skip back faces, which
      changes nothing but the time where none can be seen (`back_faces_hidden` says
      when; `jaxnm.config.load_scene` and the built-in scenes set it so).
    - `ddy`: ``"up"`` (GLSL ``dFdy``) or ``"down"`` (emulate HLSL's ``ddy``).
    - `source`: where the scene came from (named in error messages).
    """

    mesh: Mesh
    camera: Camera
    normal_map: Array | None = None
    albedo: Array = dataclasses.field(
        default_factory=lambda: np.array([0.8, 0.8, 0.8], np.float32))
    lights: Lights | None = None
    material: Material | None = None
    model: Array | None = None
    width: int = _static(512)
    height: int = _static(512)
    normal_map_options: NormalMapOptions = _static(NormalMapOptions())
    shading: str = _static("blinn_phong")
    frame: str = _static("cotangent")
    derivatives: str = _static("fine")
    precision: str = _static("float32")
    double_sided: bool = _static(True)
    cull_back: bool = _static(False)
    ddy: str = _static("up")
    source: str = _static("<scene>")

    def __post_init__(self):
        # Only the static options are checked here: a pytree is rebuilt with placeholder or
        # traced leaves inside JAX transformations, so the arrays are checked by
        # `validate_scene`, where scenes are made.
        check_scene_options(width=self.width, height=self.height,
                            normal_map_options=self.normal_map_options, shading=self.shading,
                            frame=self.frame, derivatives=self.derivatives,
                            precision=self.precision,
                            double_sided=self.double_sided, cull_back=self.cull_back,
                            ddy=self.ddy, source=self.source)

    def replace(self, **changes) -> Scene:
        """A copy with some fields changed (the options checked again; the arrays are not:
        `validate_scene` checks them)."""
        return dataclasses.replace(self, **changes)


def check_scene_options(*, width=512, height=512, normal_map_options=NormalMapOptions(),
                        shading="blinn_phong", frame="cotangent", derivatives="fine",
                        precision="float32", double_sided=True, cull_back=False, ddy="up",
                        source="<scene>") -> None:
    """Raise a `ValueError` naming ``source`` unless the static options of a `Scene` are valid
    (each vocabulary is checked by the stage that owns it): what constructing a `Scene`
    checks, for a caller that has the options before the arrays (a scene file, before its
    mesh is read)."""
    src = source
    for name, v in (("width", width), ("height", height)):
        if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v <= 0:
            raise ValueError(f"{src}: `{name}` must be a positive integer, got {v!r}")
        if v > MAX_IMAGE_SIZE:
            raise ValueError(f"{src}: `{name}` = {v} is larger than the supported "
                             f"{MAX_IMAGE_SIZE}")
    if not isinstance(normal_map_options, NormalMapOptions):
        raise ValueError(f"{src}: `normal_map_options` must be a NormalMapOptions, got "
                         f"{type(normal_map_options).__name__}")
    try:
        check_frame(frame)
        check_derivatives(derivatives, allow_none=False)
        check_precision(precision)
        check_shading_model(shading)
    except ValueError as e:
        raise ValueError(f"{src}: {e}") from None
    if ddy not in DDY_CONVENTIONS:
        raise ValueError(f"{src}: `ddy` must be 'up' (GLSL dFdy) or 'down' (HLSL ddy), got "
                         f"{ddy!r}")
    for name, v in (("double_sided", double_sided), ("cull_back", cull_back)):
        if not isinstance(v, bool):
            raise ValueError(f"{src}: `{name}` must be true or false, got {v!r}")


def _is_concrete(x) -> bool:
    return not isinstance(x, jax.core.Tracer)


def check_scene_shapes(scene: Scene) -> None:
    """Raise a `ValueError` naming ``scene.source`` unless the scene's arrays have usable
    shapes and dtypes: the mesh's, a normal map (H, W, C) of floats with enough channels, an
    albedo (3,) or (H, W, 3), a 4x4 model, and uvs where a map or texture needs them.
    Shapes only (known for traced arrays too, and no pass over the values): what
    `jaxnm.render.render` checks on every call, and the first step of `validate_scene`.
    Anything but a `Scene` raises a `TypeError`."""
    if not isinstance(scene, Scene):
        raise TypeError(f"expected a jaxnm Scene (jaxnm.config.load_scene, "
                        f"jaxnm.procedural.default_scene), got {type(scene).__name__}")
    src = scene.source
    _check_types(scene, src)
    m = scene.mesh
    check_mesh_arrays(m.positions, m.faces, m.uv, m.normals, source=src, values=False)
    opts = scene.normal_map_options
    if scene.normal_map is not None:
        shape = np.shape(scene.normal_map)
        if len(shape) != 3 or shape[2] < opts.channels or min(shape[:2]) < 1:
            raise ValueError(f"{src}: the normal map must have shape (H, W, C) with C >= "
                             f"{opts.channels} (normal_map_options.channels), got {shape}")
        if not jnp.issubdtype(jnp.result_type(scene.normal_map), jnp.floating):
            raise ValueError(f"{src}: the normal map must hold floating-point values "
                             f"(e.g. in [0, 1] for unsigned encodings), got "
                             f"{jnp.result_type(scene.normal_map)}")
        if opts.space in ("tangent", "derivative") and m.uv is None:
            raise ValueError(f"{src}: the scene has a {opts.space}-space map but the mesh has "
                             "no texture coordinates (uv)")
    if scene.model is not None and np.shape(scene.model) != (4, 4):
        raise ValueError(f"{src}: the model matrix must be 4x4, got {np.shape(scene.model)}")
    a_shape = np.shape(scene.albedo)
    if a_shape != (3,) and not (len(a_shape) == 3 and a_shape[2] == 3):
        raise ValueError(f"{src}: the albedo must be an RGB constant (3,) or an RGB texture "
                         f"(H, W, 3), got shape {a_shape}")
    if len(a_shape) == 3 and m.uv is None:
        raise ValueError(f"{src}: the scene has an albedo texture but the mesh has no texture "
                         "coordinates (uv)")
    if scene.lights is not None and scene.lights.directional is None and (
            scene.lights.point is None):
        raise ValueError(f"{src}: the scene has no lights")


def _check_types(scene: Scene, src: str) -> None:
    """A `TypeError` naming the field of ``scene`` that holds the wrong kind of object."""
    kinds = (("mesh", Mesh, "jaxnm.io.load_mesh(path), or jaxnm.Mesh(positions, faces, "
              "uv=..., normals=...)"),
             ("camera", Camera, "jaxnm.Camera.look_at(eye, target, up), or "
              "Camera.from_matrices(view, projection)"),
             ("lights", Lights, "directional_light(...), or Lights(directional="
              "stack_lights([...]), point=...)"),
             ("material", Material, "jaxnm.shading.Material(...)"))
    for name, kind, how in kinds:
        value = getattr(scene, name)
        if not isinstance(value, kind) and (value is not None or name in ("mesh", "camera")):
            raise TypeError(f"{src}: {name} must be a jaxnm.{kind.__name__} ({how}), got "
                            f"{type(value).__name__}")
    for name in ("normal_map", "albedo", "model"):
        value = getattr(scene, name)
        try:
            np.shape(value)  # (which reads a traced array's shape too)
        except (TypeError, ValueError):
            hint = (" (jaxnm.io.load_texture returns (image, bits))"
                    if isinstance(value, tuple) and len(value) == 2
                    and isinstance(value[1], int) else "")
            raise TypeError(f"{src}: {name} must be an array, got a {type(value).__name__} "
                            f"whose items do not form one{hint}") from None


def validate_scene(scene: Scene) -> Scene:
    """Check a scene's arrays and fill in the default lights and material.

    Raises a `ValueError` naming ``scene.source`` for unusable input: mesh
    arrays of the wrong shape, NaN or out-of-range indices, a tangent-space
    map without uvs, a normal map or albedo of the wrong shape, no lights, a model
    matrix that is not affine and invertible, or a camera that sees no vertex in front of
    its near plane. Value checks run only on concrete arrays (never on tracers, so this is
    safe under ``jax.grad``/``jax.jit``); shape checks always run. Scene files
    (`jaxnm.config.load_scene`) and the built-in scenes are checked so when they are made;
    `jaxnm.render.render` checks its options and the arrays' shapes (`check_scene_shapes`)
    on every call, not their values.
    """
    check_scene_shapes(scene)
    src = scene.source
    m = scene.mesh
    check_mesh_arrays(m.positions, m.faces, m.uv, m.normals, source=src)
    if scene.model is not None and _is_concrete(scene.model):
        m64 = np.asarray(scene.model, np.float64)
        if not np.all(np.isfinite(m64)) or not np.allclose(m64[3], [0, 0, 0, 1]):
            raise ValueError(f"{src}: the model matrix must be finite and affine (last row "
                             "0, 0, 0, 1)")
        if abs(np.linalg.det(m64[:3, :3])) < 1e-12:
            raise ValueError(f"{src}: the model matrix is singular")
    lights = default_lights(scene.camera) if scene.lights is None else scene.lights
    material = default_material() if scene.material is None else scene.material
    if scene.lights is None or scene.material is None:
        scene = dataclasses.replace(scene, lights=lights, material=material)
    _check_near_plane(scene)
    return scene


def back_faces_hidden(mesh: Mesh, camera: Camera, model=None) -> bool:
    """Whether ``camera`` can see none of ``mesh``'s back faces, so that a `Scene` may set
    ``cull_back`` and still show every pixel's nearest triangle: the mesh encloses a volume
    with its front faces outside (after welding vertices at equal positions, every edge is
    used by exactly two faces, once in each direction, and the enclosed volume is positive),
    ``model`` (object to world, or None) does not mirror it, and the corners of its bounding
    box are all in front of the near plane (so no part is clipped open and the camera is
    outside). Every ray from the eye then meets the surface first where it enters the
    volume, through a front face. On the host (concrete arrays; a pass over the mesh in
    NumPy), so decide it once per mesh and camera: `jaxnm.config.load_scene` and the
    built-in scenes do. The same triangles win as without culling, except where a back face
    had tied with the front face before it at a silhouette (a few pixels a frame)."""
    box = closed_shape(mesh.positions, mesh.faces)
    return box is not None and box_in_front(box, camera, model)


def _check_near_plane(scene: Scene) -> None:
    """Refuse a camera that cannot see the mesh: every vertex behind the near plane."""
    leaves = jax.tree_util.tree_leaves((scene.mesh.positions, scene.camera))
    if not all(_is_concrete(x) for x in leaves):
        return
    if scene.model is not None and not _is_concrete(scene.model):
        return
    positions = np.asarray(scene.mesh.positions)

    def any_in_front(p):  # float64 NumPy (no traced op inside jit)
        clip = clip_float64(p, scene.camera, scene.model)
        return bool(np.any(clip[:, 2] >= -clip[:, 3]))

    # a few hundred vertices usually settle it; all of them only when none of those is seen
    stride = max(1, positions.shape[0] // 256)
    if not (any_in_front(positions[::stride]) or any_in_front(positions)):
        raise ValueError(f"{scene.source}: every vertex of the mesh is behind the camera's near "
                         "plane (is the camera inside the object, or looking away from it?)")


def default_material() -> Material:
    """Blinn-Phong: white diffuse, a grey highlight (0.35, shininess 48), a little ambient."""
    return Material(diffuse=jnp.array([1.0, 1.0, 1.0]), specular=jnp.array([0.35, 0.35, 0.35]),
                    shininess=jnp.asarray(48.0), ambient=jnp.array([0.04, 0.04, 0.04]))


def default_lights(camera: Camera) -> Lights:
    """One white directional light from the camera's upper left (traceable in ``camera``)."""
    rot = jnp.asarray(camera.view)[:3, :3]  # world -> eye
    d = jnp.linalg.solve(rot, jnp.array([-0.5, 0.6, 1.0], rot.dtype))
    return Lights(directional=stack_lights([DirectionalLight(
        safe_normalize(d).astype(jnp.float32), jnp.ones(3), jnp.asarray(1.0))]))
