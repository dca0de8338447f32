"""Ray-cast baking: a tangent-space normal map of a high-poly mesh on a low-poly mesh's uv
layout, with the semantics of Blender's "selected to active" bake (Cycles).

Per texel of LOW's uv layout (texel centres; where uv triangles
overlap, the one with the highest index holds the texel, as in Blender, which draws them in
order):

1. **The ray.** The texel's point ``p`` on LOW and LOW's interpolated normal there,
   normalised, ``n``. With an extrusion ``cage`` (Blender's "Extrusion") the ray starts at
   ``p + cage n`` and runs along ``-n``; with a ``cage_mesh`` (Blender's "Cage Object", the
   same triangles as LOW) it starts at the same barycentric point ``c`` of the cage and
   runs towards ``p``, ``normalize(p - c)``, and on past it. The ray takes the *nearest*
   hit on HIGH in front of its origin, front or back face alike, and ``max_distance``
   (Blender's "Max Ray Distance", 0 = unlimited) bounds the distance from the origin
   (``calc_point_from_barycentric_extrusion``, ``calc_point_from_barycentric_cage`` and
   ``cast_ray_highpoly`` in Blender's ``source/blender/render/intern/bake.cc``).
2. **The normal.** HIGH's interpolated shading normal at the hit, ``normalize(sum_i b_i
   n_i)`` with its vertex normals (the face normal where that vanishes), in world space
   (Cycles' ``triangle_smooth_normal``, which ``integrator_init_from_bake`` in
   ``intern/cycles/kernel/integrator/init_from_bake.h`` writes to the normal pass).
3. **Samples.** Sample 0 is the hit itself. Cycles casts no further rays: samples ``k >=
   1`` move the hit *within its HIGH triangle* by ``(r - 1/2)`` times the texel's
   differentials, ``r`` uniform in ``[0, 1)^2`` (no pixel filter: Blender's filter type and
   width do not enter bakes), trying up to 10 draws to land strictly inside the triangle and
   keeping the hit itself otherwise (``bake_jitter_barycentric``). The differentials are
   half a texel's step of LOW's (or the cage's) surface point (``bake_differentials`` scales
   them by 1/2), carried along the ray onto the HIGH triangle's plane (``cast_ray_highpoly``):
   the samples spread over +-1/4 texel.
   The world-space normals of the samples are averaged, not renormalised.
4. **The frame.** The average goes into tangent space at the texel's own point on LOW
   (`jaxnm.bake.world_to_tangent`: MikkTSpace for ``frame="vertex"``, as Blender's
   ``RE_bake_normal_world_to_tangent``, or Schüler's cotangent frame).
5. **Margin.** Texels whose ray hit nothing keep no value (they are reported), and
   ``margin`` passes of Blender's "extend" filter fill the texels around the islands
   (Blender uses this margin type for every
   tangent-space normal bake, ``bake_init_api_data`` in
   ``source/blender/editors/object/object_bake_api.cc``).

The differences from Blender: texel centres are exact (Blender shifts them by 0.001 and
0.002 texel to dodge ties), rays leave along LOW's own ``normals`` (Blender uses the vertex
normals it computes, angle-weighted, for smooth faces and face normals for flat ones: they
agree for a smooth LOW whose normals are angle-weighted, `jaxnm.geometry.vertex_normals`),
the random numbers are a hash of the texel and the sample, not Cycles' sequence, and a ray
that misses HIGH is cast once more from a thousandth of the way towards its LOW triangle's
centroid (a texel centre on a chart's rim lies on LOW's edge, and where HIGH ends at that
edge, as open surfaces do, the first ray grazes HIGH's boundary).

The rays are cast with Embree (the ``bake`` extra's ``embreex``, robust mode: a ray through
an edge or a vertex shared by triangles hits one of them), in
chunks of texels on worker threads, so the rays' memory is bounded whatever the map's size
(the map's own arrays grow with its texels); the result depends neither on the
chunks nor on the threads. Embree builds HIGH's scene on a thread of its own while LOW's
inputs and texels are prepared.
"""

