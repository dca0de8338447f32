"""The frame study: how far each tangent frame is from the truth, and what it depends on.

    python -m scripts.studies.study_frames --out frames_out [--size 128] [--quick]
        [--sweeps all | NAME,...] [--asset suzanne.npz]

Besides the fixed map value's angle, every record carries measures that do not depend on
the map: the worst angle over the hemisphere of map values and the operator norm of
``F - F*`` (per pixel), the angles and relative length errors of T and B, each as mean,
p95 and max over the ``pixels``. The fov, view-angle and distance sweeps run fine, coarse
and analytic derivatives; ``orthographic`` tilts a plane under an orthographic camera (the
non-perspective frame against its closed form); ``conventions`` feeds HLSL's ddy to the
screen-space frames, reads a DirectX (green-down) map as OpenGL and decodes a plane whose
mirrored halves share their texels; ``real`` decodes a map Blender baked onto Suzanne's uv
layout (`blender_suzanne.py`) with trilinear mip-mapped sampling up to 1024x1024, against
Blender's own MikkTSpace decode in float64, with each frame's compiled cost in ms.
``frames.json`` carries the run's metadata (jaxnm version and commit, JAX version, machine,
run time) and ``frames_summary.json`` the small table data.

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

Writes ``frames.json`` (one record per configuration and method), ``frames.csv``,
``frames_summary.json``, plots (``error_vs_fov.png``, ``error_vs_view_angle.png``,
``error_vs_distance.png``, ``error_vs_tilt_orthographic.png``, ``error_vs_uv.png``,
``cost_vs_error_real.png``, and with their sweeps ``error_vs_precision.png``,
``error_vs_tessellation.png``) and per-pixel error images of every frame on Suzanne
(``real_error_maps.png``) and of the derivative modes on the torus
(``torus_error_maps.png``) into ``--out``; ``--sweeps`` picks a subset. Render programs
are compiled once per image size, mesh shape and static option set and shared by every
sweep point (the camera is an argument, not a constant), which is what keeps the default
run to minutes.
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import os
import subprocess
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

import jaxnm
from jaxnm.camera import Camera, look_at, orthographic, perspective
from jaxnm.frames import FRAMES, SCREEN_FRAMES
from jaxnm.interpolate import DERIVATIVE_MODES
from jaxnm.scene import Scene
from jaxnm.textures import NormalMapOptions, decode_normal_map, sample

MAP_VALUE = np.array([0.35, -0.25, 0.9]) / np.linalg.norm([0.35, -0.25, 0.9])
METHODS = [f for f in FRAMES if f != "none"]
GRADIENT_METHODS = ("cotangent", "cotangent_unnormalized", "nonperspective", "exact",
                    "exact_face", "axis", "gram_schmidt", "separate")
#: The map values of the worst case: a Fibonacci set over the upper hemisphere (z >= 0) and
#: ``RIM`` of them on its rim (`hemisphere`).
HEMISPHERE = 192
RIM = 48
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


class MirrorPlane(Plane):
    """A plane whose two halves share their texels: ``u`` mirrored about ``x = 0``
    (``u = 0.5 + a |x| + b y``), the layout of a symmetric asset baked once for both
    halves. The right half's uv is `Plane`'s; the left half's is its mirror image, with
    the opposite handedness. Vertices on the mirror line are shared."""

    def __init__(self, uv_matrix, size=2.0, segments=4):
        super().__init__(uv_matrix, size, segments)
        xy = self.pos[:, :2] * [[1.0, 1.0]]
        xy[:, 0] = np.abs(xy[:, 0])
        self.uv = xy @ self.a.T + 0.5

    def frame_at(self, p):
        dp_du, dp_dv, n = (np.array(x) for x in super().frame_at(p))
        left = p[:, 0] < 0
        dp_du[left, 0] *= -1  # x -> -x on the left half
        dp_dv[left, 0] *= -1
        return dp_du, dp_dv, n


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


def hemisphere(k=HEMISPHERE, rim=RIM):
    """``k`` unit vectors over the closed upper hemisphere: ``k - rim`` spread evenly over
    it (a Fibonacci set, z from 1 down to 0) and ``rim`` evenly spaced on its rim (z = 0,
    starting along +x), where a frame's error is largest (a reversed T turns the rim's +x
    into -x: 180 degrees)."""
    n = k - rim
    i = np.arange(n) + 0.5
    z = 1.0 - i / n
    phi = i * math.pi * (3.0 - math.sqrt(5.0))
    r = np.sqrt(1.0 - z * z)
    a = 2 * math.pi * np.arange(rim) / rim
    ring = np.stack([np.cos(a), np.sin(a), np.zeros(rim)], -1)
    return np.concatenate([np.stack([r * np.cos(phi), r * np.sin(phi), z], -1), ring])


def _stats(rec, prefix, e):
    rec[f"{prefix}_mean"] = float(np.mean(e))
    rec[f"{prefix}_p95"] = float(np.percentile(e, 95))
    rec[f"{prefix}_max"] = float(np.max(e))


def frame_measures(t, b, n, t0, b0, n0, chunk=4096):
    """Map-independent measures of a frame ``(t, b, n)`` against a truth ``(t0, b0, n0)``
    (each ``(P, 3)``, float64), per pixel: the worst angle over every map value of the
    upper hemisphere (`hemisphere`) between ``normalize(F m)`` and ``normalize(F* m)``, and
    the operator norm (largest singular value) of ``F - F*``, ``F = [t b n]``."""
    ms = hemisphere().T  # (3, K)
    worst = np.empty(len(t))
    for a in range(0, len(t), chunk):
        sl = slice(a, a + chunk)
        v = np.stack([t[sl], b[sl], n[sl]], -1) @ ms  # (P, 3, K): F m for every m
        v0 = np.stack([t0[sl], b0[sl], n0[sl]], -1) @ ms
        cross = np.linalg.norm(np.cross(v, v0, axis=1), axis=1)
        worst[sl] = np.degrees(np.arctan2(cross, np.sum(v * v0, 1))).max(1)
    d = np.stack([t - t0, b - b0, n - n0], -1)
    return worst, np.linalg.norm(d, ord=2, axis=(-2, -1))


def measure(surf, camera, size, methods=METHODS, modes=("fine",), keep_maps=False,
            normal_map="constant", precision="float32", ddy="up", stored=None,
            screen_modes_only=False) -> list:
    """One record per (method, mode): mean / p95 / max angles of the perturbed normal to
    the smooth surface's truth of the method's convention (``error_*``) and to the other
    convention's (``gradient_*`` / ``orthonormal_*``), to the mesh's own per-triangle
    truth (``face_*``), and the mean angles of T and B to the smooth truth.

    ``normal_map``: ``"constant"`` (every texel the fixed tilted `MAP_VALUE`) or
    ``"rivets"`` (the default scene's map, 128 texels, bilinear; the truth decodes the
    same bilinear sample at the pixel's rendered uv, so only the frame differs).

    Map-independent measures against the method's own truth: ``worst_*`` (the worst angle
    over the hemisphere of map values, per pixel), ``opnorm_*`` (the operator norm of
    ``F - F*``), the angles of T and B (``T_*``, ``B_*``) and their relative length
    errors (``Tlen_*``, ``Blen_*``: ``|T| / |T*| - 1``), each as mean, p95 and max over
    the ``pixels``.

    ``ddy="down"`` feeds HLSL's ``ddy`` to the screen-space frames; ``stored`` (a map
    value) puts that value in the texels while the truth still decodes `MAP_VALUE` (a
    map stored in another convention). With ``screen_modes_only`` the frames that take no
    screen derivatives (`jaxnm.frames.SCREEN_FRAMES` lists those that do) run with fine
    derivatives only: with the constant map's nearest sample nothing else in their render
    depends on the derivative mode."""
    texels = _map_texels(normal_map)
    if stored is not None:
        texels = np.broadcast_to(((np.asarray(stored) + 1) / 2).astype(np.float32),
                                 texels.shape).copy()
    options = NormalMapOptions(filter="nearest" if normal_map == "constant" else "bilinear",
                               wrap="clamp" if normal_map == "constant" else "repeat")
    # always with its tangents: one pytree, so every call at this size and mesh shape shares
    # each (frame, derivatives) program, whichever methods it asks for
    mesh = _mesh(surf).with_tangents()
    scene = Scene(mesh=mesh, camera=camera, width=size, height=size,
                  normal_map=jnp.asarray(texels), normal_map_options=options,
                  source="<frame study>", ddy=ddy)
    rows, maps = [], {}
    for mode in modes:
        for method in methods:
            if screen_modes_only and mode != "fine" and method not in SCREEN_FRAMES:
                continue
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
                   "precision": precision, "pixels": int(m.sum()), "ddy": ddy,
                   "stored": None if stored is None else [float(x) for x in stored]}
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
                        maps[method if len(modes) == 1 else f"{method} ({mode})"] = img
            e = angle(pn, perturbed(*face[own], n_px, mv))
            rec["face_mean"], rec["face_p95"] = float(e.mean()), float(np.percentile(e, 95))
            rec["face_max"] = float(e.max())
            t_px = np.asarray(out["tangent"], np.float64)[m]
            b_px = np.asarray(out["bitangent"], np.float64)[m]
            t_own, b_own = truth[own]
            _stats(rec, "T", angle(t_px, t_own))
            _stats(rec, "B", angle(b_px, b_own))
            ln = np.linalg.norm
            _stats(rec, "Tlen", np.abs(ln(t_px, axis=-1) / ln(t_own, axis=-1) - 1))
            _stats(rec, "Blen", np.abs(ln(b_px, axis=-1) / ln(b_own, axis=-1) - 1))
            for conv, (t, b) in truth.items():
                worst, op = frame_measures(t_px, b_px, n_px, t, b, n)
                pre = "" if conv == own else "other_"
                _stats(rec, pre + "worst", worst)
                _stats(rec, pre + "opnorm", op)
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


def _ortho_camera(view_deg, extent=1.0):
    """An orthographic camera looking at the origin at ``view_deg`` from the +z normal,
    framing a square of half-size ``extent``: no perspective, only the surface's tilt
    (foreshortening by ``cos(view)`` along one axis)."""
    r = math.radians(view_deg)
    eye = 5.0 * np.array([0.0, -math.sin(r), math.cos(r)])
    h = 1.15 * extent
    return Camera.from_matrices(look_at(eye, (0, 0, 0), (0, 1, 0) if view_deg < 1e-6 else
                                        (0, 0, 1)), orthographic(-h, h, -h, h, 0.1, 20.0))


def nonperspective_prediction(view_deg, uv_matrix, m=MAP_VALUE):
    """The non-perspective frame under an orthographic camera, in closed form (float64):
    on the plane ``z = 0`` seen at ``view_deg`` about the x axis, one pixel step is
    ``dp1 = (s, 0, 0)`` and ``dp2 = (0, s / cos(view), 0)``, ``duv = A dp``, and
    ``T = dp1 du1 + dp2 du2`` (``B`` with ``v``). Returns the angle in degrees between
    its perturbed normal and the gradient truth's for the map value ``m``."""
    a = np.asarray(uv_matrix, np.float64)
    c = math.cos(math.radians(view_deg))
    dp1, dp2 = np.array([1.0, 0.0, 0.0]), np.array([0.0, 1.0 / c, 0.0])
    duv1, duv2 = a @ dp1[:2], a @ dp2[:2]
    t = dp1 * duv1[0] + dp2 * duv2[0]
    b = dp1 * duv1[1] + dp2 * duv2[1]
    s = math.sqrt(max(t @ t, b @ b))
    n = np.array([0.0, 0.0, 1.0])
    (tg, bg), _, _ = truth_frames(*Plane(a).frame_at(n[None]))
    return float(angle(perturbed(t / s, b / s, n, m), perturbed(tg[0], bg[0], n, m)))


