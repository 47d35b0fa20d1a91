"""Tests of fgslam.core.lie against gtsam 4.3.0 (Pose3 / Similarity3), matrix exponentials and finite differences."""

import math

import gtsam
import numpy as np
import pytest
import torch

from fgslam.core.lie import SE3, Sim3, sim3_matrix_components, sim3_matrix_parts, stack
from fgslam.core.so3 import skew, so3_exp, so3_log

F64 = torch.float64
N_RANDOM = 1000


def random_tangent(n: int, dof: int, seed: int, max_angle: float = math.pi - 1e-3) -> torch.Tensor:
    """Random tangents with rotation angle uniform in [0, max_angle), translation ~ N(0, 2^2),
    log-scale uniform in [-1.5, 1.5] (Sim3)."""
    g = torch.Generator().manual_seed(seed)
    axis = torch.randn(n, 3, generator=g, dtype=F64)
    axis = axis / axis.norm(dim=-1, keepdim=True)
    angle = torch.rand(n, 1, generator=g, dtype=F64) * max_angle
    parts = [axis * angle, 2 * torch.randn(n, 3, generator=g, dtype=F64)]
    if dof == 7:
        parts.append(3 * torch.rand(n, 1, generator=g, dtype=F64) - 1.5)
    return torch.cat(parts, -1)


def hat_sim3(xi: torch.Tensor) -> torch.Tensor:
    """Standard-form algebra element [[skew(w) + lambda I, u], [0, 0]] (4x4)."""
    M = torch.zeros(*xi.shape[:-1], 4, 4, dtype=xi.dtype)
    M[..., :3, :3] = skew(xi[..., :3]) + xi[..., 6, None, None] * torch.eye(3, dtype=xi.dtype)
    M[..., :3, 3] = xi[..., 3:6]
    return M


def gtsam_sim3_std_matrix(S: gtsam.Similarity3) -> np.ndarray:
    """gtsam's [[R, t_g], [0, 1/s]] times s = the standard [[sR, t], [0, 1]]."""
    return S.matrix() * S.scale()


# ---------------------------------------------------------------- random agreement with gtsam


@pytest.fixture(scope="module")
def sim3_pairs():
    xa, xb = random_tangent(N_RANDOM, 7, 1), random_tangent(N_RANDOM, 7, 2)
    return xa, xb, Sim3.exp(xa), Sim3.exp(xb)


@pytest.fixture(scope="module")
def se3_pairs():
    xa, xb = random_tangent(N_RANDOM, 6, 3), random_tangent(N_RANDOM, 6, 4)
    return xa, xb, SE3.exp(xa), SE3.exp(xb)


def test_sim3_matches_gtsam_on_random_elements(sim3_pairs):
    xa, xb, A, B = sim3_pairs
    ga, gb = A.to_gtsam(), B.to_gtsam()
    AB, Ainv, logA = (A @ B).matrix().numpy(), A.inverse().matrix().numpy(), A.log().numpy()
    Ad, ret, loc = A.adjoint().numpy(), A.retract(xb).matrix().numpy(), A.local(B).numpy()
    X = torch.randn(N_RANDOM, 3, dtype=F64, generator=torch.Generator().manual_seed(5))
    AX, Am = A.act(X).numpy(), A.matrix().numpy()
    errs = {k: 0.0 for k in ["exp", "log", "compose", "inverse", "act", "adjoint", "retract", "local", "roundtrip"]}
    for i in range(N_RANDOM):
        e = gtsam.Similarity3.Expmap(xa[i].numpy())
        errs["exp"] = max(errs["exp"], np.abs(gtsam_sim3_std_matrix(e) - Am[i]).max())
        errs["log"] = max(errs["log"], np.abs(gtsam.Similarity3.Logmap(ga[i]) - logA[i]).max())
        errs["compose"] = max(errs["compose"], np.abs(gtsam_sim3_std_matrix(ga[i].compose(gb[i])) - AB[i]).max())
        errs["inverse"] = max(errs["inverse"], np.abs(gtsam_sim3_std_matrix(ga[i].inverse()) - Ainv[i]).max())
        errs["act"] = max(errs["act"], np.abs(ga[i].transformFrom(X[i].numpy()) - AX[i]).max())
        errs["adjoint"] = max(errs["adjoint"], np.abs(ga[i].AdjointMap() - Ad[i]).max())
        g_ret = gtsam_sim3_std_matrix(ga[i].retract(xb[i].numpy()))
        errs["retract"] = max(errs["retract"], np.abs(g_ret - ret[i]).max())
        errs["local"] = max(errs["local"], np.abs(ga[i].localCoordinates(gb[i]) - loc[i]).max())
    errs["roundtrip"] = (A.log() - xa).abs().max().item()
    assert all(v < 1e-9 for v in errs.values()), errs