from __future__ import annotations

import concurrent.futures
import dataclasses
import os
import time
import warnings

import numpy as np

from ..bake import world_to_tangent
from ..geometry import Mesh
from ._embree import ENGINES, EmbreeScene
from ._meshes import BakeWarning as BakeWarning
from ._meshes import check_mesh, prepare_low, warn_overlap, with_normals
from ._texels import extend_margin_texels, rasterize_uv, uv_box

__all__ = ["RAYCAST_FRAMES", "BakeWarning", "RaycastBake", "raycast_normal_map"]

#: The frames `raycast_normal_map` bakes for (``"vertex"``: MikkTSpace, as Blender).
RAYCAST_FRAMES = ("vertex", "cotangent")
#: Jitter draws per sample before a sample keeps the hit itself (Cycles' limit).
_JITTER_TRIES = 10
#: Texels per chunk of rays at one sample per texel (fewer at more samples).
_CHUNK = 1 << 18


@dataclasses.dataclass(frozen=True)
class RaycastBake:
    """The result of `raycast_normal_map`. Maps are in image layout (row 0 on top, uv origin
    at the bottom left), like `jaxnm.bake.bake_normal_map`'s.

    **Fields:**
    - `normals`: ``(h, w, 3)`` float32 unit tangent-space vectors, signed (decode with
      ``NormalMapOptions(encoding="signed")`` in `frame`); ``(0, 0, 1)`` where neither a
      ray nor the margin gave a value. This is what ``jaxnm fit`` writes to
      ``normal_map.npz`` under ``normals``.
    - `inside`: ``(h, w)`` bool, texels whose centre lies in one of LOW's uv triangles.
    - `missed`: ``(h, w)`` bool, texels inside whose ray hit nothing (before the margin).
    - `filled`: ``(h, w)`` bool, texels holding a value: the hits and the margin.
    - `face`: ``(h, w)`` int32, LOW's triangle holding each texel (-1 outside).
    - `texels_inside`, `texels_missed`: the counts of `inside` and `missed`.
    - `missed_uv_box`: ``(u0, v0, u1, v1)`` bounding the missed texels, or None.
    - `missed_faces`: LOW's triangles with missed texels, ascending.
    - `overlapping`: the count of texels strictly inside two or more uv triangles.
    - `cage`: the extrusion the rays started from (None with a cage mesh).
    - `cage_source`: ``"given"``, ``"automatic"`` (chosen by `raycast_normal_map`) or
      ``"mesh"``.
    - `max_distance`: the ray length bound (0: unlimited); `samples`: per texel;
      `frame`: the tangent frame; `margin`: the margin's passes.
    - `seconds`: the whole bake's wall time; `timings`: seconds per stage (``scene``: the
      wait for Embree's scene of HIGH, built on a thread during ``inputs`` and ``texels``).
    """

    normals: np.ndarray
    inside: np.ndarray
    missed: np.ndarray
    filled: np.ndarray
    face: np.ndarray
    texels_inside: int
    texels_missed: int
    missed_uv_box: tuple[float, float, float, float] | None
    missed_faces: np.ndarray
    overlapping: int
    cage: float | None
    cage_source: str
    max_distance: float
    samples: int
    frame: str
    margin: int
    seconds: float
    timings: dict[str, float]


# ----------------------------------------------------------------------------- inputs


