"""Tests of fgslam.backend: Schur-compressed blocks reach the explicit joint optimum with every
solver, windowed (fixed and marginalised) and global; two contributors on the same keys; gauge
handling, marginals, bookkeeping, pose-graph correction against gtsam's own LM."""

import dataclasses

import gtsam
import numpy as np
import pytest
import torch

from fgslam.backend import Backend, BackendConfig, GaugeConfig, LinearPiece, key_name, pose_key
from fgslam.backend.config import WindowConfig
from fgslam.core.errors import OptimizationError
from fgslam.factors.reprojection import reproject
from fgslam.factors.schur import POSE_DIM, torch_threads
from fgslam.factors.visual_block import BlockConfig, InverseDepthBlock
from fgslam.core.lie import Sim3
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


def build_backend(scene, config: BackendConfig, reverse_keys: bool = False) -> Backend:
    """One block per host keyframe over all 5 keys (slot = keyframe, or 4 - keyframe when reversed)."""
    _, T_init, hosts = scene
    backend = Backend(config)
    for kf in range(NUM_KF):
        backend.add_keyframe(kf, T_init[kf], 0.1 * kf)
    order = list(range(NUM_KF))[::-1] if reverse_keys else list(range(NUM_KF))
    keys = [pose_key(kf) for kf in order]
    slot_of = torch.tensor([order.index(kf) for kf in range(NUM_KF)])
    backend.set_blocks("visual", [
        InverseDepthBlock(keys, slot_of[host["src"]], slot_of[host["tgt"]], host["uvs"], host["uvt"], host["idx"],
                          host["w"], K, host["d_init"].clone(), BlockConfig(refine_steps=1))
        for host in hosts])
    return backend


class RelativePoseBlock:
    """A toy pose-only contributor: Sim(3) relative-pose residuals ``Log(Z_ij^-1 T_i^-1 T_j)`` between
    key pairs, one linear piece per pair (gtsam's BetweenFactorSimilarity3 supplies r and J)."""

    has_structure = False

    def __init__(self, pairs, measurements, sigma):
        noise = gtsam.noiseModel.Isotropic.Sigma(D, sigma)
        self.factors = [gtsam.BetweenFactorSimilarity3(a, b, Z, noise) for (a, b), Z in zip(pairs, measurements)]
        self.keys = tuple(sorted({k for pair in pairs for k in pair}))

    def linearize(self, values):
        pieces = []
        for f in self.factors:
            A, b = f.linearize(values).jacobian()
            pieces.append(LinearPiece(tuple(int(k) for k in f.keys()), A.T @ A, -A.T @ b, float(b @ b)))
        return pieces

    def cost(self, values, structure=None):
        return sum(f.error(values) for f in self.factors)


def toy_block(scene, seed: int, sigma: float = 0.05) -> RelativePoseBlock:
    T_true = scene[0]
    rng = np.random.default_rng(seed)
    ids = [(0, 2), (1, 3), (2, 4), (1, 4)]
    meas = [T_true[i].to_gtsam().between(T_true[j].to_gtsam()).retract(0.02 * rng.standard_normal(D)) for i, j in ids]
    return RelativePoseBlock([(pose_key(i), pose_key(j)) for i, j in ids], meas, sigma)


