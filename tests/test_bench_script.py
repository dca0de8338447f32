"""scripts/benchmarks/bench.py: the views benchmark's cameras and its report (the timings
themselves live in the script, never in tests)."""

import numpy as np

from scripts.benchmarks import bench


def test_ring_eyes_are_distinct_cameras_above_the_torus():
    eyes = np.array(bench._ring_eyes(64, radius=3.0))
    assert eyes.shape == (64, 3)
    np.testing.assert_allclose(np.linalg.norm(eyes, axis=1), 3.0, rtol=1e-12)
    assert np.all(eyes[:, 2] > 0.7)  # above the torus's plane: every view sees its top
    gaps = np.linalg.norm(eyes[:, None] - eyes[None], axis=-1) + np.eye(64) * 10
    assert gaps.min() > 0.2  # no two views coincide
    az = np.arctan2(eyes[:, 1], eyes[:, 0])
    assert np.ptp(az) > 1.8 * np.pi  # all around


def test_markdown_reports_the_views_rows():
    res = {"machine": "m", "jax": "j", "mitsuba": "none", "date": "d",
           "views": [{"views": 4, "size": 128, "chunk": "2097152", "pixels": 1000,
                      "prepared_mb": 1.5, "s_per_step": 0.1, "fit_s": 2.0, "peak_rss_mb": 500},
                     {"views": 64, "size": 256, "chunk": "none", "pixels": 16000,
                      "prepared_mb": 20.0, "s_per_step": 1.5, "fit_s": 9.0,
                      "peak_rss_mb": 900, "prepare_working_mb": 310, "fit_working_mb": 250,
                      "steps_working_mb": 120}]}
    md = bench.markdown(res)
    assert "| 4 | 128 | 2097152 | 1000 | 1.5 | 0.1 | 2.0 | 500 |" in md
    assert "| 64 | 256 | none | 16000 | 20.0 | 1.5 | 9.0 | 900 | 310 | 250 / 120 |" in md


def test_child_peak_memory_is_the_childs_not_the_benchmarks():
    """Spawned straight from a large process, a child's ru_maxrss starts at the parent's
    high-water mark (Linux keeps it across vfork + exec); `_timed_child` must report the
    child's own peak."""
    import os
    import sys

    ballast = np.ones(200_000_000 // 8)  # the benchmark process, 200 MB larger
    ballast[::4096] = 2.0  # touched: resident
    child = bench._timed_child([sys.executable, "-c", "print('ok')"], dict(os.environ))
    assert child["summary"] == "ok"
    assert child["peak_rss_mb"] < 100, child
    del ballast


def test_markdown_reports_the_forward_rows():
    res = {"machine": "m", "jax": "j", "mitsuba": "mi", "date": "d",
           "forward": [{"mesh": "20k torus", "forward_ratio": 2.0,
                        "forward_backward_ratio": 2.5,
                        "jaxnm": {"triangles": 20480, "size": "512x512", "forward_ms": 14.0,
                                  "forward_backward_ms": 55.0, "first_forward_s": 2.2,
                                  "first_backward_s": 2.1, "forward_moved_ms": 14.5},
                        "forward_moved_ratio": 0.85,
                        "mitsuba": {"forward_ms": 7.0, "forward_backward_ms": 22.0,
                                    "forward_moved_ms": 17.0}}]}
    md = bench.markdown(res)
    assert ("| 20k torus (20480 tris) | 512x512 | 14.0 | 7.0 | 2.0 | 55.0 | 22.0 | "
            "2.5 | 2.2, 2.1 | 14.5 / 17.0 (0.85) |") in md


def test_markdown_forward_row_without_mitsuba_leaves_its_columns_empty():
    res = {"machine": "m", "jax": "j", "mitsuba": "none", "date": "d",
           "forward": [{"mesh": "4k sphere",
                        "jaxnm": {"triangles": 3968, "size": "256x256", "forward_ms": 3.0,
                                  "forward_moved_ms": 3.1, "forward_backward_ms": 5.0,
                                  "first_forward_s": 2.0, "first_backward_s": 2.5}}]}
    md = bench.markdown(res)
    assert ("| 4k sphere (3968 tris) | 256x256 | 3.0 | - | - | 5.0 | - | - | "
            "2.0, 2.5 | 3.1 / - (-) |") in md


def test_forward_rows_take_the_median_of_the_runs():
    """With several runs, each figure is the median of the runs' medians, each ratio the
    median of the runs' side-by-side ratios, and the runs' forward ratios are listed."""
    from types import SimpleNamespace

    calls = [f"jaxnm {k}" for k in bench.JAXNM_CALLS] + [f"mitsuba {k}"
                                                         for k in bench.MITSUBA_CALLS]
    runs = []
    for jax_ms, mi_ms in ((4.0, 5.0), (9.0, 4.0), (5.0, 6.0)):  # a slow stretch each
        ms = {k: (jax_ms if k.startswith("jaxnm") else mi_ms) for k in calls}
        runs.append((ms, {k: 1 for k in calls}))
    q = SimpleNamespace(faces=np.zeros((7, 3)), width=64, height=64)
    mi = {"first_s": {"forward": 0.1, "forward_backward": 0.2},
          "kernel_cache_files_at_start": 0}
    first = {"jaxnm forward_backward": 3.0}
    (row,) = bench._forward_rows([("mesh", q, 2.0, mi, first)], [runs], echo=False)
    assert row["jaxnm"]["forward_ms"] == 5.0 and row["mitsuba"]["forward_ms"] == 5.0
    assert row["forward_ratio_runs"] == [0.8, 2.25, 0.83]
    assert row["forward_ratio"] == 0.83  # the median of the runs' ratios, not 5.0 / 5.0
    assert row["jaxnm"]["forward_ms_runs"] == [4.0, 9.0, 5.0]
    (one,) = bench._forward_rows([("mesh", q, 2.0, mi, first)], [runs[1:2]], echo=False)
    assert one["forward_ratio"] == 2.25 and "forward_ratio_runs" not in one


def test_forward_cells_include_a_larger_map_than_the_problems():
    """The forward table's cells: every mesh at every size with the problem's 256^2 map,
    plus the 20k torus at 512^2 with a 512^2 map, the same procedural map made larger."""
    from scripts.benchmarks import bench_problem as B

    p = B.make_problem(render_size=8, map_size=8, major=3, minor=3)
    cells = list(bench._cells(p, (512,), quick=False))
    assert [n for n, _ in cells] == ["4k sphere", "20k torus", "200k torus",
                                     "20k torus, 512x512 map"]
    name, q = cells[-1]
    assert q.gt_texels.shape == (512, 512, 3) and q.faces.shape == (20480, 3)
    assert (q.width, q.height) == (512, 512)
    np.testing.assert_allclose(np.linalg.norm(q.gt_normals, axis=-1), 1.0, atol=1e-5)
    # the same map as the problem's at 256^2 (its 2x2 box filter is far closer to it than to
    # the same map moved by half a bump cell)
    p256 = B.make_problem(render_size=8, map_size=256, major=3, minor=3).gt_texels
    box = q.gt_texels.reshape(256, 2, 256, 2, 3).mean(axis=(1, 3))
    near = np.abs(box - p256).mean()
    assert near < 0.02 and near < 0.5 * np.abs(box - np.roll(p256, 16, axis=1)).mean()
    assert [n for n, _ in bench._cells(p, (512,), quick=True)] == ["4k sphere", "20k torus"]
