"""The command line as a user meets it: Ctrl-C at any moment (no crash, exit code 130,
nothing lost), progress lines, one-line warnings and errors, files checked before anything
is loaded, frame aliases, one image per light, the outputs asked for."""

from __future__ import annotations

import gc
import json
import os
import re
import shlex
import signal
import subprocess
import sys
import threading
import time
import warnings
from pathlib import Path

import numpy as np
import pytest

import jaxnm
from jaxnm import fit as F
from jaxnm import io
from jaxnm.cli import main
from jaxnm.cli._fit import CHECKPOINT_NAME

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture
def sigint():
    """SIGINT handled by Python while the test runs (it is ignored in background jobs)."""
    before = signal.signal(signal.SIGINT, signal.default_int_handler)
    yield
    signal.signal(signal.SIGINT, before)


def _fit_folder(folder: Path, *, size: int = 24, lights: int = 4, target_size=None) -> Path:
    """A small fit file: the built-in plane seen head-on at ``size`` px under ``lights``
    directional lights, its targets rendered with the built-in rivet map (as .npy)."""
    folder.mkdir(parents=True, exist_ok=True)
    scene = {"mesh": "builtin:plane", "width": size, "height": size,
             "camera": {"eye": [0.3, -0.4, 2.6], "target": [0, 0, 0], "up": [0, 1, 0]},
             "normal_map": "builtin:rivets"}
    (folder / "scene.json").write_text(json.dumps(scene))
    s = jaxnm.load_scene(folder / "scene.json")
    targets = []
    for i in range(lights):
        a = 2 * np.pi * i / lights
        d = [float(np.cos(a)), float(np.sin(a)), 1.2]
        img = np.asarray(jaxnm.render(s.replace(lights=jaxnm.directional_light(d)))["color"])
        if target_size is not None and i == lights - 1:
            img = img[:target_size, :target_size]
        np.save(folder / f"t{i}.npy", img.astype(np.float32))
        targets.append({"image": f"t{i}.npy",
                        "lights": [{"type": "directional", "direction": d}]})
    (folder / "scene_plain.json").write_text(json.dumps({**scene, "normal_map": None}))
    fit = {"scene": "scene_plain.json", "targets": targets, "map": {"size": 16},
           "solver": {"method": "lm-texel", "max_steps": 3, "lsmr_steps": 5, "ftol": 0}}
    (folder / "fit.json").write_text(json.dumps(fit))
    return folder / "fit.json"


def _fit(*args) -> int:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", F.FitWarning)
        return main(["fit", *map(str, args)])


def _no_temporaries(folder: Path) -> None:
    assert not [p.name for p in folder.rglob("*.tmp")]


# ----------------------------------------------------------------------------- Ctrl-C


# The child restores Python's SIGINT handler itself (a child of a background job starts with
# SIGINT ignored): a ``preexec_fn`` would run the parent's fork hooks, JAX's warning included.
_LAUNCH = ("import runpy, signal; signal.signal(signal.SIGINT, signal.default_int_handler); "
           "runpy.run_module('jaxnm_launcher', run_name='__main__', alter_sys=True)")


