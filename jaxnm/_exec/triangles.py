"""The rasterizer's per-triangle work: the corners as slots read them, their orientation,
and which tiles each triangle's box touches (its slots).

A triangle gets one slot per tile of the image's grid that its clipped screen box touches
(`jaxnm._exec.slots`). The boxes are conservative: exact coverage is decided per pixel, so a
larger box only costs time. A triangle that can cover no pixel gets no slot: one that is
degenerate, culled, wholly outside the depth range or not finite, and one whose box holds
one or two pixel centres that it certainly misses (a dense mesh's sub-pixel triangles, many
of which cover no pixel at all).
"""

from __future__ import annotations

import dataclasses
import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array

from .arrays import div
from .device import choose
from .fusion import materialize

__all__ = ["Corners", "TriangleSetup", "orientation", "triangle_setup"]


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Corners:
    """Triangle corners in homogeneous window coordinates, kept as the vertices (V, 4) and
    the faces (F, 3): corners are gathered where needed (per slot, per pixel) rather than
    as an (F, 3, 4) array written and read again every frame."""

    vertices: Array
    faces: Array

    def __getitem__(self, t: Array) -> Array:
        """The corners (..., 3, 4) of triangles ``t``."""
        return self.vertices[self.faces[t]]

    @property
    def dtype(self):
        return self.vertices.dtype

    def components(self) -> list[list[Array]]:
        """``v[k][c]``: component ``c`` (x, y, z, w) of corner ``k`` of every triangle,
        each (F,), computed once into their own buffers.

        Structure of arrays: per-triangle setup on (F,) vectors fuses into a few loops,
        where the same arithmetic on (F, 3, 4) or (F, 6, 4) arrays (minor axes of 3 to 6)
        ran an order of magnitude slower on XLA's CPU backend.
        """
        return materialize([[self.vertices[:, c][self.faces[:, k]] for c in range(4)]
                            for k in range(3)])


def orientation(v: list[list[Array | None]]) -> Array:
    """``det M`` of each triangle (rows ``(x, y, w)`` of its corners), as
    ``dot(h0, cross(h1, h2))`` term by term."""
    (x0, y0, _, w0), (x1, y1, _, w1), (x2, y2, _, w2) = v
    return x0 * (y1 * w2 - w1 * y2) + y0 * (w1 * x2 - x1 * w2) + w0 * (x1 * y2 - y1 * x2)


class TriangleSetup(NamedTuple):
    """Each triangle's orientation and slots (`triangle_setup`), each (F,).

    - `sigma`: the sign of ``det M`` of the (snapped) corners: +1 counter-clockwise in the
      window (front-facing), -1 clockwise, 0 degenerate.
    - `tx0`, `ty0`: the first tile of its box (tile ``(tx, ty)`` holds the window pixels
      ``i // block == tx``, ``j // block == ty``), int32.
    - `nbx`: the box's width in tiles, int32.
    - `count`: the box's number of tiles, each one (triangle, tile) slot; 0 for a triangle
      that covers no pixel (its other fields then mean nothing).
    """

    sigma: Array
    tx0: Array
    ty0: Array
    nbx: Array
    count: Array


def triangle_setup(tri: Corners, width: int, height: int, block: int,
                   cull_back: bool) -> TriangleSetup:
    """Each triangle's orientation and its box on the image's grid of ``block x block``
    tiles (a `TriangleSetup`), for the triangles' (snapped) homogeneous window corners
    ``tri``.

    The usual frame has every vertex snapped (``w = 1``: in front of the eye, within the
    snapping range) with a depth in [0, 1]: then nothing is clipped, no corner is divided,
    and a triangle needs only its corners' x and y, gathered as (F, 2) rows (three
    gathers instead of twelve).
    Both ways give the same result there, bit for bit: a product with ``w = 1`` is exact.
    """
    h = tri.vertices
    z, w = h[:, 2], h[:, 3]
    snapped = jnp.all((w == 1.0) & (z >= 0.0) & (z <= 1.0))
    # corners on the 1/256 grid (snapped with up to 8 sub-pixel bits): `_misses_centre`'s
    # differences are exact
    q = h[:, :2] * 256.0
    on_grid = jnp.all(q == jnp.round(q))
    kw = dict(width=width, height=height, block=block, cull_back=cull_back)
    # (`choose`: on accelerators both set-ups and a select, no conditional to read back)
    sigma, tx0, ty0, nbx, count = choose(
        snapped, functools.partial(_snapped_setup, **kw),
        lambda h, faces, _: _general_setup(h, faces, **kw), h, tri.faces, on_grid)
    # a face index out of range stands for no vertex: the triangle covers nothing (a
    # non-finite corner, the general set-up's test, likewise), as a GPU drops it
    faces = tri.faces
    in_range = jnp.all((faces >= 0) & (faces < h.shape[0]), axis=1)
    return TriangleSetup(sigma, tx0, ty0, nbx, jnp.where(in_range, count, 0))


