"""The pipeline: scene -> rasterize -> interpolate -> derivatives -> frame -> texture -> shade.

`render` runs a scene's frame: the scene made camera-relative, visibility (`jaxnm.raster`),
then the per-pixel stages (`jaxnm.gbuffer`: interpolation, derivatives, frame, texture
sample plan; then the map's texels, the perturbation and the shading), computing only the
stages that the requested outputs need. `build_gbuffer` and `covered_gbuffer` stop before
the texels: a normal-map fit builds its G-buffers once and differentiates
`jaxnm.gbuffer.shade_gbuffer` every step.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array

from ._exec import pixels
from ._exec.fusion import materialize
from ._relative import NO_SHIFT, place, relative_inputs
from .camera import Camera, to_clip
from .gbuffer import OUTPUTS as OUTPUTS  # (also here: where render's outputs are listed)
from .gbuffer import GBuffer, RenderOptions, gbuffer_from_fragments, shade_gbuffer
from .geometry import Mesh
from .interpolate import require_x64
from .raster import compact, rasterize, triangle_ids
from .scene import Scene, check_scene_shapes, default_lights, default_material

__all__ = ["render", "build_gbuffer", "covered_gbuffer"]

#: The outputs that visibility alone gives.
_GEOMETRY_OUTPUTS = {"mask", "triangle_id", "depth", "front_facing"}


def render(scene: Scene, *, outputs=("color",), derivatives: str | None = None,
           frame: str | None = None, precision: str | None = None) -> dict[str, Array]:
    """Render ``scene`` and return the requested outputs as float32 (H, W, C) arrays.

    **Arguments:**
    - `scene`: a `Scene` (`jaxnm.config.load_scene`, `jaxnm.procedural.default_scene`).
    - `outputs`: names among `jaxnm.gbuffer.OUTPUTS` (a tuple, or one name); only the
      stages they need are run.
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

    **Checks.** The call's options and the shapes of the scene's arrays are checked here
    (`jaxnm.scene.check_scene_shapes`; a `ValueError` naming ``scene.source`` and the
    field); a scene's values where scenes are made (`jaxnm.scene.validate_scene`, which
    `jaxnm.config.load_scene` and the built-in scenes run: NaN or infinite values, face
    indices out of range, a camera that sees nothing). Pass a scene assembled by hand
    through `jaxnm.scene.validate_scene` once. Rendered unchecked, a triangle with a
    non-finite corner or a face index out of range covers nothing, as on a GPU.

    Differentiable: the scene's arrays (normal map, albedo, vertex positions,
    camera, lights, material) may be traced, e.g. ``jax.grad`` of a loss of
    ``render(scene.replace(normal_map=x))["color"]`` with respect to ``x``
    (visibility is piecewise constant: silhouettes and occlusion boundaries
    contribute no gradient).
    """
    asked = (outputs,) if isinstance(outputs, str) else tuple(dict.fromkeys(outputs or ()))
    if not asked:
        raise ValueError(f"render: outputs names nothing; name one or more of "
                         f"{', '.join(OUTPUTS)}")
    check_scene_shapes(scene)
    opts = RenderOptions.of(scene, outputs=asked, derivatives=derivatives, frame=frame,
                            precision=precision)
    opts.check_mesh(scene.mesh, scene.source)
    if opts.precision == "float64":
        try:
            require_x64("precision 'float64'")
        except ValueError as e:
            raise ValueError(f"{scene.source}: {e}") from None
    camera, lights, origin, placement, affine = relative_inputs(scene)
    normal_map, albedo, lights, material = _strongly_typed(
        (scene.normal_map, scene.albedo, lights, scene.material))
    args = (scene.mesh, camera, normal_map, albedo, lights, material, origin, placement)
    if not pixels.packs(opts.width * opts.height, neighbours=opts.derivatives == "gbuffer"):
        out = _frame(*args, opts=opts, affine=affine)
    else:
        seen = _visible_placed(scene.mesh, camera, placement, width=opts.width,
                               height=opts.height, cull_back=opts.cull_back, affine=affine)
        out = _packed_frame(*args, *seen, opts=opts, affine=affine)
    return {name: out[name] for name in asked}  # in the caller's order


def _strongly_typed(tree):
    """``tree`` with its weakly typed leaves (Python scalars, ``jnp.asarray(48.0)``) as arrays
    of their own dtype. A weak type is part of a compiled program's signature: without this,
    the same scene after an optimiser step (whose updates are strongly typed) would compile
    its frame again."""
    def strong(x):
        t = jax.typeof(x)
        return jax.lax.convert_element_type(x, t.dtype) if t.weak_type else x
    return jax.tree_util.tree_map(strong, tree)


@functools.partial(jax.jit, static_argnames=("opts",))
def build_gbuffer(mesh: Mesh, camera: Camera, albedo: Array, *, opts: RenderOptions) -> GBuffer:
    """The G-buffer of a whole image (`jaxnm.gbuffer.gbuffer_from_fragments` after
    `jaxnm.raster.rasterize`): positions, uvs and normals with their derivatives, the frame,
    the normal map's sample plan.

    **Arguments:**
    - `mesh`, `camera`: the geometry (world space).
    - `albedo`: (3,) constant or (H, W, 3) linear texture.
    - `opts`: a `RenderOptions` (static).
    """
    opts.check_mesh(mesh)
    return gbuffer_from_fragments(mesh, camera, albedo, _visibility(mesh, camera, opts),
                                  opts=opts)


def covered_gbuffer(mesh: Mesh, camera: Camera, albedo: Array, *,
                    opts: RenderOptions) -> tuple[GBuffer, Array, int]:
    """`build_gbuffer` for the covered pixels only: ``(gbuffer, index, count)``.

    Rasterizes (the visibility program `render` runs too), counts the covered pixels on the
    host, and runs the per-pixel
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
    opts.check_mesh(mesh)
    # render's visibility program: a fit's targets rendered first leave it compiled
    tid, clip, orientation = _visible_placed(mesh, camera, NO_SHIFT, width=opts.width,
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
    return gbuffer_from_fragments(mesh, camera, albedo, packed, opts=opts), index


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


@functools.partial(jax.jit, static_argnames=("opts", "affine"))
def _frame(mesh: Mesh, camera: Camera, normal_map, albedo, lights, material, origin,
           placement, *, opts: RenderOptions, affine: bool) -> dict[str, Array]:
    """`render` on the whole image, as one XLA program: ``mesh`` is placed by ``placement``
    (`jaxnm._relative.place`) relative to ``camera`` (at the origin), ``origin`` is the
    camera's world position."""
    mesh = place(mesh, placement, affine)
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
    per-pixel stages: each keeps its own temporary buffers, which for a large mesh together
    would pass the C library's threshold for reusing freed memory."""
    mesh = place(mesh, placement, affine)
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
    mesh = place(mesh, placement, affine)
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
        gb = gbuffer_from_fragments(mesh, camera, albedo, frags, opts=opts)
        res = {}
        if opts.shaded:
            res.update(shade_gbuffer(gb, normal_map, lights, material, opts=opts))
        values = {
            "position": lambda: jnp.where(gb.mask[..., None], gb.position + jnp.asarray(
                origin)[(None,) * (gb.position.ndim - 1)], 0.0),
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
