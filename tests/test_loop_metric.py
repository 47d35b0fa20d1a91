"""Metric-scale loop closure (stereo / RGB-D maps): the pose graph with ``hold_scale``
(fgslam.loop.pose_graph) keeps every keyframe's scale, so a correction is SE(3) even when the loop
measurements carry scale noise. The closer side (rigid verification, SE(3) corrections on rendered
frames) is in tests/test_loop_closure.py (``metric_run``); the rigid RANSAC fit in
tests/test_sim3_estimation.py.

Odometry here drifts in rotation and translation only (metric depth: no scale drift); ATE is
SE(3)-aligned (fgslam.eval.trajectory), which a scale error would show."""

from __future__ import annotations

import logging
import math

import numpy as np
import pytest
from tool_support import load_tool
import torch

from fgslam.eval.trajectory import EvalConfig, evaluate
from fgslam.io.trajectory import Trajectory
from fgslam.core.lie import Sim3
from fgslam.loop.pose_graph import PoseGraphConfig, optimize_sim3_pose_graph

LOOP_LOG_SCALE_NOISE = 0.02  # log-scale noise of the loop measurements (a Sim(3) fit's scale error)


@pytest.fixture(scope="module")
def bench():
    """The KITTI drift simulator of tools/bench_pose_graph.py (as in tests/test_pose_graph.py)."""
    return load_tool("bench_pose_graph")


def _se3_ate(gt_T_WC: np.ndarray, T_WC: Sim3) -> float:
    """SE(3)-aligned keyframe ATE RMSE (m); the estimate's rotation and position only."""
    K = gt_T_WC.shape[0]
    est = np.tile(np.eye(4), (K, 1, 1))
    est[:, :3, :3], est[:, :3, 3] = T_WC.R.numpy(), T_WC.t.numpy()
    stamps = np.arange(K, dtype=np.float64)
    cfg = EvalConfig(association="index", align="se3", rpe_delta_meters=None)
    return float(evaluate(Trajectory(stamps, gt_T_WC), Trajectory(stamps, est), cfg).ate.rmse)


def _rot_y(angle: float) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def _circle_scenario(n=120, radius=20.0, yaw_per_step=0.003, lateral_per_step=0.003, seed=0):
    """Planar circular drive (camera y vertical), metric odometry with heading and sideways drift,
    loops from the end of the lap to its start measured with rotation, translation and scale noise."""
    rng = np.random.default_rng(seed)
    a = np.linspace(0, 2 * np.pi, n, endpoint=False)
    G = np.tile(np.eye(4), (n, 1, 1))
    for k in range(n):
        G[k, :3, :3] = _rot_y(-a[k])
        G[k, :3, 3] = [radius * math.sin(a[k]), 0.0, radius * math.cos(a[k])]
    P = [G[0]]
    for k in range(n - 1):
        D = np.linalg.inv(G[k]) @ G[k + 1]
        D[:3, :3] = _rot_y(yaw_per_step) @ D[:3, :3]
        D[:3, 3] += [lateral_per_step, 0.0, 0.0]
        P.append(P[-1] @ D)
    P = np.stack(P)
    to_sim3 = lambda M: Sim3(torch.from_numpy(M[:, :3, :3]), torch.from_numpy(M[:, :3, 3]),  # noqa: E731
                             torch.ones(M.shape[0], dtype=torch.float64))
    li = np.arange(0, 12, 2)
    lj = n - 20 + li
    Z = np.linalg.inv(G[li]) @ G[lj]
    Z[:, :3, 3] += rng.normal(0, 0.02, (li.size, 3))
    s = np.exp(rng.normal(0, LOOP_LOG_SCALE_NOISE, li.size))
    T_CiCj = Sim3(torch.from_numpy(Z[:, :3, :3]), torch.from_numpy(Z[:, :3, 3]), torch.from_numpy(s))
    return G, to_sim3(P), li, lj, T_CiCj


