"""Tests of the Sim(3) between / loop residual against gtsam.BetweenFactorSimilarity3 and finite differences."""

import logging
import math

import gtsam
import numpy as np
import pytest
import torch

from fgslam.factors.sim3 import between_jacobian_factors, make_between_factors, sim3_between_residual
from fgslam.core.lie import Sim3

F64 = torch.float64


def random_sim3(n: int, seed: int, angle: float = 2.5, trans: float = 2.0, log_scale: float = 1.0) -> Sim3:
    g = torch.Generator().manual_seed(seed)
    axis = torch.randn(n, 3, generator=g, dtype=F64)
    axis = axis / axis.norm(dim=-1, keepdim=True)
    xi = torch.cat(
        [
            axis * torch.rand(n, 1, generator=g, dtype=F64) * angle,
            trans * torch.randn(n, 3, generator=g, dtype=F64),
            log_scale * (2 * torch.rand(n, 1, generator=g, dtype=F64) - 1),
        ],
        -1,
    )
    return Sim3.exp(xi)


def between_values(gi, gj) -> gtsam.Values:
    v = gtsam.Values()
    v.insert(0, gi)
    v.insert(1, gj)
    return v


def central_fd(f, batch: int, dof: int = 7, eps: float = 1e-6) -> torch.Tensor:
    """Batched central differences of f: (B, dof) -> (B, m) at 0; returns (B, m, dof)."""
    cols = []
    for k in range(dof):
        e = torch.zeros(batch, dof, dtype=F64)
        e[:, k] = eps
        cols.append((f(e) - f(-e)) / (2 * eps))
    return torch.stack(cols, -1)


@pytest.fixture(scope="module")
def configs():
    """Random poses; measurements = true relative pose perturbed by a large random error."""
    n = 200
    T_i, T_j = random_sim3(n, 1), random_sim3(n, 2)
    noise = random_sim3(n, 3, angle=1.0, trans=0.5, log_scale=0.3)
    Z_ij = (T_i.inverse() @ T_j) @ noise
    return T_i, T_j, Z_ij


def test_residual_equals_gtsam_unwhitened_error(configs):
    T_i, T_j, Z_ij = configs
    r, _, _ = sim3_between_residual(T_i, T_j, Z_ij)
    gi, gj, gz = T_i.to_gtsam(), T_j.to_gtsam(), Z_ij.to_gtsam()
    unit = gtsam.noiseModel.Unit.Create(7)
    worst = 0.0
    for k in range(len(gi)):
        f = gtsam.BetweenFactorSimilarity3(0, 1, gz[k], unit)
        worst = max(worst, np.abs(f.unwhitenedError(between_values(gi[k], gj[k])) - r[k].numpy()).max())
    assert worst < 1e-9


def test_exact_jacobians_vs_finite_differences(configs):
    T_i, T_j, Z_ij = configs
    _, J_i, J_j = sim3_between_residual(T_i, T_j, Z_ij)
    n = T_i.shape[0]
    fd_i = central_fd(lambda d: sim3_between_residual(T_i.retract(d), T_j, Z_ij)[0], n)
    fd_j = central_fd(lambda d: sim3_between_residual(T_i, T_j.retract(d), Z_ij)[0], n)
    assert torch.allclose(J_i, fd_i, atol=1e-6)
    assert torch.allclose(J_j, fd_j, atol=1e-6)


def test_first_order_jacobians_equal_gtsam_linearization(configs):
    """gtsam 4.3.0 linearises BetweenFactorSimilarity3 with -Ad(T_j^-1 T_i) and I (no Jr^-1)."""
    T_i, T_j, Z_ij = configs
    r, J_i, J_j = sim3_between_residual(T_i, T_j, Z_ij, exact=False)
    gi, gj, gz = T_i.to_gtsam(), T_j.to_gtsam(), Z_ij.to_gtsam()
    unit = gtsam.noiseModel.Unit.Create(7)
    for k in range(50):
        lin = gtsam.BetweenFactorSimilarity3(0, 1, gz[k], unit).linearize(between_values(gi[k], gj[k]))
        A, b = lin.jacobian()
        assert np.allclose(A[:, :7], J_i[k].numpy(), atol=1e-9), k
        assert np.allclose(A[:, 7:], J_j[k].numpy(), atol=1e-9), k
        assert np.allclose(b, -r[k].numpy(), atol=1e-9), k


