"""Tests of fgslam.factors.pointmap_block: the pose-only pointmap block of the backend's block contract.
Its gradient and Gauss-Newton Hessian against finite differences of its cost and residuals (ray and
calibrated modes, Huber active on part of the matches), masking, and Levenberg-Marquardt through
fgslam.backend.solver recovering the keyframe poses of room-loop renders from RGB-D pointmaps matched by
the projective matcher."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest
import torch

from fgslam.factors.blocks import Block
from fgslam.backend.keys import pose_key
from fgslam.backend.solver import LMSettings, levenberg_marquardt
from fgslam.core.errors import DataError
from fgslam.factors.pointmap import PointmapResidualConfig
from fgslam.factors.pointmap_block import PointmapBlock, PointmapBlockConfig, PointmapEdge
from fgslam.factors.robust import RobustConfig, kernel_weight
from fgslam.factors.schur import to_gaussian_factor
from fgslam.frontends.pointmap.matching import RayImage, match_pointmaps
from fgslam.frontends.pointmap.source import PointmapSourceConfig, make_pointmap_source
from fgslam.core.lie import Sim3
from pointmap_support import render, room_sequence, rotation_angle_deg

K = np.array([160.0, 160.0, 160.0, 120.0])
H_FD = 1e-6


def _random_pose(rng, t_scale=0.3, s_range=(0.7, 1.4)) -> gtsam.Similarity3:
    R = gtsam.Rot3.Expmap(rng.normal(scale=0.2, size=3))
    return gtsam.Similarity3(R, rng.normal(scale=t_scale, size=3), float(rng.uniform(*s_range)))


def _synthetic(rng, n=40, noise=0.0, outliers=0):
    """Three keys, edges (0, 1), (1, 2), (0, 2); points in front of every camera; returns (values, edges)."""
    poses = [_random_pose(rng) for _ in range(3)]
    values = gtsam.Values()
    for k, T in enumerate(poses):
        values.insert(pose_key(k), T)
    edges = []
    for a, b in ((0, 1), (1, 2), (0, 2)):
        X_i = np.stack([rng.uniform(-1, 1, n), rng.uniform(-0.8, 0.8, n), rng.uniform(2, 4, n)], -1)
        T_ij = poses[a].inverse().compose(poses[b])  # T_CiCj
        X_j = np.array([T_ij.inverse().transformFrom(x) for x in X_i])
        X_i_meas = X_i + noise * rng.normal(size=X_i.shape)
        X_i_meas[:outliers] += rng.normal(scale=0.5, size=(outliers, 3))
        uv = np.stack([K[0] * X_i_meas[:, 0] / X_i_meas[:, 2] + K[2], K[1] * X_i_meas[:, 1] / X_i_meas[:, 2] + K[3]], -1)
        uv += 2.0 * noise * rng.normal(size=uv.shape)
        edges.append(PointmapEdge(pose_key(a), pose_key(b), X_i_meas, X_j, rng.uniform(0.2, 1.5, n), uv))
    return values, edges


def _retract(values, keys, dx):
    out = gtsam.Values(values)
    for n, key in enumerate(keys):
        out.update(key, values.atSimilarity3(key).retract(dx[7 * n:7 * n + 7]))
    return out


def _assemble(block, pieces):
    index = {k: n for n, k in enumerate(block.keys)}
    H = np.zeros((7 * len(block.keys),) * 2)
    g = np.zeros(7 * len(block.keys))
    for p in pieces:
        cols = np.concatenate([np.arange(7 * index[k], 7 * index[k] + 7) for k in p.keys])
        H[np.ix_(cols, cols)] += p.H
        g[cols] += p.g
    return H, g


@pytest.mark.parametrize("mode", ["ray", "calibrated"])
def test_gradient_and_hessian_against_finite_differences(mode):
    rng = np.random.default_rng(3 if mode == "ray" else 4)
    values, edges = _synthetic(rng, noise=0.01, outliers=8)
    res_cfg = PointmapResidualConfig(sigma_ray=0.01, sigma_dist=0.05, sigma_pixel=2.0, sigma_log_depth=0.02)
    cfg = PointmapBlockConfig(mode=mode, residual=res_cfg, robust=RobustConfig(kind="huber", delta=1.345))
    block = PointmapBlock(edges, cfg, K=K)
    assert isinstance(block, Block) and not block.has_structure
    values = _retract(values, block.keys, rng.normal(scale=0.01, size=7 * len(block.keys)))
    pieces = block.linearize(values)
    assert len(pieces) == 3 and all(p.H.shape == (14, 14) for p in pieces)
    cost = block.cost(values)
    assert np.isclose(sum(p.c for p in pieces), 2 * cost)
    H, g = _assemble(block, pieces)
    # some matches are in the Huber tail, others in its quadratic zone
    norms = [torch.linalg.vector_norm(e[:, :3 if mode == "ray" else 2], dim=-1) for e in block.whitened_residuals(values)]
    inside = float(torch.cat(norms).le(cfg.robust.delta).float().mean())
    assert 0.2 < inside < 0.95
    # g: the exact gradient of the cost
    dim = H.shape[0]
    g_fd = np.array([(block.cost(_retract(values, block.keys, H_FD * e)) - block.cost(_retract(values, block.keys, -H_FD * e)))
                     / (2 * H_FD) for e in np.eye(dim)])
    np.testing.assert_allclose(g, g_fd, rtol=1e-5, atol=1e-6 * np.abs(g_fd).max())
    # H: J^T W J with J from finite differences of the whitened residuals and W the kernel weights
    groups = ((0, 3), (3, 4)) if mode == "ray" else ((0, 2), (2, 3))
    e0 = block.whitened_residuals(values)
    J_fd = []
    for e in np.eye(dim):
        plus = block.whitened_residuals(_retract(values, block.keys, H_FD * e))
        minus = block.whitened_residuals(_retract(values, block.keys, -H_FD * e))
        J_fd.append(torch.cat([((p - m) / (2 * H_FD)).reshape(-1) for p, m in zip(plus, minus)]))
    J_fd = torch.stack(J_fd, -1).numpy()
    w_rows = []
    for e in e0:
        w = [kernel_weight(torch.linalg.vector_norm(e[:, a:b], dim=-1), "huber", cfg.robust.delta) for a, b in groups]
        w_rows.append(torch.stack([w[n] for n, (a, b) in enumerate(groups) for _ in range(b - a)], -1).reshape(-1))
    W = torch.cat(w_rows).numpy()
    H_fd = J_fd.T @ (W[:, None] * J_fd)
    np.testing.assert_allclose(H, H_fd, rtol=1e-4, atol=1e-6 * np.abs(H_fd).max())


def test_hessian_is_the_cost_curvature_at_an_exact_solution():
    rng = np.random.default_rng(5)
    values, edges = _synthetic(rng, n=15)
    cfg = PointmapBlockConfig(residual=PointmapResidualConfig(sigma_ray=0.01, sigma_dist=0.05))
    block = PointmapBlock(edges, cfg)
    H, g = _assemble(block, block.linearize(values))
    assert block.cost(values) < 1e-18 and np.abs(g).max() < 1e-8
    # the cost's curvature: finite differences of its exact gradient (checked above), symmetric
    h = 1e-6
    dim = H.shape[0]

    def grad(dx):
        return _assemble(block, block.linearize(_retract(values, block.keys, dx)))[1]

    H_fd = np.stack([(grad(h * e) - grad(-h * e)) / (2 * h) for e in np.eye(dim)], -1)
    H_fd = 0.5 * (H_fd + H_fd.T)
    np.testing.assert_allclose(H, H_fd, rtol=1e-4, atol=1e-6 * np.abs(H).max())


def test_masking_weights_and_bad_input():
    rng = np.random.default_rng(6)
    values, edges = _synthetic(rng, n=10)
    e = edges[0]
    X_i = e.X_i_in_i.copy()
    X_i[0] = np.nan
    weight = e.weight.copy()
    weight[1] = 0.0
    broken = PointmapEdge(e.key_i, e.key_j, X_i, e.X_j_in_j, weight)
    moved = _retract(values, [pose_key(0)], np.full(7, 0.01))
    ref = PointmapBlock([PointmapEdge(e.key_i, e.key_j, e.X_i_in_i[2:], e.X_j_in_j[2:], e.weight[2:])])
    blk = PointmapBlock([broken])
    assert np.isfinite(blk.cost(moved)) and np.isclose(blk.cost(moved), ref.cost(moved))
    np.testing.assert_allclose(blk.linearize(moved)[0].H, ref.linearize(moved)[0].H, rtol=1e-10)
    with pytest.raises(DataError, match="itself"):
        PointmapBlock([PointmapEdge(e.key_i, e.key_i, e.X_i_in_i, e.X_j_in_j)])
    with pytest.raises(DataError, match="intrinsics"):
        PointmapBlock(edges, PointmapBlockConfig(mode="calibrated"))
    with pytest.raises(DataError, match="uv_i"):
        PointmapBlock([PointmapEdge(e.key_i, e.key_j, e.X_i_in_i, e.X_j_in_j)], PointmapBlockConfig(mode="calibrated"), K=K)
    with pytest.raises(DataError, match="shape"):
        PointmapBlock([PointmapEdge(e.key_i, e.key_j, e.X_i_in_i, e.X_j_in_j[:3])])


class PoseBlockProblem:
    """LMProblem of fgslam.backend.solver over gtsam factors (the gauge) plus pose-only blocks."""

    def __init__(self, blocks, graph, values):
        self.blocks, self.graph, self.values = blocks, graph, values

    def cost(self) -> float:
        return float(self.graph.error(self.values)) + sum(b.cost(self.values) for b in self.blocks)

    def linearize(self):
        gfg = self.graph.linearize(self.values)
        for block in self.blocks:
            for piece in block.linearize(self.values):
                gfg.push_back(to_gaussian_factor(piece.keys, piece.H, piece.g, piece.c))
        return gfg

    def trial(self, delta):
        values = self.values.retract(delta)
        return float(self.graph.error(values)) + sum(b.cost(values) for b in self.blocks), values

    def accept(self, state, cost):
        self.values = state
        return cost


def test_lm_recovers_rgbd_keyframe_poses_from_matched_pointmaps():
    """Four room-loop keyframes, RGB-D pointmaps, matches by the projective matcher (geometry from the
    source's own PnP estimate), ray + distance block with Huber; LM from poses perturbed by ~5 cm,
    ~2 degrees and 5 % scale recovers the true relative Sim(3) poses (scale 1: metric depth)."""
    seq = room_sequence()
    frames = [0, 4, 8, 12]
    views = [render(seq, f) for f in frames]
    src = make_pointmap_source(PointmapSourceConfig(kind="rgbd"), seq.K)
    for v in views:
        src.add_frame(v.index, v.image, depth=v.depth)
    edges = []
    for a, b in ((0, 1), (1, 2), (2, 3), (0, 2)):
        pair = src.predict(frames[a], frames[b])
        m = match_pointmaps(RayImage(pair.X_i_in_i, pair.C_i), pair.X_j_in_i, D_i=pair.D_i,
                            D_j=pair.D_j.reshape(-1, 16), query_valid=(pair.C_j > 0).reshape(-1))
        q = np.nonzero(m.valid.numpy())[0][::7]  # a subsample keeps the test fast
        assert q.size > 5000
        X_i = pair.X_i_in_i.reshape(-1, 3)[m.index.numpy()[q]]
        X_j = pair.X_j_in_j.reshape(-1, 3)[q]
        edges.append(PointmapEdge(pose_key(a), pose_key(b), X_i, X_j, np.ones(q.size)))
    block = PointmapBlock(edges, PointmapBlockConfig(residual=PointmapResidualConfig(sigma_dist=0.05)))
    truth = [gtsam.Similarity3(gtsam.Rot3(v.T_WC[:3, :3]), v.T_WC[:3, 3], 1.0) for v in views]
    rng = np.random.default_rng(7)
    values = gtsam.Values()
    for n, T in enumerate(truth):
        xi = np.concatenate([rng.normal(scale=0.03, size=3), rng.normal(scale=0.05, size=3), [0.05]]) if n else np.zeros(7)
        values.insert(pose_key(n), T.retract(xi))
    graph = gtsam.NonlinearFactorGraph()
    graph.add(gtsam.PriorFactorSimilarity3(pose_key(0), truth[0], gtsam.noiseModel.Isotropic.Sigma(7, 1e-6)))
    problem = PoseBlockProblem([block], graph, values)
    report = levenberg_marquardt(problem, LMSettings(max_iterations=30, lambda_initial=1e-4, lambda_factor=10.0,
                                                     lambda_max=1e10, relative_tolerance=1e-10))
    assert report.final_cost < 0.1 * report.initial_cost
    for n in range(1, len(truth)):
        # relative to the fixed first keyframe, as X -> s R X + t (fgslam.core.lie.Sim3)
        rel_est = Sim3.from_gtsam(truth[0].inverse().compose(problem.values.atSimilarity3(pose_key(n))))
        rel_true = Sim3.from_gtsam(truth[0].inverse().compose(truth[n]))
        assert abs(float(rel_est.s) - 1.0) < 0.01
        assert rotation_angle_deg(rel_est.R.numpy().T @ rel_true.R.numpy()) < 0.1
        assert np.linalg.norm(rel_est.t.numpy() - rel_true.t.numpy()) < 0.005  # m
