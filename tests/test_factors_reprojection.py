"""Inverse-depth reprojection factor: values vs gtsam, Jacobians vs central finite differences."""

import gtsam
import numpy as np
import pytest
import torch

from fgslam.core.errors import DataError
from fgslam.factors.reprojection import (
    ReprojectionConfig,
    flatten_patches,
    reproject,
    reproject_edges,
    reproject_inv_depth,
)
from fgslam.core.lie import SE3, Sim3

F64 = torch.float64
WIDTH, HEIGHT = 640, 480


# ---------------------------------------------------------------- helpers (numpy / gtsam reference)
def sim3_exp_gtsam(xi: np.ndarray) -> np.ndarray:
    """gtsam Similarity3.Expmap(xi) as a 4x4 matrix [[s R, t], [0, 1]] (fgslam's convention)."""
    S = gtsam.Similarity3.Expmap(np.asarray(xi, dtype=float))
    M = np.eye(4)
    M[:3, :3] = S.scale() * S.rotation().matrix()
    M[:3, 3] = S.scale() * np.asarray(S.translation())
    return M


def to_parts(M: np.ndarray):
    """(R, t, s) torch float64 tensors of (N, 4, 4) similarity matrices."""
    A = M[..., :3, :3]
    s = np.asarray(np.cbrt(np.linalg.det(A)))
    return (torch.from_numpy(A / s[..., None, None]), torch.from_numpy(M[..., :3, 3].copy()), torch.from_numpy(s))


def to_matrix(R, t, s) -> np.ndarray:
    M = np.zeros(R.shape[:-2] + (4, 4))
    M[..., :3, :3] = s.numpy()[..., None, None] * R.numpy()
    M[..., :3, 3] = t.numpy()
    M[..., 3, 3] = 1
    return M


def random_sim3(rng, n, rot=0.5, trans=1.0, log_s=0.3) -> np.ndarray:
    xi = np.concatenate([rng.normal(size=(n, 3)) * rot, rng.normal(size=(n, 3)) * trans,
                         rng.normal(size=(n, 1)) * log_s], 1)
    return np.stack([sim3_exp_gtsam(x) for x in xi])


def make_configurations(rng, n_per_kind=40):
    """Source/target poses, pixels and inverse depths over generic and near-degenerate cases."""
    Ti, Tj, uv, d, kinds = [], [], [], [], []
    n = n_per_kind

    def add(kind, T_i, T_j, uv_k, d_k):
        Ti.append(T_i)
        Tj.append(T_j)
        uv.append(uv_k)
        d.append(d_k)
        kinds.extend([kind] * len(d_k))

    def small_motion(T, scale_rot, scale_t, log_s=0.2):
        xi = np.concatenate([rng.normal(size=(len(T), 3)) * scale_rot, rng.normal(size=(len(T), 3)) * scale_t,
                             rng.normal(size=(len(T), 1)) * log_s], 1)
        return np.stack([T[k] @ sim3_exp_gtsam(xi[k]) for k in range(len(T))])

    pix = lambda m: rng.uniform([0, 0], [WIDTH - 1, HEIGHT - 1], size=(m, 2))  # noqa: E731
    # generic: moderate motion, moderate depth
    T = random_sim3(rng, n)
    add("generic", T, small_motion(T, 0.1, 0.2), pix(n), rng.uniform(0.05, 1.0, n))
    # pixels within a pixel of the image border
    T = random_sim3(rng, n)
    border = pix(n)
    side = rng.integers(0, 4, n)
    border[side == 0, 0] = rng.uniform(-0.5, 0.5, (side == 0).sum())
    border[side == 1, 0] = WIDTH - 1 + rng.uniform(-0.5, 0.5, (side == 1).sum())
    border[side == 2, 1] = rng.uniform(-0.5, 0.5, (side == 2).sum())
    border[side == 3, 1] = HEIGHT - 1 + rng.uniform(-0.5, 0.5, (side == 3).sum())
    add("border", T, small_motion(T, 0.05, 0.1), border, rng.uniform(0.05, 1.0, n))
    # tiny parallax: near-identical poses
    T = random_sim3(rng, n)
    add("tiny_parallax", T, small_motion(T, 1e-6, 1e-6, 1e-6), pix(n), rng.uniform(0.05, 1.0, n))
    # pure rotation between the frames (same camera centre), different scales
    T = random_sim3(rng, n)
    T2 = small_motion(T, 0.1, 0.0)
    T2[:, :3, 3] = T[:, :3, 3]
    add("pure_rotation", T, T2, pix(n), rng.uniform(0.05, 1.0, n))
    # very small inverse depth (far points)
    T = random_sim3(rng, n)
    add("far", T, small_motion(T, 0.1, 0.3), pix(n), 10 ** rng.uniform(-6, -3, n))
    # very large inverse depth (near points), small baseline keeps them in front of the target
    T = random_sim3(rng, n)
    add("near", T, small_motion(T, 0.02, 0.005), pix(n), rng.uniform(5.0, 20.0, n))
    return (np.concatenate(Ti), np.concatenate(Tj), torch.from_numpy(np.concatenate(uv)),
            torch.from_numpy(np.concatenate(d)), np.array(kinds))


