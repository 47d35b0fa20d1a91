"""RGB-D inverse-depth prior (noise models, selection, residual and Jacobian, and its use by the
patch frontend's local and global BA) and calibrated stereo term."""

import gtsam
import numpy as np
import pytest
import torch

from fgslam.core.camera import PinholeCamera, StereoRig
from fgslam.core.errors import ConfigError
from fgslam.factors.depth import DepthPriorConfig, depth_prior, depth_priors, inv_depth_sigma, reproject_stereo
from fgslam.factors.reprojection import ReprojectionConfig

F64 = torch.float64
LEFT = PinholeCamera((458.0, 457.0, 367.5, 248.5), 752, 480)
RIGHT = PinholeCamera((455.0, 454.0, 370.0, 250.0), 752, 480)
CONFIG = ReprojectionConfig(min_depth=1e-3)


def sim3_exp_gtsam(xi: np.ndarray) -> np.ndarray:
    """gtsam Similarity3.Expmap(xi) as a 4x4 matrix [[s R, t], [0, 1]] (fgslam's convention)."""
    S = gtsam.Similarity3.Expmap(np.asarray(xi, dtype=float))
    M = np.eye(4)
    M[:3, :3] = S.scale() * S.rotation().matrix()
    M[:3, 3] = S.scale() * np.asarray(S.translation())
    return M


def to_parts(M: np.ndarray):
    A = M[..., :3, :3]
    s = np.asarray(np.cbrt(np.linalg.det(A)))
    return torch.from_numpy(A / s[..., None, None]), torch.from_numpy(M[..., :3, 3].copy()), torch.from_numpy(s)


def random_sim3(rng, n, rot=0.5, trans=1.0, log_s=0.3) -> np.ndarray:
    xi = np.concatenate([rng.normal(size=(n, 3)) * rot, rng.normal(size=(n, 3)) * trans,
                         rng.normal(size=(n, 1)) * log_s], 1)
    return np.stack([sim3_exp_gtsam(x) for x in xi])


def make_rig(rng) -> StereoRig:
    T = np.eye(4)
    T[:3, :3] = gtsam.Rot3.Expmap(rng.normal(size=3) * 0.02).matrix()
    T[:3, 3] = [0.11, 0.002, -0.003]
    return StereoRig(LEFT, RIGHT, T)


# ---------------------------------------------------------------- depth prior
def test_noise_models():
    sens = np.array([0.1, 0.5, 2.0])
    rel = inv_depth_sigma(sens, DepthPriorConfig(sigma=0.01, noise="relative"))
    inv = inv_depth_sigma(sens, DepthPriorConfig(sigma=0.005, noise="inverse"))
    np.testing.assert_array_equal(rel, 0.01 * sens)  # sigma_z = 1 % of z: sigma_d = 1 % of d
    np.testing.assert_array_equal(inv, np.full(3, 0.005))  # constant in 1/m: sigma_z = 0.005 z^2
    # torch in, torch out (same numbers)
    rel_t = inv_depth_sigma(torch.from_numpy(sens), DepthPriorConfig(sigma=0.01, noise="relative"))
    inv_t = inv_depth_sigma(torch.from_numpy(sens), DepthPriorConfig(sigma=0.005, noise="inverse"))
    assert isinstance(rel_t, torch.Tensor) and isinstance(inv_t, torch.Tensor)
    np.testing.assert_array_equal(rel_t.numpy(), rel)
    np.testing.assert_array_equal(inv_t.numpy(), inv)
    with pytest.raises(ConfigError, match="relative\\|inverse"):
        inv_depth_sigma(sens, DepthPriorConfig(noise="quadratic"))


