"""Tests of fgslam.frontends.pointmap.tracking: Gauss-Newton IRLS tracking of a relative Sim(3) / SE(3)
on ray (+ distance) and calibrated residuals, with outliers and pure rotation, and the pointmap fusion of
eq. 9."""

from __future__ import annotations

import numpy as np
import torch

from fgslam.factors.pointmap_block import PointmapBlockConfig
from fgslam.frontends.pointmap.config import PointmapTrackingConfig
from fgslam.frontends.pointmap.tracking import fuse_pointmap, track_pose
from fgslam.core.lie import Sim3

K = torch.tensor([200.0, 200.0, 160.0, 120.0], dtype=torch.float64)


def _scene(n=3000, seed=0):
    g = torch.Generator().manual_seed(seed)
    uv = torch.rand(n, 2, generator=g, dtype=torch.float64) * torch.tensor([320.0, 240.0], dtype=torch.float64)
    z = 1.5 + 2.0 * torch.rand(n, generator=g, dtype=torch.float64)
    X = torch.stack(((uv[:, 0] - K[2]) / K[0] * z, (uv[:, 1] - K[3]) / K[1] * z, z), -1)
    return X


def _project(X):
    return torch.stack((K[0] * X[:, 0] / X[:, 2] + K[2], K[1] * X[:, 1] / X[:, 2] + K[3]), -1)


def _case(xi, outliers=0.0, seed=0):
    """Points of keyframe k, the frame's points ``X_f = T^-1 X_k`` with ``T = T_CkCf = Exp(xi)``, a share of
    gross outliers among the keyframe points."""
    T = Sim3.exp(torch.tensor(xi, dtype=torch.float64))
    X_k = _scene(seed=seed)
    X_f = T.inverse().act(X_k)
    X_k_meas = X_k.clone()
    n_out = int(outliers * len(X_k))
    if n_out:
        X_k_meas[:n_out] = X_k_meas[:n_out].flip(0) * 1.3  # wrong matches
    return T, X_f, X_k_meas, _project(X_k_meas)


def _error(T, T_true):
    d = (T_true.inverse() @ T).log()
    return float(d[:3].norm()), float(d[3:6].norm()), float(d[6].abs())


def _identity():
    return Sim3.exp(torch.zeros(7, dtype=torch.float64))


def test_ray_mode_recovers_a_sim3_with_outliers():
    """5 % gross outliers: Huber keeps the estimate within about a millimetre (its bias), least squares
    does not; the outliers are not inliers."""
    T_true, X_f, X_k, _ = _case([0.02, -0.05, 0.01, 0.1, -0.03, 0.05, 0.2], outliers=0.05)
    w = torch.ones(len(X_f), dtype=torch.float64)
    res = track_pose(_identity(), X_f, X_k, w, PointmapBlockConfig(mode="ray"), PointmapTrackingConfig(iterations=30), False)
    rot, trans, scale = _error(res.T_CkCf, T_true)
    # the scale comes from the weak distance row alone (sigma_dist = 10 keeps it in Huber's quadratic
    # region), so wrong matches bias it like least squares: 5 % outliers 30 % too far -> about 1 %
    assert rot < 1e-3 and trans < 2e-3 and scale < 0.02
    assert res.final_cost < res.initial_cost
    n_out = int(0.05 * len(X_f))
    assert res.inlier[n_out:].float().mean() > 0.99 and res.inlier[:n_out].float().mean() < 0.2
    plain = PointmapBlockConfig(mode="ray")
    plain.robust.kind = "none"
    ls = track_pose(_identity(), X_f, X_k, w, plain, PointmapTrackingConfig(iterations=30), False)
    assert _error(ls.T_CkCf, T_true)[1] > 5 * trans


