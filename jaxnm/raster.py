r"""Visibility: which triangle each pixel sees (OpenGL semantics), without pixels x triangles.

**Coordinates.** Window coordinates follow OpenGL: ``x`` to the right, ``y``
*up*, pixel ``(i, j)`` has its centre at ``(i + 1/2, j + 1/2)``, window depth is
``(z_ndc + 1) / 2``. Every image-shaped array jaxnm returns is in *image
layout*: row 0 is the **top** row, i.e. image row ``r`` holds window row
``j = H - 1 - r``.

**Homogeneous rasterization.** Each vertex is mapped to homogeneous window
coordinates ``h = ((X + W) w_px / 2, (Y + W) h_px / 2, W)`` (no division). For
a triangle with rows ``h_0, h_1, h_2`` and a pixel centre ``p = (x, y, 1)`` the
edge functions are ``E_i(p) = det[p; h_j; h_k]`` (``i, j, k`` cyclic), and

.. math::
    b_i = \frac{E_i}{\sum_m E_m}, \qquad w = \frac{\det M}{\sum_m E_m}, \qquad
    z_{win} = \frac{\sum_m E_m h^z_m}{\det M}

are the perspective-correct barycentrics of the point seen through ``p``, its
clip ``w`` and its window depth (``M = [h_0; h_1; h_2]``, ``h^z = (Z + W)/2``).
A pixel is covered iff every ``E_i`` has the sign of ``det M`` (which implies
``w > 0``: the point is in front of the eye) and ``0 <= z_win <= 1`` (between
the near and far planes). This is near-plane clipping without clipped
polygons and without ever dividing by ``w`` (Olano and Greer, "Triangle scan
conversion using 2D homogeneous coordinates", 1997). ``det M > 0`` means the
triangle is counter-clockwise in the window (front-facing, GL default).

**Fill rule.** A pixel centre exactly on an edge (``E_i == 0``) belongs to the
triangle whose inward edge normal ``n = sign(det M) grad E_i`` satisfies the
tie rule (see `TIE_RULE`). Each edge function is evaluated with its two
vertices in a canonical (lexicographic) order and then negated if needed, so
the two triangles that share an edge compute bit-identical values of opposite
sign: coverage is watertight (no cracks, no double coverage) in float32.

**Cost.** Work is triangle-parallel. The image is a grid of ``block x block``
pixel tiles; a *slot* is one (triangle, tile) pair, for every tile a triangle's
clipped screen bounding box touches. Slots are processed ``slots`` at a time
(a fixed buffer); the number of rounds adapts at run time, so nothing is ever
dropped, and memory stays bounded. How the work is split (the tile size, the
slots per round and the passes) is a `RasterStrategy`, chosen per backend by
`default_strategy`; it changes the time, never the image. The depth buffer is
stored tile by tile, so
each slot's depth test is a scatter of one whole tile: a scatter-min of 64-bit
keys, the depth's bits above the triangle index, which keeps the nearest
fragment and on equal depth the lowest index (``GL_LESS`` with draw order =
index order) in one order-independent scatter.
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array
from jaxtyping import ArrayLike, Float, Int, Integer

from ._exec.arrays import cumsum, div, roll_last, xyw
from ._exec.compaction import flat_nonzero
from ._exec.fusion import materialize
from .numerics import dot

__all__ = [
    "Fragments", "RasterStrategy", "default_strategy", "rasterize", "triangle_ids", "overdraw",
    "compact", "expand", "TIE_RULE", "SUBPIXEL_BITS", "MAX_SLOTS", "MAX_SLOTS_ACCELERATOR"
]

#: A pixel centre exactly on an edge belongs to the triangle whose inward edge
#: normal ``n`` (window coordinates, y up) has ``n.x > 0``, or ``n.x == 0`` and
#: ``n.y > 0``: left and bottom edges (window y up) own their centres, i.e. the
#: D3D "top-left" rule in image coordinates. This is what Mesa llvmpipe does
#: (measured; see tests/glref.py and tests/test_gl.py).
TIE_RULE = "left_bottom_yup"

#: Vertices are snapped to a 1/2**8 pixel grid for the coverage test, as GPUs do.
SUBPIXEL_BITS = 8


@dataclasses.dataclass(frozen=True)
class RasterStrategy:
    """How the rasterizer spends its work: the time and memory of a frame, never its result
    (every strategy gives the same triangle ids, depth and facing). Static (a `jax.jit`
    argument); `default_strategy` chooses one per backend and scene size.

    **Fields:**
    - `block`: the side of the square pixel tiles. A *slot* is one (triangle, tile) pair,
      for every tile a triangle's clipped bounding box touches; the depth buffer is stored
      tile by tile, and each slot's depth test is one scatter of a whole tile.
    - `slots`: the slots depth-tested together, a round (a fixed buffer); rounds repeat
      until every slot is done. A CPU wants rounds whose buffers stay in its caches, a GPU
      few large ones (its loop waits on the host for every round's condition).
    - `pass_slots`: a frame's slots are counted in int32; a frame that could have more
      than this many is depth-tested in passes over its triangles, each counting at most
      this many (a power of two; only huge images with tens of thousands of large
      triangles need more than one).
    """

    block: int = 4
    slots: int = 1 << 15
    pass_slots: int = 1 << 30

    def __post_init__(self):
        for name in ("block", "slots", "pass_slots"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < 1:
                raise ValueError(f"RasterStrategy: `{name}` must be a positive int, got {v!r}")
        if self.pass_slots & (self.pass_slots - 1):
            raise ValueError(f"RasterStrategy: `pass_slots` must be a power of two, got "
                             f"{self.pass_slots}")


#: The most slots per round, by backend (others: `MAX_SLOTS_ACCELERATOR`). On the CPU a
#: round's buffers should stay in its caches (2^15 was the fastest of 2^14 to 2^17); a
#: GPU's while loop waits on the host for its condition every round, so it wants few large
#: rounds (2^19 was the fastest of 2^15 to 2^21 for the benchmark's 200k torus at 1024^2).
#: `python -m scripts.benchmarks.bench --parts raster` measures visibility.
MAX_SLOTS = {"cpu": 1 << 15}
MAX_SLOTS_ACCELERATOR = 1 << 19

def default_strategy(num_faces: int, width: int, height: int, *, block: int = 4,
                     backend: str | None = None) -> RasterStrategy:
    """The `RasterStrategy` for ``num_faces`` triangles in a ``width`` x ``height`` image on
    ``backend`` (JAX's default if None): about one round for small scenes, at most
    `MAX_SLOTS` slots a round."""
    backend = jax.default_backend() if backend is None else backend
    cap = MAX_SLOTS.get(backend, MAX_SLOTS_ACCELERATOR)
    tiles = (-(-width // block)) * (-(-height // block))
    want = max(4 * num_faces, tiles, 256)
    return RasterStrategy(block=block, slots=int(min(cap, 1 << (want - 1).bit_length())))

_NO_TRIANGLE = np.iinfo(np.int32).max
_ANY_TRIANGLE = np.iinfo(np.int32).min  # below every id: a no-op in a max


def _pixel_centers(height: int, width: int, dtype=jnp.float32) -> tuple[Array, Array]:
    """Window coordinates (x, y), each (H, W), of the pixel centres in image layout."""
    x = jnp.arange(width, dtype=dtype) + 0.5
    y = (height - 1 - jnp.arange(height, dtype=dtype)) + 0.5
    return jnp.broadcast_to(x[None, :], (height, width)), jnp.broadcast_to(y[:, None],
                                                                           (height, width))


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Fragments:
    """What the rasterizer saw at each pixel (image layout, row 0 = top).

    **Fields:**
    - `triangle_id`: (H, W) int32 index into ``faces``, -1 for background.
    - `depth`: (H, W) float32 window depth in [0, 1]; 1 on background.
    - `front_facing`: (H, W) bool, counter-clockwise in the window (y up).
    - `clip`: (V, 4) the clip-space vertices that were rasterized.
    - `faces`: (F, 3) int32 triangle vertex indices.
    - `pixels`: None for a whole image; for fragments packed by `compact`, each
      fragment's window pixel ``(i, j)`` (int32, ``(..., 2)``; its centre is
      ``(i + 1/2, j + 1/2)``), and the other per-pixel fields have its leading shape.
    - `packed_from`: static; the ``(height, width)`` of the image packed fragments
      come from (None for a whole image).
    - `window`: None, or the vertices' window x, y and w, (V, 3) (`_window_homogeneous`
      of ``clip`` less its z), computed once by `compact` so that per-pixel stages run in
      chunks do not redo it for every chunk (the 200k torus: a pass over 100k vertices
      per chunk); None: computed from ``clip`` where needed. (Replacing ``clip`` in
      packed fragments: replace ``window`` too, or set it to None.)

    ``clip`` and ``faces`` are kept so that later stages can evaluate *the
    pixel's own triangle* anywhere on screen (helper pixels), and so that
    gradients flow from interpolated values back to the vertices.
    """

    triangle_id: Array
    depth: Array
    front_facing: Array
    clip: Array
    faces: Array
    pixels: Array | None = None
    packed_from: tuple[int, int] | None = dataclasses.field(default=None,
                                                            metadata=dict(static=True))
    window: Array | None = None

    @property
    def mask(self) -> Array:
        """True where a triangle covers the pixel."""
        return self.triangle_id >= 0

    @property
    def shape(self) -> tuple[int, ...]:
        """``(height, width)`` (a whole image), or the packed fragments' shape."""
        return self.triangle_id.shape

    @property
    def image_shape(self) -> tuple[int, int]:
        """``(height, width)`` of the image (for packed fragments, the one they come from)."""
        return self.shape if self.packed_from is None else self.packed_from

    def window_pixels(self) -> tuple[Array, Array]:
        """Window pixel indices (i, j) of each fragment (int32, of `shape`; j counts up)."""
        if self.pixels is not None:
            return self.pixels[..., 0], self.pixels[..., 1]
        height, width = self.shape
        i = jnp.arange(width, dtype=jnp.int32)
        j = height - 1 - jnp.arange(height, dtype=jnp.int32)
        return (jnp.broadcast_to(i[None, :], (height, width)),
                jnp.broadcast_to(j[:, None], (height, width)))

    def window_centers(self, dtype=jnp.float32) -> tuple[Array, Array]:
        """Window coordinates (x, y) of each fragment's pixel centre, of `shape`."""
        if self.pixels is None:
            return _pixel_centers(*self.shape, dtype)
        i, j = self.window_pixels()
        return i.astype(dtype) + 0.5, j.astype(dtype) + 0.5


