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

**Depth.** The nearest fragment wins, and on equal depth the lowest triangle index
(``GL_LESS`` with draw order = index order), whatever the order fragments arrive in.

**Work.** Triangle-parallel, in bounded memory, never pixels x triangles: the image is a
grid of tiles, and each (triangle, tile) pair that a triangle's clipped box touches is
evaluated, a fixed number at a time. How the work is split is a `RasterStrategy`
(`default_strategy` chooses one per backend); it changes the time, never the image.
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array
from jaxtyping import ArrayLike, Float, Int, Integer

from ._exec import depth as tiled
from ._exec.arrays import div, xyw
from ._exec.compaction import flat_nonzero
from ._exec.fusion import materialize
from ._exec.slots import (
    RasterStrategy,
    SlotList,
    default_strategy,
    each_pass,
    over_rounds,
    round_limits,
    slot_list,
    slot_owners,
)
from ._exec.triangles import Corners, TriangleSetup, triangle_setup
from ._exec.triangles import orientation as triangle_orientation
from .camera import to_window

__all__ = [
    "Fragments", "RasterStrategy", "default_strategy", "rasterize", "triangle_ids", "overdraw",
    "compact", "expand", "TIE_RULE", "SUBPIXEL_BITS"
]

#: A pixel centre exactly on an edge belongs to the triangle whose inward edge
#: normal ``n`` (window coordinates, y up) has ``n.x > 0``, or ``n.x == 0`` and
#: ``n.y > 0``: left and bottom edges (window y up) own their centres, i.e. the
#: D3D "top-left" rule in image coordinates. This is what Mesa llvmpipe does
#: (measured; see tests/glref.py and tests/test_gl.py).
TIE_RULE = "left_bottom_yup"

#: Vertices are snapped to a 1/2**8 pixel grid for the coverage test, as GPUs do.
SUBPIXEL_BITS = 8


def _image_pixels(height: int, width: int) -> tuple[Array, Array]:
    """Window pixel indices (i, j), each (H, W) int32, of an image in image layout."""
    i = jnp.arange(width, dtype=jnp.int32)
    j = height - 1 - jnp.arange(height, dtype=jnp.int32)
    return (jnp.broadcast_to(i[None, :], (height, width)),
            jnp.broadcast_to(j[:, None], (height, width)))


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
    - `window`: None, or the vertices' window x, y and w, (V, 3) (homogeneous window
      coordinates of ``clip`` less its z), computed once by `compact` so that per-pixel
      stages run in chunks do not redo a pass over the vertices for every chunk; None:
      computed from ``clip`` where needed. (Replacing ``clip`` in packed fragments:
      replace ``window`` too, or set it to None.)

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
        return _image_pixels(*self.shape)

    def window_centers(self, dtype=jnp.float32) -> tuple[Array, Array]:
        """Window coordinates (x, y) of each fragment's pixel centre, of `shape`."""
        i, j = self.window_pixels()
        return i.astype(dtype) + 0.5, j.astype(dtype) + 0.5


@functools.partial(jax.jit, static_argnames=("capacity", "subpixel_bits"))
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
                       window=materialize(xyw(to_window(clip, width, height))))
    tri, tri_depth = _window_corners(clip, faces, width=width, height=height,
                                     subpixel_bits=subpixel_bits)
    covered = tid >= 0
    t = jnp.maximum(tid, 0)
    if orientation is not None:  # (spares every slot a gather of its corners and snapping)
        sigma = orientation[t]
    elif capacity < faces.shape[0]:
        # the facing from the fragment's own (snapped) corners: no pass over the mesh
        corners = tri[t]  # (capacity, 3, 4)
        sigma = jnp.sign(triangle_orientation([[corners[:, k, c] for c in range(4)]
                                                for k in range(3)]))
    else:  # more slots than triangles (every pixel, under a caller's jit): per triangle
        sigma = jnp.sign(triangle_orientation(tri.components()))[t]
    depth = jnp.where(covered, _pixel_depth(tri_depth, t, *placed.window_centers(
        tri_depth.dtype)), 1.0)
    return dataclasses.replace(placed, depth=depth, front_facing=covered & (sigma > 0)), index


