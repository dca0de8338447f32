"""Per-pixel agreement with a conformant OpenGL 4.5 implementation (Mesa llvmpipe).

The same scene is drawn with real GLSL (tests/glref.py) and with jaxnm; coverage,
triangle ids, facing, depth, the interpolated p, uv, N, and the fine derivatives
(``dFdx``/``dFdy`` == ``dFdxFine``/``dFdyFine`` on llvmpipe) are compared per pixel.
"""

import numpy as np
import pytest
import trimesh
from glref import gl_available, render_gl
from helpers import clip_of, perspective_mvp, random_soup

import jaxnm

_OK, _WHY = gl_available()
pytestmark = [pytest.mark.gl, pytest.mark.skipif(not _OK, reason=f"OpenGL unavailable: {_WHY}")]


def _torus():
    m = trimesh.creation.torus(major_radius=0.8, minor_radius=0.35, major_sections=24,
                               minor_sections=12)
    pos = np.asarray(m.vertices)
    ang = np.arctan2(pos[:, 1], pos[:, 0])
    uv = np.stack([ang / (2 * np.pi) + 0.5, pos[:, 2] / 0.7 + 0.5], 1)
    return pos, np.asarray(m.faces), uv, np.asarray(m.vertex_normals)


SCENES = {
    "soup": lambda: (*random_soup(11), None, None),
    "torus": _torus,
}


# (the soup's shape and the sizes of test_raster's float64 comparison: the same rasterizers)
@pytest.mark.parametrize("scene", list(SCENES))
@pytest.mark.parametrize("size", [(64, 48), (33, 21)])
def test_matches_llvmpipe_per_pixel(scene, size):
    w, h = size
    pos, faces, uv, nrm = SCENES[scene]()
    rng = np.random.default_rng(5)
    if uv is None:
        uv = rng.uniform(0, 1, (len(pos), 2))
        nrm = rng.normal(size=(len(pos), 3))
    mvp = perspective_mvp((0.9, 1.1, 1.9), aspect=w / h, near=0.5)
    clip = clip_of(pos, mvp).astype(np.float32)
    attrs = {"p": pos.astype(np.float32), "uv": uv.astype(np.float32),
             "n": nrm.astype(np.float32)}
    gl = render_gl(clip, faces, attrs, w, h)
    fr = jaxnm.rasterize(clip, faces, width=w, height=h)
    tid = np.asarray(fr.triangle_id)

    # coverage and visibility: identical (both snap vertices to 1/256 px, same tie rule)
    assert (gl["triangle_id"] >= 0).sum() > 0.1 * w * h
    assert np.array_equal(tid, gl["triangle_id"])
    assert np.array_equal(np.asarray(fr.front_facing), gl["front_facing"])
    m = tid >= 0
    np.testing.assert_allclose(np.asarray(fr.depth)[m], gl["depth"][m], atol=5e-6)

    out = jaxnm.interpolate(attrs, fr, derivatives="fine")
    for k in attrs:
        scale = max(1.0, float(np.abs(gl[k][m]).max()))
        np.testing.assert_allclose(np.asarray(out[k].value)[m], gl[k][m], atol=2e-5 * scale)
        dscale = max(1.0, float(np.abs(gl[k + "_dx_fine"][m]).max()))
        for ours, theirs in ((out[k].ddx, gl[k + "_dx_fine"]), (out[k].ddy, gl[k + "_dy_fine"])):
            err = np.abs(np.asarray(ours)[m] - theirs[m])
            # GL forms differences of float32 values (cancellation); we form them exactly,
            # so allow a few ulps of the values on top of the derivative scale
            assert np.percentile(err, 99) < 2e-5 * dscale + 4e-6 * scale, (k, err.max())
            assert err.max() < 1e-3 * dscale + 1e-5 * scale, (k, err.max())
    # plain dFdx is dFdxFine on llvmpipe
    np.testing.assert_array_equal(gl["uv_dx"], gl["uv_dx_fine"])


def test_backface_culling_matches_llvmpipe():
    pos, faces, uv, nrm = _torus()
    clip = clip_of(pos, perspective_mvp((0.2, 1.5, 1.2), near=0.3)).astype(np.float32)
    gl = render_gl(clip, faces, {"uv": uv.astype(np.float32)}, 40, 40, cull_back=True)
    fr = jaxnm.rasterize(clip, faces, width=40, height=40, cull_back=True)
    assert np.array_equal(np.asarray(fr.triangle_id), gl["triangle_id"])
    assert np.all(gl["front_facing"][gl["triangle_id"] >= 0])


def _padded(faces, n):
    """``faces``, then zero-area faces (one vertex three times: they cover no pixel and change
    no other triangle's id) up to ``n``: every draw of a loop has one shape, one compiled
    rasterizer."""
    return np.concatenate([faces, np.zeros((n - len(faces), 3), faces.dtype)])


def test_tie_rule_matches_llvmpipe_on_exact_edges():
    """Vertices on a half-pixel grid: many pixel centres lie exactly on edges."""
    rng = np.random.default_rng(2)
    w = h = 16
    for _ in range(10):
        win = rng.integers(0, 2 * w + 1, (30, 2)) / 2.0  # window coords, multiples of 1/2
        ndc = win / np.array([w, h]) * 2 - 1
        clip = np.concatenate([ndc, rng.uniform(-0.9, 0.9, (30, 1)), np.ones((30, 1))], 1)
        faces = rng.integers(0, 30, (12, 3))
        faces = faces[(faces[:, 0] != faces[:, 1]) & (faces[:, 1] != faces[:, 2])
                      & (faces[:, 0] != faces[:, 2])]
        clip = clip.astype(np.float32)
        gl = render_gl(clip, faces, {"c": clip[:, :1]}, w, h)
        fr = jaxnm.rasterize(clip, _padded(faces, 12), width=w, height=h)
        assert np.array_equal(np.asarray(fr.triangle_id), gl["triangle_id"])