def compact(triangle_id: Array, clip: Array, faces: Array, capacity: int, *,
            subpixel_bits: int | None = SUBPIXEL_BITS,
            orientation: Array | None = None, index: Array | None = None
            ) -> tuple[Fragments, Array]:
    """The covered pixels of a whole image, packed into ``capacity`` slots as `Fragments`.

    Every per-pixel stage evaluates a pixel from its own triangle and its window position
    only, so it can run on the packed fragments (whose `Fragments.pixels` say where they
    are) and skip the background; `expand` puts its results back in image layout.

    **Arguments:**
    - `triangle_id`: (H, W) from `rasterize` (-1: background); only the ids are needed,
      so the image's depth and facing need not have been computed.
    - `clip`, `faces`, `subpixel_bits`: as given to `rasterize`.
    - `capacity`: slots; covered pixels beyond it are dropped: take at least the number
      of covered pixels. Unused slots are background (triangle -1, depth 1).
    - `orientation`: each triangle's orientation sign (F,) as `triangle_ids` gives it, if
      known; else the facing is computed from each fragment's corners again.
    - `index`: the (capacity,) flat image indices of the pixels to pack, if chosen by the
      caller (``H * W`` for unused slots; e.g. the covered pixels ranked ``k`` to
      ``k + capacity - 1``); by default the first ``capacity`` covered pixels.

    **Returns:** the packed `Fragments` (per-pixel fields of shape (capacity,); depth and
    facing as `rasterize` computes them) and the (capacity,) flat image index of each
    slot (``H * W`` for unused slots).
    """
    height, width = triangle_id.shape
    n = height * width
    ids = triangle_id.reshape(-1)
    if index is None:
        index = flat_nonzero(ids >= 0, capacity, n)
    used = index < n
    at = jnp.minimum(index, n - 1)
    row = div(at, width)
    col = at - row * width
    tid = jnp.where(used, ids[at], -1)
    placed = Fragments(triangle_id=tid, depth=None, front_facing=None, clip=clip, faces=faces,
                       pixels=jnp.stack([col, height - 1 - row], -1),
                       packed_from=(height, width),
                       window=materialize(xyw(_window_homogeneous(clip, width, height))))
    tri, tri_depth = _window_corners(clip, faces, width=width, height=height,
                                     subpixel_bits=subpixel_bits)
    covered = tid >= 0
    t = jnp.maximum(tid, 0)
    if orientation is not None:  # (spares every slot a gather of its corners and snapping)
        sigma = orientation[t]
    elif capacity < faces.shape[0]:
        # the facing from the fragment's own (snapped) corners: no pass over the mesh
        corners = tri[t]  # (capacity, 3, 4)
        sigma = jnp.sign(_orientation([[corners[:, k, c] for c in range(4)]
                                       for k in range(3)]))
    else:  # more slots than triangles (every pixel, under a caller's jit): per triangle
        sigma = jnp.sign(_orientation(tri.components()))[t]
    depth = jnp.where(covered, _pixel_depth(tri_depth, t, *placed.window_centers(
        tri_depth.dtype)), 1.0)
    return dataclasses.replace(placed, depth=depth, front_facing=covered & (sigma > 0)), index


