"""Tests of fgslam.map: Schur-compressed blocks reach the explicit joint optimum with every solver,
gauge handling, marginals and map bookkeeping."""

import gtsam
import numpy as np
import pytest
import torch

from fgslam.errors import OptimizationError
from fgslam.factors.reprojection import reproject
from fgslam.factors.schur import POSE_DIM, BlockConfig, InverseDepthBlock
from fgslam.lie import Sim3
from fgslam.map import GaugeConfig, MapConfig, SlamMap, pose_key

D = POSE_DIM
NUM_KF = 5
POINTS_PER_KF = 50
K = torch.tensor([320.0, 320.0, 320.0, 240.0], dtype=torch.float64)
WIDTH, HEIGHT = 640, 480


def make_scene(seed: int, noise_px: float):
    """5 keyframes moving sideways, 50 points hosted per keyframe, observed in all other keyframes.

    Returns true poses (Sim3, (5,)), initial (perturbed) poses, and per-host measurement dicts with
    true and perturbed inverse depths.
    """
    g = torch.Generator().manual_seed(seed)
    dtype = torch.float64
    xi = torch.zeros(NUM_KF, 7, dtype=dtype)
    xi[:, 3] = torch.arange(NUM_KF, dtype=dtype) * 0.25  # baseline along x
    xi[:, :3] = 0.05 * (torch.rand(NUM_KF, 3, generator=g, dtype=dtype) - 0.5)
    xi[:, 6] = 0.2 * (torch.rand(NUM_KF, generator=g, dtype=dtype) - 0.5)  # arbitrary per-keyframe scales
    xi[0] = 0.0
    T_true = Sim3.exp(xi)
    perturb = torch.zeros(NUM_KF, 7, dtype=dtype)
    perturb[1:, :3] = 0.02 * (torch.rand(NUM_KF - 1, 3, generator=g, dtype=dtype) - 0.5)
    perturb[1:, 3:6] = 0.05 * (torch.rand(NUM_KF - 1, 3, generator=g, dtype=dtype) - 0.5)
    perturb[1:, 6] = 0.05 * (torch.rand(NUM_KF - 1, generator=g, dtype=dtype) - 0.5)
    T_init = T_true.retract(perturb)
    hosts = []
    for h in range(NUM_KF):
        uv = torch.rand(POINTS_PER_KF, 2, generator=g, dtype=dtype) * torch.tensor([WIDTH, HEIGHT], dtype=dtype)
        d_true = 1.0 / (3.0 + 3.0 * torch.rand(POINTS_PER_KF, generator=g, dtype=dtype)) / T_true.s[h]
        src, tgt, uvs, uvt, idx = [], [], [], [], []
        for j in range(NUM_KF):
            if j == h:
                continue
            uv_j, ok = reproject(uv, d_true, T_true[h], T_true[j], K)
            ok = ok & (uv_j[:, 0] >= 0) & (uv_j[:, 0] < WIDTH) & (uv_j[:, 1] >= 0) & (uv_j[:, 1] < HEIGHT)
            n = int(ok.sum())
            uvt.append(uv_j[ok] + noise_px * torch.randn(n, 2, generator=g, dtype=dtype))
            uvs.append(uv[ok])
            idx.append(torch.arange(POINTS_PER_KF)[ok])
            src.append(torch.full((n,), h))
            tgt.append(torch.full((n,), j))
        n_total = sum(len(t) for t in tgt)
        weights = 0.5 + torch.rand(n_total, 2, generator=g, dtype=dtype)
        d_init = d_true * (1.0 + 0.2 * (torch.rand(POINTS_PER_KF, generator=g, dtype=dtype) - 0.5))
        hosts.append(dict(src=torch.cat(src), tgt=torch.cat(tgt), uvs=torch.cat(uvs), uvt=torch.cat(uvt),
                          idx=torch.cat(idx), w=weights, d_true=d_true, d_init=d_init))
    return T_true, T_init, hosts


