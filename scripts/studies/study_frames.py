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
``frames_summary.json``, the figures of `FIGURES` drawn from that summary (``--figures
SUMMARY`` draws them from a summary file alone, e.g. the one beside the frames page), and
per-pixel error images of every frame on Suzanne (``frames_real_error_maps.png``) and of
the derivative modes on the torus (``frames_torus_error_maps.png``) into ``--out``;
``--sweeps`` picks a subset. ``decoding`` compares ways of decoding a MikkTSpace map
(`DECODINGS`: where the bitangent is formed, what is renormalised) with the reference, on
Suzanne and on a torus with mirrored u, in degrees and in shading. Render programs
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
from jaxnm.tangents import mikktspace_tangents
from jaxnm.textures import NormalMapOptions, decode_normal_map, sample
from scripts._cli import output, run_script

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


class Padded:
    """``surf`` with unused vertices and zero-area triangles appended up to ``vertices`` and
    ``faces``: meshes of different sizes then share one array shape, and so one compiled
    render program per frame. The padding triangles all sit on one unused vertex (zero
    area): they cover no pixel, and MikkTSpace and the area-weighted tangents take nothing
    from them (`tests/test_study_frames.py` checks the tangents of the mesh's own faces)."""

    def __init__(self, surf, vertices: int, faces: int):
        nv, nf = len(surf.pos), len(surf.faces)
        if nv >= vertices or nf > faces:
            raise ValueError(f"cannot pad {nv} vertices, {nf} faces to {vertices}, {faces}")
        self.surf = surf
        self.pos = np.concatenate([surf.pos, np.tile([0.0, 0.0, 1e4], (vertices - nv, 1))])
        self.uv = np.concatenate([surf.uv, np.zeros((vertices - nv, 2))])
        self.nrm = np.concatenate([surf.nrm, np.tile([0.0, 0.0, 1.0], (vertices - nv, 1))])
        self.faces = np.concatenate([surf.faces, np.full((faces - nf, 3), nv)])
        self.frame_at = surf.frame_at


def padded_all(surfs):
    """Every surface of ``surfs`` padded (`Padded`) to the largest vertex and face count."""
    nv = max(len(s.pos) for s in surfs) + 1
    nf = max(len(s.faces) for s in surfs)
    return [Padded(s, nv, nf) for s in surfs]


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


def _asset_pixels(out, d, filter="trilinear"):
    """The measured pixels of a render ``out`` of the asset ``d`` (mask, front-facing), their
    triangle, float64 barycentric weights, and the map value sampled at their uv (float64):
    jaxnm's sampler (``filter``, with the render's uv derivatives for the mip level) and
    decode, independent of any frame."""
    m = (np.asarray(out["mask"])[..., 0] > 0) & (np.asarray(out["front_facing"])[..., 0] > 0)
    tri = np.asarray(out["triangle_id"])[..., 0][m].astype(np.int64)
    bary = _barycentric(np.asarray(out["position"], np.float64)[m],
                        d["positions"][d["faces"][tri]])
    raw = sample(jnp.asarray(d["image"], jnp.float32), out["uv"], out["duvdx"], out["duvdy"],
                 filter=filter, wrap="repeat")
    mv = np.asarray(decode_normal_map(raw), np.float64)[m]
    return m, tri, bary, mv


def _interpolated_corners(tangents, normals, signs, tri, bary):
    """Per pixel, the corner tangents (F, 3, 3) and normals (F, 3, 3) of its triangle ``tri``
    interpolated with ``bary``, *not* normalised, and the sign of the interpolated corner
    signs (F, 3) as ``(P, 1)`` (+1 at 0)."""
    t = np.einsum("pk,pkj->pj", bary, tangents[tri])
    n = np.einsum("pk,pkj->pj", bary, normals[tri])
    s = np.where(np.einsum("pk,pk->p", bary, signs[tri]) < 0, -1.0, 1.0)[:, None]
    return t, n, s


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
    tangents and signs (`blender_suzanne.py`) and normals interpolated with the pixel's
    barycentric weights and not normalised, ``B = sign N x T``,
    ``normalize(m.x T + m.y B + m.z N)``, with ``m`` the map value sampled (trilinear,
    mip-mapped) at the pixel's uv by jaxnm's sampler, apart from any frame
    (`_asset_pixels`). The first record (``case="tangents"``) compares jaxnm's MikkTSpace
    corner tangents with Blender's directly (``T_*``: angles in degrees over the corners of
    the triangles, ``sign_mismatches``). ``ms``: the compiled,
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
    faces, nrm = d["faces"], d["normals"]
    ours = np.asarray(mesh.tangents, np.float64)
    e = angle(ours[..., :3], d["tangents"])
    rec = {"sweep": "real", "case": "tangents", "surface": "Suzanne", "method": "vertex",
           "pixels": int(e.size), "sign_mismatches": int(np.sum(ours[..., 3] != d["signs"]))}
    _stats(rec, "T", e)
    rows, maps = [rec], {}
    if time_size == -1:
        time_size = max(sizes)
    for size in sizes:
        scene = Scene(mesh=mesh, camera=_suzanne_camera(), width=size, height=size,
                      normal_map=jnp.asarray(d["image"], jnp.float32),
                      normal_map_options=NormalMapOptions(filter="trilinear", wrap="repeat"),
                      source="<Suzanne>")
        ref_out = jaxnm.render(scene, outputs=("perturbed_normal", "position", "triangle_id",
                                                "mask", "front_facing", "uv", "duvdx",
                                                "duvdy"), frame="vertex")
        m, tri, bary, mv = _asset_pixels(ref_out, d)
        t_b, n_b, sgn = _interpolated_corners(d["tangents"], nrm[faces], d["signs"], tri, bary)
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


