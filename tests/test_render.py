"""The composed pipeline: conventions of the outputs, scenes from JSON, the CLI, bad input."""

import contextlib
import dataclasses
import importlib
import json
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from _scenes import OUTPUTS, PACKED, WHOLE, builtin_scene

import jaxnm
from jaxnm import procedural
from jaxnm.cli import main
from jaxnm.config import load_scene, scene_from_dict
from jaxnm.maps import height_to_normal_map
from jaxnm.procedural import default_scene
from jaxnm.render import render
from jaxnm.scene import Scene, default_lights, default_material, validate_scene
from jaxnm.shading import (
    DirectionalLight,
    Lights,
    Material,
    PointLight,
    directional_light,
    stack_lights,
)

EXAMPLE = (Path(__file__).resolve().parents[1] / "scripts" / "examples" / "scenes" / "torus"
           / "scene.json")


@pytest.fixture(scope="module")
def plane_scene():
    """A plane facing the camera (camera up = +y): uv = (x, y)/2 + 1/2 on screen."""
    cam = jaxnm.Camera.look_at((0.2, 0.1, 2.5), (0.0, 0.0, 0.0), (0, 1, 0), fov_y_deg=30)
    return Scene(mesh=procedural.plane(2.0, 2), camera=cam, width=32, height=24,
                 source="<plane>").replace()


#: What the renders of the plane with the built-in map ask for (each test reads its own
#: outputs): one program for those tests.
PLANE_OUTPUTS = ("color", "mask", "uv", "duvdx", "duvdy", "position", "dpdy", "normal",
                 "tangent", "bitangent", "perturbed_normal")


def _mapped(plane_scene):
    """The plane with the built-in normal map, lit by the default light and material (given
    explicitly: a scene with other lights and material renders with the same program)."""
    return plane_scene.replace(normal_map=procedural.default_normal_map_texels(64),
                               lights=default_lights(plane_scene.camera),
                               material=default_material())


def test_image_layout_uv_origin_and_dfdy_direction(plane_scene):
    out = render(_mapped(plane_scene), outputs=PLANE_OUTPUTS)
    m = out["mask"][..., 0] > 0
    assert m.all()
    uv = out["uv"]
    # row 0 is the top of the image: larger v (uv origin bottom-left, +y up on screen)
    assert (uv[0, :, 1] > uv[-1, :, 1]).all()
    assert (uv[:, -1, 0] > uv[:, 0, 0]).all()  # u grows to the right
    # dFdy is per step of window y UP: positive for v, matching row-to-row differences upwards
    assert (out["duvdy"][..., 1] > 0).all()
    np.testing.assert_allclose(out["duvdy"][1:-1, :, 1], (uv[:-2, :, 1] - uv[2:, :, 1]) / 2,
                               rtol=1e-3)
    assert (out["duvdx"][..., 0] > 0).all()
    assert (out["dpdy"][..., 1] > 0).all()


def test_only_requested_stages_run():
    """A mesh without uv or normals can still be rasterized for geometric outputs."""
    m = procedural.plane(2.0, 1)
    mesh = jaxnm.geometry.Mesh(m.positions, m.faces)
    cam = jaxnm.Camera.look_at((0, 0, 3), (0, 0, 0))
    sc = Scene(mesh=mesh, camera=cam, width=16, height=16).replace()
    out = render(sc, outputs=("mask", "depth", "triangle_id", "position"))
    assert out["mask"].sum() > 0 and set(out) == {"mask", "depth", "triangle_id", "position"}
    with pytest.raises(ValueError, match="normal"):
        render(sc, outputs=("color",))


def test_default_scene_is_lit_and_mapped():
    sc = builtin_scene(WHOLE)
    out = render(sc, outputs=OUTPUTS)
    m = out["mask"][..., 0] > 0
    assert 0.3 < m.mean() < 0.9
    for k in ("color", "normal", "perturbed_normal", "tangent", "bitangent", "mask"):
        assert np.isfinite(out[k]).all(), k
    ang = np.degrees(np.arccos(np.clip((out["normal"] * out["perturbed_normal"]).sum(-1), -1, 1)))
    assert np.percentile(ang[m], 90) > 10  # the map visibly perturbs the normal
    assert out["color"][m].mean() > 0.1
    assert np.all(out["color"][~m] == 0)
    np.testing.assert_allclose(np.linalg.norm(out["perturbed_normal"][m], axis=-1), 1, atol=1e-5)


def test_example_scene_file_matches_builtin_conventions(tmp_path):
    sc = load_scene(EXAMPLE)
    assert sc.normal_map is not None and sc.mesh.uv is not None
    out = render(sc.replace(width=48, height=36, camera=sc.camera), outputs=("color", "mask"))
    assert np.isfinite(out["color"]).all() and out["mask"].sum() > 100


def _scene_dict(**over):
    d = {"mesh": "builtin:plane", "camera": {"eye": [0, 0, 3], "target": [0, 0, 0]},
         "width": 16, "height": 16}
    d.update(over)
    return d


@pytest.mark.parametrize("over,match", [
    (dict(mesh=None), "mesh"),
    (dict(mesh="builtin:teapot"), "teapot"),
    (dict(colour=[1, 1, 1]), "unknown keys"),
    (dict(width=0), "width"),
    (dict(width="big"), "width"),
    (dict(camera={"eye": [0, 0, 3]}), "target"),
    (dict(camera={"eye": [0, 0, 0], "target": [0, 0, 0]}), "coincide"),
    (dict(camera={"eye": [0, 0, 3], "target": [0, 0, 0], "near": 0}), "near"),
    (dict(camera={"eye": [0, 0, -3], "target": [0, 0, -6]}), "behind the camera's near plane"),
    (dict(camera={"view": [[1, 0, 0, 0]], "projection": np.eye(4).tolist()}), "4x4"),
    (dict(frame="diagonal"), "frame"),
    (dict(derivatives="medium"), "derivatives"),
    (dict(lights=[]), "lights"),
    (dict(lights=[{"type": "spot"}]), "lights\\[0\\]"),
    (dict(lights=[{"type": "directional", "direction": [0, 0, 0]}]), "direction"),
    (dict(material={"shininess": -1}), "shininess"),
    (dict(material={"diffuse": [0.5, -0.1, 0.5]}), r"^bad.json: material: 'diffuse' must not "
     r"be negative \(light and reflectance are >= 0\), got \[0.5, -0.1, 0.5\]$"),
    (dict(albedo=[-0.8, 0.8, 0.8]), r"^bad.json: 'albedo' must not be negative"),
    (dict(lights=[{"type": "point", "position": [0, 0, 2], "color": [1, 1, -1]}]),
     r"^bad.json: lights\[0\]: 'color' must not be negative"),
    (dict(lights=[{"type": "directional", "direction": [0, 0, 1], "intensity": -2}]),
     r"^bad.json: lights\[0\]: 'intensity' must be >= 0, got -2.0$"),
    (dict(normal_map={"path": "builtin:rivets", "green": "sideways"}), "green"),
    (dict(model=[[1, 0, 0], [0, 1, 0]]), "model"),
])
def test_bad_scene_json_is_refused_with_the_key(over, match):
    d = _scene_dict(**over)
    if over.get("mesh", 1) is None:
        d.pop("mesh")
    with pytest.raises(ValueError, match=match):
        scene_from_dict(d, source="bad.json")


def test_scene_file_errors_name_the_file(tmp_path):
    p = tmp_path / "scene.json"
    p.write_text(json.dumps(_scene_dict(mesh="missing.obj")))
    with pytest.raises(FileNotFoundError, match="missing.obj"):
        load_scene(p)
    p.write_text("{ not json")
    with pytest.raises(ValueError, match="scene.json"):
        load_scene(p)