def build_map(scene, config: MapConfig, reverse_keys: bool = False) -> SlamMap:
    """One block per host keyframe over all 5 keys (slot = keyframe, or 4 - keyframe when reversed)."""
    _, T_init, hosts = scene
    smap = SlamMap(config)
    for kf in range(NUM_KF):
        smap.add_keyframe(kf, T_init[kf])
    order = list(range(NUM_KF))[::-1] if reverse_keys else list(range(NUM_KF))
    keys = [pose_key(kf) for kf in order]
    slot_of = torch.tensor([order.index(kf) for kf in range(NUM_KF)])
    for host in hosts:
        smap.add_block(InverseDepthBlock(keys, slot_of[host["src"]], slot_of[host["tgt"]], host["uvs"], host["uvt"],
                                         host["idx"], host["w"], K, host["d_init"].clone(), BlockConfig(refine_steps=1)))
    return smap


def explicit_joint_lm(smap: SlamMap, iterations: int = 60):
    """Reference: dense LM on the explicit joint problem, poses AND inverse depths as variables.

    One dense Jacobian over [all pose tangents | all inverse depths] per iteration (no Schur
    complement anywhere); the gauge factors are the map's own (linearised by gtsam).
    Returns (values, depths per block).
    """
    graph = smap.nonlinear_graph()
    blocks = list(smap.blocks.values())
    kf_keys = [pose_key(kf) for kf in smap.keyframe_ids]
    col = {key: D * i for i, key in enumerate(kf_keys)}
    n_pose = D * len(kf_keys)
    offsets = np.cumsum([n_pose] + [b.num_structs for b in blocks])
    ordering = gtsam.Ordering()
    for key in kf_keys:
        ordering.push_back(key)

    def cost(vals, depths):
        return graph.error(vals) + sum(b.cost(vals, d) for b, d in zip(blocks, depths))

    def to_vv(dx):
        vv = gtsam.VectorValues()
        for key in kf_keys:
            vv.insert(key, dx[col[key]:col[key] + D])
        return vv

    values = smap.values
    depths = [b.structure.clone() for b in blocks]
    current = cost(values, depths)
    lam = 1e-6
    for _ in range(iterations):
        n = offsets[-1]
        H = np.zeros((n, n))
        grad = np.zeros(n)
        Lam, eta = graph.linearize(values).hessian(ordering)
        H[:n_pose, :n_pose] += Lam
        grad[:n_pose] -= eta
        for bi, (b, d) in enumerate(zip(blocks, depths)):
            res = b.evaluate(b.poses_from_values(values), d, jacobians=True)
            rows = res.r.shape[0]
            A = np.zeros((rows, 2, n))
            for s in range(2):
                cols = np.array([col[b.keys[int(k)]] for k in b.slots[:, s]])
                for c in range(D):
                    np.add.at(A, (np.arange(rows), slice(None), cols + c), res.J[s][:, :, c].numpy())
            A[np.arange(rows), :, offsets[bi] + b.struct_idx.numpy()] += res.E.numpy()
            A = A.reshape(2 * rows, n)
            w = res.weights.numpy().reshape(-1)
            H += A.T @ (w[:, None] * A)
            grad += A.T @ (w * res.r.numpy().reshape(-1))
        while True:
            step = np.linalg.solve(H + lam * np.eye(len(H)), -grad)
            trial_values = values.retract(to_vv(step[:n_pose]))
            trial_depths = [d + torch.as_tensor(step[offsets[i]:offsets[i + 1]]) for i, d in enumerate(depths)]
            trial_cost = cost(trial_values, trial_depths)
            if trial_cost <= current:
                lam = max(lam / 10, 1e-12)
                break
            lam *= 10
            if lam > 1e8:
                return values, depths
        done = current - trial_cost <= 1e-14 * current
        values, depths, current = trial_values, trial_depths, trial_cost
        if done:
            break
    return values, depths


@pytest.fixture(scope="module", params=[0.0, 0.5], ids=["noise-free", "noisy"])
def scene_and_reference(request):
    scene = make_scene(seed=3, noise_px=request.param)
    smap = build_map(scene, MapConfig())
    ref_values, ref_depths = explicit_joint_lm(smap)
    ref_cost = smap.nonlinear_graph().error(ref_values) + sum(
        b.cost(ref_values, d) for b, d in zip(smap.blocks.values(), ref_depths))
    return scene, ref_values, ref_depths, ref_cost, request.param


@pytest.mark.parametrize("solver,reverse_keys", [("python_lm", False), ("python_lm", True), ("gtsam_lm", False),
                                                  ("isam2", False)])