def explicit_joint_lm(backend: Backend, free_kfs=None, iterations: int = 60, lam: float = 1e-6):
    """Reference: dense LM on the explicit joint problem, free poses AND inverse depths as variables,
    ``lam`` (the initial damping, x10 on rejection, /10 on acceptance) on every one of them.

    One dense Jacobian over [free pose tangents | all inverse depths] per iteration (no Schur
    complement anywhere); the built-in and gauge factors are the backend's own (linearised by gtsam,
    the columns of fixed keyframes dropped); pose-only blocks through their own factors.
    Returns (values, depths per structured block, cost).
    """
    graph = backend.nonlinear_graph()
    for block in backend.blocks():
        if not block.has_structure:
            for f in block.factors:
                graph.add(f)
    blocks = [b for b in backend.blocks() if b.has_structure]
    all_keys = [pose_key(kf) for kf in backend.keyframe_ids]
    kf_keys = all_keys if free_kfs is None else [pose_key(kf) for kf in free_kfs]
    col = {key: D * i for i, key in enumerate(kf_keys)}
    n_pose = D * len(kf_keys)
    offsets = np.cumsum([n_pose] + [b.num_structs for b in blocks])
    ordering = gtsam.Ordering()
    for key in kf_keys + [k for k in all_keys if k not in col]:
        ordering.push_back(key)

    def cost(vals, depths):
        return graph.error(vals) + sum(b.cost(vals, d) for b, d in zip(blocks, depths))

    def to_vv(dx):
        vv = gtsam.VectorValues()
        for key in kf_keys:
            vv.insert(key, dx[col[key]:col[key] + D])
        return vv

    values = backend.values
    depths = [b.structure.clone() for b in blocks]
    current = cost(values, depths)
    for _ in range(iterations):
        n = offsets[-1]
        H = np.zeros((n, n))
        grad = np.zeros(n)
        Lam, eta = graph.linearize(values).hessian(ordering)
        H[:n_pose, :n_pose] += Lam[:n_pose, :n_pose]
        grad[:n_pose] -= eta[:n_pose]
        for bi, (b, d) in enumerate(zip(blocks, depths)):
            res = b.evaluate(b.poses_from_values(values), d, jacobians=True)
            rows = res.r.shape[0]
            A = np.zeros((rows, 2, n))
            A_cols = A.transpose(0, 2, 1)  # (rows, n, 2) view
            for s in range(2):  # one pose block per row and slot: no repeated index within one slot
                slot_col = np.array([col.get(k, -1) for k in b.keys])[b.slots[:, s].numpy()]
                free_row = np.nonzero(slot_col >= 0)[0]
                cols = slot_col[free_row][:, None] + np.arange(D)
                A_cols[free_row[:, None], cols] += res.J[s][free_row].numpy().transpose(0, 2, 1)
            A[np.arange(rows), :, offsets[bi] + b.struct_idx.numpy()] += res.E.numpy()
            A = torch.as_tensor(A.reshape(2 * rows, n))
            w = res.weights.reshape(-1)
            with torch_threads(1):  # (a multi-threaded BLAS crawls on a loaded 2-core machine)
                H += (A.T @ (w[:, None] * A)).numpy()
                grad += (A.T @ (w * res.r.reshape(-1))).numpy()
        while True:
            with torch_threads(1):
                step = torch.linalg.solve(torch.as_tensor(H + lam * np.eye(len(H))), torch.as_tensor(-grad)).numpy()
            trial_values = values.retract(to_vv(step[:n_pose]))
            trial_depths = [d + torch.as_tensor(step[offsets[i]:offsets[i + 1]]) for i, d in enumerate(depths)]
            trial_cost = cost(trial_values, trial_depths)
            if trial_cost <= current:
                lam = max(lam / 10, 1e-12)
                break
            lam *= 10
            if lam > 1e8:
                return values, depths, current
        done = current - trial_cost <= 1e-14 * current
        values, depths, current = trial_values, trial_depths, trial_cost
        if done:
            break
    return values, depths, current