@pytest.mark.parametrize("noise,sigma", [("relative", 0.01), ("inverse", 0.005)])
def test_depth_priors_select_readings_and_weight_them_by_the_noise_model(noise, sigma):
    sens = np.array([0.5, np.nan, 0.25, 0.0, np.inf, -1.0, 2.0])
    pri = depth_priors(sens, DepthPriorConfig(sigma=sigma, noise=noise))
    assert pri.idx.tolist() == [0, 2, 6]
    np.testing.assert_array_equal(pri.value, sens[[0, 2, 6]])
    expected_sigma = sigma * sens[[0, 2, 6]] if noise == "relative" else np.full(3, sigma)
    np.testing.assert_allclose(pri.weight, 1.0 / expected_sigma ** 2, rtol=1e-15)
    kw = pri.kwargs()
    assert set(kw) == {"prior_idx", "prior_value", "prior_weight"} and kw["prior_weight"] is pri.weight


def test_depth_prior_residual_weights_and_invalid_readings():
    d = torch.tensor([0.5, 0.2, 1.0, 1.0, 1.0, 1.0, float("nan")], dtype=F64)
    sens = torch.tensor([0.5, 0.25, 0.0, float("nan"), float("inf"), -1.0, 1.0], dtype=torch.float32)
    w = torch.tensor([3.0, 4.0, 5.0, 6.0, 7.0, 8.0, 9.0], dtype=F64)
    res = depth_prior(d, sens, w)
    assert res.valid.tolist() == [True, True] + [False] * 5
    assert res.n_invalid == 5
    torch.testing.assert_close(res.residual[:2], torch.tensor([0.5 - 0.5, 0.2 - 0.25], dtype=F64))
    assert res.weight.tolist() == [3.0, 4.0] + [0.0] * 5
    assert res.J_d.tolist() == [1.0, 1.0] + [0.0] * 5
    for x in (res.residual, res.weight, res.J_d):
        assert torch.isfinite(x).all() and x.dtype == F64
    # a scalar weight broadcasts
    assert depth_prior(d, sens, 2.0).weight.tolist() == [2.0, 2.0] + [0.0] * 5


def test_depth_prior_jacobian_is_derivative_of_residual():
    rng = np.random.default_rng(0)
    d = torch.from_numpy(rng.uniform(0.01, 5.0, 100))
    sens = torch.from_numpy(1.0 / rng.uniform(0.2, 8.0, 100))
    res = depth_prior(d, sens, 1.0)
    h = 1e-6
    fd = (depth_prior(d + h, sens, 1.0).residual - depth_prior(d - h, sens, 1.0).residual) / (2 * h)
    torch.testing.assert_close(res.J_d, fd, rtol=1e-7, atol=1e-7)


def _prior_cost(d, pri):
    r = depth_prior(torch.from_numpy(d[pri.idx]), torch.from_numpy(pri.value), torch.from_numpy(pri.weight))
    return 0.5 * float((r.weight * r.residual ** 2).sum())


