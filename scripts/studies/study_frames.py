"""The frame study: how far each tangent frame is from the truth, and what it depends on.

    python -m scripts.studies.study_frames --out frames_out [--size 96] [--quick]

For every frame method and derivative mode, the per-pixel angle between the perturbed
normal (a fixed, clearly tilted map value) and the float64 truth, and the angles of T and
B, over sweeps of the field of view (1 to 120 deg), the view angle (0 to 89 deg), the
camera distance, the shader precision (float32, float16 = GLSL mediump, bfloat16) against
the camera distance, the uv layout (orthogonal, 1:4, sheared 30 and 60 deg, mirrored), the
derivative mode (on a plane and on a torus, with the fixed value and with a real map), and
the tessellation of curved surfaces (sphere, cylinder, torus; smooth and flat normals).

**Two truths, one per convention.** A frame method aims at one of two frames, and is
measured against its own (the other is reported too):

- *gradient* (Schüler's convention: ``cotangent``, ``cotangent_unnormalized``,
  ``nonperspective``, ``exact``, ``exact_face``, ``axis``): ``T = grad u``, ``B = grad v``
  on the surface, both scaled so that the longer is unit (for ``cotangent_unnormalized``
  unscaled); the perturbed normal ``normalize(T m.x + B m.y + N m.z)``.
- *orthonormal* (MikkTSpace's: ``vertex``, ``vertex_area``): ``T = normalize(dp/du)`` in
  the tangent plane, ``B = sign N x T``.

On a plane with an affine uv both truths are closed forms. On a curved surface there are
two: the *smooth* surface's analytic frame at the pixel's mesh point (``error_*``: the
tessellation error included) and the mesh's own exact per-triangle frame (``face_*``:
Schüler's frame built in float64 from the pixel's triangle's edges and the pixel's
interpolated normal, or that triangle's orthonormal dp/du frame), which isolates what the
method adds on top of the faceting. Only front-facing pixels are measured
(a back face's frame is flipped by ``double_sided``, and its truth is the other side's).

The fixed-axis approximation (``axis``) ignores the uv mapping: it is right only where the
uv happens to run along its axes (the ``axis-aligned`` layout: on a +z plane ``T = -x``,
``B = -y``) and wrong by tens of degrees elsewhere, which the uv sweep shows.

Writes ``frames.json`` (one record per configuration and method), ``frames.csv``, plots
(``error_vs_fov.png``, ``error_vs_view_angle.png``, ``error_vs_distance.png``,
``error_vs_precision.png``, ``error_vs_uv.png``, ``error_vs_tessellation.png``) and error
maps of one configuration (``error_map_<frame>.png``) into ``--out``; ``--sweeps`` picks a
subset.
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

import jaxnm
from jaxnm.camera import Camera, look_at, perspective
from jaxnm.frames import FRAMES
from jaxnm.interpolate import DERIVATIVE_MODES
from jaxnm.scene import Scene
from jaxnm.textures import NormalMapOptions, decode_normal_map, sample

MAP_VALUE = np.array([0.35, -0.25, 0.9]) / np.linalg.norm([0.35, -0.25, 0.9])
METHODS = [f for f in FRAMES if f != "none"]
GRADIENT_METHODS = ("cotangent", "cotangent_unnormalized", "nonperspective", "exact",
                    "exact_face", "axis")
UV_LAYOUTS = {"orthogonal": [[0.5, 0.0], [0.0, 0.5]],
              "stretched 1:4": [[0.5, 0.0], [0.0, 0.125]],
              "sheared 30 deg": [[0.5, 0.5 * math.tan(math.radians(30))], [0.0, 0.5]],
              "sheared 60 deg": [[0.5, 0.5 * math.tan(math.radians(60))], [0.0, 0.5]],
              "mirrored": [[-0.5, 0.0], [0.0, 0.5]],
              "axis-aligned": [[-0.5, 0.0], [0.0, -0.5]]}


# --------------------------------------------------------------------------------------
# truths
# --------------------------------------------------------------------------------------


def _unit(v):
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def truth_frames(dp_du, dp_dv, n):
    """(gradient T, B; orthonormal T, B) from the surface's dp/du, dp/dv and unit normal,
    per point (float64). The gradient frame is the dual basis of (dp/du, dp/dv) in the
    tangent plane, scaled so the longer is unit; its unscaled version is returned too."""
    g = np.stack([dp_du, dp_dv], -1)  # (..., 3, 2)
    gram = np.einsum("...ki,...kj->...ij", g, g)
    dual = np.einsum("...ij,...kj->...ik", np.linalg.inv(gram), g)  # (..., 2, 3)
    gu, gv = dual[..., 0, :], dual[..., 1, :]
    s = np.sqrt(np.maximum(np.sum(gu * gu, -1), np.sum(gv * gv, -1)))[..., None]
    t_o = _unit(dp_du - n * np.sum(dp_du * n, -1, keepdims=True))
    sign = np.sign(np.sum(np.cross(dp_du, dp_dv) * n, -1))[..., None]
    return (gu / s, gv / s), (gu, gv), (t_o, sign * np.cross(n, t_o))


def perturbed(t, b, n, m=MAP_VALUE):
    m = np.asarray(m, np.float64)
    return _unit(t * m[..., :1] + b * m[..., 1:2] + n * m[..., 2:3])


def angle(a, b):
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    return np.degrees(np.arctan2(np.linalg.norm(np.cross(a, b), axis=-1), np.sum(a * b, -1)))


# --------------------------------------------------------------------------------------
# surfaces: a mesh, and the smooth frame at (the point nearest to) a mesh point
# --------------------------------------------------------------------------------------


class Plane:
    def __init__(self, uv_matrix, size=2.0, segments=4):
        self.a = np.asarray(uv_matrix, np.float64)
        t = np.linspace(-size / 2, size / 2, segments + 1)
        x, y = np.meshgrid(t, t, indexing="xy")
        self.pos = np.stack([x.ravel(), y.ravel(), np.zeros(x.size)], 1)
        self.uv = self.pos[:, :2] @ self.a.T + 0.5
        self.nrm = np.tile([0.0, 0.0, 1.0], (len(self.pos), 1))
        n = segments + 1
        i, j = np.meshgrid(np.arange(segments), np.arange(segments), indexing="xy")
        k = (j * n + i).ravel()
        self.faces = np.concatenate([np.stack([k, k + 1, k + n + 1], 1),
                                     np.stack([k, k + n + 1, k + n], 1)])

    def frame_at(self, p):
        inv = np.linalg.inv(self.a)  # xy = inv @ (uv - 0.5)
        dp_du = np.broadcast_to(np.array([inv[0, 0], inv[1, 0], 0.0]), p.shape)
        dp_dv = np.broadcast_to(np.array([inv[0, 1], inv[1, 1], 0.0]), p.shape)
        return dp_du, dp_dv, np.broadcast_to(np.array([0.0, 0.0, 1.0]), p.shape)


class Torus:
    def __init__(self, segments, R=1.0, r=0.4):
        m = jaxnm.procedural.torus(R, r, 2 * segments, segments)
        self.R, self.r = R, r
        self.pos, self.faces = np.asarray(m.positions, np.float64), np.asarray(m.faces)
        self.uv, self.nrm = np.asarray(m.uv, np.float64), np.asarray(m.normals, np.float64)

    def frame_at(self, p):
        phi = np.arctan2(p[:, 1], p[:, 0])
        theta = np.arctan2(p[:, 2], np.hypot(p[:, 0], p[:, 1]) - self.R)
        ring = self.R + self.r * np.cos(theta)
        dp_dphi = np.stack([-ring * np.sin(phi), ring * np.cos(phi), 0 * phi], -1)
        dp_dth = self.r * np.stack([-np.sin(theta) * np.cos(phi), -np.sin(theta) * np.sin(phi),
                                    np.cos(theta)], -1)
        n = np.stack([np.cos(theta) * np.cos(phi), np.cos(theta) * np.sin(phi),
                      np.sin(theta)], -1)
        return 2 * np.pi * dp_dphi, 2 * np.pi * dp_dth, n


class Sphere:
    def __init__(self, segments):
        m = jaxnm.procedural.uv_sphere(1.0, 2 * segments, segments)
        self.pos, self.faces = np.asarray(m.positions, np.float64), np.asarray(m.faces)
        self.uv, self.nrm = np.asarray(m.uv, np.float64), np.asarray(m.normals, np.float64)

    def frame_at(self, p):
        n = _unit(p)
        lon = np.arctan2(n[:, 1], n[:, 0])
        lat = np.arcsin(np.clip(n[:, 2], -1, 1))
        dp_dlon = np.stack([-np.cos(lat) * np.sin(lon), np.cos(lat) * np.cos(lon), 0 * lon], -1)
        dp_dlat = np.stack([-np.sin(lat) * np.cos(lon), -np.sin(lat) * np.sin(lon),
                            np.cos(lat)], -1)
        return 2 * np.pi * dp_dlon, np.pi * dp_dlat, n


class Cylinder:
    """Radius 1 about z, height 2; u = angle / 2 pi, v = (z + 1) / 2."""

    def __init__(self, segments):
        a = 2 * np.pi * np.arange(2 * segments + 1) / (2 * segments)
        z = np.linspace(-1, 1, segments // 2 + 2)
        A, Z = np.meshgrid(a, z, indexing="ij")
        self.pos = np.stack([np.cos(A), np.sin(A), Z], -1).reshape(-1, 3)
        self.nrm = np.stack([np.cos(A), np.sin(A), 0 * A], -1).reshape(-1, 3)
        self.uv = np.stack([A / (2 * np.pi), (Z + 1) / 2], -1).reshape(-1, 2)
        nz = len(z)
        i, j = np.meshgrid(np.arange(2 * segments), np.arange(nz - 1), indexing="ij")
        k = (i * nz + j).ravel()
        self.faces = np.concatenate([np.stack([k, k + nz, k + nz + 1], 1),
                                     np.stack([k, k + nz + 1, k + 1], 1)])

    def frame_at(self, p):
        a = np.arctan2(p[:, 1], p[:, 0])
        dp_da = np.stack([-np.sin(a), np.cos(a), 0 * a], -1)
        dp_dz = np.broadcast_to(np.array([0.0, 0.0, 1.0]), p.shape)
        return 2 * np.pi * dp_da, 2 * dp_dz, np.stack([np.cos(a), np.sin(a), 0 * a], -1)


def flat_shaded(surf):
    """The same mesh with face normals: every triangle its own three vertices."""
    p = surf.pos[surf.faces]
    fn = _unit(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]))
    out = type("Flat", (), {})()
    out.pos = p.reshape(-1, 3)
    out.uv = surf.uv[surf.faces].reshape(-1, 2)
    out.nrm = np.repeat(fn, 3, axis=0)
    out.faces = np.arange(len(out.pos)).reshape(-1, 3)
    out.frame_at = surf.frame_at
    return out


# --------------------------------------------------------------------------------------
# measuring
# --------------------------------------------------------------------------------------


def _mesh(surf):
    return jaxnm.Mesh(jnp.asarray(surf.pos, jnp.float32), jnp.asarray(surf.faces, jnp.int32),
                      jnp.asarray(surf.uv, jnp.float32), jnp.asarray(surf.nrm, jnp.float32))


def face_truths(surf, tri, n):
    """Per pixel, the mesh's own exact per-triangle frames (float64) from the pixel's
    triangle ``tri`` and its interpolated unit normal ``n``: Schüler's frame built from the
    triangle's edges instead of screen derivatives (scaled so the longer is unit, and
    unscaled: the gradients of u and v on the plane normal to ``n``), and the orthonormal
    frame of the triangle's dp/du (``T = normalize(dp/du)`` normal to ``n``)."""
    p = surf.pos[surf.faces[tri]]
    uv = surf.uv[surf.faces[tri]]
    dp1, dp2 = p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]
    d1, d2 = uv[:, 1] - uv[:, 0], uv[:, 2] - uv[:, 0]
    perp2, perp1 = np.cross(dp2, n), np.cross(n, dp1)
    area = np.sum(n * np.cross(dp1, dp2), -1, keepdims=True)  # T . dp_i = area * du_i
    t = (perp2 * d1[:, :1] + perp1 * d2[:, :1]) / area
    b = (perp2 * d1[:, 1:] + perp1 * d2[:, 1:]) / area
    s = np.sqrt(np.maximum(np.sum(t * t, -1), np.sum(b * b, -1)))[:, None]
    det = d1[:, 0] * d2[:, 1] - d1[:, 1] * d2[:, 0]
    dp_du = (dp1 * d2[:, 1:] - dp2 * d1[:, 1:]) / det[:, None]
    dp_dv = (dp2 * d1[:, :1] - dp1 * d2[:, :1]) / det[:, None]
    t_o = _unit(dp_du - n * np.sum(dp_du * n, -1, keepdims=True))
    sign = np.sign(np.sum(np.cross(dp_du, dp_dv) * n, -1))[:, None]
    return (t / s, b / s), (t, b), (t_o, sign * np.cross(n, t_o))


