"""Tests of fgslam.factors.depth_align: the point-to-plane residual's Jacobian against finite differences,
the block's gradient against the finite differences of its cost, a texture-free room (two walls, a floor,
a ceiling) tracked by depth alone from a wrong start, a single plane reported as degenerate (three of six
directions), and bad input refused."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest

from fgslam.backend.keys import pose_key
from fgslam.backend.motion_only import optimize_pose
from fgslam.backend.solver import LMSettings
from fgslam.core.errors import ConfigError, DataError
from fgslam.core.lie import gtsam_matrix
from fgslam.factors.depth_align import DepthAlignBlock, DepthAlignConfig, DepthSurface, point_to_plane, relative_transform

SETTINGS = LMSettings(max_iterations=20, lambda_initial=1e-6, lambda_factor=10.0, lambda_max=1e8,
                      relative_tolerance=1e-10, damping="marquardt")
K = (260.0, 260.0, 159.5, 119.5)
SIZE = (240, 320)
ROOM = (-2.0, 2.5, -1.5, 1.8, 0.0, 2.6)  # x0, x1, y0, y1, z0 (floor), z1 (ceiling), metres


def render_depth(T_WC: np.ndarray, planes) -> np.ndarray:
    """z-depth of the nearest of ``planes`` (``(n_W, offset)``: ``n_W . X = offset``) seen from ``T_WC``."""
    h, w = SIZE
    fx, fy, cx, cy = K
    u, v = np.meshgrid(np.arange(w), np.arange(h))
    d_C = np.stack([(u - cx) / fx, (v - cy) / fy, np.ones_like(u, dtype=float)], -1)
    d_W = d_C @ T_WC[:3, :3].T
    o = T_WC[:3, 3]
    best = np.full(SIZE, np.inf)
    for n, off in planes:
        denom = d_W @ n
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (off - o @ n) / denom
        best = np.where((t > 1e-6) & (t < best), t, best)
    return np.where(np.isfinite(best), best, 0.0)


def room_planes():
    x0, x1, y0, y1, z0, z1 = ROOM
    e = np.eye(3)
    return [(e[0], x0), (e[0], x1), (e[1], y0), (e[1], y1), (e[2], z0), (e[2], z1)]


def camera(yaw: float, pitch: float, position) -> np.ndarray:
    """Camera looking along world x rotated by ``yaw`` about z, tilted down by ``pitch``."""
    R_look = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])  # optical z along world x, y down
    cz, sz, cp, sp = np.cos(yaw), np.sin(yaw), np.cos(pitch), np.sin(pitch)
    Rz = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
    Ry = np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
    T = np.eye(4)
    T[:3, :3] = Rz @ Ry @ R_look
    T[:3, 3] = position
    return T


def sim3(T: np.ndarray) -> gtsam.Similarity3:
    return gtsam.Similarity3(gtsam.Rot3(T[:3, :3]), T[:3, 3], 1.0)


def _pair(planes, T_k, T_f, config=None):
    config = config or DepthAlignConfig()
    ref = DepthSurface.from_depth(render_depth(T_k, planes), K, config)
    frm = DepthSurface.from_depth(render_depth(T_f, planes), K, config)
    return DepthAlignBlock(pose_key(0), pose_key(1), ref, frm, config)


def test_point_to_plane_jacobians_match_finite_differences():
    rng = np.random.default_rng(0)
    n = 40
    T_k = gtsam.Similarity3(gtsam.Rot3.Expmap(rng.normal(scale=0.3, size=3)), rng.normal(size=3), 1.3)
    T_f = gtsam.Similarity3(gtsam.Rot3.Expmap(rng.normal(scale=0.3, size=3)), rng.normal(size=3), 0.8)
    X_f = np.stack([rng.uniform(-1, 1, n), rng.uniform(-1, 1, n), rng.uniform(1, 3, n)], -1)
    A, b = relative_transform(gtsam_matrix(T_k), gtsam_matrix(T_f))
    X_k = X_f @ A.T + b + rng.normal(scale=0.05, size=(n, 3))
    normals = rng.normal(size=(n, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)

    def residual(Tk, Tf):
        A, b = relative_transform(gtsam_matrix(Tk), gtsam_matrix(Tf))
        return point_to_plane(A, X_f, X_f @ A.T + b, X_k, normals, jacobians=False)[0]

    r, J_k, J_f = point_to_plane(A, X_f, X_f @ A.T + b, X_k, normals)
    # the relative transform of two Sim(3) poses against gtsam's own composition
    T_kf = T_k.inverse().compose(T_f)
    assert np.allclose(X_f @ A.T + b, np.array([T_kf.transformFrom(x) for x in X_f]))
    eps = 1e-6
    for a in range(7):
        d = np.zeros(7)
        d[a] = eps
        fd_f = (residual(T_k, T_f.retract(d)) - residual(T_k, T_f.retract(-d))) / (2 * eps)
        fd_k = (residual(T_k.retract(d), T_f) - residual(T_k.retract(-d), T_f)) / (2 * eps)
        assert np.allclose(J_f[:, a], fd_f, atol=1e-6), a
        assert np.allclose(J_k[:, a], fd_k, atol=1e-6), a


def test_block_gradient_is_the_gradient_of_its_cost():
    planes = room_planes()
    T_k = camera(0.4, 0.3, [0.2, 0.1, 1.4])
    T_f = camera(0.45, 0.32, [0.25, 0.08, 1.42])
    block = _pair(planes, T_k, T_f)
    values = gtsam.Values()
    values.insert(pose_key(0), sim3(T_k))
    values.insert(pose_key(1), sim3(T_f).retract(np.array([0.004, -0.003, 0.002, 0.004, 0.003, -0.002, 0.0])))
    (piece,) = block.linearize(values)
    assert piece.keys == (pose_key(0), pose_key(1))
    assert piece.c == pytest.approx(2 * block.cost(values))
    eps = 1e-7
    for a in range(6):  # rotation and translation of the frame (the scale does not move a metric pair here)
        d = np.zeros(7)
        d[a] = eps
        vp, vm = gtsam.Values(values), gtsam.Values(values)
        vp.update(pose_key(1), values.atSimilarity3(pose_key(1)).retract(d))
        vm.update(pose_key(1), values.atSimilarity3(pose_key(1)).retract(-d))
        fd = (block.cost(vp) - block.cost(vm)) / (2 * eps)
        assert fd == pytest.approx(piece.g[7 + a], rel=1e-3, abs=1e-3 * np.abs(piece.g).max()), a


def test_a_linearisation_at_the_poses_of_the_last_cost_reuses_its_association(monkeypatch):
    """The window's LM takes a cost, then linearises at the same poses: the association runs once for
    both, and the linearisation is the one a fresh block gives there; other poses associate again."""
    import fgslam.factors.depth_align_jit as jit

    planes = room_planes()
    T_k = camera(0.4, 0.3, [0.2, 0.1, 1.4])
    T_f = camera(0.45, 0.32, [0.25, 0.08, 1.42])
    values = gtsam.Values()
    values.insert(pose_key(0), sim3(T_k))
    values.insert(pose_key(1), sim3(T_f).retract(np.array([0.004, -0.003, 0.002, 0.004, 0.003, -0.002, 0.0])))
    (fresh,) = _pair(planes, T_k, T_f).linearize(values)
    calls, associate = [], jit.associate_rows
    monkeypatch.setattr(jit, "associate_rows", lambda *a: calls.append(1) or associate(*a))
    block = _pair(planes, T_k, T_f)
    cost = block.cost(values)
    (piece,) = block.linearize(values)
    assert len(calls) == 1 and piece.c == pytest.approx(2 * cost)
    assert np.array_equal(piece.H, fresh.H) and np.array_equal(piece.g, fresh.g)
    moved = gtsam.Values(values)
    moved.update(pose_key(1), values.atSimilarity3(pose_key(1)).retract(np.full(7, 1e-4) * [1, 1, 1, 1, 1, 1, 0]))
    block.linearize(moved)
    assert len(calls) == 2


def test_texture_free_room_is_tracked_by_depth_alone():
    planes = room_planes()
    T_k = camera(0.5, 0.35, [0.0, 0.0, 1.5])
    T_f = camera(0.62, 0.30, [0.12, -0.05, 1.48])  # 7 deg of yaw, 12 cm
    block = _pair(planes, T_k, T_f)
    values = gtsam.Values()
    values.insert(pose_key(0), sim3(T_k))
    values.insert(pose_key(1), sim3(T_k))  # start at the reference: the whole motion is unknown
    hold = np.array([0, 0, 0, 0, 0, 0, np.inf])  # metric depth: rigid
    for level in range(len(block.reference.levels)):
        values = optimize_pose([block.at_level(level)], values, pose_key(1), SETTINGS, hold=hold).values
    got = values.atSimilarity3(pose_key(1))
    assert np.linalg.norm(got.translation() - T_f[:3, 3]) < 2e-3
    dR = got.rotation().matrix().T @ T_f[:3, :3]
    assert np.degrees(np.arccos(np.clip((np.trace(dR) - 1) / 2, -1, 1))) < 0.1
    c = block.constraint(values)
    assert c.ok and c.directions == 6


def test_single_plane_is_reported_degenerate():
    wall = [(np.array([1.0, 0.0, 0.0]), 2.0)]  # the camera faces one wall and sees nothing else
    T_k = camera(0.0, 0.0, [0.5, 0.0, 1.2])
    T_f = camera(0.05, 0.02, [0.55, 0.02, 1.21])
    block = _pair(wall, T_k, T_f)
    values = gtsam.Values()
    values.insert(pose_key(0), sim3(T_k))
    values.insert(pose_key(1), sim3(T_f))
    c = block.constraint(values)
    assert c.pairs >= block.config.min_pairs
    assert c.directions == 3 and not c.ok
    room = _pair(room_planes(), camera(0.6, 0.4, [0.0, 0.0, 1.5]), camera(0.62, 0.4, [0.01, 0.0, 1.5]))
    values.update(pose_key(0), sim3(camera(0.6, 0.4, [0.0, 0.0, 1.5])))
    values.update(pose_key(1), sim3(camera(0.62, 0.4, [0.01, 0.0, 1.5])))
    assert room.constraint(values).directions == 6


def test_missing_depth_gives_no_pairs_and_bad_input_is_refused():
    config = DepthAlignConfig()
    empty = DepthSurface.from_depth(np.full(SIZE, np.nan), K, config)
    full = DepthSurface.from_depth(render_depth(camera(0.5, 0.3, [0, 0, 1.5]), room_planes()), K, config)
    block = DepthAlignBlock(pose_key(0), pose_key(1), full, empty, config)
    values = gtsam.Values()
    values.insert(pose_key(0), sim3(camera(0.5, 0.3, [0, 0, 1.5])))
    values.insert(pose_key(1), sim3(camera(0.5, 0.3, [0, 0, 1.5])))
    assert block.num_points == 0
    assert block.cost(values) == 0.0
    assert not block.constraint(values).ok
    with pytest.raises(DataError, match="2-D"):
        DepthSurface.from_depth(np.zeros((4, 4, 3)), K, config)
    with pytest.raises(DataError, match="itself"):
        DepthAlignBlock(pose_key(0), pose_key(0), full, full, config)
    with pytest.raises(ConfigError, match="max_depth"):
        DepthAlignConfig(min_depth=2.0, max_depth=1.0).validate()
    assert DepthAlignConfig(grid_width=80, levels=3).strides(640) == (32, 16, 8)