@pytest.mark.parametrize("lam", [1.0, 1e3])
def test_damped_structure_takes_the_damped_joint_step(lam):
    """``map.damp_structure``: one LM iteration at the damping ``lam`` is the step of the explicit joint
    problem with ``lam`` on every pose tangent and every inverse depth (the depths re-eliminated with the
    damping, back-substituted through it); without the option the depths' step is not damped, another step."""
    scene = make_scene(seed=5, noise_px=0.5)
    config = BackendConfig(max_iterations=1, lambda_initial=lam, lambda_factor=10.0, refine_steps=0, damp_structure=True)
    ref_values, ref_depths, ref_cost = explicit_joint_lm(build_backend(scene, config), iterations=1, lam=lam)
    backend = build_backend(scene, config)
    initial = backend.cost()
    report = backend.optimize_global()
    assert report.final_cost < initial and report.final_cost == pytest.approx(ref_cost, rel=1e-9)
    check_optimum(backend, ref_values, ref_depths)
    plain = build_backend(scene, dataclasses.replace(config, damp_structure=False))
    plain.optimize_global()
    # the tolerance check_optimum holds the damped step to would reject the undamped one
    assert not all(np.allclose(b.structure.numpy(), d.numpy(), rtol=1e-6, atol=0)
                   for b, d in zip(plain.blocks(), ref_depths))
    for block in backend.blocks():  # the optimisation has ended: back to the last linearisation's system
        assert block._damped is None


def check_optimum(backend: Backend, ref_values, ref_depths, kfs=range(NUM_KF)):
    for kf in kfs:
        ref = ref_values.atSimilarity3(pose_key(kf))
        got = backend.pose(kf)
        assert np.linalg.norm(ref.localCoordinates(got)) < 1e-6
        np.testing.assert_allclose(got.matrix(), ref.matrix(), rtol=1e-6, atol=1e-6)
    for block, d_ref in zip([b for b in backend.blocks() if b.has_structure], ref_depths):
        np.testing.assert_allclose(block.structure.numpy(), d_ref.numpy(), rtol=1e-6)


def matrix_to_similarity3(M):
    s = float(np.cbrt(np.linalg.det(M[:3, :3])))
    return gtsam.Similarity3(gtsam.Rot3(M[:3, :3] / s), M[:3, 3] / s, s)


@pytest.fixture(scope="module", params=[0.0, 0.5], ids=["noise-free", "noisy"])
def scene_and_reference(request):
    scene = make_scene(seed=3, noise_px=request.param)
    ref_values, ref_depths, ref_cost = explicit_joint_lm(build_backend(scene, BackendConfig()))
    return scene, ref_values, ref_depths, ref_cost, request.param


@pytest.mark.parametrize("solver,reverse_keys,damp_structure", [
    ("lm", False, False), ("lm", True, False), ("python_lm", False, False), ("isam2", False, False),
    ("lm", False, True)])
def test_compressed_blocks_reach_explicit_joint_optimum(scene_and_reference, solver, reverse_keys, damp_structure):
    """Every solver reaches the explicit joint optimum; with ``damp_structure`` the LM damps the depths too
    (another path, the same minimum)."""
    scene, ref_values, ref_depths, ref_cost, noise = scene_and_reference
    config = BackendConfig(solver=solver, max_iterations=60, damp_structure=damp_structure)
    backend = build_backend(scene, config, reverse_keys)
    report = backend.optimize_global()
    assert report.converged
    assert report.final_cost < report.initial_cost
    assert report.final_cost == pytest.approx(ref_cost, rel=1e-9, abs=1e-12)
    check_optimum(backend, ref_values, ref_depths)
    if noise == 0.0:
        # noise-free: the optimum explains the observations exactly (up to the fixed gauge)
        assert report.final_cost < 1e-12


@pytest.fixture(scope="module")
def window_reference():
    scene = make_scene(seed=4, noise_px=0.5)
    reference = explicit_joint_lm(build_backend(scene, BackendConfig()), free_kfs=[2, 3, 4])
    global_backend = build_backend(scene, BackendConfig(max_iterations=60))
    global_backend.optimize_global()
    return scene, reference, global_backend.pose(4)


