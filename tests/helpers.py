"""Small shared scenes for the tests (float64 NumPy; cast where needed)."""

from __future__ import annotations

import numpy as np
import trimesh

import jaxnm


def jaxpr_equations(jaxpr):
    """Every equation of ``jaxpr`` (a `Jaxpr` or `ClosedJaxpr`) and of the jaxprs nested in
    its equations' parameters (loops, conds, maps, checkpoints, inner jits)."""
    jaxpr = getattr(jaxpr, "jaxpr", jaxpr)
    for eqn in jaxpr.eqns:
        yield eqn
        for p in eqn.params.values():
            for sub in p if isinstance(p, (list, tuple)) else [p]:
                inner = getattr(sub, "jaxpr", sub)
                if hasattr(inner, "eqns"):
                    yield from jaxpr_equations(inner)


def perspective_mvp(eye, target=(0.0, 0.0, 0.0), *, fov=50.0, aspect=1.0, near=0.1, far=20.0):
    """``projection @ view`` (float64) for a camera at ``eye``."""
    return jaxnm.perspective(fov, aspect, near, far) @ jaxnm.look_at(eye, target, (0, 1, 0))


def clip_of(positions, mvp) -> np.ndarray:
    """Clip coordinates (float64) of (V, 3) positions."""
    p = np.asarray(positions, np.float64)
    return np.concatenate([p, np.ones((len(p), 1))], 1) @ np.asarray(mvp).T


def random_soup(seed: int, n_vertices: int = 40, n_faces: int = 60):
    """Random intersecting triangles in [-1, 1]^3 (no repeated indices within a face)."""
    rng = np.random.default_rng(seed)
    pos = rng.uniform(-1, 1, (n_vertices, 3))
    faces = rng.integers(0, n_vertices, (n_faces * 2, 3))
    ok = (faces[:, 0] != faces[:, 1]) & (faces[:, 1] != faces[:, 2]) & (faces[:, 0] != faces[:, 2])
    return pos, faces[ok][:n_faces]


def icosphere(subdivisions: int = 2, radius: float = 1.0):
    m = trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius)
    return np.asarray(m.vertices), np.asarray(m.faces)


def box(extent: float = 2.0):
    """A closed axis-aligned box (outward CCW faces), 12 triangles."""
    m = trimesh.creation.box(extents=(extent, extent, extent))
    return np.asarray(m.vertices), np.asarray(m.faces)


def grid_plane(n: int = 4, size: float = 2.0):
    """An n x n grid of quads in the z = 0 plane, CCW seen from +z, with uv = (x, y)/size + 1/2."""
    t = np.linspace(-size / 2, size / 2, n + 1)
    x, y = np.meshgrid(t, t, indexing="xy")
    pos = np.stack([x.ravel(), y.ravel(), np.zeros(x.size)], 1)
    uv = pos[:, :2] / size + 0.5
    faces = []
    for j in range(n):
        for i in range(n):
            a = j * (n + 1) + i
            b, c, d = a + 1, a + n + 2, a + n + 1
            faces += [[a, b, c], [a, c, d]]
    return pos, np.asarray(faces), uv


def compute_frame_kw(frame, N, **kw):
    """`jaxnm.frames.compute_frame` from flat keywords: the `FrameOptions` fields
    (``normalize``, ``ddy_sign``, ``double_sided``) and the `FrameInputs` fields."""
    from jaxnm import frames as F

    opts = {k: kw.pop(k) for k in ("normalize", "ddy_sign", "double_sided") if k in kw}
    return F.compute_frame(frame, N, inputs=F.FrameInputs(**kw), options=F.FrameOptions(**opts))
