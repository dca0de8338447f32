"""scripts/benchmarks/bench_distributed.py: its cameras, its summary and its table (the timings
themselves live in the script, never in tests)."""

import numpy as np

from scripts.benchmarks import bench_distributed as bench


def test_ring_eyes_are_distinct_cameras_above_the_torus():
    eyes = np.array(bench.ring_eyes(16))
    np.testing.assert_allclose(np.linalg.norm(eyes, axis=1), 3.0, rtol=1e-12)
    assert np.all(eyes[:, 2] > 0.7)
    gaps = np.linalg.norm(eyes[:, None] - eyes[None], axis=-1) + np.eye(16) * 10
    assert gaps.min() > 0.2


def test_summary_takes_the_slowest_process_and_the_communication_fraction():
    per = [{"process": 0, "views": 4, "step_s": 1.0, "alone_step_s": 0.6, "peak_rss_mb": 700.0,
            "prepared_mb": 20.0},
           {"process": 1, "views": 4, "step_s": 1.25, "alone_step_s": 0.75,
            "peak_rss_mb": 650.0, "prepared_mb": 19.0}]
    row = bench.summarize(2, per)
    assert row["step_s"] == 1.25 and row["peak_rss_mb"] == 700.0
    assert abs(row["communication_fraction"] - (1 - 0.75 / 1.25)) < 1e-12
    one = bench.summarize(1, [{"process": 0, "views": 8, "step_s": 0.9, "peak_rss_mb": 900.0,
                                "prepared_mb": 39.0}])
    md = bench.markdown({"runs": [one, row]})
    assert "| 1 | 8 | 0.90 | — | 900 | 39.0 |" in md
    assert "| 2 | 4/4 | 1.25 | 40% (alone 0.75 s) | 700/650 | 20.0/19.0 |" in md