@pytest.mark.parametrize("solver,damp_structure", [("lm", False), ("isam2", False), ("lm", True)])
@pytest.mark.parametrize("leaving", ["fixed", "marginalize"])
def test_window_reaches_explicit_optimum_with_outside_poses_fixed(window_reference, solver, damp_structure, leaving):
    """Keyframes 0, 1 outside the window: the blocks' Schur systems restricted to the free poses equal
    the explicit joint problem over the free poses and every depth with 0, 1 held (no persistent
    built-in factor reaches outside here, so marginalize must give the same)."""
    scene, (ref_values, ref_depths, ref_cost), global_pose4 = window_reference
    config = BackendConfig(solver=solver, max_iterations=60, window=WindowConfig(leaving=leaving),
                           damp_structure=damp_structure)
    backend = build_backend(scene, config)
    before = {kf: backend.pose(kf) for kf in (0, 1)}
    report = backend.optimize_window([2, 3, 4])
    assert report.converged and report.free_keys == 3
    for kf in (0, 1):
        np.testing.assert_array_equal(backend.pose(kf).matrix(), before[kf].matrix())
    check_optimum(backend, ref_values, ref_depths, kfs=(2, 3, 4))
    assert backend.cost() == pytest.approx(ref_cost, rel=1e-9)
    # the window's optimum is not the global one: the held poses matter
    assert np.linalg.norm(global_pose4.localCoordinates(backend.pose(4))) > 1e-4


def two_contributors(scene, config):
    backend = build_backend(scene, config)
    backend.set_blocks("toy", [toy_block(scene, seed=1)])
    return backend


@pytest.fixture(scope="module")
def two_contributor_reference():
    scene = make_scene(seed=8, noise_px=0.5)
    reference = explicit_joint_lm(two_contributors(scene, BackendConfig()))
    visual_only, _, _ = explicit_joint_lm(build_backend(scene, BackendConfig()))
    return scene, reference, visual_only


@pytest.mark.parametrize("solver", ["lm", "isam2"])
def test_two_contributors_on_the_same_keys_reach_the_joint_optimum_of_their_sum(two_contributor_reference, solver):
    scene, (ref_values, ref_depths, ref_cost), visual_only = two_contributor_reference
    backend = two_contributors(scene, BackendConfig(solver=solver, max_iterations=60))
    report = backend.optimize_global()
    assert report.converged
    assert report.final_cost == pytest.approx(ref_cost, rel=1e-9)
    check_optimum(backend, ref_values, ref_depths)
    # the toy contributor really pulls: the joint optimum differs from the visual-only one
    assert np.linalg.norm(visual_only.atSimilarity3(pose_key(4)).localCoordinates(backend.pose(4))) > 1e-4


def test_set_blocks_replaces_a_contributors_blocks():
    scene = make_scene(seed=9, noise_px=0.5)
    backend = build_backend(scene, BackendConfig())
    visual_cost = backend.cost()
    first, second = toy_block(scene, seed=1), toy_block(scene, seed=2, sigma=0.01)
    backend.set_blocks("toy", [first])
    assert backend.cost() == pytest.approx(visual_cost + first.cost(backend.values), rel=1e-12)
    backend.set_blocks("toy", [second])
    assert backend.blocks("toy") == [second]
    assert len(backend.blocks("visual")) == NUM_KF
    assert backend.cost() == pytest.approx(visual_cost + second.cost(backend.values), rel=1e-12)
    backend.set_blocks("toy", [])
    assert backend.blocks("toy") == [] and backend.cost() == pytest.approx(visual_cost, rel=1e-12)


def test_factor_or_block_on_a_missing_key_is_an_error_naming_the_key():
    backend = Backend(BackendConfig())
    backend.add_keyframe(0, gtsam.Similarity3(), 0.0)
    noise = gtsam.noiseModel.Isotropic.Sigma(D, 1.0)
    with pytest.raises(OptimizationError, match=r"\bx12\b"):
        backend.add_factor(gtsam.BetweenFactorSimilarity3(pose_key(0), pose_key(12), gtsam.Similarity3(), noise))
    assert key_name(pose_key(12)) == "x12"
    with pytest.raises(OptimizationError, match=r"\bx7\b"):
        backend.set_blocks("toy", [RelativePoseBlock([(pose_key(0), pose_key(7))], [gtsam.Similarity3()], 1.0)])
    assert backend.factor_handles("user") == [] and backend.blocks() == []
    with pytest.raises(OptimizationError, match="x3"):
        backend.optimize_window([3])


