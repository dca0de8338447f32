"""Preparation, once per fit: rasterize every view, keep the covered pixels, batch the views.

The geometry is fixed during a fit, so each view's G-buffer — visibility, the
perspective-correct position, uv, normal, their screen derivatives, the frame
and the normal map's sample plan (texel indices, filter weights, mip level of
detail) — is computed **once**, and kept only for the pixels the mesh covers,
as a flat list. Views whose lights have the same kinds and counts are stacked
into `ViewBatch`es, so one ``vmap`` shades them.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array

from .. import textures as _tex
from .._host_geometry import box_in_front, closed_shape
from ..gbuffer import GBuffer, RenderOptions
from ..render import build_gbuffer, covered_gbuffer
from ..shading import Lights, Material
from ._batching import (
    check_chunk,
    chunking,
    host,
    light_key,
    map_pixels,
    stack_lights,
    stack_rows,
    tap_groups,
)
from ._processes import held_rows, host_row
from .problem import FitProblem, FitTarget, validate_problem

__all__ = ["ViewBatch", "Prepared", "View", "prepare", "with_map_size", "view_key",
           "shard_views", "CHUNK", "view_options", "rasterize_views", "assemble"]

#: Default of `prepare`'s ``chunk``: at most this many pixel-targets (a pixel under one
#: light) are evaluated at once by a fit step. A step's working memory (the shading, its
#: forward-mode tangents and the per-pixel Jacobian blocks) grows with this, not with the
#: number of views or their size. Problems smaller than this (``jaxnm fit``'s built-in one)
#: run in one piece: a loop over chunks costs compilation and time per step
#: (docs/guides/fitting.md).
CHUNK = 1 << 21


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class ViewBatch:
    """Views whose lights have the same kinds and counts, stacked so one ``vmap`` shades them.

    Only the pixels a view's mesh covers take part, as a flat list; views with
    fewer pixels or targets are padded (copies of a real pixel or target with
    weight 0, so padding is NaN-free and changes nothing); views are batched
    only when padding at most doubles a view's pixels. ``V`` views, ``T``
    targets, ``K`` pixels each:

    - `gbuffer`: the G-buffer of those pixels, every field (V, K, ...) (the
      eye (V, 3)).
    - `pixels`: (V, K) int32 row-major pixel indices into the view's image,
      -1 for padding.
    - `images`: (V, T, K, 3) linear targets; `weights`: (V, T, K, 1), 0
      outside a target's mask and for padding.
    - `lights`: `Lights` with leaves (V, T, ...): one (stacked) light per target.
    - `views` (static): the view indices (into `Prepared.options`) of the rows;
      `targets` (static): each view's real number of targets.
    - `split` (static): the first ``split`` pixels of every view read a single
      mip level (4 non-zero filter taps: magnified texels, or the coarsest
      level), the rest two (8 taps); the step gathers each group with only the
      taps it needs.
    - `chunks` (static): how many equal chunks each of the two groups is cut
      into; a step evaluates one chunk of every view at a time (see
      `prepare`'s ``chunk``). Each group is padded to a multiple of its count.
    """

    gbuffer: GBuffer
    pixels: Array
    images: Array
    weights: Array
    lights: Lights
    views: tuple[int, ...] = dataclasses.field(metadata=dict(static=True))
    targets: tuple[int, ...] = dataclasses.field(metadata=dict(static=True))
    split: int = dataclasses.field(metadata=dict(static=True), default=0)
    chunks: tuple[int, int] = dataclasses.field(metadata=dict(static=True), default=(1, 1))

    def pixel_groups(self) -> tuple[tuple[int, int, int, int | None], ...]:
        """``(start, size, count, taps)`` of each pixel group that has pixels: ``count``
        chunks of ``size`` pixels from ``start``, read with ``taps`` filter taps (4 for the
        first `split` pixels, None — the plan's own — for the rest)."""
        k = self.pixels.shape[1]
        return tuple((start, (stop - start) // n, n, taps)
                     for start, stop, n, taps in ((0, self.split, self.chunks[0], 4),
                                                  (self.split, k, self.chunks[1], None))
                     if stop > start)

    def chunk(self, start: int, size: int, c) -> tuple[GBuffer, Lights, Array, Array]:
        """The G-buffer, lights, images and weights of pixels ``start + c * size`` to
        ``start + (c + 1) * size`` of every view (``c`` may be traced)."""
        def cut(x, axis):
            return jax.lax.dynamic_slice_in_dim(x, start + c * size, size, axis)

        return (map_pixels(self.gbuffer, lambda x: cut(x, 1)), self.lights,
                cut(self.images, 2), cut(self.weights, 2))


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Prepared:
    """Everything a fit step needs, computed once (see `prepare`).

    A view is one camera (with its image size); each of its targets is one
    image under one (stacked) light. ``batches`` group the views into
    `ViewBatch` stacks; ``options[v]`` are view ``v``'s render options (they
    differ only in image size). `target_images`, `target_mask` and `view`
    give per-view, image-layout access. ``chunk`` is `prepare`'s.
    """

    batches: tuple[ViewBatch, ...]
    material: Material
    options: tuple[RenderOptions, ...] = dataclasses.field(metadata=dict(static=True))
    chunk: int | None = dataclasses.field(metadata=dict(static=True), default=CHUNK)

    @property
    def num_views(self) -> int:
        return len(self.options)

    def view(self, v: int) -> View:
        """View ``v`` unpadded, as host (NumPy) arrays: its G-buffer (K_v, ...), pixels,
        targets and lights (across processes, `jaxnm.fit.prepare_processes`: a view this
        process holds, `local_views`)."""
        for b in self.batches:
            if v in b.views:
                i = b.views.index(v)
                if not b.pixels.is_fully_addressable and i not in held_rows(b.pixels):
                    raise IndexError(f"fit: view {v} is held by another process")

                def row(x, i=i):
                    return host_row(x, i)

                pixels = row(b.pixels)
                keep = np.flatnonzero(pixels >= 0)
                t = b.targets[i]
                gb = map_pixels(b.gbuffer, lambda x: row(x)[keep], eye=row)
                return View(gb, pixels[keep], row(b.images)[:t][:, keep],
                            row(b.weights)[:t][:, keep],
                            jax.tree_util.tree_map(lambda x: row(x)[:t], b.lights))
        raise IndexError(f"fit: no view {v} (the problem has {self.num_views})")

    def local_views(self) -> tuple[int, ...]:
        """The views this process holds: all of them, but for a problem spread over
        processes (`jaxnm.fit.prepare_processes`)."""
        out = set()
        for b in self.batches:
            held = (range(len(b.views)) if b.pixels.is_fully_addressable
                    else held_rows(b.pixels))
            out |= {b.views[i] for i in held if b.views[i] >= 0}
        return tuple(sorted(out))

    def to_image(self, v: int, values) -> np.ndarray:
        """Per-pixel ``values`` (..., K_v, C) of `view` ``v`` in image layout (..., H, W, C),
        0 off the mesh (NumPy)."""
        o = self.options[v]
        pixels = self.view(v).pixels
        values = np.asarray(values)
        out = np.zeros(values.shape[:-2] + (o.height * o.width, values.shape[-1]), values.dtype)
        out[..., pixels, :] = values
        return out.reshape(values.shape[:-2] + (o.height, o.width, values.shape[-1]))

    def target_images(self, v: int) -> np.ndarray:
        """(T_v, H, W, 3) linear targets of view ``v`` (0 where the mesh is not)."""
        return self.to_image(v, self.view(v).images)

    def target_mask(self, v: int, t: int = 0) -> np.ndarray:
        """(H, W) bool: the pixels that count for target ``t`` of view ``v``."""
        return self.to_image(v, self.view(v).weights[t])[..., 0] > 0


@dataclasses.dataclass(frozen=True)
class View:
    """One view of a `Prepared` problem, unpadded: ``gbuffer`` (K, ...), ``pixels`` (K,),
    ``images`` (T, K, 3), ``weights`` (T, K, 1), ``lights`` (leaves (T, ...))."""

    gbuffer: GBuffer
    pixels: Array
    images: Array
    weights: Array
    lights: Lights


def view_key(t: FitTarget) -> tuple:
    """What identifies a target's view: its image size and camera matrices (targets with equal
    keys share one G-buffer)."""
    return (t.width, t.height, np.asarray(t.camera.view).tobytes(),
            np.asarray(t.camera.projection).tobytes())


def prepare(problem: FitProblem, *, chunk: int | None = CHUNK) -> Prepared:
    """Rasterize every view once and stack its targets (see `Prepared`).

    ``chunk`` bounds the memory of a fit step: the step evaluates at most about this many
    pixel-targets at once (`CHUNK` by default; at least 256 pixels of each view of a batch),
    looping over chunks of every view's pixels, so a fit from many or large views needs
    memory for its prepared G-buffers and targets (~0.2 KB per pixel-target) plus a bounded
    working set. None evaluates every pixel at once (fewer, larger kernels: on a GPU with
    memory to spare)."""
    if not isinstance(problem, FitProblem):
        raise TypeError(f"prepare: problem must be a FitProblem (jaxnm.config.load_fit, "
                        f"jaxnm.fit.FitProblem), got {type(problem).__name__}")
    check_chunk(chunk)
    views, opts_all, problem = rasterize_views(problem)
    return assemble(views, tuple(opts_all), problem.material, chunk)


def view_options(problem: FitProblem) -> list[RenderOptions]:
    """The render options of each view of ``problem`` (its targets grouped by `view_key`, in
    the order of their first target), from the cameras alone: nothing is rasterized."""
    groups: dict = {}
    for t in problem.targets:
        groups.setdefault(view_key(t), t)
    nm = dataclasses.replace(problem.sampling, encoding="signed", channels=3)
    # a closed mesh seen from outside shows no back face: those views skip them
    box = closed_shape(problem.mesh.positions, problem.mesh.faces)
    return [RenderOptions(width=t0.width, height=t0.height, derivatives=problem.derivatives,
                          precision=problem.precision, frame=problem.frame,
                          shading=problem.shading, double_sided=problem.double_sided,
                          cull_back=box is not None and box_in_front(box, t0.camera),
                          normal_map=nm, normal_map_shape=tuple(problem.map_size),
                          albedo_shape=(tuple(jnp.shape(problem.albedo)[:2])
                                        if jnp.ndim(problem.albedo) == 3 else None),
                          outputs=("color",))
            for t0 in groups.values()]


def rasterize_views(problem: FitProblem) -> tuple[list[View], list[RenderOptions], FitProblem]:
    """Every view of ``problem`` rasterized once: its covered pixels' G-buffer, targets and
    lights (`View`, in `view_options`' order), its options, and the problem (with
    MikkTSpace tangents where its frame needs them)."""
    validate_problem(problem)
    if problem.frame == "vertex" and problem.mesh.tangents is None:  # MikkTSpace, once
        problem = dataclasses.replace(problem, mesh=problem.mesh.with_tangents())
    groups: dict = {}
    for t in problem.targets:
        groups.setdefault(view_key(t), []).append(t)
    views, opts_all = [], []
    for ts, opts in zip(groups.values(), view_options(problem), strict=True):
        t0 = ts[0]
        opts.check_mesh(problem.mesh, problem.source)
        albedo = jax.device_put(problem.albedo)  # (jnp.asarray of NumPy compiles per shape)

        def flat(x):  # an image-layout array's covered pixels
            return x.reshape((-1,) + x.shape[2:])[pix]

        if opts.derivatives == "gbuffer":  # stored neighbours: the whole image's G-buffer
            gb = build_gbuffer(problem.mesh, t0.camera, albedo, opts=opts)
            cover = np.asarray(gb.mask)
            pix = np.flatnonzero(cover).astype(np.int32)
            covered = flat
        else:  # the per-pixel stages on the covered pixels only, in row-major order
            gb, index, count = covered_gbuffer(problem.mesh, t0.camera, albedo, opts=opts)
            pix = np.asarray(index)[:count]
            cover = np.zeros(t0.height * t0.width, bool)
            cover[pix] = True
            cover = cover.reshape(t0.height, t0.width)
            # a copy: a view of the first ``count`` slots would keep every slot (up to twice
            # the covered pixels) alive until the views are stacked
            covered = lambda x: np.array(x[:count])  # noqa: E731
        gb = host(_fit_fields(gb))  # the rest is host-side indexing, in NumPy
        ws = []
        for i, t in enumerate(ts):
            m = cover if t.mask is None else (cover & np.asarray(t.mask, bool))
            if not m.any():
                raise ValueError(f"{problem.source}: {t.name or 'a target'}: the mask and the "
                                 "mesh's silhouette do not overlap")
            ws.append(m[..., None].astype(np.float32))
        views.append(View(map_pixels(gb, covered), pix,
                          np.stack([flat(np.asarray(t.image, np.float32)) for t in ts]),
                          np.stack([flat(w) for w in ws]),
                          host(stack_lights([t.lights for t in ts]))))
        opts_all.append(opts)
        del gb  # the whole image's G-buffer: only the covered pixels are kept
    return views, opts_all, problem


def _fit_fields(gb: GBuffer) -> GBuffer:
    """Only the G-buffer fields a fit step reads (the frame, the position and eye, the albedo,
    the sample plan) and the uv it re-plans coarse-to-fine levels from."""
    return GBuffer(mask=None, triangle_id=None, depth=None, front_facing=None,
                   position=gb.position, uv=gb.uv, frame=gb.frame, plan=gb.plan,
                   albedo=gb.albedo, eye=gb.eye)


def assemble(views: list[View], options: tuple[RenderOptions, ...],
             material: Material, chunk: int | None) -> Prepared:
    """Order each view's pixels by the taps they need, pad, and stack views into batches.

    A trilinear plan always has 8 taps, but where the level of detail is
    clamped (magnification, or the coarsest level) or integral, the second
    level's 4 weights are exactly 0. The geometry is fixed, so this is known
    once; gathering those pixels with 4 taps halves their gather and its
    transpose (the scatter-add that dominates the backward pass). Views whose
    lights have the same structure share one batch (see `ViewBatch`), unless
    padding a view to the batch's largest would more than double its pixels. Each tap
    group is cut into equal chunks of at most ``chunk`` pixel-targets over the batch's
    views (see `prepare`). Takes ``views`` over: each entry is set to None once copied
    (the caller's list must hold the only references, so the memory is returned as it goes).
    """
    by_lights: dict = {}
    for v, view in enumerate(views):
        by_lights.setdefault(light_key(view.lights), []).append(v)
    size = [view.pixels.shape[0] for view in views]
    groups = []  # by decreasing pixel count; a new batch where padding would double the work
    for members in by_lights.values():
        members = sorted(members, key=lambda v: -size[v])
        batch = [members[0]]
        for v in members[1:]:
            if 2 * size[v] >= size[batch[0]]:
                batch.append(v)
            else:
                groups.append(batch)
                batch = [v]
        groups.append(batch)
    batches = []
    for members in groups:
        parts = [tap_groups(views[v]) for v in members]
        eight = views[members[0]].gbuffer.plan.num_taps == 8
        targets = tuple(views[v].images.shape[0] for v in members)
        per_chunk = None if chunk is None else max(256, chunk // (len(members) * max(targets)))
        na, ka = chunking(max(len(a) for a, _ in parts), per_chunk)
        nb, kb = chunking(max(len(b) for _, b in parts), per_chunk)
        stacked = stack_rows(views, members, parts, ka, kb, max(targets))
        # moved to the device one array at a time, each host copy dropped once moved: the
        # peak holds the batch about twice, not four times (views, rows, stack, device)
        leaves, tree = jax.tree_util.tree_flatten(stacked)
        del stacked
        for j in range(len(leaves)):
            leaves[j] = jax.device_put(leaves[j])
        stacked = jax.tree_util.tree_unflatten(tree, leaves)
        del leaves
        batches.append(ViewBatch(**stacked, views=tuple(members), targets=targets,
                                 split=ka if eight else 0, chunks=(na, nb)))
    # on the device once (a step then moves nothing to it), in float32 as the rest
    return Prepared(tuple(batches), jax.device_put(host(material)), options, chunk)


def with_map_size(prep: Prepared, size) -> Prepared:
    """``prep`` re-planned for a map of ``size`` (h, w) (same G-buffers, new sample plans):
    the levels of a coarse-to-fine fit."""
    views, opts_all = [], []
    for v, opts in enumerate(prep.options):
        view = prep.view(v)
        o = dataclasses.replace(opts, normal_map_shape=tuple(size))
        nm = o.normal_map
        plan = host(_tex.plan_sample(view.gbuffer.uv, size_hw=tuple(size), levels=o.levels,
                                      filter=nm.filter, wrap=nm.wrap, uv_origin=nm.uv_origin))
        views.append(dataclasses.replace(view, gbuffer=dataclasses.replace(view.gbuffer,
                                                                           plan=plan)))
        opts_all.append(o)
    return assemble(views, tuple(opts_all), prep.material, prep.chunk)


def shard_views(prep: Prepared, devices=None) -> Prepared:
    """``prep`` with the views of every `ViewBatch` spread over ``devices`` (default: all
    local devices), for a fit that runs on several GPUs (or hosts) at once.

    A `jax.sharding.Mesh` with one axis, ``"views"``, and a `NamedSharding` that splits the
    leading (view) axis of every batch array; the material is replicated. A batch whose
    view count is not a multiple of the device count is padded with copies of its first
    view that weigh nothing (so they change no residual, loss or gradient). `fit_normal_map`
    and `residuals` then run as one SPMD program: each device shades its views, and the
    texel gradients are summed across devices by XLA. With ``jax.distributed.initialize``
    run first, ``jax.devices()`` spans every host, and the same call spreads the views over
    all of them. Results equal the single-device ones up to the order of the sums.
    """
    from jax.sharding import Mesh, NamedSharding, PartitionSpec

    devices = list(jax.devices() if devices is None else devices)
    n = len(devices)
    if n == 1:
        return prep
    mesh = Mesh(np.array(devices), ("views",))
    split = NamedSharding(mesh, PartitionSpec("views"))
    batches = []
    for b in prep.batches:
        pad = (-len(b.views)) % n
        if pad:
            def extend(x, pad=pad):
                x = np.asarray(x)
                return np.concatenate([x, np.repeat(x[:1], pad, axis=0)], axis=0)

            b = jax.tree_util.tree_map(extend, b)
            b = dataclasses.replace(b, weights=np.concatenate(
                [np.asarray(b.weights)[:-pad], np.zeros_like(np.asarray(b.weights)[-pad:])]),
                pixels=np.concatenate([np.asarray(b.pixels)[:-pad],
                                       np.full_like(np.asarray(b.pixels)[-pad:], -1)]),
                views=b.views + (-1,) * pad, targets=b.targets + (0,) * pad)
        batches.append(jax.device_put(b, split))
    material = jax.device_put(prep.material, NamedSharding(mesh, PartitionSpec()))
    return Prepared(tuple(batches), material, prep.options, prep.chunk)
