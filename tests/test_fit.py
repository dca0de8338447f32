"""Normal-map fitting: recovery of a known map, held-out lights, solvers, bad input, the CLI."""

import contextlib
import dataclasses
import json
import re
import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxnm import fit as F
from jaxnm.camera import eye_to_world
from jaxnm.cli import main
from jaxnm.config import load_fit
from jaxnm.io import JaxnmWarning, save_png
from jaxnm.procedural import default_problem
from jaxnm.scene import default_material
from jaxnm.shading import Lights, directional_light
from jaxnm.textures import linear_to_srgb


@pytest.fixture(scope="module")
def small():
    """The built-in problem, small: 64x64 renders, a 32x32 map, 6 lights, 2 views."""
    problem, gt, scene = default_problem(render_size=64, map_size=32, n_lights=6, views=2)
    prep = F.prepare(problem)
    seen = F.seen_texels(prep, problem.map_size)
    return problem, gt, scene, prep, seen


def test_recovers_known_map_noise_free(small):
    problem, gt, _, prep, seen = small
    assert 0.2 < seen.mean() < 0.9
    res = F.fit_normal_map(problem, F.FitOptions(max_steps=25), ground_truth=gt, prepared=prep,
                           progress=False)
    rep = F.error_report(res.normals, gt, seen)
    assert rep["mean_deg"] < 1.0, rep
    # the start (a flat map) is far from the answer: the fit did the work
    flat = np.zeros_like(gt)
    flat[..., 2] = 1
    assert F.error_report(flat, gt, seen)["mean_deg"] > 10
    # unit vectors with positive z, by construction of the parameterisation
    np.testing.assert_allclose(np.linalg.norm(res.normals, axis=-1), 1, atol=1e-5)
    assert (res.normals[..., 2] > 0).all()
    hist = [h["loss"] for h in res.history]
    assert hist[-1] < 1e-3 * hist[0]


def test_held_out_light_matches_ground_truth_render(small):
    problem, gt, scene, prep, seen = small
    res = F.fit_normal_map(problem, F.FitOptions(max_steps=25), prepared=prep, progress=False)
    cam = problem.targets[0].camera
    d = eye_to_world(cam, [0.45, 0.35, 0.82])
    held = F.FitTarget(cam, 64, 64, directional_light(d), np.zeros((64, 64, 3), np.float32))
    hp = F.prepare(dataclasses.replace(problem, targets=(held,)))
    fitted = np.asarray(F.render_with_map(hp, jnp.asarray(res.normals))[0][0])
    truth = np.asarray(F.render_with_map(hp, jnp.asarray(gt))[0][0])
    m = hp.target_mask(0)
    assert F.psnr(fitted, truth, m) > 35.0


def test_held_out_scores_reuse_their_prepared_views(small, monkeypatch):
    """`prepare_held_out` up front (as `jaxnm fit` does, while the G-buffer program is
    compiled) gives `score_held_out` the same scores as preparing there, without preparing
    again."""
    import importlib

    problem, gt, _, _, _ = small
    cam = problem.targets[0].camera
    lights = directional_light(eye_to_world(cam, [0.45, 0.35, 0.82]))
    blank = F.FitTarget(cam, 64, 64, lights, np.zeros((64, 64, 3), np.float32))
    truth = np.asarray(F.render_with_map(
        F.prepare(dataclasses.replace(problem, targets=(blank,))), jnp.asarray(gt))[0][0])
    job = F.FitJob(problem=problem, ground_truth=gt,
                   held_out=(dataclasses.replace(blank, image=truth, name="held"),))
    noisy = gt + np.float32(0.02) * np.roll(gt, 1, axis=0)
    noisy /= np.linalg.norm(noisy, axis=-1, keepdims=True)
    want = F.score_held_out(job, noisy)
    assert want[0]["name"] == "held" and 20 < want[0]["psnr_db_vs_target"] < 100
    pre = F.prepare_held_out(job)
    report = importlib.import_module("jaxnm.fit.report")
    monkeypatch.setattr(report, "prepare", lambda *a, **k: pytest.fail("prepared again"))
    assert F.score_held_out(job, noisy, pre) == want


def test_noisy_targets(small):
    problem, gt, _, _, _ = small
    noisy, _, _ = default_problem(render_size=64, map_size=32, n_lights=6, views=2, noise=0.02,
                                    seed=3)
    prep = F.prepare(noisy)
    seen = F.seen_texels(prep, noisy.map_size)
    res = F.fit_normal_map(noisy, F.FitOptions(max_steps=20), prepared=prep, progress=False)
    assert F.error_report(res.normals, gt, seen)["mean_deg"] < 3.0


def test_render_with_map_reproduces_targets(small):
    """The fit's model renders exactly what the full renderer rendered (same pipeline)."""
    problem, gt, _, prep, _ = small
    out = F.render_with_map(prep, jnp.asarray(gt))
    for v, imgs in enumerate(out):
        np.testing.assert_allclose(np.asarray(imgs), prep.target_images(v), rtol=3e-3, atol=2e-3)


def test_problem_from_scene_refuses_what_is_not_a_scene_or_a_size(small):
    problem, _, scene, _, _ = small
    with pytest.raises(TypeError, match="^problem_from_scene: scene must be a Scene "
                                        r"\(jaxnm.config.load_scene\), got dict$"):
        F.problem_from_scene({}, problem.targets, (32, 32))  # ('dict' has no attribute 'model')
    for size in (32, "32x32"):  # an int raised "'int' object is not iterable"
        with pytest.raises(ValueError, match=f"the map size must be two integers >= 2, got "
                                             f"{re.escape(repr(size))}$"):
            F.problem_from_scene(scene, problem.targets, size)
    # (a size of 31.5 was truncated to 31; now kept, and refused by prepare, above)
    assert F.problem_from_scene(scene, problem.targets, np.array([16, 32])).map_size == (16, 32)
    # a scene without a material is fitted with the one it renders with, not None
    bare = F.problem_from_scene(scene.replace(material=None), problem.targets, (32, 32))
    jax.tree.map(np.testing.assert_array_equal, bare.material, default_material())


