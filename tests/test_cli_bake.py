"""``jaxnm bake`` as a user meets it: the output folder's layout and report, the maps' convention
(row 0 on top, green up) checked by decoding them and by re-rendering LOW with them against
HIGH's own normals, a low-poly mesh made from the high-poly one, one-line errors and warnings
naming the file for bad input, and Ctrl-C at a stage boundary and during the fit."""

from __future__ import annotations

import json
import signal
import warnings

import jax.numpy as jnp
import numpy as np
import pytest

import jaxnm
from jaxnm import io
from jaxnm.cli import main

#: A quad's normals vary in x and y: n(x, y) = normalize(0.6 (x - 1/2), -0.4 (y - 1/2), 1).
_TILT = (0.6, -0.4)


def _normal(x, y):
    n = np.stack([_TILT[0] * (x - 0.5), _TILT[1] * (y - 0.5), np.ones_like(x)], -1)
    return n / np.linalg.norm(n, axis=-1, keepdims=True)


def _grid(n: int, z: float = 0.0, x_max: float = 1.0):
    """An n x n grid over [0, x_max] x [0, 1] at height z, uv = xy, normals `_normal`."""
    x, y = np.meshgrid(np.linspace(0, x_max, n + 1), np.linspace(0, 1, n + 1), indexing="xy")
    p = np.stack([x, y, np.full_like(x, z)], -1).reshape(-1, 3)
    j, i = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    a = (j * (n + 1) + i).ravel()
    faces = np.concatenate([np.stack([a, a + 1, a + n + 2], 1),
                            np.stack([a, a + n + 2, a + n + 1], 1)])
    return p, faces, p[:, :2].copy(), _normal(p[:, 0], p[:, 1])


def _mesh(p, f, uv=None, n=None):
    return jaxnm.Mesh(jnp.asarray(p, jnp.float32), jnp.asarray(f, jnp.int32),
                      None if uv is None else jnp.asarray(uv, jnp.float32),
                      None if n is None else jnp.asarray(n, jnp.float32))


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    """HIGH: a 16 x 16 grid whose normals tilt with x and y; LOW: a 2 x 2 grid 0.01 above it
    with uv = xy and straight-up normals (MikkTSpace then gives the frame x, y, z, so a
    texel's stored normal is HIGH's normal there)."""
    d = tmp_path_factory.mktemp("bake")
    p, f, _, n = _grid(16)
    io.save_obj(d / "hi.obj", _mesh(p, f, None, n))
    p, f, uv, _ = _grid(2, z=0.01)
    up = np.tile([0.0, 0.0, 1.0], (len(p), 1))
    io.save_obj(d / "lo.obj", _mesh(p, f, uv, up))
    io.save_obj(d / "lo_nouv.obj", _mesh(p, f, None, up))
    io.save_obj(d / "far.obj", _mesh(p + [10, 0, 0], f, uv, up))
    io.save_obj(d / "cage_up.obj", _mesh(p + [0, 0, 0.1], f, None, up))  # no uvs
    two = np.concatenate([p, p + [0, 0, 0.02]])  # a second LOW over the first, same uvs
    io.save_obj(d / "lo_twice.obj", _mesh(two, np.concatenate([f, f + len(p)]),
                                          np.concatenate([uv, uv]), np.concatenate([up, up])))
    q, g, _, m = _grid(16, x_max=0.5)  # HIGH over the left half only
    io.save_obj(d / "hi_half.obj", _mesh(q, g, None, m))
    line = np.array([[0.2, 0.2, 0.01], [0.3, 0.3, 0.01], [0.4, 0.4, 0.01]])  # collinear
    io.save_obj(d / "lo_degenerate.obj", _mesh(
        np.concatenate([p, line]), np.concatenate([f, [[len(p), len(p) + 1, len(p) + 2]]]),
        np.concatenate([uv, line[:, :2]]), np.concatenate([up, up[:3]])))
    from scripts.benchmarks import bake_pairs as P

    pair = P.torus_pair((8, 4), (48, 24))
    io.save_obj(d / "torus.obj", P.high_mesh(pair))  # closed
    low = P.low_mesh(pair)  # closed, wound inwards, no normals (so they point inwards too)
    io.save_obj(d / "torus_lo_inside_out.obj", _mesh(np.asarray(low.positions),
                                                     np.asarray(low.faces)[:, ::-1],
                                                     np.asarray(low.uv), None))
    return d


