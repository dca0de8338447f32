"""The side-by-side benchmark's problem (scripts/benchmarks/bench_problem.py) is the one its
docstring defines."""

import numpy as np
import pytest

from scripts.benchmarks import bench_problem as B


def test_problem_geometry_lights_and_map():
    p = B.make_problem(render_size=64, map_size=32, major=128, minor=80)
    assert p.faces.shape == (20480, 3) and p.positions.shape == (129 * 81, 3)
    r = np.hypot(p.positions[:, 0], p.positions[:, 1])
    np.testing.assert_allclose(np.hypot(r - 1.0, p.positions[:, 2]), 0.4, atol=1e-6)
    f = -np.asarray(p.eye) / np.linalg.norm(p.eye)  # the camera looks at the origin
    np.testing.assert_allclose(np.linalg.norm(p.light_dirs, axis=1), 1.0, atol=1e-12)
    np.testing.assert_allclose(np.degrees(np.arcsin(p.light_dirs @ -f)), 45.0, atol=1e-9)
    np.testing.assert_allclose(np.linalg.norm(p.held_out_dir), 1.0, atol=1e-12)
    assert p.gt_texels.shape == (32, 32, 3) and p.gt_texels.min() >= 0 and p.gt_texels.max() <= 1
    np.testing.assert_allclose(np.linalg.norm(p.gt_normals, axis=-1), 1.0, atol=1e-5)
    decoded = p.gt_texels.astype(np.float64) * 2 - 1  # the truth decodes the filtered texels
    np.testing.assert_allclose(p.gt_normals, decoded / np.linalg.norm(decoded, axis=-1,
                                                                     keepdims=True), atol=1e-6)
    assert (p.gt_normals[..., 2] > 0).all()  # every texel faces out of the surface


def test_texel_masks_and_metrics():
    p = B.make_problem(render_size=64, map_size=16, major=32, minor=20)
    seen, well = B.texel_masks(p)
    assert well.sum() > 0 and (well <= seen).all() and seen.mean() < 1.0
    assert B.angle_deg(p.gt_normals, p.gt_normals).max() < 1e-6
    assert B.psnr(np.zeros((4, 4)), np.full((4, 4), 0.1)) == pytest.approx(20.0)