@functools.partial(jax.jit, static_argnames=("height", "width"))
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


# --------------------------------------------------------------------------------------
# coverage: edge functions, the fill rule, snapping
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


# --------------------------------------------------------------------------------------
# slots: coverage and depth of one triangle on one tile
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


def _slot_fragments(slot0, listed: SlotList, tri_h: Corners, tri_depth: Corners,
                    setup: TriangleSetup, *, width, height, block):
    """Evaluate the round of ``listed.size`` (triangle, tile) slots starting at ``slot0``.

    ``tri_h``, ``tri_depth``: the snapped (coverage) and unsnapped (depth) homogeneous
    window corners; ``setup``: the triangles' tiles (`triangle_setup`). Returns each slot's
    flat tile index ``ty * tiles_x + tx`` (slots,), the window depth of its ``block**2``
    pixels ``(slots, block, block)`` (indexed ``[slot, dy, dx]``; ``inf`` where the triangle
    does not cover the pixel) and its triangle index (slots,).
    """
    slots = listed.size
    sigma, tx0, ty0, nbx, _ = setup
    t, local, live = slot_owners(listed, slot0)
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
    """The triangles' corners in homogeneous window coordinates (`Corners`): snapped
    (coverage) and unsnapped (depth)."""
    h_unsnapped = to_window(jax.lax.stop_gradient(clip), width, height)
    h = _snap_vertices(h_unsnapped, subpixel_bits)
    return Corners(materialize(h), faces), Corners(h_unsnapped, faces)


_STATIC = ("width", "height", "cull_back", "subpixel_bits", "strategy")