_SMALL = ["--size", "16", "--render-size", "64", "--views", "4", "--lights", "4",
          "--eval-views", "2", "--max-steps", "3", "--no-progress"]


def _bake(*args) -> int:
    return main(["bake", *map(str, args)])


@pytest.fixture(scope="module")
def baked(files, tmp_path_factory):
    out = tmp_path_factory.mktemp("out") / "o"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        rc = _bake(files / "hi.obj", files / "lo.obj", "-o", out, *_SMALL)
    return rc, out


# ----------------------------------------------------------------------------- outputs


@pytest.mark.slow
def test_the_output_folder_and_its_report(baked):
    rc, out = baked
    assert rc == 0
    for method in ("raycast", "fit"):
        for name in ("normal_map.png", "normal_map.npz", "error_map.png"):
            assert (out / method / name).is_file(), (method, name)
    assert (out / "fit" / "coverage.png").is_file() and (out / "report.json").is_file()
    assert (out / "figure.png").is_file()
    assert not [p.name for p in out.rglob("*.tmp")]
    rep = json.loads((out / "report.json").read_text())
    assert rep["frame"] == "vertex" and rep["tangents"] == "mikktspace"
    assert rep["method"] == "both" and rep["map_size"] == [16, 16]
    assert rep["interrupted"] is False and rep["skipped"] == []
    assert rep["raycast"]["texels_missed"] == 0 and rep["raycast"]["cage_source"] == "automatic"
    f = rep["fit"]
    assert f["views"] == 4 and f["lights_per_view"] == 4 and f["start"] == "raycast"
    assert 0 <= f["unseen_texels"] <= f["chart_texels"] == 256
    assert sum(f["views_per_texel"]) == f["chart_texels"]
    ev = rep["evaluation"]["methods"]
    assert set(ev) == {"none", "raycast", "fit"}
    for s in ev.values():
        assert {"psnr_db", "flip", "angle_mean_deg", "angle_median_deg",
                "angle_p95_deg"} <= set(s)
    assert ev["raycast"]["psnr_db"] > ev["none"]["psnr_db"] + 3
    assert ev["fit"]["psnr_db"] > ev["none"]["psnr_db"] + 3
    assert set(rep["seconds"]) >= {"read", "raycast", "plan", "targets", "prepare", "fit",
                                   "evaluate"}
    listed = set(rep["files"])
    assert {"raycast/normal_map.png", "fit/normal_map.npz", "figure.png", "report.json",
            "raycast/low.glb", "fit/low.glb"} <= listed
    assert all((out / name).is_file() for name in listed)
    # LOW with each map, for glTF viewers: LOW's vertices and uvs, the PNG's codes
    low = io.load_mesh(rep["low_file"])
    for method in ("raycast", "fit"):
        glb = io.load_mesh(out / method / "low.glb")
        np.testing.assert_array_equal(glb.positions, low.positions)
        np.testing.assert_allclose(glb.uv, low.uv, atol=1e-7)
        texels, opts = io.load_gltf_normal_map(out / method / "low.glb")
        png, _ = io.load_texture(out / method / "normal_map.png", channels=3)
        np.testing.assert_array_equal(np.round(texels * 255), np.round(png * 255))