# --------------------------------------------------------------------------------------
# MikkTSpace decoding: where the bitangent is formed, and what is normalised
# --------------------------------------------------------------------------------------

#: The ways a renderer may decode a MikkTSpace map from per-corner unit tangents ``T_c``,
#: signs ``s_c`` and normals ``N_c``, each against the reference (the first): what
#: ``mikktspace.h`` prescribes ("unnormalized" interpolated ``T`` and ``N``,
#: ``B = sign cross(N, T)`` formed per fragment, only the result normalised) and Blender's
#: baker does (``RE_bake_normal_world_to_tangent``). "per vertex": ``B_c = s_c N_c x T_c``
#: formed at each corner and interpolated. "renormalised": after interpolation.
DECODINGS = ("B per fragment, nothing renormalised (reference)",
             "B per fragment, T renormalised",
             "B per fragment, N renormalised",
             "B per fragment, T and N renormalised",
             "B per vertex, nothing renormalised",
             "B per vertex, T, B and N renormalised",
             "B per fragment, T Gram-Schmidt to N, both renormalised")
#: The light of the shading comparison (directional, world space) and the Blinn-Phong
#: exponent: diffuse ``max(0, n . l)`` and specular ``max(0, n . h)^e``, in 8-bit levels.
DECODING_LIGHT = np.array([0.5, -1.5, 2.0]) / np.linalg.norm([0.5, -1.5, 2.0])
DECODING_SHININESS = 64


def decoding_frames(t_c, n_c, s_c, tri, bary) -> dict:
    """Per pixel, the frame ``(T, B, N)`` of every `DECODINGS` entry (float64), from corner
    tangents ``t_c`` (F, 3, 3), normals ``n_c`` (F, 3, 3), signs ``s_c`` (F, 3), the pixels'
    triangles ``tri`` and barycentric weights ``bary`` (P, 3)."""
    t, n, s = _interpolated_corners(t_c, n_c, s_c, tri, bary)
    b_c = s_c[..., None] * np.cross(n_c, t_c)  # (F, 3, 3): the bitangent at each corner
    b_v = np.einsum("pk,pkj->pj", bary, b_c[tri])
    tu, nu = _unit(t), _unit(n)
    gs = _unit(t - nu * np.sum(t * nu, -1, keepdims=True))
    frames = ((t, s * np.cross(n, t), n),
              (tu, s * np.cross(n, tu), n),
              (t, s * np.cross(nu, t), nu),
              (tu, s * np.cross(nu, tu), nu),
              (t, b_v, n),
              (tu, _unit(b_v), nu),
              (gs, s * np.cross(nu, gs), nu))
    return dict(zip(DECODINGS, frames))


def _shading(nrm, view_dir):
    h = _unit(DECODING_LIGHT + view_dir)
    diffuse = np.maximum(np.sum(nrm * DECODING_LIGHT, -1), 0.0)
    return diffuse, np.maximum(np.sum(nrm * h, -1), 0.0) ** DECODING_SHININESS