K_REF = torch.tensor([420.0, 410.0, 319.5, 239.5], dtype=F64)
CONFIG = ReprojectionConfig(min_depth=1e-3)


def residual_fn(uv, d, Mi, Mj, target, config=CONFIG, K=K_REF):
    return reproject_inv_depth(uv, d, to_parts(Mi), to_parts(Mj), K, target, config=config)


def fd_jacobians(uv, d, Mi, Mj, target, eps=1e-6):
    """Central differences: right perturbations via gtsam Expmap, and the inverse depth."""
    n = len(d)
    J_Ti = np.zeros((n, 2, 7))
    J_Tj = np.zeros((n, 2, 7))
    ok = torch.ones(n, dtype=torch.bool)
    for k in range(7):
        e = np.zeros(7)
        e[k] = eps
        Ep, Em = sim3_exp_gtsam(e), sim3_exp_gtsam(-e)
        for which, J in ((0, J_Ti), (1, J_Tj)):
            Mp = (Mi @ Ep, Mj) if which == 0 else (Mi, Mj @ Ep)
            Mm = (Mi @ Em, Mj) if which == 0 else (Mi, Mj @ Em)
            rp = residual_fn(uv, d, *Mp, target)
            rm = residual_fn(uv, d, *Mm, target)
            ok &= rp.valid & rm.valid
            J[:, :, k] = ((rp.residual - rm.residual) / (2 * eps)).numpy()
    h = torch.clamp(0.5 * d, max=eps)
    rp = residual_fn(uv, d + h, Mi, Mj, target)
    rm = residual_fn(uv, d - h, Mi, Mj, target)
    ok &= rp.valid & rm.valid
    J_d = ((rp.residual - rm.residual) / (2 * h[:, None])).numpy()
    return J_Ti, J_Tj, J_d, ok.numpy()


def assert_jacobian_close(J, J_fd, kinds, name):
    scale = 1.0 + np.abs(J_fd).max(axis=tuple(range(1, J.ndim)), keepdims=True)
    err = np.abs(J - J_fd) / scale
    worst = np.unravel_index(np.argmax(err), err.shape)
    assert err.max() < 2e-6, f"{name}: max scaled error {err.max():.3g} at row {worst[0]} ({kinds[worst[0]]})"


# ---------------------------------------------------------------- tests
def test_jacobians_match_finite_differences_on_degenerate_configurations():
    rng = np.random.default_rng(0)
    Mi, Mj, uv, d, kinds = make_configurations(rng)
    target = uv + torch.from_numpy(rng.normal(size=uv.shape))
    res = residual_fn(uv, d, Mi, Mj, target)
    J_Ti, J_Tj, J_d, ok = fd_jacobians(uv, d, Mi, Mj, target)
    ok &= res.valid.numpy()
    assert ok.sum() >= 200, f"only {ok.sum()} valid configurations"
    for kind in np.unique(kinds):
        assert ok[kinds == kind].sum() >= 30, f"too few valid rows of kind {kind}"
    assert_jacobian_close(res.J_Ti.numpy()[ok], J_Ti[ok], kinds[ok], "J_Ti")
    assert_jacobian_close(res.J_Tj.numpy()[ok], J_Tj[ok], kinds[ok], "J_Tj")
    assert_jacobian_close(res.J_d.numpy()[ok], J_d[ok], kinds[ok], "J_d")
    # pure rotation: the depth is unobservable
    rot = (kinds == "pure_rotation") & ok
    assert np.abs(res.J_d.numpy()[rot]).max() < 1e-9