def _check_options(size, frame, cage, cage_mesh, max_distance, samples, margin,
                   chunk_texels, workers, engine):
    hw = (size, size) if np.ndim(size) == 0 else tuple(size)
    if len(hw) != 2 or not all(not isinstance(x, bool) and int(x) == x and x > 0 for x in hw):
        raise ValueError(f"raycast_normal_map: size must be a positive int or (height, width), "
                         f"got {size!r}")
    if frame not in RAYCAST_FRAMES:
        raise ValueError(f"raycast_normal_map: frame must be one of {', '.join(RAYCAST_FRAMES)}"
                         f", got {frame!r}")
    if cage is not None and cage_mesh is not None:
        raise ValueError("raycast_normal_map: give an extrusion `cage` or a `cage_mesh`, not both")
    for what, x in (("cage", cage), ("max_distance", max_distance)):
        if x is not None and not (np.isfinite(x) and x >= 0):
            raise ValueError(f"raycast_normal_map: {what} must be finite and >= 0, got {x!r}")
    if int(samples) != samples or samples < 1:
        raise ValueError(f"raycast_normal_map: samples must be an int >= 1, got {samples!r}")
    if int(margin) != margin or margin < 0:
        raise ValueError(f"raycast_normal_map: margin must be an int >= 0, got {margin!r}")
    for what, x in (("chunk_texels", chunk_texels), ("workers", workers)):
        if x is not None and (isinstance(x, bool) or int(x) != x or x < 1):
            raise ValueError(f"raycast_normal_map: {what} must be an int >= 1 or None, got "
                             f"{x!r}")
    if engine not in (None,) + ENGINES:
        raise ValueError(f"raycast_normal_map: engine must be one of {', '.join(ENGINES)} or "
                         f"None, got {engine!r}")
    return int(hw[0]), int(hw[1])


def _cage_positions(cage_mesh: Mesh | None, low: Mesh, name: str,
                    low_name: str) -> np.ndarray | None:
    """The cage's point for each of LOW's vertices, or None without a cage. Corner ``k`` of
    the cage's face ``i`` is where corner ``k`` of LOW's face ``i`` moves: the cage must have
    LOW's triangles in LOW's order, but may split its vertices at other seams (a cage saved
    without uvs, or LOW unwrapped again), as long as it puts each of LOW's vertices at one
    place."""
    if cage_mesh is None:
        return None
    p, f = check_mesh(cage_mesh, name)
    lf = np.asarray(low.faces, np.int64).reshape(-1)
    if f.shape[0] * 3 != lf.size:
        raise ValueError(f"{name}: a cage mesh must have {low_name}'s triangles in "
                         f"{low_name}'s order; it has {f.shape[0]} faces, {low_name} "
                         f"{lf.size // 3}")
    corners = p[f.reshape(-1)]
    out = np.asarray(low.positions, np.float64).copy()  # (vertices no face uses)
    out[lf] = corners
    moved = np.abs(out[lf] - corners).max(axis=-1)
    scale = max(float(np.ptp(p, axis=0).max()), np.finfo(np.float64).tiny)
    torn = np.flatnonzero(moved > 1e-6 * scale)
    if torn.size:
        raise ValueError(f"{name}: a cage mesh must have {low_name}'s triangles in "
                         f"{low_name}'s order; its faces put {len(np.unique(lf[torn]))} of "
                         f"{low_name}'s vertices at two places (the first in face "
                         f"{torn[0] // 3})")
    return out


# ----------------------------------------------------------------------------- per texel


@dataclasses.dataclass(frozen=True)
class _Low:
    """What the rays need of LOW: positions, ray normals, the cage's positions (or None),
    and per face the jitter steps ``dxco``, ``dyco`` (half a texel's step of the surface
    point along +u and +v, on the cage mesh when there is one, as in Blender); all
    component-major, ``(3, V)`` and ``(3, F)``."""

    faces: np.ndarray
    positions: np.ndarray
    normals: np.ndarray
    cage_positions: np.ndarray | None
    dxco: np.ndarray
    dyco: np.ndarray

    @staticmethod
    def build(low: Mesh, cage_positions: np.ndarray | None, hw: tuple[int, int]) -> _Low:
        faces = np.asarray(low.faces, np.int64)
        pos = np.asarray(low.positions, np.float64)
        q = (pos if cage_positions is None else cage_positions)[faces]
        t = np.asarray(low.uv, np.float64)[faces]
        e1, e2 = q[:, 1] - q[:, 0], q[:, 2] - q[:, 0]
        d1, d2 = t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]
        det = d1[:, 0] * d2[:, 1] - d2[:, 0] * d1[:, 1]
        # Blender leaves the differentials at zero below FLT_EPSILON of doubled pixel area
        ok = (np.abs(det) * hw[0] * hw[1] > np.finfo(np.float32).eps)[:, None]
        safe = np.where(ok[:, 0], det, 1.0)[:, None]
        dpdu = np.where(ok, (e1 * d2[:, 1:] - e2 * d1[:, 1:]) / safe, 0.0)
        dpdv = np.where(ok, (e2 * d1[:, :1] - e1 * d2[:, :1]) / safe, 0.0)
        return _Low(faces, *(None if x is None else np.ascontiguousarray(np.transpose(x))
                             for x in (pos, np.asarray(low.normals, np.float64),
                                       cage_positions, 0.5 * dpdu / hw[1],
                                       0.5 * dpdv / hw[0])))