def expand(values: Array, index: Array, height: int, width: int, fill=0) -> Array:
    """Per-slot ``values`` (capacity, ...) of `compact`'s fragments as an image
    (H, W, ...), ``fill`` where no slot writes."""
    n = height * width
    out = jnp.full((n,) + values.shape[1:], fill, values.dtype)
    # Every slot writes its own pixel (unused slots: distinct indices past the end, dropped),
    # and saying so spares differentiation the general scatter's bookkeeping: for indices
    # that might repeat, JAX's forward-mode rule scatters an image of update ids and
    # gathers it back to find the winners.
    index = jnp.where(index < n, index, n + jnp.arange(index.shape[0], dtype=index.dtype))
    return out.at[index].set(values, mode="drop", unique_indices=True).reshape(
        (height, width) + values.shape[1:])


def _window_homogeneous(clip: Array, width: int, height: int) -> Array:
    """Homogeneous window coordinates ``((X+W) w/2, (Y+W) h/2, (Z+W)/2, W)`` of clip points.

    Dividing the first three by the last gives window x, y (pixels, y up) and
    window depth.
    """
    x, y, z, w = jnp.moveaxis(clip, -1, 0)
    return jnp.stack([(x + w) * (0.5 * width), (y + w) * (0.5 * height), (z + w) * 0.5, w], -1)


# --------------------------------------------------------------------------------------
# per-triangle setup
# --------------------------------------------------------------------------------------


def _lex_less(a, b) -> Array:
    """Lexicographic ``a < b`` of 3-component points given as sequences of arrays."""
    return (a[0] < b[0]) | ((a[0] == b[0]) & ((a[1] < b[1]) | ((a[1] == b[1]) & (a[2] < b[2]))))


def _edge_coefficients(hj, hk, x0: Array, y0: Array):
    """Coefficients of ``E(x0 + dx, y0 + dy) = c + a dx + b dy = det[p; hj; hk]``.

    ``hj, hk``: homogeneous window (x, y, w), each a sequence of three arrays (structure of
    arrays: XLA's CPU loops vectorise over their one axis, not over a minor axis of 3).
    The two vertices are put in canonical order before any arithmetic, so that the same
    edge gives bit-identical magnitudes in both triangles that share it.
    """
    swap = _lex_less(hk, hj)
    u = [jnp.where(swap, q, p) for p, q in zip(hj, hk)]
    v = [jnp.where(swap, p, q) for p, q in zip(hj, hk)]
    sign = jnp.where(swap, -1.0, 1.0).astype(hj[0].dtype)
    # translate so that the evaluation point is the origin (better conditioned)
    ux, uy, uw = u[0] - x0 * u[2], u[1] - y0 * u[2], u[2]
    vx, vy, vw = v[0] - x0 * v[2], v[1] - y0 * v[2], v[2]
    a = uy * vw - uw * vy
    b = uw * vx - ux * vw
    c = ux * vy - uy * vx
    return sign * a, sign * b, sign * c


def _tie_inside(na: Array, nb: Array) -> Array:
    """Tie rule on the inward normal ``(na, nb)`` of an edge (see `TIE_RULE`)."""
    return (na > 0) | ((na == 0) & (nb > 0))


def _snap_vertices(h: Array, subpixel_bits: int | None) -> Array:
    """Coverage positions: vertices in front of the eye projected and snapped to the sub-pixel grid.

    A vertex with ``w > 0`` (and a window position within +-2**14 px, where
    float32 still resolves the grid) is replaced by ``(x, y, depth, 1)`` with x, y
    rounded to multiples of ``2**-subpixel_bits``. Rescaling a row of ``M`` by a
    positive factor changes neither the signs of the edge functions nor the
    depth, so snapped and homogeneous vertices mix freely; triangles that cross
    the eye plane keep their unsnapped homogeneous vertices (a GPU would snap
    the clipped polygon instead, which can differ by 1/512 px at its edges).
    """
    if subpixel_bits is None:
        return h
    hx, hy, hz, hw = jnp.moveaxis(h, -1, 0)
    ok = hw > 0
    inv = 1.0 / jnp.where(ok, hw, 1.0)
    x, y = hx * inv, hy * inv
    lim = float(1 << 14)
    ok = ok & (jnp.abs(x) < lim) & (jnp.abs(y) < lim)
    q = float(1 << subpixel_bits)
    snapped = jnp.stack([jnp.round(x * q) / q, jnp.round(y * q) / q, hz * inv,
                         jnp.ones_like(hw)], -1)
    return jnp.where(ok[:, None], snapped, h)


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class _Corners:
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


