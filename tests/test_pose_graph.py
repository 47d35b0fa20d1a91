"""Sim(3) pose graph with false-loop rejection (fgslam.loop.pose_graph), incl. KITTI simulated drift."""

import math

import numpy as np
import pytest
from tool_support import load_tool
import torch

from fgslam.core.errors import ConfigError
from fgslam.core.lie import Sim3
from fgslam.loop.pose_graph import (
    PoseGraphConfig,
    correct_dependent_poses,
    fold_scale_into_depths,
    loop_chi2,
    optimize_sim3_pose_graph,
    relative_to_anchor,
)


@pytest.fixture(scope="module")
def bench():
    """The scenario generator of tools/bench_pose_graph.py (one source for test and benchmark)."""
    return load_tool("bench_pose_graph")


def _circle(n=120, radius=20.0, laps=1.0):
    """Planar circular drive (camera y axis vertical, z forward), poses T_WC (n,) as Sim3, scale 1."""
    a = np.linspace(0, 2 * np.pi * laps, n, endpoint=False)
    yaw = -a  # heading tangent to the circle
    R = np.zeros((n, 3, 3))
    R[:, 0, 0], R[:, 0, 2], R[:, 1, 1], R[:, 2, 0], R[:, 2, 2] = np.cos(yaw), np.sin(yaw), 1, -np.sin(yaw), np.cos(yaw)
    t = np.column_stack([radius * np.sin(a), np.zeros(n), radius * np.cos(a)])
    return Sim3(torch.from_numpy(R), torch.from_numpy(t), torch.ones(n, dtype=torch.float64))


def _drift(T_gt: Sim3, yaw_per_step=0.001, log_scale_per_step=0.0015):
    """Odometry with heading and scale drift; returns (T_odom (n,), local scale sigma (n,))."""
    n = T_gt.shape[0]
    D = T_gt[:-1].inverse() @ T_gt[1:]
    sigma = torch.exp(log_scale_per_step * torch.arange(n, dtype=torch.float64))
    c, s = math.cos(yaw_per_step), math.sin(yaw_per_step)
    R_bias = torch.tensor([[c, 0, s], [0, 1, 0], [-s, 0, c]], dtype=torch.float64)
    poses = [T_gt[0]]
    for k in range(n - 1):
        step = Sim3(R_bias @ D.R[k], sigma[k] * D.t[k], torch.tensor(1.0, dtype=torch.float64))
        poses.append(poses[-1] @ step)
    from fgslam.core.lie import stack

    return stack(poses), sigma


def _true_loops(T_gt: Sim3, sigma, pairs):
    """Loop measurements T_CiCj with the local scales of both ends (as RANSAC between two neighbourhoods)."""
    i = torch.tensor([p[0] for p in pairs])
    j = torch.tensor([p[1] for p in pairs])
    G = T_gt[i].inverse() @ T_gt[j]
    return i.numpy(), j.numpy(), Sim3(G.R, sigma[i, None] * G.t, sigma[i] / sigma[j])


def _ate(T_gt: Sim3, T: Sim3) -> float:
    from fgslam.core.geometry import umeyama

    al = umeyama(T.t.numpy(), T_gt.t.numpy(), with_scale=True)
    return float(np.sqrt(np.mean(np.sum((T.t.numpy() @ (al.s * al.R).T + al.t - T_gt.t.numpy()) ** 2, axis=1))))


# ------------------------------------------------------------------------------------------ unit tests


def test_chi2_matches_gtsam_factor_error():
    import gtsam

    rng = np.random.default_rng(0)
    T = Sim3.exp(torch.from_numpy(rng.normal(0, 0.5, (6, 7))))
    Z = Sim3.exp(torch.from_numpy(rng.normal(0, 0.5, (3, 7))))
    i, j = np.array([0, 2, 5]), np.array([3, 1, 4])
    sig = np.array([0.01, 0.02, 0.03, 0.1, 0.2, 0.3, 0.05])
    chi2 = loop_chi2(T, i, j, Z, sig)
    values = gtsam.Values()
    for k, p in enumerate(T.to_gtsam()):
        values.insert(k, p)
    for l in range(3):
        f = gtsam.BetweenFactorSimilarity3(int(i[l]), int(j[l]), Z[l].to_gtsam(), gtsam.noiseModel.Diagonal.Sigmas(sig))
        assert chi2[l] == pytest.approx(2 * f.error(values), rel=1e-8)