def _rays(low: _Low, tri: np.ndarray, bary: np.ndarray, cage: float | None):
    """Ray origins and unit directions ``(3, N)`` of texels ``(tri, bary)`` (Blender's, see
    the module docstring), and whether each is defined (a zero normal or cage offset gives
    none)."""
    fc = low.faces[tri]

    def at(a):  # the interpolated attribute, components along the first axis
        return bary[:, 0] * a[:, fc[:, 0]] + bary[:, 1] * a[:, fc[:, 1]] + bary[:, 2] * a[
            :, fc[:, 2]]

    p = at(low.positions)
    if low.cage_positions is None:
        d = at(low.normals)
    else:
        origin = at(low.cage_positions)
        d = p - origin
    length = _norm(d)
    ok = length > 0
    d = np.where(ok, d / np.where(ok, length, 1.0), np.array([[0.0], [0.0], [1.0]]))
    if low.cage_positions is None:
        return p + cage * d, -d, ok
    return origin, d, ok


def _dot(a, b) -> np.ndarray:
    """Dot products of vectors given by their components ``a[0], a[1], a[2]``."""
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def _norm(a) -> np.ndarray:
    return np.sqrt(_dot(a, a))


def _cross(a, b) -> np.ndarray:
    return np.stack([a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2],
                     a[0] * b[1] - a[1] * b[0]])


def _hash(x: np.ndarray) -> np.ndarray:
    """A 32-bit integer hash (lowbias32) of each element of ``x`` (uint32)."""
    x = x ^ (x >> np.uint32(16))  # a new array; the rest in place
    x *= np.uint32(0x7FEB352D)
    x ^= x >> np.uint32(15)
    x *= np.uint32(0x846CA68B)
    x ^= x >> np.uint32(16)
    return x


def _salt(*values: int) -> np.uint32:
    """A 32-bit hash of a few small integers (a sample's or a draw's salt)."""
    x = np.zeros(1, np.uint32)
    for v in values:
        x = _hash(x ^ np.uint32(v & 0xFFFFFFFF))
    return x[0]


def _uniform(x: np.ndarray) -> np.ndarray:
    """Uniform numbers in [0, 1) from 32-bit hashes (their top 24 bits)."""
    return (x >> np.uint32(8)).astype(np.float64) * 2.0 ** -24


class _HighHits:
    """HIGH's triangles at a chunk's hits, and the normal at barycentrics there (vectors
    component-major, ``(3, N)``, from HIGH's ``(3, V)`` positions and normals)."""

    def __init__(self, positions, faces, normals, prim):
        f = faces[prim]
        self.p = [positions[:, f[:, k]] for k in range(3)]  # per corner, (3, n)
        self.n = [normals[:, f[:, k]] for k in range(3)]
        ng = _cross(self.p[1] - self.p[0], self.p[2] - self.p[0])
        self.ng = ng / np.maximum(_norm(ng), 1e-300)

    def normal(self, a: np.ndarray, b: np.ndarray) -> np.ndarray:
        """Cycles' smooth normal at Blender's barycentrics ``(a, b)`` (weights of corners 0
        and 1): the interpolated vertex normals, normalised, or the face normal."""
        n = a * self.n[0] + b * self.n[1] + (1.0 - a - b) * self.n[2]
        length = _norm(n)
        return np.where(length > 0, n / np.where(length > 0, length, 1.0), self.ng)

    def differentials(self, direction, dxco, dyco):
        """Blender's barycentric differentials on the hit triangles: the texel steps carried
        along the ray onto the triangle's plane, in the corner-2-based edge basis."""
        cos = _dot(direction, self.ng)
        cos = np.where(cos == 0, np.inf, cos)
        e0 = self.p[0] - self.p[2]
        e1 = self.p[1] - self.p[2]
        g00, g01, g11 = _dot(e0, e0), _dot(e0, e1), _dot(e1, e1)
        det = g00 * g11 - g01 * g01
        det = np.where(det == 0, np.inf, det)
        out = []
        for step in (dxco, dyco):
            d = step - direction * (_dot(step, self.ng) / cos)
            r0, r1 = _dot(e0, d), _dot(e1, d)
            out.append(((g11 * r0 - g01 * r1) / det, (g00 * r1 - g01 * r0) / det))
        (dudx, dvdx), (dudy, dvdy) = out
        return dudx, dudy, dvdx, dvdy