def _torus_camera():
    return Camera.from_matrices(look_at((4.0, -1.4, 1.6), (1.4, 0.0, 0.0), (0, 0, 1)),
                                perspective(40, 1.0, 0.05, 50))


# --------------------------------------------------------------------------------------
# a real asset: Blender's Suzanne, its uv layout, a map baked by Cycles (MikkTSpace)
# --------------------------------------------------------------------------------------

ROOT = Path(__file__).resolve().parents[2]


def bake_asset(path: Path, size: int = 512) -> Path | None:
    """Run `scripts/studies/blender_suzanne.py` in Blender's environment (None without it)."""
    from scripts.studies.blender_bake_cases import blender_python

    py = blender_python()
    if py is None:
        return None
    if not path.exists():
        subprocess.run([py, str(ROOT / "scripts" / "studies" / "blender_suzanne.py"),
                        str(path), "--size", str(size)], check=True, capture_output=True)
    return path


def _suzanne_camera():
    return Camera.from_matrices(look_at((1.3, -4.6, 1.1), (0.0, 0.0, 0.1), (0, 0, 1)),
                                perspective(36, 1.0, 0.1, 50))


def _barycentric(p, tri):
    """Barycentric weights of points ``p`` (P, 3) in triangles ``tri`` (P, 3, 3), float64."""
    e1, e2, d = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0], p - tri[:, 0]
    g11, g12, g22 = (np.sum(e1 * e1, -1), np.sum(e1 * e2, -1), np.sum(e2 * e2, -1))
    r1, r2 = np.sum(d * e1, -1), np.sum(d * e2, -1)
    det = g11 * g22 - g12 * g12
    b1, b2 = (g22 * r1 - g12 * r2) / det, (g11 * r2 - g12 * r1) / det
    return np.stack([1 - b1 - b2, b1, b2], -1)