def test_compressed_blocks_reach_explicit_joint_optimum(scene_and_reference, solver, reverse_keys):
    scene, ref_values, ref_depths, ref_cost, noise = scene_and_reference
    smap = build_map(scene, MapConfig(solver=solver, max_iterations=60), reverse_keys)
    report = smap.optimize()
    assert report.converged
    assert report.final_cost < report.initial_cost
    assert report.final_cost == pytest.approx(ref_cost, rel=1e-9, abs=1e-12)
    for kf in range(NUM_KF):
        ref = ref_values.atSimilarity3(pose_key(kf))
        got = smap.pose(kf)
        assert np.linalg.norm(ref.localCoordinates(got)) < 1e-6
        np.testing.assert_allclose(got.matrix(), ref.matrix(), rtol=1e-6, atol=1e-6)
    for block, d_ref in zip(smap.blocks.values(), ref_depths):
        np.testing.assert_allclose(block.structure.numpy(), d_ref.numpy(), rtol=1e-6)
    if noise == 0.0:
        # noise-free: the optimum explains the observations exactly (up to the fixed gauge)
        assert report.final_cost < 1e-12


def _nullity(smap: SlamMap) -> int:
    H, _ = smap.linearize().hessian()
    eig = np.linalg.eigvalsh(H)
    return int(np.sum(eig < 1e-9 * np.median(np.abs(eig))))


def test_gauge_scale_priors_and_range_make_the_system_nonsingular():
    scene = make_scene(seed=5, noise_px=0.5)
    loose = dict(anchor_sigma=1e-2, scale_sigma=1e-2, range_sigma=1e-2)  # well-conditioned for eigvalsh
    full = build_map(scene, MapConfig(gauge=GaugeConfig(**loose)))
    assert _nullity(full) == 0
    no_scale = build_map(scene, MapConfig(gauge=GaugeConfig(hold_scale=False, **loose)))
    assert _nullity(no_scale) == NUM_KF - 1  # every non-anchor keyframe's scale is a pure gauge
    no_range = build_map(scene, MapConfig(gauge=GaugeConfig(world_scale_range=False, **loose)))
    assert _nullity(no_range) == 1  # the monocular world scale
    with pytest.raises(RuntimeError):  # gtsam's IndeterminateLinearSystemException
        no_scale.linearize().optimize()


def test_marginal_covariances_are_finite_symmetric_positive_definite():
    scene = make_scene(seed=6, noise_px=0.5)
    smap = build_map(scene, MapConfig(max_iterations=10))
    smap.optimize()
    cov = smap.marginal_covariances()
    assert sorted(cov) == list(range(NUM_KF))
    for kf, S in cov.items():
        assert S.shape == (D, D) and np.isfinite(S).all()
        np.testing.assert_allclose(S, S.T, rtol=1e-9, atol=1e-18)
        assert np.linalg.eigvalsh(0.5 * (S + S.T)).min() > 0.0
    # the far keyframe is less certain in translation than the anchor
    assert np.trace(cov[4][3:6, 3:6]) > np.trace(cov[0][3:6, 3:6])


@pytest.mark.parametrize("solver", ["python_lm", "gtsam_lm", "isam2"])
def test_pose_graph_of_builtin_factors_matches_gtsam_lm(solver):
    rng = np.random.default_rng(0)
    poses = [gtsam.Similarity3(gtsam.Rot3.Rz(0.1 * i), np.array([i, 0.2 * i, 0.0]), float(np.exp(0.05 * i)))
             for i in range(4)]
    noise = gtsam.noiseModel.Isotropic.Sigma(D, 0.1)
    smap = SlamMap(MapConfig(solver=solver, gauge=GaugeConfig(hold_scale=False, world_scale_range=False)))
    for i, T in enumerate(poses):
        smap.add_keyframe(i, T.retract(0.05 * rng.standard_normal(D)) if i else T)
    graph = gtsam.NonlinearFactorGraph()
    for i, j in [(0, 1), (1, 2), (2, 3), (0, 3), (1, 3)]:
        meas = poses[i].between(poses[j]).retract(0.02 * rng.standard_normal(D))
        factor = gtsam.BetweenFactorSimilarity3(pose_key(i), pose_key(j), meas, noise)
        smap.add_factor(factor)
    expected = gtsam.LevenbergMarquardtOptimizer(smap.nonlinear_graph(), smap.values).optimize()
    smap.optimize()
    for i in range(4):
        assert np.linalg.norm(expected.atSimilarity3(pose_key(i)).localCoordinates(smap.pose(i))) < 1e-6