def _orientation(v: list[list[Array | None]]) -> Array:
    """``det M`` of each triangle (rows ``(x, y, w)`` of its corners), as
    ``dot(h0, cross(h1, h2))`` term by term."""
    (x0, y0, _, w0), (x1, y1, _, w1), (x2, y2, _, w2) = v
    return x0 * (y1 * w2 - w1 * y2) + y0 * (w1 * x2 - x1 * w2) + w0 * (x1 * y2 - y1 * x2)


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


def _triangle_setup(tri: _Corners, width: int, height: int, block: int, cull_back: bool):
    """Per-triangle sign, block bounding box and validity.

    ``tri``: the triangles' (snapped) homogeneous window corners.
    Returns ``sigma`` (F,) sign of det M, the first tile ``tx0, ty0`` of the bounding box
    on the image's grid of ``block x block`` tiles (tile ``(tx, ty)`` holds window pixels
    ``i // block == tx``, ``j // block == ty``), the box's width in tiles ``nbx`` and its
    number of tiles, each a (triangle, tile) slot, ``count`` (F,); ``count = 0`` for
    triangles that cannot cover a pixel (their ``nbx`` means nothing).

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
    sigma, tx0, ty0, nbx, count = jax.lax.cond(
        snapped, functools.partial(_snapped_setup, **kw),
        lambda h, faces, _: _general_setup(h, faces, **kw), h, tri.faces, on_grid)
    # a face index out of range stands for no vertex: the triangle covers nothing (a
    # non-finite corner, the general set-up's test, likewise), as a GPU drops it
    faces = tri.faces
    in_range = jnp.all((faces >= 0) & (faces < h.shape[0]), axis=1)
    return sigma, tx0, ty0, nbx, jnp.where(in_range, count, 0)


def _snapped_setup(h: Array, faces: Array, on_grid: Array, *, width, height, block,
                   cull_back):
    """`_triangle_setup` where every vertex has ``w = 1`` and a depth in [0, 1].

    Where also every corner is on the 1/256 grid (``on_grid``: snapped, the default), it
    drops the triangles whose box holds one or two pixel centres that the triangle clearly
    misses (`_misses_centre`): a dense mesh's many sub-pixel triangles cover no pixel at
    all (the 200k torus at 512^2: 28,787 of its 72,897 triangles with a box, 36 % of the
    (triangle, tile) slots), and the test costs less than their slots."""
    xy = materialize(h[:, :2])
    rows = [xy[faces[:, k]] for k in range(3)]
    x, y = materialize(([r[:, 0] for r in rows], [r[:, 1] for r in rows]))
    one = jnp.ones_like(x[0])
    sigma = jnp.sign(_orientation([[x[k], y[k], None, one] for k in range(3)]))
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
    (`_slot_fragments`, at the tile's first centre and stepped by ``a dx + b dy``). For
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
    """`_triangle_setup` for any homogeneous corners: the box clipped at the near plane."""
    v = _Corners(h, faces).components()
    sigma = jnp.sign(_orientation(v))

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
    xmin, xmax, ymin, ymax, bad_w = jax.lax.cond(in_front, corners, clipped, v)
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


# --------------------------------------------------------------------------------------
# slot evaluation
# --------------------------------------------------------------------------------------


def _depth_plane(th: Array, x0: Array, y0: Array):
    """Window depth ``dz_c + dz_a dx + dz_b dy`` around ``(x0, y0)``; triangles ``th`` (S, 3, 4).

    Corner by corner on (S,) vectors (see `_edge_coefficients`), sums in corner order."""
    hx = [th[:, k, 0] - x0 * th[:, k, 3] for k in range(3)]
    hy = [th[:, k, 1] - y0 * th[:, k, 3] for k in range(3)]
    hw = [th[:, k, 3] for k in range(3)]
    hz = [th[:, k, 2] for k in range(3)]
    c, a, b = [], [], []
    for i in range(3):
        j, k = (i + 1) % 3, (i + 2) % 3
        c.append(hx[j] * hy[k] - hy[j] * hx[k])
        a.append(hy[j] * hw[k] - hw[j] * hy[k])
        b.append(hw[j] * hx[k] - hx[j] * hw[k])

    def dot3(p, q):
        return p[0] * q[0] + p[1] * q[1] + p[2] * q[2]

    det = dot3(c, hw)  # sum_i E_i(p) w_i = det M at any p
    det = jnp.where(det == 0, 1.0, det)
    return dot3(c, hz) / det, dot3(a, hz) / det, dot3(b, hz) / det


def _slot_fragments(slot0, tri_h, tri_depth, sigma, tx0, ty0, nbx, order, starts, ends,
                    starts_ahead, total, *, width, height, block, slots):
    """Evaluate ``slots`` consecutive (triangle, tile) slots starting at ``slot0``.

    ``tri_h``, ``tri_depth``: the snapped (coverage) and unsnapped (depth) homogeneous
    window corners (`_Corners`); ``order``, ``starts``, ``ends``,
    ``starts_ahead``: see `_fragment_source`. Returns each slot's flat tile index
    ``ty * tiles_x + tx`` (slots,), the window depth of its ``block**2`` pixels
    ``(slots, block, block)`` (indexed ``[slot, dy, dx]``; ``inf`` where the triangle does
    not cover the pixel) and its triangle index (slots,).
    """
    s = slot0 + jnp.arange(slots, dtype=jnp.int32)
    live = s < total
    # Which triangle owns each slot: the round starts inside triangle k0 (of those with
    # slots, in order); each of the next `slots` triangles starts at most once in the round,
    # so counting the starts up to each slot (a scatter and a prefix sum over the round)
    # replaces a binary search per slot.
    k0 = jnp.searchsorted(ends, slot0, side="right").astype(jnp.int32)
    ahead = jax.lax.dynamic_slice_in_dim(starts_ahead, k0 + 1, slots)
    marks = jnp.zeros((slots,), jnp.int32).at[ahead - slot0].add(1, mode="drop")
    k = jnp.minimum(k0 + cumsum(marks), order.shape[0] - 1)
    t = order[k]
    local = s - starts[k]
    nx = jnp.maximum(nbx[t], 1)
    row = div(local, nx)  # local >= 0, nx >= 1
    tx = tx0[t] + (local - row * nx)
    ty = ty0[t] + row
    bx, by = tx * block, ty * block  # the tile's first pixel
    x0 = bx.astype(tri_h.dtype) + 0.5
    y0 = by.astype(tri_h.dtype) + 0.5

    th = tri_h[t]  # (S, 3, 4)
    sg = sigma[t]
    # per edge, (S,) vectors: edge i joins corners i + 1 and i + 2
    corner = [(th[:, k, 0], th[:, k, 1], th[:, k, 3]) for k in range(3)]
    a, b, c = zip(*(_edge_coefficients(corner[(i + 1) % 3], corner[(i + 2) % 3], x0, y0)
                    for i in range(3)))
    tie = [_tie_inside(sg * ai, sg * bi) for ai, bi in zip(a, b)]
    # depth from the unsnapped vertices, as GPUs do (only coverage uses snapped positions)
    dz_c, dz_a, dz_b = _depth_plane(tri_depth[t], x0, y0)
    # Fold the orientation into the coefficients: inside <=> e > 0, or e >= 0 on tie edges.
    a, b, c = [sg * q for q in a], [sg * q for q in b], [sg * q for q in c]
    live = live & (sg != 0)
    tiles_x = -(-width // block)
    # Per-slot values computed once into their own buffers: fused into the per-pixel kernel,
    # XLA would recompute them for every pixel of the tile.
    a, b, c, tie, dz_c, dz_a, dz_b, live, bx, by = materialize(
        (a, b, c, tie, dz_c, dz_a, dz_b, live, bx, by))
    fx = jnp.tile(jnp.arange(block, dtype=jnp.int32), block)[None, :]  # (1, block**2):
    fy = jnp.repeat(jnp.arange(block, dtype=jnp.int32), block)[None, :]  # dx, then dy
    inside = live[:, None] & (bx[:, None] + fx < width) & (by[:, None] + fy < height)
    fx, fy = fx.astype(dz_c.dtype), fy.astype(dz_c.dtype)
    for i in range(3):
        e = c[i][:, None] + a[i][:, None] * fx + b[i][:, None] * fy  # (S, block**2)
        inside = inside & jnp.where(tie[i][:, None], e >= 0, e > 0)
    depth = dz_c[:, None] + dz_a[:, None] * fx + dz_b[:, None] * fy
    inside = inside & (depth >= 0.0) & (depth <= 1.0)
    # (the reshape after the barrier: the loop runs over the (S, block**2) shape, whose minor
    # axis of 16 vectorises better than (S, block, block)'s 4)
    depth = materialize(jnp.where(inside, depth, jnp.inf)).reshape(slots, block, block)
    # (from the materialised bx, by >= 0)
    tile = div(by, block) * tiles_x + div(bx, block)
    return tile, depth, t


def _window_corners(clip, faces, *, width, height, subpixel_bits):
    """The triangles' corners in homogeneous window coordinates (`_Corners`): snapped
    (coverage) and unsnapped (depth)."""
    h_unsnapped = _window_homogeneous(jax.lax.stop_gradient(clip), width, height)
    h = _snap_vertices(h_unsnapped, subpixel_bits)
    return _Corners(materialize(h), faces), _Corners(h_unsnapped, faces)


def _with_slots(counts: Array) -> tuple[Array, Array]:
    """The triangles that have slots (``counts > 0``, (F,)), in order, and their slot counts,
    each (F,) (padded with triangle 0 and no slots): a dense mesh has far fewer such
    triangles than triangles, and the slots' bookkeeping runs over this list."""
    n = counts.shape[0]
    order = flat_nonzero(counts > 0, n, 0)
    live = jnp.arange(n) < jnp.sum(counts > 0)
    return order, jnp.where(live, counts[order], 0)