def test_first_order_jacobian_error_is_of_residual_order():
    """|J_approx - J_exact| / |J_exact| shrinks linearly with |r| and vanishes at r = 0."""
    T_i, T_j = random_sim3(50, 4), random_sim3(50, 5)
    rel = []
    for size in (1e-1, 1e-2, 1e-3, 0.0):
        noise = random_sim3(50, 6, angle=size, trans=size, log_scale=size)
        Z_ij = (T_i.inverse() @ T_j) @ noise.inverse()
        r, Ji, Jj = sim3_between_residual(T_i, T_j, Z_ij)
        _, Ji0, Jj0 = sim3_between_residual(T_i, T_j, Z_ij, exact=False)
        rel.append(((Ji - Ji0).norm(dim=(-2, -1)) / Ji.norm(dim=(-2, -1))).max().item())
    assert rel[0] < 0.2 and rel[1] < 0.02 and rel[2] < 0.002
    assert rel[3] < 1e-12


def test_batched_broadcast_shapes():
    T = random_sim3(12, 7)
    T_i = Sim3(T.R.reshape(3, 4, 3, 3), T.t.reshape(3, 4, 3), T.s.reshape(3, 4))
    T_j = random_sim3(4, 8)  # broadcast against (3, 4)
    Z = random_sim3(1, 9)[0]
    r, J_i, J_j = sim3_between_residual(T_i, T_j, Z)
    assert r.shape == (3, 4, 7) and J_i.shape == (3, 4, 7, 7) and J_j.shape == (3, 4, 7, 7)
    r12, _, _ = sim3_between_residual(T_i[1, 2], T_j[2], Z)
    assert torch.allclose(r[1, 2], r12, atol=1e-12)


def test_float32_runs_and_is_close(configs):
    T_i, T_j, Z_ij = configs
    r64, Ji64, _ = sim3_between_residual(T_i[:20], T_j[:20], Z_ij[:20])
    f32 = [T[:20].to(torch.float32) for T in (T_i, T_j, Z_ij)]
    r32, Ji32, _ = sim3_between_residual(*f32)
    assert r32.dtype == torch.float32
    assert torch.allclose(r32.double(), r64, atol=1e-3)
    assert torch.allclose(Ji32.double(), Ji64, atol=1e-3 * max(1.0, Ji64.abs().max().item()))


def test_make_between_factors_noise_models(configs, caplog):
    T_i, T_j, Z_ij = configs
    n = 6
    sig = np.array([0.01, 0.02, 0.03, 0.1, 0.2, 0.3, 0.05])
    r, _, _ = sim3_between_residual(T_i[:n], T_j[:n], Z_ij[:n])
    gi, gj = T_i[:n].to_gtsam(), T_j[:n].to_gtsam()
    fs = make_between_factors(list(range(n)), list(range(n, 2 * n)), Z_ij[:n], sigmas=sig)
    for k, f in enumerate(fs):
        v = gtsam.Values()
        v.insert(k, gi[k])
        v.insert(n + k, gj[k])
        assert np.allclose(f.whitenedError(v), r[k].numpy() / sig, atol=1e-9)
    g = torch.Generator().manual_seed(10)
    L = torch.randn(n, 7, 7, generator=g, dtype=F64)
    info = (L @ L.transpose(-1, -2) + 0.5 * torch.eye(7, dtype=F64)).numpy()
    fs = make_between_factors(list(range(n)), list(range(n, 2 * n)), Z_ij[:n], information=info)
    for k, f in enumerate(fs):
        v = gtsam.Values()
        v.insert(k, gi[k])
        v.insert(n + k, gj[k])
        rk = r[k].numpy()
        assert np.isclose(f.error(v), 0.5 * rk @ info[k] @ rk, rtol=1e-9)
    # Huber: quadratic inside k, linear (smaller than quadratic) outside.
    fh = make_between_factors([0], [1], Z_ij[:1], sigmas=np.full(7, 1e-3), huber_k=1.0)[0]
    fq = make_between_factors([0], [1], Z_ij[:1], sigmas=np.full(7, 1e-3))[0]
    v = between_values(gi[0], gj[0])
    e = np.linalg.norm(r[0].numpy()) / 1e-3
    assert np.isclose(fh.error(v), e - 0.5, rtol=1e-9) and fh.error(v) < fq.error(v)
    # Degenerate measurements and noise are left out and counted.
    Z_bad = Sim3(Z_ij[:3].R.clone(), Z_ij[:3].t.clone(), Z_ij[:3].s.clone())
    Z_bad.t[1, 0] = math.nan
    bad_sig = np.tile(sig, (3, 1))
    bad_sig[2, 4] = 0.0
    with caplog.at_level(logging.WARNING, logger="fgslam.factors.sim3"):
        fs = make_between_factors([0, 1, 2], [3, 4, 5], Z_bad, sigmas=bad_sig)
    assert len(fs) == 1 and fs[0].keys() == [0, 3]
    assert "left out 2 of 3" in caplog.text
    bad_info = np.tile(np.eye(7), (3, 1, 1))
    bad_info[0, 3, 3] = -1.0
    Z_neg = Sim3(Z_ij[:3].R, Z_ij[:3].t, torch.tensor([1.0, -2.0, 1.0], dtype=F64))
    assert len(make_between_factors([0, 1, 2], [3, 4, 5], Z_neg, information=bad_info)) == 1
    with pytest.raises(ValueError):
        make_between_factors([0], [1], Z_ij[:1])
    with pytest.raises(ValueError):
        make_between_factors([0, 1], [1], Z_ij[:2], sigmas=sig)