def _snapped_setup(h: Array, faces: Array, on_grid: Array, *, width, height, block,
                   cull_back):
    """`triangle_setup` where every vertex has ``w = 1`` and a depth in [0, 1].

    Where also every corner is on the 1/256 grid (``on_grid``: snapped, the default), it
    drops the triangles whose box holds one or two pixel centres that the triangle clearly
    misses (`_misses_centre`): a dense mesh's many sub-pixel triangles cover no pixel at
    all (about a third of a dense mesh's slots: docs/guides/design.md), and the test costs
    less than their slots."""
    xy = materialize(h[:, :2])
    rows = [xy[faces[:, k]] for k in range(3)]
    x, y = materialize(([r[:, 0] for r in rows], [r[:, 1] for r in rows]))
    one = jnp.ones_like(x[0])
    sigma = jnp.sign(orientation([[x[k], y[k], None, one] for k in range(3)]))
    valid = (sigma > 0) if cull_back else (sigma != 0)
    i0, i1, j0, j1 = _centre_ranges(
        functools.reduce(jnp.minimum, x), functools.reduce(jnp.maximum, x),
        functools.reduce(jnp.minimum, y), functools.reduce(jnp.maximum, y), width, height)
    ni, nj = i1 - i0 + 1, j1 - j0 + 1
    # the box's centres, where it holds at most two: (i0, j0) and the next one across or up
    few = (ni >= 1) & (nj >= 1) & (ni * nj <= 2)
    first = _misses_centre(x, y, sigma, i0, j0)
    second = _misses_centre(x, y, sigma, i0 + (ni == 2), j0 + (nj == 2))
    valid = valid & ~(on_grid & few & first & second)
    return sigma, *_box_tiles(i0, i1, j0, j1, valid, block)


def _misses_centre(x, y, sigma, i, j) -> Array:
    """Whether triangles with (snapped, ``w = 1``) corners ``x[k], y[k]`` and orientation
    ``sigma`` certainly do not cover pixel centre ``(i + 1/2, j + 1/2)``: some edge function
    there is below minus a bound of the rounding of both its evaluation here and the slots'
    (`jaxnm.raster`'s, at the tile's first centre and stepped by ``a dx + b dy``). For
    corners on the 1/256 grid (the caller's condition) the differences to a centre are
    exact in float32 (within 2^16 px; farther, the bound grows with them) and each product
    rounds once; the bound, 2^-16 (|dx_j| + |dx_k| + 4)(|dy_j| + |dy_k| + 4), is 16x what
    the two evaluations can err by together."""
    px = i.astype(x[0].dtype) + 0.5
    py = j.astype(x[0].dtype) + 0.5
    dx = [xk - px for xk in x]
    dy = [yk - py for yk in y]
    out = jnp.zeros(px.shape, bool)
    for e in range(3):
        p, q = (e + 1) % 3, (e + 2) % 3
        edge = sigma * (dx[p] * dy[q] - dy[p] * dx[q])
        bound = 2.0 ** -16 * ((jnp.abs(dx[p]) + jnp.abs(dx[q]) + 4.0)
                              * (jnp.abs(dy[p]) + jnp.abs(dy[q]) + 4.0))
        out = out | (edge < -bound)
    return out