def _interrupt(out: Path, *, after: str | None, delay: float, count: int = 1,
               compile: bool = True):
    """Run ``jaxnm fit --quick -o out --no-progress`` through the ``jaxnm`` launcher, send it
    ``count`` SIGINTs ``delay`` seconds after the stderr line starting with ``after`` (after
    the start for None); returns the exit code and stderr. With ``compile`` the child has no
    compilation cache, so that XLA compiles while it runs; without, it shares the suite's
    persistent cache (conftest.py), for Ctrl-Cs that land after the compiles."""
    env = dict(os.environ)
    if compile:
        env["JAXNM_COMPILATION_CACHE"] = "off"
    proc = subprocess.Popen(
        [sys.executable, "-c", _LAUNCH, "fit", "--quick", "-o", str(out),
         "--no-progress"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        cwd=ROOT, env=env)
    lines, seen = [], threading.Event()

    def read():
        for line in proc.stderr:
            lines.append(line)
            if after is not None and line.startswith(after):
                seen.set()

    reader = threading.Thread(target=read, daemon=True)
    reader.start()
    try:
        if after is not None:
            assert seen.wait(300), "".join(lines)
        time.sleep(delay)
        for _ in range(count):
            proc.send_signal(signal.SIGINT)
            time.sleep(0.05)
        rc = proc.wait(300)
    finally:
        proc.kill()
    reader.join(10)
    proc.stdout.close()
    proc.stderr.close()
    return rc, "".join(lines)


@pytest.mark.slow
@pytest.mark.parametrize("after,delay", [
    (None, 0.3),  # while JAX is imported
    ("rendering the built-in problem's targets", 0.7),  # XLA compiling the renders
    ("preparing", 0.2),
    ("compiling the fit's step", 0.3),
    ("fit step 1/", 0.0),
    ("writing outputs", 0.0),
])
def test_ctrl_c_at_any_moment_exits_130_and_loses_nothing(tmp_path, after, delay):
    """Ctrl-C at any moment of ``jaxnm fit``: exit code 130, no crash, no Python traceback
    or ignored exception; before the fit nothing is written and what was in the folder
    stays; once the fit has run, its map and report are written, the report saying it was
    interrupted; never a temporary file left."""
    out = tmp_path / "out"
    out.mkdir()
    (out / "earlier.txt").write_text("kept")
    # Ctrl-Cs once the fit runs need no compiling child: those share the suite's cache
    rc, err = _interrupt(out, after=after, delay=delay,
                         compile=after not in ("fit step 1/", "writing outputs"))
    assert rc == 130, err
    for bad in ("Traceback", "Exception ignored", "Fatal Python error", "Segmentation"):
        assert bad not in err, err
    assert (out / "earlier.txt").read_text() == "kept"
    _no_temporaries(out)
    if (out / "report.json").exists():
        report = json.loads((out / "report.json").read_text())
        assert report["interrupted"] is True, report
        with np.load(out / "normal_map.npz") as z:
            assert np.isfinite(z["normals"]).all()
    else:
        assert err.rstrip().endswith("jaxnm fit: interrupted"), err
        assert sorted(p.name for p in out.iterdir()) == ["earlier.txt"]
    if after in ("fit step 1/", "writing outputs"):
        assert (out / "report.json").exists(), err


@pytest.mark.slow
def test_a_second_ctrl_c_while_xla_compiles_stops_at_once(tmp_path):
    out = tmp_path / "out"
    rc, err = _interrupt(out, after="rendering the built-in problem's targets", delay=0.7,
                         count=2)
    assert rc == 130 and "jaxnm fit: stopped" in err, err
    for bad in ("Traceback", "Exception ignored", "Fatal Python error"):
        assert bad not in err, err
    assert not out.exists() or not list(out.iterdir())


def test_a_ctrl_c_inside_a_garbage_collector_callback_is_not_lost(tmp_path, monkeypatch,
                                                                  sigint):
    """Python runs a signal handler wherever the main thread is, a garbage-collector callback
    included, where an exception would only be printed and the command would go on: the
    Ctrl-C that arrives there still stops the command (130, nothing written)."""
    path = _fit_folder(tmp_path / "job")
    prepare = F.prepare

    def callback(phase, info):
        if phase == "start" and not fired:
            fired.append(True)
            signal.raise_signal(signal.SIGINT)

    def prepare_with_a_collection(*a, **k):
        gc.callbacks.append(callback)
        try:
            gc.collect()
        finally:
            gc.callbacks.remove(callback)
        return prepare(*a, **k)

    fired: list = []
    monkeypatch.setattr(F, "prepare", prepare_with_a_collection)
    out = tmp_path / "out"
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # an ignored exception would be a warning
        assert _fit(path, "-o", out, "--no-progress") == 130
    assert fired and not out.exists()


# ----------------------------------------------------------------------------- output


def test_no_progress_prints_a_line_per_stage_and_per_step(tmp_path, capsys):
    path = _fit_folder(tmp_path / "job")
    assert _fit(path, "-o", tmp_path / "out", "--no-progress") == 0
    err = capsys.readouterr().err.splitlines()
    stages = [line for line in err if not line.startswith("fit step")]
    assert stages == [f"reading {path} ...",
                      "preparing 4 targets (rasterizing each view once) ...",
                      "compiling the fit's step ...", "fitting ...", "writing outputs ..."], err
    steps = [line for line in err if line.startswith("fit step")]
    assert [s.split(" (")[0] for s in steps] == ["fit step 1/3", "fit step 2/3",
                                                 "fit step 3/3"], err
    assert all("): loss " in s for s in steps)


def _quad_obj(path: Path) -> None:
    """A unit quad with uvs and no vertex normals."""
    path.write_text("v -1 -1 0\nv 1 -1 0\nv 1 1 0\nv -1 1 0\n"
                    "vt 0 0\nvt 1 0\nvt 1 1\nvt 0 1\nf 1/1 2/2 3/3\nf 1/1 3/3 4/4\n")


def test_warnings_are_one_line_naming_the_file(tmp_path, capsys):
    """A warning from the library (a mesh without normals; lights that cannot determine a
    map) is one line, ``jaxnm render: warning: FILE: ...``, without Python's source line."""
    _quad_obj(tmp_path / "quad.obj")
    (tmp_path / "scene.json").write_text(json.dumps({
        "mesh": "quad.obj", "width": 16, "height": 16,
        "camera": {"eye": [0, 0, 3], "target": [0, 0, 0]}}))
    with warnings.catch_warnings():
        warnings.simplefilter("default")
        assert main(["render", str(tmp_path / "scene.json"), "-o",
                     str(tmp_path / "r.png")]) == 0
    err = capsys.readouterr().err.splitlines()
    assert err == [f"jaxnm render: warning: {tmp_path / 'quad.obj'}: no vertex normals in "
                   "the file; computed angle-weighted normals"], err
    path = _fit_folder(tmp_path / "job", lights=1)  # one light: not identifiable
    with warnings.catch_warnings():
        warnings.simplefilter("default")
        assert main(["fit", str(path), "-o", str(tmp_path / "out"), "--max-steps", "1"]) == 0
    said = capsys.readouterr()
    assert "fit reached the step limit (1 step) after 1 step in " in said.out, said.out
    warned = [line for line in said.err.splitlines() if ": warning: " in line]
    assert len(warned) == 1 and warned[0].startswith(f"jaxnm fit: warning: {path}: "), warned
    assert "no view has at least three lights" in warned[0]


def test_an_object_space_map_given_as_tangent_space_warns(tmp_path, capsys):
    """A normal map half of whose texels point into the surface is named as a likely
    object-space map, from a scene file (with its field) and from ``--normal-map``; the
    same map declared ``"space": "object"`` is not."""
    u, v = np.meshgrid((np.arange(16) + 0.5) / 16, (np.arange(8) + 0.5) / 8)
    n = np.stack([np.sin(np.pi * v) * np.cos(2 * np.pi * u),
                  np.sin(np.pi * v) * np.sin(2 * np.pi * u), np.cos(np.pi * v)], -1)
    scene = _scene_folder(tmp_path, mesh="builtin:torus")
    io.save_png(tmp_path / "map.png", (n * 0.5 + 0.5).astype(np.float32))
    out = str(tmp_path / "r.png")
    for args, name in (([str(scene)], f"{scene}: normal_map: map.png"),
                       (["--normal-map", str(tmp_path / "map.png"), "--width", "16", "--height",
                         "16"], str(tmp_path / "map.png"))):
        with warnings.catch_warnings():
            warnings.simplefilter("default")
            assert main(["render", *args, "-o", out]) == 0
        err = capsys.readouterr().err.splitlines()
        assert err == [f"jaxnm render: warning: {name}: 50% of its texels point into the "
                       "surface (z < 0 once decoded), where a tangent-space map's point out of "
                       "it; is it an object-space map? (a scene file's normal_map takes "
                       "\"space\": \"object\")"], err
    _scene_folder(tmp_path, mesh="builtin:torus",
                  normal_map={"path": "map.png", "space": "object"})
    io.save_png(tmp_path / "map.png", (n * 0.5 + 0.5).astype(np.float32))
    assert main(["render", str(scene), "-o", out]) == 0  # (warnings are errors here)


def _scene_folder(tmp_path: Path, **changes) -> Path:
    _quad_obj(tmp_path / "quad.obj")
    io.save_png(tmp_path / "map.png", np.full((8, 8, 3), 0.5, np.float32))
    scene = {"mesh": "quad.obj", "width": 16, "height": 16,
             "camera": {"eye": [0, 0, 3], "target": [0, 0, 0]},
             "normal_map": {"path": "map.png", "encoding": "unsigned"}}
    scene.update(changes)
    (tmp_path / "scene.json").write_text(json.dumps(scene))
    return tmp_path / "scene.json"


@pytest.mark.parametrize("changes,message", [
    ({"normal_map": {"path": "map.png", "encodng": "unsigned"}},
     "normal_map: unknown keys ['encodng'] (a typo? 'encodng' for 'encoding'); known keys are "
     "['channels', 'encoding', 'filter', 'green', 'path', 'space', 'strength', 'uv_origin', "
     "'wrap']"),
    ({"normal_map": {"path": "map.png", "tint": 1}},
     "normal_map: unknown keys ['tint']; known keys are ['channels', 'encoding', 'filter', "),
    ({"normal_map": {"path": "map.png", "wrap": "around"}}, "normal_map: unknown wrap="),
    ({"normal_map": {"path": "map.png", "encoding": "sideways"}}, "normal_map: unknown encoding="),
    ({"normal_map": "mapp.png"}, "normal_map: {dir}/mapp.png: no such file"),
    ({"mesh": "quadd.obj"}, "mesh: {dir}/quadd.obj: no such file"),
    ({"albedo": {"path": "albedo.png"}}, "albedo: {dir}/albedo.png: no such file"),
    ({"mesh": "map.png"}, "mesh: {dir}/map.png: not a mesh format that jaxnm reads (.png); it "
     "reads .obj, .ply, .gltf, .glb, .stl, .off"),
    ({"normal_map": "scene.json"}, "normal_map: {dir}/scene.json: not a normal map format "
     "that jaxnm reads (.json); it reads .png, .jpg, .jpeg, .npy, .npz, .dds"),
    ({"albedo": {"path": "quad.obj"}}, "albedo: {dir}/quad.obj: not a texture format"),
    ({"frame": "sideways"}, "unknown frame 'sideways'"),
])
def test_a_scene_file_is_checked_whole_before_any_file_is_read(tmp_path, monkeypatch, capsys,
                                                               changes, message):
    """A fault anywhere in a scene file, a missing file included, is one line naming the
    file and the field, before any file (the mesh, the map) is read."""
    path = _scene_folder(tmp_path, **changes)
    read = []
    monkeypatch.setattr(io, "load_mesh", lambda *a, **k: read.append(a) or pytest.fail("read"))
    monkeypatch.setattr(io, "load_texture", lambda *a, **k: read.append(a) or pytest.fail("read"))
    assert main(["render", str(path), "-o", str(tmp_path / "r.png")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and err.startswith(f"jaxnm render: error: {path}: "), err
    assert message.format(dir=tmp_path) in err, err
    assert not read


def test_a_file_that_does_not_read_names_the_scene_or_fit_file_and_its_field(tmp_path,
                                                                             capsys):
    """A named file that exists but does not read (not an image, NaN values, a broken OBJ)
    is one line naming the scene or fit file and the field, as a missing one is (it named
    the inner file alone)."""
    path = _scene_folder(tmp_path)
    (tmp_path / "map.png").write_text("not a png")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", io.JaxnmWarning)  # (the quad's normals, computed)
        assert main(["render", str(path), "-o", str(tmp_path / "r.png")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith(f"jaxnm render: error: {path}: normal_map: {tmp_path / 'map.png'}: "
                          "not an image or unreadable"), err
    (tmp_path / "quad.obj").write_text("v 0 0 0\nvn 0 0 1\nf 1//1 2//1 3//1\n")
    assert main(["render", str(path), "-o", str(tmp_path / "r.png")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith(f"jaxnm render: error: {path}: mesh: {tmp_path / 'quad.obj'}: line 3: "
                          "a face refers to vertex 2"), err
    fit = _fit_folder(tmp_path / "job")
    data = json.loads(fit.read_text())
    np.save(fit.parent / "t1.npy", np.full((24, 24, 3), np.nan, np.float32))
    data["targets"][0]["mask"] = "scene.json.png"
    (fit.parent / "scene.json.png").write_text("{}")
    for target, field, problem in ((0, "mask", "not an image or unreadable"),
                                   (1, "image", "the image contains NaN or infinite values")):
        fit.write_text(json.dumps(data))
        assert _fit(fit, "-o", tmp_path / "out") == 2
        name = {"mask": "scene.json.png", "image": "t1.npy"}[field]
        line = capsys.readouterr().err.strip().splitlines()[-1]
        assert line.startswith(f"jaxnm fit: error: {fit}: targets[{target}]: {field}: "
                               f"{fit.parent / name}: {problem}"), line
        data["targets"][0].pop("mask", None)


def test_a_fit_file_is_checked_whole_and_targets_against_their_view(tmp_path, monkeypatch,
                                                                    capsys):
    """A target image of the wrong size is reported when it is read, before the scene's mesh
    is read and anything prepared; a missing target names its field."""
    path = _fit_folder(tmp_path / "job", target_size=20)
    loaded = []
    real = io.load_mesh
    monkeypatch.setattr(io, "load_mesh", lambda *a, **k: loaded.append(a) or real(*a, **k))
    assert _fit(path, "-o", tmp_path / "out", "--no-progress") == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1] == (f"jaxnm fit: error: {path}: targets[3]: image: {path.parent / 't3.npy'} "
                       "is 20x20, but its view renders 24x24"), err
    assert len(err) == 2 and not loaded
    fit = json.loads(path.read_text())
    fit["targets"][1]["image"] = "t9.npy"
    path.write_text(json.dumps(fit))
    assert _fit(path, "-o", tmp_path / "out") == 2
    assert capsys.readouterr().err.strip().splitlines()[-1] == (
        f"jaxnm fit: error: {path}: targets[1]: image: {path.parent / 't9.npy'}: no such file")
    fit["targets"][1]["image"] = path.name  # a file, but not an image
    path.write_text(json.dumps(fit))
    assert _fit(path, "-o", tmp_path / "out") == 2
    assert capsys.readouterr().err.strip().splitlines()[-1] == (
        f"jaxnm fit: error: {path}: targets[1]: image: {path}: not an image format that jaxnm "
        f"reads (.json); it reads .png, .jpg, .jpeg, .npy, .npz, .exr")


def test_more_coarse_levels_than_the_map_has_are_refused_before_the_work(tmp_path, capsys,
                                                                         monkeypatch):
    """A 16x16 map halves 3 times to 2x2: ``--coarse-to-fine 4`` (or the fit file's
    ``coarse_to_fine``) would solve 2x2 twice; refused before anything is prepared."""
    path = _fit_folder(tmp_path / "job")
    monkeypatch.setattr(F, "prepare", lambda *a, **k: pytest.fail("prepared"))
    assert _fit(path, "-o", tmp_path / "out", "--coarse-to-fine", "4") == 2
    assert capsys.readouterr().err.strip().splitlines()[-1] == (
        f"jaxnm fit: error: {path}: --coarse-to-fine 4 asks for levels below 2x2 texels: a "
        "16x16 map has at most 3 coarser levels")
    fit = json.loads(path.read_text())
    fit["solver"]["coarse_to_fine"] = 4
    path.write_text(json.dumps(fit))
    assert _fit(path, "-o", tmp_path / "out") == 2
    assert capsys.readouterr().err.strip().splitlines()[-1] == (
        f"jaxnm fit: error: {path}: coarse_to_fine = 4 asks for levels below 2x2 texels: a "
        "16x16 map has at most 3 coarser levels")
    assert not (tmp_path / "out").exists()


# ----------------------------------------------------------------------------- render


def test_frames_answer_to_the_names_users_know(tmp_path, capsys):
    """``--frame mikktspace`` is ``vertex``, ``--frame schuler`` is ``cotangent`` (the same
    image, byte for byte); an unknown frame is one line that says which name means what."""
    def png(frame):
        out = tmp_path / f"{frame}.png"
        assert main(["render", "-o", str(out), "--width", "32", "--height", "32",
                     "--frame", frame]) == 0
        return out.read_bytes()

    assert png("mikktspace") == png("vertex") != png("cotangent") == png("schuler")
    capsys.readouterr()
    with pytest.raises(SystemExit) as e:
        main(["render", "--frame", "tbn"])
    assert e.value.code == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and err.startswith("jaxnm render: error: argument --frame")
    assert "mikktspace = vertex" in err and "schuler = cotangent" in err, err


def test_one_image_per_light_and_a_fit_file_naming_them(tmp_path):
    """``--light`` twice: two images, each the scene rendered under that light alone, and a
    fit file whose targets are those images under those lights, seen by the scene's camera;
    ``jaxnm fit`` runs on it."""
    scene = tmp_path / "scene.json"
    scene.write_text(json.dumps({"mesh": "builtin:plane", "width": 24, "height": 20,
                                 "camera": {"eye": [0, -1, 2.5], "target": [0, 0, 0]},
                                 "normal_map": "builtin:rivets"}))
    lights = [(0.0, 0.0, 1.0), (1.0, -0.5, 1.0), (-1.0, -0.5, 1.0)]
    args = ["--light=" + ",".join(map(str, d)) for d in lights]  # (-1,... is not an option)
    out = tmp_path / "targets" / "t.png"
    assert main(["render", str(scene), "-o", str(out), *args]) == 0
    job = jaxnm.load_fit(out.parent / "t_targets.json")
    s = jaxnm.load_scene(scene)
    assert len(job.problem.targets) == 3
    for i, (d, t) in enumerate(zip(lights, job.problem.targets, strict=True)):
        ref = np.asarray(jaxnm.render(s.replace(lights=jaxnm.directional_light(d)))["color"])
        got, _ = io.load_image_float(out.parent / f"t_{i:02d}.png")
        srgb = np.asarray(jaxnm.shading.to_display(ref))
        assert np.abs(got - srgb).max() <= 0.5 / 255 + 1e-6
        np.testing.assert_array_equal(np.asarray(t.lights.directional.direction)[0], d)
        np.testing.assert_allclose(np.asarray(t.camera.view), np.asarray(s.camera.view))
        assert (t.width, t.height) == (24, 20)
    fit = json.loads((out.parent / "t_targets.json").read_text())
    fit.update(map={"size": 8}, solver={"max_steps": 1})
    (out.parent / "t_targets.json").write_text(json.dumps(fit))
    assert _fit(out.parent / "t_targets.json", "-o", tmp_path / "fit") == 0


@pytest.mark.parametrize("source", ["built-in", "mesh file", "scene file, --frame vertex"])
def test_the_targets_fit_file_names_the_scene_the_images_were_rendered_from(tmp_path, source):
    """``--light`` with the built-in scene, a mesh file, or a scene file whose frame the
    command changed: the fit file names a scene file (written beside it where the scene has
    none, or a copy whose files are named from its new folder) whose fit model, given the
    map the images were rendered with, renders those images again (to their 8-bit sRGB
    rounding), so that a fit of them fits the map that made them."""
    out = tmp_path / "targets" / "t.png"
    lights = ["--light", "0,0,1", "--light", "1,-1,1", "--light=-1,-1,1"]
    size, truth = ["--width", "24", "--height", "20"], jaxnm.procedural.default_normal_map(256)
    if source == "mesh file":
        io.save_obj(tmp_path / "m.obj", jaxnm.procedural.torus(1.0, 0.4, 24, 12))
        argv = [str(tmp_path / "m.obj"), *size]
        truth = np.broadcast_to(np.float32([0, 0, 1]), truth.shape)  # (no map: flat)
    elif source == "built-in":
        argv = size
    else:
        (tmp_path / "in").mkdir()
        io.save_png(tmp_path / "in" / "albedo.png", np.float32([[[0.9, 0.3, 0.2]]]))
        (tmp_path / "in" / "scene.json").write_text(json.dumps({
            "mesh": "builtin:torus", "width": 24, "height": 20, "normal_map": "builtin:rivets",
            "albedo": {"path": "albedo.png", "srgb": False},
            "camera": {"eye": [0, -2.3, 1.7], "target": [0, 0, 0], "up": [0, 0, 1]}}))
        argv = [str(tmp_path / "in" / "scene.json"), "--frame", "vertex"]
    assert main(["render", *argv, "-o", str(out), *lights]) == 0
    fit = json.loads((out.parent / "t_targets.json").read_text())
    assert fit["scene"] == "t_scene.json"
    if source.startswith("scene file"):
        written = json.loads((out.parent / "t_scene.json").read_text())
        assert written["frame"] == "vertex" and written["albedo"]["path"] == "../in/albedo.png"
    job = jaxnm.load_fit(out.parent / "t_targets.json")
    prep = F.prepare(job.problem)
    again = F.render_with_map(prep, np.asarray(truth, np.float32))[0]
    for i in range(3):
        got = np.asarray(jaxnm.shading.to_display(again[i]))
        png, _ = io.load_image_float(out.parent / f"t_{i:02d}.png")
        assert np.abs(got - png)[prep.target_mask(0)].max() < 3 / 255, (source, i)


def test_a_mesh_file_is_rendered_whole_and_exposure_is_refused_beside_light(tmp_path, capsys):
    """``jaxnm render MESH``: the whole mesh in view (no covered pixel on the image's border),
    filling most of its narrower side; ``--exposure`` with ``--light`` is refused, as the fit
    file could not describe the scaled images."""
    moved = np.eye(4)
    moved[:3, 3] = (5.0, -2.0, 1.0)  # far from the origin, which the view must not assume
    io.save_obj(tmp_path / "m.obj", jaxnm.procedural.uv_sphere(3.0, 16, 8).transformed(moved))
    aovs = tmp_path / "a.npz"
    assert main(["render", str(tmp_path / "m.obj"), "-o", str(tmp_path / "m.png"), "--width",
                 "40", "--height", "24", "--aovs", str(aovs), "--aov-list", "mask"]) == 0
    mask = io.load_aovs(aovs)["mask"][..., 0] > 0
    assert mask.shape == (24, 40) and not (mask[[0, -1]].any() or mask[:, [0, -1]].any())
    assert mask.any(1).sum() > 0.75 * 24
    capsys.readouterr()
    assert main(["render", "-o", str(tmp_path / "x.png"), "--light", "0,0,1", "--exposure",
                 "2"]) == 2
    assert capsys.readouterr().err.strip() == (
        "jaxnm render: error: --exposure scales the images, and the fit file --light writes "
        "beside them could not say so: leave one of them out")


def test_up_z_shows_a_z_up_mesh_upright_from_its_front(tmp_path, capsys):
    """``--up z`` (Blender's, most STL and CAD files' axis): a sphere stretched twice along z
    stands upright in the image, seen from -y, Blender's front; with the default y up the
    same mesh lies along the view and is no taller than wide. ``--up`` beside a scene file
    or the built-in scene is refused."""
    from jaxnm.cli._render import _mesh_scene

    tall = np.diag([1.0, 1.0, 2.0, 1.0])
    io.save_obj(tmp_path / "m.obj", jaxnm.procedural.uv_sphere(3.0, 16, 8).transformed(tall))
    extents = {}
    for up in ("y", "z"):
        aovs = tmp_path / f"{up}.npz"
        assert main(["render", str(tmp_path / "m.obj"), "--up", up, "-o", str(tmp_path / "m.png"),
                     "--width", "40", "--height", "24", "--aovs", str(aovs), "--aov-list",
                     "mask"]) == 0
        mask = io.load_aovs(aovs)["mask"][..., 0] > 0
        extents[up] = mask.any(1).sum(), mask.any(0).sum()  # rows, columns covered
    assert extents["z"][0] > 1.5 * extents["z"][1]
    assert extents["y"][0] <= extents["y"][1]
    view = np.asarray(_mesh_scene(str(tmp_path / "m.obj"), 40, 24, "z").camera.view, np.float64)
    eye = -view[:3, :3].T @ view[:3, 3]
    assert eye[1] < -abs(eye[0]) and eye[1] < -abs(eye[2])  # mostly from -y
    capsys.readouterr()
    assert main(["render", "--up", "z", "-o", str(tmp_path / "x.png")]) == 2
    assert "--up is a mesh file's up axis" in capsys.readouterr().err


def _quad_gltf(path, *, scale=0.5):
    """A glTF quad in z = 0, facing +z, written by hand as the glTF 2.0 specification says
    (uv (0, 0) at the image's top left, world (-1, 1); data URIs), with an 8x8 normal map whose
    top rows tilt towards +green (the image's top) and bottom rows towards +red."""
    import base64
    from io import BytesIO

    from PIL import Image

    pos = np.array([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]], np.float32)
    nrm = np.tile(np.array([0, 0, 1], np.float32), (4, 1))
    uv = np.array([[0, 1], [1, 1], [1, 0], [0, 0]], np.float32)
    idx = np.array([0, 1, 2, 0, 2, 3], np.uint16)
    blob = pos.tobytes() + nrm.tobytes() + uv.tobytes() + idx.tobytes()
    img = np.zeros((8, 8, 3), np.uint8)
    img[:4], img[4:] = (128, 191, 238), (191, 128, 238)  # (0, .5, .866), (.5, 0, .866)
    buf = BytesIO()
    Image.fromarray(img).save(buf, format="PNG")
    uri = "data:application/octet-stream;base64," + base64.b64encode(blob).decode()
    views = [dict(buffer=0, byteOffset=o, byteLength=n) for o, n in
             ((0, 48), (48, 48), (96, 32), (128, 12))]
    acc = [dict(bufferView=0, componentType=5126, count=4, type="VEC3",
                min=[-1, -1, 0], max=[1, 1, 0]),
           dict(bufferView=1, componentType=5126, count=4, type="VEC3"),
           dict(bufferView=2, componentType=5126, count=4, type="VEC2"),
           dict(bufferView=3, componentType=5123, count=6, type="SCALAR")]
    material = {"normalTexture": {"index": 0, "scale": scale}}
    tree = {"asset": {"version": "2.0"}, "scene": 0, "scenes": [{"nodes": [0]}],
            "nodes": [{"mesh": 0}], "buffers": [{"byteLength": len(blob), "uri": uri}],
            "bufferViews": views, "accessors": acc, "materials": [material],
            "meshes": [{"primitives": [{"attributes": {"POSITION": 0, "NORMAL": 1,
                                                       "TEXCOORD_0": 2},
                                        "indices": 3, "material": 0}]}],
            "textures": [{"source": 0}],
            "images": [{"uri": "data:image/png;base64,"
                        + base64.b64encode(buf.getvalue()).decode()}]}
    path.write_text(json.dumps(tree))
    return path


def test_a_gltf_files_own_normal_map_renders_as_gltf_says(tmp_path, capsys):
    """``jaxnm render FILE.gltf`` uses the file's normal map, decoded as the glTF
    specification says (uv origin at the image's top left, +green towards the image's top,
    MikkTSpace, ``normalTexture.scale`` scaling x and y): on a flat quad the perturbed normal
    is the decoded texel in world axes, the top rows' tilt towards world +y, the bottom
    rows' towards +x. ``--normal-map`` replaces it; a map that cannot be read is named, and
    the mesh renders without it."""
    quad = _quad_gltf(tmp_path / "q.gltf", scale=0.5)
    aovs = tmp_path / "a.npz"
    assert main(["render", str(quad), "-o", str(tmp_path / "q.png"), "--width", "32", "--height",
                 "32", "--aovs", str(aovs), "--aov-list", "mask,position,perturbed_normal"]) == 0
    out = io.load_aovs(aovs)
    m = out["mask"][..., 0] > 0
    y = out["position"][..., 1]
    n = out["perturbed_normal"]
    # (away from the middle row and the top and bottom edges, where bilinear filtering and
    # glTF's default repeat wrap blend the two halves)
    for region, tilt in ((m & (y > 0.3) & (y < 0.7), [0.0, 0.5, 0.866]),
                         (m & (y < -0.3) & (y > -0.7), [0.5, 0.0, 0.866])):
        t = np.array(tilt) * [0.5, 0.5, 1]  # the scale: x and y halved
        t /= np.linalg.norm(t)
        assert region.sum() > 20
        np.testing.assert_allclose(n[region], np.broadcast_to(t, n[region].shape), atol=0.01)
    # the map given on the command line replaces the file's
    flat = tmp_path / "flat.png"
    io.save_png(flat, np.full((4, 4, 3), [0.5, 0.5, 1.0], np.float32), bits=8)
    assert main(["render", str(quad), "-o", str(tmp_path / "f.png"), "--width", "32", "--height",
                 "32", "--normal-map", str(flat), "--aovs", str(aovs), "--aov-list",
                 "mask,perturbed_normal"]) == 0
    out = io.load_aovs(aovs)
    assert np.abs(out["perturbed_normal"][out["mask"][..., 0] > 0] - [0, 0, 1]).max() < 0.01
    # a map that cannot be read: the mesh renders without it, and the warning says why
    tree = json.loads(quad.read_text())
    tree["images"] = [{"uri": "missing.png"}]
    quad.write_text(json.dumps(tree))
    capsys.readouterr()
    with warnings.catch_warnings():
        warnings.simplefilter("default")
        assert main(["render", str(quad), "-o", str(tmp_path / "m.png"), "--width", "32",
                     "--height", "32", "--aovs", str(aovs), "--aov-list", "mask"]) == 0
    assert capsys.readouterr().err.splitlines() == [
        f"jaxnm render: warning: {quad}: the normal texture 'missing.png' is not beside it "
        f"({tmp_path / 'missing.png'}); rendered without it (--normal-map gives one)"]


@pytest.mark.parametrize("command,file,message", [
    ("fit", "m.obj", "a mesh file, not a fit file (JSON): 'jaxnm render {f} --light X,Y,Z "
                     "...' renders targets of it and writes their fit file, and 'jaxnm bake' "
                     "fits a map to a high-poly mesh"),
    ("fit", "t.png", "an image, not a fit file (JSON), which names its target images, views "
                     "and lights"),
    ("render", "t.png", "an image, not a scene file (JSON) or a mesh file; a map goes to "
                        "--normal-map or --height-map"),
])
def test_a_file_of_another_kind_is_named_for_what_it_is(tmp_path, capsys, command, file,
                                                        message):
    """A mesh or an image where a fit or scene file goes is named as what it is, with the
    command that takes it, not met as "invalid JSON" or "not UTF-8 text"; nothing is
    written."""
    f = tmp_path / file
    f.write_bytes(b"\x89PNG\r\n" if file.endswith(".png") else b"v 0 0 0\n")
    out = tmp_path / "out"
    assert main([command, str(f), "-o", str(out / "r.png" if command == "render" else out)]) == 2
    assert capsys.readouterr().err.strip() == f"jaxnm {command}: error: {f}: " + message.format(
        f=f)
    assert not out.exists()


def test_aovs_are_the_ones_asked_for(tmp_path, capsys):
    out = tmp_path / "a.npz"
    assert main(["render", "-o", str(tmp_path / "r.png"), "--width", "16", "--height", "16",
                 "--aovs", str(out), "--aov-list", "uv,mask,duvdx"]) == 0
    assert sorted(io.load_aovs(out)) == ["duvdx", "mask", "uv"]
    assert "arrays: uv, mask, duvdx" in capsys.readouterr().out


# ----------------------------------------------------------------------------- fit outputs


@pytest.mark.parametrize("options,kept", [([], False), (["--keep-checkpoint"], True),
                                          (["--checkpoint-every", "5"], True),
                                          (["--checkpoint-every", "0"], False)])
def test_the_checkpoint_goes_when_the_fit_ends_unless_asked_for(tmp_path, options, kept):
    path = _fit_folder(tmp_path / "job")
    out = tmp_path / "out"
    assert _fit(path, "-o", out, "--no-progress", *options) == 0
    assert (out / CHECKPOINT_NAME).exists() == kept
    report = json.loads((out / "report.json").read_text())
    assert report["checkpoint"]["file"] == (CHECKPOINT_NAME if kept else None)
    assert report["stopped"] == "max_steps"
    assert report["stopped_because"] == "reached the step limit (3 steps)"
    if kept:  # and it resumes: nothing left to do
        assert _fit(path, "-o", out, "--no-progress", "--resume", *options) == 0


def test_a_fit_without_matplotlib_says_why_there_is_no_loss_plot(tmp_path, capsys,
                                                                   monkeypatch):
    """Without the cli extra's matplotlib (`save_loss_plot` returns False), the report and
    a line on stderr say why ``loss.png`` is missing; the other outputs are written."""
    monkeypatch.setitem(sys.modules, "matplotlib", None)  # (an import of it then fails)
    monkeypatch.setitem(sys.modules, "matplotlib.figure", None)
    out = tmp_path / "out"
    assert _fit(_fit_folder(tmp_path / "job"), "-o", out, "--no-progress", "--max-steps",
                "1") == 0
    report = json.loads((out / "report.json").read_text())
    why = 'not drawn: matplotlib is not installed (the cli extra: pip install -e ".[cli]")'
    assert report["loss_plot"] == why
    assert f"no loss.png: {why}" in capsys.readouterr().err
    assert not (out / "loss.png").exists() and (out / "normal_map.png").is_file()


def test_every_key_of_the_report_is_documented(tmp_path):
    """Each key a fit's ``report.json`` holds is explained on the command-line page, and each
    key the page explains is one the code writes."""
    path = _fit_folder(tmp_path / "job")
    assert _fit(path, "-o", tmp_path / "out", "--no-progress") == 0
    report = json.loads((tmp_path / "out" / "report.json").read_text())
    page = (ROOT / "docs" / "getting-started" / "cli.md").read_text()
    table = page[page.index("`report.json` holds:"):]
    table = table[:table.index("\n\n", table.index("| key |"))]
    documented = set(re.findall(r"`(\w+)`", "\n".join(
        line.split(" | ")[0] for line in table.splitlines() if line.startswith("| `"))))
    assert set(report) <= documented, sorted(set(report) - documented)
    code = "".join(p.read_text() for p in (ROOT / "jaxnm").rglob("*.py"))
    assert not [k for k in documented if f'"{k}"' not in code]


def test_help_names_every_command_and_explains_every_option(capsys):
    """``jaxnm --help`` names the three commands in plain words, and every option of every
    command says what it does."""
    from jaxnm.cli import _parser

    parser = _parser()
    with pytest.raises(SystemExit):
        main(["--help"])
    top = " ".join(capsys.readouterr().out.split())
    assert "``" not in top
    assert all(w in top for w in ("Render a scene", "fit a tangent-space normal map", "bake"))
    commands = next(a for a in parser._actions if a.dest == "command").choices
    assert set(commands) == {"render", "fit", "bake"}
    silent = [f"{name} {'/'.join(a.option_strings) or a.dest}"
              for name, sub in commands.items() for a in sub._actions
              if not a.help and a.dest != "help"]
    assert not silent, silent


def test_version_and_python_dash_m(capsys):
    """``jaxnm --version`` says which jaxnm and JAX run, and ``python -m jaxnm`` is the
    ``jaxnm`` command."""
    import jax

    import jaxnm

    with pytest.raises(SystemExit) as e:
        main(["--version"])
    assert e.value.code == 0
    assert capsys.readouterr().out.strip() == f"jaxnm {jaxnm.__version__} (JAX {jax.__version__})"
    r = subprocess.run([sys.executable, "-m", "jaxnm", "--version"], capture_output=True,
                       text=True, timeout=120)
    assert (r.returncode, r.stdout.strip()) == (0, f"jaxnm {jaxnm.__version__} "
                                                   f"(JAX {jax.__version__})"), r.stderr
    r = subprocess.run([sys.executable, "-m", "jaxnm", "bogus"], capture_output=True,
                       text=True, timeout=120)
    assert r.returncode == 2 and r.stderr.startswith("jaxnm: error: argument command"), r.stderr


def test_the_command_line_page_names_every_frame_and_alias():
    from jaxnm.frames import FRAME_ALIASES, FRAMES

    page = (ROOT / "docs" / "getting-started" / "cli.md").read_text()
    names = list(FRAMES) + [a for a in FRAME_ALIASES if a.isascii()]
    assert not [n for n in names if f"`{n}`" not in page]


def test_the_targets_example_on_the_command_line_page_runs(tmp_path, monkeypatch):
    """The page's "Targets for a fit" commands, as written, on a small scene of one's own."""
    page = (ROOT / "docs" / "getting-started" / "cli.md").read_text()
    section = page[page.index("### Targets for a fit"):]
    block = section[section.index("```sh\n") + 6:]
    block = block[:block.index("```")]
    monkeypatch.chdir(tmp_path)
    Path("scene.json").write_text(json.dumps({
        "mesh": "builtin:plane", "width": 16, "height": 16, "normal_map": "builtin:rivets",
        "camera": {"eye": [0, -1, 2.5], "target": [0, 0, 0]}}))
    commands = [shlex.split(line) for line in block.strip().splitlines()]
    assert [c[:2] for c in commands] == [["jaxnm", "render"], ["jaxnm", "fit"]]
    for command in commands:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", F.FitWarning)
            assert main(command[1:]) == 0, command
    assert len(list(Path("targets").glob("t_0?.png"))) == 4
    assert json.loads(Path("fit_out/report.json").read_text())["steps"] > 0


def test_an_output_that_cannot_be_written_is_named_before_the_work(tmp_path, capsys,
                                                                   monkeypatch):
    """A folder where a file goes, a file where a folder goes (or above it), a folder that
    takes no file, a mesh file that is not there: one line naming the flag, exit 2, before
    the scene or the meshes are read (it was a traceback after the render, after the fit's
    preparation, after the bake)."""
    import jaxnm.cli._bake as cli_bake
    import jaxnm.cli._fit as cli_fit
    import jaxnm.cli._render as cli_render

    def too_late(*a, **k):
        raise AssertionError("the work started before the outputs were checked")

    for module, name in ((cli_render, "_scene"), (cli_fit, "read_job"), (cli_bake, "_meshes")):
        monkeypatch.setattr(module, name, too_late)
    (tmp_path / "file").write_text("x")
    (tmp_path / "dir.png").mkdir()
    d = tmp_path
    # a folder that takes no new file (Linux's /proc: even for root)
    unwritable = [(["fit", "-o", "/proc/jaxnm/out"], "-o /proc/jaxnm/out: cannot write in "
                   "/proc: No such file or directory"),
                  (["render", "-o", "/proc/x.png"], "-o /proc/x.png: cannot write in /proc: No "
                   "such file or directory")] if Path("/proc/self").is_dir() else []
    for argv, message in (
            (["render", "-o", f"{d}/file/x.png"], f"-o {d}/file/x.png: {d}/file is a file, not a "
                                                 f"folder"),
            (["render", "-o", f"{d}/dir.png"], f"-o {d}/dir.png: is a folder; name the file to "
                                              f"write"),
            (["render", "--aovs", f"{d}/file/a/b.npz"], f"--aovs {d}/file/a/b.npz: {d}/file is a "
                                                       f"file, not a folder"),
            (["fit", "-o", f"{d}/file"], f"-o {d}/file: is a file, not a folder"),
            (["fit", "-o", f"{d}/file/out"], f"-o {d}/file/out: {d}/file is a file, not a folder"),
            (["bake", f"{d}/high.obj", "--decimate", "100", "-o", f"{d}/file"],
             f"-o {d}/file: is a file, not a folder"),
            # every mesh file is looked for before the first is read
            (["bake", f"{d}/file", f"{d}/file", "--cage-mesh", f"{d}/cage.obj"],
             f"--cage-mesh {d}/cage.obj: no such file"),
            (["bake", f"{d}/file", f"{d}/dir.png"], f"{d}/dir.png: a folder, not a mesh file"),
            *unwritable):
        assert main([*argv, "--no-compile-cache"]) == 2, argv
        assert capsys.readouterr().err.strip() == f"jaxnm {argv[0]}: error: {message}"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["dir.png", "file"]


def test_a_scene_file_given_to_fit_and_a_fit_file_given_to_render_are_named_as_such(
        tmp_path, capsys):
    """(They listed every key as unknown, or asked for a camera.)"""
    scene = tmp_path / "torus.json"
    scene.write_text(json.dumps({"mesh": "builtin:torus", "width": 16, "height": 16,
                                 "camera": {"eye": [0, -3, 2], "target": [0, 0, 0]}}))
    fit = tmp_path / "fit.json"
    fit.write_text(json.dumps({"scene": "torus.json", "targets": [], "map": {"size": [8, 8]}}))
    assert main(["fit", str(scene), "--no-progress"]) == 2
    assert capsys.readouterr().err.strip().splitlines()[-1] == (
        f"jaxnm fit: error: {scene}: a scene file (it has 'mesh'), not a fit file: a fit file "
        f"names its scene (\"scene\": \"torus.json\") and lists its 'targets'")
    assert main(["render", str(fit), "-o", str(tmp_path / "x.png")]) == 2
    assert capsys.readouterr().err.strip() == (
        f"jaxnm render: error: {fit}: a fit file (it has 'targets'), not a scene file: run it "
        f"with `jaxnm fit`; the scene to render is the one its 'scene' names")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["fit.json", "torus.json"]
