"""RANSAC + Umeyama Sim(3) estimation from 3-D-3-D correspondences (fgslam.loop.sim3_estimation)."""

import numpy as np
import pytest
import torch

from fgslam.errors import ConfigError
from fgslam.lie import Sim3
from fgslam.loop.sim3_estimation import Sim3RansacConfig, estimate_sim3_ransac, sim3_errors


def _random_sim3(rng) -> Sim3:
    xi = torch.from_numpy(np.concatenate([rng.normal(0, 0.6, 3), rng.normal(0, 2.0, 3), [rng.normal(0, 0.5)]]))
    return Sim3.exp(xi)


def _scene(rng, n, T_ab: Sim3, outlier_ratio, noise_rel=0.003):
    """Points in front of camera b (depth 2..20), their images in frame a; a fraction replaced by junk."""
    X_b = np.column_stack([rng.uniform(-5, 5, n), rng.uniform(-2, 2, n), rng.uniform(2, 20, n)])
    X_a = T_ab.act(torch.from_numpy(X_b)).numpy()
    X_a = X_a + noise_rel * np.linalg.norm(X_a, axis=1, keepdims=True) * rng.normal(size=(n, 3))
    n_out = int(round(outlier_ratio * n))
    out = rng.choice(n, n_out, replace=False)
    # Outliers: points of frame a shuffled among themselves plus random offsets (wrong matches).
    X_a[out] = X_a[rng.permutation(out)] + rng.normal(0, 3.0, (n_out, 3)) * float(T_ab.s)
    is_inlier = np.ones(n, dtype=bool)
    is_inlier[out] = False
    return X_a, X_b, is_inlier


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_recovers_known_sim3_with_40_percent_outliers(seed):
    rng = np.random.default_rng(seed)
    T_ab = _random_sim3(rng)
    X_a, X_b, is_inlier = _scene(rng, 200, T_ab, 0.4)
    est = estimate_sim3_ransac(X_a, X_b, Sim3RansacConfig(seed=seed))
    assert est.success, est.reason
    xi_err = (T_ab.inverse() @ est.T_ab).log().numpy()
    assert np.linalg.norm(xi_err[:3]) < np.radians(0.5)
    assert abs(xi_err[6]) < 0.01  # log scale
    assert np.linalg.norm(est.T_ab.t.numpy() - T_ab.t.numpy()) < 0.02 * max(1.0, np.linalg.norm(T_ab.t.numpy()))
    # Inlier mask: recovers the true inliers (a few junk points may land near the model by chance).
    assert (est.inlier_mask & is_inlier).sum() >= 0.95 * is_inlier.sum()
    assert (est.inlier_mask & ~is_inlier).sum() <= 0.05 * (~is_inlier).sum()
    assert est.n_inliers == est.inlier_mask.sum()
    assert est.inlier_ratio == pytest.approx(est.n_inliers / 200)
    assert 0 < est.rms_error < Sim3RansacConfig().inlier_threshold


def test_absolute_metric_and_torch_input():
    rng = np.random.default_rng(5)
    T_ab = _random_sim3(rng)
    X_a, X_b, is_inlier = _scene(rng, 150, T_ab, 0.3, noise_rel=0.0)
    cfg = Sim3RansacConfig(error_metric="absolute", inlier_threshold=1e-6 * max(1.0, float(T_ab.s)) * 100)
    est = estimate_sim3_ransac(torch.from_numpy(X_a), torch.from_numpy(X_b), cfg)
    assert est.success, est.reason
    assert np.array_equal(est.inlier_mask, is_inlier)
    err = sim3_errors(est.T_ab, X_a, X_b, "absolute")
    assert err[is_inlier].max() < 1e-8


def test_collinear_input_returns_no_solution():
    rng = np.random.default_rng(3)
    T_ab = _random_sim3(rng)
    lam = rng.uniform(-5, 5, 100)
    X_b = np.array([1.0, 2.0, 10.0]) + lam[:, None] * np.array([0.3, -0.2, 1.0])
    X_a = T_ab.act(torch.from_numpy(X_b)).numpy()
    est = estimate_sim3_ransac(X_a, X_b)
    assert not est.success
    assert est.T_ab is None and not est.inlier_mask.any()
    assert "degenerate" in est.reason
    assert est.n_degenerate == est.iterations > 0


def test_coincident_points_and_too_few_points():
    X = np.tile([[1.0, 2.0, 5.0]], (50, 1))
    est = estimate_sim3_ransac(X, X)
    assert not est.success and "degenerate" in est.reason
    est = estimate_sim3_ransac(np.ones((2, 3)), np.ones((2, 3)))
    assert not est.success and "min_inliers" in est.reason


def test_too_few_inliers_is_no_solution_and_nan_rows_ignored():
    rng = np.random.default_rng(7)
    T_ab = _random_sim3(rng)
    X_a, X_b, is_inlier = _scene(rng, 100, T_ab, 0.9)  # 10 inliers < default min_inliers 20
    X_a[0] = np.nan
    est = estimate_sim3_ransac(X_a, X_b)
    assert not est.success and "min_inliers" in est.reason
    est = estimate_sim3_ransac(X_a, X_b, Sim3RansacConfig(min_inliers=8, max_iterations=3000))
    assert est.success, est.reason
    assert not est.inlier_mask[0]
    assert (est.inlier_mask & is_inlier).sum() >= 8


def test_bad_shapes_and_config():
    with pytest.raises(ValueError):
        estimate_sim3_ransac(np.zeros((10, 2)), np.zeros((10, 2)))
    with pytest.raises(ValueError):
        estimate_sim3_ransac(np.zeros((10, 3)), np.zeros((9, 3)))
    with pytest.raises(ConfigError):
        estimate_sim3_ransac(np.zeros((10, 3)), np.zeros((10, 3)), Sim3RansacConfig(min_inliers=2))


def test_degenerate_samples_skipped_when_most_points_are_collinear():
    rng = np.random.default_rng(11)
    T_ab = _random_sim3(rng)
    lam = rng.uniform(-5, 5, 95)
    X_line = np.array([1.0, 0.5, 10.0]) + lam[:, None] * np.array([0.3, -0.2, 1.0])
    X_spread = np.column_stack([rng.uniform(-5, 5, 5), rng.uniform(-2, 2, 5), rng.uniform(2, 20, 5)])
    X_b = np.concatenate([X_line, X_spread])
    X_a = T_ab.act(torch.from_numpy(X_b)).numpy()
    n_degenerate = 0
    for seed in range(5):  # ~86% of samples are degenerate (three points on the line)
        est = estimate_sim3_ransac(X_a, X_b, Sim3RansacConfig(seed=seed))
        assert est.success, est.reason
        assert est.inlier_mask.all()
        assert (T_ab.inverse() @ est.T_ab).log().abs().max() < 1e-6
        n_degenerate += est.n_degenerate
    assert n_degenerate > 0  # degenerate samples were skipped, not fitted