@pytest.mark.slow
def test_the_maps_have_row_0_on_top_and_green_up(baked):
    """Texel (r, c) of an h x w map sits at u = (c + 1/2) / w, v = 1 - (r + 1/2) / h: the
    stored normals there are HIGH's (LOW's frame is x, y, z); the PNG decodes to them within
    its 8 bits; and LOW rendered head-on with the PNG as a scene's normal map shows HIGH's
    normals pixel by pixel."""
    _, out = baked
    h = w = 16
    c, r = np.meshgrid(np.arange(w), np.arange(h), indexing="xy")
    want = _normal((c + 0.5) / w, 1 - (r + 0.5) / h)
    for method, tol in (("raycast", 0.5), ("fit", 3.0)):
        n = np.load(out / method / "normal_map.npz")["normals"]
        assert n.shape == (h, w, 3) and n.dtype == np.float32
        err = _angle(n, want)
        assert np.median(err) < tol, (method, np.median(err))
        png, bits = io.load_texture(out / method / "normal_map.png", channels=3)
        decoded = np.asarray(jaxnm.decode_normal_map(jnp.asarray(png), encoding="unsigned"))
        assert bits == 8 and _angle(decoded, n).max() < 0.8
    png, _ = io.load_texture(out / "raycast" / "normal_map.png", channels=3)
    cam = jaxnm.Camera.look_at([0.5, 0.5, 2.0], [0.5, 0.5, 0.0], fov_y_deg=30)
    lo_p, lo_f, lo_uv, _ = _grid(2, z=0.01)
    lo = _mesh(lo_p, lo_f, lo_uv, np.tile([0.0, 0.0, 1.0], (len(lo_p), 1))).with_tangents()
    scene = jaxnm.Scene(mesh=lo, camera=cam, width=48, height=48, frame="vertex",
                        normal_map=jnp.asarray(png),
                        normal_map_options=jaxnm.NormalMapOptions(encoding="unsigned",
                                                                  wrap="clamp"))
    got = jaxnm.render(scene, outputs=("mask", "position", "perturbed_normal"))
    mask = np.asarray(got["mask"])[..., 0] > 0
    pos = np.asarray(got["position"], np.float64)[mask]
    err = _angle(np.asarray(got["perturbed_normal"])[mask], _normal(pos[:, 0], pos[:, 1]))
    assert mask.sum() > 500 and np.median(err) < 0.5 and np.percentile(err, 99) < 2.0


def _angle(a, b):
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    return np.degrees(np.arctan2(np.linalg.norm(np.cross(a, b), axis=-1), np.sum(a * b, -1)))


@pytest.mark.parametrize("unwrap", [(), ("--unwrap", "--frame", "cotangent")],
                         ids=["decimate", "decimate-unwrap-cotangent"])
def test_decimate_writes_the_low_poly_mesh_with_uvs(files, tmp_path, capsys, unwrap):
    """``--decimate N`` makes LOW and unwraps it (it has no uvs otherwise); ``--unwrap``
    beside it changes nothing. With no scores and no fit, the output is one line. A map for
    the cotangent frame gets no ``low.glb`` (glTF viewers decode in MikkTSpace)."""
    out = tmp_path / "o"
    assert _bake(files / "torus.obj", "--decimate", "300", *unwrap, "--method", "raycast",
                 "--eval-views", "0", "--size", "32", "-o", out) == 0
    low = io.load_mesh(out / "low.obj")
    assert 280 <= low.num_faces <= 300 and low.uv is not None and low.normals is not None
    rep = json.loads((out / "report.json").read_text())
    assert rep["low_file"] == "low.obj" and rep["unwrapped"] is True
    assert "low.obj" in rep["files"] and not (out / "fit").exists()
    assert (out / "raycast" / "low.glb").is_file() == (not unwrap)
    n = np.load(out / "raycast" / "normal_map.npz")["normals"]
    assert n.shape == (32, 32, 3)
    said = capsys.readouterr().out.splitlines()  # no scores, no fit: no summary, no blank line
    assert said == [f"outputs in {out}/ ({', '.join(rep['files'])})"], said