def test_scale_gauge_structure():
    rng = np.random.default_rng(1)
    Mi, Mj, uv, d, _ = make_configurations(rng, n_per_kind=20)
    res = residual_fn(uv, d, Mi, Mj, uv)
    v = res.valid
    assert v.sum() > 100
    # target scale drops out exactly
    assert torch.all(res.J_Tj[..., 6] == 0)
    # source scale enters only through d / s_i: J_lambda_i = -d J_d
    torch.testing.assert_close(res.J_Ti[v][..., 6], -d[v][:, None] * res.J_d[v], rtol=1e-9, atol=1e-9)
    # and the residual is unchanged under (s_i, d) -> (a s_i, a d), for any s_j
    R_i, t_i, s_i = to_parts(Mi)
    R_j, t_j, s_j = to_parts(Mj)
    a = 1.7
    res2 = reproject_inv_depth(uv, a * d, (R_i, t_i, a * s_i), (R_j, t_j, 3.0 * s_j), K_REF, uv, config=CONFIG)
    torch.testing.assert_close(res2.residual[v], res.residual[v], rtol=1e-9, atol=1e-8)


def test_identical_poses_give_opposite_pose_jacobians():
    rng = np.random.default_rng(2)
    M = random_sim3(rng, 100)
    uv = torch.from_numpy(rng.uniform(0, 600, (100, 2)))
    d = torch.from_numpy(rng.uniform(0.1, 2.0, 100))
    res = residual_fn(uv, d, M, M, uv)
    assert res.valid.all()
    torch.testing.assert_close(res.residual, torch.zeros_like(uv), atol=1e-9, rtol=0)
    torch.testing.assert_close(res.J_Ti + res.J_Tj, torch.zeros_like(res.J_Ti), atol=1e-8, rtol=0)


def test_values_match_gtsam_and_pose_jacobian_matches_pinhole_camera():
    rng = np.random.default_rng(3)
    n = 60
    Mi = random_sim3(rng, n)
    Mj = Mi @ random_sim3(rng, n, rot=0.1, trans=0.2, log_s=0.0)  # s_j = s_i
    Mj[:, :3, :3] /= np.cbrt(np.linalg.det(Mj[:, :3, :3]))[:, None, None]  # target scale 1
    uv = torch.from_numpy(rng.uniform(0, 600, (n, 2)))
    d = torch.from_numpy(rng.uniform(0.1, 1.0, n))
    res = residual_fn(uv, d, Mi, Mj, torch.zeros_like(uv))
    fx, fy, cx, cy = K_REF.tolist()
    cal = gtsam.Cal3_S2(fx, fy, 0.0, cx, cy)
    checked = 0
    for k in range(n):
        Ri, ti, si = (x.numpy() for x in to_parts(Mi[k]))
        Rj, tj, sj = (x.numpy() for x in to_parts(Mj[k]))
        Si = gtsam.Similarity3(gtsam.Rot3(Ri), ti / si, float(si))
        X_i = np.array([(uv[k, 0] - cx) / fx, (uv[k, 1] - cy) / fy, 1.0]) / d[k].item()
        X_W = Si.transformFrom(X_i)
        cam = gtsam.PinholeCameraCal3_S2(gtsam.Pose3(gtsam.Rot3(Rj), tj), cal)
        if not res.valid[k]:
            continue
        Dpose = np.zeros((2, 6), order="F")
        uv_g = cam.project(X_W, Dpose, None, None)
        np.testing.assert_allclose(res.residual[k].numpy(), uv_g, rtol=0, atol=1e-8)
        np.testing.assert_allclose(res.J_Tj[k, :, :6].numpy(), Dpose, rtol=1e-9, atol=1e-7)
        checked += 1
    assert checked > 50