def _average_normal(hits: _HighHits, a, b, diffs, keys, samples: int) -> np.ndarray:
    """The mean world-space normal of Cycles' ``samples`` samples about the hit ``(a, b)``:
    sample 0 at the hit, the others jittered within the hit triangle (module docstring)."""
    acc = hits.normal(a, b)
    dudx, dudy, dvdx, dvdy = diffs
    for s in range(1, samples):
        draw = _hash(keys ^ _salt(s))  # per texel and sample; each retry hashes it again
        # the first draw for every texel, without gathers
        ja, jb, ok = _jitter(draw, 0, a, b, dudx, dudy, dvdx, dvdy)
        ja, jb, todo = np.where(ok, ja, a), np.where(ok, jb, b), np.flatnonzero(~ok)
        for attempt in range(1, _JITTER_TRIES):
            if todo.size == 0:
                break
            ca, cb, ok = _jitter(draw[todo], attempt, a[todo], b[todo], dudx[todo],
                                 dudy[todo], dvdx[todo], dvdy[todo])
            ja[todo[ok]], jb[todo[ok]] = ca[ok], cb[ok]
            todo = todo[~ok]
        acc = acc + hits.normal(ja, jb)
    return acc / samples


def _jitter(draw, attempt, a, b, dudx, dudy, dvdx, dvdy):
    """One draw of Cycles' jitter of the hits ``(a, b)``: the moved barycentrics and
    whether they lie strictly inside the triangle."""
    hx = _hash(draw ^ _salt(attempt, 0))
    rx = _uniform(hx) - 0.5
    ry = _uniform(_hash(hx ^ _salt(attempt, 1))) - 0.5
    ca = a + rx * dudx + ry * dudy
    cb = b + rx * dvdx + ry * dvdy
    return ca, cb, (ca > 0) & (cb > 0) & (ca + cb < 1)


# ----------------------------------------------------------------------------- the bake


def _workers(workers: int | None, chunks: int) -> int:
    if workers is None:
        workers = min(4, os.cpu_count() or 1)
    return max(1, min(int(workers), chunks))


def _automatic_cage(engine: EmbreeScene, low: _Low, tri, bary, chunks) -> float:
    """The smallest extrusion that starts every texel's ray outside HIGH where HIGH lies
    outside LOW: per texel, rays from LOW's point along +n and -n find the nearest HIGH
    surface each way; where the outward one is nearer, HIGH is outside there, and the cage
    must clear it. 5% more than the largest such distance, plus 1e-4 of LOW's size (so
    that rays never start on HIGH where the two coincide)."""
    need = 0.0
    for sl in chunks:
        origin, d, ok = _rays(low, tri[sl], bary[sl], 0.0)  # origin = p, d = -n
        prim_out, _, _, t_out = engine.cast(origin.T, -d.T, 0.0)
        prim_in, _, _, t_in = engine.cast(origin.T, d.T, 0.0)
        outside = ok & (prim_out >= 0) & ((prim_in < 0) | (t_out < t_in))
        if outside.any():
            need = max(need, float(t_out[outside].max()))
    size = float(np.linalg.norm(np.ptp(low.positions, axis=1)))
    return 1.05 * need + 1e-4 * size


