"""jaxnm.bake and scripts/studies/study_baking.py: the study's high-poly normals are right, a bake
decodes back to the target normals at texel centres in its own frame, and only there
(projection bakes; the fitter's bakes run in the script, at sizes too large for the
suite)."""

import jax
import numpy as np
import pytest

from scripts.studies import study_baking as B


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
    u, v = B.jaxnm.bake.texel_uv((8, 16))
    tri, bary = B.jaxnm.bake.locate_texels(m, u, v)
    assert (tri >= 0).all()
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


@pytest.mark.parametrize("frame", ["cotangent", "vertex", "vertex_area"])
def test_a_bake_decodes_back_at_texel_centres(frame):
    """Render a plane seen head-on, one pixel per texel centre: the decoded normal is the
    baked target (nearest filtering, so each pixel reads its own texel)."""
    import jax.numpy as jnp

    from jaxnm.camera import Camera, look_at, orthographic
    from jaxnm.textures import NormalMapOptions

    mesh = B.jaxnm.procedural.plane(2.0, 3).with_tangents()

    def target(u, v):  # a smooth tilted field
        n = np.stack([0.3 * np.sin(6 * u), 0.2 * np.cos(5 * v), np.ones_like(u)], -1)
        return n / np.linalg.norm(n, axis=-1, keepdims=True)

    baked = B.jaxnm.bake.bake_normal_map(mesh, target, (16, 16), frame=frame)
    cam = Camera.from_matrices(look_at((0, 0, 3), (0, 0, 0), (0, 1, 0)),
                               orthographic(-1, 1, -1, 1, 0.1, 10))
    sc = B.jaxnm.Scene(mesh=mesh, camera=cam, width=16, height=16,
                       normal_map=jnp.asarray(baked),
                       normal_map_options=NormalMapOptions(encoding="signed",
                                                           filter="nearest"),
                       frame=frame)
    out = B.jaxnm.render(sc, outputs=("perturbed_normal", "uv", "mask"))
    m = np.asarray(out["mask"])[..., 0] > 0
    uv = np.asarray(out["uv"], np.float64)[m]
    want = target(np.round(uv[:, 0] * 16 - 0.5) / 16 + 1 / 32,
                  np.round(uv[:, 1] * 16 - 0.5) / 16 + 1 / 32)
    assert m.sum() > 200
    assert B._angle(np.asarray(out["perturbed_normal"])[m], want).max() < 0.01


def test_bake_refuses_what_it_cannot_bake():
    mesh = B.jaxnm.procedural.plane(2.0, 2)
    field = lambda u, v: np.tile([0.0, 0.0, 1.0], (np.size(u), 1))  # noqa: E731
    with pytest.raises(ValueError, match="cannot bake for frame 'nonperspective'.*camera"):
        B.jaxnm.bake_normal_map(mesh, field, (4, 4), frame="nonperspective")
    with pytest.raises(ValueError, match="frame 'vertex' needs the mesh's MikkTSpace"):
        B.jaxnm.bake_normal_map(mesh, field, (4, 4), frame="vertex")
    import dataclasses

    with pytest.raises(ValueError, match="no texture coordinates"):
        B.jaxnm.bake_normal_map(dataclasses.replace(mesh, uv=None), field, (4, 4),
                                frame="cotangent")
    # texels outside every uv triangle keep the fill value
    small = dataclasses.replace(mesh, uv=mesh.uv * 0.5)  # the mesh covers uv [0, 0.5]^2
    out = B.jaxnm.bake_normal_map(small, field, (4, 4), frame="cotangent",
                                  fill=(0.0, 1.0, 0.0))
    assert np.allclose(out[0, 3], [0.0, 1.0, 0.0]) and np.allclose(out[3, 0], [0.0, 0.0, 1.0])
