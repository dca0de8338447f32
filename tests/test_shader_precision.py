"""Shader precision (``precision="float16"``, GLSL mediump; ``"bfloat16"``).

Checked against an independent construction (the quad differences of the float32
interpolants rounded with NumPy), against the float64 exact answer on a plane, and for
the behaviour Schüler's readers report: half-precision uv differences at close range.
"""

import json
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxnm
from jaxnm.camera import Camera, look_at, perspective
from jaxnm.interpolate import Attribute, at_precision
from jaxnm.procedural import default_scene
from scripts.studies import hard_cases as H


def _angle(a, b):
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    return np.degrees(np.arctan2(np.linalg.norm(np.cross(a, b), axis=-1), np.sum(a * b, -1)))


def _plane_scene(distance: float, size: int = 64):
    """The hard cases' tilted, sheared-uv plane seen from ``distance`` (60 deg fov)."""
    a = np.array([[0.5, 0.5 * math.tan(math.radians(30))], [0.0, 0.5]])
    mesh, _ = H.plane(uv_matrix=a)
    eye = np.array([0.1, -0.6, 0.8]) * distance / np.linalg.norm([0.1, -0.6, 0.8])
    cam = Camera.from_matrices(look_at(eye, (0.0, 0.0, 0.0), (0, 0, 1)),
                               perspective(60.0, 1.0, distance * 1e-2, distance * 100))
    return H._scene(mesh, cam, size), H.plane_reference(a)


#: What every render of the plane asks for (each test reads its own outputs): the renders
#: with the same options share one program.
OUTPUTS = ("perturbed_normal", "mask", "view", "dpdx", "dpdy", "triangle_id")


def _errors(scene, ref, **kw):
    """Per covered pixel, the angle to ``ref``: a (3,) normal, or a (H, W, 3) image."""
    out = jaxnm.render(scene, outputs=OUTPUTS, **kw)
    m = np.asarray(out["mask"])[..., 0] > 0
    ref = np.asarray(ref)
    return _angle(np.asarray(out["perturbed_normal"])[m], ref[m] if ref.ndim == 3 else ref)


def _render_normal(scene, **kw):
    return np.asarray(jaxnm.render(scene, outputs=OUTPUTS, **kw)["perturbed_normal"])


def test_fine_differences_are_those_of_the_rounded_quad_values():
    scene, _ = _plane_scene(2.0)
    out = jaxnm.render(scene, outputs=OUTPUTS)
    v, mask = np.asarray(out["view"]), np.asarray(out["mask"])[..., 0] > 0
    tri = np.asarray(out["triangle_id"])[..., 0]
    attr = Attribute(jnp.asarray(v), jnp.asarray(out["dpdx"]), jnp.asarray(out["dpdy"]))
    lo = at_precision(attr, "float16", jnp.asarray(mask), derivatives="fine")
    assert lo.value.dtype == jnp.float16 and lo.ddx.dtype == jnp.float16
    # independent: the stored neighbours of interior quads, rounded by NumPy
    h = v.astype(np.float16)
    left, right = h[:, 0::2], h[:, 1::2]  # window x = image column
    same = mask[:, 0::2] & mask[:, 1::2] & (tri[:, 0::2] == tri[:, 1::2])
    want = (right - left)[same]
    got_l, got_r = np.asarray(lo.ddx)[:, 0::2][same], np.asarray(lo.ddx)[:, 1::2][same]
    assert same.sum() > 500
    # the partner's value is v +- dFdx in float32: a tie at a rounding boundary may differ
    assert np.mean(got_l == want) > 0.98 and np.mean(got_r == want) > 0.98
    assert np.max(np.abs(got_l.astype(np.float64) - want)) <= 2 * np.max(
        np.spacing(np.abs(h).max()))
    # window y points up: image row 2k+1 is the lower pixel of its quad when H is even
    low, up = h[1::2], h[0::2]
    same_y = mask[1::2] & mask[0::2] & (tri[1::2] == tri[0::2])
    assert np.mean(np.asarray(lo.ddy)[1::2][same_y] == (up - low)[same_y]) > 0.98


