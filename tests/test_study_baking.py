"""scripts/study_baking.py: its high-poly normals are right, and a bake decodes correctly only
in the frame convention it was baked in (projection bakes; the fitter's bakes run in the
script, at sizes too large for the suite)."""

import importlib.util
import sys
from pathlib import Path

import jax
import numpy as np
import pytest


def _module():
    if "study_baking" in sys.modules:
        return sys.modules["study_baking"]
    path = Path(__file__).resolve().parents[1] / "scripts" / "study_baking.py"
    spec = importlib.util.spec_from_file_location("study_baking", path)
    mod = importlib.util.module_from_spec(spec)
    sys.modules["study_baking"] = mod
    spec.loader.exec_module(mod)
    return mod


B = _module()


def test_high_poly_normal_is_the_torus_normal_without_displacement(monkeypatch):
    monkeypatch.setattr(B, "AMP", 0.0)
    rng = np.random.default_rng(0)
    u, v = rng.uniform(0, 1, 50), rng.uniform(0, 1, 50)
    _, n = B._smooth(2 * np.pi * u, 2 * np.pi * v)
    assert B._angle(B.high_normal(u, v), n).max() < 1e-6
    # and the procedural torus's vertices sit on that surface with that normal
    m = B.jaxnm.procedural.torus(B.R, B.RT, 16, 8)
    uv = np.asarray(m.uv, np.float64)
    p, n = B._smooth(2 * np.pi * uv[:, 0], 2 * np.pi * uv[:, 1])
    np.testing.assert_allclose(np.asarray(m.positions), p, atol=1e-6)
    assert B._angle(np.asarray(m.normals), n).max() < 1e-3


def test_texels_are_located_in_their_uv_triangles():
    m = B.jaxnm.procedural.torus(B.R, B.RT, 12, 6)
    u, v = B.texel_uv((8, 16))
    tri, bary = B.locate(m, u, v)
    uv = np.asarray(m.uv, np.float64)[np.asarray(m.faces)[tri]]
    np.testing.assert_allclose(np.einsum("tk,tkc->tc", bary, uv),
                               np.stack([u.ravel(), v.ravel()], -1), atol=1e-12)
    assert (bary >= -1e-9).all()


@pytest.fixture(scope="module")
def matrix():
    low = B.jaxnm.procedural.torus(B.R, B.RT, 16, 8).with_tangents()
    out = {}
    for conv in ("cotangent", "vertex"):
        baked = B.bake_projection(low, (32, 64), conv)
        for frame in ("cotangent", "vertex"):
            out[conv, frame] = B.decode_errors(low, baked, frame, 64, B.EYES[:1])["mean"]
    jax.clear_caches()
    return out


def test_a_bake_decodes_only_in_its_own_convention(matrix):
    assert matrix["cotangent", "cotangent"] < 1.0 and matrix["vertex", "vertex"] < 1.0
    assert matrix["cotangent", "vertex"] > 3 * matrix["cotangent", "cotangent"]
    assert matrix["vertex", "cotangent"] > 3 * matrix["vertex", "vertex"]