def test_circle_drift_corrected_with_scale():
    T_gt = _circle()
    T_odom, sigma = _drift(T_gt)
    n = T_gt.shape[0]
    pairs = [(k, n - 20 + k) for k in range(0, 12, 2)]  # the end of the lap revisits the start
    li, lj, Z = _true_loops(T_gt, sigma, pairs)
    res = optimize_sim3_pose_graph(T_odom, li, lj, Z)
    assert res.accepted.all(), [d.reason for d in res.loops]
    before, after = _ate(T_gt, T_odom), _ate(T_gt, res.T_WC)
    assert after < 0.1 * before
    # The recovered keyframe scale follows 1 / local scale (up to the gauge s_0 = 1).
    s_expected = 1.0 / sigma
    assert torch.allclose(res.T_WC.s, s_expected, rtol=0.05)
    assert torch.allclose(res.scale_correction, res.T_WC.s / T_odom.s)
    assert res.T_WC[0].local(T_odom[0]).abs().max() < 1e-6  # gauge: first pose held
    assert all(d.reason == "accepted" and d.chi2 < 30 for d in res.loops)


def test_no_loops_and_consistent_loops_leave_poses_unchanged():
    T = _circle(40)
    res = optimize_sim3_pose_graph(T, [], [], Sim3.identity((0,)))
    assert res.accepted.shape == (0,) and torch.allclose(res.T_WC.matrix(), T.matrix())
    i, j = np.array([0, 1, 2]), np.array([30, 31, 32])
    Z = T[torch.from_numpy(i)].inverse() @ T[torch.from_numpy(j)]
    res = optimize_sim3_pose_graph(T, i, j, Z)
    assert res.accepted.all()
    assert torch.allclose(res.T_WC.matrix(), T.matrix(), atol=1e-6)


def test_gate_rejects_implausible_and_invalid_loops():
    T_gt = _circle()
    T_odom, sigma = _drift(T_gt)
    n = T_gt.shape[0]
    li, lj, Z = _true_loops(T_gt, sigma, [(k, n - 20 + k) for k in range(0, 12, 2)])
    f64 = dict(dtype=torch.float64)
    R_flip = torch.tensor([[-1.0, 0, 0], [0, 1, 0], [0, 0, -1]], **f64)
    flip = Sim3(R_flip, torch.zeros(3, **f64), torch.tensor(1.0, **f64))
    far = Sim3(torch.eye(3, **f64), torch.tensor([500.0, 0, 0], **f64), torch.tensor(1.0, **f64))
    tiny = Sim3(torch.eye(3, **f64), torch.zeros(3, **f64), torch.tensor(0.05, **f64))
    nan = Sim3(torch.eye(3, **f64), torch.tensor([math.nan, 0, 0], **f64), torch.tensor(1.0, **f64))
    bad = [Z[0] @ flip, Z[1] @ far, Z[2] @ tiny, nan, Z[0], Z[0]]
    from fgslam.core.lie import stack

    Z_all = stack([Z[k] for k in range(len(li))] + bad)
    li_all = np.concatenate([li, [li[0], li[1], li[2], 3, 5, 0]])
    lj_all = np.concatenate([lj, [lj[0], lj[1], lj[2], 60, 5, n + 3]])
    res = optimize_sim3_pose_graph(T_odom, li_all, lj_all, Z_all)
    r = [d.reason for d in res.loops]
    assert res.accepted[: len(li)].all()
    assert not res.accepted[len(li):].any()
    assert r[len(li)].startswith("implausible: rotation")
    assert r[len(li) + 1].startswith("implausible") and "position change" in r[len(li) + 1]
    assert r[len(li) + 2].startswith("implausible") and "scale" in r[len(li) + 2]
    assert all(x.startswith("invalid") for x in r[len(li) + 3:])
    assert torch.isfinite(res.T_WC.matrix()).all()
    assert _ate(T_gt, res.T_WC) < 0.1 * _ate(T_gt, T_odom)


