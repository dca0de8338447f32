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

import collections
import dataclasses
import functools
import threading
import weakref
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array

from . import frames as _frames
from . import maps as _maps
from . import textures as _tex
from .camera import Camera, clip_float64, to_clip
from .geometry import Mesh, closed_shape
from .interpolate import (
    Attribute,
    at_precision,
    barycentrics,
    check_derivatives,
    check_precision,
    interpolate,
    require_x64,
    triangle_corners,
)
from .numerics import materialize, safe_normalize
from .raster import Fragments, compact, expand, rasterize, triangle_ids
from .scene import Scene, validate_scene
from .shading import Lights, Material, check_shading_model, shade
from .textures import NormalMapOptions

__all__ = ["OUTPUTS", "PACK_MIN_PIXELS", "GBuffer", "RenderOptions", "build_gbuffer",
           "covered_gbuffer", "gbuffer_from_fragments", "shade_gbuffer", "render",
           "with_tangents_if_needed", "camera_relative", "release_frame_programs",
           "back_faces_hidden"]

#: Every output `render` can produce (image layout, row 0 = top, float32 (H, W, C)).
OUTPUTS = ("mask", "triangle_id", "depth", "front_facing", "position", "view", "uv", "normal",
           "dpdx", "dpdy", "duvdx", "duvdy", "tangent", "bitangent", "perturbed_normal",
           "color")

#: `render` packs the covered pixels of images at least this big by default (256x256):
#: below it, a frame's per-pixel stages take about a millisecond, less than one more
#: compilation's worth over any realistic number of frames.
PACK_MIN_PIXELS = 1 << 16

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
        check_derivatives(self.derivatives, allow_none=False)
        check_precision(self.precision)
        _frames.check_frame(self.frame)
        check_shading_model(self.shading)
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


def check_mesh(mesh: Mesh, opts: RenderOptions, source: str = "render") -> None:
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
    check_mesh(mesh, opts)
    return gbuffer_from_fragments(mesh, camera, albedo, _visibility(mesh, camera, opts),
                                  opts=opts)


def covered_gbuffer(mesh: Mesh, camera: Camera, albedo: Array, *,
                    opts: RenderOptions) -> tuple[GBuffer, Array, int]:
    """`build_gbuffer` for the covered pixels only: ``(gbuffer, index, count)``.

    Rasterizes with `render`'s visibility program (compiled once per image size and
    culling), counts the covered pixels on the host, and runs the per-pixel stages on them
    packed (`jaxnm.raster.compact`) into image / 2^k slots. The G-buffer's per-pixel
    fields have a leading axis of slots, of which the first ``count`` are the covered
    pixels in row-major image order (row 0 at the top); ``index`` (slots,) holds their flat
    image indices (``H * W`` for unused slots). The values equal `build_gbuffer`'s at
    those pixels to float32 rounding. The mesh and camera must be concrete; "gbuffer"
    derivatives (stored neighbours) need the whole image: use `build_gbuffer` there.
    """
    if opts.derivatives == "gbuffer":
        raise ValueError("covered_gbuffer: 'gbuffer' derivatives need the whole image's "
                         "G-buffer (build_gbuffer)")
    check_mesh(mesh, opts)
    cull = opts.cull_back or back_faces_hidden(mesh, camera)
    tid, count, clip, orientation = _visible(mesh, camera, _NO_SHIFT, width=opts.width,
                                             height=opts.height, cull_back=cull)
    count = int(count)
    gb, index = _covered(mesh, camera, albedo, tid, clip, orientation, opts=opts,
                         capacity=_capacity(count, opts.width * opts.height))
    return gb, index, count


@functools.partial(jax.jit, static_argnames=("opts", "capacity"))
def _covered(mesh: Mesh, camera: Camera, albedo, triangle_id, clip, orientation, *, opts,
             capacity):
    packed, index = _compact(mesh, camera, triangle_id, capacity, clip, orientation)
    return gbuffer_from_fragments(mesh, camera, albedo, packed, opts=opts), index