def decoding_records(frames, mv, view_dir, extra=None) -> list:
    """One record per decoding (and per ``extra`` perturbed normal, a name to (P, 3)): the
    angle of its perturbed normal for the sampled map values ``mv`` to the reference's
    (``error_*``), the worst over the hemisphere of map values (``worst_*``), and the
    difference of diffuse and specular shading under `DECODING_LIGHT` in 8-bit levels
    (``diffuse_*``, ``specular_*``: 255 times the absolute difference)."""
    ref = frames[DECODINGS[0]]
    ref_n = perturbed(*ref, mv)
    ref_d, ref_s = _shading(ref_n, view_dir)
    normals = {k: perturbed(*f, mv) for k, f in frames.items()}
    normals.update(extra or {})
    rows = []
    for name, pn in normals.items():
        rec = {"case": name, "pixels": len(mv)}
        _stats(rec, "error", angle(pn, ref_n))
        if name in frames:
            _stats(rec, "worst", frame_measures(*frames[name], *ref)[0])
        d, sp = _shading(pn, view_dir)
        _stats(rec, "diffuse", 255 * np.abs(d - ref_d))
        _stats(rec, "specular", 255 * np.abs(sp - ref_s))
        rows.append(rec)
    return rows


def mirrored_torus(segments=32):
    """The `Torus` with its u mirrored at phi = 0 and pi (``u -> 0.5 - |u - 0.5|``): the
    two halves share their texels, with opposite handedness."""
    t = Torus(segments)
    t.uv = np.stack([0.5 - np.abs(t.uv[:, 0] - 0.5), t.uv[:, 1]], -1)
    return t


def decoding(asset: Path | None, size: int, quick: bool = False) -> list:
    """`DECODINGS` against MikkTSpace's reference decoding (`decoding_records`), on the real
    asset with Blender's corner tangents and its baked map (trilinear), and on a torus with
    mirrored u (`mirrored_torus`, jaxnm's MikkTSpace tangents, the rivet map). Also jaxnm's
    own ``vertex`` frame, as rendered (float32), against the same reference."""
    cases = []
    if asset is not None:
        d = dict(np.load(asset))
        cases.append(("Suzanne", d, d["tangents"], d["signs"], _suzanne_camera()))
    torus = mirrored_torus(16 if quick else 32)
    t = mikktspace_tangents(torus.pos, torus.nrm, torus.uv, torus.faces)
    d = {"positions": torus.pos, "faces": torus.faces, "uv": torus.uv, "normals": torus.nrm,
         "image": _map_texels("rivets")}
    cases.append(("torus, mirrored u", d, t[..., :3], t[..., 3], _torus_camera()))
    rows = []
    for surface, d, tangents, signs, camera in cases:
        mesh = jaxnm.Mesh(jnp.asarray(d["positions"], jnp.float32),
                          jnp.asarray(d["faces"], jnp.int32), jnp.asarray(d["uv"], jnp.float32),
                          jnp.asarray(d["normals"], jnp.float32)).with_tangents()
        scene = Scene(mesh=mesh, camera=camera, width=size, height=size,
                      normal_map=jnp.asarray(d["image"], jnp.float32),
                      normal_map_options=NormalMapOptions(filter="trilinear", wrap="repeat"),
                      source="<frame study>")
        out = jaxnm.render(scene, outputs=("perturbed_normal", "position", "triangle_id",
                                            "mask", "front_facing", "uv", "duvdx", "duvdy"),
                           frame="vertex")
        m, tri, bary, mv = _asset_pixels(out, d)
        frames = decoding_frames(tangents, d["normals"][d["faces"]], signs, tri, bary)
        view_dir = _unit(np.asarray(camera.eye, np.float64)
                         - np.asarray(out["position"], np.float64)[m])
        jax_n = np.asarray(out["perturbed_normal"], np.float64)[m]
        recs = decoding_records(frames, mv, view_dir, {"jaxnm vertex (float32 render)": jax_n})
        for r in recs:
            r.update(sweep="decoding", surface=surface, method="vertex", size=size,
                     map="baked" if surface == "Suzanne" else "rivets")
        rows += recs
        jax.clear_caches()
    return rows


# --------------------------------------------------------------------------------------
# half precision far from the origin: world positions against camera-relative ones
# --------------------------------------------------------------------------------------


def _schuler(n, dp1, dp2, duv1, duv2):
    """Schüler's frame (float64, max-normalised) from y-up screen differences."""
    perp2, perp1 = np.cross(dp2, n), np.cross(n, dp1)
    t = perp2 * duv1[:, :1] + perp1 * duv2[:, :1]
    b = perp2 * duv1[:, 1:] + perp1 * duv2[:, 1:]
    s = np.sqrt(np.maximum(np.maximum(np.sum(t * t, -1), np.sum(b * b, -1)), 1e-300))
    return t / s[:, None], b / s[:, None]


