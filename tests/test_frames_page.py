"""The frames page (docs/studies/frames.md) against the data file the study wrote beside it
(docs/studies/data/frames_summary.json): each statement the page makes about a sweep is
checked against the sweep's numbers, and the page quotes them. Nothing is re-run here.
"""

import json
import re
from pathlib import Path

import numpy as np
import pytest

from scripts.studies import study_frames as S

ROOT = Path(__file__).resolve().parents[1]
PAGE = (ROOT / "docs" / "studies" / "frames.md").read_text(encoding="utf-8")
DATA = json.loads((ROOT / "docs" / "studies" / "data" / "frames_summary.json").read_text())
ROWS = S.summary_rows(DATA)


def rows(**kw):
    return [r for r in ROWS if all(r.get(k) == v for k, v in kw.items())]


def one(**kw):
    found = rows(**kw)
    assert len(found) == 1, (kw, len(found))
    return found[0]


def section(number: int) -> str:
    """The text of the page's section ``number`` (from its heading to the next one)."""
    m = re.search(rf"^## {number}\. .*?(?=^## )", PAGE, re.M | re.S)
    assert m, f"no section {number}"
    return m.group(0)


def flat(text: str) -> str:
    return " ".join(text.split())


def test_every_sweep_point_states_its_fixed_values():
    """The fov sweep runs at a 45 degree view, the view-angle sweep at a 60 degree field of
    view, the distance sweep at 60 degrees of both; the page says so."""
    assert {(r["view"], r["uv"]) for r in rows(sweep="fov")} == {(45, "sheared 30 deg")}
    assert {(r["fov"], r["uv"]) for r in rows(sweep="view angle")} == {(60, "sheared 30 deg")}
    assert {(r["fov"], r["view"]) for r in rows(sweep="distance")} == {(60, 60)}
    text = flat(section(1))
    assert "the fov sweep at a 45° view angle" in text
    assert "the view-angle sweep at a 60° field of view" in text
    assert "the distance sweep at a 60° field of view and a 60° view angle" in text
    assert "45° view angle unless swept" not in text


def test_gram_schmidt_and_separate_are_mikktspace_on_a_stretched_uv_and_neither_on_a_shear():
    for m in ("gram_schmidt", "separate"):
        st = one(sweep="uv", uv="stretched 1:4", method=m)
        # against the orthonormal (MikkTSpace) truth: float32 rounding, for every map value
        assert st["orthonormal_mean"] < 1e-4 and st["other_worst_max"] < 1e-4, st
        assert st["worst_max"] > 30.0  # and far from their own (gradient) convention
        for uv in ("sheared 30 deg", "sheared 60 deg"):
            sh = one(sweep="uv", uv=uv, method=m)
            assert min(sh["gradient_mean"], sh["orthonormal_mean"]) > 1.0, sh
    text = flat(section(3))
    assert "on a stretched uv both are MikkTSpace's frame" in text
    assert "on a sheared or stretched uv each is off against both" not in text


def test_the_60_degree_shear_row_is_on_the_page():
    text = section(3)
    for m in ("gram_schmidt", "separate", "cotangent", "vertex"):
        r = one(sweep="uv", uv="sheared 60 deg", method=m)
        line = next(x for x in text.splitlines() if x.startswith(f"| {m} |") and "60°" in x)
        for k in ("gradient_mean", "orthonormal_mean"):
            v = r[k]
            assert (f"{v:.2f}" if v > 0.01 else f"{v:.0e}") in line, (m, k, v, line)


def test_schuler_t_and_b_turn_with_the_interpolated_normal():
    """Schüler's frame of one triangle at two interpolated normals (the mesh's own frame,
    `face_truths`): on the plane z = 0 with uv = xy, N tilted by a about y turns T by exactly
    a (T = (1, 0, -tan a)), so T and B are not constant on a triangle."""
    tri = type("Tri", (), {})()
    tri.pos = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]])
    tri.uv = tri.pos[:, :2].copy()
    tri.faces = np.array([[0, 1, 2]])
    a = np.radians(20.0)
    n = np.array([[0.0, 0.0, 1.0], [np.sin(a), 0.0, np.cos(a)]])
    _, (t, b), _ = S.face_truths(tri, np.zeros(2, np.int64), n)
    np.testing.assert_allclose(S.angle(t[0], t[1]), 20.0, atol=1e-9)
    np.testing.assert_allclose(np.sum(t * n, -1), 0.0, atol=1e-12)
    np.testing.assert_allclose(np.sum(b * n, -1), 0.0, atol=1e-12)
    text = flat(section(7))
    assert "constant on each triangle" not in text
    assert "turn with the interpolated N" in text