def test_a_cage_mesh_without_uvs_with_an_unwrapped_low(files, tmp_path):
    """LOW without uvs, unwrapped by xatlas (its vertices split at new seams), and its cage
    0.1 above it saved without uvs: the cage is matched face by face, and its rays (from 0.1
    above each texel's point, straight down) are those of a 0.1 extrusion along LOW's
    straight-up normals, so both maps agree to float rounding."""
    maps, missed = [], []
    for i, cage in enumerate((["--cage-mesh", files / "cage_up.obj"], ["--cage", "0.1"])):
        out = tmp_path / f"o{i}"
        with warnings.catch_warnings():  # (texels on the chart's rim: rays along HIGH's rim)
            warnings.simplefilter("ignore")
            assert _bake(files / "hi.obj", files / "lo_nouv.obj", "--unwrap", "--method",
                         "raycast", "--eval-views", "0", "--size", "16", *cage, "-o", out) == 0
        rep = json.loads((out / "report.json").read_text())
        assert rep["raycast"]["cage_source"] == ("mesh" if i == 0 else "given")
        missed.append(rep["raycast"]["texels_missed"])
        maps.append(np.load(out / "raycast" / "normal_map.npz")["normals"])
    assert missed[0] == missed[1] < 0.2 * 16 * 16
    np.testing.assert_allclose(maps[0], maps[1], rtol=0, atol=1e-6)
    assert np.abs(maps[0][..., :2]).max() > 0.05  # HIGH's normals tilt: the rays found them


def test_a_map_of_another_width_and_height(files, tmp_path):
    """``--size 32x16`` bakes a map 32 texels wide and 16 high (LOW's uv is its xy, origin
    at the bottom left): each texel holds HIGH's normal at its centre, in image layout."""
    out = tmp_path / "o"
    assert _bake(files / "hi.obj", files / "lo.obj", "--method", "raycast", "--eval-views", "0",
                 "--size", "32x16", "-o", out) == 0
    assert json.loads((out / "report.json").read_text())["map_size"] == [16, 32]
    n = np.load(out / "raycast" / "normal_map.npz")["normals"]
    assert n.shape == (16, 32, 3) and io.load_texture(out / "raycast" / "normal_map.png")[
        0].shape == (16, 32, 3)
    u, v = np.meshgrid((np.arange(32) + 0.5) / 32, 1 - (np.arange(16) + 0.5) / 16)
    err = _angle(n, _normal(u, v))
    assert np.median(err) < 0.5 and np.percentile(err, 99) < 2.0, (np.median(err), err.max())


def test_held_out_views_of_an_open_surface_score_its_front(files, tmp_path):
    """LOW and HIGH are one-sided grids: a held-out view from the spiral alone would see the
    single view's grid edge-on and score no pixel (no PSNR); the views face the grid."""
    out = tmp_path / "o"
    assert _bake(files / "hi.obj", files / "lo.obj", "--method", "raycast", "--eval-views", "1",
                 "--size", "16", "-o", out) == 0
    ev = json.loads((out / "report.json").read_text())["evaluation"]
    assert ev["scored_pixels_per_view"][0] > 50  # of 16x16
    for method in ("none", "raycast"):
        assert 10 < ev["methods"][method]["psnr_db"] < 100
        assert 0 < ev["methods"][method]["flip"] < 1