@pytest.mark.parametrize("noise,sigma", [("relative", 0.01), ("inverse", 0.005)])
def test_local_and_global_ba_carry_the_same_prior_cost_and_information(noise, sigma):
    """The local BA's block (PatchBlock) and the global BA's problem evaluate the priors through
    depth_prior: with no edge weight, their cost is the priors' cost, and the structure's
    information is the prior weight (the global BA's depth step solves the prior exactly)."""
    rng = np.random.default_rng(5)
    P = 12
    d = rng.uniform(0.2, 1.0, P)
    sens = d * np.exp(rng.normal(0.0, 0.05, P))
    sens[[2, 7]] = np.nan
    pri = depth_priors(sens, DepthPriorConfig(sigma=sigma, noise=noise))
    expected = _prior_cost(d, pri)
    assert expected > 0

    # local: two frames, one zero-weight edge per patch
    import gtsam

    from fgslam.frontends.patch.ba import PatchBlock
    from fgslam.backend.config import GlobalBAConfig
    from fgslam.backend.global_ba import GlobalBAProblem, global_bundle_adjustment
    from fgslam.backend.keys import pose_key

    K = np.array([200.0, 200.0, 160.0, 120.0])
    uv = rng.uniform([40, 30], [280, 210], (P, 2))
    T = np.stack([np.eye(4), np.eye(4)])
    T[1, 0, 3] = 0.1
    block = PatchBlock([pose_key(0), pose_key(1)], torch.zeros(0, 3, 3), torch.zeros(0, 3), torch.zeros(0),
                       np.zeros(P, np.int64), np.ones(P, np.int64), np.zeros(P, bool), uv, uv, np.zeros(P),
                       np.arange(P), torch.as_tensor(K), d, **pri.kwargs())
    values = gtsam.Values()
    for i in range(2):
        values.insert(pose_key(i), gtsam.Similarity3(gtsam.Rot3(), T[i, :3, 3], 1.0))
    assert block.cost(values) == pytest.approx(expected, rel=1e-12)

    # global: the same patches, one pose free; zero edge weights leave the priors alone
    prob = GlobalBAProblem(T_WC=T, fixed=np.array([True, False]), src=np.zeros(P, np.int64), tgt=np.ones(P, np.int64),
                           right=np.zeros(P, bool), uv_src=uv, uv=uv, weight=np.zeros(P), struct_idx=np.arange(P),
                           inv_depth=d, K=K, **pri.kwargs())
    res = global_bundle_adjustment(prob, GlobalBAConfig(iterations=1, robust_rounds=1))
    assert res.initial_cost == pytest.approx(expected, rel=1e-12)
    # one Gauss-Newton step on the prior rows lands the depths on the readings (no reading: unchanged)
    target = d.copy()
    target[pri.idx] = pri.value
    np.testing.assert_allclose(res.inv_depth, target, rtol=1e-9)


# ---------------------------------------------------------------- stereo
def stereo_fn(rig, uv, d, Mi, Mj, target):
    return reproject_stereo(uv, d, to_parts(Mi), to_parts(Mj), rig, target, config=CONFIG)


def stereo_configurations(rng, n=40):
    """Generic, tiny-parallax, pure-rotation, far and near configurations."""
    Mi_all, Mj_all, d_all = [], [], []
    for rot, trans, log_s, d_lo, d_hi in ((0.1, 0.3, 0.2, 0.05, 1.0), (1e-6, 1e-6, 1e-6, 0.05, 1.0),
                                          (0.1, 0.0, 0.2, 0.05, 1.0), (0.1, 0.3, 0.2, 1e-6, 1e-3),
                                          (0.02, 0.005, 0.0, 3.0, 10.0)):
        Mi = random_sim3(rng, n)
        Mj = np.stack([M @ sim3_exp_gtsam(x) for M, x in zip(Mi, np.concatenate(
            [rng.normal(size=(n, 3)) * rot, rng.normal(size=(n, 3)) * trans, rng.normal(size=(n, 1)) * log_s], 1))])
        if trans == 0.0:
            Mj[:, :3, 3] = Mi[:, :3, 3]
        Mi_all.append(Mi)
        Mj_all.append(Mj)
        d_all.append(rng.uniform(d_lo, d_hi, n))
    uv = torch.from_numpy(rng.uniform([0, 0], [751, 479], (5 * n, 2)))
    return np.concatenate(Mi_all), np.concatenate(Mj_all), uv, torch.from_numpy(np.concatenate(d_all))