def _fragment_source(tri, tri_depth, setup, order, counts, *, width, height, block, slots):
    """Returns ``(fragments(slot0), total_slots)`` for triangles with corners ``tri``
    (coverage), ``tri_depth`` (depth) and `_triangle_setup` result ``setup``, taking
    ``counts`` slots of each triangle ``order`` (`_with_slots`)."""
    sigma, tx0, ty0, nbx, _ = setup  # (the slot counts come as `counts`)
    ends = cumsum(counts)
    starts = ends - counts
    total = ends[-1]
    # the starts again, padded so that any `slots` of them after one triangle can be sliced
    starts_ahead = jnp.concatenate([starts, jnp.full((slots + 1,), total, jnp.int32)])
    fragments = functools.partial(
        _slot_fragments, tri_h=tri, tri_depth=tri_depth, sigma=sigma, tx0=tx0,
        ty0=ty0, nbx=nbx, order=order, starts=starts, ends=ends, starts_ahead=starts_ahead,
        total=total, width=width, height=height, block=block, slots=slots,
    )
    return fragments, total


_STATIC = ("width", "height", "cull_back", "subpixel_bits", "strategy")


def _depth_test(tri, tri_depth, setup, counts, buf, *, width, height, block, slots):
    """Depth-test triangles into the tiled buffer ``buf`` (tiles, block, block): uint64 keys
    (`_depth_keys`) where the depth is at most 32 bits wide, else a pair (depth, triangle).
    ``counts`` (F,): each triangle's slots (`_each_pass`)."""
    fragments, total = _fragment_source(tri, tri_depth, setup, *_with_slots(counts),
                                        width=width, height=height, block=block, slots=slots)
    keyed = not isinstance(buf, tuple)
    x64 = bool(jax.config.jax_enable_x64)  # the caller's

    def round_(carry):
        # One round of slots, depth-tested straight into the running buffer. Each slot
        # updates one whole tile, so XLA's scatters loop over slots, not pixels, and a
        # round's work does not grow with the image.
        q, buf = carry
        with jax.enable_x64(x64):  # the slots' own arithmetic as everywhere else
            tile, depth, t = fragments(q * slots)
        if keyed:
            return q + 1, buf.at[tile].min(_depth_keys(depth, t), mode="drop")
        return q + 1, _depth_test_pair(buf, tile, depth, t)

    # the keys are 64-bit integers, whatever the caller's jax_enable_x64
    with jax.enable_x64(keyed or x64):
        return jax.lax.while_loop(lambda c: c[0] * slots < total, round_,
                                  (jnp.int32(0), buf))[1]