def far_from_origin(size, offsets=(0.0, 10.0, 100.0), distances=(3, 0.3, 0.03, 0.003)):
    """The cotangent frame from fine differences of positions rounded to the shader's
    precision, where the position is the world position (the plane moved ``offset`` along
    x, the camera with it) or the camera-relative one (jaxnm's, Schüler's ``-V``).

    A model, not a render: jaxnm renders the plane (sheared 30 deg uv, 60 deg view and
    field of view) and returns its camera-relative position and uv per pixel in float32;
    the world position is that plus the eye in float64. Each is rounded to ``precision``
    (float32 or float16), and each fully covered 2x2 quad's lower-left pixel takes the
    quad's differences (``dFdx``, ``dFdy`` up), then Schüler's frame in float64 with the
    plane's exact normal, against the gradient truth."""
    plane = Plane(UV_LAYOUTS["sheared 30 deg"])
    (tg, bg), _, _ = truth_frames(*plane.frame_at(np.zeros((1, 3))))
    n = np.array([[0.0, 0.0, 1.0]])
    want = perturbed(tg, bg, n)
    base = 1.15 / math.tan(math.radians(30))
    rows = []
    for off in offsets:
        moved = Plane(plane.a)
        moved.pos = plane.pos + [off, 0.0, 0.0]
        for f in distances:
            cam = _camera(60, 60, target=(off, 0.0, 0.0), dist=f * base)
            scene = Scene(mesh=_mesh(moved), camera=cam, width=size, height=size,
                          source="<frame study>")
            out = jaxnm.render(scene, outputs=("view", "uv", "mask"))
            mask = np.asarray(out["mask"])[..., 0] > 0
            quad = mask.reshape(size // 2, 2, size // 2, 2).all((1, 3))
            view = np.asarray(out["view"], np.float64)
            world = view + np.asarray(cam.eye, np.float64)
            for case, pos in (("world position", world), ("camera-relative position", view)):
                for precision in ("float32", "float16"):
                    def q(x):  # rounded, then the quad's lower-left pixel's differences
                        x = x.astype(precision).astype(np.float64)
                        x = x.reshape(size // 2, 2, size // 2, 2, -1).transpose(0, 2, 1, 3, 4)
                        x = x[quad]  # (quads, row, column, channel), row 0 on top
                        return x[:, 1, 1] - x[:, 1, 0], x[:, 0, 0] - x[:, 1, 0]
                    (dp1, dp2), (duv1, duv2) = q(pos), q(np.asarray(out["uv"]))
                    t, b = _schuler(n, dp1, dp2, duv1, duv2)
                    rec = {"sweep": "precision", "case": case, "offset": off, "distance": f,
                           "precision": precision, "method": "cotangent", "mode": "fine",
                           "surface": "plane", "uv": "sheared 30 deg", "fov": 60, "view": 60,
                           "pixels": int(quad.sum())}
                    _stats(rec, "error", angle(perturbed(t, b, n), want))
                    rows.append(rec)
    return rows


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
          "conventions", "real", "decoding", "precision", "tessellation")
#: The default run (the two long ones, precision and tessellation, on request).
DEFAULT_SWEEPS = SWEEPS[:-2]
#: The derivative modes of the fov, view-angle and distance sweeps.
SWEEP_MODES = ("fine", "coarse", "analytic")
#: The screen-space frames the convention sweep feeds HLSL's ddy to.
DDY_METHODS = ("cotangent", "nonperspective", "gram_schmidt", "separate", "cross",
               "surface_gradient")
#: The frames of the orthographic sweep.
ORTHO_METHODS = ("cotangent", "nonperspective", "cross", "exact")
#: The frames of the real asset at its smaller sizes (every frame at the largest).
REAL_METHODS = ("cotangent", "nonperspective", "vertex", "cross", "surface_gradient")
#: ``--quick``: these frames, fine derivatives, two or three points per sweep (a smoke test
#: of every sweep; its numbers are not the document's).
QUICK_METHODS = ("cotangent", "nonperspective", "vertex", "surface_gradient")


def sweeps(size: int, quick: bool, only=DEFAULT_SWEEPS, asset: Path | None = None,
           real_sizes=(256, 1024), time_size=-1) -> tuple[list, dict]:
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
                                time_size=0 if quick else time_size, keep_maps=True)
        rows.extend(recs)
        maps.update({f"real_{k}": v for k, v in rmaps.items()})
        forget()
    if "decoding" in only:
        rows.extend(decoding(asset, 128 if quick else 512, quick))
        print(json.dumps({"sweep": "decoding", "records": len(DECODINGS) + 1}), flush=True)
        forget()
    if "precision" in only:  # shader precision against the camera distance (close-ups)
        # the plane and the torus padded to one shape, both with the rivet map: one program
        # per frame and precision for both; the analytic derivatives for Schüler's frame
        pplane, ptorus = padded_all([plane, Torus(32)])
        for precision in ("float32", "float16", "bfloat16"):
            for f in ((0.01, 1) if quick else (0.003, 0.03, 0.3, 3)):
                recs = measure(pplane, _camera(60, 60, dist=f * base), size, methods,
                               normal_map="rivets", precision=precision)
                recs += measure(pplane, _camera(60, 60, dist=f * base), size, pick(
                    ("cotangent",)), modes=("analytic",), normal_map="rivets",
                    precision=precision)
                tag(recs, sweep="precision", fov=60, view=60, distance=f, surface="plane",
                    uv="sheared 30 deg", map="rivets")
            tag(measure(ptorus, _torus_camera(), size, methods, modes=("fine",),
                        normal_map="rivets", precision=precision),
                sweep="precision", surface="torus", segments=32, normals="smooth",
                uv="surface", map="rivets")
            forget()
        recs = far_from_origin(size, distances=(0.01, 1) if quick else (0.003, 0.03, 0.3, 3))
        rows.extend(recs)
        print(json.dumps({"sweep": "precision", "case": "far from the origin",
                          "records": len(recs)}), flush=True)
        forget()
    if "tessellation" in only:
        # every surface, both normals, padded to one shape: one program per frame
        cases = [(name, seg, normals) for seg in ((8, 32) if quick else (8, 16, 32, 64))
                 for name in ("torus", "sphere", "cylinder") for normals in ("smooth", "flat")]
        make = {"torus": Torus, "sphere": Sphere, "cylinder": Cylinder}
        surfs = [make[name](seg) for name, seg, _ in cases]
        surfs = padded_all([s if normals == "smooth" else flat_shaded(s)
                            for s, (_, _, normals) in zip(surfs, cases)])
        for (name, seg, normals), s in zip(cases, surfs):
            target = (1.4, 0.0, 0.0) if name == "torus" else (0.7, 0.0, 0.0)
            cam = Camera.from_matrices(
                look_at(np.array(target) + [2.6, -1.4, 1.6], target, (0, 0, 1)),
                perspective(40, 1.0, 0.05, 50))
            tag(measure(s, cam, size, methods=methods), sweep="tessellation", surface=name,
                segments=seg, normals=normals, uv="surface")
        forget()
    return rows, maps