def test_invalid_geometry_is_masked_zeroed_and_counted():
    rng = np.random.default_rng(4)
    n = 12
    M = random_sim3(rng, n, trans=0.0, log_s=0.0)
    Mj = M.copy()
    uv = torch.from_numpy(rng.uniform(0, 600, (n, 2)))
    d = torch.full((n,), 0.5, dtype=F64)
    target = uv.clone()
    # row 0: target camera 3 units in front of the source along its optical axis -> point behind it
    Mj[0, :3, 3] = M[0, :3, :3] @ np.array([0.0, 0.0, 3.0])
    d[1] = -0.1  # behind the source camera
    d[2] = float("nan")
    d[3] = float("inf")
    uv[4, 0] = float("nan")
    target[5, 1] = float("nan")
    # row 6: point 0.1 in front of the target camera (source depth 2, target moved 1.9 forward)
    Mj[6, :3, 3] = M[6, :3, :3] @ np.array([0.0, 0.0, 1.9])
    uv[6] = K_REF[2:]
    res = residual_fn(uv, d, M, Mj, target, config=ReprojectionConfig(min_depth=0.2))
    expected_invalid = {0, 1, 2, 3, 4, 5, 6}
    assert set(np.flatnonzero(~res.valid.numpy())) == expected_invalid
    assert res.n_invalid == len(expected_invalid)
    for x in (res.residual, res.J_Ti, res.J_Tj, res.J_d):
        assert torch.isfinite(x).all()
        assert (x[~res.valid] == 0).all()
    # the row at depth 0.1 is valid with a smaller minimum depth
    res2 = residual_fn(uv, d, M, Mj, target, config=ReprojectionConfig(min_depth=0.05))
    assert res2.valid[6] and not res2.valid[0]
    # points at infinity (d = 0) are valid
    uv0 = torch.from_numpy(rng.uniform(0, 600, (n, 2)))
    res3 = residual_fn(uv0, torch.zeros(n, dtype=F64), M, Mj, uv0)
    assert res3.valid.all() and torch.isfinite(res3.J_Ti).all()


def test_float32_degenerate_inputs_stay_finite():
    rng = np.random.default_rng(5)
    n = 200
    Mi = random_sim3(rng, n)
    Mj = random_sim3(rng, n)  # unrelated poses: many points behind the target
    parts_i = tuple(x.float() for x in to_parts(Mi))
    parts_j = tuple(x.float() for x in to_parts(Mj))
    uv = torch.from_numpy(rng.uniform(-1e4, 1e4, (n, 2))).float()
    d = torch.from_numpy(10 ** rng.uniform(-30, 30, n)).float()
    d[::7] = 0
    res = reproject_inv_depth(uv, d, parts_i, parts_j, K_REF.float(), uv)
    assert res.residual.dtype == torch.float32
    assert 0 < res.n_invalid < n
    for x in (res.residual, res.J_Ti, res.J_Tj, res.J_d):
        assert torch.isfinite(x).all()


def test_accepts_lie_objects_and_broadcasts_shared_poses():
    rng = np.random.default_rng(6)
    E, m = 4, 30
    Mi = random_sim3(rng, E)
    Mj = Mi @ random_sim3(rng, E, rot=0.05, trans=0.1)
    Ti = Sim3(*to_parts(Mi))
    Tj = Sim3(*to_parts(Mj))
    uv = torch.from_numpy(rng.uniform(0, 600, (E, m, 2)))
    d = torch.from_numpy(rng.uniform(0.1, 1.0, (E, m)))
    target = uv + 1.0
    per_edge = reproject_inv_depth(uv, d, Ti[:, None], Tj[:, None], K_REF, target)
    idx = torch.arange(E).repeat_interleave(m)
    gathered = reproject_inv_depth(uv.reshape(-1, 2), d.reshape(-1), Ti[idx], Tj[idx], K_REF.expand(E * m, 4),
                                   target.reshape(-1, 2))
    assert per_edge.residual.shape == (E, m, 2) and per_edge.J_Ti.shape == (E, m, 2, 7)
    for a, b in ((per_edge.residual, gathered.residual), (per_edge.J_Ti, gathered.J_Ti),
                 (per_edge.J_Tj, gathered.J_Tj), (per_edge.J_d, gathered.J_d)):
        torch.testing.assert_close(a.reshape(b.shape), b, rtol=1e-12, atol=1e-10)
    # SE3 poses (no scale attribute) mean scale 1
    Ti_se3 = SE3(Ti.R, Ti.t)
    Tj_se3 = SE3(Tj.R, Tj.t)
    ones = torch.ones(E, dtype=F64)
    a = reproject_inv_depth(uv, d, Ti_se3[:, None], Tj_se3[:, None], K_REF, target)
    b = reproject_inv_depth(uv, d, (Ti.R[:, None], Ti.t[:, None], ones[:, None]),
                            (Tj.R[:, None], Tj.t[:, None], ones[:, None]), K_REF, target)
    torch.testing.assert_close(a.J_Ti, b.J_Ti)