def test_float32_is_unchanged_and_the_default():
    scene, _ = _plane_scene(2.0)
    a = jaxnm.render(scene, outputs=OUTPUTS)["perturbed_normal"]
    b = jaxnm.render(scene, outputs=OUTPUTS, precision="float32")
    assert scene.precision == "float32"
    np.testing.assert_array_equal(np.asarray(a), np.asarray(b["perturbed_normal"]))


@pytest.mark.parametrize("frame", ["cotangent", "exact", "vertex"])
def test_half_arithmetic_alone_costs_hundredths_of_a_degree(frame):
    """With exact (analytic) derivatives only the arithmetic is rounded: float16 keeps the
    frame within a few of its units of rounding (2^-11 rad = 0.03 deg) of the exact normal."""
    scene, ref = _plane_scene(2.0)
    if frame == "vertex":  # MikkTSpace's orthonormal frame: its own float32 render
        scene = scene.replace(mesh=scene.mesh.with_tangents())
        ref = _render_normal(scene, frame=frame)
    e32 = _errors(scene, ref, derivatives="analytic", frame=frame)
    e16 = _errors(scene, ref, derivatives="analytic", frame=frame, precision="float16")
    ebf = _errors(scene, ref, derivatives="analytic", frame=frame, precision="bfloat16")
    assert e32.max() < 1e-3
    assert e16.mean() < 0.05 and e16.max() < 0.3
    assert 0.05 < ebf.mean() < 0.6  # 8-bit significand: eight times coarser
    assert np.isfinite(e16).all() and np.isfinite(ebf).all()


def test_half_face_normals_of_small_triangles_do_not_underflow():
    """``exact_face`` crosses the triangle's edges: for 0.03-unit triangles the squared
    length of the cross product (1e-6) is below float16's normal range; the edges are
    scaled first (the direction does not change). Unscaled, every pixel lost its frame
    (18.8 deg); what remains is the rounding of the corners' camera-relative positions
    (about 2 units from the eye: steps of 2^-10 against 0.03-unit edges)."""
    a = np.array([[0.5, 0.5 * math.tan(math.radians(30))], [0.0, 0.5]])
    mesh, _ = H.plane(segments=64, uv_matrix=a)
    scene, ref = _plane_scene(2.0)
    scene = scene.replace(mesh=mesh)
    e16 = _errors(scene, ref, derivatives="analytic", frame="exact_face", precision="float16")
    assert e16.mean() < 0.5 and e16.max() < 3.0


def test_half_close_up_noise_comes_from_the_uv_differences():
    """Schüler's readers: "when approaching the camera close to the object, a strong noise"
    (2019 comment): uv keeps its absolute rounding step (about 2^-11 near 0.5 in float16)
    while its per-pixel difference shrinks with the distance, so the fine derivatives, and
    the frame, get noisier close up. The camera-relative position (the article's ``-V``)
    shrinks with the distance and keeps its relative precision. float32 stays exact."""
    far, ref = _plane_scene(4.0)
    near, _ = _plane_scene(0.05)
    e_far = _errors(far, ref, precision="float16")
    e_near = _errors(near, ref, precision="float16")
    assert e_near.mean() > 4 * e_far.mean() and e_near.mean() > 1.0
    assert _errors(near, ref).max() < 1e-3  # float32
    # the same close-up with exact derivatives: the noise is the quantised differences
    assert _errors(near, ref, precision="float16", derivatives="analytic").mean() < 0.05
    # per-vertex tangents take no screen differences: unaffected
    near_v = near.replace(mesh=near.mesh.with_tangents())
    assert _errors(near_v, _render_normal(near_v, frame="vertex"), precision="float16",
                   frame="vertex").mean() < 0.05


