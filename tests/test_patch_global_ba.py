"""Global bundle adjustment of the patch graph (fgslam.backend.global_ba): its sparse
per-source-frame Schur reduction against the dense PatchBlock reduction, recovery of the truth,
outlier handling, a drifted chain closed by loop edges, and bad input."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from fgslam.backend.config import GlobalBAConfig
from fgslam.backend.global_ba import GlobalBAProblem, _Problem, global_bundle_adjustment
from fgslam.core.errors import OptimizationError
from fgslam.factors.reprojection import ReprojectionConfig, reproject
from fgslam.frontends.patch.ba import PatchBlock
from fgslam.core.lie import Sim3

K = np.array([300.0, 300.0, 160.0, 120.0])
W, H = 320, 240


def _pose(yaw: float, t) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    T = np.eye(4)
    T[:3, :3] = [[c, 0, s], [0, 1, 0], [-s, 0, c]]
    T[:3, 3] = t
    return T


def _perturb(T: np.ndarray, rng, rot: float, trans: float) -> np.ndarray:
    xi = np.concatenate([rng.normal(0, rot, 3), rng.normal(0, trans, 3), [0.0]])
    return T @ Sim3.exp(torch.as_tensor(xi)).matrix().numpy()


def make_problem(rng, frames=8, patches=24, lifetime=3, stereo=False, priors=False, noise=0.0,
                 circle=False, loop_pairs=()):
    """Frames moving forward (or round a circle), patches at random depths, edges to the frames at
    most ``lifetime`` away (plus ``loop_pairs`` (i, j) both ways), observations from the truth."""
    if circle:
        ang = np.linspace(0, 2 * np.pi, frames, endpoint=False)
        T_true = np.stack([_pose(-a, [3 * np.sin(a), 0, 3 * np.cos(a) - 3]) for a in ang])
    else:
        T_true = np.stack([_pose(0.02 * i, [0.05 * i, 0.01 * i, 0.3 * i]) for i in range(frames)])
    T_CRCL = np.eye(4)
    T_CRCL[0, 3] = -0.1
    uv_p = np.stack([rng.uniform(20, W - 20, frames * patches), rng.uniform(20, H - 20, frames * patches)], 1)
    d_true = 1.0 / rng.uniform(2.0, 6.0, frames * patches)
    owner = np.repeat(np.arange(frames), patches)
    pairs = [(i, j) for i in range(frames) for j in range(frames) if i != j and abs(i - j) <= lifetime]
    pairs += [p for a, b in loop_pairs for p in ((a, b), (b, a))]
    src, tgt, right, sidx = [], [], [], []
    for i, j in pairs:
        ps = np.nonzero(owner == i)[0]
        src += [i] * len(ps); tgt += [j] * len(ps); right += [False] * len(ps); sidx += list(ps)
    if stereo:
        for i in range(frames):
            ps = np.nonzero(owner == i)[0]
            src += [i] * len(ps); tgt += [i] * len(ps); right += [True] * len(ps); sidx += list(ps)
    src, tgt, right, sidx = map(np.array, (src, tgt, right, sidx))
    Tt = torch.as_tensor(T_true)
    uv = np.zeros((len(src), 2))
    ok = np.zeros(len(src), bool)
    for r_flag in (False, True):
        m = right == r_flag
        if not m.any():
            continue
        R, t, s = Tt[:, :3, :3], Tt[:, :3, 3], torch.ones(frames, dtype=torch.float64)
        a, b = torch.as_tensor(src[m]), torch.as_tensor(tgt[m])
        proj, valid = reproject(torch.as_tensor(uv_p[sidx[m]]), torch.as_tensor(d_true[sidx[m]]), (R[a], t[a], s[a]),
                                (R[b], t[b], s[b]), torch.as_tensor(K), torch.as_tensor(K),
                                T_CtCj=torch.as_tensor(T_CRCL) if r_flag else None)
        uv[m], ok[m] = proj.numpy(), valid.numpy()
    inside = ok & (uv[:, 0] > 0) & (uv[:, 0] < W) & (uv[:, 1] > 0) & (uv[:, 1] < H)
    src, tgt, right, sidx, uv = src[inside], tgt[inside], right[inside], sidx[inside], uv[inside]
    uv = uv + rng.normal(0, noise, uv.shape) if noise else uv
    fixed = np.zeros(frames, bool)
    fixed[:2] = True
    prior = {}
    if priors:
        idx = np.arange(0, frames * patches, 3)
        prior = dict(prior_idx=idx, prior_value=d_true[idx], prior_weight=np.full(len(idx), 400.0))
    prob = GlobalBAProblem(T_WC=T_true.copy(), fixed=fixed, src=src, tgt=tgt, right=right, uv_src=uv_p[sidx], uv=uv,
                           weight=rng.uniform(0.5, 1.0, len(src)), struct_idx=sidx, inv_depth=d_true.copy(), K=K,
                           K_right=K if stereo else None, T_CRCL=T_CRCL if stereo else None, **prior)
    return prob, T_true, d_true


@pytest.mark.parametrize("stereo,priors", [(False, False), (True, True)])
def test_sparse_reduction_equals_dense_patch_block(stereo, priors):
    """H and g of the per-source-frame reduction (one GTSAM factor per source frame, the structure
    eliminated by schur.py's batched elimination) equal PatchBlock's dense Schur
    complement (scale rows dropped), at a perturbed state with fixed frames, several chunks and
    right edges."""
    import gtsam

    rng = np.random.default_rng(3)
    prob, T_true, d_true = make_problem(rng, stereo=stereo, priors=priors)
    T0 = np.stack([_perturb(T, rng, 0.01, 0.02) for T in T_true])
    d0 = d_true * rng.uniform(0.8, 1.2, d_true.shape)
    rep = ReprojectionConfig(min_depth=0.05)
    cfg = GlobalBAConfig(chunk_edges=150)  # several chunks
    p = _Problem(prob, cfg, rep)
    assert len(p.chunks) > 2
    system = p.linearize(torch.as_tensor(T0), torch.as_tensor(d0))
    V = p.V
    H_sparse, g_sparse = system.dense()
    var = np.nonzero(~prob.fixed)[0]
    fixed = np.nonzero(prob.fixed)[0]
    local = np.empty(len(T0), np.int64)
    local[var] = np.arange(len(var))
    local[fixed] = len(var) + np.arange(len(fixed))
    Tf = torch.as_tensor(T0[fixed])
    keys = [gtsam.symbol("x", int(f)) for f in var]
    extra = {}
    if priors:
        extra = dict(prior_idx=prob.prior_idx, prior_value=prob.prior_value, prior_weight=prob.prior_weight)
    block = PatchBlock(keys, Tf[:, :3, :3], Tf[:, :3, 3], torch.ones(len(fixed), dtype=torch.float64),
                       local[prob.src], local[prob.tgt], prob.right, prob.uv_src, prob.uv, prob.weight,
                       prob.struct_idx, K, d0, K_right=prob.K_right, T_CRCL=prob.T_CRCL, reprojection=rep, **extra)
    values = gtsam.Values()
    for f, key in zip(var, keys):
        values.insert(key, Sim3.from_matrix(torch.as_tensor(T0[f])).to_gtsam())
    _, H_dense, g_dense, _ = block.linearize(values)[0]
    keep = np.concatenate([np.arange(7 * i, 7 * i + 6) for i in range(V)])
    H_ref, g_ref = H_dense[np.ix_(keep, keep)], g_dense[keep]
    scale = np.abs(H_ref).max()
    assert np.abs(H_sparse - H_ref).max() <= 1e-9 * scale
    assert np.abs(g_sparse - g_ref).max() <= 1e-9 * np.abs(g_ref).max()
    # back-substitution agrees as well
    dx = rng.normal(0, 1e-3, (V, 6))
    dd = p.back_substitute(torch.as_tensor(dx))
    dx7 = np.concatenate([np.concatenate([row, [0.0]]) for row in dx])
    dd_ref = block.back_substitute(dx7).numpy()
    assert np.allclose(dd.numpy(), dd_ref, atol=1e-9 * max(1.0, np.abs(dd_ref).max()))


def test_recovers_the_truth_from_perturbed_poses_and_depths():
    rng = np.random.default_rng(0)
    prob, T_true, d_true = make_problem(rng, frames=10, patches=30)
    T0 = T_true.copy()
    for i in range(2, len(T0)):
        T0[i] = _perturb(T_true[i], rng, 0.01, 0.03)
    prob.T_WC = T0
    prob.inv_depth = d_true * rng.uniform(0.85, 1.15, d_true.shape)
    res = global_bundle_adjustment(prob, GlobalBAConfig(iterations=30, robust_rounds=1, relative_tolerance=1e-14))
    assert res.initial_cost > 1.0
    assert res.final_cost < 1e-10 * res.initial_cost
    assert np.abs(res.T_WC - T_true).max() < 1e-6
    assert np.allclose(res.T_WC[:2], T_true[:2])  # fixed frames untouched
    used = np.unique(prob.struct_idx)
    assert np.abs(res.inv_depth[used] - d_true[used]).max() < 1e-6
    assert res.num_variables == 8 and res.num_edges == len(prob.src)


def test_outliers_get_zero_weight_and_do_not_bias_the_result():
    rng = np.random.default_rng(1)
    prob, T_true, d_true = make_problem(rng, frames=10, patches=30, noise=0.3)
    bad = rng.choice(len(prob.src), len(prob.src) // 20, replace=False)
    prob.uv = prob.uv.copy()
    prob.uv[bad] += rng.uniform(15, 40, (len(bad), 2)) * rng.choice([-1, 1], (len(bad), 2))
    T0 = T_true.copy()
    for i in range(2, len(T0)):
        T0[i] = _perturb(T_true[i], rng, 0.005, 0.02)
    prob.T_WC = T0
    res = global_bundle_adjustment(prob, GlobalBAConfig(iterations=15, robust_rounds=3))
    assert (res.robust[bad] == 0).mean() > 0.95
    good = np.setdiff1d(np.arange(len(prob.src)), bad)
    assert (res.robust[good] > 0).mean() > 0.98
    err = np.linalg.norm(res.T_WC[:, :3, 3] - T_true[:, :3, 3], axis=1).max()
    assert err < 0.01
    # plain least squares (one round, no kernel) is visibly biased by the same outliers
    plain = global_bundle_adjustment(prob, GlobalBAConfig(iterations=15, robust_rounds=1, huber_first_round=False))
    assert np.linalg.norm(plain.T_WC[:, :3, 3] - T_true[:, :3, 3], axis=1).max() > 2 * err


def test_loop_edges_close_a_drifted_circle():
    """A circle whose poses carry accumulated drift: local edges alone keep it, loop edges between
    the last and the first frames pull it back to the truth."""
    rng = np.random.default_rng(2)
    n = 24
    prob, T_true, d_true = make_problem(rng, frames=n, patches=40, lifetime=2, circle=True, noise=0.2,
                                        loop_pairs=[(n - 1, 0), (n - 1, 1), (n - 2, 0)])
    drift = Sim3.exp(torch.tensor([0.0, 0.01, 0.0, 0.01, 0.0, 0.02, 0.0], dtype=torch.float64)).matrix().numpy()
    T0 = T_true.copy()
    for i in range(2, n):  # odometry drift grows along the circle
        T0[i] = T0[i - 1] @ drift @ np.linalg.inv(T_true[i - 1]) @ T_true[i]
    prob.T_WC = T0
    before = np.linalg.norm(T0[:, :3, 3] - T_true[:, :3, 3], axis=1).max()
    res = global_bundle_adjustment(prob, GlobalBAConfig(iterations=20, robust_rounds=2))
    after = np.linalg.norm(res.T_WC[:, :3, 3] - T_true[:, :3, 3], axis=1).max()
    assert before > 0.5
    assert after < 0.05 * before
    loop = (prob.src >= n - 2) & (prob.tgt <= 1)
    assert (res.robust[loop] > 0).mean() > 0.9


def test_bad_input_is_rejected():
    rng = np.random.default_rng(4)
    prob, _, _ = make_problem(rng, frames=4, patches=8)
    with pytest.raises(OptimizationError, match="shape"):
        global_bundle_adjustment(GlobalBAProblem(**{**prob.__dict__, "uv": prob.uv[:-1]}))
    wrong_owner = prob.src.copy()
    e = int(np.nonzero(prob.src == 1)[0][0])
    wrong_owner[e] = 2  # the patch of edge e now belongs to two source frames
    with pytest.raises(OptimizationError, match="one source frame"):
        global_bundle_adjustment(GlobalBAProblem(**{**prob.__dict__, "src": wrong_owner}))
    nan_w = prob.weight.copy()
    nan_w[0] = np.nan
    with pytest.raises(OptimizationError, match="weights"):
        global_bundle_adjustment(GlobalBAProblem(**{**prob.__dict__, "weight": nan_w}))
    with pytest.raises(OptimizationError, match="right-image"):
        global_bundle_adjustment(GlobalBAProblem(**{**prob.__dict__, "right": np.ones_like(prob.right)}))


def test_everything_fixed_or_no_edges_returns_the_input():
    rng = np.random.default_rng(5)
    prob, T_true, d_true = make_problem(rng, frames=4, patches=8)
    prob.fixed[:] = True
    res = global_bundle_adjustment(prob, GlobalBAConfig())
    assert np.array_equal(res.T_WC, T_true) and res.num_variables == 0


@pytest.mark.parametrize("stereo", [False, True])
@pytest.mark.parametrize("frames,lifetime,loops", [(8, 3, ()), (40, 4, ((38, 2), (39, 5), (30, 0)))])
def test_lm_loop_steps_solve_the_marquardt_damped_system(frames, lifetime, loops, stereo):
    """The backend's LM loop on the global BA's factors (one per source frame) takes the step
    ``-(H + diag(damping_diagonal(diag H, lambda)))^-1 g`` of the explicit reduced system at every
    damping it tries, on a small and a medium problem (loop edges, a fixed frame inside some
    source frames' slots, padded slots), mono and stereo."""
    from fgslam.backend.solver import LMSettings, damping_diagonal, levenberg_marquardt

    rng = np.random.default_rng(11)
    prob, T_true, d_true = make_problem(rng, frames=frames, patches=20, lifetime=lifetime, stereo=stereo,
                                        circle=bool(loops), loop_pairs=loops, noise=0.3)
    T0 = np.stack([T if f else _perturb(T, rng, 0.01, 0.02) for T, f in zip(T_true, prob.fixed)])
    d0 = torch.as_tensor(d_true * rng.uniform(0.8, 1.2, d_true.shape))
    p = _Problem(prob, GlobalBAConfig(chunk_edges=400), ReprojectionConfig(min_depth=0.05))
    system = p.linearize(torch.as_tensor(T0), d0)
    H, g = system.dense()

    class Rejecting:  # every step rejected: one solve per damping, lambda 1e-6 .. 1e1
        steps = []

        def cost(self):
            return 1.0

        def linearize(self):
            return system.graph

        def hessian_diagonal(self):
            return system.hessian_diagonal()

        def trial(self, delta):
            self.steps.append(np.asarray(delta.vector()))
            return float("inf"), None

    problem = Rejecting()
    settings = LMSettings(max_iterations=1, lambda_initial=1e-6, lambda_factor=10.0, lambda_max=10.0,
                          damping="marquardt", ordering="metis")
    levenberg_marquardt(problem, settings)
    assert len(problem.steps) == 8
    for lam, dx in zip(1e-6 * 10.0 ** np.arange(8), problem.steps):
        expected = -np.linalg.solve(H + np.diag(damping_diagonal(np.diag(H), lam)), g)
        assert np.abs(expected).max() > 1e-6  # a real step
        assert np.abs(dx - expected).max() <= 1e-9 * np.abs(expected).max()
    # damping acts: the steps shrink as lambda grows
    norms = [np.linalg.norm(dx) for dx in problem.steps]
    assert norms[0] > norms[5] > norms[7]
