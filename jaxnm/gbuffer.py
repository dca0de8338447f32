"""The per-pixel stages of a frame, from fragments to a G-buffer and from a G-buffer to the
shaded outputs.

They are split where the data stop depending on the geometry:

- `gbuffer_from_fragments` computes what depends only on the mesh and the camera:
  perspective-correct ``p``, ``uv``, ``N`` and their screen derivatives, the tangent frame,
  the texture sample *plan* of the normal map (texel indices and filter weights, including
  the mip level of detail) and the albedo. A normal-map fit computes this once per view.
- `shade_gbuffer` computes what depends on the normal-map texels, the lights and the
  material: a gather and a weighted sum per pixel, the decode, the perturbation and the
  shading. This is what a fit differentiates, every step.

Only the stages that the requested outputs (`RenderOptions.outputs`) need are computed.
`jaxnm.render` runs them over a scene's visible pixels.
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
from jax import Array

from . import frames as _frames
from . import maps as _maps
from . import textures as _tex
from ._exec.fusion import materialize
from .camera import Camera
from .geometry import Mesh
from .interpolate import (
    Attribute,
    at_precision,
    barycentrics,
    check_derivatives,
    check_precision,
    interpolate,
    triangle_corners,
)
from .numerics import safe_normalize
from .raster import Fragments
from .scene import Scene
from .shading import Lights, Material, check_shading_model, shade
from .textures import NormalMapOptions

__all__ = ["OUTPUTS", "GBuffer", "RenderOptions", "gbuffer_from_fragments", "shade_gbuffer"]

#: Every output `render` can produce (image layout, row 0 = top, float32 (H, W, C)).
OUTPUTS = ("mask", "triangle_id", "depth", "front_facing", "position", "view", "uv", "normal",
           "dpdx", "dpdy", "duvdx", "duvdy", "tangent", "bitangent", "perturbed_normal",
           "color")


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
            outputs=_in_order(outputs))

    def check_mesh(self, mesh: Mesh, source: str = "render") -> None:
        """Raise a `ValueError` naming ``source`` if ``mesh`` lacks an attribute the
        requested outputs need (uvs, normals, MikkTSpace tangents)."""
        has_map, _, need_tb, need_uv, _, need_n = _needs(self)
        if need_uv and mesh.uv is None:
            why = "a normal map" if has_map else f"the outputs {list(self.outputs)}"
            raise ValueError(f"{source}: the mesh has no texture coordinates (uv), needed for "
                             f"{why}")
        if need_n and mesh.normals is None:
            raise ValueError(f"{source}: the mesh has no vertex normals, needed for "
                             f"{list(self.outputs)} (compute them with Mesh.with_normals())")
        if need_tb and self.frame == "vertex" and mesh.tangents is None:
            raise ValueError(f"{source}: frame 'vertex' needs the mesh's MikkTSpace tangents "
                             "(Mesh.with_tangents(), or a glTF file's TANGENT attribute)")

    @property
    def shaded(self) -> bool:
        """Whether an output needs `shade_gbuffer` (the frame, the perturbed normal or the
        colour)."""
        return bool(set(self.outputs) & _NEEDS_FRAME)

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


def _in_order(outputs) -> tuple:
    """``outputs`` in the order of `OUTPUTS`, each once (unknown names after them, for
    `RenderOptions` to refuse): the same set of outputs, asked for in any order, is one set
    of options and one compiled program."""
    asked = list(dict.fromkeys(outputs))
    return tuple([o for o in OUTPUTS if o in asked] + [o for o in asked if o not in OUTPUTS])


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


def gbuffer_from_fragments(mesh: Mesh, camera: Camera, albedo: Array, frags: Fragments, *,
                           opts: RenderOptions) -> GBuffer:
    """The G-buffer of fragments ``frags``, a whole image's or packed ones
    (`jaxnm.raster.compact`; the G-buffer then has their shape): the per-pixel stages that
    depend on the geometry only, those that ``opts.outputs`` need.

    **Arguments:**
    - `mesh`, `camera`: the geometry, as rasterized into ``frags``.
    - `albedo`: (3,) constant or (H, W, 3) linear texture.
    - `frags`: `jaxnm.raster.Fragments`.
    - `opts`: a `RenderOptions`.
    """
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

    options = _frames.FrameOptions(ddy_sign=opts.ddy_sign, double_sided=opts.double_sided)
    inputs = {}
    n = low(gb["normal"])
    if kind in _frames.SCREEN_FRAMES:
        quads = None if frags.pixels is None else frags.window_pixels()
        inputs = dict(p_attr=at_precision(gb["view"], prec, frags.mask, derivatives=mode,
                                          pixels=quads),
                      uv_attr=at_precision(gb["uv"], prec, frags.mask, derivatives=mode,
                                           pixels=quads))
    elif kind in ("exact", "exact_face"):
        inputs = dict(tri_p=low(triangle_corners(mesh.positions, frags)),
                      tri_uv=low(triangle_corners(mesh.uv, frags)))
    elif kind == "vertex":  # MikkTSpace: per-corner tangents, the normal as interpolated
        at = interpolate({"t": mesh.tangents, "n": mesh.normals[mesh.faces]}, frags,
                         derivatives=None, bary=bary)
        return _frames.compute_frame(kind, low(at["n"].value), inputs=_frames.FrameInputs(
            tangent=low(at["t"].value), front_facing=frags.front_facing), options=options)
    elif kind == "vertex_area":
        tangents = _frames.vertex_tangents(mesh.positions, mesh.normals, mesh.uv, mesh.faces)
        inputs = dict(tangent=low(interpolate(tangents, frags, derivatives=None,
                                              bary=bary).value))
    return _frames.compute_frame(kind, n, options=options, inputs=_frames.FrameInputs(
        front_facing=frags.front_facing, **inputs))


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