def test_reproject_matches_residual_and_separate_target_intrinsics():
    rng = np.random.default_rng(7)
    n = 80
    Mi = random_sim3(rng, n)
    Mj = Mi @ random_sim3(rng, n, rot=0.05, trans=0.1)
    uv = torch.from_numpy(rng.uniform(0, 600, (n, 2)))
    d = torch.from_numpy(rng.uniform(0.1, 1.0, n))
    K_j = torch.tensor([300.0, 310.0, 200.0, 150.0], dtype=F64)
    target = torch.from_numpy(rng.uniform(0, 600, (n, 2)))
    res = reproject_inv_depth(uv, d, to_parts(Mi), to_parts(Mj), K_REF, target, K_j)
    uv_j, valid = reproject(uv, d, to_parts(Mi), to_parts(Mj), K_REF, K_j)
    assert torch.equal(valid, res.valid) and valid.sum() > 60
    torch.testing.assert_close(uv_j[valid], (res.residual + target)[valid])
    # the target intrinsics act on the target side only: same normalised coordinates
    uv_ref, _ = reproject(uv, d, to_parts(Mi), to_parts(Mj), K_REF)
    xn_ref = (uv_ref - K_REF[2:]) / K_REF[:2]
    xn_j = (uv_j - K_j[2:]) / K_j[:2]
    torch.testing.assert_close(xn_j[valid], xn_ref[valid])


def test_patch_rows_share_one_depth():
    rng = np.random.default_rng(8)
    P, p = 5, 3
    centres = torch.from_numpy(rng.uniform(50, 550, (P, 2)))
    offsets = torch.stack(torch.meshgrid(torch.arange(p) - 1.0, torch.arange(p) - 1.0, indexing="ij"), -1).to(F64)
    uv_patches = centres[:, None, None, :] + offsets.flip(-1)[None]  # (P, p, p, 2) as (u, v)
    d_patch = torch.from_numpy(rng.uniform(0.2, 1.0, P))
    uv, d = flatten_patches(uv_patches, d_patch)
    assert uv.shape == (P * p * p, 2) and d.shape == (P * p * p,)
    k, a, b = 3, 2, 1
    torch.testing.assert_close(uv[k * p * p + a * p + b], uv_patches[k, a, b])
    assert torch.equal(d.reshape(P, p * p), d_patch[:, None].expand(P, p * p))
    # the patch depth gradient is the sum over its rows: check against a finite difference
    M = random_sim3(rng, 1)
    Mj = M @ random_sim3(rng, 1, rot=0.05, trans=0.2)
    target = uv + 0.5
    res = residual_fn(uv, d, M[0], Mj[0], target)
    g = (res.J_d * res.residual).sum(-1).reshape(P, p * p).sum(-1)  # d(0.5 |r|^2)/d(d_patch)
    eps = 1e-6

    def cost(dp):
        r = residual_fn(uv, flatten_patches(uv_patches, dp)[1], M[0], Mj[0], target).residual
        return 0.5 * (r**2).sum(-1).reshape(P, p * p).sum(-1)

    e = torch.full((P,), eps, dtype=F64)
    g_fd = (cost(d_patch + e) - cost(d_patch - e)) / (2 * eps)
    torch.testing.assert_close(g, g_fd, rtol=1e-6, atol=1e-6)
    with pytest.raises(DataError):
        flatten_patches(uv_patches, d_patch[:-1])


# ---------------------------------------------------------------- left / right split
K_RIGHT = torch.tensor([415.0, 405.0, 322.0, 236.0], dtype=F64)


def _rig_extrinsic() -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = gtsam.Rot3.Expmap(np.array([0.01, -0.02, 0.005])).matrix()
    T[:3, 3] = [-0.11, 0.003, 0.002]  # T_CRCL: the right camera 11 cm to the right of the left
    return T


def _edges(rng, n):
    Mi = random_sim3(rng, n)
    Mj = Mi @ random_sim3(rng, n, rot=0.05, trans=0.1, log_s=0.1)
    uv = torch.from_numpy(rng.uniform(50, 550, (n, 2)))
    d = torch.from_numpy(rng.uniform(0.1, 1.0, n))
    return Mi, Mj, uv, d, uv + torch.from_numpy(rng.normal(size=(n, 2)))


