"""Views and lights for fitting a low-poly mesh's map to a high-poly mesh's shading.

A fitted map is only determined where the targets see it: every texel of LOW's uv chart
should be seen by some views, not at a grazing angle, and lit from three or more
non-coplanar directions (photometric stereo; `jaxnm.fit.check_identifiability`). `plan_views`
chooses the views by measuring, with jaxnm's own rasterizer, which texels each candidate
view sees:

1. **Candidates.** ``candidates`` directions spread evenly over the sphere (a Fibonacci
   spiral) around the centre of the pair's bounding sphere; each is a perspective camera
   that frames the whole sphere (`framing_camera`).
2. **What a view sees.** LOW is rendered from each candidate at the fit's render size
   (`jaxnm.render`: uv, normal, position, front facing). A pixel sees the texel its uv falls
   in (the nearest texel, as the map is stored: row 0 on top) when its surface is front
   facing and LOW's interpolated normal there is within ``max_angle_deg`` of the direction
   to the camera. Texels outside LOW's uv triangles (no texel centre inside one) do not
   count.
3. **Greedy cover.** ``views`` times, the candidate that adds most to the texels still seen
   by fewer than ``min_views`` chosen views (a texel counts once per view) is chosen; once
   no candidate adds to those, the next gives a third view to the most texels that have
   only ``min_views`` (their weight is 1/100 of a texel still short of views).
4. **Lights.** Each view gets ``lights`` directional lights on two cones about its
   direction (30 and 60 degrees off it, alternately), their azimuths evenly spread and
   turned from view to view by the golden angle, so that three or more never lie in one
   plane and the views' lights together cover the hemispheres they face.

`held_out_views` chooses views and lights for scoring: directions as far as possible from the
plan's and from each other, with lights on a 45-degree cone at azimuths between the plan's.
"""

from __future__ import annotations

import dataclasses
import math
import time

import numpy as np

from ..camera import Camera, eye_to_world
from ..geometry import Mesh, bounding_sphere
from ._surfaces import facing, surface
from ._texels import rasterize_uv

__all__ = ["ViewPlan", "plan_views", "held_out_views", "front_area", "framing_camera",
           "fibonacci_sphere", "view_lights", "texels_seen",
           "FIELD_OF_VIEW_DEG"]

#: The vertical (and horizontal) field of view of every planned camera.
FIELD_OF_VIEW_DEG = 30.0
#: The golden angle, in radians: how far each view's lights turn from the previous view's.
_GOLDEN = math.pi * (3.0 - math.sqrt(5.0))


@dataclasses.dataclass(frozen=True)
class ViewPlan:
    """The views and lights `plan_views` chose, and how well they cover LOW's uv chart.

    **Fields:**
    - `cameras`: the chosen views' cameras (square images of `render_size`).
    - `directions`: ``(K, 3)`` unit directions from `centre` towards each camera.
    - `lights`: ``(K, L, 3)`` unit directions towards each view's lights (world space).
    - `render_size`: the side of every view's image; `map_size`: ``(h, w)``.
    - `chart`: ``(h, w)`` bool, the texels whose centre lies in one of LOW's uv triangles.
    - `counts`: ``(h, w)`` int, how many chosen views see each texel (step 2 of the module).
    - `unseen`: chart texels seen by fewer than `min_views` chosen views.
    - `centre`, `radius`: the bounding sphere the cameras frame.
    - `candidates`, `max_angle_deg`, `min_views`: the plan's settings.
    - `candidate_order`: the chosen candidates' indices, in the order chosen.
    - `seconds`: the time the plan took.
    """

    cameras: tuple[Camera, ...]
    directions: np.ndarray
    lights: np.ndarray
    render_size: int
    map_size: tuple[int, int]
    chart: np.ndarray
    counts: np.ndarray
    unseen: int
    centre: np.ndarray
    radius: float
    candidates: int
    max_angle_deg: float
    min_views: int
    candidate_order: tuple[int, ...]
    seconds: float


def fibonacci_sphere(n: int, *, turn: float = 0.0) -> np.ndarray:
    """``n`` unit vectors spread evenly over the sphere (a Fibonacci spiral), ``(n, 3)``;
    ``turn`` (radians) rotates the spiral about +z."""
    k = np.arange(n) + 0.5
    z = 1.0 - 2.0 * k / n
    r = np.sqrt(np.maximum(0.0, 1.0 - z * z))
    a = _GOLDEN * np.arange(n) + turn
    return np.stack([r * np.cos(a), r * np.sin(a), z], -1)