def _compact(mesh: Mesh, camera: Camera, triangle_id: Array, capacity: int,
             clip: Array | None = None, orientation: Array | None = None):
    """`jaxnm.raster.compact` of ``mesh`` seen by ``camera``: (packed fragments, index);
    ``clip``, ``orientation``: the mesh's clip-space vertices and its triangles'
    orientations where the caller has them (`_visible`)."""
    if clip is None:
        clip = to_clip(mesh.positions, camera)
    return compact(triangle_id, clip, mesh.faces.astype(jnp.int32), capacity,
                   orientation=orientation)


def _visibility(mesh: Mesh, camera: Camera, opts: RenderOptions):
    return rasterize(to_clip(mesh.positions, camera), mesh.faces, width=opts.width,
                     height=opts.height, cull_back=opts.cull_back)


def gbuffer_from_fragments(mesh: Mesh, camera: Camera, albedo: Array, frags: Fragments, *,
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
        gb["frame"] = materialize(_frame(frame_opts, mesh, frags, gb, bary))
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


def _frame(opts: RenderOptions, mesh: Mesh, frags, gb, bary) -> _frames.Frame:
    """The tangent frame named by ``opts.frame`` (face-forwarded when double-sided), computed
    at ``opts.precision`` from inputs rounded to it (`jaxnm.interpolate.at_precision`)."""
    kind, prec, mode = opts.frame, opts.precision, opts.derivatives

    def low(x):  # a shader input at the shader's precision
        return at_precision(Attribute(x), prec, frags.mask, derivatives=None).value

    inputs = {}
    n = low(gb["normal"])
    if kind in ("cotangent", "cotangent_unnormalized", "nonperspective"):
        quads = None if frags.pixels is None else frags.window_pixels()
        inputs = dict(p_attr=at_precision(gb["view"], prec, frags.mask, derivatives=mode,
                                          pixels=quads),
                      uv_attr=at_precision(gb["uv"], prec, frags.mask, derivatives=mode,
                                           pixels=quads),
                      ddy_sign=opts.ddy_sign)
    elif kind in ("exact", "exact_face"):
        inputs = dict(tri_p=low(triangle_corners(mesh.positions, frags)),
                      tri_uv=low(triangle_corners(mesh.uv, frags)))
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


def perturbed_normal(gb: GBuffer, normal_map: Array, opts: RenderOptions,
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
    n = perturbed_normal(gb, normal_map, opts) if normal_map is not None else gb.frame.N
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
           frame: str | None = None, precision: str | None = None,
           pack: bool | int | None = None) -> dict[str, Array]:
    """Render ``scene`` and return the requested outputs as float32 (H, W, C) arrays.

    **Arguments:**
    - `scene`: a `Scene` (`jaxnm.config.load_scene`, `jaxnm.procedural.default_scene`).
    - `outputs`: any of `OUTPUTS`; only the stages they need are run.
    - `derivatives`, `frame`, `precision`: override the scene's choices.
    - `pack`: run the per-pixel stages on the covered pixels only, packed into
      image / 2^k slots (`jaxnm.raster.compact`), where at most half the image is
      covered. Each slot count is one more compilation, so by default (None) only
      images of at least `PACK_MIN_PIXELS` pixels are packed, where the time saved
      per frame is worth it, and only on the CPU: on a GPU the wait for the count
      and the second program cost more than the per-pixel work they save
      (measured on an H100: README, GPU); True packs any image, False none.
      The slot count is read on the host where the mesh and camera are concrete (the
      map, lights and material may be traced). Inside the caller's `jax.jit` (or with
      a traced mesh or camera) the count is not known when tracing: there the default
      runs every pixel of the image (on the CPU packed covered first, in chunks of
      `PIXEL_CHUNK` slots, skipping the chunks past the covered ones), and
      ``pack=True`` (or an int, the slot count) compiles both a packed program of
      image / 4 slots (or that many) and an all-pixel one and runs the first when the
      covered pixels fit (`jax.lax.cond`): on the CPU a step 1.1-1.6x faster than the
      default for about 1 s more compilation.
      "gbuffer" derivatives (stored neighbours) always run on the whole image. The
      results are the same either way (coverage, ids and facing exactly, the rest to
      float32 rounding).

    Row 0 is the top of the image. ``color`` is linear RGB (see
    `jaxnm.shading.to_display` for an sRGB PNG); ``triangle_id`` is -1 on the
    background; ``dpdx``/``dpdy`` are derivatives of the world position per
    pixel step in window x (right) and y (**up**).

    Differentiable: the scene's arrays (normal map, albedo, vertex positions,
    camera, lights, material) may be traced, e.g. ``jax.grad`` of a loss of
    ``render(scene.replace(normal_map=x))["color"]`` with respect to ``x``
    (visibility is piecewise constant: silhouettes and occlusion boundaries
    contribute no gradient). The scene is validated first (`validate_scene`); that host
    work is remembered for the last few scenes, keyed by their JAX arrays' identities and
    their small NumPy arrays' bytes, so rendering the same scene again (or with another
    normal map of the same shape) skips it.
    """
    prep = _prepare(scene, outputs, derivatives, frame, precision)
    opts, cull = prep.opts, prep.cull
    nm = scene.normal_map
    if nm is not None and not isinstance(nm, jax.Array):  # (jnp.asarray of one: 20-40 us)
        nm = jnp.asarray(nm)
    args = (prep.mesh, prep.camera, nm, prep.albedo, prep.lights, prep.material, prep.origin,
            prep.shift)
    pixels = opts.width * opts.height
    slots = _traced_capacity(pack, pixels, scene.source)
    if pack is None:
        pack = pixels >= PACK_MIN_PIXELS and jax.default_backend() == "cpu"
    if (pack is False or opts.derivatives == "gbuffer"
            or (slots is None and not _concrete(prep.mesh, prep.camera))):
        return _render(*args, opts=dataclasses.replace(opts, cull_back=cull))
    tid, count, clip, orientation = _visible(prep.mesh, prep.camera, prep.shift,
                                             width=opts.width, height=opts.height,
                                             cull_back=cull)
    if not isinstance(count, jax.core.Tracer):
        return _render(*args, tid, clip, orientation, opts=opts,
                       capacity=_capacity(int(count), pixels))
    if slots is None:  # the count is traced (the caller's jit): the whole image
        return _render(*args, opts=opts)
    # packed when the covered pixels fit, else every pixel (the ids are reused either way)
    return jax.lax.cond(count <= slots,
                        lambda a, t, c, o: _render(*a, t, c, o, opts=opts, capacity=slots,
                                                   traced_slots=slots),
                        lambda a, t, c, o: _render(*a, t, c, o, opts=opts, capacity=pixels,
                                                   traced_slots=slots),
                        args, tid, clip, orientation)


class _Prepared(NamedTuple):
    """What `render` works out on the host before a scene's programs run: the options,
    whether back faces may be skipped, and the camera-relative mesh, camera, lights,
    albedo and material (small arrays on the device), ``origin`` and ``shift``
    (`_camera_relative`)."""

    opts: RenderOptions
    cull: bool
    mesh: Mesh
    camera: Camera
    lights: Lights
    albedo: Array
    material: Material
    origin: Array
    shift: Array


#: `render`'s `_Prepared` scenes, the most recent last: key (`_prepared_key`) ->
#: (weak references to the scene's JAX arrays, `_Prepared`). Rendering the same scene
#: again (the same JAX arrays, the same small NumPy values; any normal map of the same
#: shape and dtype) skips the validation, the culling test and the camera-relative copies:
#: 0.3-0.7 ms of host time a frame on the 2-core VM, 8-11% of the 4k sphere's 512^2
#: frame. JAX arrays cannot change, so their identities (checked through the weak
#: references, as `jaxnm.geometry` does) stand for their values; small NumPy arrays (a
#: camera's eye, a constant albedo) are keyed by their bytes, and a scene with a larger
#: NumPy array (which could change in place) or a traced one is prepared afresh every time.
#: An entry keeps its prepared mesh (often the scene's own) alive until it is one of the
#: `_PREPARED_MAX` least recent, or `release_frame_programs` forgets them all.
_PREPARED: collections.OrderedDict = collections.OrderedDict()
_PREPARED_MAX = 8
_PREPARED_LOCK = threading.Lock()  # `render` may be called from several threads
_SMALL_HOST_ARRAY = 64  # elements: a NumPy array up to this size is keyed by its bytes
_SCENE_OPTIONS = tuple(f.name for f in dataclasses.fields(Scene) if f.metadata.get("static"))


def _prepared_key(scene: Scene, choices: tuple) -> tuple[tuple | None, list]:
    """`_PREPARED`'s key for ``scene`` rendered with ``choices`` (outputs, derivatives,
    frame, precision), and the scene's JAX arrays; (None, []) where the scene cannot be
    keyed (a tracer, a large NumPy array, an unhashable option)."""
    leaves, tree = jax.tree_util.tree_flatten(
        (scene.mesh, scene.camera, scene.albedo, scene.lights, scene.material, scene.model))
    parts, arrays = [], []
    for x in leaves:
        if isinstance(x, jax.core.Tracer):
            return None, []
        if isinstance(x, jax.Array):
            parts.append(id(x))
            arrays.append(x)
        elif isinstance(x, np.ndarray) and x.size <= _SMALL_HOST_ARRAY:
            parts.append((x.dtype.str, x.shape, x.tobytes()))
        elif isinstance(x, (bool, int, float, np.generic)):
            parts.append((type(x).__name__, x))
        else:
            return None, []
    nm = scene.normal_map
    outputs, *rest = choices
    try:
        key = (tree, tuple(parts), tuple(getattr(scene, f) for f in _SCENE_OPTIONS),
               None if nm is None else (jnp.shape(nm), jnp.result_type(nm)),
               tuple(outputs), tuple(rest), bool(jax.config.jax_enable_x64),
               jax.config.jax_default_device, jax.default_backend())
        hash(key)
    except TypeError:
        return None, []
    return key, arrays


def _prepare(scene: Scene, outputs, derivatives, frame, precision) -> _Prepared:
    """`render`'s host work for ``scene`` (see `_Prepared`), remembered in `_PREPARED`."""
    key, arrays = _prepared_key(scene, (outputs, derivatives, frame, precision))
    hit = None if key is None else _PREPARED.get(key)
    if hit is not None and all(r() is x for r, x in zip(hit[0], arrays)):
        with _PREPARED_LOCK:  # (another thread may have dropped it meanwhile)
            if key in _PREPARED:
                _PREPARED.move_to_end(key)
        return hit[1]
    scene = validate_scene(scene)
    opts = RenderOptions.of(scene, outputs=outputs, derivatives=derivatives, frame=frame,
                            precision=precision)
    if opts.precision == "float64":
        try:
            require_x64("precision 'float64'")
        except ValueError as e:
            raise ValueError(f"{scene.source}: {e}") from None
    scene = with_tangents_if_needed(scene, opts)
    check_mesh(scene.mesh, opts, scene.source)
    # a closed mesh wholly in front of the camera: its back faces are never the nearest
    cull = opts.cull_back or back_faces_hidden(scene.mesh, scene.camera, scene.model)
    # the mesh's shift to the camera is left to the compiled programs (``shift``): done here
    # it would be an eager operation and a transfer per frame (1.1 ms of host time on an H100)
    scene, origin, shift = _camera_relative(scene, defer_shift=True)
    camera, lights, albedo, origin, shift = _on_device(scene, origin, shift)
    prepared = _Prepared(opts, cull, scene.mesh, camera, lights, albedo, scene.material,
                         origin, shift)
    if key is not None:
        with _PREPARED_LOCK:
            _PREPARED[key] = (tuple(weakref.ref(x) for x in arrays), prepared)
            while len(_PREPARED) > _PREPARED_MAX:
                _PREPARED.popitem(last=False)
    return prepared


def _traced_capacity(pack, pixels: int, source: str) -> int | None:
    """The packed slot count for a traced coverage count: image / 4 for ``pack=True``, the
    int itself, or None (no packing where the count is traced)."""
    if pack is None or pack is False:
        return None
    if pack is True:
        return max(1, pixels // 4)
    if not isinstance(pack, int) or not 0 < pack <= pixels:
        raise ValueError(f"{source}: pack must be None, a bool or a slot count in 1..{pixels} "
                         f"(the image's pixels), got {pack!r}")
    return pack


def release_frame_programs() -> None:
    """Forget `render`'s compiled frame programs (one per scene shape, options and slot
    count: ~26 MB for the built-in problem's targets), keeping the visibility program,
    which `covered_gbuffer` (a fit's `jaxnm.fit.prepare`) runs again for the same image
    size (1 s to compile). `jaxnm fit` calls it once the targets are rendered."""
    _render.clear_cache()
    with _PREPARED_LOCK:
        _PREPARED.clear()


def _concrete(*xs) -> bool:
    return all(not isinstance(x, jax.core.Tracer)
               for x in jax.tree_util.tree_leaves(xs))


def camera_relative(scene: Scene) -> tuple[Scene, Array]:
    """``scene`` with its model matrix applied and everything moved so that the camera sits
    at the origin, and that origin (the camera's world position).

    The model's translation and the eye are subtracted in float64 on the host before
    anything is rounded to float32 (what engines call camera-relative rendering), so a mesh
    far from the world origin keeps its precision: its float32 positions are small numbers
    near the camera. Point lights move with it; directional lights, normals and the view
    rotation do not change. When the camera or the model is traced (``jax.grad`` with
    respect to them), the same is done in float32 with JAX.
    """
    scene, origin, _ = _camera_relative(scene, defer_shift=False)
    return scene, origin


def _camera_relative(scene: Scene, *, defer_shift: bool):
    """`camera_relative`, and with ``defer_shift`` the mesh's translation to the camera left
    undone where the model has no rotation: returned as a (3,) float32 NumPy ``shift`` for
    the caller's compiled program to add (`_shifted`; `_NO_SHIFT` where nothing is left)."""
    cam, model = scene.camera, scene.model
    if not _concrete(cam.eye, cam.view, model):  # traced: JAX, float32
        eye = jnp.asarray(cam.eye, jnp.float32)
        mesh = scene.mesh
        if model is not None:
            m = jnp.asarray(model, jnp.float32)
            pos = jnp.matmul(mesh.positions, m[:3, :3].T, precision=jax.lax.Precision.HIGHEST)
            nrm = None if mesh.normals is None else safe_normalize(jnp.matmul(
                mesh.normals, jnp.linalg.inv(m[:3, :3]), precision=jax.lax.Precision.HIGHEST))
            mesh = dataclasses.replace(mesh, positions=pos + m[None, :3, 3], normals=nrm)
        return dataclasses.replace(scene, mesh=mesh, model=None), np.zeros(3), _NO_SHIFT
    eye = np.asarray(cam.eye, np.float64)
    m = np.eye(4) if model is None else np.asarray(model, np.float64)
    rel = m.copy()
    rel[:3, 3] = m[:3, 3] - eye  # large model offset and large eye cancel in float64 here
    shift = _NO_SHIFT
    if not np.array_equal(rel[:3, :3], np.eye(3)):
        mesh = scene.mesh.transformed(rel)
    elif defer_shift:
        mesh, shift = scene.mesh, rel[:3, 3].astype(np.float32)
    else:
        mesh = _shifted(scene.mesh, rel[:3, 3].astype(np.float32))
    view = np.asarray(cam.view, np.float64).copy()
    view[:3, 3] = 0.0
    camera = Camera(view=view.astype(np.float32), projection=cam.projection, eye=np.zeros(3))
    lights = scene.lights
    if lights is not None and lights.point is not None:
        p = lights.point
        moved = ((np.asarray(p.position, np.float64) - eye).astype(np.float32)
                 if _concrete(p.position)
                 else p.position - jnp.asarray(eye, jnp.float32).reshape((1,) * (
                     jnp.ndim(p.position) - 1) + (3,)))
        lights = dataclasses.replace(lights, point=dataclasses.replace(p, position=moved))
    return (dataclasses.replace(scene, mesh=mesh, camera=camera, lights=lights, model=None), eye,
            shift)


def _on_device(scene: Scene, origin, shift):
    """The small host arrays of a frame as device arrays: the camera-relative view and eye,
    the moved point lights, ``origin`` and ``shift`` that `_camera_relative` made, and a
    constant albedo given as NumPy; ``(camera, lights, albedo, origin, shift)``. Each NumPy
    argument of a compiled program is one host-to-device copy per call (together 0.1-0.2
    ms of a 1.5 ms frame on an H100), so the same values are copied once and kept: a few
    cached sets, keyed by their bytes, the default device and the x64 mode. Other arrays
    (JAX's, traced, an albedo texture) pass through."""
    camera, lights, albedo = scene.camera, scene.lights, scene.albedo
    point = None if lights is None else lights.point
    values = [camera.view, camera.eye, np.asarray(origin, np.float32), shift,
              None if point is None else point.position,
              albedo if np.ndim(albedo) == 1 else None]
    host = tuple(i for i, x in enumerate(values) if isinstance(x, np.ndarray))
    if host:
        on_device = _device_constants(
            tuple((values[i].tobytes(), values[i].dtype.str, values[i].shape) for i in host),
            jax.config.jax_default_device, jax.config.jax_enable_x64, jax.default_backend())
        for i, x in zip(host, on_device):
            values[i] = x
    view, eye, origin, shift, position, constant = values
    if point is not None:
        lights = dataclasses.replace(lights, point=dataclasses.replace(point, position=position))
    return (Camera(view=view, projection=camera.projection, eye=eye), lights,
            albedo if constant is None else constant, origin, shift)


@functools.lru_cache(maxsize=16)
def _device_constants(key, *_context):
    """`_on_device`'s cache: ``key`` holds each array's (bytes, dtype, shape); ``_context``
    the default device, x64 mode and backend. Copied now even inside a caller's trace
    (where the arrays are then constants), so that no tracer is cached."""
    with jax.ensure_compile_time_eval():
        return tuple(jax.device_put(np.frombuffer(b, dtype).reshape(shape))
                     for b, dtype, shape in key)


#: The shift of a mesh already where it belongs: `_visible` and `_render` always take one
#: (an array, never None), so that `render` and `covered_gbuffer` share one compiled
#: visibility program per image size.
_NO_SHIFT = np.zeros(3, np.float32)


def _shifted(mesh: Mesh, shift) -> Mesh:
    """``mesh`` translated by ``shift`` (3,) (None: unchanged)."""
    if shift is None:
        return mesh
    return dataclasses.replace(mesh, positions=mesh.positions
                               + jnp.asarray(shift, jnp.float32)[None])


def with_tangents_if_needed(scene: Scene, opts: RenderOptions) -> Scene:
    """``scene`` with MikkTSpace tangents on its mesh when ``opts`` renders the ``"vertex"``
    frame and the mesh has none (computed on the host: the mesh must be concrete). Compute
    them once with ``scene.replace(mesh=scene.mesh.with_tangents())`` to render many times."""
    m = scene.mesh
    if opts.frame != "vertex" or m.tangents is not None or m.uv is None or m.normals is None:
        return scene
    if any(isinstance(x, jax.core.Tracer) for x in (m.positions, m.normals, m.uv)):
        return scene  # `check_mesh` explains
    return dataclasses.replace(scene, mesh=m.with_tangents())


def back_faces_hidden(mesh: Mesh, camera: Camera, model=None) -> bool:
    """Whether ``camera`` can see none of ``mesh``'s back faces, so that visibility may skip
    them (`jaxnm.raster.triangle_ids`' ``cull_back``) and still find every pixel's nearest
    triangle: the mesh encloses a volume with its front faces outside
    (`jaxnm.geometry.closed_shape`), ``model`` (object to world, or None) does not mirror
    it, and the corners of its bounding box are all in front of the near plane (so no
    part is clipped open and the camera is outside). Every ray from the eye then meets the
    surface first where it enters the volume, through a front face. On the host; False
    where the mesh, camera or model is traced. `render` and `covered_gbuffer` cull this
    way by themselves: the same triangles win, except where a back face had tied with the
    front face before it at a silhouette (the benchmark's tori and sphere at 512^2 and
    1024^2: 0-3 pixels a frame), and frames take 0.87-0.94x the time."""
    if not _concrete(mesh.positions, mesh.faces, camera, model):
        return False
    box = closed_shape(mesh.positions, mesh.faces)
    if box is None:
        return False
    if model is not None and not np.linalg.det(np.asarray(model, np.float64)[:3, :3]) > 0:
        return False
    corners = [[box[i, 0], box[j, 1], box[k, 2]] for i in (0, 1) for j in (0, 1) for k in (0, 1)]
    clip = clip_float64(corners, camera, model)
    w = clip[:, 3]
    return bool(np.all(w > 0) and np.all(clip[:, 2] + w > 1e-6 * w))


def _capacity(count: int, pixels: int) -> int:
    """Slots for ``count`` covered pixels of a ``pixels``-pixel image: the smallest of
    pixels / 2, / 4, ..., / 64 that holds them, or all of them when more than half the
    image is covered (packing then only saves rasterizing again). Few sizes, because each
    is one compilation."""
    capacity = pixels
    for k in range(1, 7):
        if (pixels >> k) < max(count, 1):
            break
        capacity = pixels >> k
    return capacity


@functools.partial(jax.jit, static_argnames=("width", "height", "cull_back"))
def _visible(mesh: Mesh, camera: Camera, shift=None, *, width: int, height: int,
             cull_back: bool):
    """Each pixel's triangle (-1: background), how many pixels are covered, the (shifted)
    mesh's clip-space vertices and its triangles' orientations, which the per-pixel
    program then need not compute again; the depth is left to the packed pixels
    (`compact`). Only the options visibility depends on are static: one compilation serves
    every output, frame and map. ``shift``: see `_camera_relative`."""
    mesh = _shifted(mesh, shift)
    # computed once: XLA fused the transform into the snapping's loop as well as the
    # output's, doing it twice (200k torus at 512^2: frame 0.95-0.97x, one process A/B)
    clip = materialize(to_clip(mesh.positions, camera))
    tid, orientation = triangle_ids(clip, mesh.faces, width=width, height=height,
                                    cull_back=cull_back)
    return tid, jnp.count_nonzero(tid >= 0), clip, orientation


#: The per-pixel stages run over packed pixels in chunks of at most this many slots on
#: the CPU (a `jax.lax.map`), ``(counted, traced)``: where the covered pixels were counted
#: on the host (`render`'s default) and where they were not (under the caller's jit, all
#: the image's pixels). Chunks without a covered pixel are skipped. Their intermediates, a
#: few (slots, 3) float32 arrays each, then stay in the caches: on the 2-core VM (1 MiB
#: of L2 a core), the per-pixel program for the same 51k covered pixels took 4.5 ms in
#: 2^16 slots and 18.6 ms in 2^17. Counted, chunks of 2^14 waste fewer slots past the
#: covered pixels (4k sphere at 512^2, 39k covered pixels in 2^16 slots: per-pixel
#: program 3.7 -> 2.7 ms; elsewhere the same within noise); traced, 2^16, because each
#: chunk's backward pass adds up the whole map's gradient (20k torus at 1024^2,
#: forward+backward: 71 ms in chunks of 2^16, 81 ms in 2^14). A packed program whose count
#: is traced (``pack=True`` in the caller's jit, most often a gradient step) takes at most
#: four chunks between the two sizes, the all-pixel one in the same chunks (1024^2
#: forward+backward 0.91-0.95x, no more compilation). Other backends
#: (a GPU wants all the slots at once): no chunks.
PIXEL_CHUNK = {"cpu": (1 << 14, 1 << 16)}


def _over_chunks(fn, frags: Fragments, chunk: int):
    """``fn(frags)`` for packed fragments (per-slot fields (S, ...)), evaluated ``chunk``
    slots at a time (a `jax.lax.map`; one chunk: a plain call). ``fn`` returns a pytree of
    per-slot arrays (S, ...), zero on background slots; the chunks' results are put back
    together (padding slots are background and are cut off). A chunk without a covered
    slot is not evaluated (a `jax.lax.cond`; its results are zeros)."""
    n = frags.triangle_id.shape[0]
    k = -(-n // chunk)
    if k <= 1:
        return fn(frags)
    size = -(-n // k)
    pad = k * size - n

    def split(x, fill):
        x = jnp.pad(x, [(0, pad)] + [(0, 0)] * (x.ndim - 1), constant_values=fill)
        return x.reshape((k, size) + x.shape[1:])

    per_slot = (split(frags.triangle_id, -1), split(frags.depth, 1.0),
                split(frags.front_facing, False), split(frags.pixels, 0))

    def run(chunk_fields):
        tid, depth, front, pixels = chunk_fields
        return fn(dataclasses.replace(frags, triangle_id=tid, depth=depth, front_facing=front,
                                      pixels=pixels))

    shapes = jax.eval_shape(run, jax.tree_util.tree_map(lambda x: x[0], per_slot))

    def one(chunk_fields):
        return jax.lax.cond(
            jnp.any(chunk_fields[0] >= 0), run,
            lambda _: jax.tree_util.tree_map(lambda a: jnp.zeros(a.shape, a.dtype), shapes),
            chunk_fields)

    # (`jax.checkpoint`: under reverse mode each chunk's forward is evaluated again in the
    # backward pass rather than its intermediates kept; stacking them chunk by chunk
    # (zero-filled buffers, dynamic updates, copies) cost twice the recomputation: 4k
    # sphere at 512^2, forward+backward w.r.t. the map 32 -> 14 ms)
    out = jax.lax.map(jax.checkpoint(one), per_slot)
    return jax.tree_util.tree_map(lambda y: y.reshape((k * size,) + y.shape[2:])[:n], out)


@functools.partial(jax.jit, static_argnames=("opts", "capacity", "traced_slots"))
def _render(mesh: Mesh, camera: Camera, normal_map, albedo, lights, material, origin,
            shift=None, triangle_id: Array | None = None, clip: Array | None = None,
            orientation: Array | None = None, *, opts: RenderOptions,
            capacity: int | None = None,
            traced_slots: int | None = None) -> dict[str, Array]:
    """`render` as one XLA program (one compilation per scene shape, options and capacity);
    the scene is camera-relative (`_camera_relative`; the mesh still to be moved by
    ``shift``), ``origin`` the camera's world position. With ``capacity``, the per-pixel
    stages run on the covered pixels of ``triangle_id`` (from `_visible`, with the clip-space
    vertices ``clip``), packed by
    `compact`, and their results are put back in image layout. Without, on the CPU, on
    every pixel of the image packed the same way, covered first, where chunks without a
    covered pixel are skipped; on other backends on the image as it is. The per-pixel
    stages run in chunks of `PIXEL_CHUNK` slots (those without a covered pixel skipped),
    except for "gbuffer" derivatives (stored neighbours), which need the whole image."""
    mesh = _shifted(mesh, shift)
    height, width = opts.height, opts.width
    counted = capacity is not None
    small, large = PIXEL_CHUNK.get(jax.default_backend(), (None, None))
    chunk = small if counted else large
    if counted and traced_slots is not None and chunk is not None:
        # a count traced in the caller's jit (``pack=True``: a cond between a program of
        # ``traced_slots`` slots and an all-pixel one), most often a gradient's: the fewer
        # chunks the less the backward pass adds up whole-map gradients (the empty ones
        # skipped), the more slots a partly covered chunk wastes: the packed program in at
        # most four chunks, the all-pixel one in chunks of the same size (one chunk program
        # to compile for both: 1 s less than two)
        chunk = min(max(small, -(-traced_slots // 4)), large)
    if capacity is None and (opts.derivatives == "gbuffer" or chunk is None):
        frags = _visibility(mesh, camera, opts)
        packed, index = frags, None
        image = {"mask": lambda: frags.mask, "triangle_id": lambda: frags.triangle_id,
                 "depth": lambda: frags.depth, "front_facing": lambda: frags.front_facing}
    else:
        if capacity is None:
            # the coverage is not known when tracing: every pixel a slot, the covered ones
            # first (`compact`), so that the chunks past them are skipped
            frags = _visibility(mesh, camera, opts)
            triangle_id, clip = frags.triangle_id, frags.clip
            capacity = height * width
        packed, index = _compact(mesh, camera, triangle_id, capacity, clip, orientation)
        image = {"mask": lambda: triangle_id >= 0, "triangle_id": lambda: triangle_id,
                 "depth": lambda: expand(packed.depth, index, height, width, 1.0),
                 "front_facing": lambda: expand(packed.front_facing, index, height, width)}
    wanted = [n for n in opts.outputs if n not in image]

    def per_pixel(frags):
        gb = gbuffer_from_fragments(mesh, camera, albedo, frags, opts=opts)
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

    if packed.pixels is None or chunk is None:  # the image, or all the slots, at once
        values = per_pixel(packed)
    else:
        values = _over_chunks(per_pixel, packed, chunk)
    result = {}
    for name in opts.outputs:
        if name in image:
            v = image[name]()
        else:
            v = values[name]
            if index is not None:
                v = expand(v, index, height, width)
        if v.ndim == 2:
            v = v[..., None]
        result[name] = v.astype(jnp.float32)
    return result