def test_the_summary_says_when_no_pixel_was_scored_and_when_images_are_identical():
    """The report stores a score that is not finite as null; the printed summary says which
    it was: no held-out pixel scored (no scores at all, not "PSNR nan"), or, with pixels
    scored, identical images (an infinite PSNR)."""
    from jaxnm.cli._bake import _summary

    def report(pixels, psnr):
        s = {"psnr_db": psnr, "flip": 0.0 if pixels else None,
             "angle_mean_deg": 0.0 if pixels else None}
        return {"interrupted": False, "evaluation": {"scored_pixels_per_view": pixels,
                                                     "methods": {"none": s, "raycast": s}}}

    text = _summary(report([0, 0], None))
    assert "no pixel scored" in text and "nan" not in text and "PSNR" not in text
    text = _summary(report([0, 12], None))
    assert text.count("held-out PSNR inf dB, FLIP 0.0000") == 2 and "nan" not in text
    assert "held-out PSNR 21.50 dB" in _summary(report([3], 21.5))


# ----------------------------------------------------------------------------- bad input


@pytest.mark.parametrize("argv,message", [
    (["{d}/hi.obj"], "jaxnm bake: error: no LOW: give the low-poly mesh, or --decimate N to "
                     "make one from HIGH"),
    (["{d}/hi.obj", "{d}/lo.obj", "--decimate", "10", "--unwrap"],
     "jaxnm bake: error: give LOW or --decimate N (LOW made from HIGH), not both"),
    (["{d}/hi.obj", "{d}/lo.obj", "--frame", "nonperspective"],
     "jaxnm bake: error: --frame 'nonperspective': ray casting bakes for the frames vertex, "
     "cotangent only (method 'fit' fits a map for any frame)"),
    (["{d}/hi.obj", "{d}/lo.obj", "--lights", "2"],
     "jaxnm bake: error: --lights: a fit needs at least 3 lights per view"),
    (["{d}/hi.obj", "{d}/lo.obj", "--store", "bc5", "--size", "30"],
     "jaxnm bake: error: --store bc5: a BC5 map's sides must be multiples of 4, got --size 30"),
    (["{d}/hi.obj", "{d}/lo.obj", "--store", "bc5", "--size", "32x30"],
     "jaxnm bake: error: --store bc5: a BC5 map's sides must be multiples of 4, got --size "
     "32x30"),
    (["{d}/hi.obj", "--decimate", "10", "--size", "32x16"],
     "jaxnm bake: error: --size 32x16: xatlas packs a square atlas, so --decimate takes one "
     "side"),
    (["{d}/hi.obj", "{d}/lo.obj", "--unwrap", "--size", "16x32"],
     "jaxnm bake: error: --size 16x32: xatlas packs a square atlas, so --unwrap takes one side"),
    (["{d}/hi.obj", "{d}/lo.obj", "--size", "32x16x2"],
     "jaxnm bake: error: argument --size: give the map's side N or its width and height WxH, "
     "each an integer >= 4, got '32x16x2'"),
    (["{d}/hi.obj", "{d}/lo.obj", "--size", "8"],
     "jaxnm bake: error: --size 8: without a --render-size, each view's image takes the map's "
     "larger side, which must then be 16 to 8192 pixels"),
    (["{d}/hi.obj", "{d}/lo.obj", "--size", "8x12"],
     "jaxnm bake: error: --size 8x12: without a --render-size, each view's image takes the "
     "map's larger side, which must then be 16 to 8192 pixels"),
    (["{d}/hi.obj", "{d}/lo.obj", "--size", "8", "--render-size", "12"],
     "jaxnm bake: error: --render-size must be 16 to 8192 pixels, got 12"),
    (["{d}/hi.obj", "{d}/lo.obj", "--method", "fit", "--cage", "0.1"],
     "jaxnm bake: error: --cage: an option of ray casting, and --method fit casts no rays"),
    (["{d}/hi.obj", "{d}/lo.obj", "--method", "fit", "--samples", "2", "--max-distance", "1"],
     "jaxnm bake: error: --max-distance, --samples: options of ray casting, and --method fit "
     "casts no rays"),
    (["{d}/hi.obj", "{d}/lo.obj", "--method", "raycast", "--views", "3"],
     "jaxnm bake: error: --views: an option of the fit, and --method raycast fits nothing"),
    (["{d}/hi.obj", "{d}/nope.obj"], "jaxnm bake: error: {d}/nope.obj: no such file"),
    (["{d}/hi.obj", "{d}/lo.obj", "--size", "2"],
     "jaxnm bake: error: argument --size: give the map's side N or its width and height WxH, "
     "each an integer >= 4, got '2'"),
    (["{d}/hi.obj", "--decimate", "10", "--cage-mesh", "{d}/lo.obj"],
     "jaxnm bake: error: --cage-mesh: a cage has LOW's triangles, and --decimate makes new "
     "ones; give LOW and its cage, or --cage DIST"),
    (["{d}/hi.obj", "{d}/lo.obj", "--method", "raycast", "--cage-mesh", "{d}/lo_twice.obj"],
     "jaxnm bake: error: {d}/lo_twice.obj: a cage mesh must have {d}/lo.obj's triangles in "
     "{d}/lo.obj's order; it has 16 faces, {d}/lo.obj 8"),
    (["{d}/hi.obj", "{d}/lo_nouv.obj", "--method", "raycast"],
     "jaxnm bake: error: {d}/lo_nouv.obj: the mesh has no texture coordinates (uv); a normal "
     "map is baked into LOW's uv layout (--unwrap makes one with xatlas)"),
    (["{d}/hi.obj", "{d}/far.obj", "--method", "raycast", "--eval-views", "0"],
     "jaxnm bake: error: {d}/hi.obj and {d}/far.obj do not overlap: none of the"),
])
def test_bad_input_is_one_line_naming_the_file(files, tmp_path, capsys, argv, message):
    out = tmp_path / "o"
    try:
        rc = _bake("-o", out, "--size", "16", *[a.format(d=files) for a in argv])
    except SystemExit as e:  # (argparse's errors: the same one line)
        rc = e.code
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and err[-1].startswith(message.format(d=files)), err
    assert [line for line in err if ": error: " in line] == [err[-1]]
    assert not out.exists()