def test_se3_matches_gtsam_on_random_elements(se3_pairs):
    xa, xb, A, B = se3_pairs
    ga, gb = A.to_gtsam(), B.to_gtsam()
    AB, Ainv, logA = (A @ B).matrix().numpy(), A.inverse().matrix().numpy(), A.log().numpy()
    Ad, ret, loc = A.adjoint().numpy(), A.retract(xb).matrix().numpy(), A.local(B).numpy()
    X = torch.randn(N_RANDOM, 3, dtype=F64, generator=torch.Generator().manual_seed(6))
    AX, Am = A.act(X).numpy(), A.matrix().numpy()
    errs = {k: 0.0 for k in ["exp", "log", "compose", "inverse", "act", "adjoint", "retract", "local"]}
    for i in range(N_RANDOM):
        errs["exp"] = max(errs["exp"], np.abs(gtsam.Pose3.Expmap(xa[i].numpy()).matrix() - Am[i]).max())
        errs["log"] = max(errs["log"], np.abs(gtsam.Pose3.Logmap(ga[i]) - logA[i]).max())
        errs["compose"] = max(errs["compose"], np.abs(ga[i].compose(gb[i]).matrix() - AB[i]).max())
        errs["inverse"] = max(errs["inverse"], np.abs(ga[i].inverse().matrix() - Ainv[i]).max())
        errs["act"] = max(errs["act"], np.abs(ga[i].transformFrom(X[i].numpy()) - AX[i]).max())
        errs["adjoint"] = max(errs["adjoint"], np.abs(ga[i].AdjointMap() - Ad[i]).max())
        errs["retract"] = max(errs["retract"], np.abs(ga[i].retract(xb[i].numpy()).matrix() - ret[i]).max())
        errs["local"] = max(errs["local"], np.abs(ga[i].localCoordinates(gb[i]) - loc[i]).max())
    assert all(v < 1e-9 for v in errs.values()), errs
    assert (A.log() - xa).abs().max() < 1e-9


def test_from_gtsam_roundtrip(sim3_pairs, se3_pairs):
    A = sim3_pairs[2][:50]
    back = Sim3.from_gtsam(A.to_gtsam())
    assert torch.allclose(back.matrix(), A.matrix(), atol=1e-12)
    P = se3_pairs[2][:50]
    assert torch.allclose(SE3.from_gtsam(P.to_gtsam()).matrix(), P.matrix(), atol=1e-12)
    grid = A[:6]
    grid = Sim3(grid.R.reshape(2, 3, 3, 3), grid.t.reshape(2, 3, 3), grid.s.reshape(2, 3))
    flat = grid.to_gtsam()
    assert len(flat) == 6 and np.allclose(gtsam_sim3_std_matrix(flat[4]), grid[1, 1].matrix().numpy(), atol=1e-12)
    g32 = A[5].to(torch.float32).to_gtsam().rotation().matrix()
    assert np.allclose(g32 @ g32.T, np.eye(3), atol=1e-14) and np.allclose(g32, A[5].R.numpy(), atol=1e-6)
    one = Sim3.from_gtsam(A[3].to_gtsam())
    assert one.shape == () and torch.allclose(one.matrix(), A[3].matrix(), atol=1e-12)
    # The documented mapping: Similarity3(Rot3(R), t / s, s).
    g = A[7].to_gtsam()
    assert np.allclose(g.translation() * g.scale(), A[7].t.numpy(), atol=1e-12)
    assert np.isclose(g.scale(), A[7].s.item())


def test_ad_matches_gtsam_and_adjoint_identity():
    xi = random_tangent(20, 7, 7, max_angle=2.0)
    eta = random_tangent(20, 7, 8, max_angle=2.0)
    T = Sim3.exp(xi)
    for i in range(20):
        assert np.allclose(gtsam.Similarity3.adjointMap(xi[i].numpy()), Sim3.ad(xi[i]).numpy(), atol=1e-12)
    lhs = (T @ Sim3.exp(eta) @ T.inverse()).matrix()
    rhs = Sim3.exp((T.adjoint() @ eta[..., None])[..., 0]).matrix()
    assert torch.allclose(lhs, rhs, atol=1e-9)
    xs, es = random_tangent(20, 6, 9, max_angle=2.0), random_tangent(20, 6, 10, max_angle=2.0)
    P = SE3.exp(xs)
    for i in range(20):
        assert np.allclose(gtsam.Pose3.adjointMap(xs[i].numpy()), SE3.ad(xs[i]).numpy(), atol=1e-12)
    lhs = (P @ SE3.exp(es) @ P.inverse()).matrix()
    assert torch.allclose(lhs, SE3.exp((P.adjoint() @ es[..., None])[..., 0]).matrix(), atol=1e-9)