def _map_texels(kind: str) -> np.ndarray:
    if kind == "constant":
        return np.broadcast_to(((MAP_VALUE + 1) / 2).astype(np.float32), (4, 4, 3)).copy()
    return ((jaxnm.procedural.default_normal_map(128) + 1) / 2).astype(np.float32)


def measure(surf, camera, size, methods=METHODS, modes=("fine",), keep_maps=False,
            normal_map="constant", precision="float32") -> list:
    """One record per (method, mode): mean / p95 / max angles of the perturbed normal to
    the smooth surface's truth of the method's convention (``error_*``) and to the other
    convention's (``gradient_*`` / ``orthonormal_*``), to the mesh's own per-triangle
    truth (``face_*``), and the mean angles of T and B to the smooth truth.

    ``normal_map``: ``"constant"`` (every texel the fixed tilted `MAP_VALUE`) or
    ``"rivets"`` (the default scene's map, 128 texels, bilinear; the truth decodes the
    same bilinear sample at the pixel's rendered uv, so only the frame differs)."""
    texels = _map_texels(normal_map)
    options = NormalMapOptions(filter="nearest" if normal_map == "constant" else "bilinear",
                               wrap="clamp" if normal_map == "constant" else "repeat")
    mesh = _mesh(surf)
    if "vertex" in methods:
        mesh = mesh.with_tangents()
    scene = Scene(mesh=mesh, camera=camera, width=size, height=size,
                  normal_map=jnp.asarray(texels), normal_map_options=options,
                  source="<frame study>")
    rows, maps = [], {}
    for mode in modes:
        for method in methods:
            out = jaxnm.render(scene, outputs=("perturbed_normal", "tangent", "bitangent",
                                               "position", "normal", "uv", "triangle_id",
                                               "mask", "front_facing"),
                               derivatives=mode, frame=method, precision=precision)
            m = np.asarray(out["mask"])[..., 0] > 0
            m &= np.asarray(out["front_facing"])[..., 0] > 0
            if m.sum() == 0:
                continue
            p = np.asarray(out["position"], np.float64)[m]
            if normal_map == "constant":
                mv = np.broadcast_to(MAP_VALUE, p.shape)
            else:
                raw = sample(jnp.asarray(texels), out["uv"], filter="bilinear", wrap="repeat")
                mv = np.asarray(decode_normal_map(raw), np.float64)[m]
            dp_du, dp_dv, n = surf.frame_at(p)
            (tg, bg), (tu, bu), (to, bo) = truth_frames(dp_du, dp_dv, n)
            n_px = _unit(np.asarray(out["normal"], np.float64)[m])
            tri = np.asarray(out["triangle_id"])[..., 0][m].astype(np.int64)
            (fg, fb), (fu, fbu), (fo, fbo) = face_truths(surf, tri, n_px)
            unnorm = method == "cotangent_unnormalized"
            own = "gradient" if method in GRADIENT_METHODS else "orthonormal"
            truth = {"gradient": (tu, bu) if unnorm else (tg, bg), "orthonormal": (to, bo)}
            face = {"gradient": (fu, fbu) if unnorm else (fg, fb), "orthonormal": (fo, fbo)}
            pn = np.asarray(out["perturbed_normal"], np.float64)[m]
            rec = {"method": method, "mode": mode, "convention": own, "map": normal_map,
                   "precision": precision, "pixels": int(m.sum())}
            for conv, (t, b) in truth.items():
                e = angle(pn, perturbed(t, b, n, mv))
                rec[f"{conv}_mean"] = float(e.mean())
                rec[f"{conv}_p95"] = float(np.percentile(e, 95))
                rec[f"{conv}_max"] = float(e.max())
                if conv == own:
                    rec["error_mean"], rec["error_p95"] = rec[f"{conv}_mean"], rec[f"{conv}_p95"]
                    rec["error_max"] = rec[f"{conv}_max"]
                    if keep_maps:
                        img = np.full(m.shape, np.nan)
                        img[m] = e
                        maps[method] = img
            e = angle(pn, perturbed(*face[own], n_px, mv))
            rec["face_mean"], rec["face_p95"] = float(e.mean()), float(np.percentile(e, 95))
            rec["face_max"] = float(e.max())
            t_px = np.asarray(out["tangent"], np.float64)[m]
            b_px = np.asarray(out["bitangent"], np.float64)[m]
            t_own, b_own = truth[own]
            rec["T_mean"] = float(angle(t_px, t_own).mean())
            rec["B_mean"] = float(angle(b_px, b_own).mean())
            rows.append(rec)
    return (rows, maps) if keep_maps else rows


