"""The pipeline: scene -> rasterize -> interpolate -> derivatives -> frame -> texture -> shade.

It is split where the data stop depending on the geometry:

- `build_gbuffer` runs everything that depends only on the mesh and the camera:
  visibility, perspective-correct ``p``, ``uv``, ``N`` and their screen
  derivatives, the tangent frame, the texture sample *plan* of the normal map
  (texel indices and filter weights, including the mip level of detail) and
  the albedo. A normal-map fit computes this once.
- `shade_gbuffer` runs what depends on the normal-map texels, the lights and
  the material: a gather and a weighted sum per pixel, the decode, the
  perturbation and the shading. This is what a fit differentiates, per step.

`render` composes both and computes only the stages that the requested
outputs need ("model only what a scene needs").
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array

from . import frames as _frames
from . import maps as _maps
from . import textures as _tex
from ._exec import pixels
from ._exec.fusion import materialize
from .camera import Camera, to_clip
from .geometry import Mesh
from .interpolate import (
    Attribute,
    _check_derivatives,
    _check_precision,
    _require_x64,
    _triangle_corners,
    at_precision,
    barycentrics,
    interpolate,
)
from .numerics import safe_normalize
from .raster import Fragments, compact, rasterize, triangle_ids
from .scene import Scene, _check_scene_shapes, default_lights, default_material
from .shading import Lights, Material, _check_shading_model, shade
from .textures import NormalMapOptions

__all__ = ["OUTPUTS", "GBuffer", "RenderOptions", "build_gbuffer", "covered_gbuffer",
           "shade_gbuffer", "render"]

#: Every output `render` can produce (image layout, row 0 = top, float32 (H, W, C)).
OUTPUTS = ("mask", "triangle_id", "depth", "front_facing", "position", "view", "uv", "normal",
           "dpdx", "dpdy", "duvdx", "duvdy", "tangent", "bitangent", "perturbed_normal",
           "color")

_GEOMETRY_OUTPUTS = {"mask", "triangle_id", "depth", "front_facing"}
_NEEDS_P = {"position", "view", "dpdx", "dpdy", "color", "tangent", "bitangent",
            "perturbed_normal"}
_NEEDS_FRAME = {"tangent", "bitangent", "perturbed_normal", "color"}


@dataclasses.dataclass(frozen=True)
class RenderOptions:
    """Static render configuration (hashable; a `jax.jit` static argument), validated when
    constructed. `RenderOptions.of` derives it from a `Scene`."""

    width: int
    height: int
    derivatives: str = "fine"
    frame: str = "cotangent"
    precision: str = "float32"
    shading: str = "blinn_phong"
    double_sided: bool = True
    cull_back: bool = False
    ddy_sign: int = 1
    normal_map: NormalMapOptions | None = NormalMapOptions()
    normal_map_shape: tuple[int, int] | None = None
    albedo_shape: tuple[int, int] | None = None  # None: a constant albedo
    outputs: tuple[str, ...] = ("color",)

    def __post_init__(self):
        _check_derivatives(self.derivatives, allow_none=False)
        _check_precision(self.precision)
        _frames._check_frame(self.frame)
        _check_shading_model(self.shading)
        bad = [o for o in self.outputs if o not in OUTPUTS]
        if bad or not isinstance(self.outputs, tuple):
            raise ValueError(f"unknown outputs {bad or self.outputs!r}; expected a tuple of "
                             f"any of {OUTPUTS}")
        if self.ddy_sign not in (1, -1):
            raise ValueError(f"RenderOptions: ddy_sign must be 1 or -1, got {self.ddy_sign!r}")

    @staticmethod
    def of(scene: Scene, *, outputs=("color",), derivatives=None, frame=None,
           precision=None) -> RenderOptions:
        """The options that render ``outputs`` of ``scene`` (``derivatives``, ``frame`` and
        ``precision`` override the scene's)."""
        nm = scene.normal_map
        alb = jnp.shape(scene.albedo)
        return RenderOptions(
            width=int(scene.width), height=int(scene.height),
            derivatives=scene.derivatives if derivatives is None else derivatives,
            frame=scene.frame if frame is None else frame,
            precision=scene.precision if precision is None else precision,
            shading=scene.shading,
            double_sided=scene.double_sided, cull_back=scene.cull_back,
            ddy_sign=1 if scene.ddy == "up" else -1,
            normal_map=None if nm is None else scene.normal_map_options,
            normal_map_shape=None if nm is None else tuple(jnp.shape(nm)[:2]),
            albedo_shape=tuple(alb[:2]) if len(alb) == 3 else None,
            outputs=tuple(dict.fromkeys(outputs)))

    @property
    def levels(self) -> int:
        if self.normal_map_shape is None:
            return 1
        if self.normal_map.filter != "trilinear":
            return 1
        return len(_tex.mip_sizes(self.normal_map_shape))


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class GBuffer:
    """Per-pixel geometry (image layout); fields not needed by the options are None.

    ``frame`` is the (face-forwarded) tangent frame, ``plan`` the normal map's
    sample plan, ``albedo`` the sampled linear albedo (H, W, 3).
    """

    mask: Array
    triangle_id: Array
    depth: Array
    front_facing: Array
    position: Array | None = None
    view: Attribute | None = None
    uv: Attribute | None = None
    normal: Array | None = None
    frame: _frames.Frame | None = None
    plan: _tex.SamplePlan | None = None
    albedo: Array | None = None
    eye: Array | None = None


def _needs(opts: RenderOptions):
    """Which stages the requested outputs need: (map, frame, tangent frame, uv, p, N)."""
    out = set(opts.outputs)
    need_p = False
    need_frame = bool(out & _NEEDS_FRAME)
    has_map = opts.normal_map is not None and opts.frame != "none" and bool(
        out & {"perturbed_normal", "color"})
    # the named frame (T and B) only when they are shown or a tangent-space map uses them
    need_tb = opts.frame != "none" and (bool(out & {"tangent", "bitangent"}) or (
        has_map and opts.normal_map.space == "tangent"))
    if has_map and opts.normal_map.space == "derivative":
        need_p = True  # the surface gradient needs the position's screen derivatives
    need_uv = bool(out & {"uv", "duvdx", "duvdy"}) or (need_tb and opts.frame != "axis") or (
        has_map) or (
        "color" in out and opts.albedo_shape is not None)
    need_p = need_p or bool(out & _NEEDS_P)
    need_n = bool(out & ({"normal"} | _NEEDS_FRAME))
    return has_map, need_frame, need_tb, need_uv, need_p, need_n


def _check_mesh(mesh: Mesh, opts: RenderOptions, source: str = "render") -> None:
    """Raise a clear `ValueError` if ``mesh`` lacks an attribute the requested outputs need."""
    has_map, _, need_tb, need_uv, _, need_n = _needs(opts)
    if need_uv and mesh.uv is None:
        why = "a normal map" if has_map else f"the outputs {list(opts.outputs)}"
        raise ValueError(f"{source}: the mesh has no texture coordinates (uv), needed for {why}")
    if need_n and mesh.normals is None:
        raise ValueError(f"{source}: the mesh has no vertex normals, needed for "
                         f"{list(opts.outputs)} (compute them with Mesh.with_normals())")
    if need_tb and opts.frame == "vertex" and mesh.tangents is None:
        raise ValueError(f"{source}: frame 'vertex' needs the mesh's MikkTSpace tangents "
                         "(Mesh.with_tangents(), or a glTF file's TANGENT attribute)")


@functools.partial(jax.jit, static_argnames=("opts",))
def build_gbuffer(mesh: Mesh, camera: Camera, albedo: Array, *, opts: RenderOptions) -> GBuffer:
    """Rasterize and interpolate; build the frame and the normal map's sample plan.

    **Arguments:**
    - `mesh`, `camera`: the geometry (world space).
    - `albedo`: (3,) constant or (H, W, 3) linear texture.
    - `opts`: a `RenderOptions` (static).
    """
    _check_mesh(mesh, opts)
    return _gbuffer_from_fragments(mesh, camera, albedo, _visibility(mesh, camera, opts),
                                  opts=opts)


def covered_gbuffer(mesh: Mesh, camera: Camera, albedo: Array, *,
                    opts: RenderOptions) -> tuple[GBuffer, Array, int]:
    """`build_gbuffer` for the covered pixels only: ``(gbuffer, index, count)``.

    Rasterizes (`_visible_placed`), counts the covered pixels on the host, and runs the per-pixel
    stages on them packed (`jaxnm.raster.compact`) into image / 2^k slots. The G-buffer's
    per-pixel fields have a leading axis of slots, of which the first ``count`` are the
    covered pixels in row-major image order (row 0 at the top); ``index`` (slots,) holds
    their flat image indices (``H * W`` for unused slots). The values equal
    `build_gbuffer`'s at those pixels to float32 rounding. The mesh and camera must be
    concrete; "gbuffer" derivatives (stored neighbours) need the whole image: use
    `build_gbuffer` there. A fit's `jaxnm.fit.prepare` builds each view from this.
    """
    if opts.derivatives == "gbuffer":
        raise ValueError("covered_gbuffer: 'gbuffer' derivatives need the whole image's "
                         "G-buffer (build_gbuffer)")
    _check_mesh(mesh, opts)
    # render's visibility program: a fit's targets rendered first leave it compiled
    tid, clip, orientation = _visible_placed(mesh, camera, _NO_SHIFT, width=opts.width,
                                             height=opts.height, cull_back=opts.cull_back,
                                             affine=False)
    count = int(np.count_nonzero(np.asarray(tid) >= 0))
    gb, index = _covered(mesh, camera, albedo, tid, clip, orientation, opts=opts,
                         capacity=pixels.capacity(count, opts.width * opts.height))
    return gb, index, count


@functools.partial(jax.jit, static_argnames=("opts", "capacity"))
def _covered(mesh: Mesh, camera: Camera, albedo, triangle_id, clip, orientation, *, opts,
             capacity):
    packed, index = _compact(mesh, camera, triangle_id, capacity, clip, orientation)
    return _gbuffer_from_fragments(mesh, camera, albedo, packed, opts=opts), index


def _compact(mesh: Mesh, camera: Camera, triangle_id: Array, capacity: int,
             clip: Array | None = None, orientation: Array | None = None):
    """`jaxnm.raster.compact` of ``mesh`` seen by ``camera``: (packed fragments, index);
    ``clip``, ``orientation``: the mesh's clip-space vertices and its triangles'
    orientations where the caller has them (`_visible_placed`)."""
    if clip is None:
        clip = to_clip(mesh.positions, camera)
    return compact(triangle_id, clip, mesh.faces.astype(jnp.int32), capacity,
                   orientation=orientation)


def _visibility(mesh: Mesh, camera: Camera, opts: RenderOptions):
    return rasterize(to_clip(mesh.positions, camera), mesh.faces, width=opts.width,
                     height=opts.height, cull_back=opts.cull_back)


def _gbuffer_from_fragments(mesh: Mesh, camera: Camera, albedo: Array, frags: Fragments, *,
                           opts: RenderOptions) -> GBuffer:
    """`build_gbuffer` after visibility: the per-pixel stages for ``frags``, a whole
    image's or packed ones (`jaxnm.raster.compact`; the G-buffer then has their shape)."""
    has_map, need_frame, need_tb, need_uv, need_p, need_n = _needs(opts)
    mask = frags.mask
    gb = dict(mask=mask, triangle_id=frags.triangle_id, depth=frags.depth,
              front_facing=frags.front_facing, eye=camera.eye)
    mode = opts.derivatives

    attrs = {}
    if need_p:
        attrs["view"] = mesh.positions - camera.eye[None, :]  # camera-relative: precise far out
    if need_uv:
        attrs["uv"] = mesh.uv
    # one evaluation of the barycentrics (the per-pixel corner gather and edge functions)
    # for every attribute interpolated below
    needs_bary = attrs or need_n or (need_tb and opts.frame in ("vertex", "vertex_area"))
    bary = (materialize(barycentrics(frags, derivatives=mode if attrs else None)) if needs_bary
            else None)
    if attrs:
        out = interpolate(attrs, frags, derivatives=mode, bary=bary)
        if need_p:
            gb["view"] = out["view"]
            view = out["view"].value
            gb["position"] = jnp.where(mask[..., None], view + _like(camera.eye, view), 0.0)
        if need_uv:
            gb["uv"] = out["uv"]
    if need_n:
        n = interpolate(mesh.normals, frags, derivatives=None, bary=bary).value
        gb["normal"] = materialize(safe_normalize(n))
    if need_frame:
        frame_opts = opts if need_tb else dataclasses.replace(opts, frame="none")
        gb["frame"] = materialize(_tangent_frame(frame_opts, mesh, frags, gb, bary))
    if has_map:
        nm = opts.normal_map
        gb["plan"] = _tex.plan_sample(gb["uv"], size_hw=opts.normal_map_shape, levels=opts.levels,
                                      filter=nm.filter, wrap=nm.wrap, uv_origin=nm.uv_origin)
    if "color" in opts.outputs:
        if opts.albedo_shape is None:
            gb["albedo"] = jnp.broadcast_to(jnp.asarray(albedo, jnp.float32),
                                            frags.shape + (3,))
        else:
            mips = _tex.build_mipmaps(albedo)
            gb["albedo"] = _tex.sample(mips, gb["uv"], filter="trilinear", wrap="repeat")
    return GBuffer(**gb)


def _like(v: Array, x: Array) -> Array:
    """A (3,) vector with leading axes to broadcast against the per-pixel array ``x``."""
    return jnp.asarray(v)[(None,) * (x.ndim - 1)]


def _tangent_frame(opts: RenderOptions, mesh: Mesh, frags, gb, bary) -> _frames.Frame:
    """The tangent frame named by ``opts.frame`` (face-forwarded when double-sided), computed
    at ``opts.precision`` from inputs rounded to it (`jaxnm.interpolate.at_precision`)."""
    kind, prec, mode = opts.frame, opts.precision, opts.derivatives

    def low(x):  # a shader input at the shader's precision
        return at_precision(Attribute(x), prec, frags.mask, derivatives=None).value

    inputs = {}
    n = low(gb["normal"])
    if kind in _frames.SCREEN_FRAMES:
        quads = None if frags.pixels is None else frags.window_pixels()
        inputs = dict(p_attr=at_precision(gb["view"], prec, frags.mask, derivatives=mode,
                                          pixels=quads),
                      uv_attr=at_precision(gb["uv"], prec, frags.mask, derivatives=mode,
                                           pixels=quads),
                      ddy_sign=opts.ddy_sign)
    elif kind in ("exact", "exact_face"):
        inputs = dict(tri_p=low(_triangle_corners(mesh.positions, frags)),
                      tri_uv=low(_triangle_corners(mesh.uv, frags)))
    elif kind == "vertex":  # MikkTSpace: per-corner tangents, the normal as interpolated
        at = interpolate({"t": mesh.tangents, "n": mesh.normals[mesh.faces]}, frags,
                         derivatives=None, bary=bary)
        return _frames.compute_frame(kind, N=low(at["n"].value), tangent=low(at["t"].value),
                                     front_facing=frags.front_facing,
                                     double_sided=opts.double_sided)
    elif kind == "vertex_area":
        tangents = _frames.vertex_tangents(mesh.positions, mesh.normals, mesh.uv, mesh.faces)
        inputs = dict(tangent=low(interpolate(tangents, frags, derivatives=None,
                                              bary=bary).value))
    return _frames.compute_frame(kind, N=n, front_facing=frags.front_facing,
                                 double_sided=opts.double_sided, **inputs)


def _perturbed_normal(gb: GBuffer, normal_map: Array, opts: RenderOptions,
                     strength: Array | None = None) -> Array:
    """The normal after applying the map's texels (stored values, image layout)."""
    if gb.plan is None:
        return gb.frame.N
    nm = opts.normal_map
    mips = (_tex.build_mipmaps(normal_map, levels=opts.levels) if opts.levels > 1
            else (normal_map,))
    raw = materialize(_tex.apply_plan(gb.plan, mips))  # else refused into each use
    if nm.space == "derivative":  # surface-gradient bump mapping (Mikkelsen)
        s = nm.strength if strength is None else strength
        return _maps.derivative_map_normal(gb.frame.N, gb.view.ddx, gb.view.ddy, gb.uv.ddx,
                                           gb.uv.ddy, raw[..., :2], scale=s)
    # an object-space map stores object xyz: no green/uv-origin flip applies to it
    tangent = nm.space == "tangent"
    m = _tex.decode_normal_map(raw, encoding=nm.encoding, channels=nm.channels,
                               green=nm.green if tangent else "up",
                               strength=nm.strength if strength is None else strength,
                               bits=nm.bits, uv_origin=nm.uv_origin if tangent else "bottom_left")
    if nm.space == "object":
        n = _maps.object_space_normal(m, fallback=gb.frame.N)
        return jnp.where(gb.front_facing[..., None] | (not opts.double_sided), n, -n)
    # at the frame's precision (the texture unit returns float32; the shader rounds it)
    return _frames.perturb_normal(gb.frame, m.astype(gb.frame.N.dtype)).astype(jnp.float32)


@functools.partial(jax.jit, static_argnames=("opts",))
def shade_gbuffer(gb: GBuffer, normal_map: Array | None, lights: Lights, material: Material, *,
                  opts: RenderOptions) -> dict[str, Array]:
    """The texture-dependent stages: sample and decode the map, perturb, shade.

    Returns the requested outputs among ``tangent``, ``bitangent``,
    ``perturbed_normal`` and ``color`` (linear RGB, 0 on background).
    """
    out = {}
    want = set(opts.outputs)
    if gb.frame is None:
        return out
    n = _perturbed_normal(gb, normal_map, opts) if normal_map is not None else gb.frame.N
    n = n.astype(jnp.float32)  # lighting is float32 whatever the frame's precision
    mask = gb.mask[..., None]
    if "tangent" in want:
        out["tangent"] = jnp.where(mask, gb.frame.T.astype(jnp.float32), 0.0)
    if "bitangent" in want:
        out["bitangent"] = jnp.where(mask, gb.frame.B.astype(jnp.float32), 0.0)
    if "perturbed_normal" in want:
        out["perturbed_normal"] = jnp.where(mask, n, 0.0)
    if "color" in want:
        c = shade(opts.shading, n, gb.position, gb.eye, lights, material, albedo=gb.albedo)
        out["color"] = jnp.where(mask, c, 0.0)
    return out


def render(scene: Scene, *, outputs=("color",), derivatives: str | None = None,
           frame: str | None = None, precision: str | None = None) -> dict[str, Array]:
    """Render ``scene`` and return the requested outputs as float32 (H, W, C) arrays.

    **Arguments:**
    - `scene`: a `Scene` (`jaxnm.config.load_scene`, `jaxnm.procedural.default_scene`).
    - `outputs`: any of `OUTPUTS`; only the stages they need are run.
    - `derivatives`, `frame`, `precision`: override the scene's choices.

    Row 0 is the top of the image. ``color`` is linear RGB (see
    `jaxnm.shading.to_display` for an sRGB PNG); ``triangle_id`` is -1 on the
    background; ``dpdx``/``dpdy`` are derivatives of the world position per
    pixel step in window x (right) and y (**up**).

    **How a frame runs.** The scene is made camera-relative (in float64 on the host where
    the camera and the model are concrete), the rasterizer finds each pixel's triangle
    (`jaxnm.raster`), and the per-pixel stages (interpolation, derivatives, frame, texture,
    shading) run on the whole image in the same compiled program, or, on the CPU for
    larger images, in a second program on the covered pixels only (packed with
    `jaxnm.raster.compact`). Nothing waits for the host between the two, and the same runs
    under the caller's `jax.jit` or `jax.grad`. Both ways give the same image: coverage,
    ids and facing exactly, the rest to float32 rounding. Nothing is remembered between
    calls but the compiled programs.

    **Checks.** Options and array shapes are checked here (a `ValueError` naming
    ``scene.source``); array values where scenes are made (`validate_scene`, which
    `jaxnm.config.load_scene` and the built-in scenes run: NaN or infinite values, face
    indices out of range, a camera that sees nothing). Rendered unchecked, a triangle with
    a non-finite corner or a face index out of range covers nothing, as on a GPU.

    Differentiable: the scene's arrays (normal map, albedo, vertex positions,
    camera, lights, material) may be traced, e.g. ``jax.grad`` of a loss of
    ``render(scene.replace(normal_map=x))["color"]`` with respect to ``x``
    (visibility is piecewise constant: silhouettes and occlusion boundaries
    contribute no gradient).
    """
    opts = RenderOptions.of(scene, outputs=outputs, derivatives=derivatives, frame=frame,
                            precision=precision)
    _check_scene_shapes(scene)
    _check_mesh(scene.mesh, opts, scene.source)
    if opts.precision == "float64":
        try:
            _require_x64("precision 'float64'")
        except ValueError as e:
            raise ValueError(f"{scene.source}: {e}") from None
    camera, lights, origin, placement, affine = _relative_inputs(scene)
    args = (scene.mesh, camera, scene.normal_map, scene.albedo, lights, scene.material, origin,
            placement)
    if not pixels.packs(opts.width * opts.height, neighbours=opts.derivatives == "gbuffer"):
        return _frame(*args, opts=opts, affine=affine)
    seen = _visible_placed(scene.mesh, camera, placement, width=opts.width, height=opts.height,
                           cull_back=opts.cull_back, affine=affine)
    return _packed_frame(*args, *seen, opts=opts, affine=affine)


@functools.partial(jax.jit, static_argnames=("opts", "affine"))
def _frame(mesh: Mesh, camera: Camera, normal_map, albedo, lights, material, origin,
           placement, *, opts: RenderOptions, affine: bool) -> dict[str, Array]:
    """`render` on the whole image, as one XLA program: ``mesh`` is placed by ``placement``
    (`_place`) relative to ``camera`` (at the origin), ``origin`` is the camera's world
    position."""
    mesh = _place(mesh, placement, affine)
    clip = materialize(to_clip(mesh.positions, camera))
    frags = rasterize(clip, mesh.faces.astype(jnp.int32), width=opts.width, height=opts.height,
                      cull_back=opts.cull_back)
    result = {"mask": frags.mask, "triangle_id": frags.triangle_id, "depth": frags.depth,
              "front_facing": frags.front_facing}
    result.update(_per_pixel(mesh, camera, normal_map, albedo, lights, material, origin,
                             opts)(frags))
    return _image_layout(result, opts)


@functools.partial(jax.jit, static_argnames=("width", "height", "cull_back", "affine"))
def _visible_placed(mesh: Mesh, camera: Camera, placement, *, width: int, height: int,
                    cull_back: bool, affine: bool):
    """Visibility, a program of its own: each pixel's triangle (-1: background), the (placed)
    mesh's clip-space vertices and its triangles' orientations (`triangle_ids`), which the
    per-pixel program (`_packed_frame`, a fit's `covered_gbuffer`) then need not compute
    again. Only what visibility depends on is static, so `render` and `covered_gbuffer`
    share one compiled program per image size and culling. Two programs, not one with the
    per-pixel stages: each keeps its own temporary buffers, which for a 200k-triangle mesh
    together passed glibc's threshold for reusing freed memory."""
    mesh = _place(mesh, placement, affine)
    clip = materialize(to_clip(mesh.positions, camera))
    tid, orientation = triangle_ids(clip, mesh.faces.astype(jnp.int32), width=width,
                                    height=height, cull_back=cull_back)
    return tid, clip, orientation


@functools.partial(jax.jit, static_argnames=("opts", "affine"))
def _packed_frame(mesh: Mesh, camera: Camera, normal_map, albedo, lights, material, origin,
                  placement, tid, clip, orientation, *, opts: RenderOptions,
                  affine: bool) -> dict[str, Array]:
    """`render`'s per-pixel stages on the covered pixels of `_visible_placed`'s ``tid``
    (`jaxnm._exec.pixels.over_covered_pixels`)."""
    mesh = _place(mesh, placement, affine)
    per_pixel = _per_pixel(mesh, camera, normal_map, albedo, lights, material, origin, opts)
    faces = mesh.faces.astype(jnp.int32)

    def pack(capacity, index):
        return compact(tid, clip, faces, capacity, orientation=orientation, index=index)

    return _image_layout(pixels.over_covered_pixels(per_pixel, tid, pack, outputs=opts.outputs),
                         opts)


def _per_pixel(mesh, camera, normal_map, albedo, lights, material, origin, opts):
    """The per-pixel stages of ``opts.outputs`` but the visibility ones, as a function of
    fragments (an image's or packed ones)."""
    if lights is None:
        lights = default_lights(camera)
    if material is None:
        material = default_material()
    wanted = [n for n in opts.outputs if n not in _GEOMETRY_OUTPUTS]

    def per_pixel(frags):
        gb = _gbuffer_from_fragments(mesh, camera, albedo, frags, opts=opts)
        res = {}
        if set(wanted) & _NEEDS_FRAME:
            res.update(shade_gbuffer(gb, normal_map, lights, material, opts=opts))
        values = {
            "position": lambda: jnp.where(gb.mask[..., None],
                                          gb.position + _like(origin, gb.position), 0.0),
            "view": lambda: gb.view.value,
            "uv": lambda: gb.uv.value,
            "normal": lambda: jnp.where(gb.mask[..., None], gb.normal, 0.0),
            "dpdx": lambda: gb.view.ddx,
            "dpdy": lambda: gb.view.ddy,
            "duvdx": lambda: gb.uv.ddx,
            "duvdy": lambda: gb.uv.ddy,
        }
        return {n: res[n] if n in res else values[n]() for n in wanted}

    return per_pixel


def _image_layout(result: dict, opts: RenderOptions) -> dict[str, Array]:
    """``opts.outputs`` of ``result`` as float32 (H, W, C) arrays."""
    return {n: (result[n][..., None] if result[n].ndim == 2 else result[n]).astype(jnp.float32)
            for n in opts.outputs}


def _relative_inputs(scene: Scene):
    """What `_frame` needs to render ``scene`` camera-relative: the camera at the origin (its
    view's rotation only), the point lights moved with everything else, the camera's world
    position ``origin``, the ``placement`` of the mesh and whether it is ``affine``
    (`_place`). In float64 on the host where the camera, the model and the point lights are
    concrete (then rounded to float32: a model's large translation and a large eye cancel
    before any rounding), in float32 with JAX where any is traced."""
    cam, model, lights = scene.camera, scene.model, scene.lights
    point = None if lights is None else lights.point
    if _concrete(cam.eye, cam.view, model, None if point is None else point.position):
        eye = np.asarray(cam.eye, np.float64)
        rel = np.eye(4) if model is None else np.array(model, np.float64)
        rel[:3, 3] -= eye
        view = np.array(cam.view, np.float64)
        view[:3, 3] = 0.0
        if point is not None:
            moved = np.asarray(point.position, np.float64) - eye
            lights = dataclasses.replace(lights, point=dataclasses.replace(
                point, position=moved.astype(np.float32)))
        camera = Camera(view=view.astype(np.float32), projection=cam.projection,
                        eye=np.zeros(3, np.float32))
        linear = rel[:3, :3]
        if np.array_equal(linear, np.eye(3)):
            return camera, lights, eye.astype(np.float32), rel[:3, 3].astype(np.float32), False
        placement = (rel.astype(np.float32), np.linalg.inv(linear).T.astype(np.float32))
        return camera, lights, eye.astype(np.float32), placement, True
    eye = jnp.asarray(cam.eye, jnp.float32)
    view = jnp.asarray(cam.view, jnp.float32).at[:3, 3].set(0.0)
    if point is not None:
        lights = dataclasses.replace(lights, point=dataclasses.replace(
            point, position=point.position - eye.reshape((1,) * (jnp.ndim(point.position) - 1)
                                                           + (3,))))
    camera = Camera(view=view, projection=cam.projection, eye=jnp.zeros(3, jnp.float32))
    if model is None:
        return camera, lights, eye, -eye, False
    rel = jnp.asarray(model, jnp.float32).at[:3, 3].add(-eye)
    return camera, lights, eye, (rel, jnp.linalg.inv(rel[:3, :3]).T), True


def _place(mesh: Mesh, placement, affine: bool) -> Mesh:
    """``mesh`` moved by ``placement``: a translation (3,) (``affine`` False), or
    ``(rel, normal_matrix)``: positions by the 4x4 affine ``rel``, normals by
    ``normal_matrix`` (the inverse transpose of its linear part) and renormalised, tangents
    by the linear part; a mirroring ``rel`` reverses the faces' winding, so that
    counter-clockwise stays front."""
    if not affine:
        return dataclasses.replace(mesh, positions=mesh.positions
                                   + jnp.asarray(placement, jnp.float32)[None])
    rel, normal_matrix = (jnp.asarray(x, jnp.float32) for x in placement)
    linear = rel[:3, :3]
    highest = jax.lax.Precision.HIGHEST
    positions = jnp.matmul(mesh.positions, linear.T, precision=highest) + rel[None, :3, 3]
    normals, tangents, faces = mesh.normals, mesh.tangents, mesh.faces
    if normals is not None:
        normals = safe_normalize(jnp.matmul(normals, normal_matrix.T, precision=highest))
    mirrored = jnp.linalg.det(linear) < 0
    if tangents is not None:
        xyz = safe_normalize(jnp.matmul(tangents[..., :3], linear.T, precision=highest))
        moved = jnp.concatenate([xyz, tangents[..., 3:]], -1)
        # a mirror flips the winding: the corners reversed, and cross(N, T) with them
        flipped = moved[:, ::-1] * jnp.asarray([1.0, 1.0, 1.0, -1.0], moved.dtype)
        tangents = jnp.where(mirrored, flipped, moved)
    faces = jnp.where(mirrored, faces[:, ::-1], faces)
    return dataclasses.replace(mesh, positions=positions, normals=normals, faces=faces,
                               tangents=tangents)


def _concrete(*xs) -> bool:
    return all(not isinstance(x, jax.core.Tracer)
               for x in jax.tree_util.tree_leaves(xs))


#: The placement of a mesh already where it belongs (`_place`): zero shift.
_NO_SHIFT = np.zeros(3, np.float32)