@pytest.mark.parametrize("argv,missing", [
    (["{d}/hi.obj", "{d}/lo.obj", "--unwrap"], "embreex, xatlas and flip-evaluator"),
    (["{d}/hi.obj", "{d}/lo.obj"], "embreex and flip-evaluator"),
    (["{d}/hi.obj", "{d}/lo.obj", "--method", "fit", "--eval-views", "0"], None),
    (["{d}/hi.obj", "{d}/lo.obj", "--method", "fit", "--eval-views", "0", "--unwrap"],
     "xatlas"),
    (["{d}/hi.obj", "--decimate", "50", "--method", "fit", "--eval-views", "0"],
     "xatlas and fast-simplification"),
])
def test_a_missing_bake_extra_is_named_before_the_meshes_are_read(files, tmp_path, capsys,
                                                                   monkeypatch, argv, missing):
    """Without the bake extra's packages (hidden here), the command names those this bake
    needs and how to install them, before it reads a mesh (it said so only where each
    package was first used, after minutes of work)."""
    import importlib.util

    import jaxnm.cli._bake as cli_bake

    real = importlib.util.find_spec
    hidden = ("embreex", "xatlas", "fast_simplification", "flip_evaluator")
    monkeypatch.setattr(importlib.util, "find_spec",
                        lambda name, *a: None if name in hidden else real(name, *a))
    def meshes(*args):  # (where the meshes are read: reached only with nothing missing)
        raise ValueError("reached the meshes")

    monkeypatch.setattr(cli_bake, "_meshes", meshes)
    rc = _bake("-o", tmp_path / "o", *[a.format(d=files) for a in argv])
    err = capsys.readouterr().err.strip().splitlines()
    expected = (f'this bake needs {missing}, from the bake extra: pip install -e ".[bake]"'
                if missing else "reached the meshes")
    assert rc == 2 and err[-1] == f"jaxnm bake: error: {expected}", err