# ---------------------------------------------------------------- edge cases


EDGE_VALUES = [0.0, 1e-14, 1e-10, 1e-7, 1e-4, 3e-3, 1e-2 - 1e-9, 1e-2 + 1e-9, 0.05, 0.1 - 1e-7, 0.1 + 1e-7, 0.7]


@pytest.mark.parametrize("lam_abs", EDGE_VALUES + [1.9999999, 2.0000001, 4.0])
@pytest.mark.parametrize("theta", EDGE_VALUES)
def test_sim3_exp_log_small_angle_small_lambda(theta, lam_abs):
    """Exp against torch's matrix exponential of the 4x4 algebra element, Log(Exp) = id, no NaN."""
    axis = torch.tensor([0.48, -0.6, 0.64], dtype=F64)
    for lam in (lam_abs, -lam_abs):
        xi = torch.cat([theta * axis, torch.tensor([0.3, -1.2, 2.0], dtype=F64), torch.tensor([lam], dtype=F64)])
        T = Sim3.exp(xi)
        ref = torch.linalg.matrix_exp(hat_sim3(xi))
        assert torch.allclose(T.matrix(), ref, rtol=0, atol=1e-13), (theta, lam)
        back = T.log()
        assert torch.isfinite(back).all()
        assert torch.allclose(back, xi, rtol=0, atol=1e-12), (theta, lam, back - xi)
        T32 = Sim3.exp(xi.float())
        scale = max(1.0, ref.abs().max().item())  # float32 errors are relative to the largest entry
        assert torch.allclose(T32.matrix().double(), ref, rtol=0, atol=2e-6 * scale)
        assert torch.allclose(T32.log().double(), xi, rtol=0, atol=5e-5 * scale)


def test_gtsam_agrees_on_a_small_angle_small_lambda_grid():
    """Exp and Log vs gtsam over theta in [0, 2.5], |lambda| in [0, 3.2] (log-spaced near 0); gtsam
    switches to series at theta^2, lambda^2 < 1e-9 and stays within 1e-10 of the exact value."""
    axis = np.array([0.48, -0.6, 0.64])
    thetas = np.concatenate([[0.0], np.logspace(-7, 0.4, 12)])
    lams = np.concatenate([[0.0], np.logspace(-7, 0.5, 12), -np.logspace(-7, 0.5, 12)])
    xi = np.array([np.concatenate([th * axis, [0.3, -1.2, 2.0], [lam]]) for th in thetas for lam in lams])
    mine = Sim3.exp(torch.tensor(xi))
    ref = torch.linalg.matrix_exp(hat_sim3(torch.tensor(xi))).numpy()
    mine_m, mine_log = mine.matrix().numpy(), mine.log().numpy()
    worst_gtsam = worst_mine = worst_log = 0.0
    for k in range(len(xi)):
        g = gtsam.Similarity3.Expmap(xi[k])
        worst_gtsam = max(worst_gtsam, np.abs(gtsam_sim3_std_matrix(g) - ref[k]).max())
        worst_mine = max(worst_mine, np.abs(mine_m[k] - ref[k]).max())
        worst_log = max(worst_log, np.abs(gtsam.Similarity3.Logmap(g) - mine_log[k]).max())
    assert worst_mine < 1e-11 and worst_gtsam < 1e-9 and worst_log < 1e-9, (worst_mine, worst_gtsam, worst_log)


def test_identity_has_no_nan_and_zero_log():
    for G, dof in ((SE3, 6), (Sim3, 7)):
        for dtype in (torch.float32, F64):
            I = G.identity((2, 3), dtype=dtype)
            assert I.shape == (2, 3) and I.dtype == dtype
            xi = I.log()
            assert xi.shape == (2, 3, dof) and torch.all(xi == 0)
            assert torch.equal(G.exp(torch.zeros(dof, dtype=dtype)).matrix(), torch.eye(4, dtype=dtype))