def test_tangent_map_without_uv_is_refused(tmp_path):
    obj = tmp_path / "tri.obj"
    obj.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nvn 0 0 1\nvn 0 0 1\nvn 0 0 1\nf 1//1 2//2 3//3\n")
    p = tmp_path / "scene.json"
    p.write_text(json.dumps(_scene_dict(mesh="tri.obj", normal_map="builtin:rivets")))
    with pytest.raises(ValueError, match="no texture coordinates"):
        load_scene(p)


def test_cli_render_writes_png_and_aovs(tmp_path, capsys):
    png, npz = tmp_path / "out.png", tmp_path / "aovs.npz"
    rc = main(["render", "-o", str(png), "--aovs", str(npz), "--width", "40", "--height", "32",
               "--derivatives", "coarse", "--frame", "cotangent"])
    assert rc == 0 and png.exists()
    aovs = np.load(npz)
    for name in ("mask", "triangle_id", "depth", "position", "uv", "normal", "front_facing",
                 "dpdx", "dpdy", "duvdx", "duvdy", "tangent", "bitangent", "perturbed_normal",
                 "color"):
        assert aovs[name].shape[:2] == (32, 40) and aovs[name].dtype == np.float32, name
    assert (aovs["triangle_id"][aovs["mask"] == 0] == -1).all()
    from jaxnm.io import load_texture

    img, bits = load_texture(png)
    assert img.shape == (32, 40, 3) and bits == 8


def test_cli_errors_are_one_line_and_exit_2(tmp_path, capsys):
    assert main(["render", str(tmp_path / "nope.json")]) == 2
    err = capsys.readouterr().err
    assert "nope.json" in err and "Traceback" not in err
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps(_scene_dict(frame="wrong")))
    assert main(["render", str(bad), "-o", str(tmp_path / "x.png")]) == 2
    assert "frame" in capsys.readouterr().err


@pytest.mark.parametrize("argv,message", [
    (["--width", "-5"], "--width must be 1 to 16384 pixels, got -5"),
    (["--height", "20000"], "--height must be 1 to 16384 pixels, got 20000"),
    (["--exposure", "-1"], "--exposure must be a positive finite scale, got -1.0"),
    (["--exposure", "nan"], "--exposure must be a positive finite scale, got nan"),
    (["-o", "{d}/x.jpg"], "-o {d}/x.jpg: jaxnm render writes PNG images; the name must end "
                          "in .png"),
    (["--aovs", "{d}/a.txt"], "--aovs {d}/a.txt: the arrays are written as NumPy .npz; the "
                              "name must end in .npz"),
    (["--aov-list", "uv"], "--aov-list names the arrays that --aovs writes: give --aovs "
                           "OUT.npz too"),
    (["--aovs", "{d}/a.npz", "--aov-list", " ,"],
     "--aov-list names no array; name at least one of mask, triangle_id, depth, front_facing, "
     "position, view, uv, normal, dpdx, dpdy, duvdx, duvdy, tangent, bitangent, "
     "perturbed_normal, color"),
    (["--height-scale", "0.1"], "--height-scale scales the map --height-map reads: give "
                                "--height-map PATH too"),
    (["--height-map", "{d}/h.png", "--height-scale", "inf"],
     "--height-scale must be finite, got inf"),
    (["--height-map", "{d}/h.png"], "--height-map: {d}/h.png: no such file"),
    (["--normal-map", "{d}"], "--normal-map: {d}: not a regular file"),
])
def test_cli_options_are_checked_before_anything_is_loaded(tmp_path, capsys, monkeypatch,
                                                          argv, message):
    import jaxnm.cli._render as R

    def no_scene(args):
        raise AssertionError("the scene was made before the options were checked")

    monkeypatch.setattr(R, "_scene", no_scene)
    assert main(["render", *[a.format(d=tmp_path) for a in argv]]) == 2
    err = capsys.readouterr().err.strip()
    assert err == f"jaxnm render: error: {message.format(d=tmp_path)}", err
    assert not list(tmp_path.iterdir())


def test_cli_height_map_scale_defaults_to_the_documented_value(tmp_path):
    import imageio.v3 as iio

    y, x = np.mgrid[0:16, 0:16]
    iio.imwrite(tmp_path / "h.png", (127.5 + 127.5 * np.sin(x / 2.0) * np.cos(y / 3.0))
                .astype(np.uint8))
    images = {}
    for name, scale in (("default", ()), ("explicit", ("--height-scale", "0.02")),
                        ("steeper", ("--height-scale", "0.2"))):
        out = tmp_path / f"{name}.png"
        assert main(["render", "--height-map", str(tmp_path / "h.png"), *scale, "--width", "24",
                     "--height", "24", "-o", str(out)]) == 0
        images[name] = iio.imread(out)
    assert np.array_equal(images["default"], images["explicit"])  # the help's 0.02
    assert not np.array_equal(images["default"], images["steeper"])


def test_cli_takes_a_normal_map_or_a_height_map_not_both(tmp_path, capsys):
    with pytest.raises(SystemExit) as e:
        main(["render", "--normal-map", "n.png", "--height-map", "h.png"])
    assert e.value.code == 2
    assert capsys.readouterr().err.strip() == ("jaxnm render: error: argument --height-map: not "
                                               "allowed with argument --normal-map (see jaxnm "
                                               "render --help)")


def test_cli_normal_map_override_must_be_rgb(tmp_path, capsys):
    from jaxnm.io import save_png

    gray = tmp_path / "gray.png"
    save_png(gray, np.full((8, 8), 0.5, np.float32))
    assert main(["render", "--normal-map", str(gray), "--width", "16", "--height", "16",
                 "-o", str(tmp_path / "x.png")]) == 2
    assert "gray.png" in capsys.readouterr().err


def test_lights_and_material_change_the_image(plane_scene):
    base = _mapped(plane_scene)
    a = render(base, outputs=PLANE_OUTPUTS)["color"]
    left = Lights(directional=stack_lights([DirectionalLight(jnp.array([-1.0, 0, 0.5]),
                                                             jnp.ones(3), jnp.asarray(1.0))]))
    lit_left = base.replace(lights=left, material=Material(
        jnp.ones(3), jnp.zeros(3), jnp.asarray(1.0), jnp.zeros(3)))
    b = render(lit_left, outputs=PLANE_OUTPUTS)["color"]
    assert np.abs(a - b).mean() > 0.05


def test_height_map_bumps_toward_the_light(tmp_path):
    """A single bump as a height map (surface-gradient bump mapping) on a plane lit from +x:
    the bump's +x flank is brighter than its -x flank, and it agrees with the equivalent
    tangent-space normal map."""
    from jaxnm.io import save_png

    n = 64
    t = (np.arange(n) + 0.5) / n
    u, v = np.meshgrid(t, 1 - t)
    h = np.exp(-((u - 0.5) ** 2 + (v - 0.5) ** 2) / 0.02)
    save_png(tmp_path / "h.png", h.astype(np.float32), bits=16)
    base = {"mesh": "builtin:plane", "width": 64, "height": 64,
            "camera": {"eye": [0, 0, 3], "target": [0, 0, 0], "fov_y_deg": 40},
            "lights": [{"type": "directional", "direction": [1, 0, 0.3]}],
            "material": {"model": "lambert", "ambient": [0, 0, 0]}, "albedo": [1, 1, 1]}
    p = tmp_path / "s.json"
    p.write_text(json.dumps({**base, "height_map": {"path": "h.png", "scale": 0.1}}))
    sc = load_scene(p)
    assert sc.normal_map_options.space == "derivative"
    c = render(sc, outputs=("color", "perturbed_normal"))
    lum = c["color"][..., 0]
    assert lum[32, 40:46].mean() > lum[32, 18:24].mean() + 0.2
    assert np.isfinite(c["perturbed_normal"]).all()
    # the same bump as a tangent-space normal map (builtin:plane spans 2 x 2 world units)
    hn = np.asarray(height_to_normal_map(h * 0.1 / 2.0 * n, scale=1.0))
    q = tmp_path / "s2.json"
    save_png(tmp_path / "n.png", (hn + 1) / 2, bits=16)
    q.write_text(json.dumps({**base, "normal_map": {"path": "n.png"}}))
    c2 = render(load_scene(q), outputs=("perturbed_normal", "mask"))
    m = c2["mask"][..., 0] > 0
    ang = np.degrees(np.arccos(np.clip((c["perturbed_normal"] * c2["perturbed_normal"]).sum(-1),
                                       -1, 1)))
    assert np.median(ang[m]) < 1.0 and np.percentile(ang[m], 95) < 4.0