def test_hold_scale_corrects_rigidly_despite_scale_noise():
    G, T_odom, li, lj, Z = _circle_scenario()
    ate_before = _se3_ate(G, T_odom)
    res = optimize_sim3_pose_graph(T_odom, li, lj, Z, hold_scale=True)
    assert res.accepted.all(), [d.reason for d in res.loops]
    assert torch.equal(res.scale_correction, torch.ones_like(res.scale_correction))
    assert torch.equal(res.T_WC.s, T_odom.s)
    assert all(d.log_scale < 1e-12 for d in res.loops)     # the held scales imply s_j / s_i = 1
    ate_after = _se3_ate(G, res.T_WC)
    assert ate_before > 1.5 and ate_after < 0.06 * ate_before, (ate_before, ate_after)
    assert res.T_WC[0].local(T_odom[0]).abs().max() < 1e-6
    # The same loops in a Sim(3) graph bend the keyframe scales (by their scale noise and drift).
    free = optimize_sim3_pose_graph(T_odom, li, lj, Z)
    assert free.accepted.all()
    assert float(torch.log(free.scale_correction).abs().max()) > 0.1 * LOOP_LOG_SCALE_NOISE


def test_hold_scale_keeps_non_unit_scales_and_consistent_poses():
    """Held scales other than 1 are kept too, and consistent loops leave the poses unchanged."""
    G, T_odom, li, lj, _ = _circle_scenario(n=40)
    lj = li + 25
    T = Sim3(T_odom.R, T_odom.t, torch.full((40,), 2.5, dtype=torch.float64))
    Z = T[torch.from_numpy(li)].inverse() @ T[torch.from_numpy(lj)]
    Z_noisy = Sim3(Z.R, Z.t, Z.s * 1.05)                   # the scale is replaced by s_j / s_i = 1
    res = optimize_sim3_pose_graph(T, li, lj, Z_noisy, PoseGraphConfig(), hold_scale=True)
    assert res.accepted.all()
    assert torch.equal(res.T_WC.s, T.s)
    assert torch.allclose(res.T_WC.matrix(), T.matrix(), atol=1e-6)


@pytest.mark.shared_data
@pytest.mark.parametrize("seq", ["00", "05"])
def test_kitti_metric_drift_hold_scale(shared_data, bench, seq):
    """KITTI ground truth with metric odometry drift (heading bias + noise, no scale drift), true loops
    with scale noise and false loops: the metric pose graph rejects the false loops, cuts the
    SE(3)-aligned ATE and never changes a scale."""
    from fgslam.io.trajectory import read_trajectory

    gt = read_trajectory(shared_data / "kitti_gt" / f"{seq}.txt", "kitti")
    sim = bench.DriftSimConfig(stride=2, scale_trend_per_km=0.0, scale_walk_per_sqrt_km=0.0,
                               heading_bias_deg_per_100m=1.0, loop_log_scale_noise=LOOP_LOG_SCALE_NOISE)
    scn = bench.simulate_kitti_drift(gt.T_WC, sim, 1.0 / bench.KITTI_FRAME_RATE_HZ)
    res = optimize_sim3_pose_graph(scn.T_WC_odom, scn.loop_i, scn.loop_j, scn.T_CiCj, hold_scale=True)
    n_true = int((~scn.is_false).sum())
    assert not (res.accepted & scn.is_false).any()
    assert (res.accepted & ~scn.is_false).sum() >= 0.9 * n_true
    assert torch.equal(res.scale_correction, torch.ones_like(res.scale_correction))
    before, after = _se3_ate(scn.gt_T_WC, scn.T_WC_odom), _se3_ate(scn.gt_T_WC, res.T_WC)
    logging.getLogger(__name__).info("KITTI %s metric: SE(3) ATE %.2f m -> %.2f m, %d/%d loops accepted, %.2f s",
                                     seq, before, after, int(res.accepted.sum()), res.accepted.size, res.solve_time_s)
    assert after < 0.1 * before, (before, after)
