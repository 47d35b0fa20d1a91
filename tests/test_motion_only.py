"""Tests of fgslam.backend.motion_only: one pose optimised against blocks whose other keys stay fixed,
on the one LM loop. A pointmap edge between a fixed keyframe and a perturbed frame recovers the frame's
true Sim(3); a hold on the log-scale keeps the scale; the reduced system is the free key's part of the
block's gradient (finite differences); bad arguments are refused."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest

from fgslam.backend.keys import pose_key
from fgslam.backend.motion_only import MotionOnlyProblem, optimize_pose
from fgslam.backend.solver import LMSettings
from fgslam.factors.pointmap_block import PointmapBlock, PointmapEdge

SETTINGS = LMSettings(max_iterations=30, lambda_initial=1e-4, lambda_factor=10.0, lambda_max=1e8,
                      relative_tolerance=1e-12, damping="marquardt")


def _problem(rng, n=60):
    T_k = gtsam.Similarity3(gtsam.Rot3.Expmap(rng.normal(scale=0.2, size=3)), rng.normal(scale=0.3, size=3), 1.3)
    T_f = gtsam.Similarity3(gtsam.Rot3.Expmap(rng.normal(scale=0.2, size=3)), rng.normal(scale=0.3, size=3), 0.8)
    X_k = np.stack([rng.uniform(-1, 1, n), rng.uniform(-0.8, 0.8, n), rng.uniform(2, 4, n)], -1)
    T_kf = T_k.inverse().compose(T_f)
    X_f = np.array([T_kf.inverse().transformFrom(x) for x in X_k])
    block = PointmapBlock([PointmapEdge(pose_key(0), pose_key(1), X_k, X_f)])
    values = gtsam.Values()
    values.insert(pose_key(0), T_k)
    values.insert(pose_key(1), T_f.retract(np.array([0.03, -0.02, 0.04, 0.05, -0.04, 0.03, 0.0])))
    return block, values, T_k, T_f


def test_recovers_the_free_pose_and_keeps_the_fixed_one():
    block, values, T_k, T_f = _problem(np.random.default_rng(3))
    result = optimize_pose([block], values, pose_key(1), SETTINGS)
    assert result.report.final_cost < 1e-12 * max(result.report.initial_cost, 1.0) + 1e-14
    got = result.values.atSimilarity3(pose_key(1))
    # ray residuals fix the frame's pose up to the scale of the frame's own points: compare the rotation and
    # the camera centre, which the keyframe's points fix
    assert np.allclose(got.rotation().matrix(), T_f.rotation().matrix(), atol=1e-6)
    assert np.allclose(got.translation(), T_f.translation(), atol=1e-6)
    assert result.values.atSimilarity3(pose_key(0)).equals(T_k, 1e-12)


def test_hold_keeps_the_log_scale():
    block, values, _, _ = _problem(np.random.default_rng(4))
    s0 = values.atSimilarity3(pose_key(1)).scale()
    hold = np.array([0, 0, 0, 0, 0, 0, 1e12])
    result = optimize_pose([block], values, pose_key(1), SETTINGS, hold=hold)
    assert result.values.atSimilarity3(pose_key(1)).scale() == pytest.approx(s0, rel=1e-8)
    assert result.report.final_cost < result.report.initial_cost


def test_reduced_gradient_matches_finite_differences():
    block, values, _, _ = _problem(np.random.default_rng(5))
    problem = MotionOnlyProblem([block], values, pose_key(1))
    _, g, _ = problem.reduced_system()
    h = 1e-6
    fd = np.zeros(7)
    for n in range(7):
        dx = np.zeros(7)
        dx[n] = h
        plus, minus = gtsam.Values(values), gtsam.Values(values)
        plus.update(pose_key(1), values.atSimilarity3(pose_key(1)).retract(dx))
        minus.update(pose_key(1), values.atSimilarity3(pose_key(1)).retract(-dx))
        fd[n] = (block.cost(plus) - block.cost(minus)) / (2 * h)
    assert np.allclose(g, fd, rtol=1e-4, atol=1e-7)


def test_bad_arguments():
    block, values, _, _ = _problem(np.random.default_rng(6))
    with pytest.raises(ValueError, match="at least one block"):
        MotionOnlyProblem([], values, pose_key(1))
    with pytest.raises(ValueError, match="does not touch"):
        MotionOnlyProblem([block], values, pose_key(2))