def test_other_variables_are_optimised_with_the_poses():
    """A non-pose variable (a Point3 landmark key 'l0') with a prior: moved by a global optimisation
    and by a window that names it, held by a window that does not."""
    from fgslam.backend.keys import symbol

    backend = Backend(BackendConfig())
    backend.add_keyframe(0, gtsam.Similarity3(), 0.0)
    point = symbol("l", 0)
    backend.add_variable(point, np.zeros(3))
    assert backend.has_key(point) and key_name(point) == "l0"
    with pytest.raises(OptimizationError, match="l0"):
        backend.add_variable(point, np.zeros(3))
    target = np.array([1.0, 2.0, 3.0])
    backend.add_factor(gtsam.PriorFactorPoint3(point, target, gtsam.noiseModel.Isotropic.Sigma(3, 0.1)), owner="toy")
    backend.optimize_window([0])
    np.testing.assert_array_equal(backend.values.atPoint3(point), np.zeros(3))
    backend.optimize_window([0], extra_free_keys=[point])
    np.testing.assert_allclose(backend.values.atPoint3(point), target, atol=1e-9)
    backend.remove_variable(point)
    assert not backend.has_key(point) and backend.factor_handles("toy") == []


def test_marginalized_window_keeps_outside_factors_as_a_linear_prior():
    """A Sim(3) chain 0-5 with a loop, anchored at 0; a toy block pulls keyframes 4 and 5. The window
    {4, 5}: held fixed, keyframes 0-3 cannot give way; marginalised, their between factors become a
    linear prior on keyframes 4 and 5 that lets the chain bend as in the global optimum. The result
    is near the global optimum (exact up to the outside factors' linearisation)."""
    rng = np.random.default_rng(3)
    poses = [gtsam.Similarity3(gtsam.Rot3.Rz(0.2 * i), np.array([i, 0.3 * i, 0.0]), 1.0) for i in range(6)]
    noise = gtsam.noiseModel.Isotropic.Sigma(D, 0.05)
    gauge = GaugeConfig(hold_scale=False, world_scale_range=False)
    pull = [poses[4].retract(0.03 * rng.standard_normal(D)), poses[5].retract(0.03 * rng.standard_normal(D))]

    def build(leaving):
        backend = Backend(BackendConfig(max_iterations=60, gauge=gauge, window=WindowConfig(leaving=leaving)))
        for i, T in enumerate(poses):
            backend.add_keyframe(i, T, float(i))
        for i, j in [(0, 1), (1, 2), (2, 3), (3, 4), (4, 5), (0, 5)]:
            backend.add_factor(gtsam.BetweenFactorSimilarity3(pose_key(i), pose_key(j), poses[i].between(poses[j]),
                                                              noise), owner="loop")
        block = RelativePoseBlock([(pose_key(0), pose_key(4)), (pose_key(0), pose_key(5))],
                                  [poses[0].between(p) for p in pull], 0.05)
        backend.set_blocks("toy", [block])
        return backend

    ref = build("fixed")
    ref.optimize_global()
    fixed, marg = build("fixed"), build("marginalize")
    fixed.optimize_window([4, 5])
    marg.optimize_window([4, 5])
    for kf in range(4):
        np.testing.assert_array_equal(marg.pose(kf).matrix(), poses[kf].matrix())  # outside keys are not moved
    err_fixed = max(np.linalg.norm(ref.pose(k).localCoordinates(fixed.pose(k))) for k in (4, 5))
    err_marg = max(np.linalg.norm(ref.pose(k).localCoordinates(marg.pose(k))) for k in (4, 5))
    assert err_fixed > 5e-3
    assert err_marg < 0.05 * err_fixed


