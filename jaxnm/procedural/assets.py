"""Procedural assets generated in code (no downloads): meshes with uvs and normal maps.

The built-in default scene is a torus with angle uvs (u around the ring, v around
the tube, both in [0, 1] with duplicated seam vertices) and a normal map of
rounded rivets and grooves derived analytically from a height field.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from ..geometry import Mesh
from ..maps import height_to_normal_map
from ..textures import encode_normal_map, quantize

__all__ = ["torus", "default_torus", "plane", "uv_sphere", "rivet_height", "default_normal_map",
           "default_normal_map_texels", "RIVET_STRENGTH", "BUILTIN_MESHES", "builtin_mesh"]


def torus(major_radius: float = 1.0, minor_radius: float = 0.4, major_segments: int = 96,
          minor_segments: int = 48, *, uv_scale: tuple[float, float] = (1.0, 1.0)) -> Mesh:
    """A torus around the z axis with angle uvs and analytic unit normals.

    ``u = phi / 2 pi`` (angle around the z axis, counter-clockwise seen from +z),
    ``v = theta / 2 pi`` (angle around the tube, 0 on the outer equator, moving
    towards +z first), each multiplied by ``uv_scale``. Seam vertices are
    duplicated so uvs are continuous on every triangle.
    ``2 * major_segments * minor_segments`` triangles, CCW seen
    from outside.
    """
    i = np.arange(major_segments + 1)
    j = np.arange(minor_segments + 1)
    phi = 2 * np.pi * i / major_segments
    theta = 2 * np.pi * j / minor_segments
    P, T = np.meshgrid(phi, theta, indexing="ij")  # (I+1, J+1)
    ring = major_radius + minor_radius * np.cos(T)
    pos = np.stack([ring * np.cos(P), ring * np.sin(P), minor_radius * np.sin(T)], -1)
    nrm = np.stack([np.cos(T) * np.cos(P), np.cos(T) * np.sin(P), np.sin(T)], -1)
    uv = np.stack([P / (2 * np.pi) * uv_scale[0], T / (2 * np.pi) * uv_scale[1]], -1)
    n_j = minor_segments + 1
    a = (i[:-1, None] * n_j + j[None, :-1]).ravel()
    b = a + n_j  # next phi
    c = b + 1  # next phi, next theta
    d = a + 1  # next theta
    # orientation: d(pos)/d(phi) x d(pos)/d(theta) points outwards -> (a, b, c) is CCW
    faces = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    return _mesh(pos.reshape(-1, 3), faces, uv.reshape(-1, 2), nrm.reshape(-1, 3))


def default_torus() -> Mesh:
    """The built-in scene's torus: radii 1 and 0.42, 128 x 64 segments (16384 triangles),
    the rivet map tiled three times around the ring (``uv_scale=(3, 1)``)."""
    return torus(1.0, 0.42, 128, 64, uv_scale=(3.0, 1.0))


def plane(size: float = 2.0, segments: int = 1, *, uv_scale: float = 1.0) -> Mesh:
    """A square in the z = 0 plane facing +z, uv = (x, y) / size + 1/2 (times ``uv_scale``)."""
    t = np.linspace(-size / 2, size / 2, segments + 1)
    x, y = np.meshgrid(t, t, indexing="xy")
    pos = np.stack([x.ravel(), y.ravel(), np.zeros(x.size)], 1)
    uv = (pos[:, :2] / size + 0.5) * uv_scale
    n = segments + 1
    ii, jj = np.meshgrid(np.arange(segments), np.arange(segments), indexing="xy")
    a = (jj * n + ii).ravel()
    faces = np.concatenate([np.stack([a, a + 1, a + n + 1], 1), np.stack([a, a + n + 1, a + n], 1)])
    nrm = np.tile([0.0, 0.0, 1.0], (len(pos), 1))
    return _mesh(pos, faces, uv, nrm)


def uv_sphere(radius: float = 1.0, segments: int = 64, rings: int = 32) -> Mesh:
    """A latitude-longitude sphere: ``u = longitude / 2 pi``, ``v = latitude / pi + 1/2``."""
    lon = 2 * np.pi * np.arange(segments + 1) / segments
    lat = np.pi * (np.arange(rings + 1) / rings - 0.5)
    L, B = np.meshgrid(lon, lat, indexing="ij")
    nrm = np.stack([np.cos(B) * np.cos(L), np.cos(B) * np.sin(L), np.sin(B)], -1)
    uv = np.stack([L / (2 * np.pi), B / np.pi + 0.5], -1)
    n_j = rings + 1
    i = np.arange(segments)
    j = np.arange(rings)
    a = (i[:, None] * n_j + j[None, :]).ravel()
    b, c, d = a + n_j, a + n_j + 1, a + 1
    faces = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    # drop the zero-area triangles at the poles
    pos = (radius * nrm).reshape(-1, 3)
    p = pos[faces]
    area = np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1)
    return _mesh(pos, faces[area > 1e-12 * radius**2], uv.reshape(-1, 2), nrm.reshape(-1, 3))


def _mesh(pos, faces, uv, nrm) -> Mesh:
    return Mesh(jnp.asarray(pos, jnp.float32), jnp.asarray(faces, jnp.int32),
                jnp.asarray(uv, jnp.float32), jnp.asarray(nrm, jnp.float32))


def rivet_height(size: int = 256, *, cells: int = 8, groove: float = 0.08) -> np.ndarray:
    """A tileable height field (H, W) in [0, 1]: rounded rivets in a grid with grooves.

    Image layout (row 0 = top = v near 1). Periodic in both directions, so it
    tiles seamlessly with ``wrap="repeat"``.
    """
    t = (np.arange(size) + 0.5) / size
    u, v = np.meshgrid(t, 1.0 - t, indexing="xy")  # v measured upwards
    fu, fv = (u * cells) % 1.0 - 0.5, (v * cells) % 1.0 - 0.5
    r = np.sqrt(fu**2 + fv**2)
    rivet = np.clip(1 - (r / 0.3) ** 2, 0, None) ** 1.5
    # grooves along the cell borders, smooth V profile
    edge = 0.5 - np.maximum(np.abs(fu), np.abs(fv))
    grooves = np.clip(edge / groove, 0, 1)
    grooves = grooves * grooves * (3 - 2 * grooves)
    return (0.35 * grooves + 0.65 * rivet * grooves).astype(np.float32)


#: Bumpiness of the built-in rivet map (height units per texel, see `height_to_normal_map`).
RIVET_STRENGTH = 24.0


def default_normal_map(size: int = 256) -> np.ndarray:
    """The built-in scene's tangent-space normal map: decoded unit vectors (size, size, 3)
    ("green up", image layout), from `rivet_height` by `jaxnm.maps.height_to_normal_map`."""
    return np.asarray(height_to_normal_map(rivet_height(size), scale=RIVET_STRENGTH))


def default_normal_map_texels(size: int = 256, bits: int = 8) -> np.ndarray:
    """`default_normal_map` as a ``bits``-bit unsigned image stores it: floats in [0, 1] on the
    ``2^bits`` codes (what ``builtin:rivets`` in a scene file loads)."""
    return np.asarray(_rivet_texels(rivet_height(size), bits))


@functools.partial(jax.jit, static_argnames="bits")
def _rivet_texels(height, bits: int):
    """One program (as separate operations: ~20 small compilations at every start); the codes
    equal the operation-by-operation ones (the decoded vectors differ by an ulp, below a
    code's width)."""
    n = height_to_normal_map(height, scale=RIVET_STRENGTH)
    return quantize(encode_normal_map(n, encoding="unsigned", bits=bits), bits)


#: The meshes a scene file can name as ``"builtin:<name>"``.
BUILTIN_MESHES = {
    "torus": lambda: default_torus(),
    "plane": lambda: plane(2.0, 8),
    "sphere": lambda: uv_sphere(1.0, 96, 48),
}


def builtin_mesh(name: str) -> Mesh:
    """The mesh named ``name`` in `BUILTIN_MESHES`."""
    if name not in BUILTIN_MESHES:
        raise ValueError(f"unknown built-in mesh {name!r}; expected one of "
                         f"{', '.join(BUILTIN_MESHES)}")
    return BUILTIN_MESHES[name]()