def test_each_figure_is_drawn_by_the_study_and_captioned_with_its_command():
    figures = re.findall(r"!\[[^\]]*\]\(\.\./img/([\w.]+)\)", PAGE)
    drawn = set(S.FIGURES) | {"frames_real_error_maps.png", "frames_torus_error_maps.png"}
    assert figures and set(figures) <= drawn, set(figures) - drawn
    for name in figures:
        after = PAGE.split(f"(../img/{name})", 1)[1].lstrip("\n").split("\n\n", 1)[0]
        assert after.startswith("*") and "python -m scripts.studies.study_frames" in after, name
        if name in S.FIGURES:
            assert S.FIGURES_COMMAND in flat(after), name
    assert (ROOT / "docs" / "img").is_dir()


def test_each_frame_method_has_its_own_colour_and_marker():
    methods = [f for f in S.FRAMES if f != "none"]
    assert sorted(S.METHOD_STYLE) == sorted(methods)
    colours = [c.lower() for c, _ in S.METHOD_STYLE.values()]
    markers = [m for _, m in S.METHOD_STYLE.values()]
    assert len(set(colours)) == len(colours) and len(set(markers)) == len(markers)


def test_update_summary_replaces_only_the_rerun_sweeps():
    old = {"metadata": {"command": "a"}, "columns": ["sweep", "x"],
           "rows": [["fov", 1], ["real", 2]]}
    new = {"metadata": {"command": "b"}, "columns": ["sweep", "y"], "rows": [["real", 3]]}
    out = S.update_summary(old, new, ("real",))
    assert [r["command"] for r in out["metadata"]["runs"]] == ["a", "b"]
    assert [r["sweeps"] for r in out["metadata"]["runs"]] == [["fov"], ["real"]]
    assert S.summary_rows(out) == [{"sweep": "fov", "x": 1}, {"sweep": "real", "y": 3}]


def test_the_data_file_names_the_run_of_every_sweep():
    runs = DATA["metadata"]["runs"]
    covered = [s for r in runs for s in r["sweeps"]]
    assert sorted(covered) == sorted({r["sweep"] for r in ROWS})
    for r in runs:
        assert r["jax"] and r["machine"] and r["command"].startswith(
            "python -m scripts.studies.study_frames")
        assert r["command"].split(" --out")[0] + " --out DIR" in flat(PAGE), r["command"]


@pytest.mark.parametrize("sweep", ["tessellation", "precision"])
def test_precision_and_tessellation_cover_every_frame(sweep):
    got = {r["method"] for r in rows(sweep=sweep)}
    assert got == set(S.METHODS)


def test_mikktspace_is_blenders_decode_and_its_tangents_are_blenders():
    """On Suzanne the MikkTSpace frame is Blender's decode to float32 rounding, and jaxnm's
    corner tangents are Blender's (compared directly); the page quotes both."""
    tangents = one(sweep="real", case="tangents")
    assert tangents["sign_mismatches"] == 0 and tangents["T_max"] < 0.01
    for r in rows(sweep="real", method="vertex", mode="fine"):
        assert r["error_max"] < 0.01, r
    text = flat(section(5))
    assert "differ by 1.4e-4° on the mean and 1.7e-3° at most" in text
    assert f"{tangents['T_mean']:.1e}".replace("e-0", "e-") in text
    assert "jaxnm's MikkTSpace tangents differing" not in PAGE


def test_without_tangents_cross_and_surface_gradient_tie_on_the_mean_not_at_the_max():
    big = max(r["size"] for r in rows(sweep="real") if "size" in r)
    cross = one(sweep="real", method="cross", size=big)
    sg = one(sweep="real", method="surface_gradient", size=big)
    assert abs(cross["error_mean"] - sg["error_mean"]) < 0.02
    assert sg["error_max"] > 2 * cross["error_max"]
    for r in rows(sweep="real", size=big):
        if r["method"] not in ("vertex", "vertex_area", "cross", "surface_gradient"):
            assert r["error_mean"] > cross["error_mean"] + 0.5, r
    assert "the best frame without tangents" not in PAGE
    assert (f"({sg['error_max']:.0f}° against {cross['error_max']:.1f}°)"
            in flat(section(5)))


def _decoding(surface):
    return {r["case"]: r for r in rows(sweep="decoding", surface=surface)}


@pytest.mark.parametrize("surface", ["Suzanne", "torus, mirrored u"])
def test_mikktspace_decoding_forms_b_per_fragment_and_normalises_nothing(surface):
    """The reference decoding (B per fragment from the unnormalised interpolated N and T) is
    what jaxnm's vertex frame renders, and every other choice differs from it."""
    dec = _decoding(surface)
    assert set(S.DECODINGS) < set(dec)
    assert dec[S.DECODINGS[0]]["error_max"] == 0.0
    assert dec["jaxnm vertex (float32 render)"]["error_max"] < 1e-3
    for name in S.DECODINGS[1:]:
        assert dec[name]["error_max"] > 0.01 and dec[name]["specular_max"] > 0.5, name