def _depth_keys(depth: Array, t: Array) -> Array:
    """uint64 keys whose order is the depth test's, ``GL_LESS`` in draw order: the nearer
    fragment first, on equal depth the lower triangle index. The depth's bits (a float of
    at most 32 bits, in [0, 1] or ``inf``; its sign bit cleared so that -0 is +0) are the
    high word, and read as an unsigned integer they order as the depths do; the index
    (>= 0) is the low word. A background pixel is `_EMPTY_KEY` (inf, no triangle). One
    scatter-min of these keys does what a min of depths, then a min of indices among the
    nearest would (two scatters and two gathers per round): it is order-independent, and
    on GPUs a single 64-bit atomic min. Call under ``jax.enable_x64(True)``."""
    bits = jax.lax.bitcast_convert_type(depth.astype(jnp.float32), jnp.uint32)
    high = (bits & np.uint32(0x7FFFFFFF)).astype(jnp.uint64) << np.uint64(32)
    key = high | t.astype(jnp.uint32).astype(jnp.uint64)[:, None, None]
    return jnp.where(depth < jnp.inf, key, _EMPTY_KEY)


#: An empty pixel's key (`_depth_keys`): depth ``inf``, triangle `_NO_TRIANGLE`.
_EMPTY_KEY = np.uint64((0x7F800000 << 32) | _NO_TRIANGLE)


def _depth_test_pair(bufs, tile, depth, t):
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
    ids = ids.at[tile].max(jnp.where(after < before, _NO_TRIANGLE, _ANY_TRIANGLE),
                           mode="drop")
    win = (depth == after) & (depth < jnp.inf)
    ids = ids.at[tile].min(jnp.where(win, t[:, None, None], _NO_TRIANGLE), mode="drop")
    return zbuf, ids


def _empty_depth_buffer(tiles: int, block: int, dtype) -> Array | tuple[Array, Array]:
    """The depth test's buffer before any triangle (`_depth_test`)."""
    if jnp.dtype(dtype).itemsize <= 4:
        with jax.enable_x64(True):
            return jnp.full((tiles, block, block), _EMPTY_KEY, jnp.uint64)
    return (jnp.full((tiles, block, block), jnp.inf, dtype),
            jnp.full((tiles, block, block), _NO_TRIANGLE, jnp.int32))


def _winners(buf) -> Array:
    """Each pixel's triangle index in the depth test's buffer (`_NO_TRIANGLE`: none)."""
    if isinstance(buf, tuple):
        return buf[1]
    with jax.enable_x64(True):
        return (buf & np.uint64(0xFFFFFFFF)).astype(jnp.uint32).astype(jnp.int32)