def gtsam_cost_gradient(graph: gtsam.NonlinearFactorGraph, poses: Sim3, eps: float = 1e-6) -> np.ndarray:
    """Central-difference gradient of gtsam's graph.error w.r.t. right perturbations of all poses."""

    def cost(T: Sim3) -> float:
        v = gtsam.Values()
        for k, g in enumerate(T.to_gtsam()):
            v.insert(k, g)
        return graph.error(v)

    n = poses.shape[0]
    grad = np.zeros(7 * n)
    for m in range(7 * n):
        d = torch.zeros(n, 7, dtype=F64)
        d.view(-1)[m] = eps
        grad[m] = (cost(poses.retract(d)) - cost(poses.retract(-d))) / (2 * eps)
    return grad


def test_gauss_newton_with_exact_jacobians_reaches_true_optimum():
    """A 6-pose Sim(3) loop with inconsistent measurements, optimised by a Python Gauss-Newton on
    between_jacobian_factors (exact Jacobians) and by gtsam LM on the same built-in factors. The
    cost (gtsam's graph.error) is the same function; our result is a stationary point of it.
    gtsam 4.3.0's first-order Jacobians make its LM stop early at a slightly higher cost."""
    n = 6
    truth = random_sim3(n, 11, angle=1.0)
    edges = [(k, k + 1) for k in range(n - 1)] + [(0, n - 1), (1, 4)]
    ii, jj = [e[0] for e in edges], [e[1] for e in edges]
    noise = random_sim3(len(edges), 12, angle=0.2, trans=0.2, log_scale=0.1)
    Z = (truth[ii].inverse() @ truth[jj]) @ noise
    sig = np.array([0.05] * 3 + [0.1] * 3 + [0.02])
    graph = gtsam.NonlinearFactorGraph()
    for f in make_between_factors(ii, jj, Z, sigmas=sig):
        graph.add(f)
    graph.add(gtsam.PriorFactorSimilarity3(0, truth[0].to_gtsam(), gtsam.noiseModel.Isotropic.Sigma(7, 1e-6)))
    init = gtsam.Values()
    start = truth.retract(0.3 * torch.randn(n, 7, dtype=F64, generator=torch.Generator().manual_seed(13)))
    start_g = start.to_gtsam()
    for k in range(n):
        init.insert(k, start_g[k])
    params = gtsam.LevenbergMarquardtParams()
    params.setRelativeErrorTol(1e-14)
    params.setAbsoluteErrorTol(1e-14)
    params.setMaxIterations(200)
    result = gtsam.LevenbergMarquardtOptimizer(graph, init, params).optimize()
    ref = Sim3.from_gtsam([result.atSimilarity3(k) for k in range(n)])

    # Python-driven Gauss-Newton: exact between linearisations + gtsam's linearisation of the prior.
    prior_graph = gtsam.NonlinearFactorGraph()
    prior_graph.add(graph.at(graph.size() - 1))
    T = start
    for _ in range(30):
        values = gtsam.Values()
        for k, g in enumerate(T.to_gtsam()):
            values.insert(k, g)
        gfg = prior_graph.linearize(values)
        for f in between_jacobian_factors(ii, jj, T[ii], T[jj], Z, sigmas=sig):
            gfg.add(f)
        delta = gfg.optimize()
        dx = torch.tensor(np.stack([delta.at(k) for k in range(n)]), dtype=F64)
        T = T.retract(dx)
        if dx.abs().max() < 1e-12:
            break
    # Gradient w.r.t. the free poses 1..n-1 (pose 0's stiff prior only adds rounding noise).
    ours, theirs = gtsam_cost_gradient(graph, T)[7:], gtsam_cost_gradient(graph, ref)[7:]
    assert np.abs(ours).max() < 1e-5 and np.abs(theirs).max() > 1e-2
    v_ours, v_ref = gtsam.Values(), gtsam.Values()
    for k, (a, b) in enumerate(zip(T.to_gtsam(), ref.to_gtsam())):
        v_ours.insert(k, a)
        v_ref.insert(k, b)
    assert graph.error(v_ours) <= graph.error(v_ref)
    # Started at our optimum, gtsam's LM stays there (same cost function, no descent left).
    again = gtsam.LevenbergMarquardtOptimizer(graph, v_ours, params).optimize()
    assert np.isclose(graph.error(again), graph.error(v_ours), rtol=1e-12)