def test_the_decoding_answer_is_on_the_page():
    text = flat(section(9))
    suz = _decoding("Suzanne")
    per_vertex = suz["B per vertex, nothing renormalised"]
    t_norm = suz["B per fragment, T renormalised"]
    assert f"{per_vertex['error_mean']:.2f}° mean, {per_vertex['error_max']:.1f}° max" in text
    assert f"{t_norm['error_mean']:.2f}° mean, {t_norm['error_max']:.1f}° max" in text
    assert "B = sign · cross(N, T)" in text and "per fragment" in text


def _tessellation(surface, method, normals="smooth"):
    rs = sorted(rows(sweep="tessellation", surface=surface, method=method, normals=normals),
                key=lambda r: r["segments"])
    assert [r["segments"] for r in rs] == [8, 16, 32, 64], (surface, method)
    return rs


def test_the_tessellation_orders():
    """Per-triangle frames (Schüler's, cross, surface_gradient) are the mesh's own frame and
    halve their error per doubling on doubly curved surfaces; per-vertex tangents quarter
    it; on the cylinder the orthonormal per-triangle frames and area-weighted tangents are
    exact; the variants listed as gradient frames stay off on these stretched uvs."""
    for surface in ("torus", "sphere"):
        for m in ("cotangent", "exact", "cross", "surface_gradient"):
            rs = _tessellation(surface, m)
            assert 1.8 < rs[-2]["error_mean"] / rs[-1]["error_mean"] < 2.3, (surface, m)
            assert max(r["face_mean"] for r in rs) < 1e-4, (surface, m)
        for m in ("vertex", "vertex_area"):
            rs = _tessellation(surface, m)
            assert 3.5 < rs[-2]["error_mean"] / rs[-1]["error_mean"] < 4.5, (surface, m)
        for m in ("gram_schmidt", "separate", "nonperspective", "axis"):
            rs = _tessellation(surface, m)
            assert rs[-1]["error_mean"] > 5.0 and rs[-2]["error_mean"] / rs[-1]["error_mean"] < 1.1
    for m in ("cross", "surface_gradient", "vertex_area"):
        assert max(r["error_mean"] for r in _tessellation("cylinder", m)) < 1e-4, m
    rs = _tessellation("cylinder", "cotangent")
    assert 3.5 < rs[-2]["error_mean"] / rs[-1]["error_mean"] < 4.5
    for m in S.METHODS:  # flat normals: the faceting, halving per doubling
        rs = _tessellation("torus", m, "flat")
        assert rs[0]["error_mean"] > 5.0
    text = section(7)
    for m in ("cotangent", "vertex"):
        rs = _tessellation("torus", m)
        assert f"{rs[-1]['error_mean']:.3g}" in text


def _precision(method, precision, mode="fine", key="error_mean"):
    rs = [r for r in rows(sweep="precision", surface="plane", method=method, mode=mode,
                          precision=precision) if "case" not in r]
    assert sorted(r["distance"] for r in rs) == [0.003, 0.03, 0.3, 3], (method, precision)
    return {r["distance"]: r[key] for r in rs}


def test_half_precision_breaks_the_screen_space_frames_close_up():
    for m in ("cotangent", "cotangent_unnormalized", "exact", "exact_face", "vertex",
              "vertex_area", "cross", "surface_gradient"):
        assert max(_precision(m, "float32").values()) < 1e-3, m
    # the worst over the hemisphere (independent of the map): about tenfold per tenfold
    # approach with fine differences, flat with rounded analytic derivatives
    worst = _precision("cotangent", "float16", key="worst_mean")
    assert worst[0.3] > 5 * worst[3] and worst[0.03] > 5 * worst[0.3] and worst[0.003] > 60
    assert max(_precision("cotangent", "float16", "analytic", "worst_mean").values()) < 0.1
    for m in ("exact", "exact_face", "vertex", "vertex_area"):
        assert max(_precision(m, "float16").values()) < 0.05, m
        assert max(_precision(m, "float16", key="worst_mean").values()) < 0.1, m
    for m in ("cross", "surface_gradient"):
        assert _precision(m, "float16")[3] > 10.0, m
        assert min(_precision(m, "float16", key="worst_mean").values()) > 80.0, m
    text = flat(section(8))
    assert "(0.384° → 2.5° → 25.6° → 95°)" in text
    assert f"{worst[0.03]:.3g}°" in text


def _far(case, offset, precision):
    rs = rows(sweep="precision", case=case, offset=offset, precision=precision)
    return {r["distance"]: r["error_mean"] for r in rs}


def test_world_positions_far_from_the_origin_lose_precision_camera_relative_ones_do_not():
    for precision in ("float32", "float16"):
        near = _far("camera-relative position", 0.0, precision)
        assert len(near) == 4
        far = _far("camera-relative position", 100.0, precision)
        assert far == pytest.approx(near, rel=0.05)
        world = _far("world position", 100.0, precision)
        assert world[3] > 10 * near[3] or world[0.003] > 10 * near[0.003], precision
    assert _far("world position", 100.0, "float32")[0.003] > 0.1
    assert "position far from the origin would be" not in PAGE