def _general_setup(h: Array, faces: Array, *, width, height, block, cull_back):
    """`triangle_setup` for any homogeneous corners: the box clipped at the near plane."""
    v = Corners(h, faces).components()
    sigma = jnp.sign(orientation(v))

    # Clipped bounding box: vertices in front of the near plane, plus the points where
    # edges cross it. (Also excludes triangles wholly behind near or beyond far.)
    hz = [v[k][2] for k in range(3)]
    front = [z >= 0.0 for z in hz]  # z_clip >= -w  <=>  (Z + W)/2 >= 0
    in_far = [v[k][2] <= v[k][3] for k in range(3)]

    def clipped(v):
        pts, ok = [v[k] for k in range(3)], list(front)
        for i in range(3):
            j = (i + 1) % 3
            di, dj = hz[i], hz[j]
            crosses = front[i] != front[j]
            t = jnp.where(crosses, di / jnp.where(crosses, di - dj, 1.0), 0.0)
            pts.append([pi + t * (pj - pi) for pi, pj in zip(v[i], v[j])])
            ok.append(crosses)
        return _window_box(pts, ok)

    def corners(v):  # every corner in front: no edge crosses, the same box
        return _window_box(v, [jnp.ones_like(f) for f in front])

    # the usual scene lies wholly in front of the near plane: then the crossings, their
    # divisions and selects are not computed
    in_front = functools.reduce(jnp.logical_and, [jnp.all(f) for f in front])
    xmin, xmax, ymin, ymax, bad_w = choose(in_front, corners, clipped, v)
    # a weird projection (kept point with w <= 0): fall back to the whole screen
    xmin = jnp.where(bad_w, 0.0, xmin)
    ymin = jnp.where(bad_w, 0.0, ymin)
    xmax = jnp.where(bad_w, float(width), xmax)
    ymax = jnp.where(bad_w, float(height), ymax)

    finite = functools.reduce(jnp.logical_and, [jnp.isfinite(c) for k in v for c in k])
    valid = (
        finite
        & (sigma != 0)
        & (front[0] | front[1] | front[2])
        & (in_far[0] | in_far[1] | in_far[2])
    )
    if cull_back:
        valid = valid & (sigma > 0)
    return sigma, *_box_tiles(*_centre_ranges(xmin, xmax, ymin, ymax, width, height), valid,
                              block)


def _window_box(pts, keep):
    """The window-space box ``(xmin, xmax, ymin, ymax)`` of the homogeneous points ``pts``
    where ``keep`` (one boolean array per point), and whether a kept point is not in front
    of the eye (w <= 0)."""
    bad_w = functools.reduce(jnp.logical_or, [k & ~(p[3] > 0.0) for k, p in zip(keep, pts)])
    big = jnp.asarray(np.finfo(np.float32).max, pts[0][0].dtype)
    xmin = ymin = big
    xmax = ymax = -big
    for k, p in zip(keep, pts):
        w_safe = jnp.where(k & (p[3] > 0.0), p[3], 1.0)
        px, py = p[0] / w_safe, p[1] / w_safe
        xmin, xmax = jnp.minimum(xmin, jnp.where(k, px, big)), jnp.maximum(xmax, jnp.where(
            k, px, -big))
        ymin, ymax = jnp.minimum(ymin, jnp.where(k, py, big)), jnp.maximum(ymax, jnp.where(
            k, py, -big))
    # computed once: XLA would otherwise recompute the box (its divisions) in each fusion
    # that uses it (four at first)
    return (*materialize((xmin, xmax, ymin, ymax)), bad_w)


def _centre_ranges(xmin, xmax, ymin, ymax, width: int, height: int):
    """The pixel-centre ranges ``i0..i1``, ``j0..j1`` (int32, clamped to the image; empty
    where ``i0 > i1`` or ``j0 > j1``) of window-space boxes: ``i + 1/2`` in [xmin, xmax],
    widened by a hair for rounding in the box's divisions (exact coverage is decided per
    pixel: a wider box is only slower)."""
    lim = float(1 << 24)

    def lo(v):
        v = jnp.clip(v - 0.5, -lim, lim)
        return jnp.ceil(v - (1e-3 + 1e-6 * jnp.abs(v))).astype(jnp.int32)

    def hi(v):
        v = jnp.clip(v - 0.5, -lim, lim)
        return jnp.floor(v + (1e-3 + 1e-6 * jnp.abs(v))).astype(jnp.int32)

    i0, i1, j0, j1 = lo(xmin), hi(xmax), lo(ymin), hi(ymax)
    return (jnp.maximum(i0, 0), jnp.minimum(i1, width - 1), jnp.maximum(j0, 0),
            jnp.minimum(j1, height - 1))


def _box_tiles(i0, i1, j0, j1, valid, block: int):
    """The first tile ``tx0, ty0``, the width in tiles ``nbx`` and the number of tiles
    ``count`` (0 where not ``valid`` or where the box holds no pixel centre) of pixel-centre
    ranges (`_centre_ranges`). (``valid`` enters one loop only, the count's: where it was
    also the width's, XLA evaluated it, and the centre tests in it, twice.)"""
    # the tiles of the image's block x block grid that the box touches
    # (i0, j0 >= 0, and i1, j1 too wherever the box holds a centre)
    tx0, ty0 = div(i0, block), div(j0, block)
    nbx = div(i1, block) - tx0 + 1
    nby = div(j1, block) - ty0 + 1
    count = jnp.where(valid & (i0 <= i1) & (j0 <= j1), nbx * nby, 0)
    return tx0, ty0, nbx, count