def test_isolated_plausible_false_loop_rejected():
    T_gt = _circle(160, laps=1.3)
    T_odom, sigma = _drift(T_gt)
    n = T_gt.shape[0]
    li, lj, Z = _true_loops(T_gt, sigma, [(k, 123 + k) for k in range(0, 30, 3)])
    # False loop: claims keyframe 100 is 2 m beside keyframe 5 (they are ~25 m apart after ~100 m
    # of driving: passes the plausibility gate) with the odometry's relative rotation.
    f64 = dict(dtype=torch.float64)
    Z_false = Sim3((T_odom[5].inverse() @ T_odom[100]).R, torch.tensor([2.0, 0, 0], **f64), torch.tensor(1.0, **f64))
    from fgslam.core.lie import stack

    Z_all = stack([Z[k] for k in range(len(li))] + [Z_false])
    res = optimize_sim3_pose_graph(T_odom, np.append(li, 5), np.append(lj, 100), Z_all)
    assert res.accepted[:-1].all() and not res.accepted[-1]
    assert res.loops[-1].reason.startswith("unsupported")
    # Without the pairwise check, the robust solve + chi-square test must catch it.
    cfg = PoseGraphConfig(min_pairwise_support=0)
    res2 = optimize_sim3_pose_graph(T_odom, np.append(li, 5), np.append(lj, 100), Z_all, cfg)
    assert res2.accepted[:-1].all() and not res2.accepted[-1]
    assert res2.loops[-1].reason.startswith("inconsistent")
    assert _ate(T_gt, res2.T_WC) < 0.1 * _ate(T_gt, T_odom)


def test_round_rejecting_every_loop_does_not_crash():
    """Regression: a chi-square round that rejects every active loop left an empty loop set."""
    n = 60
    f64 = dict(dtype=torch.float64)
    R = torch.eye(3, **f64).expand(n, 3, 3).clone()
    t = torch.zeros(n, 3, **f64)
    t[:, 2] = torch.arange(n, **f64)
    T = Sim3(R, t, torch.ones(n, **f64))
    twist = Sim3(torch.from_numpy(_rot_y(math.radians(30.0))), torch.zeros(3, **f64), torch.tensor(1.0, **f64))
    pairs = [(50, 2), (51, 3)]
    from fgslam.core.lie import stack

    Z = stack([(T[i].inverse() @ T[j]) @ twist for i, j in pairs])
    res = optimize_sim3_pose_graph(T, np.array([p[0] for p in pairs]), np.array([p[1] for p in pairs]), Z,
                                   PoseGraphConfig(min_pairwise_support=0))
    assert not res.accepted.any()
    assert torch.allclose(res.T_WC.t, T.t, atol=1e-6)


def _rot_y(angle: float) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def test_dependent_poses_and_scale_folding():
    rng = np.random.default_rng(1)
    T_old = Sim3.exp(torch.from_numpy(rng.normal(0, 0.5, (5, 7))))
    T_new = Sim3.exp(torch.from_numpy(rng.normal(0, 0.5, (5, 7))))
    T_WF_old = Sim3.exp(torch.from_numpy(rng.normal(0, 0.5, (8, 7))))
    anchor = np.array([0, 0, 1, 2, 2, 3, 4, 4])
    T_KF = relative_to_anchor(T_old, anchor, T_WF_old)
    T_WF_new = correct_dependent_poses(T_new, anchor, T_KF)
    # Each frame keeps its pose relative to its keyframe.
    rel_new = T_new[torch.from_numpy(anchor)].inverse() @ T_WF_new
    assert torch.allclose(rel_new.matrix(), T_KF.matrix(), atol=1e-9)
    assert torch.allclose(correct_dependent_poses(T_old, anchor, T_KF).matrix(), T_WF_old.matrix(), atol=1e-9)
    # Folding the scale change into inverse depths keeps world points.
    d = torch.from_numpy(rng.uniform(0.1, 2.0, (5, 4, 3)))
    xy = torch.from_numpy(rng.normal(0, 0.5, (5, 4, 3, 2)))
    xy1 = torch.cat([xy, torch.ones(5, 4, 3, 1, dtype=torch.float64)], -1)
    folded, d_new = fold_scale_into_depths(T_old, T_new, d)
    assert torch.allclose(folded.s, T_old.s) and torch.allclose(folded.R, T_new.R) and torch.allclose(folded.t, T_new.t)
    assert torch.allclose(d_new, d / (T_new.s / T_old.s)[:, None, None])
    X_new = T_new[:, None, None].act(xy1 / d[..., None])
    X_folded = folded[:, None, None].act(xy1 / d_new[..., None])
    assert torch.allclose(X_new, X_folded, atol=1e-9)


