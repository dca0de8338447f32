"""MikkTSpace tangents (`jaxnm.tangents`) against Blender's (an independent implementation of
the same algorithm, run in its own environment: see tests/blender_ref.py), and invariants.

Without Blender the comparisons skip with the reason; CI installs it (``JAXNM_REQUIRE_BLENDER=1``
turns a missing Blender into a failure)."""

from __future__ import annotations

import os
import re
import subprocess
from pathlib import Path

import numpy as np
import pytest

from jaxnm import procedural
from jaxnm.tangents import mikktspace_tangents
from scripts.studies import blender_bake_cases

HERE = Path(__file__).resolve().parent


BLENDER = blender_bake_cases.blender_python()  # $JAXNM_BLENDER_PYTHON or .venv-blender
needs_blender = pytest.mark.skipif(
    BLENDER is None and os.environ.get("JAXNM_REQUIRE_BLENDER") != "1",
    reason="no Blender Python (set JAXNM_BLENDER_PYTHON or make .venv-blender with bpy)")


def run_blender(cmd: str, payload: dict, tmp_path: Path) -> dict:
    assert BLENDER is not None, "JAXNM_REQUIRE_BLENDER=1 but no Blender Python was found"
    src, dst = tmp_path / f"{cmd}_in.npz", tmp_path / f"{cmd}_out.npz"
    np.savez(src, **payload)
    out = subprocess.run([BLENDER, str(HERE / "blender_ref.py"), cmd, str(src), str(dst)],
                         capture_output=True, text=True, timeout=900)
    assert out.returncode == 0, out.stderr[-3000:]
    return dict(np.load(dst))


# --------------------------------------------------------------------------------------
# test meshes: (positions, faces, uv, normals), float64/int
# --------------------------------------------------------------------------------------


def _arrays(mesh):
    return (np.asarray(mesh.positions, np.float64), np.asarray(mesh.faces),
            np.asarray(mesh.uv, np.float64), np.asarray(mesh.normals, np.float64))


def torus_plain():
    return _arrays(procedural.torus(1.0, 0.4, 24, 12))


def torus_stretched_sheared():
    pos, faces, uv, nrm = torus_plain()
    uv = np.stack([3.0 * uv[:, 0] + 0.6 * uv[:, 1], 0.5 * uv[:, 1]], -1)  # 1:6, sheared
    return pos, faces, uv, nrm


def bent_grid(n: int = 8):
    """A curved n x n patch (part of a cylinder), smooth normals, uv = grid."""
    s = np.linspace(0.0, 1.0, n + 1)
    uu, vv = np.meshgrid(s, s, indexing="xy")
    a = (uu - 0.5) * 1.5  # angle around the cylinder's axis (y)
    pos = np.stack([np.sin(a), vv * 2 - 1, np.cos(a)], -1).reshape(-1, 3)
    nrm = np.stack([np.sin(a), 0 * a, np.cos(a)], -1).reshape(-1, 3)
    uv = np.stack([uu, vv], -1).reshape(-1, 2)
    faces = []
    for j in range(n):
        for i in range(n):
            k = j * (n + 1) + i
            faces += [[k, k + 1, k + n + 2], [k, k + n + 2, k + n + 1]]
    return pos, np.asarray(faces), uv, nrm


def grid_mirrored():
    """The patch with u mirrored about its middle column, whose vertices (u = 1 on both
    sides) are shared by both halves: MikkTSpace gives them one tangent per handedness."""
    pos, faces, uv, nrm = bent_grid()
    uv = np.stack([1.0 - np.abs(2.0 * uv[:, 0] - 1.0), uv[:, 1]], -1)
    return pos, faces, uv, nrm


def box_hard_edges():
    """A box with split (per-face) normals: every face has its own four vertices."""
    pos, faces, uv, nrm = [], [], [], []
    for axis in range(3):
        for s in (-1.0, 1.0):
            n = np.zeros(3)
            n[axis] = s
            u_ax, v_ax = np.eye(3)[(axis + 1) % 3], np.eye(3)[(axis + 2) % 3] * s
            base = len(pos)
            for du, dv in ((0, 0), (1, 0), (1, 1), (0, 1)):
                pos.append(n + (2 * du - 1) * u_ax + (2 * dv - 1) * v_ax)
                uv.append([0.1 + 0.3 * du + 0.3 * axis, 0.1 + 0.3 * dv + 0.4 * (s > 0)])
                nrm.append(n)
            faces += [[base, base + 1, base + 2], [base, base + 2, base + 3]]
    return np.asarray(pos), np.asarray(faces), np.asarray(uv), np.asarray(nrm)


def degenerate_uv():
    """The patch with two columns of uvs collapsed onto their neighbours (zero uv area
    triangles, which group with anything) and one column collapsed in v too."""
    pos, faces, uv, nrm = bent_grid()
    uv = uv.copy()
    n = 9
    col = np.arange(len(uv)) % n
    uv[col == 4, 0] = uv[col == 3, 0]
    uv[col == 6] = uv[col == 5]
    return pos, faces, uv, nrm


def degenerate_position():
    """The patch plus a sliver: a triangle whose two corners share a position."""
    pos, faces, uv, nrm = bent_grid()
    pos = np.concatenate([pos, pos[[10]]])
    uv = np.concatenate([uv, uv[[11]]])
    nrm = np.concatenate([nrm, nrm[[10]]])
    faces = np.concatenate([faces, [[10, 11, len(pos) - 1]]])
    return pos, faces, uv, nrm


MESHES = {"torus_plain": torus_plain, "torus_stretched_sheared": torus_stretched_sheared,
          "grid_mirrored": grid_mirrored, "box_hard_edges": box_hard_edges,
          "degenerate_uv": degenerate_uv, "degenerate_position": degenerate_position}