def test_render_with_map_refuses_a_map_or_lights_the_problem_does_not_have(small):
    problem, gt, _, prep, _ = small
    h, w = gt.shape[:2]
    cases = [
        ((problem, gt), {}, TypeError, "render_with_map: prep must be a Prepared "
                                       "(jaxnm.fit.prepare), got FitProblem"),
        ((prep, gt[: h // 2, : w // 2]), {}, ValueError,
         f"render_with_map: normals must be {(h, w, 3)}, the prepared problem's map, got "
         f"{(h // 2, w // 2, 3)}"),
        ((prep, gt[..., :2]), {}, ValueError, f"got {(h, w, 2)}"),
        ((prep, gt), {"lights": []}, ValueError,
         f"render_with_map: lights must hold one Lights per view ({prep.num_views}), got 0"),
    ]
    for args, kw, error, message in cases:  # (said "mip_sizes: levels must be ..." or raised
        with pytest.raises(error, match=re.escape(message)):  # from inside JAX)
            F.render_with_map(*args, **kw)


def test_prepared_keeps_only_covered_pixels_and_needed_taps(small):
    """The compact step model: covered pixels only, views stacked for one vmap, 4-tap gathers
    where one mip level is read, and padding that weighs nothing."""
    from jaxnm import textures as T
    from jaxnm.render import render

    problem, gt, scene, prep, _ = small
    assert len(prep.batches) == 1 and sorted(prep.batches[0].views) == [0, 1]
    b = prep.batches[0]
    real = np.asarray(b.pixels) >= 0  # (V, K)
    assert (~real).any()  # the two views cover different pixel counts: one is padded
    w = np.asarray(b.gbuffer.plan.weight)
    assert 0 < b.split < b.pixels.shape[1]  # both tap groups are exercised
    assert np.all(w[:, :b.split, 4:][real[:, :b.split]] == 0)
    assert np.all(np.any(w[:, b.split:, 4:] > 0, axis=-1)[real[:, b.split:]])
    assert np.all(np.asarray(b.weights)[..., 0].transpose(1, 0, 2)[:, ~real] == 0)
    mips = T.build_mipmaps(jnp.asarray(gt), levels=prep.options[0].levels)
    full = np.asarray(T.apply_plan(b.gbuffer.plan, mips))
    split = np.asarray(jax.vmap(lambda p: F.sample_split(p, mips, b.split))(b.gbuffer.plan))
    np.testing.assert_allclose(split[real], full[real], atol=1e-6)
    for v in range(prep.num_views):
        mine = [t for t in problem.targets if F.view_key(t) == F.view_key(
            [t for t in problem.targets if t.name.startswith(f"view{v}_")][0])]
        o = prep.options[v]
        # the pixel list is exactly what the renderer covers
        aov = render(scene.replace(camera=mine[0].camera), outputs=("mask",))["mask"]
        cover = np.asarray(aov).reshape(o.height, o.width) > 0.5
        np.testing.assert_array_equal(prep.target_mask(v), cover)
        pix = np.asarray(prep.view(v).pixels)
        assert len(np.unique(pix)) == len(pix) == cover.sum()
        imgs = prep.target_images(v)
        assert imgs.shape == (len(mine), o.height, o.width, 3)
        for t, img in zip(mine, imgs):
            np.testing.assert_array_equal(img[cover], np.asarray(t.image)[cover])
            assert np.all(img[~cover] == 0)


#: The loss and its gradient, one program per problem layout (a test needing either takes
#: both).
_loss_and_grad = jax.jit(jax.value_and_grad(F.loss))


@pytest.mark.slow
def test_views_with_different_sizes_targets_and_light_kinds(small):
    """Views of different image sizes and target counts share one vmapped batch (padded);
    views with other kinds of lights, or far fewer pixels, get their own batch. The model still
    reproduces every target the full renderer made, and its gradient is finite."""
    from jaxnm.camera import Camera, look_at, perspective
    from jaxnm.render import render
    from jaxnm.shading import PointLight

    problem, gt, scene, _, _ = small
    gt_scene = scene  # renders with the ground-truth map
    cams = [Camera.from_matrices(look_at(eye, (0, 0, 0), (0, 0, 1)),
                                 perspective(45.0, w / h, 0.1, 50.0))
            for eye, (w, h) in [((0.0, -2.35, 1.75), (64, 64)), ((1.6, 1.5, 1.9), (60, 52)),
                                ((-2.1, 0.6, -1.2), (64, 64)), ((0.0, -2.35, 1.75), (24, 24))]]
    sizes = [(64, 64), (60, 52), (64, 64), (24, 24)]
    point = lambda p: Lights(point=PointLight(jnp.asarray(p, jnp.float32),  # noqa: E731
                                              jnp.ones(3), jnp.asarray(3.0)))
    plan = [(0, directional_light(eye_to_world(cams[0], d)))
            for d in ([0.3, 0.2, 1.0], [-0.5, 0.1, 0.8], [0.1, -0.6, 0.7])]
    plan += [(1, directional_light(eye_to_world(cams[1], [0.2, 0.4, 0.9])))]
    plan += [(2, point(p)) for p in ([-2.0, 1.5, 0.5], [-2.5, -0.5, -1.0])]
    plan += [(3, directional_light(eye_to_world(cams[3], [0.3, 0.2, 1.0])))]
    targets = []
    for k, (v, lt) in enumerate(plan):
        w, h = sizes[v]
        img = render(gt_scene.replace(camera=cams[v], width=w, height=h, lights=lt),
                     outputs=("color",))["color"]
        targets.append(F.FitTarget(cams[v], w, h, lt, img, name=f"t{k}"))
    mixed = dataclasses.replace(problem, targets=tuple(targets))
    prep = F.prepare(mixed)
    # views 0 and 1 share a batch (similar pixel counts), the 24x24 view would be padded
    # more than 2x there and gets its own; view 2's point lights make another
    assert sorted(sorted(b.views) for b in prep.batches) == [[0, 1], [2], [3]]
    b01 = [b for b in prep.batches if 0 in b.views][0]
    assert dict(zip(b01.views, b01.targets)) == {0: 3, 1: 1}
    out = F.render_with_map(prep, jnp.asarray(gt))
    for v, imgs in enumerate(out):
        assert imgs.shape[1:3] == sizes[v][::-1]
        np.testing.assert_allclose(np.asarray(imgs), prep.target_images(v), rtol=3e-3, atol=2e-3)
    args = F.ModelArgs.create(prep)
    slopes = F.normals_to_slopes(jnp.asarray(gt))
    at_truth = float(_loss_and_grad(slopes, args)[0])
    flat, g = _loss_and_grad(jnp.zeros_like(slopes), args)
    assert at_truth < 1e-3 * float(flat)
    assert np.all(np.isfinite(np.asarray(g))) and np.any(np.asarray(g) != 0)


def test_lbfgs_baseline_decreases_loss_and_is_deterministic(small):
    problem, gt, _, prep, seen = small
    opts = F.FitOptions(solver="lbfgs", max_steps=15, seed=1, init_noise=0.05)
    a = F.fit_normal_map(problem, opts, prepared=prep, progress=False)
    b = F.fit_normal_map(problem, opts, prepared=prep, progress=False)
    np.testing.assert_array_equal(a.normals, b.normals)
    assert a.history[-1]["loss"] < 0.5 * a.history[0]["loss"]


@pytest.mark.parametrize("solver", ["lm-texel", "lm", "gn", "lbfgs"])
def test_a_fit_with_64_bit_types_on_is_the_float32_fit(small, solver):
    """With ``jax_enable_x64`` on (a notebook that checks against float64), every solver
    fits, in float32, the map it fits with it off: the G-buffer is then rasterized in
    float64 and kept in float32, so the two differ by float32 rounding where the targets
    see the map. (With 64-bit
    types on inside the step, the solvers' float64 step sizes beside float32 maps would be
    refused by their programs.)"""
    problem, _, _, prep, seen = small
    opts = F.FitOptions(solver=solver, max_steps=2)
    ref = F.fit_normal_map(problem, opts, prepared=prep, progress=False)
    with jax.enable_x64(True):
        wide = F.prepare(problem)
        res = F.fit_normal_map(problem, opts, prepared=wide, progress=False)
        assert jnp.zeros(()).dtype == jnp.float64  # the caller's setting, left as it was
    assert res.normals.dtype == np.float32 and len(res.history) == len(ref.history)
    np.testing.assert_allclose([h["loss"] for h in res.history],
                               [h["loss"] for h in ref.history], rtol=1e-3)
    # on the texels the targets see: elsewhere the problem leaves the map free, and an
    # undamped Gauss-Newton step's least-squares solve may put anything there (lineax 0.1.0
    # does, under 64-bit types: up to 0.4 on unseen texels, 1e-3 on seen ones)
    assert np.all(np.isfinite(res.normals))
    np.testing.assert_allclose(res.normals[seen], ref.normals[seen], atol=2e-3)


def test_time_limit_keeps_best_so_far(small):
    problem, gt, _, prep, _ = small
    res = F.fit_normal_map(problem, F.FitOptions(max_steps=50), prepared=prep, progress=False,
                           time_limit=0.0)
    assert res.stopped == "time_limit" and [h["step"] for h in res.history] == [0]
    assert np.isfinite(res.best_loss) and res.best_loss <= min(h["loss"] for h in res.history)


def test_gradient_wrt_slopes_matches_finite_differences(small):
    problem, _, _, prep, _ = small
    rng = np.random.default_rng(0)
    z = jnp.asarray(rng.normal(0, 0.3, (32, 32, 2)), jnp.float32)
    args = F.ModelArgs.create(prep)
    loss = lambda x: _loss_and_grad(x, args)[0]  # noqa: E731
    g = _loss_and_grad(z, args)[1]
    assert np.all(np.isfinite(np.asarray(g)))
    d = jnp.asarray(rng.normal(size=z.shape), jnp.float32)
    d = d / jnp.linalg.norm(d)
    eps = 1e-2
    fd = (loss(z + eps * d) - loss(z - eps * d)) / (2 * eps)
    np.testing.assert_allclose(float(jnp.vdot(g, d)), float(fd), rtol=2e-2)


def test_one_light_warns_that_the_map_is_not_determined(small):
    problem = small[0]
    one = dataclasses.replace(problem, targets=problem.targets[:1])
    with pytest.warns(F.FitWarning, match="one light cannot determine"):
        F.check_identifiability(F.prepare(one))


def _bad(problem, **target_changes):
    t = dataclasses.replace(problem.targets[0], **target_changes)
    return dataclasses.replace(problem, targets=(t,) + problem.targets[1:])


@pytest.mark.parametrize("change,match", [
    (lambda p: _bad(p, image=np.zeros((32, 64, 3), np.float32)), "32 but its camera"),
    (lambda p: _bad(p, image=np.full((64, 64, 3), np.nan, np.float32)), "NaN"),
    (lambda p: _bad(p, mask=np.zeros((64, 64), bool)), "covers nothing"),
    (lambda p: _bad(p, lights=Lights()), "no lights"),
    (lambda p: dataclasses.replace(p, mesh=dataclasses.replace(p.mesh, uv=None)),
     "no texture coordinates"),
    (lambda p: dataclasses.replace(p, targets=()), "no target"),
    (lambda p: _bad(p, width=0), r"view0_light0: width and height must be positive integers, got "
                                 r"0 x 64$"),
    (lambda p: _bad(p, height=64.0), "width and height must be positive integers, got 64 x 64.0"),
    (lambda p: _bad(p, camera=None), "view0_light0: the camera must be a Camera, got NoneType$"),
    (lambda p: dataclasses.replace(p, targets=(p.targets[0].image,)),
     "target 0 must be a FitTarget, got ndarray$"),
    (lambda p: dataclasses.replace(p, map_size=(31.5, 32)),
     r"the map size must be two integers >= 2, got \(31.5, 32\)$"),
    (lambda p: dataclasses.replace(p, material=None), r"the material must be a jaxnm Material "
     r"\(jaxnm.scene.default_material\(\) is the built-in scene's\), got NoneType$"),
    (lambda p: _bad(p, lights=[directional_light((0, 0, 1))]), r"view0_light0: lights must be "
     r"a jaxnm Lights \(jaxnm.directional_light\(...\)\), got list$"),
    (lambda p: dataclasses.replace(p, mesh=p.mesh.positions), "the mesh must be a jaxnm Mesh "
     r"\(jaxnm.io.load_mesh\), got ArrayImpl$"),
])
def test_bad_input_is_refused_before_compiling(small, change, match):
    with pytest.raises(ValueError, match=match):
        F.prepare(change(small[0]))


@pytest.mark.slow
def test_fit_file_and_cli(tmp_path, small, capsys):
    """A fit JSON with PNG targets (sRGB) runs through `jaxnm fit` and writes every output."""
    problem, gt, scene, prep, _ = small
    scene_file = tmp_path / "scene.json"
    scene_file.write_text(json.dumps({
        "mesh": "builtin:torus", "width": 64, "height": 64,
        "camera": {"eye": [0.0, -2.35, 1.75], "target": [0, 0, 0], "up": [0, 0, 1],
                   "fov_y_deg": 45},
        "normal_map": {"path": "builtin:rivets", "filter": "trilinear"},
        "albedo": [0.85, 0.6, 0.38],
        "material": {"model": "blinn_phong", "specular": [0.15, 0.15, 0.15], "shininess": 24,
                     "ambient": [0, 0, 0]}}))
    targets = []
    for i, t in enumerate(problem.targets[:6]):  # view 0, six lights
        save_png(tmp_path / f"t{i}.png", np.asarray(linear_to_srgb(np.clip(t.image, 0, 1))),
                 bits=16)
        d = np.asarray(t.lights.directional.direction)[0].tolist()
        targets.append({"view": 0, "image": f"t{i}.png", "lights": [
            {"type": "directional", "direction": d}]})
    save_png(tmp_path / "gt.png", (gt + 1) / 2, bits=16)
    cfg = tmp_path / "fit.json"
    cfg.write_text(json.dumps({
        "scene": "scene.json", "targets": targets, "map": {"size": [32, 32], "bits": 16},
        "ground_truth": {"path": "gt.png"}, "solver": {"method": "lm", "max_steps": 4}}))
    job = load_fit(cfg)
    problem2 = job.problem
    assert problem2.map_size == (32, 32) and len(problem2.targets) == 6
    # the camera of the scene file is the view: the sRGB round trip keeps the targets
    np.testing.assert_allclose(problem2.targets[0].image, problem.targets[0].image, atol=2e-3)
    out = tmp_path / "out"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", F.FitWarning)  # one view: identifiable, no warning
        rc = main(["fit", str(cfg), "-o", str(out), "--no-progress"])
    assert rc == 0
    for name in ("normal_map.png", "normal_map.npz", "render_00.png", "loss.png", "loss.json",
                 "report.json", "error_map.png"):
        assert (out / name).exists(), name
    rep = json.loads((out / "report.json").read_text())
    assert rep["error"]["mean_deg"] < 20 and rep["steps"] == 4
    assert rep["frame"] == "cotangent" and rep["map_encoding"]["bits"] == 16
    assert "angular error" in capsys.readouterr().out


@pytest.mark.slow
def test_example_fit_script_writes_the_built_in_problem(tmp_path, small):
    """scripts/examples/make_example_fit.py writes a fit file that loads back as the built-in
    problem."""
    from scripts.examples import make_example_fit as mod

    problem, gt, _, _, _ = small
    path = mod.write_example(tmp_path, render_size=64, map_size=32)
    job = load_fit(path)
    loaded = job.problem
    assert loaded.map_size == (32, 32) and len(loaded.targets) == len(problem.targets) == 12
    for a, b in zip(loaded.targets, problem.targets):
        np.testing.assert_allclose(np.asarray(a.camera.view), np.asarray(b.camera.view),
                                   atol=1e-6)
        np.testing.assert_allclose(np.asarray(a.lights.directional.direction),
                                   np.asarray(b.lights.directional.direction), atol=1e-6)
        np.testing.assert_allclose(a.image, b.image, atol=2e-3)  # 16-bit sRGB round trip
    np.testing.assert_allclose(job.ground_truth, gt, atol=1e-6)
    assert len(job.held_out) == 1 and job.options.solver == "lm-texel"
    np.testing.assert_allclose(np.asarray(loaded.material.shininess),
                               np.asarray(problem.material.shininess))


def test_an_object_space_ground_truth_warns_without_the_scene_files_remedy(tmp_path):
    """A fit file's ground truth that looks like an object-space map warns, saying that a
    ground truth is a tangent-space map (it takes no "space" key, as a scene's map does)."""
    u, v = np.meshgrid((np.arange(8) + 0.5) / 8, (np.arange(8) + 0.5) / 8)
    n = np.stack([np.sin(np.pi * v) * np.cos(2 * np.pi * u),
                  np.sin(np.pi * v) * np.sin(2 * np.pi * u), np.cos(np.pi * v)], -1)
    save_png(tmp_path / "gt.png", (n * 0.5 + 0.5).astype(np.float32))
    save_png(tmp_path / "t.png", np.full((16, 16, 3), 0.5, np.float32))
    (tmp_path / "scene.json").write_text(json.dumps({
        "mesh": "builtin:torus", "width": 16, "height": 16,
        "camera": {"eye": [0.0, -2.35, 1.75], "target": [0, 0, 0], "up": [0, 0, 1]}}))
    (tmp_path / "fit.json").write_text(json.dumps({
        "scene": "scene.json", "map": {"size": [8, 8]}, "ground_truth": {"path": "gt.png"},
        "targets": [{"view": 0, "image": "t.png", "lights": [
            {"type": "directional", "direction": [0, 0, 1]}]}]}))
    with pytest.warns(JaxnmWarning) as caught:
        load_fit(tmp_path / "fit.json")
    said = [str(w.message) for w in caught]
    assert len(said) == 1 and said[0].endswith(
        "is it an object-space map? (a fit's ground truth is a tangent-space map)"), said


def test_a_target_listed_twice_or_fitted_and_held_out_warns(tmp_path):
    """A fit file's target repeated (its keys in another order, the image by another path)
    counts twice and warns, as does a held-out target that is also fitted; the same image
    under other lights does not."""
    save_png(tmp_path / "t.png", np.full((16, 16, 3), 0.5, np.float32))
    (tmp_path / "scene.json").write_text(json.dumps({
        "mesh": "builtin:torus", "width": 16, "height": 16,
        "camera": {"eye": [0.0, -2.35, 1.75], "target": [0, 0, 0], "up": [0, 0, 1]}}))
    light = {"type": "directional", "direction": [0, 0, 1]}
    (tmp_path / "fit.json").write_text(json.dumps({
        "scene": "scene.json", "map": {"size": [8, 8]},
        "targets": [{"view": 0, "image": "t.png", "lights": [light]},
                    {"image": "t.png", "lights": [{**light, "direction": [1, 0, 1]}]},
                    {"lights": [dict(reversed(light.items()))], "image": "./t.png"}],
        "held_out": [{"image": "t.png", "lights": [light]}]}))
    with pytest.warns(JaxnmWarning) as caught:
        load_fit(tmp_path / "fit.json")
    where = f"{tmp_path / 'fit.json'}: "
    assert [str(w.message) for w in caught] == [
        f"{where}targets[2] repeats targets[0] (the same view, image and lights), so it counts "
        "twice in the fit",
        f"{where}held_out[0] repeats targets[0] (the same view, image and lights), so its "
        "score is not a held-out one"]


def test_fit_file_errors_name_the_file(tmp_path):
    cfg = tmp_path / "fit.json"
    cfg.write_text(json.dumps({"targets": []}))
    with pytest.raises(ValueError, match="fit.json.*targets"):
        load_fit(cfg)


@pytest.mark.slow
def test_level_sizes_halve_down_to_two_texels_and_no_further():
    """Each allowed level count gives levels that all differ (each side halved, at least 2);
    one more level, which would repeat a 2 x 2 level, is refused naming the source."""
    for hw in [(64, 64), (64, 16), (16, 64), (5, 8), (3, 3), (2, 2), (6, 6), (1000, 3)]:
        most = 0  # halve until neither side is above 2, counted by hand
        h, w = hw
        while max(h, w) > 2:
            h, w, most = max(2, h // 2), max(2, w // 2), most + 1
        sizes = F.level_sizes(hw, most)
        assert sizes[-1] == hw and len(set(sizes)) == most + 1
        assert most == 0 or sizes[0] == (2, 2)
        with pytest.raises(ValueError, match=f"^fit.json: coarse_to_fine = {most + 1} asks "
                                             f"for levels below 2x2 texels: a {hw[0]}x{hw[1]} "
                                             f"map has at most {most} coarser levels$"):
            F.level_sizes(hw, most + 1, "fit.json")


def test_coarse_to_fine_and_smoothness(small):
    """Coarse-to-fine solves 16x16 then 32x32 (upsampling the start); smoothness pulls
    towards flat slopes. Both still recover the map roughly and keep unit normals."""
    problem, gt, _, prep, seen = small
    res = F.fit_normal_map(problem, F.FitOptions(max_steps=8, coarse_to_fine=1), prepared=prep,
                           progress=False)
    sizes = [tuple(h["size"]) for h in res.history]
    assert sizes[0] == (16, 16) and sizes[-1] == (32, 32)
    assert res.normals.shape == (32, 32, 3)
    assert F.error_report(res.normals, gt, seen)["mean_deg"] < 5.0
    smooth = F.fit_normal_map(problem, F.FitOptions(max_steps=8, smoothness=10.0),
                              prepared=prep, progress=False)
    rough = F.fit_normal_map(problem, F.FitOptions(max_steps=8), prepared=prep, progress=False)
    tv = lambda s: np.abs(np.diff(s, axis=0)).mean() + np.abs(np.diff(s, axis=1)).mean()  # noqa
    assert tv(smooth.slopes) < 0.8 * tv(rough.slopes)


def test_ctrl_c_stops_after_the_current_step_and_keeps_the_best(small):
    """A KeyboardInterrupt (Ctrl-C) during the fit (here raised in the main thread after step
    3, as SIGINT would be) ends it with the best map so far; the library leaves the SIGINT
    handler alone."""
    import _thread
    import signal

    problem, _, _, prep, _ = small

    def interrupt(rec):
        if rec["step"] == 3:
            _thread.interrupt_main()  # KeyboardInterrupt at the next bytecode: in the loop
        return False

    # (SIG_IGN where pytest runs as a background job: interrupt_main would do nothing)
    before = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        res = F.fit_normal_map(problem, F.FitOptions(max_steps=100, ftol=0.0, rtol=0.0,
                                                     atol=0.0), prepared=prep, progress=False,
                               should_stop=interrupt)
        assert signal.getsignal(signal.SIGINT) is signal.default_int_handler
    finally:
        signal.signal(signal.SIGINT, before)
    assert res.stopped == "interrupted" and res.stop_test == "keyboard_interrupt"
    assert [h["step"] for h in res.history] == [0, 1, 2, 3]
    assert np.isfinite(res.best_loss) and res.best_loss == min(h["loss"] for h in res.history)


_COMPILES: list = []
_COUNTING = [False]


def _on_event(name, seconds, **kwargs):
    if _COUNTING[0] and name == "/jax/core/compile/backend_compile_duration":
        _COMPILES.append(seconds)


# registered once for the session (jax 0.8.0, the floor, cannot unregister a listener)
jax.monitoring.register_event_duration_secs_listener(_on_event)


@contextlib.contextmanager
def _backend_compiles():
    """Collect the durations of XLA backend compilations that happen inside the block."""
    _COMPILES.clear()
    _COUNTING[0] = True
    events = []
    try:
        yield events
    finally:
        _COUNTING[0] = False
        events.extend(_COMPILES)


def test_the_solver_step_compiles_once_per_problem_shape(small):
    """A second fit of a problem of the same shapes (another step count, another start, a
    coarse-to-fine schedule already seen) compiles nothing; the first one did compile."""
    problem, gt, _, prep, _ = small
    with _backend_compiles() as first:
        F.fit_normal_map(problem, F.FitOptions(max_steps=2, lsmr_steps=5, coarse_to_fine=1),
                         ground_truth=gt, prepared=prep, progress=False)
    assert len(first) > 0  # the check can fail: compilations are seen
    with _backend_compiles() as again:
        F.fit_normal_map(problem, F.FitOptions(max_steps=3, lsmr_steps=5, coarse_to_fine=1,
                                               init_noise=0.01, seed=4),
                         ground_truth=gt, prepared=prep, progress=False)
    assert again == [], f"{len(again)} recompilations ({sum(again):.1f} s)"


def _fit_folder(tmp_path, **changes):
    """A small valid fit file (a plane, two 16x16 .npy targets) with top-level changes;
    a change of None removes the key."""
    (tmp_path / "scene.json").write_text(json.dumps({
        "mesh": "builtin:plane", "width": 16, "height": 16,
        "camera": {"eye": [0, 0, 3], "target": [0, 0, 0]}}))
    for i in range(2):
        np.save(tmp_path / f"t{i}.npy", np.full((16, 16, 3), 0.5, np.float32))
    fit = {"scene": "scene.json",
           "targets": [{"image": f"t{i}.npy", "lights": [
               {"type": "directional", "direction": [0.3 * i, 0.2, 1]}]} for i in range(2)],
           "map": {"size": 8}, "solver": {"method": "lm", "max_steps": 2}}
    for k, v in changes.items():
        if v is None:
            fit.pop(k)
        else:
            fit[k] = v
    path = tmp_path / "fit.json"
    path.write_text(json.dumps(fit))
    return path


_TARGET = {"image": "t0.npy", "lights": [{"type": "directional", "direction": [0, 0, 1]}]}


@pytest.mark.parametrize("changes,match", [
    (dict(solver={"max_steps": "30"}), r"solver: 'max_steps' must be an integer, got '30'"),
    (dict(solver={"method": "newton"}), r"solver: unknown solver 'newton'"),
    (dict(solver={"max_steps": 0}), r"solver: max_steps must be an integer >= 1"),
    (dict(solver={"smoothness": -1}), r"solver: smoothness must be a finite number >= 0"),
    (dict(solver={"time_limit": "soon"}), r"solver: 'time_limit' must be a number"),
    (dict(solver={"time_limit": -1}), r"solver: 'time_limit' must be a positive number of "
     r"seconds, got -1"),
    (dict(solver={"lsmr": 3}), r"solver: unknown keys \['lsmr'\]"),
    (dict(solver={"texel_sums": "atomic"}), r"solver: unknown texel_sums 'atomic'"),
    (dict(solver={"method": "lm", "texel_sums": "tables"}), r"solver: texel_sums 'tables' is"),
    (dict(map={"size": 8, "encoding": "bogus"}), r"map: unknown encoding='bogus'"),
    (dict(map={"size": 8, "bits": 12}), r"map: 'bits' must be 8 or 16"),
    (dict(map={"size": [1, 8]}), r"map: 'size' must be"),
    (dict(map={"size": 8, "green": "left"}), r"map: unknown green='left'"),
    (dict(extra=1), r"unknown keys \['extra'\]"),
    (dict(scene=None), r"'scene' must name a scene JSON file"),
    (dict(targets=[]), r"'targets' must be a non-empty list"),
    (dict(targets=[{**_TARGET, "view": 3}]), r"targets\[0\]: 'view' = 3 but there is 1 view$"),
    (dict(targets=[{**_TARGET, "color_space": "xyz"}]), r"targets\[0\]: 'color_space' must be"),
    (dict(targets=[{**_TARGET, "lights": [{"type": "spot"}]}]), r"targets\[0\]: lights\[0\]"),
    (dict(targets=[{**_TARGET, "image": "missing.png"}]), r"missing.png"),
    (dict(ground_truth={"path": "gt.png", "encoding": "weird"}),
     r"ground_truth: unknown encoding='weird'"),
    (dict(views=[{"camera": {"eye": [0, 0, 3]}, "width": 16, "height": 16}]),
     r"views\[0\]: camera: needs 'eye' and 'target'"),
    (dict(views=[{"camera": {"eye": [0, 0, 3], "target": [0, 0, 0]}, "width": "16"}]),
     r"views\[0\]: 'width' must be an integer"),
])
def test_fit_file_errors_are_one_line_naming_file_and_field(tmp_path, capsys, changes, match):
    path = _fit_folder(tmp_path, **changes)
    with pytest.raises((ValueError, FileNotFoundError), match=match) as e:
        load_fit(path)
    assert str(path) in str(e.value) or "missing.png" in str(e.value)
    assert main(["fit", str(path), "-o", str(tmp_path / "out"), "--no-progress"]) == 2
    err = capsys.readouterr().err.strip()
    errors = [line for line in err.splitlines() if line.startswith("jaxnm fit: error: ")]
    assert len(errors) == 1 and errors[0] == err.splitlines()[-1] and "Traceback" not in err
    assert "preparing" not in err  # (checked before anything is prepared)


def test_fit_file_and_command_line_set_texel_sums(tmp_path, monkeypatch):
    """``"texel_sums"`` in the fit file's solver, and ``--texel-sums`` over it."""
    path = _fit_folder(tmp_path, solver={"method": "lm-texel", "texel_sums": "tables"})
    assert load_fit(path).options.texel_sums == "tables"
    seen = {}
    import jaxnm.fit as jfit

    def fake_fit(problem, options, **kw):
        seen["texel_sums"] = options.texel_sums
        raise KeyboardInterrupt  # stop here: only the options are checked

    monkeypatch.setattr(jfit, "fit_normal_map", fake_fit)
    assert main(["fit", str(path), "-o", str(tmp_path / "out"), "--no-progress",
                 "--texel-sums", "scatter"]) == 130  # (an interrupted command)
    assert seen == {"texel_sums": "scatter"}


def test_fit_file_fields_are_checked_before_any_file_is_read(tmp_path):
    """A bad solver field is reported although the scene file does not even exist."""
    path = _fit_folder(tmp_path, scene="nowhere.json", solver={"max_steps": "30"})
    with pytest.raises(ValueError, match="max_steps"):
        load_fit(path)


def test_fit_cli_option_errors_exit_2_naming_the_flag(tmp_path, capsys):
    path = _fit_folder(tmp_path)
    for args, message in (
            (["--max-steps", "0"], "--max-steps must be an integer >= 1, got 0"),
            (["--coarse-to-fine", "-1"], "--coarse-to-fine must be an integer >= 0, got -1"),
            (["--smoothness", "nan"], "--smoothness must be a finite number >= 0.0, got nan"),
            (["--time-limit", "-1"], "--time-limit must be a positive number of seconds, got "
                                     "-1.0"),
            (["--timeout", "10"], "--timeout is how long the processes of a fit across "
                                  "processes wait for each other: give it with --distributed"),
            (["--keep-checkpoint", "--checkpoint-every", "0"],
             "--keep-checkpoint keeps the checkpoint that --checkpoint-every 0 turns off: give "
             "one of them"),
            # a value that is wrong only with the fit file's options, once that is read
            (["--texel-sums", "tables"], f"{path} with the command line's options: "
                                         "--texel-sums 'tables' is for the 'lm-texel' solver, "
                                         "not 'lm'")):
        assert main(["fit", str(path), "--no-progress", *args]) == 2
        # (after the stage lines: "reading fit.json ...")
        assert capsys.readouterr().err.strip().splitlines()[-1] == f"jaxnm fit: error: {message}"
    job = load_fit(path)  # the valid file loads
    assert job.problem.map_size == (8, 8) and job.options.max_steps == 2


def test_fit_cli_runs_without_the_optional_extras(tmp_path, capsys, monkeypatch):
    """Without tqdm and matplotlib (the `cli` extra) `jaxnm fit` prints a line per step and
    skips loss.png; everything else is written."""
    import sys

    for name in ("tqdm", "matplotlib", "matplotlib.figure"):
        monkeypatch.setitem(sys.modules, name, None)  # `import name` raises ImportError
    path = _fit_folder(tmp_path)
    out = tmp_path / "out"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", F.FitWarning)  # two lights: not identifiable
        assert main(["fit", str(path), "-o", str(out)]) == 0
    captured = capsys.readouterr()
    assert "fit step 1/2" in captured.err and "preparing" in captured.err
    assert not (out / "loss.png").exists()
    for name in ("normal_map.png", "normal_map.npz", "render_00.png", "loss.json",
                 "report.json"):
        assert (out / name).exists(), name


def test_sample_split_when_every_pixel_reads_one_level(small):
    """A view where no pixel blends two mip levels (split == pixel count): the 4-tap gather
    alone, equal to the full plan (regression: an empty 8-tap group broke on jax 0.8)."""
    from jaxnm import textures as T

    _, gt, _, prep, _ = small
    b = prep.batches[0]
    plan = jax.tree_util.tree_map(lambda x: x[0], b.gbuffer.plan)
    k = b.split
    head = jax.tree_util.tree_map(lambda x: x[:k], plan)
    mips = T.build_mipmaps(jnp.asarray(gt), levels=prep.options[0].levels)
    np.testing.assert_allclose(np.asarray(F.sample_split(head, mips, k)),
                               np.asarray(T.apply_plan(head, mips)), atol=1e-6)


@jax.jit
def _normal_products(z, v, args):
    """J^T r and J^T J v of the residuals at ``z`` (one program per problem layout, shared by
    the tests below)."""
    r, lin = jax.linearize(lambda q: F.residuals(q, args), z)
    transpose = jax.linear_transpose(lin, z)
    return transpose(r)[0], transpose(lin(v))[0]


def test_reduced_residuals_keep_the_loss_and_the_gauss_newton_model(small):
    """The reduced residuals (4 per pixel) have the loss of the full ones (3 per target and
    pixel), the same gradient J^T r and the same Gauss-Newton products J^T J v."""
    _, gt, _, prep, _ = small
    rng = np.random.default_rng(5)
    z = jnp.asarray(rng.normal(0, 0.3, (32, 32, 2)), jnp.float32)
    v = jnp.asarray(rng.normal(0, 1.0, (32, 32, 2)), jnp.float32)
    full, red = F.ModelArgs.create(prep), F.ModelArgs.create(prep, reduce=True)
    r_full, r_red = jax.eval_shape(F.residuals, z, full), jax.eval_shape(F.residuals, z, red)
    assert sum(r.size for r in r_red) < 0.3 * sum(r.size for r in r_full)
    loss_red, g_loss = _loss_and_grad(z, red)
    np.testing.assert_allclose(float(loss_red), float(_loss_and_grad(z, full)[0]), rtol=1e-5)

    (g_full, h_full), (g_red, h_red) = _normal_products(z, v, full), _normal_products(z, v, red)
    scale = lambda x: float(jnp.max(jnp.abs(x)))  # noqa: E731
    np.testing.assert_allclose(np.asarray(g_red), np.asarray(g_full), atol=2e-4 * scale(g_full))
    np.testing.assert_allclose(np.asarray(h_red), np.asarray(h_full), atol=2e-4 * scale(h_full))
    # the loss gradient through the reduced form is exact
    np.testing.assert_allclose(np.asarray(g_loss), np.asarray(g_full), atol=2e-4 * scale(g_full))


def test_stops_when_the_loss_stops_falling(small):
    """With a loose ftol the fit stops as converged before max_steps, and the rule holds on
    the recorded history (the loss changed by less than ftol over the last `patience` steps
    and the solver's model promised no more), not one step earlier; ftol=0 runs every
    step."""
    from jaxnm.fit.stopping import promised as _promised
    from jaxnm.fit.stopping import stop_test as _stop_test

    problem, _, _, prep, _ = small
    opts = F.FitOptions(max_steps=40, ftol=0.3, patience=2)
    res = F.fit_normal_map(problem, opts, prepared=prep, progress=False)
    assert res.stopped == "converged" and res.stop_test == "ftol"
    assert len(res.history) - 1 < 40
    loss = [h["loss"] for h in res.history]
    assert abs(loss[-3] - loss[-1]) <= 0.3 * loss[-3]
    assert all(_promised(h) <= 0.3 * before["loss"]
               for before, h in zip(res.history[-3:], res.history[-2:]))
    assert _stop_test(res.history, opts) == "ftol" and _stop_test(res.history[:-1], opts) is None
    full = F.fit_normal_map(problem, F.FitOptions(max_steps=6, ftol=0.0, rtol=0.0, atol=0.0),
                            prepared=prep, progress=False)
    assert full.stopped == "max_steps" and len(full.history) == 7


def test_repeated_fits_on_one_prepared_problem_keep_it_alive(small):
    """The solver state is donated to each step; the prepared problem the caller owns must
    survive any number of fits with any solver (regression: a donated state that aliased
    the problem's arrays freed them)."""
    problem, _, _, prep, _ = small
    for solver in ("lm", "gn", "lm-texel", "lbfgs", "lm"):
        res = F.fit_normal_map(problem, F.FitOptions(solver=solver, max_steps=2),
                               prepared=prep, progress=False)
        assert np.isfinite(res.best_loss)
    leaves = jax.tree_util.tree_leaves(prep)
    assert all(not x.is_deleted() for x in leaves if isinstance(x, jax.Array))


def test_chunked_steps_equal_the_whole_step(small):
    """A problem prepared in chunks (`prepare(chunk=...)`: the step loops over pieces of every
    view) has the same per-pixel residuals, loss, gradient and Gauss-Newton products as the
    one evaluated whole; chunks are equal, and their padding weighs nothing."""
    problem, _, _, prep, _ = small
    with pytest.raises(ValueError, match="chunk"):
        F.prepare(problem, chunk=0)
    whole = prep  # (the default chunk holds this problem whole)
    cut = F.prepare(problem, chunk=600)  # 12 targets over 2 views: 256 pixels per chunk
    b, bw = cut.batches[0], whole.batches[0]
    assert bw.chunks == (1, 1) and min(b.chunks) > 1, b.chunks
    k_tail = b.pixels.shape[1] - b.split
    assert b.split % b.chunks[0] == 0 and k_tail % b.chunks[1] == 0
    assert b.split // b.chunks[0] <= 256 and k_tail // b.chunks[1] <= 256
    real = np.asarray(b.pixels) >= 0
    assert np.all(np.asarray(b.weights)[..., 0].transpose(1, 0, 2)[:, ~real] == 0)

    def images(prep, z):  # the full residuals per view, target and image pixel
        r = F.residuals(z, F.ModelArgs.create(prep))[0]
        bb = prep.batches[0]
        v, t, k = bb.images.shape[:3]
        out = np.zeros((v, t, 64 * 64, 3), np.float32)
        for i in range(v):
            keep = np.asarray(bb.pixels[i]) >= 0
            out[i][:, np.asarray(bb.pixels[i])[keep]] = np.asarray(r).reshape(v, t, k, 3)[i][
                :, keep]
        return out

    rng = np.random.default_rng(1)
    z = jnp.asarray(rng.normal(0, 0.3, (32, 32, 2)), jnp.float32)
    v = jnp.asarray(rng.normal(0, 1.0, (32, 32, 2)), jnp.float32)
    # equal up to float32 rounding (the loop fuses the shading differently: specular powers
    # amplify a last-bit difference to ~4e-5 relative on a few pixels)
    np.testing.assert_allclose(images(cut, z), images(whole, z), rtol=1e-4, atol=1e-6)
    for reduce in (False, True):
        a_cut = F.ModelArgs.create(cut, reduce=reduce)
        a_whole = F.ModelArgs.create(whole, reduce=reduce)
        np.testing.assert_allclose(float(_loss_and_grad(z, a_cut)[0]),
                                   float(_loss_and_grad(z, a_whole)[0]), rtol=1e-5)

        for got, want in zip(_normal_products(z, v, a_cut), _normal_products(z, v, a_whole)):
            scale = float(jnp.max(jnp.abs(want)))
            np.testing.assert_allclose(np.asarray(got), np.asarray(want), atol=1e-5 * scale)


def test_the_fit_follows_optimistix_own_steps(small):
    """The fit loop keeps one linearisation in the state it carries between steps (optimistix's
    LM holds it twice); its path must still be optimistix's: the same map as the solver's own
    ``init`` and ``step`` on the whole state, from the same start, for as many steps."""
    import equinox as eqx

    from jaxnm.fit.solve import _start_slopes

    problem, _, _, prep, _ = small
    opts = F.FitOptions(solver="lm", max_steps=4, lsmr_steps=5, ftol=0.0, init_noise=0.05)
    res = F.fit_normal_map(problem, opts, prepared=prep, progress=False)
    scale = F.preconditioner(prep)
    args = F.ModelArgs.create(prep, scale=scale, reduce=True)
    z = jnp.asarray(_start_slopes(problem.map_size, opts)) / scale
    solver = F.make_solver(opts)
    fn = lambda z, a: (F.residuals(z, a), None)  # noqa: E731
    state = solver.init(fn, z, args, {}, jax.eval_shape(F.residuals, z, args), None,
                        frozenset())
    step = eqx.filter_jit(lambda z, s: solver.step(fn, z, args, {}, s, frozenset())[:2])
    start = np.asarray(z * scale)
    for _ in range(opts.max_steps + 1):  # the fit's first step evaluates the start
        z, state = step(z, state)
    assert res.stopped == "max_steps" and len(res.history) == opts.max_steps + 1
    np.testing.assert_allclose(res.slopes, np.asarray(z * scale), rtol=1e-4, atol=1e-5)
    assert np.abs(res.slopes - start).max() > 0.5  # the fit moved


def test_prepare_with_stored_neighbour_derivatives_builds_the_whole_image(small):
    """"gbuffer" derivatives need the whole image's G-buffer (`build_gbuffer`), every other
    mode the covered pixels only (`covered_gbuffer`): the same pixels either way, and the
    same positions and sample plans where the two agree (away from silhouettes the
    difference of stored neighbours is the fine derivative)."""
    problem, _, _, prep, _ = small
    whole = F.prepare(dataclasses.replace(problem, derivatives="gbuffer"))
    for v in range(prep.num_views):
        a, b = prep.view(v), whole.view(v)
        ia, ib = np.argsort(a.pixels), np.argsort(b.pixels)  # (batched by their taps first)
        np.testing.assert_array_equal(a.pixels[ia], b.pixels[ib])
        np.testing.assert_allclose(a.gbuffer.position[ia], b.gbuffer.position[ib], atol=1e-5)
        np.testing.assert_array_equal(a.images[:, ia], b.images[:, ib])


@pytest.mark.parametrize("map_size", [(32, 32), (21, 27)])
def test_texel_influence_is_the_sampling_operators_column_sums(small, map_size, monkeypatch):
    """`texel_influence` (NumPy, the mip filter's transpose as matrices) against the VJP of
    sampling the mip chain (JAX), with odd and even levels (21x27 -> 10x13 -> 5x6 -> 2x3 ->
    1x1); summed in one piece and in pieces of a few pixels."""
    import importlib

    from jaxnm import textures as T

    prep = small[3] if map_size == (32, 32) else F.prepare(
        dataclasses.replace(small[0], map_size=map_size))
    levels = prep.options[0].levels
    assert levels == len(T.mip_sizes(map_size)) > 1  # trilinear: the whole chain

    def sampled(t):
        mips = T.build_mipmaps(t, levels=levels)
        return [T.apply_plan(b.gbuffer.plan, mips)[..., 0] * b.weights.sum(1)[..., 0]
                for b in prep.batches]

    _, vjp = jax.vjp(sampled, jnp.zeros(map_size + (1,), jnp.float32))
    want = np.asarray(vjp([jnp.ones(b.pixels.shape, jnp.float32) for b in prep.batches])[0])
    got = F.texel_influence(prep)
    assert got.shape == map_size and got.dtype == np.float32
    assert (got > 0).sum() > 0.3 * got.size
    np.testing.assert_allclose(got, want[..., 0], rtol=2e-5, atol=1e-6 * want.max())
    D = importlib.import_module("jaxnm.fit.diagnostics")
    b = prep.batches[0]
    texels = sum(h * w for h, w in T.mip_sizes(map_size))
    assert b.pixels.size <= D._INFLUENCE_ROWS  # one piece above; several below:
    assert b.pixels.size > 2 * max(7, texels // b.gbuffer.plan.index.shape[-1])
    monkeypatch.setattr(D, "_INFLUENCE_ROWS", 7)  # pieces as short as the levels allow
    np.testing.assert_allclose(F.texel_influence(prep), got, rtol=1e-6, atol=1e-7 * got.max())


@pytest.fixture(scope="module")
def tiny_problem():
    return default_problem(render_size=16, map_size=8, n_lights=3, views=1)[0]


@pytest.mark.parametrize("call,error,message", [
    (dict(options={"max_steps": 2}), TypeError,
     "fit_normal_map: options must be a FitOptions, got dict"),
    (dict(problem="fit.json"), TypeError, "fit_normal_map: problem must be a FitProblem, got str"),
    (dict(strength=0.0), ValueError, "strength must be a finite number other than 0 (the map's "
                                     "x/y scale), got 0.0"),
    (dict(strength=float("nan")), ValueError, "strength must be a finite number other than 0"),
    (dict(time_limit=-1), ValueError, "time_limit must be a number of seconds >= 0 (0: the "
                                      "start alone) or None, got -1"),
    (dict(time_limit=float("nan")), ValueError, "time_limit must be a number of seconds >= 0"),
    (dict(progress="bars"), ValueError, "fit_normal_map: progress must be True, False or "
                                        "'lines', got 'bars'"),
])
def test_fit_arguments_of_the_wrong_kind_or_range_are_refused_before_anything_runs(
        monkeypatch, tiny_problem, call, error, message):
    import jaxnm.fit.solve as S

    def no_setup(*a, **k):
        raise AssertionError("the fit was set up before its arguments were checked")

    monkeypatch.setattr(S, "_setup", no_setup)
    args = {"problem": tiny_problem, "options": F.FitOptions(max_steps=1), **call}
    with pytest.raises(error, match=re.escape(message)):
        F.fit_normal_map(args.pop("problem"), args.pop("options"), **args)


def test_prepare_refuses_what_is_not_a_problem():
    with pytest.raises(TypeError, match=r"^prepare: problem must be a FitProblem "
                                        r"\(jaxnm.config.load_fit, jaxnm.fit.FitProblem\), got "
                                        r"str$"):
        F.prepare("fit.json")


@pytest.mark.parametrize("call, message", [
    (dict(render_size=0), "default_problem: render_size must be an integer 1 to 16384, got 0"),
    (dict(render_size=16.0), "default_problem: render_size must be an integer 1 to 16384, "
                             "got 16.0"),
    (dict(map_size=1), "default_problem: map_size must be an integer >= 2, got 1"),
    (dict(n_lights=0), "default_problem: n_lights must be an integer >= 1, got 0"),
    (dict(views=True), "default_problem: views must be an integer 1 to 3, got True"),
    (dict(views=4), "default_problem: views must be an integer 1 to 3, got 4"),
    (dict(seed=None), "default_problem: seed must be an integer >= 0, got None"),
    (dict(noise=-0.1), "default_problem: noise must be a finite number >= 0, got -0.1"),
    (dict(noise=float("nan")), "default_problem: noise must be a finite number >= 0, got nan"),
])
def test_the_built_in_problem_refuses_arguments_out_of_range_before_rendering(
        monkeypatch, call, message):
    """Each argument is named in one line (a render size of 0 divided by zero, no lights
    made a problem without targets, a negative or NaN noise was ignored)."""
    import jaxnm.procedural.builtin as B

    def no_render(*a, **k):
        raise AssertionError("the problem was rendered before its arguments were checked")

    monkeypatch.setattr(B, "render", no_render)
    with pytest.raises(ValueError, match=f"^{re.escape(message)}$"):
        default_problem(**{"render_size": 16, "map_size": 8, **call})


def test_the_built_in_scene_names_a_size_out_of_range():
    from jaxnm.procedural import default_fit_job, default_scene

    with pytest.raises(ValueError, match=r"^default_scene: `width` must be a positive integer, "
                                         r"got 0$"):
        default_scene(width=0, height=8)  # said "camera: `aspect` must be positive"
    with pytest.raises(ValueError, match=r"^default_scene: `height` must be a positive integer, "
                                         r"got '8'$"):
        default_scene(width=8, height="8")
    with pytest.raises(ValueError, match="^default_fit_job: quick must be True or False, got "
                                         "'yes'$"):
        default_fit_job(quick="yes")