def test_a_low_mesh_wound_inwards_is_named(files, tmp_path, capsys):
    """A closed LOW turned inside out: a warning names it, and the fit, which no view shows
    its front faces to, says why instead of "do not overlap"."""
    with warnings.catch_warnings():
        warnings.simplefilter("default")
        rc = _bake(files / "torus.obj", files / "torus_lo_inside_out.obj", "-o", tmp_path / "o",
                   "--method", "fit", "--size", "16", "--render-size", "32", "--views", "2")
    err = capsys.readouterr().err.splitlines()
    lo = files / "torus_lo_inside_out.obj"
    assert rc == 2 and f"jaxnm bake: warning: {lo}: a closed mesh whose faces wind inwards (the " \
        "volume they enclose is negative), so its front faces look inside; reverse their " \
        "winding" in err, err
    assert err[-1] == (f"jaxnm bake: error: {lo}: no view shows its front faces over "
                       f"{files / 'torus.obj'}: they wind inwards (a closed mesh of negative "
                       "volume); reverse their winding"), err


@pytest.mark.parametrize("low,high,extra,warning", [
    ("lo_twice.obj", "hi.obj", [], r"{d}/lo_twice.obj: \d+ texels lie inside more than one uv "
                                   r"triangle \(overlapping uv islands"),
    ("lo.obj", "hi_half.obj", ["--cage", "0.05", "--max-distance", "0.1"],
     r"{d}/lo.obj: the rays of \d+ of 256 texels hit nothing on {d}/hi_half.obj \(given cage "
     r"0.05\): uv \[0.5"),
    ("lo_degenerate.obj", "hi.obj", [], r"{d}/lo_degenerate.obj: 1 degenerate \(zero-area\) "
                                        r"triangles \(first: face 8\)"),
])
def test_suspicious_input_is_a_one_line_warning(files, tmp_path, capsys, low, high, extra,
                                                warning):
    import re

    out = tmp_path / "o"
    with warnings.catch_warnings():
        warnings.simplefilter("default")
        rc = _bake(files / high, files / low, "-o", out, "--method", "raycast",
                   "--eval-views", "0", "--size", "16", *extra)
    err = capsys.readouterr().err.splitlines()
    warned = [line for line in err if ": warning: " in line]
    assert rc == 0 and len(warned) == 1, err
    assert re.match("jaxnm bake: warning: " + warning.format(d=re.escape(str(files))),
                    warned[0]), warned
    if high == "hi_half.obj":
        rep = json.loads((out / "report.json").read_text())
        r = rep["raycast"]
        assert r["missed_mask"] == "raycast/missed.png" and r["texels_missed"] > 0
        missed = io.load_texture(out / "raycast" / "missed.png", channels=1)[0][..., 0] > 0.5
        assert missed.sum() == r["texels_missed"]
        cols = np.nonzero(missed)[1]
        assert (cols + 0.5).min() / 16 > 0.5  # the right half, where HIGH is not


# ----------------------------------------------------------------------------- Ctrl-C


@pytest.fixture
def sigint():
    """SIGINT handled by Python while the test runs (it is ignored in background jobs)."""
    before = signal.signal(signal.SIGINT, signal.default_int_handler)
    yield
    signal.signal(signal.SIGINT, before)


def _ctrl_c_before(monkeypatch, module, name):
    """Press Ctrl-C (SIGINT to this process) just before ``module.name`` runs."""
    real = getattr(module, name)

    def pressed(*a, **k):
        signal.raise_signal(signal.SIGINT)
        return real(*a, **k)

    monkeypatch.setattr(module, name, pressed)


def test_ctrl_c_at_a_stage_boundary_stops_with_130_and_writes_nothing(files, tmp_path,
                                                                      monkeypatch, sigint,
                                                                      capfd):
    from jaxnm.transfer import pair

    _ctrl_c_before(monkeypatch, pair, "raycast_normal_map")
    out = tmp_path / "o"
    assert _bake(files / "hi.obj", files / "lo.obj", "-o", out, *_SMALL) == 130
    err = capfd.readouterr().err  # (the handler writes to the file descriptor)
    assert "Ctrl-C: stopping after this stage" in err and err.rstrip().endswith(
        "jaxnm bake: interrupted")
    assert "planning" not in err and not out.exists()