def test_config_validation():
    T = _circle(10)
    with pytest.raises(ConfigError):
        optimize_sim3_pose_graph(T, [], [], Sim3.identity((0,)), PoseGraphConfig(loop_sigmas=(0.1,) * 6))
    with pytest.raises(ConfigError):
        optimize_sim3_pose_graph(T, [], [], Sim3.identity((0,)), PoseGraphConfig(robust_kernel="tukey"))
    with pytest.raises(ConfigError):
        optimize_sim3_pose_graph(T, [], [], Sim3.identity((0,)), PoseGraphConfig(consistency_probability=1.0))
    with pytest.raises(ConfigError, match="hold_scale_sigma"):
        optimize_sim3_pose_graph(T, [], [], Sim3.identity((0,)), PoseGraphConfig(hold_scale_sigma=0.0), hold_scale=True)
    with pytest.raises(ValueError):
        optimize_sim3_pose_graph(T, [0, 1], [5], Sim3.identity((2,)))


# ------------------------------------------------------------------------------ KITTI simulated drift

# Sequence 08 drives its second half through streets it never revisits (no ground-truth revisit
# within 5 m between keyframes ~1000 and ~1800 at stride 2), so drift there is unobservable by any
# loop closure: the cut reaches 0.76-0.83 over seeds 0-4, below the 0.9. Asserted at 0.7.
MIN_ATE_CUT = {"00": 0.9, "05": 0.9, "06": 0.9, "08": 0.7}


@pytest.mark.shared_data
@pytest.mark.parametrize("seq", ["00", "05", "06", "08"])
def test_kitti_simulated_drift(shared_data, bench, seq):
    from fgslam.io.trajectory import read_trajectory

    gt = read_trajectory(shared_data / "kitti_gt" / f"{seq}.txt", "kitti")
    scn = bench.simulate_kitti_drift(gt.T_WC, bench.DriftSimConfig(stride=2), 1.0 / bench.KITTI_FRAME_RATE_HZ)
    n_true, n_false = int((~scn.is_false).sum()), int(scn.is_false.sum())
    assert n_true >= 40 and n_false >= 0.1 * n_true
    r = bench.run_scenario(scn, PoseGraphConfig())
    assert r["false_accepted"] == 0, [d.reason for d, f in zip(r["result"].loops, scn.is_false) if f]
    assert r["true_accepted"] >= 0.9 * n_true
    assert r["ate_cut"] >= MIN_ATE_CUT[seq], (r["ate_before_m"], r["ate_after_m"])


@pytest.mark.shared_data
def test_kitti_perceptual_aliasing_clusters(shared_data, bench):
    """False loops in consistent clusters of 3 (pairwise check passes them): chi-square rounds and
    re-admission trials must still reject all of them and keep the true loops (sequence 08)."""
    from fgslam.io.trajectory import read_trajectory

    gt = read_trajectory(shared_data / "kitti_gt" / "08.txt", "kitti")
    cfg = bench.DriftSimConfig(stride=2, false_loop_cluster=3)
    scn = bench.simulate_kitti_drift(gt.T_WC, cfg, 1.0 / bench.KITTI_FRAME_RATE_HZ)
    r = bench.run_scenario(scn, PoseGraphConfig())
    assert r["false_accepted"] == 0
    assert r["false_rejected_by_chi2"] >= 3
    assert r["true_accepted"] >= 0.9 * r["true_loops"]
    assert r["ate_cut"] >= MIN_ATE_CUT["08"]