#: Each frame method's colour and marker in every figure (no two share either).
METHOD_STYLE = {
    "cotangent": ("#1f77b4", "o"), "cotangent_unnormalized": ("#aec7e8", "s"),
    "nonperspective": ("#d62728", "^"), "exact": ("#2ca02c", "v"),
    "exact_face": ("#98df8a", "D"), "vertex": ("#000000", "P"),
    "vertex_area": ("#7f7f7f", "X"), "axis": ("#8c564b", "*"),
    "gram_schmidt": ("#ff7f0e", "h"), "separate": ("#ffbb78", "<"),
    "cross": ("#9467bd", ">"), "surface_gradient": ("#e377c2", "p"),
}
#: The figures `plot_figures` writes, by file name: what each shows.
FIGURES = {
    "frames_fov.png": "fixed map value's mean error and hemisphere's p95 against the fov",
    "frames_view_angle.png": "the same against the view angle",
    "frames_distance.png": "the same against the camera distance",
    "frames_orthographic.png": "mean error against the tilt under an orthographic camera",
    "frames_uv.png": "mean error per uv layout",
    "frames_real_cost.png": "cost against error on Suzanne",
    "frames_decoding.png": "MikkTSpace decodings against the reference",
    "frames_precision.png": "hemisphere's worst against the distance per precision",
    "frames_tessellation.png": "mean error against the segments of curved meshes",
}
#: The command that draws the figures of the frames page from its data file.
FIGURES_COMMAND = ("python -m scripts.studies.study_frames --figures "
                   "docs/studies/data/frames_summary.json --out docs/img")


def _style(method):
    color, marker = METHOD_STYLE[method]
    return {"color": color, "marker": marker}


def _floor(v, lo=1e-6):
    return max(v, lo) if v is not None else np.nan