def _each_fragment(clip, faces, write, init, *, width, height, cull_back, subpixel_bits,
                   strategy: RasterStrategy):
    """Fold ``write(buf, tile, depth, triangle)`` (`over_rounds`) over every fragment of the
    triangles, a pass and a round of slots at a time, into a tiled buffer that starts as
    ``init(tiles)`` (`jaxnm._exec.depth`). Returns the buffer, each triangle's orientation sign
    (F,) in the window (the snapped corners' ``sign(det M)``: +1 counter-clockwise, i.e.
    front-facing) and the unsnapped corners (`Corners`)."""
    block, slots = strategy.block, strategy.slots
    tiles = (-(-width // block)) * (-(-height // block))
    limits = round_limits(faces.shape[0], tiles, slots, strategy.pass_slots)
    tri, tri_depth = _window_corners(clip, faces, width=width, height=height,
                                     subpixel_bits=subpixel_bits)
    setup = triangle_setup(tri, width, height, block, cull_back)

    def one_pass(counts, buf):  # ``counts`` (F,): each triangle's slots in this pass
        listed = slot_list(counts, slots)
        fragments = functools.partial(_slot_fragments, listed=listed, tri_h=tri,
                                      tri_depth=tri_depth, setup=setup, width=width,
                                      height=height, block=block)
        return over_rounds(fragments, write, buf, total=listed.total, size=slots,
                           limits=limits)

    buf = each_pass(one_pass, setup.count, init(tiles), tiles=tiles,
                    pass_slots=strategy.pass_slots)
    return buf, setup.sigma, tri_depth


@functools.partial(jax.jit, static_argnames=_STATIC)
def _rasterize(clip, faces, *, width, height, cull_back, subpixel_bits, strategy):
    tid, sigma, tri_depth = _visible_triangles(
        clip, faces, width=width, height=height, cull_back=cull_back,
        subpixel_bits=subpixel_bits, strategy=strategy)
    # facing from the coverage (snapped) orientation, as the rasterizer saw the triangle
    i, j = _image_pixels(height, width)
    dtype = tri_depth.dtype
    depth, front = _depth_and_facing(tri_depth, sigma, tid, i.astype(dtype) + 0.5,
                                     j.astype(dtype) + 0.5)
    return tid, depth, front


def _visible_triangles(clip, faces, *, strategy: RasterStrategy, **kw):
    """Each pixel's triangle (H, W) (-1: background), each triangle's orientation sign and
    its unsnapped corners (`_each_fragment`)."""
    buf, sigma, tri_depth = _each_fragment(
        clip, faces, tiled.write, lambda tiles: tiled.empty_buffer(tiles, strategy.block,
                                                                   clip.dtype),
        strategy=strategy, **kw)
    ids = tiled.tiles_to_image(tiled.winners(buf), kw["width"], kw["height"])
    return jnp.where(ids != tiled.NO_TRIANGLE, ids, -1), sigma, tri_depth


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
    return _triangle_ids(clip, faces, **kw)


@functools.partial(jax.jit, static_argnames=_STATIC)
def _triangle_ids(clip, faces, *, width, height, cull_back, subpixel_bits, strategy):
    tid, sigma, _ = _visible_triangles(clip, faces, width=width, height=height,
                                       cull_back=cull_back, subpixel_bits=subpixel_bits,
                                       strategy=strategy)
    return tid, sigma


def _depth_and_facing(tri_depth: Corners, sigma: Array, tid: Array, x: Array, y: Array):
    """Window depth (1 on background) and front-facing of each pixel's triangle ``tid`` (-1:
    background) at the pixel centres ``x``, ``y`` (broadcastable to ``tid``), from the
    unsnapped corners ``tri_depth`` (`Corners`) and the snapped orientation ``sigma``
    (F,)."""
    covered = tid >= 0
    t = jnp.maximum(tid, 0)
    # facing per triangle (F,), then gathered (per-pixel work here would fuse badly with
    # the depth below)
    front = covered & (sigma[t] > 0)
    return jnp.where(covered, _pixel_depth(tri_depth, t, x, y), 1.0), front


def _pixel_depth(tri_depth: Corners, tid: Array, x: Array, y: Array) -> Array:
    """Window depth of each pixel's triangle at the pixel centre (x, y), from its unsnapped
    corners ``tri_depth`` (`Corners`)."""
    # corner by corner on image-shaped arrays: one loop with the corners' gathers in it, where
    # (..., 3, 4) corners and their rolled copies were image-sized buffers (96 MiB at
    # 1024x1024), allocated on every call
    v, faces = tri_depth.vertices, tri_depth.faces
    h = [[v[:, c][faces[:, k][tid]] for c in range(4)] for k in range(3)]
    hx = [h[k][0] - x * h[k][3] for k in range(3)]
    hy = [h[k][1] - y * h[k][3] for k in range(3)]
    e = [hx[(k + 1) % 3] * hy[(k + 2) % 3] - hy[(k + 1) % 3] * hx[(k + 2) % 3]
         for k in range(3)]
    num = e[0] * h[0][2] + e[1] * h[1][2] + e[2] * h[2][2]
    den = e[0] * h[0][3] + e[1] * h[1][3] + e[2] * h[2][3]
    return num / jnp.where(den == 0, 1.0, den)


@functools.partial(jax.jit, static_argnames=_STATIC)
def _overdraw(clip, faces, *, width, height, cull_back, subpixel_bits, strategy):
    block = strategy.block

    def add(count, tile, depth, _):
        return count.at[tile].add((depth < jnp.inf).astype(jnp.int32), mode="drop")

    count, _, _ = _each_fragment(
        clip, faces, add, lambda tiles: jnp.zeros((tiles, block, block), jnp.int32),
        width=width, height=height, cull_back=cull_back, subpixel_bits=subpixel_bits,
        strategy=strategy)
    return tiled.tiles_to_image(count, width, height)


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