def front_area(mesh: Mesh, directions: np.ndarray) -> np.ndarray:
    """The area of ``mesh``'s front faces (counter-clockwise winding) projected along each
    unit direction ``(N, 3)`` towards the viewer, occlusion ignored, ``(N,)``."""
    p = np.asarray(mesh.positions, np.float64)[np.asarray(mesh.faces)]
    half_normals = 0.5 * np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    return np.maximum(half_normals @ np.asarray(directions, np.float64).T, 0.0).sum(0)


def _facing_views(low: Mesh, dirs: np.ndarray, used: np.ndarray) -> np.ndarray:
    """``dirs`` with those that show little of ``low`` replaced (`held_out_views`)."""
    dense = fibonacci_sphere(256, turn=0.25 * _GOLDEN)
    area = front_area(low, dense)
    good = dense[area >= 0.5 * area.max()]
    dirs = dirs.copy()
    for i in np.flatnonzero(front_area(low, dirs) < 0.1 * area.max()):
        others = np.concatenate([np.delete(dirs, i, axis=0), used])
        if len(others):
            good_far = np.min(np.arccos(np.clip(good @ others.T, -1.0, 1.0)), axis=1)
            dirs[i] = good[int(np.argmax(good_far))]
        else:
            dirs[i] = good[0]
    return dirs


def framing_camera(centre, radius: float, direction) -> Camera:
    """A square perspective camera (`FIELD_OF_VIEW_DEG`) on the ray from ``centre`` along
    ``direction``, looking at ``centre``, far enough that the sphere of ``radius`` fills its
    view (`jaxnm.camera.Camera.framing`)."""
    return Camera.framing(centre, radius, direction, fov_y_deg=FIELD_OF_VIEW_DEG)


def view_lights(camera: Camera, count: int, index: int) -> np.ndarray:
    """``(count, 3)`` unit world directions towards the lights of view number ``index``
    (step 4 of the module): on cones of 30 and 60 degrees about the direction to the
    camera, alternately, the azimuths evenly spread and turned by ``index`` golden angles."""
    out = []
    for i in range(count):
        polar = math.radians(30.0 if i % 2 == 0 else 60.0)
        az = 2 * math.pi * i / count + _GOLDEN * index
        out.append(eye_to_world(camera, (math.sin(polar) * math.cos(az),
                                         math.sin(polar) * math.sin(az), math.cos(polar))))
    return np.asarray(out)


def texels_seen(low: Mesh, camera: Camera, render_size: int, map_size: tuple[int, int], *,
                max_angle_deg: float = 60.0) -> np.ndarray:
    """The flat indices (row-major, row 0 on top) of the texels of a ``map_size`` map that
    LOW's render from ``camera`` sees (step 2 of the module), ascending and unique: the
    texel each front-facing pixel's uv falls in, where LOW's interpolated normal is within
    ``max_angle_deg`` of the direction to the camera."""
    s = surface(low, camera, render_size, uv=True, source="LOW")
    uv = s.uv[facing(s, max_angle_deg)].astype(np.float64)
    h, w = map_size
    u, v = np.mod(uv[:, 0], 1.0), np.mod(uv[:, 1], 1.0)
    col = np.minimum((u * w).astype(np.int64), w - 1)
    row = np.minimum(((1.0 - v) * h).astype(np.int64), h - 1)
    return np.unique(row * w + col)


def _greedy(seen: list[np.ndarray], chart: np.ndarray, views: int, min_views: int):
    """The greedy cover of step 3 of the module: the chosen candidates in order and the
    counts per texel (flat)."""
    counts = np.zeros(chart.size, np.int64)
    inside = chart.ravel()
    seen = [s[inside[s]] for s in seen]
    order: list[int] = []
    for _ in range(min(views, len(seen))):
        best, best_gain = -1, -1.0
        for i, s in enumerate(seen):
            if i in order:
                continue
            c = counts[s]
            gain = float(np.count_nonzero(c < min_views)) + 0.01 * np.count_nonzero(
                c == min_views)
            if gain > best_gain:
                best, best_gain = i, gain
        order.append(best)
        counts[seen[best]] += 1
    return order, counts