@pytest.mark.parametrize("noise_kind", ["sigmas", "information", "huber"])
def test_jacobian_factors_match_gtsam_linearize(configs, noise_kind):
    """exact=False reproduces gtsam's own linearisation (same quadratic form); exact=True has A = S J."""
    T_i, T_j, Z_ij = configs
    n = 30
    g = torch.Generator().manual_seed(14)
    sig = 0.05 + torch.rand(n, 7, generator=g, dtype=F64).numpy()
    L = torch.randn(n, 7, 7, generator=g, dtype=F64)
    info = (L @ L.transpose(-1, -2) + torch.eye(7, dtype=F64)).numpy()
    kw = {
        "sigmas": {"sigmas": sig},
        "information": {"information": info},
        "huber": {"sigmas": sig, "huber_k": 2.0},
    }[noise_kind]
    keys_i, keys_j = list(range(n)), list(range(n, 2 * n))
    ours = between_jacobian_factors(keys_i, keys_j, T_i[:n], T_j[:n], Z_ij[:n], exact=False, **kw)
    exact = between_jacobian_factors(keys_i, keys_j, T_i[:n], T_j[:n], Z_ij[:n], **kw)
    built = make_between_factors(keys_i, keys_j, Z_ij[:n], **kw)
    _, J_i, J_j = sim3_between_residual(T_i[:n], T_j[:n], Z_ij[:n])
    gi, gj = T_i[:n].to_gtsam(), T_j[:n].to_gtsam()
    for k in range(n):
        v = gtsam.Values()
        v.insert(k, gi[k])
        v.insert(n + k, gj[k])
        A_ref, b_ref = built[k].linearize(v).jacobian()
        A, b = ours[k].jacobian()
        assert ours[k].keys() == [k, n + k]
        assert np.allclose(A.T @ A, A_ref.T @ A_ref, rtol=1e-9, atol=1e-9 * np.abs(A_ref.T @ A_ref).max())
        assert np.allclose(A.T @ b, A_ref.T @ b_ref, rtol=1e-9, atol=1e-9 * np.abs(A_ref.T @ b_ref).max())
        assert np.isclose(b @ b, b_ref @ b_ref, rtol=1e-9)
        # Exact: same b, Jacobian blocks S J (up to the common row scaling/rotation S).
        A_x, b_x = exact[k].jacobian()
        assert np.allclose(b_x, b, atol=1e-12)
        S = A[:, 7:]  # exact=False has J_j = I, so its A_j block is the (reweighted) square-root information
        assert np.allclose(A_x[:, :7], S @ J_i[k].numpy(), atol=1e-9 * max(1.0, np.abs(A_x).max()))
        assert np.allclose(A_x[:, 7:], S @ J_j[k].numpy(), atol=1e-9 * max(1.0, np.abs(A_x).max()))