def _nullity(backend: Backend) -> int:
    H, _ = backend.linearize().hessian()
    eig = np.linalg.eigvalsh(H)
    return int(np.sum(eig < 1e-9 * np.median(np.abs(eig))))


def test_gauge_scale_priors_and_range_make_the_system_nonsingular():
    scene = make_scene(seed=5, noise_px=0.5)
    loose = dict(anchor_sigma=1e-2, scale_sigma=1e-2, range_sigma=1e-2)  # well-conditioned for eigvalsh
    full = build_backend(scene, BackendConfig(gauge=GaugeConfig(**loose)))
    assert _nullity(full) == 0
    no_scale = build_backend(scene, BackendConfig(gauge=GaugeConfig(hold_scale=False, **loose)))
    assert _nullity(no_scale) == NUM_KF - 1  # every non-anchor keyframe's scale is a pure gauge
    no_range = build_backend(scene, BackendConfig(gauge=GaugeConfig(world_scale_range=False, **loose)))
    assert _nullity(no_range) == 1  # the monocular world scale
    with pytest.raises(RuntimeError):  # gtsam's IndeterminateLinearSystemException
        no_scale.linearize().optimize()
    # set_gauge moves the anchor and the range: neither leaves the 7-dof similarity gauge free
    full.set_gauge(anchor=None, scale_pair=None)
    assert _nullity(full) == D
    full.set_gauge(anchor=3, scale_pair=(3, 4))
    assert _nullity(full) == 0


def test_marginal_covariances_are_finite_symmetric_positive_definite():
    scene = make_scene(seed=6, noise_px=0.5)
    backend = build_backend(scene, BackendConfig(max_iterations=10))
    backend.optimize_global()
    cov = backend.marginal_covariances()
    assert sorted(cov) == list(range(NUM_KF))
    for kf, S in cov.items():
        assert S.shape == (D, D) and np.isfinite(S).all()
        np.testing.assert_allclose(S, S.T, rtol=1e-9, atol=1e-18)
        assert np.linalg.eigvalsh(0.5 * (S + S.T)).min() > 0.0
    # the far keyframe is less certain in translation than the anchor
    assert np.trace(cov[4][3:6, 3:6]) > np.trace(cov[0][3:6, 3:6])


@pytest.mark.parametrize("solver", ["lm", "isam2"])
def test_pose_graph_of_builtin_factors_matches_gtsam_lm(solver):
    rng = np.random.default_rng(0)
    poses = [gtsam.Similarity3(gtsam.Rot3.Rz(0.1 * i), np.array([i, 0.2 * i, 0.0]), float(np.exp(0.05 * i)))
             for i in range(4)]
    noise = gtsam.noiseModel.Isotropic.Sigma(D, 0.1)
    backend = Backend(BackendConfig(solver=solver, gauge=GaugeConfig(hold_scale=False, world_scale_range=False)))
    for i, T in enumerate(poses):
        backend.add_keyframe(i, T.retract(0.05 * rng.standard_normal(D)) if i else T, float(i))
    for i, j in [(0, 1), (1, 2), (2, 3), (0, 3), (1, 3)]:
        meas = poses[i].between(poses[j]).retract(0.02 * rng.standard_normal(D))
        backend.add_factor(gtsam.BetweenFactorSimilarity3(pose_key(i), pose_key(j), meas, noise))
    expected = gtsam.LevenbergMarquardtOptimizer(backend.nonlinear_graph(), backend.values).optimize()
    backend.optimize_global()
    for i in range(4):
        assert np.linalg.norm(expected.atSimilarity3(pose_key(i)).localCoordinates(backend.pose(i))) < 1e-6


