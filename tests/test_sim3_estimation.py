"""RANSAC + Umeyama Sim(3) estimation from 3-D-3-D correspondences (fgslam.loop.sim3_estimation)."""

import numpy as np
import pytest
import torch

from fgslam.core.errors import ConfigError
from fgslam.core.lie import Sim3
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


# ------------------------------------------------------------------------------ rigid fit (metric maps)


def _with_scale(T: Sim3, s: float) -> Sim3:
    return Sim3(T.R, T.t, torch.tensor(s, dtype=torch.float64))


@pytest.mark.parametrize("seed", [0, 1])
def test_rigid_fit_on_rigid_data_equals_sim3_fit(seed):
    rng = np.random.default_rng(seed)
    T_ab = _with_scale(_random_sim3(rng), 1.0)
    X_a, X_b, is_inlier = _scene(rng, 200, T_ab, 0.3)
    est_rigid = estimate_sim3_ransac(X_a, X_b, Sim3RansacConfig(seed=seed), with_scale=False)
    est_sim3 = estimate_sim3_ransac(X_a, X_b, Sim3RansacConfig(seed=seed))
    assert est_rigid.success and est_sim3.success, (est_rigid.reason, est_sim3.reason)
    assert float(est_rigid.T_ab.s) == 1.0  # exactly: no scale estimated
    assert abs(float(est_sim3.T_ab.s) - 1.0) < 0.01
    xi = (est_sim3.T_ab.inverse() @ est_rigid.T_ab).log().numpy()
    assert np.linalg.norm(xi[:3]) < np.radians(0.2) and np.linalg.norm(xi[3:6]) < 0.02
    assert (T_ab.inverse() @ est_rigid.T_ab).log()[:6].abs().max() < 0.02
    assert (est_rigid.inlier_mask & is_inlier).sum() >= 0.95 * is_inlier.sum()
    assert (est_rigid.inlier_mask & ~is_inlier).sum() <= 0.05 * (~is_inlier).sum()


def test_rigid_fit_does_not_absorb_scale():
    rng = np.random.default_rng(4)
    T_ab = _with_scale(_random_sim3(rng), 1.3)
    X_a, X_b, _ = _scene(rng, 150, T_ab, 0.0, noise_rel=0.0)
    # Sim(3): every point fits; rigid: the 30 % scale difference is a residual (relative errors ~0.2 >
    # 0.05), a rigid motion only fits a thin slice of the points (its translation absorbing the scale
    # at one depth), never most of them
    assert estimate_sim3_ransac(X_a, X_b).inlier_ratio == 1.0
    est = estimate_sim3_ransac(X_a, X_b, with_scale=False)
    assert est.inlier_ratio < 0.3 and (not est.success or float(est.T_ab.s) == 1.0)
    # With every point an inlier the rigid fit still keeps s = 1 and recovers the rotation (Umeyama's
    # rotation does not depend on the scale); its residuals carry the scale difference.
    cfg = Sim3RansacConfig(error_metric="absolute", inlier_threshold=1e6)
    est = estimate_sim3_ransac(X_a, X_b, cfg, with_scale=False)
    assert est.success and float(est.T_ab.s) == 1.0
    R_err = est.T_ab.R.numpy().T @ T_ab.R.numpy()
    assert np.degrees(np.arccos(np.clip((np.trace(R_err) - 1) / 2, -1, 1))) < 1e-4
    assert est.rms_error > 0.1 * np.linalg.norm(X_b - X_b.mean(0), axis=1).mean()


def test_rigid_fit_rejects_degenerate_samples():
    rng = np.random.default_rng(3)
    T_ab = _with_scale(_random_sim3(rng), 1.0)
    lam = rng.uniform(-5, 5, 100)
    X_b = np.array([1.0, 2.0, 10.0]) + lam[:, None] * np.array([0.3, -0.2, 1.0])
    X_a = T_ab.act(torch.from_numpy(X_b)).numpy()
    est = estimate_sim3_ransac(X_a, X_b, with_scale=False)
    assert not est.success and "degenerate" in est.reason
    assert est.n_degenerate == est.iterations > 0
    X = np.tile([[1.0, 2.0, 5.0]], (50, 1))
    est = estimate_sim3_ransac(X, X, with_scale=False)
    assert not est.success and "degenerate" in est.reason