def test_stereo_jacobians_match_finite_differences():
    rng = np.random.default_rng(1)
    rig = make_rig(rng)
    Mi, Mj, uv, d = stereo_configurations(rng)
    target = uv + 3.0
    res = stereo_fn(rig, uv, d, Mi, Mj, target)
    ok = res.valid.clone()
    eps = 1e-6
    J_Ti = np.zeros((len(d), 2, 7))
    J_Tj = np.zeros((len(d), 2, 7))
    for k in range(7):
        e = np.zeros(7)
        e[k] = eps
        Ep, Em = sim3_exp_gtsam(e), sim3_exp_gtsam(-e)
        for J, plus, minus in ((J_Ti, (Mi @ Ep, Mj), (Mi @ Em, Mj)), (J_Tj, (Mi, Mj @ Ep), (Mi, Mj @ Em))):
            rp = stereo_fn(rig, uv, d, *plus, target)
            rm = stereo_fn(rig, uv, d, *minus, target)
            ok &= rp.valid & rm.valid
            J[:, :, k] = ((rp.residual - rm.residual) / (2 * eps)).numpy()
    h = torch.clamp(0.5 * d, max=eps)
    rp = stereo_fn(rig, uv, d + h, Mi, Mj, target)
    rm = stereo_fn(rig, uv, d - h, Mi, Mj, target)
    ok &= rp.valid & rm.valid
    J_d = ((rp.residual - rm.residual) / (2 * h[:, None])).numpy()
    ok = ok.numpy()
    assert ok.sum() >= 150
    pairs = (("J_Ti", res.J_Ti.numpy(), J_Ti), ("J_Tj", res.J_Tj.numpy(), J_Tj), ("J_d", res.J_d.numpy(), J_d))
    for name, J, J_fd in pairs:
        scale = 1 + np.abs(J_fd[ok]).max(axis=tuple(range(1, J.ndim)), keepdims=True)
        assert (np.abs(J[ok] - J_fd[ok]) / scale).max() < 2e-6, name
    # a metric baseline observes the target scale; the source scale still trades with d only
    assert np.abs(res.J_Tj[..., 6].numpy()[ok]).max() > 1e-3
    v = res.valid
    torch.testing.assert_close(res.J_Ti[v][..., 6], -d[v][:, None] * res.J_d[v], rtol=1e-9, atol=1e-9)


def test_intra_keyframe_stereo_depends_on_inverse_depth_only():
    rng = np.random.default_rng(2)
    rig = make_rig(rng)
    n = 100
    uv = torch.from_numpy(rng.uniform([0, 0], [751, 479], (n, 2)))
    d = torch.from_numpy(rng.uniform(0.05, 2.0, n))
    target = uv.clone()
    Ma, Mb = random_sim3(rng, n), random_sim3(rng, n)
    ref = reproject_stereo(uv, d, None, None, rig, target, config=CONFIG)
    assert ref.valid.all()
    assert (ref.J_Ti == 0).all() and (ref.J_Tj == 0).all()
    for M in (Ma, Mb):
        same = stereo_fn(rig, uv, d, M, M, target)
        torch.testing.assert_close(same.residual, ref.residual, rtol=0, atol=1e-8)
        torch.testing.assert_close(same.J_d, ref.J_d, rtol=1e-8, atol=1e-8)
        torch.testing.assert_close(same.J_Ti + same.J_Tj, torch.zeros_like(same.J_Ti), rtol=0, atol=1e-7)
    h = torch.clamp(0.5 * d, max=1e-6)
    fd = (reproject_stereo(uv, d + h, None, None, rig, target).residual
          - reproject_stereo(uv, d - h, None, None, rig, target).residual) / (2 * h[:, None])
    torch.testing.assert_close(ref.J_d, fd, rtol=1e-6, atol=1e-6)