def _camera(view_deg, fov, target=(0.0, 0.0, 0.0), dist=None, extent=1.0):
    """A camera looking at ``target`` at ``view_deg`` from the +z normal, at the distance
    where a square of half-size ``extent`` fills the view at this field of view."""
    if dist is None:
        dist = 1.15 * extent / math.tan(math.radians(fov) / 2)
    r = math.radians(view_deg)
    eye = np.asarray(target) + dist * np.array([0.0, -math.sin(r), math.cos(r)])
    return Camera.from_matrices(look_at(eye, target, (0, 1, 0) if view_deg < 1e-6 else
                                        (0, 0, 1)),
                                perspective(fov, 1.0, dist * 1e-3, dist * 10))


def _torus_camera():
    return Camera.from_matrices(look_at((4.0, -1.4, 1.6), (1.4, 0.0, 0.0), (0, 0, 1)),
                                perspective(40, 1.0, 0.05, 50))


SWEEPS = ("fov", "view angle", "uv", "distance", "derivatives", "precision", "tessellation")


def sweeps(size: int, quick: bool, only=SWEEPS) -> list:
    rows = []

    def tag(records, **kw):
        for r in records:
            r.update(kw)
        rows.extend(records)
        print(json.dumps({**kw, "methods": len(records)}), flush=True)

    def forget():
        # drop compiled programs no later sweep point reuses: XLA's CPU backend keeps every
        # executable mapped, and a long run would pass Linux's vm.max_map_count (65530)
        jax.clear_caches()

    plane = Plane(UV_LAYOUTS["sheared 30 deg"])
    base = 1.15 / math.tan(math.radians(30))
    if "precision" in only:  # shader precision against the camera distance (close-ups)
        for precision in ("float32", "float16", "bfloat16"):
            for f in ((0.01, 1) if quick else (0.003, 0.03, 0.3, 3)):
                tag(measure(plane, _camera(60, 60, dist=f * base), size,
                            modes=("fine", "analytic"), precision=precision),
                    sweep="precision", fov=60, view=60, distance=f, surface="plane",
                    uv="sheared 30 deg")
            forget()
        for precision in ("float16", "bfloat16"):
            tag(measure(Torus(32), _torus_camera(), size, modes=("fine", "analytic"),
                        normal_map="rivets", precision=precision),
                sweep="precision", surface="torus", segments=32, normals="smooth",
                uv="surface", map="rivets")
            forget()
    for fov in ([] if "fov" not in only else
                (1, 30, 120) if quick else (1, 10, 30, 60, 90, 120)):
        tag(measure(plane, _camera(45, fov), size), sweep="fov", fov=fov, view=45,
            surface="plane", uv="sheared 30 deg")
    for view in ([] if "view angle" not in only else
                 (0, 60, 89) if quick else (0, 30, 60, 75, 85, 89)):
        tag(measure(plane, _camera(view, 60), size), sweep="view angle", fov=60, view=view,
            surface="plane", uv="sheared 30 deg")
    for name, a in (UV_LAYOUTS.items() if "uv" in only else ()):
        tag(measure(Plane(a), _camera(45, 60), size), sweep="uv", fov=60, view=45,
            surface="plane", uv=name)
    for f in ([] if "distance" not in only else
              (0.1, 1, 10) if quick else (0.1, 0.3, 1, 3, 10)):
        tag(measure(plane, _camera(60, 60, dist=f * base), size), sweep="distance", fov=60,
            view=60, distance=f, surface="plane", uv="sheared 30 deg")
    if "derivatives" in only:
        tag(measure(plane, _camera(45, 60), size, modes=DERIVATIVE_MODES),
            sweep="derivatives", fov=60, view=45, surface="plane", uv="sheared 30 deg")
    torus = Torus(32)
    for normal_map in (("constant", "rivets") if "derivatives" in only else ()):
        tag(measure(torus, _torus_camera(), size, modes=DERIVATIVE_MODES,
                    normal_map=normal_map),
            sweep="derivatives", surface="torus", segments=32, normals="smooth",
            uv="surface", map=normal_map)
        forget()
    for seg in ([] if "tessellation" not in only else (8, 32) if quick else (8, 16, 32, 64)):
        for name, surf in (("torus", Torus(seg)), ("sphere", Sphere(seg)),
                           ("cylinder", Cylinder(seg))):
            for normals in ("smooth", "flat"):
                s = surf if normals == "smooth" else flat_shaded(surf)
                target = (1.4, 0.0, 0.0) if name == "torus" else (0.7, 0.0, 0.0)
                cam = Camera.from_matrices(
                    look_at(np.array(target) + [2.6, -1.4, 1.6], target, (0, 0, 1)),
                    perspective(40, 1.0, 0.05, 50))
                tag(measure(s, cam, size, methods=("cotangent", "exact", "exact_face",
                                                   "vertex", "vertex_area")),
                    sweep="tessellation", surface=name, segments=seg, normals=normals,
                    uv="surface")
                forget()
    return rows