@pytest.mark.parametrize("layout", ["mixed", "sorted", "left", "right"])
def test_reproject_edges_splits_left_and_right_like_separate_calls(layout):
    rng = np.random.default_rng(11)
    n = 60
    Mi, Mj, uv, d, target = _edges(rng, n)
    right = {"mixed": rng.random(n) < 0.4, "sorted": np.arange(n) >= 35, "left": np.zeros(n, bool),
             "right": np.ones(n, bool)}[layout]
    right_t = torch.from_numpy(right)
    T_CRCL = _rig_extrinsic()
    Ti, Tj = to_parts(Mi), to_parts(Mj)
    res = reproject_edges(uv, d, Ti, Tj, K_REF, target, right=right_t, K_right=K_RIGHT, T_CRCL=T_CRCL, config=CONFIG)
    uv_pred, valid = reproject_edges(uv, d, Ti, Tj, K_REF, right=right_t, K_right=K_RIGHT, T_CRCL=T_CRCL, config=CONFIG)
    assert res.valid.sum() > 50
    for mask, K_t, T_ext in ((~right, K_REF, None), (right, K_RIGHT, T_CRCL)):
        if not mask.any():
            continue
        m = torch.from_numpy(mask)
        parts_i, parts_j = tuple(x[m] for x in Ti), tuple(x[m] for x in Tj)
        ref = reproject_inv_depth(uv[m], d[m], parts_i, parts_j, K_REF, target[m], K_t, T_CtCj=T_ext, config=CONFIG)
        for name in ("residual", "J_Ti", "J_Tj", "J_d", "valid"):
            assert torch.equal(getattr(res, name)[m], getattr(ref, name)), name
        ref_uv, ref_valid = reproject(uv[m], d[m], parts_i, parts_j, K_REF, K_t, T_CtCj=T_ext, config=CONFIG)
        assert torch.equal(uv_pred[m], ref_uv) and torch.equal(valid[m], ref_valid)
    # no split at all: the plain left-image functions
    if layout == "left":
        assert torch.equal(reproject_edges(uv, d, Ti, Tj, K_REF, target, config=CONFIG).residual, res.residual)
    # right edges observe the metric baseline: a different prediction than the left image's
    if right.any():
        left_pred, _ = reproject(uv, d, Ti, Tj, K_REF, config=CONFIG)
        assert (uv_pred[right_t] - left_pred[right_t]).abs().max() > 1.0


def test_reproject_edges_jacobians_match_finite_differences_on_a_mixed_batch():
    rng = np.random.default_rng(12)
    n = 40
    Mi, Mj, uv, d, target = _edges(rng, n)
    right = torch.from_numpy(rng.random(n) < 0.5)
    sides = dict(right=right, K_right=K_RIGHT, T_CRCL=_rig_extrinsic(), config=CONFIG)

    def fn(Mi_, Mj_, d_):
        return reproject_edges(uv, d_, to_parts(Mi_), to_parts(Mj_), K_REF, target, **sides)

    res = fn(Mi, Mj, d)
    ok = res.valid.clone()
    eps = 1e-6
    J_Ti, J_Tj = np.zeros((n, 2, 7)), np.zeros((n, 2, 7))
    for k in range(7):
        e = np.zeros(7)
        e[k] = eps
        Ep, Em = sim3_exp_gtsam(e), sim3_exp_gtsam(-e)
        for J, plus, minus in ((J_Ti, (Mi @ Ep, Mj), (Mi @ Em, Mj)), (J_Tj, (Mi, Mj @ Ep), (Mi, Mj @ Em))):
            rp, rm = fn(*plus, d), fn(*minus, d)
            ok &= rp.valid & rm.valid
            J[:, :, k] = ((rp.residual - rm.residual) / (2 * eps)).numpy()
    rp, rm = fn(Mi, Mj, d + eps), fn(Mi, Mj, d - eps)
    ok &= rp.valid & rm.valid
    J_d = ((rp.residual - rm.residual) / (2 * eps)).numpy()
    ok = ok.numpy()
    assert ok.sum() > 30 and ok[right.numpy()].sum() > 10
    kinds = np.where(right.numpy(), "right", "left")
    assert_jacobian_close(res.J_Ti.numpy()[ok], J_Ti[ok], kinds[ok], "J_Ti")
    assert_jacobian_close(res.J_Tj.numpy()[ok], J_Tj[ok], kinds[ok], "J_Tj")
    assert_jacobian_close(res.J_d.numpy()[ok], J_d[ok], kinds[ok], "J_d")