def test_hlsl_ddy_turns_bumps_into_dents(plane_scene):
    """HLSL's ddy points down: fed to the GLSL cotangent frame it negates T and B (not the
    handedness), i.e. the map's tangential part is rotated by 180 degrees about N."""
    sc = _mapped(plane_scene)
    up = render(sc, outputs=PLANE_OUTPUTS)
    down = render(sc.replace(ddy="down"), outputs=("tangent", "bitangent", "perturbed_normal"))
    m = up["mask"][..., 0] > 0
    np.testing.assert_allclose(down["tangent"][m], -up["tangent"][m], atol=1e-5)
    np.testing.assert_allclose(down["bitangent"][m], -up["bitangent"][m], atol=1e-5)
    # the tangential offset from N flips: reflection of the perturbed normal about N
    n = up["normal"][m]
    pu, pd = up["perturbed_normal"][m], down["perturbed_normal"][m]
    refl = 2 * (pu * n).sum(-1, keepdims=True) * n - pu
    np.testing.assert_allclose(pd, refl, atol=2e-4)
    with pytest.raises(ValueError, match="ddy"):
        sc.replace(ddy="sideways")


def test_scene_fields_are_checked_before_the_mesh_is_loaded(tmp_path):
    p = tmp_path / "scene.json"
    p.write_text(json.dumps(_scene_dict(mesh="not_there.obj", frame="diagonal")))
    with pytest.raises(ValueError, match=r"scene.json: unknown frame 'diagonal'"):
        load_scene(p)


def test_options_are_validated_however_they_are_built(plane_scene):
    """A bad option is refused when its object is made, not inside `render`."""
    import dataclasses

    from jaxnm.gbuffer import RenderOptions
    from jaxnm.textures import NormalMapOptions

    with pytest.raises(ValueError, match="wrap='bogus'"):
        NormalMapOptions(wrap="bogus")
    with pytest.raises(ValueError, match="filter"):
        dataclasses.replace(NormalMapOptions(), filter="cubic")
    with pytest.raises(ValueError, match="unknown frame"):
        dataclasses.replace(plane_scene, frame="tangent")
    with pytest.raises(ValueError, match="derivatives"):
        Scene(mesh=plane_scene.mesh, camera=plane_scene.camera, derivatives="smooth")
    with pytest.raises(ValueError, match="width"):
        Scene(mesh=plane_scene.mesh, camera=plane_scene.camera, width=0)
    with pytest.raises(ValueError, match="outputs"):
        RenderOptions(width=8, height=8, outputs=("colour",))
    with pytest.raises(ValueError, match="falloff"):
        jaxnm.PointLight(jnp.zeros(3), jnp.ones(3), jnp.asarray(1.0), falloff="linear")


def test_cli_normal_map_is_decoded_as_its_help_says(tmp_path, plane_scene):
    """`--normal-map` overrides the scene's map options to unsigned, green up, tangent space."""
    from jaxnm.io import save_png

    texels = procedural.default_normal_map_texels(32)
    save_png(tmp_path / "n.png", texels)
    scene_file = tmp_path / "s.json"
    scene_file.write_text(json.dumps({**_scene_dict(), "normal_map": {
        "path": "n.png", "green": "down", "encoding": "unsigned_exact"}}))
    out_cli = tmp_path / "cli.npz"
    assert main(["render", str(scene_file), "--normal-map", str(tmp_path / "n.png"),
                 "-o", str(tmp_path / "x.png"), "--aovs", str(out_cli),
                 "--aov-list", "perturbed_normal"]) == 0
    ref = render(load_scene(scene_file).replace(
        normal_map=texels, normal_map_options=jaxnm.NormalMapOptions()),
        outputs=("color", "perturbed_normal"))["perturbed_normal"]  # the command's outputs
    np.testing.assert_allclose(np.load(out_cli)["perturbed_normal"], ref, atol=1e-6)


_CACHE_PROBE = """
import sys, jax, jax.monitoring as m
events = {"hits": 0, "misses": 0}
def on(name, **kw):
    if name == "/jax/compilation_cache/cache_hits": events["hits"] += 1
    if name == "/jax/compilation_cache/cache_misses": events["misses"] += 1
m.register_event_listener(on)
from jaxnm.cli import main
rc = main(sys.argv[1:])
import os
print("EVENTS", rc, events["hits"], events["misses"])
print("DETERMINISTIC", "--xla_gpu_deterministic_ops=true" in os.environ.get("XLA_FLAGS", ""))
"""


@pytest.mark.slow
def test_cli_uses_the_persistent_compilation_cache(tmp_path):
    """A second `jaxnm render` loads its programs from the cache the first one filled;
    `--no-compile-cache` turns it off (as JAXNM_COMPILATION_CACHE=off does: below). The CLI
    also asks XLA for deterministic GPU ops unless told `--nondeterministic`."""
    import os
    import subprocess
    import sys

    cache = tmp_path / "cache"
    env = dict(os.environ, JAXNM_COMPILATION_CACHE=str(cache), XLA_FLAGS="")
    args = ["render", "--width", "24", "--height", "24", "-o", str(tmp_path / "x.png")]

    deterministic = []

    def run(*extra, env=env):
        out = subprocess.run([sys.executable, "-c", _CACHE_PROBE, *args, *extra], env=env,
                             capture_output=True, text=True, timeout=300, check=True).stdout
        rc, hits, misses = map(int, out.split("EVENTS")[1].split("DETERMINISTIC")[0].split())
        deterministic.append(out.split("DETERMINISTIC")[1].strip() == "True")
        assert rc == 0
        return hits, misses

    hits, first_misses = run()
    assert hits == 0 and first_misses > 0 and any(cache.iterdir())
    hits, _ = run()
    # JAX's "miss" event is a write: every program the first run stored is read back. (A
    # program compiled in under `min_compile_seconds` is not stored; one near that threshold
    # may be stored by the second run only, so the second run's writes are not bounded.)
    assert hits >= first_misses
    # (the two flags are independent: one run checks both)
    assert run("--no-compile-cache", "--nondeterministic") == (0, 0)
    assert deterministic == [True, True, False]