def _tiles_to_image(tiles: Array, width: int, height: int) -> Array:
    """(tiles_y * tiles_x, block, block) per-tile values (rows: window y up) as an
    (H, W) image in image layout (row 0 = top)."""
    _, block, _ = tiles.shape
    tiles_x, tiles_y = -(-width // block), -(-height // block)
    window = tiles.reshape(tiles_y, tiles_x, block, block).transpose(0, 2, 1, 3).reshape(
        tiles_y * block, tiles_x * block)
    return window[:height, :width][::-1]


def _slot_passes(counts: Array, pass_slots: int) -> tuple[Array, Array]:
    """The pass of each triangle (F,) int32 and the number of passes, for triangles with
    ``counts`` slots each (each at most ``pass_slots``): triangle i is in pass
    ``floor(start_i / pass_slots)`` where ``start_i`` is its first slot in the frame, counted
    exactly (mod 2**32 plus the number of wrap-arounds) though it may exceed int32."""
    ends = jnp.cumsum(counts.astype(jnp.uint32))  # exact mod 2**32
    wrapped = jnp.concatenate([jnp.zeros((1,), bool), ends[1:] < ends[:-1]])
    laps = jnp.cumsum(wrapped.astype(jnp.int32))  # 2**32 wrap-arounds up to each end
    starts = ends - counts.astype(jnp.uint32)
    # the start's wrap-arounds are the previous end's (an end that wrapped, starts before)
    laps = jnp.concatenate([jnp.zeros((1,), jnp.int32), laps[:-1]])
    shift = pass_slots.bit_length() - 1
    passes = laps * (1 << (32 - shift)) + (starts >> shift).astype(jnp.int32)
    return passes, passes[-1] + 1


def _each_pass(fn, counts, carry, *, tiles: int, pass_slots: int):
    """``carry = fn(counts_p, carry)`` for the triangles of each pass in turn
    (`_slot_passes`), ``counts_p`` (F,) being ``counts`` (each triangle's slots: its box's
    tiles) for that pass's triangles and 0 for the others; a single call with ``counts``
    itself where the frame cannot have more than ``pass_slots`` slots (faces x tiles;
    static). A while loop, not a ``lax.cond`` between it and one pass: XLA's CPU
    conditional around the depth test made the whole frame slower at 200k triangles
    (the ``lax.cond`` below only chooses how the passes are counted)."""
    n = counts.shape[0]
    if n * tiles <= pass_slots:
        return fn(counts, carry)
    # Most frames fit in one pass, and a float32 sum of the counts (each < 2**28) says so
    # for far less than `_slot_passes`' exact running sums:
    # its rounding error is below F * 2**-24 of the sum
    fits = jnp.sum(counts.astype(jnp.float32)) * (1.0 + n * 2.0**-24) < pass_slots
    passes, n_passes = jax.lax.cond(
        fits, lambda c: (jnp.zeros_like(c), jnp.int32(1)),
        lambda c: _slot_passes(c, pass_slots), counts)

    x64 = bool(jax.config.jax_enable_x64)  # the caller's

    def one_pass(c):
        p, carry = c
        with jax.enable_x64(x64):
            return p + 1, fn(jnp.where(passes == p, counts, 0), carry)

    # (a carry of 64-bit depth keys stays 64-bit whatever the caller's jax_enable_x64)
    with jax.enable_x64(x64 or any(x.dtype == np.uint64 for x in jax.tree.leaves(carry))):
        return jax.lax.while_loop(lambda c: c[0] < n_passes, one_pass,
                                  (jnp.int32(0), carry))[1]


@functools.partial(jax.jit, static_argnames=_STATIC)
def _rasterize(clip, faces, *, width, height, cull_back, subpixel_bits, strategy):
    tid, sigma, tri_depth = _visible_triangles(
        clip, faces, width=width, height=height, cull_back=cull_back,
        subpixel_bits=subpixel_bits, strategy=strategy)
    # facing from the coverage (snapped) orientation, as the rasterizer saw the triangle
    depth, front = _depth_and_facing(tri_depth, sigma, tid,
                                     *_pixel_centers(height, width, tri_depth.dtype))
    return tid, depth, front


def _visible_triangles(clip, faces, *, width, height, cull_back, subpixel_bits,
                       strategy: RasterStrategy):
    """Each pixel's triangle (H, W) (-1: background), each triangle's orientation sign
    (F,) in the window (the snapped corners' ``sign(det M)``: +1 counter-clockwise, i.e.
    front-facing) and the unsnapped corners (`_Corners`)."""
    block = strategy.block
    kw = dict(width=width, height=height, block=block, slots=strategy.slots)
    tiles = (-(-width // block)) * (-(-height // block))
    tri, tri_depth = _window_corners(clip, faces, width=width, height=height,
                                     subpixel_bits=subpixel_bits)
    setup = _triangle_setup(tri, width, height, block, cull_back)
    buf = _each_pass(lambda n, buf: _depth_test(tri, tri_depth, setup, n, buf, **kw),
                     setup[4], _empty_depth_buffer(tiles, block, clip.dtype), tiles=tiles,
                     pass_slots=strategy.pass_slots)
    ids = _tiles_to_image(_winners(buf), width, height)
    return jnp.where(ids != _NO_TRIANGLE, ids, -1), setup[0], tri_depth


def triangle_ids(clip: Float[ArrayLike, "V 4"], faces: Integer[ArrayLike, "F 3"], *,
                 width: int, height: int, cull_back: bool = False,
                 subpixel_bits: int | None = SUBPIXEL_BITS,
                 strategy: RasterStrategy | None = None) -> tuple[Array, Array]:
    """`rasterize`'s triangle ids alone, (H, W) int32 (-1: background), and each triangle's
    orientation in the window (F,) (+1: counter-clockwise, front-facing; -1: clockwise; 0:
    degenerate), which `compact` takes instead of computing the facing of every packed
    pixel again. Same arguments as `rasterize`; traceable (no eager checks of values)."""
    clip, faces, kw = _prepare_args(clip, faces, width, height, cull_back, subpixel_bits,
                                    strategy)
    if faces.shape[0] == 0:
        return jnp.full((height, width), -1, jnp.int32), jnp.zeros((0,), clip.dtype)
    tid, sigma, _ = _visible_triangles(clip, faces, **kw)
    return tid, sigma


def _depth_and_facing(tri_depth: _Corners, sigma: Array, tid: Array, x: Array, y: Array):
    """Window depth (1 on background) and front-facing of each pixel's triangle ``tid`` (-1:
    background) at the pixel centres ``x``, ``y`` (broadcastable to ``tid``), from the
    unsnapped corners ``tri_depth`` (`_Corners`) and the snapped orientation ``sigma``
    (F,)."""
    covered = tid >= 0
    t = jnp.maximum(tid, 0)
    # facing per triangle (F,), then gathered (per-pixel work here would fuse badly with
    # the depth below)
    front = covered & (sigma[t] > 0)
    return jnp.where(covered, _pixel_depth(tri_depth, t, x, y), 1.0), front


def _pixel_depth(tri_depth: _Corners, tid: Array, x: Array, y: Array) -> Array:
    """Window depth of each pixel's triangle at the pixel centre (x, y), from its unsnapped
    corners ``tri_depth`` (`_Corners`)."""
    hv = tri_depth[tid]  # (..., 3, 4)
    x, y = x[..., None], y[..., None]
    hx = hv[..., 0] - x * hv[..., 3]
    hy = hv[..., 1] - y * hv[..., 3]
    e = roll_last(hx, 1) * roll_last(hy, 2) - roll_last(hy, 1) * roll_last(hx, 2)
    num = dot(e, hv[..., 2])
    den = dot(e, hv[..., 3])
    return num / jnp.where(den == 0, 1.0, den)


@functools.partial(jax.jit, static_argnames=_STATIC)
def _overdraw(clip, faces, *, width, height, cull_back, subpixel_bits, strategy):
    block, slots = strategy.block, strategy.slots
    tri, tri_depth = _window_corners(clip, faces, width=width, height=height,
                                     subpixel_bits=subpixel_bits)
    tiles = (-(-width // block)) * (-(-height // block))
    setup = _triangle_setup(tri, width, height, block, cull_back)

    def one_pass(counts, count):
        fragments, total = _fragment_source(tri, tri_depth, setup, *_with_slots(counts),
                                            width=width, height=height, block=block,
                                            slots=slots)

        def round_(c):
            q, count = c
            tile, depth, _ = fragments(q * slots)
            return q + 1, count.at[tile].add((depth < jnp.inf).astype(jnp.int32), mode="drop")

        return jax.lax.while_loop(lambda c: c[0] * slots < total, round_,
                                  (jnp.int32(0), count))[1]

    count = _each_pass(one_pass, setup[4], jnp.zeros((tiles, block, block), jnp.int32),
                       tiles=tiles, pass_slots=strategy.pass_slots)
    return _tiles_to_image(count, width, height)


def overdraw(clip: Float[ArrayLike, "V 4"], faces: Integer[ArrayLike, "F 3"], *, width: int,
             height: int, cull_back: bool = False, subpixel_bits: int | None = SUBPIXEL_BITS,
             strategy: RasterStrategy | None = None) -> Int[Array, "{height} {width}"]:
    """(H, W) int32: how many triangles cover each pixel, before the depth test.

    Same coverage rules as `rasterize` (fill rule, clipping, culling). Useful to
    visualise overdraw and to check watertightness: a closed mesh seen from
    outside covers every pixel 0 or 2 times, from inside exactly once.
    """
    clip, faces, kw = _prepare_args(clip, faces, width, height, cull_back, subpixel_bits,
                                    strategy)
    if faces.shape[0] == 0:
        return jnp.zeros((height, width), jnp.int32)
    return _overdraw(clip, faces, **kw)


def rasterize(clip: Float[ArrayLike, "V 4"], faces: Integer[ArrayLike, "F 3"], *, width: int,
              height: int, cull_back: bool = False, subpixel_bits: int | None = SUBPIXEL_BITS,
              strategy: RasterStrategy | None = None) -> Fragments:
    """Rasterize triangles given in clip space (see the module docstring for the conventions).

    **Arguments:**
    - `clip`: (V, 4) float clip-space vertex positions (``projection @ view @ p``).
    - `faces`: (F, 3) int vertex indices.
    - `width`, `height`: image size in pixels (static).
    - `cull_back`: drop clockwise (back-facing) triangles.
    - `subpixel_bits`: snap vertex positions to this sub-pixel grid for the
      coverage test (8, like llvmpipe and most GPUs), or None for exact
      (unsnapped) coverage. Interpolation always uses the unsnapped positions.
    - `strategy`: how the work is split (tiles, rounds, windows, passes; the same result
      whatever it is): a `RasterStrategy`, by default `default_strategy`'s.

    **Returns:** a `Fragments`. Visibility is not differentiable; gradients of
    interpolated attributes flow through `Fragments.clip` instead.
    """
    clip, faces, kw = _prepare_args(clip, faces, width, height, cull_back, subpixel_bits,
                                    strategy)
    num_faces = faces.shape[0]
    if num_faces == 0:
        tid = jnp.full((height, width), -1, jnp.int32)
        return Fragments(tid, jnp.ones((height, width), clip.dtype),
                         jnp.zeros((height, width), bool), clip, faces)
    tid, depth, front = _rasterize(clip, faces, **kw)
    return Fragments(tid, depth, front, clip, faces)


def _prepare_args(clip, faces, width, height, cull_back, subpixel_bits, strategy):
    """Validate `rasterize` arguments (eagerly where values are concrete)."""
    if not all(isinstance(v, (int, np.integer)) and v > 0 for v in (width, height)):
        raise ValueError(f"rasterize: image size must be positive integers, got width={width!r}, "
                         f"height={height!r}")
    width, height = int(width), int(height)
    clip = jnp.asarray(clip)
    faces = jnp.asarray(faces)
    if clip.ndim != 2 or clip.shape[1] != 4:
        raise ValueError(f"rasterize: `clip` must have shape (V, 4), got {clip.shape}")
    if faces.ndim != 2 or faces.shape[1] != 3:
        raise ValueError(f"rasterize: `faces` must have shape (F, 3), got {faces.shape}")
    if not jnp.issubdtype(faces.dtype, jnp.integer):
        raise ValueError(f"rasterize: `faces` must be integers, got {faces.dtype}")
    faces = faces.astype(jnp.int32)
    if not jnp.issubdtype(clip.dtype, jnp.floating):
        clip = clip.astype(jnp.float32)
    if subpixel_bits is not None and not 0 <= subpixel_bits <= 12:
        raise ValueError(f"rasterize: `subpixel_bits` must be in [0, 12] or None, got "
                         f"{subpixel_bits}")
    if strategy is None:
        strategy = default_strategy(faces.shape[0], width, height)
    elif not isinstance(strategy, RasterStrategy):
        raise ValueError(f"rasterize: `strategy` must be a RasterStrategy, got "
                         f"{type(strategy).__name__}")
    block = strategy.block
    if width * height >= 2**31 or (-(-width // block)) * (-(-height // block)) > 2**28:
        raise ValueError(f"rasterize: a {width}x{height} image is too large (at most 2**31 - 1 "
                         f"pixels and 2**28 tiles of block x block)")
    if not isinstance(clip, jax.core.Tracer) and clip.size:
        bad = ~np.all(np.isfinite(np.asarray(clip)), axis=1)
        if bad.any():
            raise ValueError(f"rasterize: `clip` has {int(bad.sum())} non-finite vertices "
                             f"(first: {int(np.argmax(bad))})")
    if not isinstance(faces, jax.core.Tracer) and faces.size:
        lo, hi = int(faces.min()), int(faces.max())
        if lo < 0 or hi >= clip.shape[0]:
            raise ValueError(f"rasterize: face indices must be in [0, {clip.shape[0] - 1}], "
                             f"found {lo if lo < 0 else hi}")
    kw = dict(width=width, height=height, cull_back=cull_back, subpixel_bits=subpixel_bits,
              strategy=strategy)
    return clip, faces, kw
