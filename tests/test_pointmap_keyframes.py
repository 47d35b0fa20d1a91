"""Edges between two pointmap keyframes (fgslam.frontends.pointmap.keyframes.measure_edge): the loop,
relocalisation and mixed-family edges. From a perturbed relative pose the edge's refined pose reaches the
truth and its matches are true correspondences; from a wrong pose no edge is made."""

from __future__ import annotations

import numpy as np
import torch

from fgslam.factors.pointmap_block import PointmapBlockConfig
from fgslam.frontends.pointmap.config import PointmapGraphConfig, PointmapTrackingConfig
from fgslam.frontends.pointmap.keyframes import PointmapKeyframe, measure_edge
from fgslam.frontends.pointmap.matching import MatchingConfig
from fgslam.frontends.pointmap.descriptors import DescriptorConfig
from fgslam.frontends.pointmap.source import unproject_depth
from fgslam.core.lie import Sim3
from fgslam.core.so3 import so3_exp
from pointmap_support import render, room_sequence, rotation_angle_deg

I, J = 40, 50


def _keyframe(seq, view) -> PointmapKeyframe:
    H, W = view.depth.shape
    X = torch.from_numpy(unproject_depth(view.depth, seq.K).reshape(-1, 3).astype(np.float32))
    C = torch.from_numpy((view.depth > 0).reshape(-1).astype(np.float32))
    return PointmapKeyframe(view.index, float(view.index), view.index, H, W, X, C, view.image)


def _measure(a, b, T, K, fixed_scale=True):
    return measure_edge(a, b, T, K, PointmapBlockConfig(), PointmapTrackingConfig(), PointmapGraphConfig(), MatchingConfig(),
                        DescriptorConfig(), fixed_scale, query_stride=2)


def test_edge_from_a_perturbed_pose_reaches_the_truth():
    seq = room_sequence()
    vi, vj = render(seq, I), render(seq, J)
    a, b = _keyframe(seq, vi), _keyframe(seq, vj)
    T_true = np.linalg.inv(vi.T_WC) @ vj.T_WC
    T_guess = T_true.copy()
    T_guess[:3, :3] = so3_exp(torch.tensor([0.0, 0.01, 0.0], dtype=torch.float64)).numpy() @ T_guess[:3, :3]
    T_guess[:3, 3] += [0.02, -0.01, 0.0]
    meas = _measure(a, b, T_guess, seq.K)
    assert meas is not None and meas.num_inliers >= PointmapGraphConfig().min_edge_matches
    T = meas.T_CaCb.matrix().numpy()
    assert rotation_angle_deg(T[:3, :3].T @ T_true[:3, :3]) < 0.1
    assert np.linalg.norm(T[:3, 3] - T_true[:3, 3]) < 0.005  # m (from 2.2 cm and 0.6 degree off)
    e = meas.edge
    resid = Sim3.from_matrix(torch.as_tensor(T_true)).act(torch.as_tensor(e.X_j_in_j)) - torch.as_tensor(e.X_i_in_i)
    assert float(resid.norm(dim=-1).median()) < 0.02  # matched points agree under the true pose
    assert len(e.X_i_in_i) <= PointmapGraphConfig().max_edge_matches


def test_no_edge_from_a_wrong_pose():
    seq = room_sequence()
    vi, vj = render(seq, I), render(seq, J)
    a, b = _keyframe(seq, vi), _keyframe(seq, vj)
    T_wrong = np.linalg.inv(vi.T_WC) @ vj.T_WC
    T_wrong[:3, :3] = so3_exp(torch.tensor([0.0, np.pi / 2, 0.0], dtype=torch.float64)).numpy() @ T_wrong[:3, :3]
    assert _measure(a, b, T_wrong, seq.K) is None