@pytest.mark.parametrize("delta", [0.0, 1e-12, 1e-9, 1e-6, 1e-3, 0.1, 0.6, 1.2])
def test_so3_log_near_pi(delta):
    g = torch.Generator().manual_seed(11)
    axis = torch.randn(50, 3, generator=g, dtype=F64)
    axis = axis / axis.norm(dim=-1, keepdim=True)
    w = (math.pi - delta) * axis
    R = so3_exp(w)
    w_back = so3_log(R)
    assert torch.isfinite(w_back).all()
    # Exp(Log R) = R, the angle is recovered, and the vector is w itself except exactly at pi (+-w).
    assert torch.allclose(so3_exp(w_back), R, atol=1e-12)
    assert torch.allclose(w_back.norm(dim=-1), w.norm(dim=-1), atol=1e-9)
    if delta >= 1e-9:
        assert torch.allclose(w_back, w, atol=1e-6 if delta < 1e-6 else 1e-10)
    for i in range(5):
        gw = gtsam.Rot3.Logmap(gtsam.Rot3(R[i].numpy()))
        assert np.allclose(gtsam.Rot3.Expmap(gw).matrix(), R[i].numpy(), atol=1e-9)
        if delta >= 1e-6:
            assert np.allclose(gw, w_back[i].numpy(), atol=1e-8)
    # float32 stays finite and close.
    w32 = so3_log(R.float())
    assert torch.isfinite(w32).all()
    assert torch.allclose(so3_exp(w32).double(), R, atol=1e-5)


# ---------------------------------------------------------------- float32, batching, containers


def test_float32_close_to_float64(sim3_pairs):
    xa, xb, A, B = sim3_pairs
    A32, B32 = Sim3.exp(xa.float()), Sim3.exp(xb.float())
    assert A32.dtype == torch.float32
    assert torch.allclose((A32 @ B32).matrix().double(), (A @ B).matrix(), rtol=1e-5, atol=1e-4)
    assert torch.allclose(A32.inverse().matrix().double(), A.inverse().matrix(), rtol=1e-5, atol=1e-4)
    # Away from the angle-pi cut the log is well conditioned in float32.
    ok = xa[:, :3].norm(dim=-1) < 3.0
    assert torch.allclose(A32.log().double()[ok], xa[ok], rtol=1e-4, atol=1e-4)
    xs = random_tangent(200, 6, 12, max_angle=3.0)
    assert torch.allclose(SE3.exp(xs.float()).log().double(), xs, atol=1e-4)


def test_batch_shapes_broadcast_index_stack():
    xi = random_tangent(24, 7, 13).reshape(2, 3, 4, 7)
    T = Sim3.exp(xi)
    assert T.shape == (2, 3, 4)
    assert T.adjoint().shape == (2, 3, 4, 7, 7) and T.matrix().shape == (2, 3, 4, 4, 4)
    assert torch.allclose(T.log(), xi, atol=1e-12)
    X = torch.randn(2, 3, 4, 5, 3, dtype=F64)
    assert T[..., None].act(X).shape == (2, 3, 4, 5, 3)
    assert T[..., None].act_jacobian(X).shape == (2, 3, 4, 5, 3, 7)
    # Broadcasting compose: one element against a batch.
    C = T[0, 1, 2] @ T
    assert C.shape == (2, 3, 4)
    assert torch.allclose(C[1, 2, 3].matrix(), T[0, 1, 2].matrix() @ T[1, 2, 3].matrix(), atol=1e-12)
    S = stack([T[0], T[1]])
    assert S.shape == (2, 3, 4) and torch.equal(S.matrix(), T.matrix())
    assert stack([T[:, 0], T[:, 1]], dim=1).shape == (2, 2, 4)
    assert torch.allclose(Sim3.from_matrix(T.matrix()).matrix(), T.matrix(), atol=1e-12)
    P = SE3.exp(random_tangent(6, 6, 14)).__getitem__(slice(1, 4))
    assert P.shape == (3,) and torch.allclose(SE3.from_matrix(P.matrix()).matrix(), P.matrix(), atol=1e-12)
    assert T.to(torch.float32).dtype == torch.float32
    U = Sim3.from_se3(P, 2.0)
    assert torch.allclose(U.act(torch.ones(3, dtype=F64)), 2 * (P.R @ torch.ones(3, dtype=F64)) + P.t)


# ---------------------------------------------------------------- Jacobians vs finite differences


def central_fd(f, x: torch.Tensor, eps: float = 1e-6) -> torch.Tensor:
    """Batched central differences: f maps (B, d) -> (B, m); returns df/dx (B, m, d)."""
    cols = []
    for k in range(x.shape[-1]):
        e = torch.zeros_like(x)
        e[..., k] = eps
        cols.append((f(x + e) - f(x - e)) / (2 * eps))
    return torch.stack(cols, -1)