def test_reproject_edges_needs_the_right_camera_for_right_edges():
    rng = np.random.default_rng(13)
    Mi, Mj, uv, d, target = _edges(rng, 4)
    right = torch.tensor([False, True, False, False])
    with pytest.raises(DataError, match="K_right and T_CRCL"):
        reproject_edges(uv, d, to_parts(Mi), to_parts(Mj), K_REF, target, right=right)
    # all-left batches need neither
    reproject_edges(uv, d, to_parts(Mi), to_parts(Mj), K_REF, target, right=torch.zeros(4, dtype=torch.bool))


@pytest.mark.parametrize("extrinsic", [False, True])
def test_compiled_rows_and_element_wise_rows_give_the_same_bytes(extrinsic):
    """The row arithmetic runs compiled (float64 CPU tensors without gradients: every frontend) or
    element-wise on the tensors (autograd, another dtype or device: the learned networks' training).
    Both are the same functions (``fgslam.factors.reprojection_jit``), so on every configuration kind,
    invalid rows (NaN, negative and zero depths, a non-finite target), shared and per-row poses and
    per-row intrinsics they must agree to the bit."""
    rng = np.random.default_rng(21)
    Mi, Mj, uv, d, kinds = make_configurations(rng)
    n = len(d)
    d = d.clone()
    d[:3] = torch.tensor([float("nan"), -0.1, 0.0], dtype=F64)
    target = uv + torch.from_numpy(rng.normal(size=uv.shape))
    target[5] = float("inf")
    K_rows = K_REF + torch.from_numpy(rng.normal(size=(n, 4)))  # per-row target intrinsics
    ext = dict(T_CtCj=_rig_extrinsic()) if extrinsic else {}
    Ti, Tj = to_parts(Mi), to_parts(Mj)
    shared_i, shared_j = tuple(x[0] for x in Ti), tuple(x[0] for x in Tj)
    for poses in ((Ti, Tj), (shared_i, shared_j)):
        compiled = reproject_inv_depth(uv, d, *poses, K_REF, target, K_rows, config=CONFIG, **ext)
        with torch.enable_grad():  # a tensor that requires gradients takes the element-wise rows
            d_grad = d.clone().requires_grad_(True)
            element_wise = reproject_inv_depth(uv, d_grad, *poses, K_REF, target, K_rows, config=CONFIG, **ext)
        assert 0 < int(compiled.valid.sum()) < n
        for name in ("residual", "J_Ti", "J_Tj", "J_d", "valid"):
            a, b = getattr(compiled, name), getattr(element_wise, name).detach()
            assert a.shape == b.shape and a.numpy().tobytes() == b.numpy().tobytes(), name
        uv_c, ok_c = reproject(uv, d, *poses, K_REF, K_rows, config=CONFIG, **ext)
        with torch.enable_grad():
            uv_e, ok_e = reproject(uv, d_grad, *poses, K_REF, K_rows, config=CONFIG, **ext)
        assert uv_c.numpy().tobytes() == uv_e.detach().numpy().tobytes() and torch.equal(ok_c, ok_e)


def test_element_wise_rows_are_differentiable():
    """The training graph back-propagates through the residual in every input (``fgslam.nets.dba``): the
    element-wise rows' gradients match finite differences (torch's gradcheck) in the inverse depths, both
    poses' rotations, translations and scales, the intrinsics and the target, with and without an
    extrinsic; and the cost's gradient in the inverse depths is ``J_d`` of the compiled rows."""
    rng = np.random.default_rng(22)
    Mi, Mj, uv, d, target = _edges(rng, 12)
    (Ri, ti, si), (Rj, tj, sj) = to_parts(Mi), to_parts(Mj)

    for ext in ({}, {"T_CtCj": _rig_extrinsic()}):
        def residual(d_, Ri_, ti_, si_, Rj_, tj_, sj_, K_, target_):
            res = reproject_inv_depth(uv, d_, (Ri_, ti_, si_), (Rj_, tj_, sj_), K_, target_, config=CONFIG, **ext)
            return res.residual, res.J_d, res.J_Ti, res.J_Tj

        inputs = tuple(x.clone().requires_grad_(True) for x in (d, Ri, ti, si, Rj, tj, sj, K_REF, target))
        assert torch.autograd.gradcheck(residual, inputs, eps=1e-7, atol=1e-5, rtol=1e-4)
    res = reproject_inv_depth(uv, d, (Ri, ti, si), (Rj, tj, sj), K_REF, target, config=CONFIG)
    d_grad = d.clone().requires_grad_(True)
    cost = 0.5 * (reproject_inv_depth(uv, d_grad, (Ri, ti, si), (Rj, tj, sj), K_REF, target,
                                      config=CONFIG).residual ** 2).sum()
    cost.backward()
    expected = (res.J_d * res.residual).sum(-1)
    assert res.valid.all() and torch.allclose(d_grad.grad, expected, rtol=1e-10, atol=1e-12)


