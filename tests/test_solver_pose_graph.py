"""The backend's one LM loop (fgslam.backend.solver) on pose graphs: its damped step against the
explicit solution of ``(H + D) dx = -g`` (identity and Marquardt damping, variables of two
dimensions), and the KITTI 00 Sim(3) pose graph of tools/bench_kitti_pose_graph.py (every 9th pose,
its loops) solved to GTSAM's own LM's final cost."""

from __future__ import annotations

import numpy as np
import pytest
from tool_support import load_tool

from fgslam.backend.solver import LMSettings, NonlinearProblem, damping_diagonal, levenberg_marquardt

gtsam = pytest.importorskip("gtsam")


class _FirstStep(NonlinearProblem):
    """Records the first step the loop tries, then rejects every step (one solve per damping)."""

    def __init__(self, graph, values):
        super().__init__(graph, values)
        self.steps = []
        self.linearized = None

    def linearize(self):
        self.linearized = super().linearize()
        return self.linearized

    def hessian_diagonal(self):
        ordering = gtsam.Ordering()
        for k in self.keys:
            ordering.push_back(k)
        H, _ = self.linearized.hessian(ordering)
        diag = np.diag(np.asarray(H))
        out, at = {}, 0
        for k, d in zip(self.keys, self.dims):
            out[k] = diag[at:at + d]
            at += d
        return out

    def trial(self, delta):
        self.steps.append(np.concatenate([np.asarray(delta.at(k)) for k in self.keys]))
        return float("inf"), None


def _mixed_graph(rng):
    """Pose3 loop plus a chain of Point3 variables (keys of dimension 6 and 3 in one graph)."""
    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    poses = [gtsam.Pose3(gtsam.Rot3.Expmap(rng.normal(0, 0.3, 3)), rng.normal(0, 2, 3)) for _ in range(6)]
    graph.add(gtsam.PriorFactorPose3(0, poses[0], gtsam.noiseModel.Isotropic.Sigma(6, 0.01)))
    odo = gtsam.noiseModel.Diagonal.Sigmas(np.array([0.05, 0.05, 0.05, 0.1, 0.1, 0.1]))
    for i, j in [(0, 1), (1, 2), (2, 3), (3, 4), (4, 5), (5, 0)]:
        graph.add(gtsam.BetweenFactorPose3(i, j, poses[i].between(poses[j]).retract(rng.normal(0, 0.05, 6)), odo))
    for i, p in enumerate(poses):
        values.insert(i, p.retract(rng.normal(0, 0.1, 6)))
    points = rng.normal(0, 3, (3, 3))
    for m, X in enumerate(points):
        graph.add(gtsam.PriorFactorPoint3(100 + m, X, gtsam.noiseModel.Isotropic.Sigma(3, 0.2 + 0.1 * m)))
        values.insert(100 + m, X + rng.normal(0, 0.3, 3))
        if m:
            graph.add(gtsam.BetweenFactorPoint3(99 + m, 100 + m, X - points[m - 1] + rng.normal(0, 0.1, 3),
                                                gtsam.noiseModel.Isotropic.Sigma(3, 0.1)))
    return graph, values


@pytest.mark.parametrize("damping", ["identity", "marquardt"])
def test_damped_steps_solve_the_explicit_damped_system(damping):
    """Every step the loop tries (rising damping after rejections) is ``-(H + D(lambda))^-1 g`` of the
    linearisation, with D = lambda I or Marquardt's damping_diagonal(diag H, lambda)."""
    rng = np.random.default_rng(0)
    graph, values = _mixed_graph(rng)
    problem = _FirstStep(graph, values)
    problem.keys = [int(k) for k in graph.linearize(values).keyVector()]
    problem.dims = [6 if k < 100 else 3 for k in problem.keys]
    settings = LMSettings(max_iterations=1, lambda_initial=1e-3, lambda_factor=10.0, lambda_max=1e4, damping=damping)
    report = levenberg_marquardt(problem, settings)
    assert report.solves == len(problem.steps) == 8  # 1e-3 .. 1e4, every step rejected
    ordering = gtsam.Ordering()
    for k in problem.keys:
        ordering.push_back(k)
    H, eta = problem.linearized.hessian(ordering)  # eta = -g
    H, eta = np.asarray(H), np.asarray(eta)
    for step, lam in zip(problem.steps, 1e-3 * 10.0 ** np.arange(8)):
        D = np.full(H.shape[0], lam) if damping == "identity" else damping_diagonal(np.diag(H), lam)
        expected = np.linalg.solve(H + np.diag(D), eta)
        assert np.abs(step - expected).max() <= 1e-9 * np.abs(expected).max()
    assert np.linalg.norm(problem.steps[0]) > 2 * np.linalg.norm(problem.steps[-1])  # damping acts


def test_kitti00_sim3_pose_graph_reaches_gtsam_lm_cost(shared_data):
    """KITTI 00 with simulated drift and its ground-truth revisits as loops (every 9th pose: 505
    poses, 31 loops): the backend's loop ends at GTSAM's own LM's final cost (1e-6 relative) and
    poses, and the solve undoes the drift (the cost falls by orders of magnitude)."""
    from fgslam.io.trajectory import read_trajectory

    bench = load_tool("bench_kitti_pose_graph")
    gt = read_trajectory(shared_data / "kitti_gt" / "00.txt", "kitti").T_WC[::9]
    graph, initial, info = bench.build_kitti_pose_graph(gt, frame_dt_s=0.9)
    assert info["poses"] == 505 and info["loops"] > 20
    tolerances = (100, 1e-5, 1e-5)  # gtsam's defaults
    ref, _ = bench.solve_gtsam(graph, initial, *tolerances)
    ours, report = bench.solve_fgslam(graph, initial, *tolerances)
    ref_cost, our_cost = graph.error(ref), graph.error(ours)
    assert graph.error(initial) > 1e4 * ref_cost
    assert report.converged and report.final_cost == pytest.approx(our_cost, rel=1e-12)
    assert our_cost == pytest.approx(ref_cost, rel=1e-6)
    for k in range(0, info["poses"], 50):
        assert ours.atSimilarity3(k).equals(ref.atSimilarity3(k), 1e-6)


def test_kitti00_pose_graph_through_the_backend_reaches_gtsam_lm_cost(shared_data):
    """The same drifted keyframes and loops held by a Backend (loops as persistent factors): its
    pose-graph correction ends at the cost GTSAM's LM reaches on the graph the backend builds
    (1e-6 relative) and undoes the drift."""
    from fgslam.io.trajectory import read_trajectory

    bench = load_tool("bench_kitti_pose_graph")
    gt = read_trajectory(shared_data / "kitti_gt" / "00.txt", "kitti").T_WC[::9]
    out = bench.run_backend(gt, repeats=1, max_iterations=100, relative_tolerance=1e-5, frame_dt_s=0.9)
    assert out["keyframes"] == 505 and out["loops"] > 20
    assert out["initial_cost"] > 1e4 * out["gtsam"]["final_cost"]
    assert out["cost_relative_difference"] <= 1e-6
