"""scripts/studies/speed_vs_error.py measures what it says: its errors against the float64 truth
order the configurations the way the frame study and the precision tests establish, its
image error is zero where the normal is exact, and its Pareto front is the set of
non-dominated configurations."""

import jax
import pytest

from scripts.studies import speed_vs_error as V


@pytest.fixture(scope="module")
def rows():
    surf = V.Torus(12)
    cfgs = [{**V.BASE, "size": 48, "filter": "bilinear", **c} for c in (
        {}, {"frame": "exact"}, {"frame": "vertex"}, {"frame": "nonperspective"},
        {"precision": "bfloat16"}, {"derivatives": "gbuffer"}, {"precision": "float64"})]
    out = {}
    for i, c in enumerate(cfgs):  # forward + backward timed for the base one only (~3 s each)
        r = V.run_one(c, surf, reps=2, grad=i == 0)
        out[r["frame"], r["derivatives"], r["precision"]] = r
    jax.clear_caches()
    return out


def test_errors_order_as_the_frame_study_says(rows):
    cot, exact = rows["cotangent", "fine", "float32"], rows["exact", "fine", "float32"]
    assert all(r["finite"] and r["pixels"] > 300 for r in rows.values())
    # cotangent and exact build the same per-triangle frame: the same faceting error
    assert abs(cot["normal_mean"] - exact["normal_mean"]) < 1e-3 * max(1, cot["normal_mean"])
    assert cot["normal_mean"] < 3.0  # a 12-segment torus: first-order faceting error
    assert rows["vertex", "fine", "float32"]["normal_mean"] < cot["normal_mean"]
    assert rows["nonperspective", "fine", "float32"]["normal_mean"] > 2 * cot["normal_mean"]
    assert rows["cotangent", "fine", "bfloat16"]["normal_mean"] > cot["normal_mean"]
    # float64 arithmetic on float32 interpolants: the same frame to float32 rounding
    assert abs(rows["cotangent", "fine", "float64"]["normal_mean"] - cot["normal_mean"]) < 1e-3
    assert rows["cotangent", "gbuffer", "float32"]["normal_p95"] > cot["normal_p95"]
    # the image error follows the normal error
    assert rows["nonperspective", "fine", "float32"]["image_rmse"] > cot["image_rmse"]
    for r in rows.values():
        assert r["forward_ms"] > 0 and r["compile_s"] > 0
    assert cot["grad_ms"] > 0 and cot["grad_compile_s"] > 0
    assert exact["grad_ms"] is None and exact["grad_compile_s"] is None
    table = V._table(list(rows.values()), set())
    assert f"| {cot['forward_ms']:.1f} | {cot['grad_ms']:.1f} |" in table
    assert (f"| {V._label(exact)} | {exact['forward_ms']:.1f} | - | {exact['compile_s']:.1f} / - |"
            in table)


def test_pareto_front_is_the_non_dominated_set():
    rows = [dict(size=256, forward_ms=t, normal_mean=e) for t, e in
            ((1, 5), (2, 1), (3, 1), (4, 0.5), (5, 2), (1.5, 5))]
    assert V._pareto(rows) == {0, 1, 3}