@pytest.mark.parametrize("solver", ["lm", "isam2"])
def test_pose_graph_correction_of_a_sim3_loop_matches_gtsam_lm(solver):
    """Drifted odometry around a loop (scale drift included) closed by one loop factor:
    correct_pose_graph reaches gtsam's own LM optimum of the same graph (same cost to 1e-6) and
    returns the poses without applying them."""
    n = 8
    rng = np.random.default_rng(5)
    angle = [2 * np.pi * i / n for i in range(n)]
    truth = [gtsam.Similarity3(gtsam.Rot3.Rz(a), 5.0 * np.array([np.cos(a), np.sin(a), 0.0]), 1.0) for a in angle]
    backend = Backend(BackendConfig(solver=solver, max_iterations=100))
    est = [truth[0]]
    for i in range(1, n):
        drift = gtsam.Similarity3.Expmap(np.concatenate([0.02 * rng.standard_normal(3), 0.1 * rng.standard_normal(3),
                                                         [0.03]]))
        est.append(est[-1].compose(truth[i - 1].between(truth[i])).compose(drift))
    for i, T in enumerate(est):
        backend.add_keyframe(i, T, float(i))
    loop_noise = gtsam.noiseModel.Isotropic.Sigma(D, 0.01)
    backend.add_factor(gtsam.BetweenFactorSimilarity3(pose_key(n - 1), pose_key(0), truth[n - 1].between(truth[0]),
                                                      loop_noise), owner="loop")
    before = {i: backend.pose_matrix(i) for i in range(n)}
    corrected = backend.correct_pose_graph()
    assert sorted(corrected) == list(range(n))
    for i in range(n):
        np.testing.assert_array_equal(backend.pose_matrix(i), before[i])  # not applied
    # the same graph for gtsam's own LM
    pg = backend.config.pose_graph
    sigmas = np.array([pg.rotation_sigma] * 3 + [pg.translation_sigma] * 3 + [pg.log_scale_sigma])
    graph = gtsam.NonlinearFactorGraph()
    values = gtsam.Values()
    for i in range(n):
        values.insert(pose_key(i), est[i])
    for i in range(n - 1):
        graph.add(gtsam.BetweenFactorSimilarity3(pose_key(i), pose_key(i + 1), est[i].between(est[i + 1]),
                                                 gtsam.noiseModel.Diagonal.Sigmas(sigmas)))
    graph.add(backend.factor(backend.factor_handles("loop")[0]))
    graph.add(gtsam.PriorFactorSimilarity3(pose_key(0), est[0],
                                           gtsam.noiseModel.Isotropic.Sigma(D, backend.config.gauge.anchor_sigma)))
    params = gtsam.LevenbergMarquardtParams()
    params.setRelativeErrorTol(1e-12)
    params.setAbsoluteErrorTol(1e-16)
    params.setMaxIterations(200)
    expected = gtsam.LevenbergMarquardtOptimizer(graph, values, params).optimize()
    got = gtsam.Values()
    for i in range(n):
        got.insert(pose_key(i), matrix_to_similarity3(corrected[i]))
    assert graph.error(values) > 100 * graph.error(expected)  # the loop really corrects
    assert graph.error(got) == pytest.approx(graph.error(expected), rel=1e-6)