def _time_render(scene, method, reps):
    """Median wall time (ms) of a compiled render of the perturbed normal (steady state)."""
    def run():
        out = jaxnm.render(scene, outputs=("perturbed_normal",), frame=method)
        jax.block_until_ready(out)

    run()
    run()
    times = []
    for _ in range(reps):
        t0 = time.perf_counter()
        run()
        times.append(1e3 * (time.perf_counter() - t0))
    return float(np.median(times))


def real_mesh(asset: Path, sizes=(256, 1024), methods=METHODS, reps=5,
              time_size=-1, keep_maps=False, small_methods=None):
    """Each frame decoding a real baked map on a real uv layout, against the baker's decode.

    The reference is MikkTSpace as Blender decodes it, in float64: Blender's own corner
    tangents and signs (`blender_suzanne.py`) interpolated with the pixel's barycentric
    weights, ``B = sign N x T``, ``normalize(m.x T + m.y B + m.z N)``, with ``m`` the map
    value jaxnm sampled (trilinear, mip-mapped) at the pixel. ``ms``: the compiled,
    steady-state time of rendering the perturbed normal (median of ``reps``), at
    ``time_size`` only (-1: the largest of ``sizes``, None: every size, 0: none);
    ``frame_ms``: less the time of the same render with no frame (``none``). With
    ``keep_maps``, also each method's error image at the largest size. ``small_methods``:
    the methods at the smaller sizes (default: ``methods``)."""
    d = np.load(asset)
    mesh = jaxnm.Mesh(jnp.asarray(d["positions"], jnp.float32), jnp.asarray(d["faces"],
                                                                                jnp.int32),
                      jnp.asarray(d["uv"], jnp.float32),
                      jnp.asarray(d["normals"], jnp.float32)).with_tangents()
    pos, faces, nrm = d["positions"], d["faces"], d["normals"]
    rows, maps = [], {}
    if time_size == -1:
        time_size = max(sizes)
    for size in sizes:
        scene = Scene(mesh=mesh, camera=_suzanne_camera(), width=size, height=size,
                      normal_map=jnp.asarray(d["image"], jnp.float32),
                      normal_map_options=NormalMapOptions(filter="trilinear", wrap="repeat"),
                      source="<Suzanne>")
        ref_out = jaxnm.render(scene, outputs=("perturbed_normal", "tangent", "bitangent",
                                                "normal", "position", "triangle_id", "mask",
                                                "front_facing"), frame="vertex")
        m = (np.asarray(ref_out["mask"])[..., 0] > 0) & (
            np.asarray(ref_out["front_facing"])[..., 0] > 0)
        tri = np.asarray(ref_out["triangle_id"])[..., 0][m].astype(np.int64)
        bary = _barycentric(np.asarray(ref_out["position"], np.float64)[m], pos[faces[tri]])
        t_b = np.einsum("pk,pkj->pj", bary, d["tangents"][tri])
        sgn = np.where(np.einsum("pk,pk->p", bary, d["signs"][tri]) < 0, -1.0, 1.0)[:, None]
        n_b = np.einsum("pk,pkj->pj", bary, nrm[faces[tri]])
        # the sampled map value, from jaxnm's MikkTSpace decode: m ~ F^-1 n'
        f = np.stack([np.asarray(ref_out[k], np.float64)[m] for k in
                      ("tangent", "bitangent", "normal")], -1)
        pn = np.asarray(ref_out["perturbed_normal"], np.float64)[m]
        mv = _unit(np.linalg.solve(f, pn[..., None])[..., 0])
        ref = _unit(t_b * mv[:, :1] + sgn * np.cross(n_b, t_b) * mv[:, 1:2] + n_b * mv[:, 2:3])
        none_ms = (_time_render(scene, "none", reps)
                   if time_size in (None, size) else None)
        for method in methods if small_methods is None or size == max(sizes) else [
                m for m in methods if m in small_methods]:
            # the reference render is MikkTSpace's own: its perturbed normal is the same
            out = ref_out if method == "vertex" else jaxnm.render(
                scene, outputs=("perturbed_normal",), frame=method)
            e = angle(np.asarray(out["perturbed_normal"], np.float64)[m], ref)
            rec = {"sweep": "real", "surface": "Suzanne", "method": method, "size": size,
                   "mode": "fine", "map": "baked", "pixels": int(m.sum()),
                   "convention": "gradient" if method in GRADIENT_METHODS else "orthonormal"}
            _stats(rec, "error", e)
            rec["above_5deg"] = int(np.sum(e > 5.0))
            if none_ms is not None:
                rec["ms"] = _time_render(scene, method, reps)
                rec["frame_ms"] = rec["ms"] - none_ms
                rec["none_ms"] = none_ms
            rows.append(rec)
            if keep_maps and size == max(sizes):
                img = np.full(m.shape, np.nan)
                img[m] = e
                maps[method] = img
            print(json.dumps({k: rec[k] for k in ("method", "size", "error_mean")}),
                  flush=True)
        jax.clear_caches()
    return (rows, maps) if keep_maps else rows