def test_pair_index_points_rows_at_their_pose_pair():
    """A block's edges in one call (``pair_index``: row ``r`` uses pose pair ``pair_index[r]``) give the
    bytes of one call per edge with its pose pair broadcast over its rows, compiled and element-wise."""
    rng = np.random.default_rng(23)
    G, per_edge = 4, 25
    Mi, Mj, uv, d, target = _edges(rng, G * per_edge)
    Mi, Mj = Mi[::per_edge], Mj[::per_edge]
    Ti, Tj = to_parts(Mi), to_parts(Mj)
    pair_index = torch.arange(G).repeat_interleave(per_edge)
    joined = reproject_inv_depth(uv, d, Ti, Tj, K_REF, target, config=CONFIG, pair_index=pair_index)
    with torch.enable_grad():
        element_wise = reproject_inv_depth(uv, d.clone().requires_grad_(True), Ti, Tj, K_REF, target, config=CONFIG,
                                           pair_index=pair_index)
    uv_joined, ok_joined = reproject(uv, d, Ti, Tj, K_REF, config=CONFIG, pair_index=pair_index)
    assert int(joined.valid.sum()) > G * per_edge // 2
    for e in range(G):
        rows = slice(e * per_edge, (e + 1) * per_edge)
        pose_i, pose_j = tuple(x[e] for x in Ti), tuple(x[e] for x in Tj)
        alone = reproject_inv_depth(uv[rows], d[rows], pose_i, pose_j, K_REF, target[rows], config=CONFIG)
        for name in ("residual", "J_Ti", "J_Tj", "J_d", "valid"):
            expected = getattr(alone, name).numpy().tobytes()
            assert getattr(joined, name)[rows].numpy().tobytes() == expected, name
            assert getattr(element_wise, name)[rows].detach().numpy().tobytes() == expected, name
        uv_alone, ok_alone = reproject(uv[rows], d[rows], pose_i, pose_j, K_REF, config=CONFIG)
        assert torch.equal(uv_joined[rows], uv_alone) and torch.equal(ok_joined[rows], ok_alone)


def test_pair_index_is_checked():
    """A malformed ``pair_index`` is refused in one line, and an index past the pose pairs raises (the
    compiled loop checks every row's index before it reads)."""
    rng = np.random.default_rng(24)
    Mi, Mj, uv, d, target = _edges(rng, 6)
    Ti, Tj = to_parts(Mi[:2]), to_parts(Mj[:2])
    good = torch.tensor([0, 0, 0, 1, 1, 1])
    assert reproject_inv_depth(uv, d, Ti, Tj, K_REF, target, config=CONFIG, pair_index=good).valid.shape == (6,)
    for bad, match in ((good[:4], "one per row"), (good.bool(), "1-D integer"), (good.double(), "1-D integer"),
                       (good[None], "1-D integer")):
        with pytest.raises(DataError, match=match):
            reproject_inv_depth(uv, d, Ti, Tj, K_REF, target, config=CONFIG, pair_index=bad)
    with pytest.raises(DataError, match="one batch dimension"):
        reproject_inv_depth(uv, d, tuple(x[0] for x in Ti), tuple(x[0] for x in Tj), K_REF, target, config=CONFIG,
                            pair_index=good)
    for past in (torch.tensor([0, 0, 0, 1, 1, 2]), torch.tensor([0, 0, 0, 1, 1, 10**9]), torch.tensor([-1, 0, 0, 1, 1, 1])):
        with pytest.raises(IndexError, match="out of range"):
            reproject_inv_depth(uv, d, Ti, Tj, K_REF, target, config=CONFIG, pair_index=past)
