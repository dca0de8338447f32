"""The depth test's buffer, stored tile by tile so that each slot writes one whole tile.

A slot (one triangle on one tile, `jaxnm._exec.slots`) covers up to ``block**2`` pixels; with
the buffer stored as (tiles, block, block), its depth test is one scatter of a whole tile,
so XLA's scatters loop over slots, not pixels. Every scatter here combines by min or max,
so its result does not depend on the order of repeated tiles (deterministic GPU ops leave
them alone). The result is OpenGL's ``GL_LESS`` in draw order: the nearest fragment, and on
equal depth the lowest triangle index.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array

__all__ = ["EMPTY_KEY", "NO_TRIANGLE", "depth_keys", "empty_buffer", "tiles_to_image",
           "winners", "write"]

#: The triangle of a pixel that no triangle covers (above every index: a no-op in a min).
NO_TRIANGLE = np.iinfo(np.int32).max
_ANY_TRIANGLE = np.iinfo(np.int32).min  # below every id: a no-op in a max


def depth_keys(depth: Array, t: Array) -> Array:
    """uint64 keys whose order is the depth test's, ``GL_LESS`` in draw order: the nearer
    fragment first, on equal depth the lower triangle index. The depth's bits (a float of
    at most 32 bits, in [0, 1] or ``inf``; its sign bit cleared so that -0 is +0) are the
    high word, and read as an unsigned integer they order as the depths do; the index
    (>= 0) is the low word. A background pixel is `EMPTY_KEY` (inf, no triangle). One
    scatter-min of these keys does what a min of depths, then a min of indices among the
    nearest would (two scatters and two gathers per round): it is order-independent, and
    on GPUs a single 64-bit atomic min. Call under ``jax.enable_x64(True)``."""
    bits = jax.lax.bitcast_convert_type(depth.astype(jnp.float32), jnp.uint32)
    high = (bits & np.uint32(0x7FFFFFFF)).astype(jnp.uint64) << np.uint64(32)
    key = high | t.astype(jnp.uint32).astype(jnp.uint64)[:, None, None]
    return jnp.where(depth < jnp.inf, key, EMPTY_KEY)


#: An empty pixel's key (`depth_keys`): depth ``inf``, triangle `NO_TRIANGLE`.
EMPTY_KEY = np.uint64((0x7F800000 << 32) | NO_TRIANGLE)


def write(buf, tile: Array, depth: Array, t: Array):
    """``buf`` after one round of slots: slot ``s`` writes the depths ``depth[s]`` (block,
    block) (``inf``: not covered) of triangle ``t[s]`` into tile ``tile[s]``; the nearer
    fragment wins, on equal depth the lower triangle index. A keyed buffer takes one
    scatter-min of `depth_keys` (under ``jax.enable_x64(True)``)."""
    if not isinstance(buf, tuple):
        return buf.at[tile].min(depth_keys(depth, t), mode="drop")
    return _write_pair(buf, tile, depth, t)


def _write_pair(bufs, tile, depth, t):
    """One round of the depth test into separate depth and triangle buffers (depths wider
    than 32 bits): nearer wins; on equal depth the lower triangle index."""
    zbuf, ids = bufs
    before = zbuf[tile]
    zbuf = zbuf.at[tile].min(depth, mode="drop")
    after = zbuf[tile]
    # where this round brought a pixel nearer, the earlier winner is gone. A max, not a
    # set: every scatter here combines by min or max, which XLA knows to be independent
    # of the order of repeated tiles, so deterministic GPU ops leave them alone (a set
    # with repeated indices it would serialise)
    ids = ids.at[tile].max(jnp.where(after < before, NO_TRIANGLE, _ANY_TRIANGLE),
                           mode="drop")
    win = (depth == after) & (depth < jnp.inf)
    ids = ids.at[tile].min(jnp.where(win, t[:, None, None], NO_TRIANGLE), mode="drop")
    return zbuf, ids


def empty_buffer(tiles: int, block: int, dtype) -> Array | tuple[Array, Array]:
    """The buffer before any triangle, (tiles, block, block): `depth_keys` where the depth is
    at most 32 bits wide, else a pair of depths and triangles."""
    if jnp.dtype(dtype).itemsize <= 4:
        with jax.enable_x64(True):
            return jnp.full((tiles, block, block), EMPTY_KEY, jnp.uint64)
    return (jnp.full((tiles, block, block), jnp.inf, dtype),
            jnp.full((tiles, block, block), NO_TRIANGLE, jnp.int32))


def winners(buf) -> Array:
    """Each pixel's triangle index in the buffer (`NO_TRIANGLE`: none), per tile."""
    if isinstance(buf, tuple):
        return buf[1]
    with jax.enable_x64(True):
        return (buf & np.uint64(0xFFFFFFFF)).astype(jnp.uint32).astype(jnp.int32)


def tiles_to_image(tiles: Array, width: int, height: int) -> Array:
    """(tiles_y * tiles_x, block, block) per-tile values (rows: window y up) as an
    (H, W) image in image layout (row 0 = top)."""
    _, block, _ = tiles.shape
    tiles_x, tiles_y = -(-width // block), -(-height // block)
    window = tiles.reshape(tiles_y, tiles_x, block, block).transpose(0, 2, 1, 3).reshape(
        tiles_y * block, tiles_x * block)
    return window[:height, :width][::-1]