def plan_views(low: Mesh, map_size: tuple[int, int], *, views: int = 8, lights: int = 4,
               render_size: int = 512, candidates: int = 48, max_angle_deg: float = 60.0,
               min_views: int = 2, high: Mesh | None = None) -> ViewPlan:
    """Choose ``views`` views of LOW, and ``lights`` lights for each, so that every texel of
    LOW's uv chart is seen by ``min_views`` views at ``max_angle_deg`` or less from its
    normal (the module docstring says how).

    **Arguments:**
    - `low`: the mesh whose map is fitted, with uvs and normals.
    - `map_size`: ``(h, w)`` of the map.
    - `views`, `lights`: how many of each (``lights >= 3`` for a determined fit).
    - `render_size`: the side of each view's image (the fit renders at this size).
    - `candidates`: directions tried.
    - `high`: the high-poly mesh, when the cameras must frame it too.

    **Returns:** a `ViewPlan`; its `unseen` counts the chart texels seen fewer than
    ``min_views`` times.
    """
    for name, v, lo in (("views", views, 1), ("lights", lights, 1),
                        ("render_size", render_size, 8), ("candidates", candidates, 1),
                        ("min_views", min_views, 1)):
        if isinstance(v, bool) or int(v) != v or v < lo:
            raise ValueError(f"plan_views: {name} must be an integer >= {lo}, got {v!r}")
    if not 0 < max_angle_deg < 90:
        raise ValueError(f"plan_views: max_angle_deg must be in (0, 90), got {max_angle_deg}")
    size = tuple(map_size) if np.iterable(map_size) else ()
    if len(size) != 2 or not all(not isinstance(s, bool) and isinstance(s, (int, np.integer))
                                 and s >= 1 for s in size):
        raise ValueError(f"plan_views: map_size must be two integers >= 1, (h, w), got "
                         f"{map_size!r}")
    t0 = time.perf_counter()
    h, w = (int(s) for s in size)
    centre, radius = bounding_sphere(low, *(() if high is None else (high,)))
    chart = rasterize_uv(np.asarray(low.uv), np.asarray(low.faces), (h, w)).face >= 0
    dirs = fibonacci_sphere(int(candidates))
    cams = [framing_camera(centre, radius, d) for d in dirs]
    seen = []
    for cam in cams:
        seen.append(texels_seen(low, cam, int(render_size), (h, w), max_angle_deg=max_angle_deg))
    order, counts = _greedy(seen, chart, int(views), int(min_views))
    chosen = tuple(cams[i] for i in order)
    return ViewPlan(cameras=chosen, directions=dirs[order],
                    lights=np.stack([view_lights(c, int(lights), k)
                                     for k, c in enumerate(chosen)]),
                    render_size=int(render_size), map_size=(h, w), chart=chart,
                    counts=counts.reshape(h, w),
                    unseen=int(np.count_nonzero(chart.ravel() & (counts < min_views))),
                    centre=centre, radius=radius, candidates=int(candidates),
                    max_angle_deg=float(max_angle_deg), min_views=int(min_views),
                    candidate_order=tuple(int(i) for i in order),
                    seconds=time.perf_counter() - t0)


def held_out_views(centre, radius: float, used: np.ndarray, views: int = 4,
                   lights: int = 2, *, low: Mesh | None = None
                   ) -> tuple[tuple[Camera, ...], np.ndarray]:
    """Views and lights for scoring maps, none of which a plan uses: ``views`` directions
    spread evenly over the sphere (a Fibonacci spiral turned by half a golden angle off the
    candidates', so that no direction is a candidate's), each framing the sphere
    (``centre``, ``radius``), with ``lights`` lights on a 45-degree cone about the direction
    at azimuths half-way between a plan's. ``used`` (``(K, 3)``, `ViewPlan.directions`) is
    only checked: a direction within 1 degree of one of them is turned away from it.

    With ``low``, a direction from which LOW's front faces show less than a tenth of the
    area they show at most (`front_area`: an open surface seen edge-on or from behind, where
    a view would score no pixel) is replaced by the direction, of a denser spiral, that
    shows at least half of that area and lies farthest from the other views and ``used``.
    A closed mesh keeps the spiral's directions unless it is far longer than it is wide.

    Returns the cameras and ``(E, lights, 3)`` light directions."""
    dirs = fibonacci_sphere(int(views), turn=0.5 * _GOLDEN + 0.1)
    used = np.asarray(used, np.float64).reshape(-1, 3)
    for i, d in enumerate(dirs):
        if len(used) and np.max(used @ d) > math.cos(math.radians(1.0)):
            e = np.cross(d, np.eye(3)[int(np.argmin(np.abs(d)))])
            dirs[i] = d * math.cos(0.1) + e / np.linalg.norm(e) * math.sin(0.1)
    if low is not None:
        dirs = _facing_views(low, dirs, used)
    cams = tuple(framing_camera(centre, radius, d) for d in dirs)
    polar = math.radians(45.0)
    out = []
    for k, cam in enumerate(cams):
        az = [2 * math.pi * (i + 0.5) / lights + _GOLDEN * (k + 0.5) for i in range(lights)]
        out.append([eye_to_world(cam, (math.sin(polar) * math.cos(a),
                                       math.sin(polar) * math.sin(a), math.cos(polar)))
                    for a in az])
    return cams, np.asarray(out)