@pytest.mark.slow
def test_ctrl_c_during_the_fit_keeps_the_maps_and_the_report(files, baked, tmp_path,
                                                            monkeypatch, sigint, capsys):
    """The fit stops after the step it is in; the maps and the report are written, the
    scores left out, and the exit code is 130."""
    from jaxnm.transfer import pair

    _ctrl_c_before(monkeypatch, pair, "fit_normal_map")
    out = tmp_path / "o"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        assert _bake(files / "hi.obj", files / "lo.obj", "-o", out, *_SMALL) == 130
    rep = json.loads((out / "report.json").read_text())
    assert rep["interrupted"] is True and "evaluation" in rep["skipped"]
    assert rep["fit"]["stopped"] == "interrupted" and rep["fit"]["steps"] <= 1
    assert "evaluation" not in rep and not (out / "figure.png").exists()
    for method in ("raycast", "fit"):
        assert (out / method / "normal_map.npz").is_file()
    assert not [p.name for p in out.rglob("*.tmp")]


def test_the_help_states_the_library_defaults(capsys):
    from jaxnm.transfer import PairBakeOptions

    with pytest.raises(SystemExit):
        main(["bake", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    o = PairBakeOptions()
    for flag, value in (("--views K views the fit plans", o.views),
                        ("--lights L directional lights per view, at least 3", o.lights),
                        ("--max-steps N the fit's steps at most", o.fit.max_steps),
                        ("--margin PX texels filled around the uv islands", o.margin),
                        ("--samples K ray-cast samples per texel", o.samples),
                        ("--eval-views E held-out views that score the maps, 2 lights each",
                         o.eval_views),
                        ("--size N|WxH the map's side, or its width and height, in texels",
                         o.size)):
        assert f"{flag} (default: {value}" in text, flag
    assert o.eval_lights == 2 and o.frame == "vertex" and o.method == "both"


def test_a_small_map_needs_a_render_size_where_anything_is_rendered():
    """Without ``render_size`` the views' images take the map's side; a map under 16 texels
    a side is refused up front, unless nothing is rendered (ray casting, no scores) or a
    render size is given."""
    from jaxnm.transfer import PairBakeOptions

    with pytest.raises(ValueError, match=r"^PairBakeOptions: size 8: without a render_size"):
        PairBakeOptions(size=8)
    with pytest.raises(ValueError, match=r"size \(8, 20000\): without a render_size"):
        PairBakeOptions(size=(8, 20000))
    for ok in (dict(method="raycast", eval_views=0), dict(render_size=16)):
        assert PairBakeOptions(size=8, **ok).map_size == (8, 8)


def test_store_bc5_writes_a_dds_beside_the_png(files, tmp_path):
    pytest.importorskip("quicktex")
    from jaxnm.storage import load_dds_normal_map

    out = tmp_path / "o"
    assert _bake(files / "hi.obj", files / "lo.obj", "-o", out, "--method", "raycast",
                 "--eval-views", "0", "--size", "16", "--store", "bc5") == 0
    n = np.load(out / "raycast" / "normal_map.npz")["normals"]
    dds = load_dds_normal_map(out / "raycast" / "normal_map.dds")
    decoded = np.asarray(jaxnm.decode_normal_map(
        jnp.asarray(dds.texels), encoding="unsigned", channels=2))
    assert decoded.shape == (16, 16, 3) and np.median(_angle(decoded, n)) < 1.0
    rep = json.loads((out / "report.json").read_text())
    assert rep["store"] == "bc5" and "raycast/normal_map.dds" in rep["files"]