def plot_figures(rows, out: Path) -> list:
    """Every figure of `FIGURES` whose sweep is in ``rows`` (run records, or the rows of a
    summary, `summary_rows`) into ``out``; returns the file names written. Each frame method
    keeps its `METHOD_STYLE` in every figure."""
    try:
        from matplotlib.figure import Figure
    except ImportError:
        print("matplotlib missing: no plots (pip install '.[notebook]')")
        return []
    out = Path(out)
    written = []

    def save(fig, name):
        fig.tight_layout()
        fig.savefig(out / name)
        written.append(name)

    def sel(**kw):
        return [r for r in rows if all(r.get(k) == v for k, v in kw.items())]

    for sweep, key, name, xlabel in (("fov", "fov", "frames_fov.png", "field of view (deg)"),
                                     ("view angle", "view", "frames_view_angle.png",
                                      "view angle from the normal (deg)"),
                                     ("distance", "distance", "frames_distance.png",
                                      "camera distance / distance that frames the plane")):
        if not sel(sweep=sweep):
            continue
        fig = Figure(figsize=(10, 4.2), dpi=80)
        for k, (stat, label) in enumerate((("error_mean", "mean error, the fixed map value"),
                                           ("worst_p95", "p95 of the worst over the "
                                            "hemisphere"))):
            ax = fig.add_subplot(1, 2, k + 1)
            for method in METHOD_STYLE:
                for mode, ls in (("fine", "-"), ("coarse", ":"), ("analytic", "--")):
                    pts = sorted((r[key], _floor(r[stat])) for r in
                                 sel(sweep=sweep, method=method, mode=mode))
                    if pts:
                        plot = ax.loglog if sweep == "distance" else ax.semilogy
                        plot(*zip(*pts), ls=ls, ms=4, mfc="none", **_style(method),
                             label=method if mode == "fine" else None)
            ax.set(xlabel=xlabel, ylabel=f"{label} (deg)",
                   title=f"{sweep}: solid fine, dotted coarse, dashed analytic")
            if k == 0:
                ax.legend(fontsize=6, ncol=2)
        save(fig, name)
    ortho = sel(sweep="orthographic")
    if ortho:
        fig = Figure(figsize=(6.5, 4), dpi=80)
        ax = fig.add_subplot()
        for method in METHOD_STYLE:
            for uv, ls in (("orthogonal", "-"), ("sheared 30 deg", "--")):
                pts = sorted((r["view"], _floor(r["error_mean"]), r.get("predicted"))
                             for r in ortho if r["method"] == method and r["uv"] == uv)
                if not pts:
                    continue
                ax.semilogy([x for x, _, _ in pts], [y for _, y, _ in pts], ls=ls,
                            **_style(method), mfc="none", label=f"{method}, {uv} uv")
                if method == "nonperspective":
                    ax.semilogy([x for x, _, _ in pts], [_floor(z) for _, _, z in pts], "k:",
                                lw=1)
        ax.set(xlabel="tilt of the plane from the image plane (deg)",
               ylabel="mean error vs own truth (deg)",
               title="orthographic camera (dotted black: closed form)")
        ax.legend(fontsize=6)
        save(fig, "frames_orthographic.png")
    uvrows = sel(sweep="uv")
    if uvrows:
        fig = Figure(figsize=(9, 4), dpi=80)
        ax = fig.add_subplot()
        layouts = list(UV_LAYOUTS)
        methods = [m for m in METHOD_STYLE if sel(sweep="uv", method=m)]
        w = 0.8 / len(methods)
        for k, method in enumerate(methods):
            vals = [next((_floor(r["error_mean"]) for r in sel(sweep="uv", uv=u, method=method)),
                         np.nan) for u in layouts]
            x = np.arange(len(layouts)) + w * k
            color, marker = METHOD_STYLE[method]
            ax.bar(x, vals, w, color=color, label=method)
            ax.plot(x, vals, ls="none", marker=marker, color="k", ms=3)
        ax.set_yscale("log")
        ax.set_xticks(np.arange(len(layouts)) + 0.4, layouts, fontsize=7)
        ax.set(ylabel="mean error vs own truth (deg)", title="uv layout")
        ax.legend(fontsize=6, ncol=2)
        save(fig, "frames_uv.png")
    real = [r for r in sel(sweep="real") if r.get("frame_ms") is not None]
    if real:
        big = max(r["size"] for r in real)
        fig = Figure(figsize=(6.5, 4.2), dpi=80)
        ax = fig.add_subplot()
        for r in (x for x in real if x["size"] == big):
            xy = (_floor(r["frame_ms"], 0.01), _floor(r["error_mean"], 1e-5))
            ax.scatter(*xy, s=30, **_style(r["method"]), label=r["method"])
        ax.set(xscale="log", yscale="log", xlabel=f"frame's cost at {big}x{big} (ms, above "
               "'none')", ylabel="mean angle to Blender's decode (deg)",
               title="Suzanne, baked map, trilinear")
        ax.legend(fontsize=6, ncol=2)
        save(fig, "frames_real_cost.png")
    dec = sel(sweep="decoding")
    if dec:
        surfaces = list(dict.fromkeys(r["surface"] for r in dec))
        names = list(dict.fromkeys(r["case"] for r in dec))
        fig = Figure(figsize=(9, 4.2), dpi=80)
        for k, (stat, label) in enumerate((("error_mean", "mean angle (deg)"),
                                           ("error_max", "max angle (deg)"),
                                           ("specular_max", "max specular (8-bit levels)"))):
            ax = fig.add_subplot(1, 3, k + 1)
            for j, surface in enumerate(surfaces):
                vals = [next((_floor(r[stat]) for r in dec if r["surface"] == surface
                              and r["case"] == c), np.nan) for c in names]
                ax.barh(np.arange(len(names)) + 0.4 * j, vals, 0.4, label=surface,
                        color=("#1f77b4", "#ff7f0e")[j % 2])
            ax.set_xscale("log")
            ax.set_yticks(np.arange(len(names)) + 0.2,
                          names if k == 0 else [""] * len(names), fontsize=6)
            ax.set(xlabel=label)
            if k == 0:
                ax.legend(fontsize=6)
        fig.suptitle("decoding a MikkTSpace map, against the reference (B per fragment, "
                     "nothing renormalised)", fontsize=9)
        save(fig, "frames_decoding.png")
    prec = [r for r in sel(sweep="precision", surface="plane") if r.get("case") is None]
    if prec:
        fig = Figure(figsize=(11, 4), dpi=80)
        for k, precision in enumerate(("float32", "float16", "bfloat16")):
            ax = fig.add_subplot(1, 3, k + 1)
            for method in METHOD_STYLE:
                for mode, ls in (("fine", "-"), ("analytic", "--")):
                    pts = sorted((r["distance"], _floor(r["worst_mean"])) for r in prec
                                 if r["method"] == method and r["mode"] == mode
                                 and r["precision"] == precision)
                    if pts:
                        ax.loglog(*zip(*pts), ls=ls, ms=4, mfc="none", **_style(method),
                                  label=method if mode == "fine" else None)
            ax.set(xlabel="camera distance / distance that frames the plane",
                   ylabel="worst over the hemisphere, mean (deg)",
                   title=f"{precision}: solid fine, dashed analytic")
            if k == 0:
                ax.legend(fontsize=5, ncol=2)
        save(fig, "frames_precision.png")
    tess = sel(sweep="tessellation")
    if tess:
        fig = Figure(figsize=(12, 7), dpi=72)
        for i, normals in enumerate(("smooth", "flat")):
            for j, surf in enumerate(("torus", "sphere", "cylinder")):
                ax = fig.add_subplot(2, 3, 3 * i + j + 1)
                for method in METHOD_STYLE:
                    pts = sorted((r["segments"], _floor(r["error_mean"])) for r in tess
                                 if r["surface"] == surf and r["normals"] == normals
                                 and r["method"] == method)
                    if pts:
                        ax.loglog(*zip(*pts), ms=4, mfc="none", **_style(method),
                                  label=method)
                ax.set(xlabel="segments", ylabel="mean error vs smooth truth (deg)",
                       title=f"{surf}, {normals} normals")
                segs = sorted({r["segments"] for r in tess})
                ax.set_xticks(segs, [str(x) for x in segs])
                ax.set_xticks([], minor=True)
                if i == 0 and j == 0:
                    ax.legend(fontsize=5, ncol=2)
        save(fig, "frames_tessellation.png")
    return written


