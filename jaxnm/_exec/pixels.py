"""Per-pixel stages on the covered pixels only: packed, in passes and in chunks.

Every per-pixel stage of the pipeline evaluates a pixel from its own triangle and its window
position (`jaxnm.raster.Fragments`), so it can run on the covered pixels alone, packed
(`jaxnm.raster.compact`), and skip the background. `over_covered_pixels` does so: it takes
the covered pixels a pass at a time, evaluates a per-pixel function on each pass's packed
fragments in chunks, and writes the results back into images. Whether a frame runs this way
is `packs`: on the CPU for images large enough to pay for the packing. The result is the
same as the function evaluated on the whole image: coverage, triangle ids and facing
exactly, the rest to float32 rounding.

Why passes and chunks: a pass is at most a quarter of the image's pixels, so XLA's temporary
buffers stay under glibc's threshold for reusing freed memory (larger ones are mapped and
page-faulted in again on every call); a chunk's intermediates (a few (slots, 3) float32
arrays) stay in the CPU's caches. docs/guides/design.md has the measurements.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

import jax
import jax.numpy as jnp
from jax import Array

from .compaction import ranked_nonzero
from .device import resident

__all__ = ["PACK_MIN_PIXELS", "PASS_SLOTS", "PIXEL_CHUNK", "capacity", "over_covered_pixels",
           "packs"]

#: On the CPU, the covered pixels of images of at least this many pixels (256x256) are
#: packed; smaller images run on every pixel, where the packing's own work and a second
#: program to compile cost more than they save.
PACK_MIN_PIXELS = 1 << 16

#: Packed per-pixel stages run in chunks of this many slots at least and at most (a
#: `jax.lax.map`; a pass's slots in four chunks within these bounds): chunks small enough
#: that their intermediates stay in the caches, few enough that a backward pass has few
#: whole-map gradient sums.
PIXEL_CHUNK = (1 << 14, 1 << 16)

#: A pass packs at most this many covered pixels, and at most a quarter of the image's.
PASS_SLOTS = 1 << 16


def packs(pixels: int, *, neighbours: bool, backend: str | None = None) -> bool:
    """Whether per-pixel stages of a ``pixels``-pixel image run on its packed covered pixels
    (`over_covered_pixels`) on ``backend`` (JAX's default if None): on the CPU, for images of
    at least `PACK_MIN_PIXELS`, unless the stages read their ``neighbours`` (stored values of
    adjacent pixels, which only the whole image has). A GPU evaluates every pixel at once
    (and where programs are `jaxnm._exec.device.resident`, one program per frame: packing
    counts the covered pixels at run time)."""
    return not resident(backend) and pixels >= PACK_MIN_PIXELS and not neighbours


def capacity(count: int, pixels: int) -> int:
    """Slots for ``count`` covered pixels of a ``pixels``-pixel image: the smallest of
    pixels / 2, / 4, ..., / 64 that holds them, or all of them when more than half the
    image is covered. Few sizes, because each is one compilation."""
    capacity = pixels
    for k in range(1, 7):
        if (pixels >> k) < max(count, 1):
            break
        capacity = pixels >> k
    return capacity


def _chunk(slots: int) -> int:
    """The chunk size of `PIXEL_CHUNK` for a packed program of ``slots`` slots."""
    return min(max(PIXEL_CHUNK[0], -(-slots // 4)), PIXEL_CHUNK[1])


def over_covered_pixels(per_pixel: Callable, tid: Array, pack: Callable, *,
                        outputs: tuple[str, ...]) -> dict[str, Array]:
    """``outputs`` of the image whose triangle ids are ``tid`` (H, W) (-1: background), with
    ``per_pixel`` evaluated on its covered pixels only.

    **Arguments:**
    - `per_pixel`: packed `jaxnm.raster.Fragments` -> a dict of per-slot values (slots,
      ...), zero on background slots: the outputs other than the fragments' own.
    - `tid`: the image's triangle ids.
    - `pack`: ``pack(capacity, index)`` -> ``(fragments, index)``, `jaxnm.raster.compact`
      of this image's covered pixels into ``capacity`` slots (``index``: the flat image
      indices of the pixels to pack, None for the first ``capacity`` covered ones).
    - `outputs`: the names wanted, among ``per_pixel``'s and the fragments' own: ``mask``,
      ``triangle_id``, ``depth`` (1 on background), ``front_facing``.

    **Returns:** each output as an (H, W, ...) image, zero (depth: 1) on background.

    The covered pixels are taken a quarter of the image's pixels at a time (pass ``p``
    takes those ranked ``p * Q`` to ``(p + 1) * Q - 1``, `ranked_nonzero`), each pass packed
    and evaluated in chunks (`_over_chunks`) and its results written into the images; the
    passes past the covered pixels are skipped. A frame with at most a quarter of the image
    covered runs one pass."""
    height, width = tid.shape
    pixels = height * width
    slots = min(-(-pixels // 4), PASS_SLOTS)
    total, window = ranked_nonzero(tid.reshape(-1) >= 0)
    names = [n for n in outputs if n not in ("mask", "triangle_id")]
    shapes = jax.eval_shape(lambda: per_pixel(pack(slots, None)[0]))
    fill = {"depth": 1.0}

    def one_pass(p, images):
        index = window(p * slots, slots, pixels)
        frags, index = pack(slots, index)
        values = _over_chunks(per_pixel, frags, _chunk(slots))
        values.update(depth=frags.depth, front_facing=frags.front_facing)
        # each covered pixel is written once (the unused slots' indices distinct, past the
        # end: dropped), as XLA is told
        at = jnp.where(index < pixels, index, pixels + jnp.arange(slots, dtype=index.dtype))
        return {n: images[n].at[at].set(values[n].astype(images[n].dtype), mode="drop",
                                        unique_indices=True) for n in names}

    def step(p, images):
        return jax.lax.cond(p * slots < total, one_pass, lambda p, images: images, p, images)

    def blank(n):
        if n in ("depth", "front_facing"):
            return jnp.full((pixels,), fill.get(n, False), jnp.float32 if n == "depth" else bool)
        s = shapes[n]
        return jnp.zeros((pixels,) + s.shape[1:], s.dtype)

    # (`jax.checkpoint`: differentiated, a pass is evaluated again in the backward pass. Else
    # the conditional's residuals, which its skipping branch fills with zeros, are stacked
    # pass by pass: a copy of the mesh's arrays and of the normal map per pass, written on
    # every call, and per-pixel intermediates where a pass is one chunk)
    images = jax.lax.fori_loop(0, -(-pixels // slots), jax.checkpoint(step),
                               {n: blank(n) for n in names})
    out = {"mask": tid >= 0, "triangle_id": tid}
    out.update({n: v.reshape((height, width) + v.shape[1:]) for n, v in images.items()})
    return {n: out[n] for n in outputs}


def _over_chunks(fn: Callable, frags, chunk: int):
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
    # (zero-filled buffers, dynamic updates, copies) cost twice the recomputation)
    out = jax.lax.map(jax.checkpoint(one), per_slot)
    return jax.tree_util.tree_map(lambda y: y.reshape((k * size,) + y.shape[2:])[:n], out)