def test_the_compilation_cache_folder_follows_the_environment(monkeypatch, tmp_path):
    """JAXNM_COMPILATION_CACHE names the folder, or turns the cache off; unset, the cache is
    under XDG_CACHE_HOME, else ~/.cache."""
    from jaxnm.cli import _compilation_cache_dir

    for off in ("off", "OFF", "", " ", "0", "false", "no"):
        monkeypatch.setenv("JAXNM_COMPILATION_CACHE", off)
        assert _compilation_cache_dir() is None, off
    monkeypatch.setenv("JAXNM_COMPILATION_CACHE", str(tmp_path / "c"))
    assert _compilation_cache_dir() == tmp_path / "c"
    monkeypatch.delenv("JAXNM_COMPILATION_CACHE")
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "x"))
    assert _compilation_cache_dir() == tmp_path / "x" / "jaxnm" / "xla"
    monkeypatch.delenv("XDG_CACHE_HOME")
    monkeypatch.setenv("HOME", str(tmp_path / "h"))
    assert _compilation_cache_dir() == tmp_path / "h" / ".cache" / "jaxnm" / "xla"


@pytest.mark.parametrize("outputs", [None, (), []])
def test_render_refuses_outputs_that_name_nothing(outputs):
    with pytest.raises(ValueError, match="^render: outputs names nothing; name one or more of "
                                         "mask, triangle_id, "):
        render(default_scene(width=16, height=16), outputs=outputs)


def test_render_refuses_what_is_not_a_scene():
    with pytest.raises(TypeError, match=r"^expected a jaxnm Scene \(jaxnm.config.load_scene, "
                                        r"jaxnm.procedural.default_scene\), got dict$"):
        render({"mesh": "builtin:plane"})


@pytest.mark.parametrize("field,value,message", [
    ("normal_map", np.zeros((8, 8), np.float32), r"the normal map must have shape \(H, W, C\)"),
    ("normal_map", np.zeros((8, 8, 3), np.uint8), "the normal map must hold floating-point"),
    ("albedo", np.zeros(5, np.float32), r"the albedo must be .* got shape \(5,\)"),
    ("model", np.eye(3, dtype=np.float32), r"the model matrix must be 4x4, got \(3, 3\)"),
])
def test_render_names_the_scene_and_the_field_of_an_array_of_the_wrong_shape(field, value,
                                                                             message):
    """A scene changed by hand after it was made (`Scene.replace` checks no arrays) is
    refused by `render` in one line naming the scene and what is wrong, before anything is
    traced, under the caller's `jax.jit` too."""
    sc = default_scene(width=16, height=16).replace(source="my scene", **{field: value})
    with pytest.raises(ValueError, match=f"^my scene: {message}"):
        render(sc)
    with pytest.raises(ValueError, match=f"^my scene: {message}"):
        jax.jit(lambda s: render(s)["color"])(sc)


@pytest.mark.parametrize("field,value,message", [
    ("lights", [directional_light((0, 0, 1))],
     r"lights must be a jaxnm.Lights \(directional_light\(...\), or "
     r"Lights\(directional=stack_lights\(\[...\]\), point=...\)\), got list$"),
    ("material", {"diffuse": (1, 1, 1)}, r"material must be a jaxnm.Material \(.*\), got dict$"),
    ("mesh", "trimesh", r"mesh must be a jaxnm.Mesh \(jaxnm.io.load_mesh\(path\), or "
     r"jaxnm.Mesh\(positions, faces, uv=..., normals=...\)\), got Trimesh$"),
    ("mesh", "lists", r"positions must be an array \(np.asarray\(positions, np.float32\), "
     r"say\), got a list$"),
    ("camera", None, r"camera must be a jaxnm.Camera \(jaxnm.Camera.look_at\(eye, target, "
     r"up\), or Camera.from_matrices\(view, projection\)\), got NoneType$"),
    ("camera", np.eye(4), r"camera must be a jaxnm.Camera \(.*\), got ndarray$"),
    ("normal_map", "texture", r"normal_map must be an array, got a tuple whose items do not "
     r"form one \(jaxnm.io.load_texture returns \(image, bits\)\)$"),
    ("albedo", ([0.5, 0.5], 0.5), r"albedo must be an array, got a tuple whose items do not "
     r"form one$"),
])
def test_render_names_a_field_of_the_wrong_type(field, value, message):
    """A list of lights (which the shading functions take), a dict for a material, a trimesh
    mesh or a `Mesh` of lists, a camera that is none or a matrix, or what `load_texture`
    returns (an image and its bit depth) for a map is named in one line, not met as an
    AttributeError or NumPy's ragged-array error deep in the renderer."""
    import trimesh

    from jaxnm.io import load_texture

    if isinstance(value, str) and value == "lists":
        value = jaxnm.Mesh(positions=[[0, 0, 0], [1, 0, 0], [0, 1, 0]], faces=[[0, 1, 2]])
    elif isinstance(value, str):
        value = trimesh.creation.icosahedron() if value == "trimesh" else load_texture(
            Path(__file__).parents[1] / "scripts" / "examples" / "scenes" / "torus" / "rivets.png")
    sc = default_scene(width=16, height=16).replace(source="my scene", **{field: value})
    with pytest.raises(TypeError, match=f"^my scene: {message}"):
        render(sc)