def metadata(run_s: float, argv) -> dict:
    """What produced a run: jaxnm's version and commit, JAX's version, the machine."""
    import platform

    try:
        commit = subprocess.run(["git", "rev-parse", "HEAD"], cwd=ROOT, capture_output=True,
                                text=True, check=True).stdout.strip()
        dirty = bool(subprocess.run(["git", "status", "--porcelain", "--", "jaxnm",
                                     "scripts/studies/study_frames.py"], cwd=ROOT,
                                    capture_output=True, text=True).stdout.strip())
    except (OSError, subprocess.CalledProcessError):
        commit, dirty = None, None
    cpu = platform.processor()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return {"jaxnm": jaxnm.__version__, "commit": commit, "modified": dirty,
            "jax": jax.__version__, "backend": jax.default_backend(),
            "machine": f"{platform.machine()}, {os.cpu_count()} cores, {cpu}",
            "python": platform.python_version(), "run_s": round(run_s, 1),
            "command": "python -m scripts.studies.study_frames " + " ".join(argv)}


SWEEPS = ("fov", "view angle", "uv", "distance", "derivatives", "orthographic",
          "conventions", "real", "precision", "tessellation")
#: The default run (the two long ones, precision and tessellation, on request).
DEFAULT_SWEEPS = SWEEPS[:-2]
#: The derivative modes of the fov, view-angle and distance sweeps.
SWEEP_MODES = ("fine", "coarse", "analytic")
#: The screen-space frames the convention sweep feeds HLSL's ddy to.
DDY_METHODS = ("cotangent", "nonperspective", "gram_schmidt", "separate", "cross",
               "surface_gradient")