def test_rectified_rig_matches_gtsam_stereo_camera():
    rng = np.random.default_rng(3)
    fx, fy, cx, cy = LEFT.K
    b = 0.11
    T = np.eye(4)
    T[:3, 3] = [b, 0.0, 0.0]
    rig = StereoRig(LEFT, LEFT, T)
    n = 60
    Mi = random_sim3(rng, n)
    Mj = Mi @ random_sim3(rng, n, rot=0.05, trans=0.2, log_s=0.0)
    Mj[:, :3, :3] /= np.cbrt(np.linalg.det(Mj[:, :3, :3]))[:, None, None]  # target pose in metres: s_j = 1
    uv = torch.from_numpy(rng.uniform([0, 0], [751, 479], (n, 2)))
    d = torch.from_numpy(rng.uniform(0.1, 1.0, n))
    res = stereo_fn(rig, uv, d, Mi, Mj, torch.zeros_like(uv))
    cal = gtsam.Cal3_S2Stereo(fx, fy, 0.0, cx, cy, b)
    checked = 0
    for k in np.flatnonzero(res.valid.numpy()):
        Ri, ti, si = (x.numpy() for x in to_parts(Mi[k]))
        Rj, tj, _ = (x.numpy() for x in to_parts(Mj[k]))
        X_i = np.array([(uv[k, 0].item() - cx) / fx, (uv[k, 1].item() - cy) / fy, 1.0]) / d[k].item()
        X_W = gtsam.Similarity3(gtsam.Rot3(Ri), ti / si, float(si)).transformFrom(X_i)
        cam = gtsam.StereoCamera(gtsam.Pose3(gtsam.Rot3(Rj), tj), cal)
        H1 = np.zeros((3, 6), order="F")
        sp = cam.project2(X_W, H1, None)
        np.testing.assert_allclose(res.residual[k].numpy(), [sp.uR(), sp.v()], rtol=0, atol=1e-8)
        np.testing.assert_allclose(res.J_Tj[k, :, :6].numpy(), H1[1:], rtol=1e-9, atol=1e-7)
        checked += 1
    assert checked > 40
    # intra-keyframe disparity of a rectified rig: u_L - u_R = fx * baseline * d (metric d)
    intra = reproject_stereo(uv, d, None, None, rig, torch.zeros_like(uv))
    torch.testing.assert_close(uv[:, 0] - intra.residual[:, 0], fx * b * d)
    torch.testing.assert_close(intra.residual[:, 1], uv[:, 1])


def test_stereo_invalid_rows_are_zero_and_float32_works():
    rng = np.random.default_rng(4)
    rig = make_rig(rng)
    uv = torch.tensor([[100.0, 100.0], [200.0, 150.0], [300.0, 200.0], [10.0, 10.0]])
    d = torch.tensor([0.5, -1.0, float("nan"), 200.0])  # last: 5 mm in front, below min depth in the right camera
    res = reproject_stereo(uv, d, None, None, rig, uv, config=ReprojectionConfig(min_depth=0.1))
    assert res.valid.tolist() == [True, False, False, False] and res.n_invalid == 3
    assert res.residual.dtype == torch.float32
    for x in (res.residual, res.J_Ti, res.J_Tj, res.J_d):
        assert torch.isfinite(x).all() and (x[~res.valid] == 0).all()


@pytest.mark.parametrize("s", [0.5, 2.0])
def test_stereo_scale_means_world_units_per_metre(s):
    """Scaling the whole world (poses' translations and scales) by s leaves the stereo residual unchanged."""
    rng = np.random.default_rng(5)
    rig = make_rig(rng)
    n = 50
    Mi = random_sim3(rng, n)
    Mj = Mi @ random_sim3(rng, n, rot=0.05, trans=0.2, log_s=0.1)
    uv = torch.from_numpy(rng.uniform([0, 0], [751, 479], (n, 2)))
    d = torch.from_numpy(rng.uniform(0.1, 1.0, n))
    res = stereo_fn(rig, uv, d, Mi, Mj, uv)
    S = np.diag([s, s, s, 1.0])
    res_s = stereo_fn(rig, uv, d, S @ Mi, S @ Mj, uv)
    assert res.valid.sum() > 30
    torch.testing.assert_close(res_s.residual, res.residual, rtol=1e-9, atol=1e-8)


def test_configs_load_from_overrides():
    from fgslam.core.config import load_config

    cfg = load_config(DepthPriorConfig, None, ["sigma=0.2", "noise=inverse"])
    assert (cfg.sigma, cfg.noise) == (0.2, "inverse")
    with pytest.raises(ConfigError, match="sigma"):
        load_config(DepthPriorConfig, None, ["sigma=0"])
    assert load_config(ReprojectionConfig, None, ["min_depth=0.05"]).min_depth == 0.05