@pytest.mark.parametrize("aspect", [0.5, 1.0, 2.0])
def test_framing_sees_the_whole_sphere_and_touches_the_narrower_side(aspect):
    """`Camera.framing`: every point of the sphere (enlarged by the margin) projects inside
    the view, the sphere itself lies between the near and far planes, and the enlarged
    sphere touches the view's narrower side (|NDC| reaches 1 there, to the sampling's
    resolution); the eye is on the ray from the centre along the direction."""
    from jaxnm.camera import Camera

    rng = np.random.default_rng(0)
    u = rng.normal(size=(20000, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    c, r, margin = np.array([3.0, -2.0, 7.0]), 2.5, 1.1
    for d in ([0.3, -1.0, 0.4], [0.0, 0.0, 1.0], [-1.0, 0.0, 0.0]):
        cam = Camera.framing(c, r, d, aspect=aspect, margin=margin, fov_y_deg=40.0)
        m = np.asarray(cam.projection, np.float64) @ np.asarray(cam.view, np.float64)

        def ndc(p):
            clip = np.c_[p, np.ones(len(p))] @ m.T
            assert (clip[:, 3] > 0).all()
            return clip[:, :3] / clip[:, 3:]

        outer, inner = ndc(c + r * margin * u), ndc(c + r * u)
        assert np.abs(outer[:, :2]).max() < 1 + 1e-5
        assert np.abs(outer[:, 0 if aspect < 1 else 1]).max() > 0.995
        assert np.abs(inner[:, 2]).max() < 1
        to_eye = np.asarray(cam.eye) - c
        assert np.linalg.norm(np.cross(to_eye, d)) < 1e-9 * np.linalg.norm(to_eye)
        assert to_eye @ np.asarray(d) > 0


def test_a_camera_built_from_traced_values_is_named_and_a_traced_camera_renders():
    """`Camera.look_at` and `Camera.from_matrices` compute on the host in float64: a traced
    eye is refused in one line that says what to trace instead, and tracing the arrays
    of a ready camera renders what the concrete camera renders."""
    sc = default_scene(width=16, height=16)
    eye = jnp.asarray(sc.camera.eye, jnp.float32)
    with pytest.raises(TypeError, match=r"^camera: look_at builds a camera on the host in "
                       r"float64 and takes concrete values, but `eye` is traced"):
        jax.jit(lambda e: jaxnm.Camera.look_at(e, (0, 0, 0), (0, 0, 1)))(eye)
    with pytest.raises(TypeError, match="^camera: from_matrices .* `view` is traced"):
        jax.jit(lambda v: jaxnm.Camera.from_matrices(v, sc.camera.projection))(
            sc.camera.view)
    traced = jax.jit(lambda c: render(sc.replace(camera=c))["color"])(sc.camera)
    np.testing.assert_allclose(traced, render(sc)["color"], atol=1e-5)


def test_one_output_may_be_named_alone():
    sc = default_scene(width=16, height=16)
    alone, listed = render(sc, outputs="mask"), render(sc, outputs=("mask",))
    assert list(alone) == ["mask"]
    np.testing.assert_array_equal(alone["mask"], listed["mask"])


def test_value_checks_are_for_where_scenes_are_made():
    """`check_mesh_arrays` scans the values of concrete arrays, JAX's and NumPy's alike, every
    time it is asked (``values=False``: shapes and dtypes only, what `render` checks on every
    call); a NaN written into a NumPy mesh in place is found."""
    from jaxnm import geometry

    mesh = procedural.plane(1.0, 2)
    host = np.array(mesh.positions)
    geometry.check_mesh_arrays(host, mesh.faces, mesh.uv, mesh.normals, source="m")
    host[1, 0] = np.nan
    for pos in (host, jnp.asarray(host)):
        with pytest.raises(ValueError, match=r"m: 1 vertex position is NaN or infinite \(the "
                           r"first: vertex 1, counting from 0\)"):
            geometry.check_mesh_arrays(pos, mesh.faces, mesh.uv, mesh.normals, source="m")
        geometry.check_mesh_arrays(pos, mesh.faces, mesh.uv, mesh.normals, source="m",
                                 values=False)
    host[3, 2] = np.inf
    with pytest.raises(ValueError, match=r"m: 2 vertex positions are NaN or infinite \(the "
                       r"first: vertex 1, counting from 0\)"):
        geometry.check_mesh_arrays(host, mesh.faces, mesh.uv, mesh.normals, source="m")
    with pytest.raises(ValueError, match=r"m: positions must have shape \(V, 3\)"):
        geometry.check_mesh_arrays(host[:, :2], mesh.faces, values=False, source="m")
    uv, normals = np.array(mesh.uv), np.array(mesh.normals)
    uv[2, 1], normals[[0, 3], 0] = np.nan, np.inf  # counted and named as positions are
    with pytest.raises(ValueError, match=r"^m: 1 vertex uv is NaN or infinite \(the first: "
                       r"vertex 2, counting from 0\)$"):
        geometry.check_mesh_arrays(mesh.positions, mesh.faces, uv, mesh.normals, source="m")
    with pytest.raises(ValueError, match=r"^m: 2 vertex normals are NaN or infinite \(the "
                       r"first: vertex 0, counting from 0\)$"):
        geometry.check_mesh_arrays(mesh.positions, mesh.faces, mesh.uv, normals, source="m")


@pytest.mark.parametrize("size", [WHOLE, PACKED])  # the whole image; packed pixels
def test_triangles_with_nan_corners_or_bad_indices_cover_nothing(size):
    """`render` does not scan values on the host (`validate_scene` does, where scenes are
    made); a triangle with a NaN or infinite corner, or a face index out of range, covers
    no pixel, as on a GPU: the image is the one of the mesh without those triangles. (Every
    render asks for the same outputs: the meshes of the mesh's shape share one program.)"""
    sc = builtin_scene(size)
    m = sc.mesh
    faces = np.asarray(m.faces)
    outs = OUTPUTS  # (those of the other tests' renders of this scene)
    tid = np.asarray(render(sc, outputs=outs)["triangle_id"])
    rows, cols = np.nonzero(tid[..., 0] >= 0)
    k = len(rows) // 2
    victim = int(faces[int(tid[rows[k], cols[k], 0]), 0])  # a vertex in view
    uses = np.any(faces == victim, axis=1)
    without = render(sc.replace(mesh=dataclasses.replace(m, faces=jnp.asarray(faces[~uses]))),
                     outputs=outs)
    for bad in (np.nan, np.inf):
        pos = jnp.asarray(m.positions).at[victim, 1].set(bad)
        got = render(sc.replace(mesh=dataclasses.replace(m, positions=pos)), outputs=outs)
        for name in ("color", "mask"):
            np.testing.assert_array_equal(got[name], without[name], err_msg=f"{bad} {name}")
    bad_faces = np.where(uses[:, None], np.array([[0, 1, 10**6]]), faces)
    got = render(sc.replace(mesh=dataclasses.replace(m, faces=jnp.asarray(bad_faces))),
                 outputs=outs)
    # they were in view
    assert not np.array_equal(without["color"], render(sc, outputs=outs)["color"])
    for name in ("color", "mask"):
        np.testing.assert_array_equal(got[name], without[name], err_msg=f"indices {name}")


def test_near_plane_check_finds_the_one_vertex_in_front():
    """The near-plane check looks at a sample of vertices first; a mesh whose only visible
    vertex is outside the sample still renders, and one with none is refused."""
    n = 4000
    rng = np.random.default_rng(0)
    pos = np.column_stack([rng.uniform(-1, 1, n), rng.uniform(-1, 1, n), np.full(n, 5.0)])
    pos[1237] = [0.0, 0.0, -2.0]  # the camera at z = 3 looks down -z: only this one is seen
    faces = np.array([[1236, 1237, 1238]])
    mesh = jaxnm.Mesh(jnp.asarray(pos, jnp.float32), jnp.asarray(faces))
    cam = jaxnm.Camera.look_at([0, 0, 3], [0, 0, 0])
    validate_scene(Scene(mesh=mesh, camera=cam, width=8, height=8))
    mesh_behind = jaxnm.Mesh(jnp.asarray(np.where(np.arange(n)[:, None] == 1237, pos + [0, 0, 7],
                                                  pos), jnp.float32), jnp.asarray(faces))
    with pytest.raises(ValueError, match="behind the camera's near plane"):
        validate_scene(Scene(mesh=mesh_behind, camera=cam, width=8, height=8))


@pytest.fixture
def strategy(monkeypatch):
    """``run(packed, chunk, fn)``: ``fn()`` with `render`'s per-pixel stages on the whole
    image (``packed`` False) or on packed covered pixels in chunks of ``chunk`` slots
    (whatever the image size), its frame program compiled afresh; the cache is cleared
    again afterwards."""
    R = importlib.import_module("jaxnm.render")
    P = importlib.import_module("jaxnm._exec.pixels")

    def clear():
        for program in (R._frame, R._visible_placed, R._packed_frame):
            program.clear_cache()

    def run(packed, chunk, fn):
        monkeypatch.setattr(P, "PACK_MIN_PIXELS", 1 if packed else 1 << 40)
        monkeypatch.setattr(P, "PIXEL_CHUNK", (chunk, chunk))
        clear()
        return fn()

    yield run
    clear()


@pytest.mark.parametrize("frame,derivatives,precision,eye", [
    ("cotangent", "fine", "float32", (0.5, -4.5, 3.0)),
    ("exact", "coarse", "float16", (0.5, -4.5, 3.0)),
    ("vertex", "analytic", "float32", (0.5, -4.5, 3.0)),
    ("cotangent", "fine", "float32", (0.0, -2.35, 1.75))])  # over a quarter: all slots
def test_packed_pixels_render_what_the_whole_image_renders(frame, derivatives, precision, eye,
                                                          strategy):
    """On the CPU `render` runs the per-pixel stages on the covered pixels only, packed into
    a quarter of the image's slots when they fit and into all of them otherwise, in chunks
    (those past the covered pixels skipped): every output must be what the per-pixel stages
    give on the image as it is (each pixel sees its own triangle and its own window
    position, quad partners included): coverage, ids and facing exactly, the rest to float32
    rounding."""
    from jaxnm.camera import Camera, look_at, perspective
    from jaxnm.gbuffer import OUTPUTS

    sc = default_scene(width=96, height=64)
    sc = sc.replace(mesh=sc.mesh.with_tangents(), camera=Camera.from_matrices(
        look_at(eye, (0.3, 0.0, -0.1), (0.0, 0.0, 1.0)),
        perspective(45.0, 1.5, 0.1, 50.0)))
    kw = dict(outputs=OUTPUTS, frame=frame, derivatives=derivatives, precision=precision)
    whole = strategy(False, 256, lambda: render(sc, **kw))  # image layout
    covered = np.asarray(whole["mask"][..., 0]) > 0
    assert 0.05 < covered.mean() < 0.25 or covered.mean() > 0.5  # 1/4 of the slots, or all
    # chunks of 256 slots: 6 (or 24), some skipped
    packed = strategy(True, 256, lambda: render(sc, **kw))
    for name in OUTPUTS:
        if name in ("mask", "triangle_id", "front_facing"):
            np.testing.assert_array_equal(packed[name], whole[name], err_msg=name)
        else:  # the same arithmetic, fused differently by XLA: float32 ulps of the terms
            scale = float(np.abs(np.asarray(whole[name])).max())
            np.testing.assert_allclose(packed[name], whole[name], rtol=0,
                                       atol=2e-6 * max(scale, 1e-3), err_msg=name)
    assert np.abs(np.asarray(whole["duvdx"])[covered]).max() > 0  # derivatives are there


def test_chunked_pixels_give_the_image_layouts_gradient(strategy):
    """Forward and reverse mode through the packed chunks (a `lax.cond` choosing the slot
    count, a `lax.map` over chunks, a `lax.cond` skipping chunks without a covered pixel)
    give the gradient with respect to the map, the albedo and the light of the per-pixel
    stages run on the image as it is, eagerly and under the caller's jit."""
    import jax

    sc = default_scene(width=48, height=32)
    texels = jnp.asarray(sc.normal_map)
    first = render(sc, outputs=("color", "mask"))
    target = first["color"] * 0.9

    def loss(t, albedo):
        s = sc.replace(normal_map=t, albedo=albedo)
        return jnp.sum((render(s)["color"] - target) ** 2)

    args = (texels, jnp.asarray([0.7, 0.6, 0.5], jnp.float32))
    grad = jax.value_and_grad(loss, argnums=(0, 1))
    ref = strategy(False, 256, lambda: jax.jit(grad)(*args))
    assert float(jnp.abs(ref[1][0]).max()) > 0 and float(jnp.abs(ref[1][1]).max()) > 0
    covered = int(jnp.count_nonzero(first["mask"]))
    # over a quarter: all 1536 slots, 6 chunks of 256, the last 2 skipped (the quarter's
    # branch: `test_render_under_a_callers_jit_and_grad`)
    assert 48 * 32 // 4 < covered <= 48 * 32 - 2 * 256
    for jit in (True, False):
        value, (g_map, g_albedo) = strategy(True, 256, lambda: (jax.jit(grad) if jit
                                                                else grad)(*args))
        np.testing.assert_allclose(value, ref[0], rtol=1e-5)
        np.testing.assert_allclose(g_map, ref[1][0], rtol=1e-4,
                                   atol=1e-5 * float(jnp.abs(ref[1][0]).max()))
        np.testing.assert_allclose(g_albedo, ref[1][1], rtol=1e-4)


def test_compact_and_expand_round_trip():
    """`compact` packs the covered pixels with their window positions, depth and facing (as
    `rasterize` gives them); `expand` puts per-slot values back; unused slots are background
    and write nothing; 'gbuffer' derivatives (stored neighbours) are refused on packed
    fragments."""
    from jaxnm.raster import compact, expand

    sc = default_scene(width=16, height=12)
    frags = jaxnm.rasterize(jaxnm.to_clip(sc.mesh.positions, sc.camera), sc.mesh.faces,
                            width=16, height=12)
    n = int(frags.mask.sum())
    packed, index = compact(frags.triangle_id, frags.clip, frags.faces, n + 5)
    assert packed.shape == (n + 5,) and packed.image_shape == (12, 16)
    assert int(packed.mask.sum()) == n and np.all(np.asarray(index[n:]) == 16 * 12)
    x, y = frags.window_centers()
    px, py = packed.window_centers()
    for whole, part in ((x, px), (y, py), (frags.front_facing, packed.front_facing),
                        (frags.triangle_id, packed.triangle_id)):
        back = expand(part, index, 12, 16)
        np.testing.assert_array_equal(np.where(frags.mask, back, 0), np.where(frags.mask,
                                                                              whole, 0))
    np.testing.assert_allclose(expand(packed.depth, index, 12, 16, 1.0), frags.depth,
                               rtol=0, atol=4e-7)  # the same plane, fused differently
    # the vertices' window x, y, w computed once for the per-pixel stages: what they would
    # compute from the clip vertices, and the same interpolation either way
    from jaxnm.camera import to_window

    np.testing.assert_array_equal(packed.window, np.asarray(to_window(
        frags.clip, 16, 12))[:, [0, 1, 3]])
    at = jaxnm.interpolate(sc.mesh.uv, packed, derivatives="fine")
    again = jaxnm.interpolate(sc.mesh.uv, dataclasses.replace(packed, window=None),
                              derivatives="fine")
    for u, v in zip((at.value, at.ddx, at.ddy), (again.value, again.ddx, again.ddy)):
        np.testing.assert_array_equal(u, v)
    with pytest.raises(ValueError, match="packed fragments"):
        jaxnm.interpolate(sc.mesh.uv, packed, derivatives="gbuffer")
    # derivatives of expand (a scatter told its indices are unique, the unused slots' too):
    # forward and reverse mode against the same map written as a dense 0/1 matrix
    import jax

    vals = jnp.asarray(np.random.default_rng(0).normal(size=(n + 5, 3)), jnp.float32)
    tan = jnp.asarray(np.random.default_rng(1).normal(size=(n + 5, 3)), jnp.float32)
    place = np.zeros((12 * 16, n + 5), np.float32)
    used = np.asarray(index) < 12 * 16
    place[np.asarray(index)[used], np.flatnonzero(used)] = 1.0

    def dense(v):
        return (place @ np.asarray(v, np.float64)).reshape(12, 16, 3)

    def fn(v):
        return expand(v, index, 12, 16)

    _, jvp_out = jax.jvp(fn, (vals,), (tan,))
    np.testing.assert_allclose(jvp_out, dense(tan), rtol=1e-6)
    np.testing.assert_allclose(fn(vals), dense(vals), rtol=1e-6)
    ct = jnp.asarray(np.random.default_rng(2).normal(size=(12, 16, 3)), jnp.float32)
    (g,) = jax.vjp(fn, vals)[1](ct)
    np.testing.assert_allclose(g, place.T @ np.asarray(ct, np.float64).reshape(-1, 3),
                               rtol=1e-6, atol=1e-7)


@pytest.mark.parametrize("backend, size, derivatives, packs", [
    ("cpu", 256, "fine", True), ("cpu", 128, "fine", False), ("gpu", 256, "fine", False),
    ("cpu", 256, "gbuffer", False)])
def test_packing_is_for_large_images_on_the_cpu(backend, size, derivatives, packs):
    """`render` packs the covered pixels of images of at least `PACK_MIN_PIXELS` pixels on
    the CPU only (a GPU shades every pixel at once), never for "gbuffer" derivatives (they
    read stored neighbours)."""
    P = importlib.import_module("jaxnm._exec.pixels")
    assert (size * size >= P.PACK_MIN_PIXELS) == (packs or backend != "cpu"
                                                   or derivatives == "gbuffer")
    assert P.packs(size * size, neighbours=derivatives == "gbuffer", backend=backend) == packs


@pytest.mark.parametrize("eye", [(0.5, -4.5, 3.0), (0.0, -1.6, 1.2)])  # fits a quarter, not
def test_render_under_a_callers_jit_and_grad(eye, strategy):
    """Inside a caller's `jax.jit` (the scene closed over, or an argument) and under
    `jax.grad`, `render` runs the same program as eagerly: the same image, and the same
    gradient as the whole image's, whether the covered pixels fit in a quarter of the slots
    or not."""
    import jax

    from jaxnm.camera import Camera, look_at, perspective

    sc = default_scene(width=48, height=32)
    sc = sc.replace(camera=Camera.from_matrices(
        look_at(eye, (0.3, 0.0, -0.1), (0.0, 0.0, 1.0)), perspective(45.0, 1.5, 0.1, 50.0)))
    texels = jnp.asarray(sc.normal_map)

    def loss(s, t):
        return jnp.sum(render(s.replace(normal_map=t))["color"])

    g_whole = strategy(False, 256, lambda: jax.grad(loss, argnums=1)(sc, texels))
    assert float(jnp.abs(g_whole).max()) > 0
    tol = dict(rtol=1e-4, atol=1e-5 * float(jnp.abs(g_whole).max()))

    def packed():
        eager = render(sc)["color"]
        covered = int(jnp.count_nonzero(eager.sum(-1) > 0))
        jitted = jax.jit(lambda t: render(sc.replace(normal_map=t))["color"])(texels)
        # closed over, the scene is a compile-time constant XLA folds: float32 rounding,
        # amplified by the specular power
        np.testing.assert_allclose(jitted, eager, rtol=0, atol=1e-4)
        np.testing.assert_allclose(jax.grad(loss, argnums=1)(sc, texels), g_whole, **tol)
        value, g = jax.jit(jax.value_and_grad(loss, argnums=1))(sc, texels)
        np.testing.assert_allclose(value, jnp.sum(eager), rtol=1e-5)
        np.testing.assert_allclose(g, g_whole, **tol)
        return covered

    covered = strategy(True, 256, packed)
    assert 0 < covered
    assert (covered <= 48 * 32 // 4) == (eye[1] < -2)  # both of the program's branches run


@pytest.mark.parametrize("derivatives", ["fine", "analytic"])
def test_covered_gbuffer_is_the_whole_images_at_the_covered_pixels(derivatives):
    """`covered_gbuffer` (what `jaxnm.fit.prepare` builds a view from) holds, in its first
    ``count`` slots, the covered pixels in row-major order with `build_gbuffer`'s values
    there: ids, mask and facing exactly, the rest to float32 rounding (fused differently);
    "gbuffer" derivatives are refused."""
    import dataclasses

    import jax

    from jaxnm.camera import Camera, look_at, perspective
    from jaxnm.gbuffer import RenderOptions
    from jaxnm.render import build_gbuffer, covered_gbuffer

    sc = default_scene(width=48, height=32)
    sc = sc.replace(camera=Camera.from_matrices(
        look_at((0.5, -4.5, 3.0), (0.3, 0.0, -0.1), (0.0, 0.0, 1.0)),
        perspective(45.0, 1.5, 0.1, 50.0)))
    opts = RenderOptions.of(sc, outputs=("color",), derivatives=derivatives)
    albedo = jnp.asarray(sc.albedo)
    whole = build_gbuffer(sc.mesh, sc.camera, albedo, opts=opts)
    gb, index, count = covered_gbuffer(sc.mesh, sc.camera, albedo, opts=opts)
    pix = np.flatnonzero(np.asarray(whole.mask))
    assert 0 < count == pix.size < 48 * 32 // 2
    np.testing.assert_array_equal(np.asarray(index)[:count], pix)
    assert np.all(np.asarray(index)[count:] == 48 * 32)  # unused slots
    flat_whole = jax.tree_util.tree_leaves(jax.tree_util.tree_map(
        lambda x: np.asarray(x).reshape((-1,) + x.shape[2:])[pix],
        dataclasses.replace(whole, eye=None)))
    flat_covered = jax.tree_util.tree_leaves(jax.tree_util.tree_map(
        lambda x: np.asarray(x)[:count], dataclasses.replace(gb, eye=None)))
    assert len(flat_whole) == len(flat_covered) > 8
    for a, b in zip(flat_covered, flat_whole):
        if a.dtype.kind in "biu":
            np.testing.assert_array_equal(a, b)
        else:
            scale = max(float(np.abs(b).max()), 1e-30)
            np.testing.assert_allclose(a, b, rtol=0, atol=4e-6 * scale)
    with pytest.raises(ValueError, match="whole image"):
        covered_gbuffer(sc.mesh, sc.camera, albedo,
                        opts=RenderOptions.of(sc, derivatives="gbuffer"))


def test_closed_shape_knows_a_closed_outward_mesh():
    """`jaxnm._host_geometry.closed_shape`: the tori and the uv sphere (seams and poles welded) are
    closed with their front faces outside, and their boxes are the positions' bounds; a
    plane, a torus with a face removed, one with its faces turned inside out and one with a
    single face flipped are not."""
    from jaxnm._host_geometry import closed_shape

    for mesh in (procedural.default_torus(), procedural.torus(1.0, 0.4, 16, 8),
                 procedural.uv_sphere(1.0, 16, 8)):
        box = closed_shape(mesh.positions, mesh.faces)
        pos = np.asarray(mesh.positions, np.float64)
        np.testing.assert_array_equal(box, np.stack([pos.min(0), pos.max(0)]))
    torus = procedural.torus(1.0, 0.4, 16, 8)
    faces = np.asarray(torus.faces)
    flipped_one = faces.copy()
    flipped_one[5] = flipped_one[5, ::-1]
    for f in (faces[1:], faces[:, ::-1], flipped_one):
        assert closed_shape(torus.positions, jnp.asarray(f)) is None
    plane = procedural.plane()
    assert closed_shape(plane.positions, plane.faces) is None
    assert closed_shape(np.asarray(torus.positions), faces) is not None  # NumPy alike


def test_back_faces_are_culled_only_where_none_can_be_seen():
    """A closed mesh wholly in front of the camera (`back_faces_hidden`, which the built-in
    scene uses to set ``cull_back``) renders with its back faces culled what it renders
    without: every output equal. Not hidden where the camera is inside the mesh's box,
    where the near plane cuts the mesh, where the model mirrors it, or for an open mesh."""
    from jaxnm.scene import back_faces_hidden as hidden

    scene = builtin_scene(WHOLE)
    assert scene.cull_back and hidden(scene.mesh, scene.camera, scene.model)
    outputs = ("color", "triangle_id", "front_facing", "perturbed_normal", "depth")
    culled = render(scene, outputs=OUTPUTS)
    plain = render(scene.replace(cull_back=False), outputs=OUTPUTS)
    for name in outputs:
        np.testing.assert_array_equal(np.asarray(culled[name]), np.asarray(plain[name]), name)
    inside = jaxnm.Camera.look_at((0.0, 0.0, 0.2), (1.0, 0.0, 0.0), up=(0, 0, 1))
    assert not hidden(scene.mesh, inside)  # in the torus's hole: inside its box
    eye = np.asarray(scene.camera.eye, np.float64)
    d = float(np.linalg.norm(eye))
    cut = jaxnm.Camera.look_at(eye, (0.0, 0.0, 0.0), up=(0, 0, 1), near=d - 0.5, far=d + 5)
    assert not hidden(scene.mesh, cut)  # the near plane cuts the torus open
    mirror = np.diag([-1.0, 1.0, 1.0, 1.0])
    assert not hidden(scene.mesh, scene.camera, mirror)
    assert hidden(scene.mesh, scene.camera, np.diag([2.0, 2.0, 2.0, 1.0]))
    plane = procedural.plane()
    assert not hidden(plane, scene.camera)


@pytest.mark.parametrize("offset", [0.0, 1e4])
def test_to_clip_matches_float64_far_from_the_origin(offset):
    """`jaxnm.to_clip` (written out term by term, camera-relative) agrees with the float64
    transform to float32 rounding of the clip coordinates, near the origin and 1e4 away
    from it (camera and mesh moved together)."""
    rng = np.random.default_rng(3)
    o = np.array([offset, -0.5 * offset, 0.25 * offset])
    eye, target = o + np.array([0.3, -2.0, 1.2]), o
    cam = jaxnm.Camera.look_at(eye, target, up=(0, 0, 1), near=0.05, far=50.0)
    p = (o + rng.uniform(-1, 1, (500, 3))).astype(np.float32)
    got = np.asarray(jaxnm.to_clip(jnp.asarray(p), cam), np.float64)
    view, proj = (np.asarray(m, np.float64) for m in (cam.view, cam.projection))
    eye64 = np.asarray(cam.eye, np.float32).astype(np.float64)  # the eye jaxnm uses
    ref = (np.asarray(p, np.float64) - eye64) @ view[:3, :3].T @ proj[:, :3].T + proj[:, 3]
    # a few float32 roundings of the largest term of each coordinate
    scale = np.abs(np.asarray(p, np.float64) - eye64).max(1, keepdims=True) * 4
    err = np.abs(got - ref) / scale
    assert err.max() < 8 * np.finfo(np.float32).eps, err.max()
    # the eye as a tuple or a JAX array (the camera built by hand, or traced) changes nothing
    for eye_as in (tuple, jnp.asarray):
        other = jaxnm.Camera(view=cam.view, projection=cam.projection, eye=eye_as(cam.eye))
        assert np.array_equal(np.asarray(jaxnm.to_clip(jnp.asarray(p), other), np.float64), got)


def test_render_keeps_nothing_between_calls(plane_scene):
    """`render` remembers nothing but its compiled programs: NumPy arrays changed in place
    between two calls (an eye, a mesh) render what a fresh scene renders, and a moved point
    light is seen."""
    eye = np.array([0.2, 0.1, 2.5])
    cam = dataclasses.replace(plane_scene.camera, eye=eye)
    m = procedural.plane(2.0, 8)
    host = jaxnm.Mesh(*(np.array(a) for a in (m.positions, m.faces, m.uv, m.normals)))
    lights = Lights(point=PointLight(position=np.array([[0.5, 0.5, 2.0]], np.float32),
                                     color=jnp.ones((1, 3)), intensity=jnp.array([3.0])))
    scene = dataclasses.replace(plane_scene, camera=cam, mesh=host, lights=lights)

    def fresh():
        return np.asarray(render(jax_copy(scene))["color"])

    first = np.asarray(render(scene)["color"])
    assert np.array_equal(first, fresh())
    for change in (lambda: eye.__setitem__(0, 0.6),
                   lambda: host.positions.__setitem__((slice(None), 2), 0.3),
                   lambda: lights.point.position.__setitem__((0, 0), -0.5)):
        change()
        again = np.asarray(render(scene)["color"])
        assert not np.array_equal(again, first) and np.array_equal(again, fresh())
        first = again


def jax_copy(scene):
    """``scene`` with every NumPy array copied (nothing shared with the caller's arrays)."""
    import jax

    return jax.tree_util.tree_map(lambda x: np.array(x) if isinstance(x, np.ndarray) else x,
                                  scene)


#: The lists `_compiles` is filling (the innermost last), and its listener once registered
#: (one for the module: JAX 0.8.0 cannot unregister one).
_COUNTING: list[list[str]] = []
_LISTENERS: list = []


def _listen(name, seconds, **kwargs):
    if _COUNTING and name == "/jax/core/compile/backend_compile_duration":
        _COUNTING[-1].append(kwargs.get("fun_name", "?"))


@contextlib.contextmanager
def _compiles():
    """The names of the programs XLA compiles inside the block (a list filled as it runs)."""
    if _listen not in _LISTENERS:
        jax.monitoring.register_event_duration_secs_listener(_listen)
        _LISTENERS.append(_listen)
    names: list[str] = []
    _COUNTING.append(names)
    try:
        yield names
    finally:
        _COUNTING.remove(names)


def test_render_and_a_fits_prepare_share_one_visibility_program():
    """`render` (a fit's targets) and `covered_gbuffer` (its `prepare`) run one compiled
    visibility program per image size and culling: after a render, `covered_gbuffer`
    compiles its per-pixel program only (a second rasterizer was a second of `jaxnm fit`)."""

    from jaxnm.gbuffer import RenderOptions
    from jaxnm.render import covered_gbuffer

    if jax.default_backend() != "cpu":
        pytest.skip("on a GPU `render` runs the whole image in one program: no visibility "
                    "program of its own to share")
    scene = builtin_scene(PACKED)  # packed: visibility a program of its own
    jax.block_until_ready(render(scene, outputs=OUTPUTS)["color"])
    with _compiles() as compiles:
        gb, index, count = covered_gbuffer(scene.mesh, scene.camera, jnp.asarray(scene.albedo),
                                           opts=RenderOptions.of(scene))
        assert count > 0 and "jit(_covered)" in compiles
        assert not any("visible" in c for c in compiles), compiles


def test_outputs_asked_in_another_order_run_the_same_program():
    """The same outputs in another order (or repeated) are the same options and the same
    compiled program; the result lists them in the order asked."""

    from jaxnm.gbuffer import RenderOptions

    scene = builtin_scene(WHOLE)
    first = render(scene, outputs=OUTPUTS)
    with _compiles() as compiles:
        again = render(scene, outputs=OUTPUTS[::-1] + OUTPUTS[:1])
    assert not any("frame" in c for c in compiles), compiles
    assert list(first) == list(OUTPUTS) and list(again) == list(OUTPUTS[::-1])
    for name in first:
        np.testing.assert_array_equal(np.asarray(again[name]), np.asarray(first[name]))
    assert RenderOptions.of(scene, outputs=OUTPUTS) == RenderOptions.of(scene,
                                                                          outputs=OUTPUTS[::-1])


def test_weakly_and_strongly_typed_scalars_run_the_same_program():
    """A scene whose material and lights hold weakly typed scalars (Python floats,
    ``jnp.asarray(48.0)``, as the built-in scenes do) and the same scene after an optimiser
    step, whose updates are strongly typed arrays, run one compiled frame and give the same
    image."""

    scene = builtin_scene(WHOLE)
    scene = scene.replace(material=dataclasses.replace(scene.material, shininess=48.0))

    def weak(tree):
        return [jax.typeof(x).weak_type for x in jax.tree_util.tree_leaves(tree)]

    assert any(weak((scene.material, scene.lights)))  # else this test would test nothing
    stepped = scene.replace(**{k: jax.tree_util.tree_map(
        lambda x: jnp.zeros(jnp.shape(x), jnp.float32) + x, getattr(scene, k))
        for k in ("material", "lights")})
    assert not any(weak((stepped.material, stepped.lights)))
    first = render(scene, outputs=OUTPUTS)
    with _compiles() as compiles:
        again = render(stepped, outputs=OUTPUTS)
    assert not any("frame" in c for c in compiles), compiles
    for name in first:
        np.testing.assert_array_equal(np.asarray(again[name]), np.asarray(first[name]))
