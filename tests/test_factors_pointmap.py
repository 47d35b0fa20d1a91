"""Tests of fgslam.factors.pointmap: residual values, analytic Jacobians vs central finite
differences (float64, >= 100 random configurations incl. near-degenerate ones), the
relative-to-global chain rule, scale (non-)invariance, weighting and masking."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest
import torch

from fgslam.core.errors import DataError
from fgslam.factors.pointmap import (
    PointmapResidualConfig,
    as_sim3,
    calibrated_residuals,
    point_residuals,
    ray_dist_residuals,
    relative_to_global,
    relative_to_global_normal,
)
from fgslam.core.lie import Sim3

FD_STEP = 1e-6
N_MATCHES = 3
K_PINHOLE = np.array([420.0, 410.0, 320.0, 240.0])


# ----------------------------------------------------------------------------- Sim(3) helpers
# Poses are fgslam.core.lie.Sim3 batches (X -> s R X + t; right perturbation T @ Sim3.exp(xi), tangent
# [w, u, lambda] = gtsam Similarity3.Logmap, which fgslam.core.lie's own tests check against gtsam).


def to_gtsam(R, t, s) -> gtsam.Similarity3:
    return gtsam.Similarity3(gtsam.Rot3(R), np.asarray(t) / s, float(s))


def poses_tensor(poses) -> Sim3:
    """list of numpy (R, t, s) -> float64 Sim3 of shape (B,)."""
    R = torch.tensor(np.stack([p[0] for p in poses]))
    t = torch.tensor(np.stack([p[1] for p in poses]))
    s = torch.tensor(np.array([p[2] for p in poses]))
    return Sim3(R, t, s)


def flat(T: Sim3) -> Sim3:
    shape = T.shape
    R = T.R.expand(*shape, 3, 3).reshape(-1, 3, 3)
    return Sim3(R, T.t.expand(*shape, 3).reshape(-1, 3), T.s.expand(shape).reshape(-1))


def fd_directions(h: float) -> torch.Tensor:
    """(14, 7): +h e_j, -h e_j for j = 0..6 (j major)."""
    eye = torch.eye(7, dtype=torch.float64) * h
    return torch.stack((eye, -eye), 1).reshape(14, 7)


def perturbed(T: Sim3, h: float) -> Sim3:
    """T (B,) -> (B*14,) poses T Exp(+-h e_j), pose major, then j, then sign."""
    E = Sim3.exp(fd_directions(h))
    return flat(Sim3(T.R[:, None], T.t[:, None], T.s[:, None]) @ E)


def random_rotation(rng, max_angle=np.pi):
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    return gtsam.Rot3.Expmap(axis * rng.uniform(0, max_angle)).matrix()


# ----------------------------------------------------------------------------- configurations
KINDS = ("generic", "tiny_translation", "pure_rotation", "near_axis", "scale_extreme")


def make_configs(seed: int, per_kind: int = 24):
    """Random relative poses T_CkCf and matches; 5 kinds x per_kind configurations.

    Points are generated in frame k in front of the camera (so the calibrated residual is
    defined), X_f = T_CkCf^-1 Y, and X_k is a noisy copy of Y. Scales are log-uniform in
    [0.1, 10]; 'scale_extreme' uses exactly 0.1 or 10.
    """
    rng = np.random.default_rng(seed)
    poses, X_f, X_k, uv_k = [], [], [], []
    for kind in KINDS:
        for i in range(per_kind):
            R = random_rotation(rng)
            s = float(np.exp(rng.uniform(np.log(0.1), np.log(10.0))))
            t = rng.normal(size=3)
            if kind == "tiny_translation":
                t = rng.normal(size=3) * 1e-7
            elif kind == "pure_rotation":
                t, s = np.zeros(3), 1.0
            elif kind == "scale_extreme":
                s = 0.1 if i % 2 == 0 else 10.0
            if kind == "near_axis":
                Y = np.column_stack(
                    (rng.normal(size=(N_MATCHES, 2)) * 1e-5, rng.uniform(0.5, 5.0, N_MATCHES))
                )
            else:
                Y = np.column_stack(
                    (rng.uniform(-1, 1, (N_MATCHES, 2)), np.ones(N_MATCHES))
                ) * rng.uniform(0.5, 5.0, (N_MATCHES, 1))
            Xf = ((Y - t) / s) @ R  # T^-1 Y = R^T (Y - t) / s
            Xk = Y * (1 + 0.05 * rng.normal(size=(N_MATCHES, 1))) + 0.02 * rng.normal(size=Y.shape)
            Xk[:, 2] = np.abs(Xk[:, 2])
            uv = Y[:, :2] / Y[:, 2:] * K_PINHOLE[:2] + K_PINHOLE[2:] + rng.normal(size=(N_MATCHES, 2))
            poses.append((R, t, s))
            X_f.append(Xf)
            X_k.append(Xk)
            uv_k.append(uv)
    return poses, torch.tensor(np.stack(X_f)), torch.tensor(np.stack(X_k)), torch.tensor(np.stack(uv_k))


def residual_fn(name: str):
    """Uniform signature f(T, X_f, X_k, uv_k) for the three residual families."""
    K = torch.tensor(K_PINHOLE)
    return {
        "point": lambda T, Xf, Xk, uv: point_residuals(T, Xf, Xk),
        "ray_dist": lambda T, Xf, Xk, uv: ray_dist_residuals(T, Xf, Xk),
        "calibrated": lambda T, Xf, Xk, uv: calibrated_residuals(T, Xf, Xk, uv, K),
    }[name]


def repeat14(x: torch.Tensor) -> torch.Tensor:
    return x.repeat_interleave(14, dim=0)


def fd_from_batch(r_batch: torch.Tensor, B: int, h: float) -> torch.Tensor:
    """(B*14, N, m) residuals at [+h, -h] per tangent direction -> (B, N, m, 7) Jacobian."""
    r = r_batch.reshape(B, 7, 2, *r_batch.shape[1:])
    J = (r[:, :, 0] - r[:, :, 1]) / (2 * h)  # (B, 7, N, m)
    return J.permute(0, 2, 3, 1)


def assert_jacobian_close(J, J_fd, what):
    J, J_fd = J.numpy(), J_fd.numpy()
    scale = np.maximum(1.0, np.abs(J_fd).max(axis=-1, keepdims=True))
    err = np.abs(J - J_fd) / scale
    worst = np.unravel_index(np.argmax(err), err.shape)
    assert err.max() < 1e-7, f"{what}: max scaled error {err.max():.3g} at {worst}"


# ----------------------------------------------------------------------------- tests
RESIDUALS = ("point", "ray_dist", "calibrated")


def test_configurations_cover_the_brief():
    poses, X_f, _, _ = make_configs(0)
    assert len(poses) >= 100 and X_f.dtype == torch.float64
    scales = np.array([p[2] for p in poses])
    assert scales.min() == pytest.approx(0.1) and scales.max() == pytest.approx(10.0)


@pytest.mark.parametrize("name", RESIDUALS)
def test_relative_jacobian_matches_central_differences(name):
    f = residual_fn(name)
    poses, X_f, X_k, uv_k = make_configs(1)
    T = poses_tensor(poses)
    res = f(T, X_f, X_k, uv_k)
    assert bool(res.valid.all()), "generated configurations must all be valid"
    r_batch = f(perturbed(T, FD_STEP), repeat14(X_f), repeat14(X_k), repeat14(uv_k)).r
    assert_jacobian_close(res.J, fd_from_batch(r_batch, len(poses), FD_STEP), f"{name} d r / d xi_CkCf")


def repeat_pose14(T: Sim3) -> Sim3:
    B = T.shape[0]
    R = T.R[:, None].expand(B, 14, 3, 3)
    return flat(Sim3(R, T.t[:, None].expand(B, 14, 3), T.s[:, None].expand(B, 14)))


@pytest.mark.parametrize("name", RESIDUALS)
def test_global_jacobians_match_central_differences(name):
    """J_WCk, J_WCf from relative_to_global equal FD of r(T_WCk^-1 T_WCf) under right
    perturbations of each global pose."""
    f = residual_fn(name)
    rel, X_f, X_k, uv_k = make_configs(2)
    rng = np.random.default_rng(3)
    B = len(rel)
    log_s = rng.uniform(np.log(0.1), np.log(10.0), B)
    T_WCk = poses_tensor([(random_rotation(rng), rng.normal(size=3) * 3, np.exp(ls)) for ls in log_s])
    T_WCf = T_WCk @ poses_tensor(rel)
    T_CkCf = T_WCk.inverse() @ T_WCf
    res = f(T_CkCf, X_f, X_k, uv_k)
    J_WCk, J_WCf = relative_to_global(res.J, T_CkCf)

    args = (repeat14(X_f), repeat14(X_k), repeat14(uv_k))
    fd_k = fd_from_batch(f(perturbed(T_WCk, FD_STEP).inverse() @ repeat_pose14(T_WCf), *args).r, B, FD_STEP)
    fd_f = fd_from_batch(f(repeat_pose14(T_WCk).inverse() @ perturbed(T_WCf, FD_STEP), *args).r, B, FD_STEP)
    assert_jacobian_close(J_WCk, fd_k, f"{name} d r / d xi_WCk")
    assert_jacobian_close(J_WCf, fd_f, f"{name} d r / d xi_WCf")


@pytest.mark.parametrize("name", RESIDUALS)
def test_keyframe_jacobian_equals_closed_form(name):
    """-J_CkCf Ad(T_CkCf^-1) equals -dr/dY [-[Y]x, I, Y] (left perturbation of the prediction)."""
    f = residual_fn(name)
    poses, X_f, X_k, uv_k = make_configs(5, per_kind=6)
    T = poses_tensor(poses)
    res = f(T, X_f, X_k, uv_k)
    J_WCk, _ = relative_to_global(res.J, T)
    # dr/dY from the relative Jacobian's translation block: J[..., 3:6] = dr/dY s R.
    R, t, s = T.R, T.t, T.s
    dr_dY = res.J[..., 3:6] @ (R.transpose(-1, -2) / s[:, None, None])[:, None]
    Y = torch.einsum("bij,bnj->bni", s[:, None, None] * R, X_f) + t[:, None]
    skewY = torch.zeros(*Y.shape, 3, dtype=Y.dtype)
    skewY[..., 0, 1], skewY[..., 0, 2], skewY[..., 1, 2] = -Y[..., 2], Y[..., 1], -Y[..., 0]
    skewY = skewY - skewY.transpose(-1, -2)
    G = torch.cat((-skewY, torch.eye(3, dtype=Y.dtype).expand_as(skewY), Y[..., None]), -1)
    np.testing.assert_allclose(J_WCk.numpy(), (-(dr_dY @ G)).numpy(), rtol=1e-9, atol=1e-9)


def test_residual_values_match_gtsam():
    poses, X_f, X_k, uv_k = make_configs(6, per_kind=4)
    T = poses_tensor(poses)
    pt = point_residuals(T, X_f, X_k).r.numpy()
    rd = ray_dist_residuals(T, X_f, X_k).r.numpy()
    ca = calibrated_residuals(T, X_f, X_k, uv_k, torch.tensor(K_PINHOLE)).r.numpy()
    cam = gtsam.PinholeCameraCal3_S2(gtsam.Pose3(), gtsam.Cal3_S2(*K_PINHOLE[:2], 0.0, *K_PINHOLE[2:]))
    for b, p in enumerate(poses):
        G = to_gtsam(*p)
        for n in range(N_MATCHES):
            Y = G.transformFrom(X_f[b, n].numpy())
            Xk = X_k[b, n].numpy()
            np.testing.assert_allclose(pt[b, n], Y - Xk, atol=1e-10)
            ray = Y / np.linalg.norm(Y) - Xk / np.linalg.norm(Xk)
            np.testing.assert_allclose(rd[b, n], [*ray, np.linalg.norm(Y) - np.linalg.norm(Xk)], atol=1e-10)
            uv = cam.project(Y) - uv_k[b, n].numpy()
            np.testing.assert_allclose(ca[b, n], [*uv, np.log(Y[2] / Xk[2])], atol=1e-8)


def test_ray_is_scale_invariant_distance_is_not():
    """Scaling the relative pose uniformly (Exp(lambda e_s) T_CkCf, i.e. the right tangent
    direction Ad(T^-1) e_s) leaves the rays unchanged but not the distance; for t = 0 the
    right tangent's own scale column of the ray rows is zero. The keyframe's global scale
    (right perturbation of T_WCk) also leaves the rays unchanged."""
    poses, X_f, X_k, _ = make_configs(7)
    T = poses_tensor(poses)
    res = ray_dist_residuals(T, X_f, X_k)
    e_s = torch.zeros(7, dtype=torch.float64)
    e_s[6] = 1.0
    direction = T.inverse().adjoint() @ e_s  # (B, 7)
    J_dir = (res.J @ direction[:, None, :, None]).squeeze(-1)  # (B, N, 4)
    R, t, s = T.R, T.t, T.s
    Y = torch.einsum("bij,bnj->bni", s[:, None, None] * R, X_f) + t[:, None]
    assert J_dir[..., :3].abs().max() < 1e-12
    np.testing.assert_allclose(J_dir[..., 3].numpy(), Y.norm(dim=-1).numpy(), rtol=1e-12)
    assert J_dir[..., 3].abs().min() > 0.1

    # Finite check of the invariance itself: (R, e^l t, e^l s) gives identical rays.
    lam = 0.7
    scaled = ray_dist_residuals((R, t * np.exp(lam), s * np.exp(lam)), X_f, X_k)
    np.testing.assert_allclose(scaled.r[..., :3].numpy(), res.r[..., :3].numpy(), atol=1e-12)
    assert (scaled.r[..., 3] - res.r[..., 3]).abs().min() > 1e-3

    # Pure rotation (t = 0): the right tangent's scale column of the ray rows vanishes.
    pure = torch.tensor([bool((p[1] == 0).all()) for p in poses])
    assert pure.sum() >= 20
    assert res.J[pure][..., :3, 6].abs().max() < 1e-12
    assert res.J[pure][..., 3, 6].abs().min() > 0.1

    # Keyframe scale: d ray / d lambda_WCk = 0 exactly, distance row = -||Y||.
    J_WCk, _ = relative_to_global(res.J, T)
    assert J_WCk[..., :3, 6].abs().max() < 1e-12
    np.testing.assert_allclose(J_WCk[..., 3, 6].numpy(), -Y.norm(dim=-1).numpy(), rtol=1e-10)


def test_weights_whiten_rows():
    poses, X_f, X_k, uv_k = make_configs(8, per_kind=2)
    T = poses_tensor(poses)
    cfg = PointmapResidualConfig(sigma_ray=0.01, sigma_dist=2.0)
    w = torch.rand(X_f.shape[:2], dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    w[0, 0] = 0.0
    res = ray_dist_residuals(T, X_f, X_k, weight=w, config=cfg)
    expected = torch.sqrt(w)[..., None] / torch.tensor([0.01, 0.01, 0.01, 2.0], dtype=torch.float64)
    np.testing.assert_allclose(res.sqrt_info.numpy(), expected.numpy(), rtol=1e-14)
    r_w, J_w = res.whitened()
    np.testing.assert_allclose(r_w.numpy(), (res.r * expected).numpy(), rtol=1e-14)
    np.testing.assert_allclose(J_w.numpy(), (res.J * expected[..., None]).numpy(), rtol=1e-14)
    assert bool(res.valid[0, 0]) and res.num_masked == 0  # zero weight is not a degeneracy
    with pytest.raises(DataError, match="weight"):
        ray_dist_residuals(T, X_f, X_k, weight=-w)


def _degenerate_batch():
    """One pose, 9 matches: 3 good, then degenerate ones of every kind."""
    rng = np.random.default_rng(9)
    R, t, s = random_rotation(rng), np.array([0.3, -0.2, 0.5]), 2.0
    Y_good = np.array([[0.1, 0.2, 2.0], [-0.5, 0.3, 1.0], [0.0, 0.0, 3.0]])
    X_f = ((Y_good - t) / s) @ R
    zero_Y = ((np.zeros(3) - t) / s) @ R  # maps to the centre of camera k
    behind = ((np.array([0.2, 0.1, -1.0]) - t) / s) @ R  # maps behind camera k
    X_f = np.vstack((X_f, np.zeros(3), X_f[0], zero_Y, X_f[1], behind, X_f[2]))
    bad_k = [Y_good[0], np.zeros(3), Y_good[0], [np.nan, 1.0, 1.0], [0.2, 0.1, -1.0], [0.1, 0.1, -0.5]]
    X_k = np.vstack((Y_good, bad_k))
    uv = np.tile(K_PINHOLE[2:], (9, 1))
    pose = (torch.tensor(R)[None], torch.tensor(t)[None], torch.tensor([s]))
    return pose, torch.tensor(X_f)[None], torch.tensor(X_k)[None], torch.tensor(uv)[None]


@pytest.mark.parametrize(
    "name, expected_valid",
    [
        # good x3, zero X_f, zero X_k, Y at camera centre, NaN X_k, Y and X_k behind, X_k behind
        ("point", [1, 1, 1, 0, 0, 1, 0, 1, 1]),
        ("ray_dist", [1, 1, 1, 0, 0, 0, 0, 1, 1]),
        ("calibrated", [1, 1, 1, 0, 0, 0, 0, 0, 0]),
    ],
)
def test_degenerate_matches_are_masked_and_counted(name, expected_valid):
    pose, X_f, X_k, uv = _degenerate_batch()
    res = residual_fn(name)(pose, X_f, X_k, uv)
    expected = torch.tensor(expected_valid, dtype=torch.bool)[None]
    assert torch.equal(res.valid, expected)
    assert res.num_masked == int((~expected).sum())
    for tensor in (res.r, res.J, res.sqrt_info, *res.whitened()):
        assert bool(torch.isfinite(tensor).all())
    bad = ~expected
    assert res.r[bad].abs().max() == 0 and res.J[bad].abs().max() == 0 and res.sqrt_info[bad].abs().max() == 0
    # Good matches are unaffected by their degenerate neighbours.
    alone = residual_fn(name)(pose, X_f[:, :3], X_k[:, :3], uv[:, :3])
    torch.testing.assert_close(res.r[:, :3], alone.r, rtol=0, atol=0)
    torch.testing.assert_close(res.J[:, :3], alone.J, rtol=0, atol=0)


def test_pose_argument_forms_agree():
    """A Sim3, a tuple (R, t, s) and any object with .R/.t/.s give the same result."""
    from types import SimpleNamespace

    poses, X_f, X_k, _ = make_configs(11, per_kind=2)
    T = poses_tensor(poses)
    ref = ray_dist_residuals(T, X_f, X_k)
    for form in ((T.R, T.t, T.s), SimpleNamespace(R=T.R, t=T.t, s=T.s)):
        assert isinstance(as_sim3(form), Sim3)
        torch.testing.assert_close(ray_dist_residuals(form, X_f, X_k).J, ref.J, rtol=0, atol=0)


def test_invalid_pose_raises():
    pose, X_f, X_k, _ = _degenerate_batch()
    R, t, s = pose
    with pytest.raises(DataError, match="non-finite"):
        point_residuals((R, t * np.nan, s), X_f, X_k)
    with pytest.raises(DataError, match="scale"):
        point_residuals((R, t, -s), X_f, X_k)


@pytest.mark.parametrize("name", RESIDUALS)
def test_float32_agrees_with_float64(name):
    f = residual_fn(name)
    poses, X_f, X_k, uv_k = make_configs(10, per_kind=4)
    T = poses_tensor(poses)
    R, t, s = T.R, T.t, T.s
    r64 = f((R, t, s), X_f, X_k, uv_k)
    r32 = f((R.float(), t.float(), s.float()), X_f.float(), X_k.float(), uv_k.float())
    assert r32.r.dtype == torch.float32 and r32.J.dtype == torch.float32
    scale = r64.J.abs().amax(dim=-1, keepdim=True).clamp(min=1.0)
    assert ((r32.J.double() - r64.J) / scale).abs().max() < 1e-3


def test_residuals_without_jacobians_are_the_same_residuals():
    """A cost evaluation (``jacobians=False``) gives the same whitened residuals and mask, and no Jacobian."""
    import numpy as _np

    from fgslam.factors.pointmap import calibrated_residuals, point_residuals, ray_dist_residuals
    from fgslam.core.lie import Sim3 as _Sim3

    rng = _np.random.default_rng(11)
    n = 50
    X_k = torch.as_tensor(_np.stack([rng.uniform(-1, 1, n), rng.uniform(-1, 1, n), rng.uniform(2, 4, n)], -1))
    X_f = X_k + torch.as_tensor(rng.normal(scale=0.05, size=(n, 3)))
    X_f[3] = float("nan")
    w = torch.as_tensor(rng.uniform(0.1, 1.0, n))
    T = _Sim3.exp(torch.tensor([0.02, -0.01, 0.03, 0.05, 0.0, -0.02, 0.1], dtype=torch.float64))
    uv = torch.as_tensor(rng.uniform(0, 300, (n, 2)))
    K = torch.tensor([300.0, 300.0, 160.0, 120.0], dtype=torch.float64)
    for f, extra in ((point_residuals, ()), (ray_dist_residuals, ()), (calibrated_residuals, (uv, K))):
        full = f(T, X_f, X_k, *extra, w)
        cheap = f(T, X_f, X_k, *extra, w, jacobians=False)
        e_full, J_full = full.whitened()
        e_cheap, J_cheap = cheap.whitened()
        assert J_full is not None and J_cheap is None
        assert torch.equal(e_full, e_cheap) and torch.equal(full.valid, cheap.valid)
        assert not bool(cheap.valid[3])


def test_normal_equations_chain_rule_equals_the_stacked_jacobians():
    """relative_to_global_normal (one 7-column reduction, then the adjoint) gives the H and g that
    summing [J_WCk, J_WCf]^T W [J_WCk, J_WCf] over the matches gives."""
    rng = np.random.default_rng(11)
    R, t, s = random_rotation(rng), rng.normal(size=3), 1.7
    T = Sim3(torch.tensor(R), torch.tensor(t), torch.tensor(s))
    X_f = torch.tensor(rng.normal(size=(50, 3)) + [0, 0, 3])
    X_k = torch.tensor(rng.normal(size=(50, 3)) + [0, 0, 3])
    res = ray_dist_residuals(T, X_f, X_k, weight=torch.tensor(rng.uniform(0.1, 1, 50)))
    e, J = res.whitened()
    w = torch.tensor(rng.uniform(0.2, 1.0, (50, 4)))  # arbitrary row weights (IRLS)
    J_k, J_f = relative_to_global(J, T)
    J14 = torch.cat((J_k, J_f), -1).reshape(-1, 14)
    H_ref = J14.T @ (w.reshape(-1, 1) * J14)
    g_ref = J14.T @ (w.reshape(-1) * e.reshape(-1))
    J7 = J.reshape(-1, 7)
    H, g = relative_to_global_normal(J7.T @ (w.reshape(-1, 1) * J7), J7.T @ (w.reshape(-1) * e.reshape(-1)), T)
    np.testing.assert_allclose(H.numpy(), H_ref.numpy(), rtol=1e-10, atol=1e-8 * float(H_ref.abs().max()))
    np.testing.assert_allclose(g.numpy(), g_ref.numpy(), rtol=1e-10, atol=1e-8 * float(g_ref.abs().max()))