#: How far a missed texel's ray is moved towards its LOW triangle's centroid for its second
#: cast, as a fraction of the way.
_RETRY_INWARD = 1e-3


def _cast(engine, low: _Low, tri, bary, cage, max_distance):
    """The rays of texels ``(tri, bary)`` (`_rays`) cast on HIGH: the directions, whether
    each is defined, and Embree's hit triangle (-1: none) and weights. A texel centre on the
    edge of LOW's uv chart lies on the edge of its triangle, and where HIGH ends at the same
    edge (open surfaces: a grid, a terrain patch) its ray grazes HIGH's boundary and may miss
    it; a ray that misses is cast once more from a point `_RETRY_INWARD` of the way towards
    its triangle's centroid."""
    origin, direction, ok = _rays(low, tri, bary, cage)
    prim, u, v, _ = engine.cast(origin.T, direction.T, max_distance)
    again = np.flatnonzero(ok & (prim < 0))
    if again.size:
        inward = (1.0 - _RETRY_INWARD) * bary[again] + _RETRY_INWARD / 3.0
        o2, d2, _ = _rays(low, tri[again], inward, cage)
        p2, u2, v2, _ = engine.cast(o2.T, d2.T, max_distance)
        direction[:, again] = d2
        prim[again], u[again], v[again] = p2, u2, v2
    return direction, ok, prim, u, v


def _bake_chunk(engine, high, low, tri, bary, keys, *, cage, max_distance, samples):
    """World-space normals ``(3, N)`` and hit flags of one chunk of texels."""
    direction, ok, prim, u, v = _cast(engine, low, tri, bary, cage, max_distance)
    hit = ok & (prim >= 0)
    world = np.zeros((3, len(tri)))
    if hit.any():
        hits = _HighHits(*high, prim[hit])
        a, b = 1.0 - u[hit] - v[hit], u[hit]  # Blender's weights of corners 0 and 1
        diffs = ((None,) * 4 if samples == 1 else
                 hits.differentials(direction[:, hit], low.dxco[:, tri[hit]],
                                    low.dyco[:, tri[hit]]))
        world[:, hit] = _average_normal(hits, a, b, diffs, keys[hit], samples)
    return world, hit


def _report_misses(missed: np.ndarray, face: np.ndarray, n_inside: int, cage, source: str,
                   high_name: str, low_name: str):
    box = uv_box(missed)
    faces = np.unique(face[missed])
    if missed.any():
        where = ", ".join(str(i) for i in faces[:8]) + (", ..." if faces.size > 8 else "")
        cage_txt = "the cage mesh" if cage is None else f"{source} cage {cage:.6g}"
        warnings.warn(f"{low_name}: the rays of {int(missed.sum())} of {n_inside} texels hit "
                      f"nothing on {high_name} ({cage_txt}): uv [{box[0]:.4f}, {box[1]:.4f}] "
                      f"to [{box[2]:.4f}, {box[3]:.4f}], faces {where}; the margin fills them "
                      "where it reaches", BakeWarning, stacklevel=4)
    return box, faces


