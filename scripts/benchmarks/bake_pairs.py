"""High-poly / low-poly mesh pairs for ray-cast baking, built in NumPy (and, for Suzanne,
by Blender), deterministic: the torus pair of `bench_bake` and of the tests against
Blender, and the helpers that turn a modeller's mesh (welded vertices, a uv per face
corner) into a `jaxnm.Mesh` and into the arrays `tests/blender_ref.py` rebuilds in Blender.

A pair is a dict: ``hi_positions``, ``hi_faces`` (welded, smooth), ``lo_positions``,
``lo_faces`` (welded) and ``lo_corner_uv`` (F, 3, 2).
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

import jaxnm

__all__ = ["torus_pair", "displaced", "angle_normals", "low_mesh", "high_mesh", "suzanne_pair",
           "suzanne_height"]


def _grid(n: int, m: int) -> np.ndarray:
    """Triangles of an n x m grid of quads that wraps in both directions (vertex j * n + i)."""
    j, i = np.meshgrid(np.arange(m), np.arange(n), indexing="ij")
    a = j * n + i
    b = j * n + (i + 1) % n
    c = ((j + 1) % m) * n + (i + 1) % n
    d = ((j + 1) % m) * n + i
    return np.concatenate([np.stack([a, b, c], -1), np.stack([a, c, d], -1)]).reshape(-1, 3)


def _torus_points(s, t, radius, tube, h=0.0):
    """Points of a torus about z at parameters s (major) and t (minor) in [0, 1), the tube
    radius displaced by ``h`` along the tube's normal."""
    a, b = 2 * np.pi * s, 2 * np.pi * t
    r = tube + h
    return np.stack([(radius + r * np.cos(b)) * np.cos(a), (radius + r * np.cos(b)) * np.sin(a),
                     r * np.sin(b)], -1)


def torus_height(s, t, amplitude=0.025):
    """The detail: mirror-symmetric in s about 0 and 1/2 (so a mirrored uv layout suits it)
    and periodic in both."""
    return amplitude * (np.cos(2 * np.pi * 3 * s) * np.cos(2 * np.pi * 2 * t)
                        + 0.6 * np.cos(2 * np.pi * 5 * s) * np.sin(2 * np.pi * t + 0.4))


def torus_pair(lo_n=(48, 24), hi_n=(384, 192), *, mirrored=True, radius=1.0, tube=0.35,
               margin=0.05):
    """A displaced torus (``hi_n`` quads, two triangles each) over a plain one (``lo_n``),
    with the low-poly uv layout in ``[margin, 1 - margin]^2``: u along the major circle,
    mirrored about s = 1/2 when ``mirrored`` (both halves share the texels), v around the
    tube, with a uv seam where the tube's angle wraps."""
    n, m = lo_n
    s, t = np.meshgrid(np.arange(n) / n, np.arange(m) / m, indexing="xy")
    lo_pos = _torus_points(s.ravel(), t.ravel(), radius, tube)
    lo_faces = _grid(n, m)
    # per corner uv, unwrapped: a corner's (s, t) from its position in the grid quad
    j, i = np.divmod(lo_faces, n)
    s_c, t_c = i / n, j / m
    first = lo_faces[:, :1]
    jf, if_ = np.divmod(first, n)
    s_c = np.where(i < if_, s_c + 1, s_c)  # the quad that wraps in s
    t_c = np.where(j < jf, t_c + 1, t_c)
    u = 1 - np.abs(2 * s_c - 1) if mirrored else s_c
    uv = margin + (1 - 2 * margin) * np.stack([u, t_c], -1)
    n2, m2 = hi_n
    s, t = np.meshgrid(np.arange(n2) / n2, np.arange(m2) / m2, indexing="xy")
    hi_pos = _torus_points(s.ravel(), t.ravel(), radius, tube, torus_height(s.ravel(), t.ravel()))
    return dict(hi_positions=hi_pos, hi_faces=_grid(n2, m2), lo_positions=lo_pos,
                lo_faces=lo_faces, lo_corner_uv=uv)