def update_summary(old: dict, new: dict, sweeps) -> dict:
    """``old`` (a summary) with the rows of ``sweeps`` replaced by ``new``'s. The metadata
    becomes ``{"runs": [...]}``: each run's metadata with the ``sweeps`` whose rows it gave."""
    meta = old["metadata"]
    runs = meta["runs"] if "runs" in meta else [
        dict(meta, sweeps=list(dict.fromkeys(r["sweep"] for r in summary_rows(old))))]
    runs = [dict(r, sweeps=[x for x in r["sweeps"] if x not in sweeps]) for r in runs]
    runs = [r for r in runs if r["sweeps"]]
    kept = [r for r in summary_rows(old) if r["sweep"] not in sweeps] + summary_rows(new)
    runs.append(dict(new["metadata"], sweeps=list(dict.fromkeys(
        r["sweep"] for r in summary_rows(new)))))
    cols = list(dict.fromkeys(old["columns"] + new["columns"]))
    return {"metadata": {"runs": runs}, "columns": cols,
            "rows": [[r.get(k) for k in cols] for r in kept]}


def summary_rows(data: dict) -> list:
    """The records of a summary (`summary`) as dicts, without the fields a record lacked."""
    cols = data["columns"]
    return [{k: v for k, v in zip(cols, row) if v is not None} for row in data["rows"]]