#: The frames of the orthographic sweep.
ORTHO_METHODS = ("cotangent", "nonperspective", "cross", "exact")
#: The frames of the precision sweep.
PRECISION_METHODS = ("cotangent", "nonperspective", "exact", "exact_face", "vertex")
#: The frames of the real asset at its smaller sizes (every frame at the largest).
REAL_METHODS = ("cotangent", "nonperspective", "vertex", "cross", "surface_gradient")
#: ``--quick``: these frames, fine derivatives, two or three points per sweep (a smoke test
#: of every sweep; its numbers are not the document's).
QUICK_METHODS = ("cotangent", "nonperspective", "vertex", "surface_gradient")


def sweeps(size: int, quick: bool, only=DEFAULT_SWEEPS, asset: Path | None = None,
           real_sizes=(256, 1024)) -> tuple[list, dict]:
    """The records of the sweeps ``only``, and error images (per frame) of the real asset
    (``real_<frame>``) and of the torus (``torus_<frame> (<derivatives>)``).

    Compiled programs are shared: a render program depends on the image size, the mesh's
    array shapes and the static options (frame, derivatives, precision, ddy, the map's
    shape and filter), not on the camera, so the plane sweeps (one mesh shape) compile
    each (frame, derivatives) pair once."""
    rows, maps = [], {}
    methods = QUICK_METHODS if quick else METHODS
    modes = ("fine",) if quick else SWEEP_MODES

    def pick(names):
        return tuple(m for m in names if m in methods)

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
    for fov in ([] if "fov" not in only else
                (1, 120) if quick else (1, 10, 30, 60, 90, 120)):
        tag(measure(plane, _camera(45, fov), size, methods, modes,
                    screen_modes_only=True), sweep="fov", fov=fov,
            view=45, surface="plane", uv="sheared 30 deg")
    for view in ([] if "view angle" not in only else
                 (0, 89) if quick else (0, 30, 60, 75, 85, 89)):
        tag(measure(plane, _camera(view, 60), size, methods, modes,
                    screen_modes_only=True), sweep="view angle",
            fov=60, view=view, surface="plane", uv="sheared 30 deg")
    for name, a in (UV_LAYOUTS.items() if "uv" in only else ()):
        tag(measure(Plane(a), _camera(45, 60), size, methods), sweep="uv", fov=60, view=45,
            surface="plane", uv=name)
    for f in ([] if "distance" not in only else
              (0.1, 10) if quick else (0.1, 0.3, 1, 3, 10)):
        tag(measure(plane, _camera(60, 60, dist=f * base), size, methods, modes,
                    screen_modes_only=True),
            sweep="distance", fov=60, view=60, distance=f, surface="plane",
            uv="sheared 30 deg")
    for view in ([] if "orthographic" not in only else
                 (0, 60) if quick else (0, 15, 30, 45, 60, 75, 89)):
        for name in ("orthogonal", "sheared 30 deg"):
            recs = measure(Plane(UV_LAYOUTS[name]), _ortho_camera(view), size,
                           methods=pick(ORTHO_METHODS))
            for r in recs:
                if r["method"] == "nonperspective":
                    r["predicted"] = nonperspective_prediction(view, UV_LAYOUTS[name])
            tag(recs, sweep="orthographic", view=view, surface="plane", uv=name,
                camera="orthographic")
    if "conventions" in only:
        tag(measure(plane, _camera(45, 60), size, ddy="down",
                    methods=("cotangent",) if quick else DDY_METHODS),
            sweep="conventions", case="HLSL ddy", fov=60, view=45, surface="plane",
            uv="sheared 30 deg")
        green_down = MAP_VALUE * [1.0, -1.0, 1.0]
        tag(measure(plane, _camera(45, 60), size, methods, stored=green_down),
            sweep="conventions", case="DirectX map read as OpenGL", fov=60, view=45,
            surface="plane", uv="sheared 30 deg")
        for name in ("sheared 30 deg", "orthogonal"):
            tag(measure(MirrorPlane(UV_LAYOUTS[name]), _camera(45, 60), size, methods),
                sweep="conventions", case="mirrored halves share texels", fov=60, view=45,
                surface="mirror plane", uv=name)
    if "derivatives" in only:
        # the screen-space frame in every mode; the per-triangle one with fine derivatives
        # and with G-buffer differences (its frame takes none: only its sampling would)
        cot, exact = pick(("cotangent",)), pick(("exact",))
        d_modes = ("fine",) if quick else DERIVATIVE_MODES
        tag(measure(plane, _camera(45, 60), size, cot + exact, ("gbuffer",)),
            sweep="derivatives", fov=60, view=45, surface="plane", uv="sheared 30 deg")
        forget()
        torus = Torus(32)
        for normal_map in ("constant",) if quick else ("constant", "rivets"):
            recs, tmaps = measure(torus, _torus_camera(), size, cot, d_modes,
                                  normal_map=normal_map, keep_maps=True)
            recs += measure(torus, _torus_camera(), size, exact, ("fine", "gbuffer"),
                            normal_map=normal_map)
            if normal_map == "constant":
                maps.update({f"torus_{k}": v for k, v in tmaps.items()})
            tag(recs, sweep="derivatives", surface="torus", segments=32, normals="smooth",
                uv="surface", map=normal_map)
            forget()
    if "real" in only and asset is not None:
        recs, rmaps = real_mesh(asset, sizes=(64,) if quick else real_sizes,
                                methods=("cotangent", "vertex") if quick else methods,
                                small_methods=REAL_METHODS, reps=5,
                                time_size=0 if quick else -1, keep_maps=True)
        rows.extend(recs)
        maps.update({f"real_{k}": v for k, v in rmaps.items()})
        forget()
    if "precision" in only:  # shader precision against the camera distance (close-ups)
        for precision in ("float32", "float16", "bfloat16"):
            for f in ((0.01, 1) if quick else (0.003, 0.03, 0.3, 3)):
                tag(measure(plane, _camera(60, 60, dist=f * base), size,
                            pick(PRECISION_METHODS), modes=("fine", "analytic"),
                            precision=precision),
                    sweep="precision", fov=60, view=60, distance=f, surface="plane",
                    uv="sheared 30 deg")
        forget()
        for precision in ("float32", "float16", "bfloat16"):
            tag(measure(Torus(32), _torus_camera(), size, pick(PRECISION_METHODS),
                        modes=("fine",), normal_map="rivets", precision=precision),
                sweep="precision", surface="torus", segments=32, normals="smooth",
                uv="surface", map="rivets")
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
    return rows, maps


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
        if not any(r["sweep"] == sweep for r in rows):
            continue
        fig = Figure(figsize=(10, 4), dpi=90)
        for k, (stat, label) in enumerate((("error_mean", "mean error, the fixed map value"),
                                           ("worst_p95", "p95 of the worst over the "
                                            "hemisphere"))):
            ax = fig.add_subplot(1, 2, k + 1)
            for j, method in enumerate(METHODS):
                for mode, style in (("fine", "o-"), ("coarse", "x:"), ("analytic", "+--")):
                    pts = sorted((r[key], r[stat]) for r in rows if r["sweep"] == sweep
                                 and r["method"] == method and r["mode"] == mode)
                    if pts:
                        plot = ax.loglog if sweep == "distance" else ax.semilogy
                        plot(*zip(*[(x, max(y, 1e-6)) for x, y in pts]), style,
                             color=f"C{j % 10}", ms=4,
                             label=method if mode == "fine" else None)
            ax.set(xlabel=xlabel, ylabel=f"{label} (deg)", title=f"{sweep}: o fine, x coarse, "
                   "+ analytic")
            if k == 0:
                ax.legend(fontsize=6, ncol=2)
        fig.tight_layout()
        fig.savefig(out / fname)
    ortho = [r for r in rows if r["sweep"] == "orthographic"]
    if ortho:
        fig = Figure(figsize=(6.5, 4), dpi=90)
        ax = fig.add_subplot()
        for j, (method, uv) in enumerate((("nonperspective", "orthogonal"),
                                          ("nonperspective", "sheared 30 deg"),
                                          ("cotangent", "sheared 30 deg"),
                                          ("cross", "orthogonal"))):
            pts = sorted((r["view"], r["error_mean"], r.get("predicted")) for r in ortho
                         if r["method"] == method and r["uv"] == uv)
            ax.semilogy([x for x, _, _ in pts], [max(y, 1e-6) for _, y, _ in pts], "o-",
                        color=f"C{j}", label=f"{method}, {uv} uv")
            if method == "nonperspective":
                ax.semilogy([x for x, _, _ in pts], [max(z, 1e-6) for _, _, z in pts], "k:",
                            lw=1)
        ax.set(xlabel="tilt of the plane from the image plane (deg)",
               ylabel="mean error vs own truth (deg)",
               title="orthographic camera (dotted: closed form)")
        ax.legend(fontsize=7)
        fig.tight_layout()
        fig.savefig(out / "error_vs_tilt_orthographic.png")
    real = [r for r in rows if r["sweep"] == "real" and "frame_ms" in r]
    if real:
        big = max(r["size"] for r in real)
        fig = Figure(figsize=(6.5, 4.2), dpi=90)
        ax = fig.add_subplot()
        for j, r in enumerate(x for x in real if x["size"] == big):
            ax.scatter(max(r["frame_ms"], 0.01), max(r["error_mean"], 1e-4), color=f"C{j % 10}",
                       marker="os^D"[j // 10])
            ax.annotate(r["method"], (max(r["frame_ms"], 0.01), max(r["error_mean"], 1e-4)),
                        fontsize=7)
        ax.set(xscale="log", yscale="log", xlabel=f"frame's cost at {big}x{big} (ms, above "
               "'none')", ylabel="mean angle to Blender's decode (deg)",
               title="Suzanne, baked map, trilinear")
        fig.tight_layout()
        fig.savefig(out / "cost_vs_error_real.png")
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
        w = 0.8 / len(METHODS)
        ax.bar(np.arange(len(layouts)) + w * k, np.maximum(vals, 1e-6), w, label=method)
    ax.set_yscale("log")
    ax.set_xticks(np.arange(len(layouts)) + 0.4, layouts, fontsize=7)
    ax.set(ylabel="mean error vs own truth (deg)", title="uv layout")
    ax.legend(fontsize=6)
    fig.tight_layout()
    fig.savefig(out / "error_vs_uv.png")
    fig = Figure(figsize=(9, 4), dpi=100)
    if not any(r["sweep"] == "tessellation" for r in rows):
        return
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


def summary(rows, meta) -> dict:
    """The rows behind the document's tables, with only the columns they show, as a table
    (``columns``, and ``rows`` of values, None where a record has no such field; numbers
    to 4 significant digits): small enough to keep beside the document."""
    keep = ("sweep", "case", "method", "mode", "convention", "fov", "view", "distance", "uv",
            "surface", "camera", "map", "precision", "segments", "normals", "size", "pixels",
            "predicted", "ddy", "above_5deg", "ms", "frame_ms")
    stats = [f"{k}_{q}" for k in ("error", "gradient", "orthonormal", "worst", "other_worst")
             for q in ("mean", "p95", "max")]
    stats += [f"{k}_{q}" for k in ("opnorm", "T", "B", "Tlen", "Blen") for q in ("p95", "max")]
    stats += ["face_mean"]
    cols = [k for k in keep + tuple(stats) if any(k in r for r in rows)]

    def value(r, k):
        v = r.get(k)
        return float(f"{v:.4g}") if isinstance(v, float) else v

    return {"metadata": meta, "columns": cols,
            "rows": [[value(r, k) for k in cols] for r in rows]}


def _error_maps(maps, path: Path, title: str = "") -> None:
    """One panel per frame: its angle to the reference, 0 (black) to 10 degrees (white)."""
    try:
        from matplotlib.figure import Figure
    except ImportError:
        return
    names = list(maps)
    cols = 4
    rows = -(-len(names) // cols)
    fig = Figure(figsize=(2.2 * cols, 2.3 * rows), dpi=80)
    for k, name in enumerate(names):
        ax = fig.add_subplot(rows, cols, k + 1)
        im = ax.imshow(maps[name], vmin=0, vmax=10, cmap="magma")
        ax.set_title(name, fontsize=8)
        ax.axis("off")
    fig.colorbar(im, ax=fig.axes, shrink=0.6, label="deg")
    if title:
        fig.suptitle(f"{title}: angle to the reference per pixel", fontsize=9)
    fig.savefig(path)


def main(argv=None) -> None:
    argv = list(argv) if argv is not None else None
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="frames_out")
    ap.add_argument("--size", type=int, default=None,
                    help="render size of the plane and torus sweeps (default 128, --quick 32)")
    ap.add_argument("--quick", action="store_true", help="fewer sweep points (a smoke test)")
    ap.add_argument("--sweeps", default=",".join(DEFAULT_SWEEPS),
                    help="comma-separated subset of: " + ", ".join(SWEEPS) + " (default: all "
                    "but precision and tessellation); 'all' for every one")
    ap.add_argument("--asset", default=None,
                    help="the real asset's npz (default: OUT/suzanne.npz, baked by Blender "
                    "when missing; the real sweep is left out without Blender)")
    args = ap.parse_args(argv)
    if args.size is None:
        args.size = 32 if args.quick else 128
    only = SWEEPS if args.sweeps == "all" else tuple(x.strip() for x in args.sweeps.split(","))
    if bad := [x for x in only if x not in SWEEPS]:
        ap.error(f"--sweeps: unknown {bad}; expected any of {', '.join(SWEEPS)}")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    asset = None
    if "real" in only:
        asset = Path(args.asset) if args.asset else bake_asset(out / "suzanne.npz")
        if asset is None:
            print("no Blender environment: the real-asset sweep is left out")
    rows, maps = sweeps(args.size, args.quick, only, asset=asset)
    _plot(rows, out)
    for family, title in (("real", "Suzanne"), ("torus", "torus")):
        fam = {k.split("_", 1)[1]: v for k, v in maps.items() if k.startswith(family + "_")}
        if fam:
            _error_maps(fam, out / f"{family}_error_maps.png", title)
    meta = metadata(time.perf_counter() - t0, sys.argv[1:] if argv is None else argv)
    (out / "frames.json").write_text(json.dumps({"metadata": meta, "rows": rows}, indent=1)
                                     + "\n")
    (out / "frames_summary.json").write_text(json.dumps(summary(rows, meta)) + "\n")
    keys = sorted({k for r in rows for k in r})
    with open(out / "frames.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=keys)
        w.writeheader()
        w.writerows(rows)
    print(f"wrote {out} in {meta['run_s']:.0f} s")


if __name__ == "__main__":
    main()
