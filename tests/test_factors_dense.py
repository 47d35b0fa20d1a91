"""Tests of fgslam.factors.dense: the dense (DROID-SLAM) bundle-adjustment block."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest
import torch

from dense_support import gauge_graph, solve
from fgslam.factors.blocks import Block, LinearPiece, StructureBlock
from fgslam.backend.keys import pose_key
from fgslam.factors.dense import DenseBlock, DenseBlockConfig, DenseEdge, DenseKeyframe, DenseSourceBlock, pixel_grid
from fgslam.factors.depth import DepthPriorConfig
from fgslam.factors.reprojection import reproject
from fgslam.factors.schur import POSE_DIM
from fgslam.factors.visual_block import BlockConfig
from fgslam.core.lie import Sim3

D = POSE_DIM
H_MAP, W_MAP = 6, 8  # a 1/8-resolution map of a 64 x 48 image
K8 = torch.tensor([7.0, 7.0, 3.5, 2.5], dtype=torch.float64)


def _pose(w, t, s=1.0) -> Sim3:
    return Sim3.exp(torch.tensor([*w, 0.0, 0.0, 0.0, 0.0], dtype=torch.float64)) @ Sim3(
        torch.eye(3, dtype=torch.float64), torch.tensor(t, dtype=torch.float64), torch.tensor(s, dtype=torch.float64))


def scene(n_kf=3, h=H_MAP, w=W_MAP, seed=0):
    """Ground-truth poses (camera-to-world, metric) and smooth inverse-depth maps of ``n_kf`` keyframes."""
    rng = np.random.default_rng(seed)
    poses = [_pose([0, 0, 0], [0, 0, 0])] + [
        _pose(rng.normal(0, 0.04, 3), [0.25 * k, 0.05 * rng.normal(), 0.1 * rng.normal()]) for k in range(1, n_kf)]
    yy, xx = np.meshgrid(np.arange(h), np.arange(w), indexing="ij")
    depths = []
    for k in range(n_kf):
        z = 2.5 + 0.08 * xx - 0.05 * yy + 0.3 * np.sin(0.9 * xx + k) * np.cos(0.7 * yy)
        depths.append(torch.as_tensor(1.0 / z, dtype=torch.float64))
    return poses, depths


def exact_edges(poses, depths, pairs, keys, weight_seed=None):
    """Edges whose targets p*_ij are the exact reprojections (noiseless measurements)."""
    h, w = depths[0].shape
    grid = pixel_grid(h, w)
    g = np.random.default_rng(weight_seed) if weight_seed is not None else None
    edges = []
    for i, j in pairs:
        uv, ok = reproject(grid, depths[i].reshape(-1), poses[i], poses[j], K8)
        assert bool(ok.all())
        wt = np.ones((h, w, 2)) if g is None else g.uniform(0.2, 1.5, (h, w, 2))
        edges.append(DenseEdge(keys[i], keys[j], uv.reshape(h, w, 2), wt))
    return edges


def values_of(poses, keys):
    values = gtsam.Values()
    for key, T in zip(keys, poses):
        values.insert(key, T.to_gtsam())
    return values


ALL_PAIRS = [(0, 1), (1, 0), (0, 2), (2, 0), (1, 2), (2, 1)]


# ------------------------------------------------------------------------------ Jacobians


def test_row_jacobians_match_finite_differences_flow_and_depth_prior():
    poses, depths = scene()
    keys = [pose_key(k) for k in range(3)]
    rng = np.random.default_rng(1)
    edges = exact_edges(poses, depths, [(0, 1), (0, 2)], keys)
    for e in edges:  # measurements off the current estimate: non-zero residuals
        e.uv_target = e.uv_target + torch.as_tensor(rng.normal(0, 0.5, e.uv_target.shape))
    sensor = 1.0 / depths[0] * (1 + 0.03 * torch.as_tensor(rng.normal(size=depths[0].shape)))
    sensor[0, :3] = 0.0  # holes: no prior rows there
    block = DenseSourceBlock(DenseKeyframe(keys[0], depths[0], sensor_depth=sensor), edges, K8)
    assert len(block.struct_idx) == 2 * H_MAP * W_MAP + H_MAP * W_MAP - 3
    T = Sim3(torch.stack([p.R for p in poses]), torch.stack([p.t for p in poses]), torch.stack([p.s for p in poses]))
    T = T.retract(torch.as_tensor(rng.normal(0, 0.01, (3, 7))))  # off the ground truth
    d = block.structure * (1 + 0.05 * torch.as_tensor(rng.normal(size=block.num_structs)))
    res = block.evaluate(T, d, jacobians=True)
    assert int(res.weights[:, 0].gt(0).sum()) == len(block.struct_idx)  # every row valid
    eps = 1e-6
    for slot in range(3):
        for a in range(D):
            xi = torch.zeros(3, 7, dtype=torch.float64)
            xi[slot, a] = eps
            rp = block.evaluate(T.retract(xi), d, jacobians=False).r
            rm = block.evaluate(T.retract(-xi), d, jacobians=False).r
            fd = (rp - rm) / (2 * eps)
            analytic = sum(torch.where((block.slots[:, c] == slot)[:, None], res.J[c][..., a], torch.zeros(()))
                           for c in range(2))
            if slot == 0:  # the prior rows sit at slots (0, 0) with zero pose Jacobian: count them once
                analytic = torch.where((block.slots == 0).all(1)[:, None], res.J[0][..., a], analytic)
            np.testing.assert_allclose(analytic.numpy(), fd.numpy(), atol=1e-6, rtol=1e-5)
    # structure: each row depends on its own pixel's inverse depth only
    for p in (0, 5, 17, 40):
        dp = d.clone()
        dm = d.clone()
        dp[p] += eps
        dm[p] -= eps
        fd = (block.evaluate(T, dp, jacobians=False).r - block.evaluate(T, dm, jacobians=False).r) / (2 * eps)
        rows = block.struct_idx == p
        np.testing.assert_allclose(res.E[rows].numpy(), fd[rows].numpy(), atol=1e-6, rtol=1e-5)
        np.testing.assert_allclose(fd[~rows].numpy(), 0.0, atol=1e-9)
    prior_rows = (block.slots == 0).all(1)
    assert int(prior_rows.sum()) == H_MAP * W_MAP - 3
    np.testing.assert_allclose(res.E[prior_rows, 0].numpy(), 1.0)


# ------------------------------------------------------------------------------ Schur complement


def explicit_system(block, values, eta):
    """Dense joint normal equations over (poses of block.keys, all depths), eliminated explicitly."""
    T = block.poses_from_values(values)
    res = block.evaluate(T, block.structure, jacobians=True)
    n, m = res.r.shape
    k, P = len(block.keys), block.num_structs
    A_x = np.zeros((n * m, k * D))
    A_d = np.zeros((n * m, P))
    for row in range(n):
        for a in range(m):
            for c in range(2):
                s = int(block.slots[row, c])
                if c == 1 and s == int(block.slots[row, 0]) and bool(res.J[1][row].eq(0).all()):
                    continue  # prior rows: one zero Jacobian at slots (0, 0)
                A_x[row * m + a, s * D:(s + 1) * D] += res.J[c][row, a].numpy()
            A_d[row * m + a, int(block.struct_idx[row])] = res.E[row, a]
    W = np.diag(res.weights.reshape(-1).numpy())
    r = res.r.reshape(-1).numpy()
    Hxx, Hxd, Hdd = A_x.T @ W @ A_x, A_x.T @ W @ A_d, A_d.T @ W @ A_d + np.diag(eta)
    gx, gd, c = A_x.T @ W @ r, A_d.T @ W @ r, r @ W @ r
    inv = np.linalg.inv(Hdd)
    return Hxx - Hxd @ inv @ Hxd.T, gx - Hxd @ inv @ gd, c - gd @ inv @ gd, (Hxd, Hdd, gd)


def test_schur_reduced_system_equals_explicit_elimination_with_per_pixel_damping():
    poses, depths = scene()
    keys = [pose_key(k) for k in range(3)]
    rng = np.random.default_rng(2)
    edges = exact_edges(poses, depths, [(1, 0), (1, 2)], keys, weight_seed=3)
    for e in edges:
        e.uv_target = e.uv_target + torch.as_tensor(rng.normal(0, 0.3, e.uv_target.shape))
    eta = rng.uniform(0.01, 2.0, (H_MAP, W_MAP))
    sensor = 1.0 / depths[1] * 1.02
    # a weak prior (weight 1/16, like a unit-weight pixel's share) so that the per-pixel damping shows
    weak = DepthPriorConfig(sigma=4.0, noise="inverse")
    block = DenseSourceBlock(DenseKeyframe(keys[1], depths[1] * 1.1, sensor_depth=sensor, damping=eta), edges, K8,
                             DenseBlockConfig(depth_prior=weak))
    assert block.keys == (keys[1], keys[0], keys[2])
    noisy = [p.retract(torch.as_tensor(rng.normal(0, 0.01, 7))) for p in poses]
    values = values_of(noisy, keys)
    (piece,) = block.linearize(values)
    assert isinstance(piece, LinearPiece) and piece.keys == block.keys
    H, g, c, (Hxd, Hdd, gd) = explicit_system(block, values, eta.reshape(-1))
    scale = np.abs(H).max()
    np.testing.assert_allclose(piece.H, H, atol=1e-9 * scale)
    np.testing.assert_allclose(piece.g, g, atol=1e-9 * np.abs(g).max())
    assert piece.c == pytest.approx(c, rel=1e-9)
    # back-substitution = the explicit minimiser of the joint quadratic over the depths
    dx = rng.normal(0, 0.01, 3 * D)
    dd = -np.linalg.solve(Hdd, gd + Hxd.T @ dx)
    delta = gtsam.VectorValues()
    for n, key in enumerate(block.keys):
        delta.insert(key, dx[n * D:(n + 1) * D])
    np.testing.assert_allclose(block.back_substitute(delta).numpy(), dd, rtol=1e-8, atol=1e-12)
    # a key missing from the update is held fixed (window solves): the same as a zero update
    partial = gtsam.VectorValues()
    partial.insert(block.keys[0], dx[:D])
    dx_fixed = np.concatenate([dx[:D], np.zeros(2 * D)])
    np.testing.assert_allclose(block.back_substitute(partial).numpy(),
                               -np.linalg.solve(Hdd, gd + Hxd.T @ dx_fixed), rtol=1e-8, atol=1e-12)
    # the damping really is per pixel: a constant eta gives another system
    flat = DenseSourceBlock(DenseKeyframe(keys[1], depths[1] * 1.1, sensor_depth=sensor), edges, K8,
                            DenseBlockConfig(block=BlockConfig(structure_damping=float(eta.mean())), depth_prior=weak))
    assert np.abs(flat.linearize(values)[0].H - piece.H).max() > 1e-6 * scale


def test_dense_block_damped_linearisation_damps_every_source_and_its_back_substitution():
    """``DenseBlock.linearize_damped(lam)`` (the backend's LM damping of the depths): each source's system
    eliminated again with ``lam`` on every pixel's information, merged as ``linearize`` merges; the
    back-substitution then follows the damped system, whose depth steps shrink as ``lam`` grows."""
    poses, depths = scene()
    keys = [pose_key(k) for k in (4, 7, 9)]
    edges = exact_edges(poses, depths, ALL_PAIRS, keys, weight_seed=6)
    kfs = [DenseKeyframe(keys[k], depths[k] * 1.05) for k in range(3)]
    merged = DenseBlock(kfs, edges, K8, DenseBlockConfig(pieces="merged"))
    values = values_of(poses, keys)
    (plain,) = merged.linearize(values)
    delta = np.random.default_rng(6).standard_normal(3 * D) * 1e-3
    step0 = merged.back_substitute(delta).abs().max()
    (tiny,) = merged.linearize_damped(1e-12)
    np.testing.assert_allclose(tiny.H, plain.H, rtol=1e-9, atol=1e-9 * np.abs(plain.H).max())
    sizes = []
    for lam in (1.0, 1e3, 1e6):
        (damped,) = merged.linearize_damped(lam)
        assert np.abs(damped.H - plain.H).max() > 1e-9 * np.abs(plain.H).max()
        # the same as a block whose own damping is lam on every pixel
        (direct,) = DenseBlock(kfs, edges, K8, DenseBlockConfig(pieces="merged", block=BlockConfig(structure_damping=lam))
                               ).linearize(values)
        np.testing.assert_allclose(damped.H, direct.H, rtol=1e-10, atol=1e-12 * np.abs(direct.H).max())
        np.testing.assert_allclose(damped.g, direct.g, rtol=1e-10, atol=1e-12 * np.abs(direct.g).max())
        sizes.append(float(merged.back_substitute(delta).abs().max()))
    assert step0 > sizes[0] > sizes[1] > sizes[2]


def test_dense_block_pieces_per_source_sum_to_merged_and_structure_round_trips():
    poses, depths = scene()
    keys = [pose_key(k) for k in (4, 7, 9)]
    edges = exact_edges(poses, depths, ALL_PAIRS, keys, weight_seed=5)
    kfs = [DenseKeyframe(keys[k], depths[k] * 1.05) for k in range(3)]
    per_source = DenseBlock(kfs, edges, K8)
    merged = DenseBlock(kfs, edges, K8, DenseBlockConfig(pieces="merged"))
    assert isinstance(per_source, Block) and isinstance(per_source, StructureBlock)
    values = values_of(poses, keys)
    pieces = per_source.linearize(values)
    assert [p.keys[0] for p in pieces] == keys and all(len(p.keys) == 3 for p in pieces)
    (one,) = merged.linearize(values)
    assert one.keys == tuple(keys)
    H = np.zeros_like(one.H)
    g = np.zeros_like(one.g)
    for p in pieces:
        cols = np.concatenate([np.arange(keys.index(k) * D, keys.index(k) * D + D) for k in p.keys])
        H[np.ix_(cols, cols)] += p.H
        g[cols] += p.g
    np.testing.assert_allclose(one.H, H, atol=1e-9 * np.abs(H).max())
    np.testing.assert_allclose(one.g, g, atol=1e-9 * np.abs(g).max())
    assert one.c == pytest.approx(sum(p.c for p in pieces), rel=1e-12)
    # c is the cost minimised over the depths of the linearised model: below the cost at the current depths
    assert 0.0 <= 0.5 * one.c < 0.01 * merged.cost(values)
    s = per_source.structure
    assert s.shape == (3 * H_MAP * W_MAP,)
    per_source.set_structure(2 * s)
    np.testing.assert_allclose(per_source.source(keys[1]).inverse_depth.numpy(), 2 * depths[1].numpy() * 1.05)
    assert per_source.cost(values, s) == pytest.approx(merged.cost(values), rel=1e-12)
    # at the true poses, per-pixel Gauss-Newton on the depths alone recovers the true maps
    assert merged.refine_structure(values, steps=8) < 1e-16
    for k, key in enumerate(keys):
        np.testing.assert_allclose(merged.source(key).inverse_depth.numpy(), depths[k].numpy(), rtol=1e-9)


def test_bad_edges_and_maps_are_refused():
    poses, depths = scene()
    keys = [pose_key(k) for k in range(3)]
    edges = exact_edges(poses, depths, [(0, 1)], keys)
    with pytest.raises(ValueError, match="does not start"):
        DenseSourceBlock(DenseKeyframe(keys[1], depths[1]), edges, K8)
    with pytest.raises(ValueError, match="do not match"):
        DenseSourceBlock(DenseKeyframe(keys[0], depths[0][:-1]), edges, K8)
    with pytest.raises(ValueError, match="without a source"):
        DenseBlock([DenseKeyframe(keys[1], depths[1])], edges, K8)
    with pytest.raises(ValueError, match="damping"):
        DenseSourceBlock(DenseKeyframe(keys[0], depths[0], damping=-np.ones((H_MAP, W_MAP))), edges, K8)
    # a non-finite target is no measurement (zero weight), not a NaN in the system
    edges[0].uv_target = edges[0].uv_target.clone()
    edges[0].uv_target[2, 3] = float("nan")
    block = DenseSourceBlock(DenseKeyframe(keys[0], depths[0]), edges, K8)
    (piece,) = block.linearize(values_of(poses, keys))
    assert np.isfinite(piece.H).all() and piece.c == pytest.approx(0.0, abs=1e-18)


# ------------------------------------------------------------------------------ LM to the ground truth


def perturbed(poses, depths, seed):
    rng = np.random.default_rng(seed)
    noisy = [poses[0]] + [p.retract(torch.as_tensor(np.r_[rng.normal(0, 0.03, 3), rng.normal(0, 0.05, 3), 0.0]))
                          for p in poses[1:]]
    maps = [d * torch.as_tensor(rng.uniform(0.85, 1.15, d.shape)) for d in depths]
    return noisy, maps


def test_lm_reaches_ground_truth_rgbd_three_keyframes():
    """Noiseless RGB-D: the sensor depth fixes the metric scale, so LM from perturbed poses (3 degrees,
    5 cm) and depths (15 %) through the backend's solver reaches poses and depths exactly."""
    poses, depths = scene()
    keys = [pose_key(k) for k in range(3)]
    edges = exact_edges(poses, depths, ALL_PAIRS, keys, weight_seed=7)
    noisy, maps = perturbed(poses, depths, 8)
    kfs = [DenseKeyframe(keys[k], maps[k], sensor_depth=1.0 / depths[k]) for k in range(3)]
    block = DenseBlock(kfs, edges, K8, DenseBlockConfig(depth_prior=DepthPriorConfig(sigma=1.0, noise="inverse")))
    start_scale = [p.s for p in noisy]
    problem, report = solve(block, gauge_graph(noisy, keys), values_of(noisy, keys))
    assert report.initial_cost > 1.0 and report.final_cost < 1e-12, report
    for k, key in enumerate(keys):
        est = Sim3.from_gtsam(problem.values.atSimilarity3(key))
        np.testing.assert_allclose(est.R.numpy(), poses[k].R.numpy(), atol=1e-6)
        np.testing.assert_allclose(est.t.numpy(), poses[k].t.numpy(), atol=1e-6)
        assert float(est.s) == pytest.approx(float(start_scale[k]), abs=1e-9)
        np.testing.assert_allclose(block.source(key).inverse_depth.numpy(), depths[k].numpy(), rtol=1e-6)


def test_lm_reaches_ground_truth_monocular_up_to_scale():
    """Noiseless monocular: two keyframes' edges both ways, world scale free (a gauge): the optimum is the
    ground truth times one scale factor (translations x a, inverse depths / a), reached by LM."""
    poses, depths = scene(n_kf=2, h=8, w=10, seed=3)
    keys = [pose_key(k) for k in range(2)]
    edges = exact_edges(poses, depths, [(0, 1), (1, 0)], keys)
    noisy, maps = perturbed(poses, depths, 4)
    block = DenseBlock([DenseKeyframe(keys[k], maps[k]) for k in range(2)], edges, K8)
    problem, report = solve(block, gauge_graph(noisy, keys), values_of(noisy, keys))
    assert report.initial_cost > 1.0 and report.final_cost < 1e-12, report
    est = [Sim3.from_gtsam(problem.values.atSimilarity3(key)) for key in keys]
    a = float(torch.linalg.norm(est[1].t) / torch.linalg.norm(poses[1].t))
    assert 0.5 < a < 2.0
    for k in range(2):
        np.testing.assert_allclose(est[k].R.numpy(), poses[k].R.numpy(), atol=1e-6)
        np.testing.assert_allclose(est[k].t.numpy(), a * poses[k].t.numpy(), atol=1e-6)
        np.testing.assert_allclose(block.source(keys[k]).inverse_depth.numpy(), depths[k].numpy() / a, rtol=1e-6)


# ------------------------------------------------------------------------------ stereo rows


def test_stereo_rows_depend_on_depth_only_and_match_finite_differences():
    """Left-right rows of a stereo keyframe (calibrated T_CRCL fixed in the factor): zero pose
    Jacobians, depth Jacobians equal to finite differences, zero residual at the true depths, and the
    rows alone recover a wrong depth map at fixed poses (metric depth from the baseline)."""
    from fgslam.factors.dense import DenseStereo

    poses, depths = scene()
    keys = [pose_key(k) for k in range(3)]
    T_CRCL = np.eye(4)
    T_CRCL[0, 3] = -0.3  # right camera 0.3 m to the right of the left one
    grid = pixel_grid(H_MAP, W_MAP)
    I = (torch.eye(3, dtype=torch.float64), torch.zeros(3, dtype=torch.float64), torch.ones((), dtype=torch.float64))
    uv_r, ok = reproject(grid, depths[0].reshape(-1), I, I, K8, K8, T_CtCj=torch.as_tensor(T_CRCL))
    assert bool(ok.all())
    stereo = DenseStereo(uv_r.reshape(H_MAP, W_MAP, 2), np.ones((H_MAP, W_MAP, 2)), K8, T_CRCL)
    edges = exact_edges(poses, depths, [(0, 1)], keys)
    block = DenseSourceBlock(DenseKeyframe(keys[0], depths[0], stereo=stereo), edges, K8)
    n_pix = H_MAP * W_MAP
    assert len(block.struct_idx) == 2 * n_pix
    T = Sim3(torch.stack([p.R for p in poses[:2]]), torch.stack([p.t for p in poses[:2]]),
             torch.stack([p.s for p in poses[:2]]))
    res = block.evaluate(T, block.structure, jacobians=True)
    stereo_rows = torch.arange(len(block.struct_idx)) >= n_pix
    np.testing.assert_allclose(res.r[stereo_rows].numpy(), 0.0, atol=1e-9)
    for J in res.J:
        np.testing.assert_allclose(J[stereo_rows].numpy(), 0.0)
    rng = np.random.default_rng(3)
    d = block.structure * (1 + 0.1 * torch.as_tensor(rng.normal(size=n_pix)))
    res = block.evaluate(T, d, jacobians=True)
    eps = 1e-7
    for p in (0, 9, 30):
        dp, dm = d.clone(), d.clone()
        dp[p] += eps
        dm[p] -= eps
        fd = (block.evaluate(T, dp, jacobians=False).r - block.evaluate(T, dm, jacobians=False).r) / (2 * eps)
        rows = (block.struct_idx == p) & stereo_rows
        assert int(rows.sum()) == 1
        np.testing.assert_allclose(res.E[rows].numpy(), fd[rows].numpy(), rtol=1e-5, atol=1e-8)
        assert abs(float(res.E[rows, 0])) > 0  # the disparity observes the depth
    # stereo rows alone (no flow edge): a 20 %-off map goes back to the truth at fixed poses
    only = DenseSourceBlock(DenseKeyframe(keys[0], depths[0] * 1.2, stereo=stereo), [], K8)
    values = values_of(poses[:1], keys[:1])
    only.refine_structure(values, steps=8)
    np.testing.assert_allclose(only.inverse_depth.numpy(), depths[0].numpy(), rtol=1e-6)


def test_zero_weight_rows_are_left_out_with_the_same_linear_system():
    """Pixels of zero weight on both axes are not rows of the block (they add nothing): the reduced
    system, the cost and the structure step equal those of the block that keeps them with a weight
    too small to count."""
    poses, depths = scene()
    keys = [pose_key(k) for k in range(3)]
    edges = exact_edges(poses, depths, [(0, 1), (0, 2)], keys, weight_seed=3)
    rng = np.random.default_rng(4)
    noisy = [DenseEdge(e.source, e.target, np.asarray(e.uv_target) + rng.normal(0, 0.3, (H_MAP, W_MAP, 2)), e.weight)
             for e in edges]
    zero = rng.uniform(size=(2, H_MAP, W_MAP)) < 0.4
    dropped = [DenseEdge(e.source, e.target, e.uv_target, np.where(z[..., None], 0.0, e.weight))
               for e, z in zip(noisy, zero)]
    tiny = [DenseEdge(e.source, e.target, e.uv_target, np.where(z[..., None], 1e-300, e.weight))
            for e, z in zip(noisy, zero)]
    init = depths[0] * 1.1
    a = DenseSourceBlock(DenseKeyframe(keys[0], init), dropped, K8)
    b = DenseSourceBlock(DenseKeyframe(keys[0], init), tiny, K8)
    assert a._flow.uv_source.shape[0] == int((~zero).sum()) < b._flow.uv_source.shape[0] == 2 * H_MAP * W_MAP
    values = values_of(poses, keys)
    (pa,), (pb,) = a.linearize(values), b.linearize(values)
    np.testing.assert_allclose(pa.H, pb.H, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(pa.g, pb.g, rtol=1e-10, atol=1e-12)
    assert pa.c == pytest.approx(pb.c, rel=1e-12)
    assert a.cost(values) == pytest.approx(b.cost(values), rel=1e-12)
    delta = np.random.default_rng(5).normal(0, 1e-3, 7 * len(a.keys))
    np.testing.assert_allclose(a.back_substitute(delta).numpy(), b.back_substitute(delta).numpy(), rtol=1e-9, atol=1e-12)
    # new measurements of the same edges (set_edges) choose their own rows
    a.set_edges(noisy)
    assert a._flow.uv_source.shape[0] == 2 * H_MAP * W_MAP