def raycast_normal_map(high: Mesh, low: Mesh, size: int | tuple[int, int], *,
                       frame: str = "vertex", cage: float | None = None,
                       cage_mesh: Mesh | None = None, max_distance: float = 0.0,
                       samples: int = 1, margin: int = 16, seed: int = 0,
                       chunk_texels: int | None = None, workers: int | None = None,
                       engine: str | None = None, high_name: str = "HIGH",
                       low_name: str = "LOW", cage_name: str = "cage mesh") -> RaycastBake:
    """Bake HIGH's normals into a tangent-space map on LOW's uv layout by casting rays, as
    Blender's Cycles "selected to active" bake does (the module docstring has the rules and
    the Blender sources they follow).

    **Arguments:**
    - `high`: the detailed mesh; its vertex normals are interpolated at the hits
      (angle-weighted normals are computed where it has none, as Blender does).
    - `low`: the mesh whose uv layout the map covers; needs uvs; its normals aim the rays
      and, with its MikkTSpace tangents (computed where it has none), give the frame.
    - `size`: the map's side, or ``(height, width)``.
    - `frame`: one of `RAYCAST_FRAMES`: ``"vertex"`` (MikkTSpace: Blender, glTF viewers,
      jaxnm's ``frame: "vertex"``) or ``"cotangent"``.
    - `cage`: the extrusion (Blender's ``cage_extrusion``), in LOW's units; None (with no
      `cage_mesh`) chooses one so that rays start outside HIGH (`RaycastBake.cage`).
    - `cage_mesh`: a mesh with LOW's triangles, in LOW's order, whose points the rays start
      from (Blender's cage object); its vertices may be split at other seams than LOW's.
    - `max_distance`: rays longer than this from their origin miss (0: no limit).
    - `samples`: Cycles' bake samples per texel (jittered within the hit triangle).
    - `margin`: passes of the extend filter around the islands (Blender's default 16).
    - `seed`: varies the jitter; `chunk_texels`: texels per chunk of rays (memory bound;
      the result does not depend on it); `workers`: threads baking chunks at once
      (default: the machine's cores, at most 4; the result does not depend on it);
      `engine`: how to reach Embree, ``"direct"`` (its library through ctypes, rays in
      packets on every worker) or ``"embreex"`` (embreex's scene, one ray at a time), the
      same hits; None: ``"direct"`` where it can be had;
      `high_name`, `low_name`, `cage_name`: for messages (the files).

    **Returns:** a `RaycastBake`. Raises ValueError when no ray hits HIGH (the meshes do not
    overlap) and for unusable input; warns (`BakeWarning`) about missed texels, overlapping
    uv islands, uvs outside the unit square, degenerate or non-manifold triangles, a LOW
    turned inside out, and HIGH facing away from LOW."""
    t0 = time.perf_counter()
    timings = {}
    lap = [t0]

    def tick(stage):
        now = time.perf_counter()
        timings[stage] = timings.get(stage, 0.0) + now - lap[0]
        lap[0] = now

    hw = _check_options(size, frame, cage, cage_mesh, max_distance, samples, margin,
                        chunk_texels, workers, engine)
    hp, hf = check_mesh(high, high_name)
    with concurrent.futures.ThreadPoolExecutor(1) as pool:  # Embree builds meanwhile
        scene = pool.submit(EmbreeScene, hp, hf, engine=engine)
        low = prepare_low(low, frame, low_name)
        hn = np.asarray(with_normals(high, high_name).normals, np.float64)
        geo = _Low.build(low, _cage_positions(cage_mesh, low, cage_name, low_name), hw)
        tick("inputs")
        cover, texels, tri, bary = _texels(low, hw, low_name)
        tick("texels")
        engine = scene.result()
    tick("scene")
    step = max(1, int(chunk_texels or _CHUNK // samples))
    chunks = [slice(i, i + step) for i in range(0, texels.size, step)]
    source = "given" if cage is not None else "mesh" if cage_mesh is not None else "automatic"
    if source == "automatic":
        cage = _automatic_cage(engine, geo, tri, bary, chunks)
    tick("cage")
    m, hit = _bake_texels(engine, (hp, hf, hn), low, geo, tri, bary,
                          texels.astype(np.uint32) ^ _salt(seed, 0x5EED), chunks,
                          _workers(workers, len(chunks)),
                          dict(cage=cage, max_distance=max_distance, samples=samples), frame)
    tick("rays and frames")
    _check_hits(hit, m, "the cage mesh" if cage_mesh is not None else f"cage {cage:.6g}",
                max_distance, high_name, low_name)
    return _finish(cover, texels, hit, m, hw, margin, dict(
        cage=None if cage_mesh is not None else float(cage), cage_source=source,
        max_distance=float(max_distance), samples=int(samples), frame=frame,
        margin=int(margin)), (high_name, low_name), tick, timings, t0)


def _check_hits(hit: np.ndarray, m: np.ndarray, start: str, max_distance: float,
                high_name: str, low_name: str) -> None:
    """A ValueError where no ray (from ``start``) hit HIGH; a `BakeWarning` where most hits
    found HIGH facing away from LOW: the tangent-space ``z`` of HIGH's normal negative (more
    than 90 degrees from LOW's), as where one mesh's faces wind the other way."""
    if not hit.any():
        raise ValueError(f"{high_name} and {low_name} do not overlap: none of the "
                         f"{hit.size} rays from {low_name}'s texels hit {high_name} "
                         f"({start}, max distance {max_distance:g}); are both in the same "
                         "space and units?")
    z = m[hit, 2]
    k = int(np.sum(z < 0))
    if 2 * k > z.size:
        warnings.warn(f"{high_name} faces away from {low_name}: at {k} of {z.size} texels "
                      f"whose ray hit it, its normal is more than 90 degrees from "
                      f"{low_name}'s; do the two meshes' faces wind the same way?", BakeWarning,
                      stacklevel=3)


def _texels(low: Mesh, hw: tuple[int, int], name: str):
    """LOW's uv layout over the map: the cover, and the covered texels' (flat image index,
    face, barycentrics)."""
    cover = rasterize_uv(low.uv, low.faces, hw)
    warn_overlap(cover, name)
    texels = np.flatnonzero(cover.face.ravel() >= 0)
    if texels.size == 0:
        raise ValueError(f"{name}: no texel centre of the {hw[0]}x{hw[1]} map lies in a uv "
                         "triangle (uvs outside [0, 1] or zero-area uv triangles)")
    return (cover, texels, cover.face.ravel()[texels].astype(np.int64),
            cover.bary.reshape(-1, 3)[texels])


def _bake_texels(engine, high, low, geo, tri, bary, keys, chunks, workers, rays, frame):
    """Tangent-space vectors and hit flags of all covered texels, chunk by chunk on
    ``workers`` threads (NumPy and XLA release the GIL, embreex's casts do not; each chunk
    writes only its own rows, so the result does not depend on the threads)."""
    m = np.zeros((len(tri), 3))
    hit = np.zeros(len(tri), bool)
    high = (np.ascontiguousarray(high[0].T), high[1], np.ascontiguousarray(high[2].T))  # (3, V)

    def bake(sl):
        world, hit[sl] = _bake_chunk(engine, high, geo, tri[sl], bary[sl], keys[sl], **rays)
        h = hit[sl]
        if h.any():
            m[sl][h] = world_to_tangent(low, tri[sl][h], bary[sl][h], world[:, h].T,
                                        frame=frame)

    with concurrent.futures.ThreadPoolExecutor(workers) as pool:
        list(pool.map(bake, chunks))
    return m, hit


def _finish(cover, texels, hit, m, hw, margin, settings, names, tick, timings, t0):
    """The margin, the miss report and the `RaycastBake`."""
    h, w = hw
    idx, v = extend_margin_texels(texels[hit], m[hit], hw, margin)
    length = _norm(v.T)
    idx, v, length = idx[length > 0], v[length > 0], length[length > 0]
    filled = np.zeros((h, w), bool)
    filled.flat[idx] = True
    normals = np.zeros((h * w, 3), np.float32)
    normals[:, 2] = 1.0
    normals[idx] = (v / length[:, None]).astype(np.float32)
    normals = normals.reshape(h, w, 3)
    inside = cover.face >= 0
    missed = np.zeros(h * w, bool)
    missed[texels[~hit]] = True
    missed = missed.reshape(h, w)
    box, faces = _report_misses(missed, cover.face, int(inside.sum()), settings["cage"],
                                settings["cage_source"], *names)
    tick("margin")
    return RaycastBake(normals=normals, inside=inside, missed=missed, filled=filled,
                       face=cover.face, texels_inside=int(inside.sum()),
                       texels_missed=int(missed.sum()), missed_uv_box=box,
                       missed_faces=faces.astype(np.int64),
                       overlapping=int(cover.overlapping.sum()), **settings,
                       seconds=time.perf_counter() - t0, timings=dict(timings))