@pytest.mark.parametrize("G,dof", [(Sim3, 7), (SE3, 6)])
def test_act_jacobian_vs_finite_differences(G, dof):
    xi = random_tangent(20, dof, 15)
    T = G.exp(xi)
    X = torch.randn(20, 3, dtype=F64, generator=torch.Generator().manual_seed(16))
    J = T.act_jacobian(X)
    fd = central_fd(lambda d: T.retract(d).act(X), torch.zeros(20, dof, dtype=F64))
    assert torch.allclose(J, fd, atol=1e-7)


@pytest.mark.parametrize("G,dof", [(Sim3, 7), (SE3, 6)])
def test_right_jacobian_inverse_vs_finite_differences(G, dof):
    xi = random_tangent(15, dof, 17, max_angle=2.5)
    Jinv = G.right_jacobian_inv(xi)
    Jr = G.right_jacobian(xi)
    T = G.exp(xi)
    zero = torch.zeros(15, dof, dtype=F64)
    assert torch.allclose(Jinv, central_fd(lambda d: (T @ G.exp(d)).log(), zero), atol=1e-7)
    assert torch.allclose(Jr, central_fd(lambda d: (T.inverse() @ G.exp(xi + d)).log(), zero), atol=1e-7)
    # At zero both are the identity.
    assert torch.allclose(G.right_jacobian_inv(torch.zeros(dof, dtype=F64)), torch.eye(dof, dtype=F64))



@pytest.mark.parametrize("G,dof", [(Sim3, 7), (SE3, 6)])
def test_right_jacobian_matches_augmented_matrix_exponential(G, dof):
    """J_r = top-right block of expm([[-ad, I], [0, 0]]) for tangents from 1e-9 to ~6 in norm."""
    g = torch.Generator().manual_seed(18)
    xi = torch.randn(60, dof, generator=g, dtype=F64)
    xi = xi * torch.logspace(-9, 0.3, 60, dtype=F64)[:, None]
    xi[-5:, :3] = xi[-5:, :3] / xi[-5:, :3].norm(dim=-1, keepdim=True) * (math.pi - 1e-6)
    ad = G.ad(xi)
    big = torch.zeros(60, 2 * dof, 2 * dof, dtype=F64)
    big[:, :dof, :dof] = -ad
    big[:, :dof, dof:] = torch.eye(dof, dtype=F64)
    ref = torch.linalg.matrix_exp(big)[:, :dof, dof:]
    assert torch.allclose(G.right_jacobian(xi), ref, rtol=0, atol=1e-12)
    inv = G.right_jacobian_inv(xi)
    assert torch.allclose(inv @ ref, torch.eye(dof, dtype=F64).expand(60, dof, dof), atol=1e-10)


def test_sim3_matrix_parts_matches_sim3_and_projects():
    """The numpy one-element helper agrees with Sim3, and ``project`` restores a rotation."""
    gen = torch.Generator().manual_seed(7)
    xi = torch.randn(20, 7, generator=gen, dtype=torch.float64)
    T = Sim3.exp(xi)
    for k in range(20):
        M = T[k].matrix().numpy()
        R, t, s = sim3_matrix_parts(M)
        assert np.allclose(R, T.R[k].numpy(), atol=1e-12)
        assert np.allclose(t, T.t[k].numpy(), atol=1e-12)
        assert abs(s - float(T.s[k])) < 1e-12
        noisy = M.copy()
        noisy[:3, :3] += 1e-6 * s * np.random.default_rng(k).standard_normal((3, 3))  # relative to the scale
        R_p, _, _ = sim3_matrix_parts(noisy, project=True)
        assert np.allclose(R_p @ R_p.T, np.eye(3), atol=1e-12) and np.linalg.det(R_p) > 0
        assert np.allclose(R_p, T.R[k].numpy(), atol=1e-5)


def test_sim3_matrix_components_batched_matches_sim3():
    """The batched torch helper agrees with Sim3 on numpy and torch input of any batch shape."""
    gen = torch.Generator().manual_seed(8)
    T = Sim3.exp(torch.randn(4, 5, 7, generator=gen, dtype=torch.float64))
    M = T.matrix()
    for arg in (M, M.numpy()):
        R, t, s = sim3_matrix_components(arg)
        assert R.shape == (4, 5, 3, 3) and t.shape == (4, 5, 3) and s.shape == (4, 5)
        assert torch.allclose(R, T.R, atol=1e-12) and torch.allclose(t, T.t, atol=1e-12)
        assert torch.allclose(s, T.s, atol=1e-12)