def test_precision_in_scene_files_cli_and_fit_problems(tmp_path):
    from jaxnm.config import scene_from_dict

    base = {"mesh": "builtin:torus", "camera": {"eye": [0, -3, 2], "target": [0, 0, 0]},
            "width": 16, "height": 16}
    assert scene_from_dict({**base, "precision": "float16"}).precision == "float16"
    with pytest.raises(ValueError, match="s.json: unknown precision .half.; expected one of "
                       "float32, float16, bfloat16, float64"):
        scene_from_dict({**base, "precision": "half"}, source="s.json")
    with pytest.raises(ValueError, match="<built-in default scene>: precision 'float64' "
                       "needs 64-bit JAX: set JAX_ENABLE_X64=1"):
        jaxnm.render(default_scene().replace(width=8, height=8), precision="float64")
    from jaxnm.fit import problem_from_scene

    sc = default_scene().replace(width=8, height=8, precision="float16")
    assert problem_from_scene(sc, [], (8, 8)).precision == "float16"
    path = tmp_path / "s.json"
    path.write_text(json.dumps({**base, "normal_map": "builtin:rivets"}))
    from jaxnm.cli import main

    assert main(["render", str(path), "-o", str(tmp_path / "a.png"),
                 "--precision", "float16"]) == 0
    assert (tmp_path / "a.png").exists()


def test_half_precision_gradients_are_finite():
    scene = default_scene().replace(width=32, height=32)

    def loss(nm):
        return jnp.sum(jaxnm.render(scene.replace(normal_map=nm), precision="float16")["color"])

    g = jax.grad(loss)(jnp.asarray(scene.normal_map))
    assert np.isfinite(np.asarray(g)).all() and float(jnp.abs(g).sum()) > 0


def test_float64_frames_from_float32_interpolants():
    """With 64-bit JAX the frame and the perturbation run in float64; the interpolants are
    still float32, so the error to the exact answer is float32's (a few 1e-6 deg), and the
    outputs stay float32."""
    scene, ref = _plane_scene(2.0)
    with jax.enable_x64(True):
        out = jaxnm.render(scene, outputs=("perturbed_normal", "mask"), precision="float64")
        e32 = _errors(scene, ref)
    assert out["perturbed_normal"].dtype == jnp.float32
    m = np.asarray(out["mask"])[..., 0] > 0
    e64 = _angle(np.asarray(out["perturbed_normal"])[m], ref)
    assert e64.max() < 1e-3 and e32.max() < 1e-3


def test_a_map_fitted_for_a_half_precision_shader():
    """``FitProblem.precision``: the fitted map is the one a float16 shader needs. Targets
    rendered by a float16 renderer are matched better by a float16 fit than by a float32
    one (the map absorbs the frame's rounding), and both end close to the true map."""
    import dataclasses

    from jaxnm import fit as F
    from jaxnm.procedural import default_problem

    problem, gt, scene = default_problem(render_size=48, map_size=16, n_lights=4, views=1)
    t16 = [dataclasses.replace(t, image=np.asarray(jaxnm.render(scene.replace(
        camera=t.camera, lights=t.lights, width=t.width, height=t.height),
        precision="float16")["color"])) for t in problem.targets]
    losses, errors = {}, {}
    for prec in ("float32", "float16"):
        p = dataclasses.replace(problem, targets=tuple(t16), precision=prec)
        res = F.fit_normal_map(p, F.FitOptions(max_steps=12), progress=False)
        seen = F.seen_texels(F.prepare(p), p.map_size)
        losses[prec] = res.best_loss
        errors[prec] = F.error_report(res.normals, gt, seen)["mean_deg"]
        assert np.isfinite(res.normals).all()
    assert losses["float16"] < losses["float32"]
    assert errors["float16"] < 3.0 and errors["float32"] < 3.0