def test_backend_bookkeeping_remove_keyframe_drops_factors_blocks_and_moves_anchor():
    scene = make_scene(seed=7, noise_px=0.5)
    backend = build_backend(scene, BackendConfig(max_iterations=5))
    seen = []
    backend.on_keyframe(lambda kf, t, key: seen.append((kf, t, key)))
    assert len(backend.blocks()) == NUM_KF
    report = backend.optimize_global(iterations=1)  # per-call iteration cap
    assert report.iterations == 1 and report.final_cost < report.initial_cost
    with pytest.raises(OptimizationError):
        backend.add_keyframe(2, backend.pose(2))
    assert backend.timestamp(3) == pytest.approx(0.3)
    backend.remove_keyframe(0)
    assert backend.keyframe_ids == [1, 2, 3, 4] and not backend.has_keyframe(0)
    assert len(backend.blocks()) == 0  # every block of the scene touches keyframe 0
    graph = backend.nonlinear_graph()
    keys = {k for i in range(graph.size()) for k in graph.at(i).keys()}
    assert pose_key(0) not in keys
    # new anchor: keyframe 1 carries a 7-dof prior; range gauge between keyframes 1 and 2
    ordering = gtsam.Ordering()
    for kf in backend.keyframe_ids:
        ordering.push_back(pose_key(kf))
    H, _ = backend.linearize().hessian(ordering)
    sigma = GaugeConfig().anchor_sigma
    assert np.linalg.eigvalsh(H[:D, :D]).min() >= 0.999 / sigma**2  # anchor prior on keyframe 1
    assert np.linalg.eigvalsh(H[D:, D:]).min() >= -1e-9 * np.abs(H).max()  # PSD up to rounding
    with pytest.raises(OptimizationError, match="x0"):
        backend.add_factor(gtsam.PriorFactorSimilarity3(pose_key(0), gtsam.Similarity3(),
                                                        gtsam.noiseModel.Isotropic.Sigma(D, 1.0)))
    backend.add_keyframe(9, backend.pose(4), 0.9)
    assert seen == [(9, 0.9, pose_key(9))]
    version = backend.pose_version(9)
    backend.set_pose(9, backend.pose_matrix(9))
    assert backend.pose_version(9) != version


def test_backend_config_preset_loads_with_overrides(repo_root):
    from fgslam.core.config import load_config
    from fgslam.core.errors import ConfigError

    cfg = load_config(BackendConfig, repo_root / "fgslam" / "configs" / "map.yaml",
                      ["solver=isam2", "gauge.hold_scale=false", "window.leaving=marginalize"])
    assert cfg.solver == "isam2" and cfg.gauge.hold_scale is False and cfg.window.leaving == "marginalize"
    assert cfg.gauge.anchor_sigma == GaugeConfig().anchor_sigma and cfg.max_iterations == BackendConfig().max_iterations
    assert load_config(BackendConfig, None, ["solver=python_lm"]).solver_kind == "lm"
    with pytest.raises(ConfigError, match="solver"):
        load_config(BackendConfig, None, ["solver=gtsam_lm"])


def test_isam2_stays_exact_across_incremental_additions_and_removals():
    rng = np.random.default_rng(1)
    poses = [gtsam.Similarity3(gtsam.Rot3.Rx(0.1 * i), np.array([i, 0.0, 0.1 * i]), float(np.exp(0.03 * i)))
             for i in range(5)]
    noise = gtsam.noiseModel.Isotropic.Sigma(D, 0.1)
    gauge = GaugeConfig(hold_scale=False, world_scale_range=False)
    backend = Backend(BackendConfig(solver="isam2", gauge=gauge))

    def between(i, j):
        meas = poses[i].between(poses[j]).retract(0.02 * rng.standard_normal(D))
        return gtsam.BetweenFactorSimilarity3(pose_key(i), pose_key(j), meas, noise)

    for i in range(3):
        backend.add_keyframe(i, poses[i].retract(0.05 * rng.standard_normal(D)) if i else poses[i], float(i))
    handles = [backend.add_factor(between(0, 1)), backend.add_factor(between(1, 2)), backend.add_factor(between(0, 2))]
    backend.optimize_global()
    for i in (3, 4):  # new keyframes and factors
        backend.add_keyframe(i, poses[i].retract(0.05 * rng.standard_normal(D)), float(i))
        backend.add_factor(between(i - 1, i))
    backend.add_factor(between(1, 4))
    backend.remove_factor(handles[2])
    backend.optimize_global()
    expected = gtsam.LevenbergMarquardtOptimizer(backend.nonlinear_graph(), backend.values).optimize()
    for i in range(5):
        assert np.linalg.norm(expected.atSimilarity3(pose_key(i)).localCoordinates(backend.pose(i))) < 1e-6