def test_calibrated_mode_and_fixed_scale():
    T_true, X_f, X_k, uv = _case([0.01, 0.03, -0.02, -0.08, 0.02, 0.04, 0.0])
    w = torch.ones(len(X_f), dtype=torch.float64)
    res = track_pose(_identity(), X_f, X_k, w, PointmapBlockConfig(mode="calibrated"), PointmapTrackingConfig(), True, uv, K)
    rot, trans, scale = _error(res.T_CkCf, T_true)
    assert rot < 1e-5 and trans < 1e-4
    assert abs(float(res.T_CkCf.s) - 1.0) < 1e-12  # SE(3): the scale never moves
    # with the true relative pose scaled, SE(3) tracking cannot reach it, Sim(3) tracking does
    T_s, X_f2, X_k2, uv2 = _case([0.01, 0.03, -0.02, -0.08, 0.02, 0.04, 0.1])
    fixed = track_pose(_identity(), X_f2, X_k2, w, PointmapBlockConfig(mode="calibrated"), PointmapTrackingConfig(), True, uv2, K)
    free = track_pose(_identity(), X_f2, X_k2, w, PointmapBlockConfig(mode="calibrated"), PointmapTrackingConfig(), False, uv2, K)
    assert _error(free.T_CkCf, T_s)[2] < 1e-4 and _error(fixed.T_CkCf, T_s)[2] > 0.09


def test_pure_rotation_stays_well_posed():
    """Zero translation: the ray rows alone leave the scale free along t = 0; the distance row fixes it."""
    T_true, X_f, X_k, _ = _case([0.0, 0.08, 0.02, 0.0, 0.0, 0.0, 0.0])
    w = torch.ones(len(X_f), dtype=torch.float64)
    res = track_pose(_identity(), X_f, X_k, w, PointmapBlockConfig(mode="ray"), PointmapTrackingConfig(iterations=30), False)
    rot, trans, scale = _error(res.T_CkCf, T_true)
    assert rot < 1e-5 and trans < 1e-3 and scale < 1e-3 and torch.isfinite(res.T_CkCf.matrix()).all()


def test_confidence_weighting_and_degenerate_matches():
    """Zero-confidence and NaN matches do not move the estimate; with no usable match the pose stays."""
    T_true, X_f, X_k, _ = _case([0.01, 0.02, 0.0, 0.05, 0.0, 0.0, 0.0])
    w = torch.ones(len(X_f), dtype=torch.float64)
    X_k_bad = X_k.clone()
    X_k_bad[:500] = torch.nan
    X_k_bad[500:1000] *= 2.0
    w[500:1000] = 0.0  # wrong but zero confidence
    res = track_pose(_identity(), X_f, X_k_bad, w, PointmapBlockConfig(mode="ray"), PointmapTrackingConfig(iterations=30), False)
    assert max(_error(res.T_CkCf, T_true)) < 1e-3
    assert not bool(res.inlier[:1000].any())
    none = track_pose(_identity(), X_f, X_k, torch.zeros_like(w), PointmapBlockConfig(mode="ray"), PointmapTrackingConfig(), False)
    assert torch.allclose(none.T_CkCf.matrix(), _identity().matrix()) and none.num_inliers == 0


def test_fusion_is_the_confidence_weighted_average():
    X = torch.zeros(4, 3)
    X[:, 2] = 1.0
    C = torch.tensor([1.0, 0.0, 2.0, 1.0])
    index = torch.tensor([0, 1, 2, 2, 3])
    X_new = torch.tensor([[0.0, 0.0, 2.0], [1.0, 1.0, 1.0], [0.0, 0.0, 4.0], [0.0, 0.0, 7.0], [float("nan"), 0, 1]])
    C_new = torch.tensor([1.0, 0.5, 1.0, 1.0, 1.0])
    fuse_pointmap(X, C, index, X_new, C_new, max_confidence=3.5)
    np.testing.assert_allclose(X[0].numpy(), [0, 0, 1.5])  # (1 * 1 + 1 * 2) / 2
    np.testing.assert_allclose(X[1].numpy(), [1, 1, 1])  # a hole filled by the new point
    np.testing.assert_allclose(X[2].numpy(), [0, 0, (2 * 1 + 4 + 7) / 4])  # two new points at one pixel
    np.testing.assert_allclose(X[3].numpy(), [0, 0, 1])  # the NaN point is skipped
    np.testing.assert_allclose(C.numpy(), [2.0, 0.5, 3.5, 1.0])  # capped at max_confidence