def _plot(rows, out: Path) -> None:
    try:
        from matplotlib.figure import Figure
    except ImportError:
        print("matplotlib missing: no plots (pip install '.[notebook]')")
        return
    for sweep, key, fname, xlabel in (("fov", "fov", "error_vs_fov.png", "field of view (deg)"),
                                      ("view angle", "view", "error_vs_view_angle.png",
                                       "view angle from the normal (deg)"),
                                      ("distance", "distance", "error_vs_distance.png",
                                       "camera distance / distance that frames the plane")):
        fig = Figure(figsize=(6.5, 4), dpi=100)
        ax = fig.add_subplot()
        for method in METHODS:
            pts = sorted((r[key], r["error_mean"]) for r in rows
                         if r["sweep"] == sweep and r["method"] == method)
            if pts:
                plot = ax.loglog if sweep == "distance" else ax.semilogy
                plot(*zip(*[(x, max(y, 1e-6)) for x, y in pts]), "o-", label=method)
        ax.set(xlabel=xlabel, ylabel="mean error vs own truth (deg)", title=sweep)
        ax.legend(fontsize=7)
        fig.tight_layout()
        fig.savefig(out / fname)
    prec = [r for r in rows if r["sweep"] == "precision" and r["surface"] == "plane"]
    if prec:
        fig = Figure(figsize=(9, 4), dpi=100)
        for k, mode in enumerate(("fine", "analytic")):
            ax = fig.add_subplot(1, 2, k + 1)
            for method, color in (("cotangent", "C0"), ("exact", "C1"), ("vertex", "C2"),
                                  ("nonperspective", "C3")):
                for precision, style in (("float32", ":"), ("float16", "-"),
                                         ("bfloat16", "--")):
                    pts = sorted((r["distance"], r["error_mean"]) for r in prec
                                 if r["method"] == method and r["mode"] == mode
                                 and r["precision"] == precision)
                    if pts:
                        ax.loglog(*zip(*[(x, max(y, 1e-6)) for x, y in pts]), style,
                                  color=color, marker="o", ms=3, label=f"{method} {precision}")
            ax.set(xlabel="camera distance / distance that frames the plane",
                   ylabel="mean error vs own truth (deg)", title=f"{mode} derivatives")
            ax.legend(fontsize=5)
        fig.tight_layout()
        fig.savefig(out / "error_vs_precision.png")
    fig = Figure(figsize=(8, 4), dpi=100)
    ax = fig.add_subplot()
    layouts = list(UV_LAYOUTS)
    for k, method in enumerate(METHODS):
        vals = [next((r["error_mean"] for r in rows if r["sweep"] == "uv" and r["uv"] == u
                      and r["method"] == method), np.nan) for u in layouts]
        ax.bar(np.arange(len(layouts)) + 0.1 * k, np.maximum(vals, 1e-6), 0.1, label=method)
    ax.set_yscale("log")
    ax.set_xticks(np.arange(len(layouts)) + 0.35, layouts, fontsize=7)
    ax.set(ylabel="mean error vs own truth (deg)", title="uv layout")
    ax.legend(fontsize=6)
    fig.tight_layout()
    fig.savefig(out / "error_vs_uv.png")
    fig = Figure(figsize=(9, 4), dpi=100)
    for k, normals in enumerate(("smooth", "flat")):
        ax = fig.add_subplot(1, 2, k + 1)
        for surf in ("torus", "sphere", "cylinder"):
            for method, style in (("cotangent", "-"), ("vertex", "--")):
                pts = sorted((r["segments"], r["error_mean"]) for r in rows
                             if r["sweep"] == "tessellation" and r["surface"] == surf
                             and r["normals"] == normals and r["method"] == method)
                if pts:
                    ax.loglog(*zip(*pts), style, marker="o", label=f"{surf} {method}")
        ax.set(xlabel="segments", ylabel="mean error vs smooth truth (deg)",
               title=f"{normals} normals")
        ax.legend(fontsize=6)
    fig.tight_layout()
    fig.savefig(out / "error_vs_tessellation.png")


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="frames_out")
    ap.add_argument("--size", type=int, default=96)
    ap.add_argument("--quick", action="store_true", help="fewer sweep points (a smoke test)")
    ap.add_argument("--sweeps", default=",".join(SWEEPS),
                    help="comma-separated subset of: " + ", ".join(SWEEPS))
    args = ap.parse_args(argv)
    only = tuple(x.strip() for x in args.sweeps.split(","))
    if bad := [x for x in only if x not in SWEEPS]:
        ap.error(f"--sweeps: unknown {bad}; expected any of {', '.join(SWEEPS)}")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    rows = sweeps(args.size, args.quick, only)
    (out / "frames.json").write_text(json.dumps(rows, indent=1) + "\n")
    keys = sorted({k for r in rows for k in r})
    with open(out / "frames.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=keys)
        w.writeheader()
        w.writerows(rows)
    _plot(rows, out)
    _, maps = measure(Torus(32), _torus_camera(), args.size, keep_maps=True)
    from jaxnm.io import save_png

    for method, img in maps.items():
        save_png(out / f"error_map_{method}.png",
                 np.nan_to_num(np.clip(img / 5.0, 0, 1), nan=0.25).astype(np.float32))
    print(f"wrote {out} in {time.perf_counter() - t0:.0f} s")


if __name__ == "__main__":
    main()