def summary(rows, meta) -> dict:
    """The rows behind the document's tables, with only the columns they show, as a table
    (``columns``, and ``rows`` of values, None where a record has no such field; numbers
    to 4 significant digits): small enough to keep beside the document."""
    keep = ("sweep", "case", "method", "mode", "convention", "fov", "view", "distance", "uv",
            "surface", "camera", "map", "precision", "segments", "normals", "offset", "size",
            "pixels", "predicted", "ddy", "above_5deg", "sign_mismatches", "ms", "frame_ms")
    stats = [f"{k}_{q}" for k in ("error", "gradient", "orthonormal", "worst", "other_worst",
                                  "diffuse", "specular") for q in ("mean", "p95", "max")]
    stats += ["T_mean"]
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
    ap.add_argument("--real-sizes", default="256,1024",
                    help="image sizes of the real asset (timed at the largest)")
    ap.add_argument("--time-size", type=int, default=-1,
                    help="the real-asset size whose renders are timed (default: the largest)")
    ap.add_argument("--update", default=None, metavar="SUMMARY",
                    help="also replace this run's sweeps in a summary file (e.g. "
                    "docs/studies/data/frames_summary.json), keeping the other sweeps' rows "
                    "and the metadata of the runs they came from")
    ap.add_argument("--figures", default=None, metavar="SUMMARY",
                    help="only draw the figures from a summary file (frames_summary.json, "
                    "e.g. docs/studies/data/frames_summary.json) into --out; runs nothing")
    args = ap.parse_args(argv)
    output("--out", args.out, folder=True)  # before the work
    if args.figures:
        out = Path(args.out)
        out.mkdir(parents=True, exist_ok=True)
        data = json.loads(Path(args.figures).read_text())
        names = plot_figures(summary_rows(data), out)
        print(f"wrote {', '.join(names)} into {out}")
        return
    if args.size is None:
        args.size = 32 if args.quick else 128
    only = SWEEPS if args.sweeps == "all" else tuple(x.strip() for x in args.sweeps.split(","))
    if bad := [x for x in only if x not in SWEEPS]:
        ap.error(f"--sweeps: unknown {bad}; expected any of {', '.join(SWEEPS)}")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    t0, c0 = time.perf_counter(), time.process_time()
    asset = None
    if "real" in only or "decoding" in only:
        asset = Path(args.asset) if args.asset else bake_asset(out / "suzanne.npz")
        if asset is None:
            print("no Blender environment: the real asset is left out")
    rows, maps = sweeps(args.size, args.quick, only, asset=asset,
                        real_sizes=tuple(int(x) for x in args.real_sizes.split(",")),
                        time_size=args.time_size)
    meta = metadata(time.perf_counter() - t0, sys.argv[1:] if argv is None else argv)
    meta["cpu_s"] = round(time.process_time() - c0, 1)
    # the figures from the summary, exactly as --figures draws them from the data file
    plot_figures(summary_rows(summary(rows, meta)), out)
    for family, title in (("real", "Suzanne"), ("torus", "torus")):
        fam = {k.split("_", 1)[1]: v for k, v in maps.items() if k.startswith(family + "_")}
        if fam:
            _error_maps(fam, out / f"frames_{family}_error_maps.png", title)
    (out / "frames.json").write_text(json.dumps({"metadata": meta, "rows": rows}, indent=1)
                                     + "\n")
    (out / "frames_summary.json").write_text(json.dumps(summary(rows, meta)) + "\n")
    if args.update:
        path = Path(args.update)
        data = update_summary(json.loads(path.read_text()), summary(rows, meta), only)
        path.write_text(json.dumps(data) + "\n")
    keys = sorted({k for r in rows for k in r})
    with open(out / "frames.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=keys)
        w.writeheader()
        w.writerows(rows)
    print(f"wrote {out} in {meta['run_s']:.0f} s")


if __name__ == "__main__":
    sys.exit(run_script(main))