def _angle_deg(a, b):
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    return np.degrees(np.arctan2(np.linalg.norm(np.cross(a, b), axis=-1), np.sum(a * b, -1)))


# --------------------------------------------------------------------------------------
# invariants (no Blender needed)
# --------------------------------------------------------------------------------------


@pytest.mark.parametrize("name", list(MESHES))
def test_tangents_are_unit_in_the_tangent_plane_with_a_sign(name):
    pos, faces, uv, nrm = MESHES[name]()
    t = mikktspace_tangents(pos, nrm, uv, faces)
    assert t.shape == (len(faces), 3, 4) and np.isfinite(t).all()
    np.testing.assert_allclose(np.linalg.norm(t[..., :3], axis=-1), 1.0, atol=1e-6)
    assert set(np.unique(t[..., 3])) <= {-1.0, 1.0}
    good = ~np.isin(np.arange(len(faces)), [len(faces) - 1]) if "position" in name else ...
    n = nrm[faces]
    assert np.abs(np.sum(t[good][..., :3] * n[good], -1)).max() < 1e-5


def test_unusable_arrays_are_refused_in_one_line():
    """(NumPy's errors from inside: a concatenation's dimensions, an index out of bounds.)"""
    m = procedural.torus(major_segments=8, minor_segments=6)
    p, n, uv, f = (np.asarray(a) for a in (m.positions, m.normals, m.uv, m.faces))
    cases = [
        ((p, n, None, f), "mikktspace_tangents: needs uv, got None"),
        ((p, None, uv, f), "mikktspace_tangents: needs normals, got None"),
        ((p, n, uv[:3], f), f"mikktspace_tangents: uv must have shape ({len(p)}, 2), got (3, 2)"),
        ((p, n, uv, f + 1000), f"mikktspace_tangents: face indices must be in [0, {len(p) - 1}]"),
        ((np.where(p > 0.5, np.nan, p), n, uv, f), "mikktspace_tangents: "),
    ]
    for args, message in cases:
        with pytest.raises(ValueError, match=re.escape(message)) as ei:
            mikktspace_tangents(*args)
        assert "\n" not in str(ei.value)


def test_a_mirror_seam_gives_shared_vertices_two_tangents():
    pos, faces, uv, nrm = grid_mirrored()
    t = mikktspace_tangents(pos, nrm, uv, faces)
    # corners of the shared middle column: the left half's sign is +1, the right half's -1,
    # and both tangents point along +u of their own half (towards the mirror line)
    mid = np.isclose(pos[faces][..., 0], 0.0) & np.isclose(uv[faces][..., 0], 1.0)
    left = pos[faces][..., 0].mean(-1, keepdims=True) < 0
    assert (t[..., 3][mid & left] == 1).all() and (t[..., 3][mid & ~left] == -1).all()
    x = t[..., 0]
    assert (x[mid & left] > 0.9).all() and (x[mid & ~left] < -0.9).all()


def test_tangent_follows_dp_du_on_a_smooth_torus():
    """Away from the u seam a vertex's tangent is the symmetric average of its triangles'
    dp/du: the analytic direction around the ring (to the tessellation's accuracy)."""
    m = procedural.torus(1.0, 0.4, 96, 48)
    pos, faces, uv, nrm = _arrays(m)
    t = mikktspace_tangents(pos, nrm, uv, faces)
    p = pos[faces]
    phi = np.arctan2(p[..., 1], p[..., 0])
    du = np.stack([-np.sin(phi), np.cos(phi), 0 * phi], -1)
    inner = (uv[faces][..., 0] > 0.01) & (uv[faces][..., 0] < 0.99)
    assert _angle_deg(t[..., :3], du)[inner].max() < 0.05


# --------------------------------------------------------------------------------------
# against Blender
# --------------------------------------------------------------------------------------


def _per_corner(pos, faces, uv, normals):
    """The mesh with one vertex per face corner, carrying per-corner normals (welding, in
    either implementation, merges the corners that are equal in position, normal and uv)."""
    return (pos[faces].reshape(-1, 3), np.arange(faces.size).reshape(-1, 3),
            uv[faces].reshape(-1, 2), np.asarray(normals).reshape(-1, 3))


@needs_blender
@pytest.mark.parametrize("name", list(MESHES))
def test_tangents_match_blender(name, tmp_path):
    """Every corner's sign, and its tangent to 1e-4 deg, given the same (Blender's
    compressed) corner normals. Blender leaves degenerate triangles (two corners at one
    position) at the default tangent where the reference copies a neighbour's; they cover no
    pixel, so they are left out."""
    pos, faces, uv, nrm = MESHES[name]()
    ref = run_blender("tangents", dict(positions=pos, faces=faces, uv=uv, normals=nrm),
                      tmp_path)
    cp, cf, cuv, cn = _per_corner(pos, faces, uv, ref["normals"])
    ours = mikktspace_tangents(cp, cn, cuv, cf)
    p = pos[faces]
    keep = ~(np.all(p[:, 0] == p[:, 1], -1) | np.all(p[:, 0] == p[:, 2], -1)
             | np.all(p[:, 1] == p[:, 2], -1))
    np.testing.assert_array_equal(ours[keep][..., 3], ref["signs"][keep])
    err = _angle_deg(ours[keep][..., :3], ref["tangents"][keep])
    assert err.max() < 1e-4, (name, err.max())
    # with our own (uncompressed) normals the tangents differ by the compression only
    direct = mikktspace_tangents(pos, nrm, uv, faces)
    assert _angle_deg(direct[keep][..., :3], ref["tangents"][keep]).max() < 0.01