def test_map_bookkeeping_remove_keyframe_drops_factors_blocks_and_moves_anchor():
    scene = make_scene(seed=7, noise_px=0.5)
    smap = build_map(scene, MapConfig(max_iterations=5))
    assert len(smap.blocks) == NUM_KF
    report = smap.optimize(max_iterations=1)  # per-call iteration cap
    assert report.iterations == 1 and report.final_cost < report.initial_cost
    with pytest.raises(OptimizationError):
        smap.add_keyframe(2, smap.pose(2))
    smap.remove_keyframe(0)
    assert smap.keyframe_ids == [1, 2, 3, 4]
    assert len(smap.blocks) == 0  # every block of the scene touches keyframe 0
    graph = smap.nonlinear_graph()
    keys = {k for i in range(graph.size()) for k in graph.at(i).keys()}
    assert pose_key(0) not in keys
    # new anchor: keyframe 1 carries a 7-dof prior; range gauge between keyframes 1 and 2
    ordering = gtsam.Ordering()
    for kf in smap.keyframe_ids:
        ordering.push_back(pose_key(kf))
    H, _ = smap.linearize().hessian(ordering)
    sigma = GaugeConfig().anchor_sigma
    assert np.linalg.eigvalsh(H[:D, :D]).min() >= 0.999 / sigma**2  # anchor prior on keyframe 1
    assert np.linalg.eigvalsh(H[D:, D:]).min() >= -1e-9 * np.abs(H).max()  # PSD up to rounding
    with pytest.raises(OptimizationError):
        smap.add_factor(gtsam.PriorFactorSimilarity3(pose_key(0), gtsam.Similarity3(),
                                                     gtsam.noiseModel.Isotropic.Sigma(D, 1.0)))


def test_map_config_preset_loads_with_overrides(repo_root):
    from fgslam.config import load_config

    cfg = load_config(MapConfig, repo_root / "fgslam" / "configs" / "map.yaml", ["solver=isam2", "gauge.hold_scale=false"])
    assert cfg.solver == "isam2" and cfg.gauge.hold_scale is False
    assert cfg.gauge.anchor_sigma == GaugeConfig().anchor_sigma and cfg.max_iterations == MapConfig().max_iterations


def test_isam2_stays_exact_across_incremental_additions_and_removals():
    rng = np.random.default_rng(1)
    poses = [gtsam.Similarity3(gtsam.Rot3.Rx(0.1 * i), np.array([i, 0.0, 0.1 * i]), float(np.exp(0.03 * i)))
             for i in range(5)]
    noise = gtsam.noiseModel.Isotropic.Sigma(D, 0.1)
    gauge = GaugeConfig(hold_scale=False, world_scale_range=False)
    smap = SlamMap(MapConfig(solver="isam2", gauge=gauge))

    def between(i, j):
        meas = poses[i].between(poses[j]).retract(0.02 * rng.standard_normal(D))
        return gtsam.BetweenFactorSimilarity3(pose_key(i), pose_key(j), meas, noise)

    for i in range(3):
        smap.add_keyframe(i, poses[i].retract(0.05 * rng.standard_normal(D)) if i else poses[i])
    handles = [smap.add_factor(between(0, 1)), smap.add_factor(between(1, 2)), smap.add_factor(between(0, 2))]
    smap.optimize()
    for i in (3, 4):  # new keyframes and factors go into the same iSAM2 instance
        smap.add_keyframe(i, poses[i].retract(0.05 * rng.standard_normal(D)))
        smap.add_factor(between(i - 1, i))
    smap.add_factor(between(1, 4))
    smap.remove_factor(handles[2])
    smap.optimize()
    expected = gtsam.LevenbergMarquardtOptimizer(smap.nonlinear_graph(), smap.values).optimize()
    for i in range(5):
        assert np.linalg.norm(expected.atSimilarity3(pose_key(i)).localCoordinates(smap.pose(i))) < 1e-6
