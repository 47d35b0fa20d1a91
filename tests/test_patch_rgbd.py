"""RGB-D patch frontend: the scale stays exactly 1, per-row edge weights of
PatchBlock, the virtual right-camera convention of the depth-observation model
(``patch.ba.depth_model: observation``), and that model end to end on a short synthetic
room-loop clip (same bound as tests/test_patch_frontend.py: 0.5 % of the path + 1 mm)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from fgslam.eval.trajectory import EvalConfig, evaluate
from fgslam.frontends.patch import PatchFrontend
from fgslam.frontends.patch.ba import PatchBlock
from fgslam.io.trajectory import Trajectory
from fgslam.core.lie import Sim3, sim3_matrix_parts
from fgslam.core.so3 import so3_exp
from fgslam.backend.keys import pose_key
from fgslam.backend import Backend, BackendConfig
from patch_support import light_patch_config, render_room

FRAMES = 48
K = torch.tensor([200.0, 200.0, 160.0, 120.0], dtype=torch.float64)


@pytest.fixture(scope="module")
def room(tmp_path_factory):
    return render_room(tmp_path_factory, "room", [f"frames={FRAMES}", "camera.width=320", "camera.height=240"])


def _open(root):
    from fgslam.io.datasets import DatasetConfig, open_dataset

    return open_dataset(root, config=DatasetConfig(load_right=False, load_depth=True, load_imu=False))


def _run(root, config):
    ds = _open(root)
    fe = PatchFrontend(config, sensor_mode="rgbd", backend=Backend(BackendConfig()))
    for frame in ds:
        fe.process(frame)
    fe.finish()
    return ds, fe


def _poses(n=3):
    R = torch.stack([so3_exp(torch.tensor([0.0, 0.03 * f, 0.01 * f], dtype=torch.float64)) for f in range(n)])
    t = torch.tensor([[0.15 * f, 0.02 * f, 0.05 * f] for f in range(n)], dtype=torch.float64)
    return Sim3(R, t, torch.ones(n, dtype=torch.float64))


def _values(poses):
    import gtsam

    values = gtsam.Values()
    for i in range(poses.shape[0]):
        values.insert(pose_key(i), poses[i].to_gtsam())
    return values


def test_rgbd_scale_stays_one(room):
    """Every keyframe scale is exactly 1 in RGB-D mode (the per-BA soft scale hold used to let it
    drift from BA to BA: 0.87 after 200 frames of 7-Scenes with a 1 % depth prior)."""
    cfg = light_patch_config()
    cfg.ba.depth_prior_sigma = 0.01
    _, fe = _run(room, cfg)
    frames = list(fe._final.values()) + fe.graph.frames
    scales = np.array([sim3_matrix_parts(f.T_WC)[2] for f in frames])
    assert len(scales) >= 5
    np.testing.assert_allclose(scales, 1.0, rtol=0, atol=1e-12)


def test_per_row_weights():
    """(N, 2) weights weight the u and v rows separately; equal columns equal (N,) weights."""
    rng = np.random.default_rng(0)
    poses = _poses()
    n = 30
    uv = np.stack([rng.uniform(40, 280, n), rng.uniform(30, 210, n)], 1)
    d = 1.0 / rng.uniform(3.0, 6.0, n)
    src, tgt = np.zeros(n, np.int64), rng.integers(1, 3, n)
    uv_obs = uv + rng.normal(0, 2.0, (n, 2))  # not the reprojection: non-zero residuals
    w = rng.uniform(0.5, 2.0, n)
    args = ([pose_key(i) for i in range(3)], torch.zeros(0, 3, 3), torch.zeros(0, 3), torch.zeros(0), src, tgt,
            np.zeros(n, bool), uv, uv_obs)
    values = _values(poses)
    one = PatchBlock(*args, w, np.arange(n), K, d)
    two = PatchBlock(*args, np.stack([w, w], 1), np.arange(n), K, d)
    u_only = PatchBlock(*args, np.stack([w, np.zeros(n)], 1), np.arange(n), K, d)
    _, H1, g1, c1 = one.linearize(values)[0]
    _, H2, g2, c2 = two.linearize(values)[0]
    np.testing.assert_allclose(H2, H1, rtol=1e-12)
    np.testing.assert_allclose(g2, g1, rtol=1e-12)
    r, valid = one.residuals(values)
    assert bool(valid.all())
    assert one.cost(values) == pytest.approx(0.5 * float((w * (r ** 2).sum(1).numpy()).sum()), rel=1e-10)
    assert u_only.cost(values) == pytest.approx(0.5 * float((w * r[:, 0].numpy() ** 2).sum()), rel=1e-10)


def test_virtual_right_camera_convention():
    """The observation model's virtual right pixel ``u - fx b d_target`` (d_target: inverse depth
    of the point in the target camera) is the exact reprojection into a right camera through
    ``T_CRCL = [I | (-b, 0, 0)]`` with the left intrinsics: zero residual at the truth, a depth
    reading 5 % off gives a u-row residual of ``fx b`` times the inverse-depth error."""
    rng = np.random.default_rng(1)
    poses = _poses()
    n = 20
    uv = np.stack([rng.uniform(40, 280, n), rng.uniform(30, 210, n)], 1)
    d = 1.0 / rng.uniform(1.0, 4.0, n)
    b = 0.08
    T_CRCL = np.eye(4)
    T_CRCL[0, 3] = -b
    tgt = np.full(n, 2)
    # the left observation in the target and the point's inverse depth there (from the truth)
    rays = np.stack([(uv[:, 0] - 160) / 200, (uv[:, 1] - 120) / 200, np.ones(n)], 1) / d[:, None]
    T_C2C0 = poses[2].inverse().compose(poses[0]).matrix().numpy()
    X2 = rays @ T_C2C0[:3, :3].T + T_C2C0[:3, 3]
    uv_left = np.stack([200 * X2[:, 0] / X2[:, 2] + 160, 200 * X2[:, 1] / X2[:, 2] + 120], 1)
    for scale, expect_zero in ((1.0, True), (1.05, False)):
        d_tgt = scale / X2[:, 2]
        uv_R = uv_left - np.stack([200 * b * d_tgt, np.zeros(n)], 1)
        block = PatchBlock([pose_key(i) for i in range(3)], torch.zeros(0, 3, 3), torch.zeros(0, 3), torch.zeros(0),
                           np.zeros(n, np.int64), tgt, np.ones(n, bool), uv, uv_R, np.stack([np.ones(n), np.zeros(n)], 1),
                           np.arange(n), K, d, K_right=K, T_CRCL=T_CRCL)
        r, valid = block.residuals(_values(poses))
        assert bool(valid.all())
        np.testing.assert_allclose(r[:, 1].numpy(), 0.0, atol=1e-9)  # v_R = v
        if expect_zero:
            np.testing.assert_allclose(r[:, 0].numpy(), 0.0, atol=1e-9)
        else:
            np.testing.assert_allclose(r[:, 0].numpy(), 200 * b * (d_tgt - 1 / X2[:, 2]), rtol=1e-9)


@pytest.mark.parametrize("noise", ["relative", "inverse"])
def test_depth_observation_model_accuracy(room, noise):
    cfg = light_patch_config()
    cfg.ba.depth_model = "observation"
    cfg.ba.depth_noise = noise
    cfg.ba.depth_prior_sigma = 0.01 if noise == "relative" else 0.005
    ds, fe = _run(room, cfg)
    stamps, poses, _ = fe.trajectory()
    assert fe.num_failures == 0 and len(stamps) == FRAMES
    res = evaluate(ds.groundtruth, Trajectory(stamps, poses), EvalConfig(align="se3"))
    path = res.gt_path_length_m
    assert res.ate.rmse <= 0.005 * path + 0.001, f"ATE {res.ate.rmse:.4f} m on a {path:.2f} m path"
    est = np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1).sum()
    assert est == pytest.approx(path, rel=0.02)
    # depth maps are released when frames leave the graph
    assert all(f.depth is None for f in fe._final.values())


@pytest.mark.parametrize("field,value", [("depth_model", "measurement"), ("depth_noise", "quadratic")])
def test_depth_model_names_are_checked(field, value):
    from fgslam.core.errors import ConfigError

    cfg = light_patch_config()
    setattr(cfg.ba, field, value)
    with pytest.raises(ConfigError, match=f"patch.ba.depth_model must be prior\\|observation"):
        PatchFrontend(cfg, sensor_mode="rgbd", backend=Backend(BackendConfig()))



@pytest.mark.parametrize("noise,sigma", [("relative", 0.01), ("inverse", 0.005)])
def test_global_ba_depth_priors_follow_the_noise_model(room, noise, sigma, monkeypatch):
    """The global BA weights its depth priors by ``ba.depth_noise`` like the local BA (it used the
    relative model whatever the setting: with ``inverse``, weights off by z^2, 25x too strong at 5 m)."""
    cfg = light_patch_config()
    cfg.ba.depth_noise = noise
    cfg.ba.depth_prior_sigma = sigma
    fe = PatchFrontend(cfg, sensor_mode="rgbd", backend=Backend(BackendConfig()))
    for i, frame in enumerate(_open(room)):
        fe.process(frame)
        if i >= 12:
            break
    job = fe.contributor.global_ba_job(None)  # what the loop service hands to the worker: global_bundle_adjustment(problem, ...)
    prob = job.solve.args[0]
    assert len(prob.prior_idx) >= 20
    sigma_d = sigma * prob.prior_value if noise == "relative" else np.full(len(prob.prior_value), sigma)
    np.testing.assert_allclose(prob.prior_weight, 1.0 / sigma_d ** 2, rtol=1e-12)