def angle_normals(positions: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Angle-weighted vertex normals in float64 (Blender's vertex normals)."""
    p = positions[faces]
    cross = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    unit = cross / np.maximum(np.linalg.norm(cross, axis=-1, keepdims=True), 1e-300)
    acc = np.zeros_like(positions)
    for k in range(3):
        e1 = p[:, (k + 1) % 3] - p[:, k]
        e2 = p[:, (k + 2) % 3] - p[:, k]
        cos = np.sum(e1 * e2, -1) / np.maximum(
            np.linalg.norm(e1, axis=-1) * np.linalg.norm(e2, axis=-1), 1e-300)
        np.add.at(acc, faces[:, k], unit * np.arccos(np.clip(cos, -1, 1))[:, None])
    return acc / np.maximum(np.linalg.norm(acc, axis=-1, keepdims=True), 1e-300)


def displaced(positions: np.ndarray, faces: np.ndarray, height) -> np.ndarray:
    """``positions`` moved along their angle-weighted normals by ``height(positions)``."""
    return positions + height(positions)[:, None] * angle_normals(positions, faces)


def low_mesh(pair: dict, positions_key: str = "lo_positions") -> jaxnm.Mesh:
    """The low-poly mesh of ``pair`` as a `jaxnm.Mesh`: one vertex per distinct (welded
    vertex, uv), with the welded mesh's angle-weighted normals (so seams split nothing
    but the uvs); ``positions_key`` picks other positions of the same triangles (a cage)."""
    faces = np.asarray(pair["lo_faces"])
    uv = np.asarray(pair["lo_corner_uv"], np.float64).reshape(-1, 2)
    key = np.concatenate([faces.reshape(-1, 1).astype(np.float64), uv], 1)
    _, first, inverse = np.unique(key, axis=0, return_index=True, return_inverse=True)
    vert = faces.reshape(-1)[first]
    pos = np.asarray(pair[positions_key], np.float64)
    normals = angle_normals(pos, faces)[vert]
    return jaxnm.Mesh(jnp.asarray(pos[vert], jnp.float32),
                      jnp.asarray(inverse.reshape(-1, 3), jnp.int32),
                      jnp.asarray(uv[first], jnp.float32), jnp.asarray(normals, jnp.float32))


def high_mesh(pair: dict) -> jaxnm.Mesh:
    """The high-poly mesh of ``pair`` with its angle-weighted vertex normals."""
    pos = np.asarray(pair["hi_positions"], np.float64)
    faces = np.asarray(pair["hi_faces"])
    return jaxnm.Mesh(jnp.asarray(pos, jnp.float32), jnp.asarray(faces, jnp.int32), None,
                      jnp.asarray(angle_normals(pos, faces), jnp.float32))


def suzanne_height(p: np.ndarray) -> np.ndarray:
    """The detail the Suzanne pair adds to the subdivided head (0.02 at most)."""
    return 0.02 * np.sin(9 * p[:, 0]) * np.sin(8 * p[:, 1] + 0.5) * np.sin(7 * p[:, 2] + 1)


def suzanne_pair(blender: str, levels: int = 3) -> dict:
    """Blender's Suzanne (LOW, its own uvs) and the same head subdivided ``levels`` times
    (Catmull-Clark) and displaced by `suzanne_height` along its normals (HIGH), built by
    ``tests/blender_ref.py suzanne`` in Blender's Python ``blender``."""
    import subprocess
    import tempfile
    from pathlib import Path

    root = Path(__file__).resolve().parents[2]
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "suzanne.npz"
        run = subprocess.run([blender, str(root / "tests" / "blender_ref.py"), "suzanne",
                              str(levels), str(out)], capture_output=True, text=True)
        if run.returncode != 0:
            raise RuntimeError(f"Blender failed: {run.stderr[-2000:]}")
        s = dict(np.load(out))
    return dict(hi_positions=displaced(s["sub_positions"], s["sub_faces"], suzanne_height),
                hi_faces=s["sub_faces"], lo_positions=s["positions"], lo_faces=s["faces"],
                lo_corner_uv=s["corner_uv"])
