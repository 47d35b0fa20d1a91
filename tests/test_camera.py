"""Pinhole camera math: projections vs gtsam, Jacobians vs finite differences, masks, intrinsics edits."""

import gtsam
import numpy as np
import pytest
import torch

from fgslam.core.camera import PinholeCamera, StereoRig, normalize_rays, pixel_rays, project, unproject
from fgslam.core.errors import ConfigError

F64 = torch.float64
K_REF = torch.tensor([420.0, 410.0, 319.5, 239.5], dtype=F64)


def random_points(rng, n):
    """Points in front of the camera: generic, near the optical axis, far off-axis, very near/far."""
    X = rng.normal(size=(n, 3))
    X[:, 2] = 10 ** rng.uniform(-3, 3, n)
    X[: n // 4, :2] *= 1e-6  # near the principal point
    X[n // 4 : n // 2, :2] *= X[n // 4 : n // 2, 2:] * 3  # far outside the image
    return torch.from_numpy(X)


def central_difference(f, x, eps):
    """d f / d x (..., out, in) by central differences; ``eps`` per row (...,)."""
    cols = []
    for k in range(x.shape[-1]):
        e = torch.zeros_like(x)
        e[..., k] = eps
        cols.append((f(x + e) - f(x - e)) / (2 * eps[..., None]))
    return torch.stack(cols, dim=-1)


def test_project_matches_gtsam_pinhole_and_finite_differences():
    rng = np.random.default_rng(0)
    X = random_points(rng, 200)
    uv, J, valid = project(X, K_REF)
    assert valid.all()
    fx, fy, cx, cy = K_REF.tolist()
    cam = gtsam.PinholeCameraCal3_S2(gtsam.Pose3(), gtsam.Cal3_S2(fx, fy, 0.0, cx, cy))
    for k in range(0, 200, 7):
        Dpoint = np.zeros((2, 3), order="F")
        uv_g = cam.project(X[k].numpy(), None, Dpoint, None)
        np.testing.assert_allclose(uv[k].numpy(), uv_g, rtol=1e-12, atol=1e-9)
        np.testing.assert_allclose(J[k].numpy(), Dpoint, rtol=1e-12, atol=1e-12)
    J_fd = central_difference(lambda x: project(x, K_REF)[0], X, 1e-6 * X[:, 2])
    scale = 1 + J_fd.abs().amax((-2, -1), keepdim=True)
    assert ((J - J_fd).abs() / scale).max() < 1e-6


def test_project_masks_points_behind_or_on_the_camera_plane():
    X = torch.tensor([[0.1, 0.2, 1.0], [0.1, 0.2, 0.0], [0.1, 0.2, -1.0], [1.0, 1.0, 1e-320], [0.0, 0.0, 0.05]],
                     dtype=F64)
    for dtype in (torch.float32, F64):
        uv, J, valid = project(X.to(dtype), K_REF.to(dtype), min_depth=0.01)
        assert valid.tolist() == [True, False, False, False, True]
        assert torch.isfinite(uv).all() and torch.isfinite(J).all()
        assert (uv[~valid] == 0).all() and (J[~valid] == 0).all()
    _, _, valid = project(X, K_REF, min_depth=0.1)
    assert valid.tolist() == [True, False, False, False, False]


def test_unproject_roundtrip_and_depth_derivative():
    rng = np.random.default_rng(1)
    n = 300
    uv = torch.from_numpy(rng.uniform(-0.5, 639.5, (n, 2)))
    d = torch.from_numpy(10 ** rng.uniform(-4, 2, n))
    X, dX_dd, valid = unproject(uv, d, K_REF)
    assert valid.all()
    torch.testing.assert_close(1.0 / X[:, 2], d)
    uv2, _, valid2 = project(X, K_REF)
    assert valid2.all()
    torch.testing.assert_close(uv2, uv, rtol=0, atol=1e-9)
    torch.testing.assert_close(pixel_rays(uv, K_REF), X * d[:, None])
    h = 1e-6 * d
    fd = (unproject(uv, d + h, K_REF)[0] - unproject(uv, d - h, K_REF)[0]) / (2 * h[:, None])
    torch.testing.assert_close(dX_dd, fd, rtol=1e-6, atol=1e-9)


def test_unproject_masks_zero_negative_and_nonfinite_inverse_depth():
    uv = torch.tensor([[10.0, 20.0]] * 5, dtype=torch.float32)
    d = torch.tensor([0.5, 0.0, -1.0, float("nan"), 1e-30])
    X, dX_dd, valid = unproject(uv, d, K_REF.float())
    assert valid.tolist() == [True, False, False, False, False]  # 1e-30: dX/dd overflows float32
    assert torch.isfinite(X).all() and torch.isfinite(dX_dd).all()
    assert (X[~valid] == 0).all() and (dX_dd[~valid] == 0).all()


def test_normalize_rays_unit_norm_jacobian_and_zero_vector():
    rng = np.random.default_rng(2)
    X = torch.from_numpy(rng.normal(size=(200, 3)) * 10 ** rng.uniform(-3, 3, (200, 1)))
    psi, J, valid = normalize_rays(X)
    assert valid.all()
    torch.testing.assert_close(psi.norm(dim=-1), torch.ones(200, dtype=F64))
    torch.testing.assert_close(psi * X.norm(dim=-1, keepdim=True), X)
    J_fd = central_difference(lambda x: normalize_rays(x)[0], X, 1e-6 * X.norm(dim=-1))
    scale = 1 + J_fd.abs().amax((-2, -1), keepdim=True)
    assert ((J - J_fd).abs() / scale).max() < 1e-6
    psi0, J0, valid0 = normalize_rays(torch.zeros(2, 3))
    assert not valid0.any() and (psi0 == 0).all() and (J0 == 0).all()


def test_pinhole_camera_resize_is_half_pixel_exact():
    cam = PinholeCamera((420.0, 410.0, 319.5, 239.5), 640, 480)
    small = cam.scaled(1 / 8)
    assert (small.width, small.height) == (80, 60)
    rng = np.random.default_rng(3)
    X = torch.from_numpy(rng.normal(size=(50, 3)) + np.array([0, 0, 5.0]))
    uv, _, _ = project(X, cam.K_tensor())
    uv_small, _, _ = project(X, small.K_tensor())
    a = 80 / 640
    torch.testing.assert_close(uv_small, a * (uv + 0.5) - 0.5)
    # the principal point of a centred camera stays at the image centre
    assert small.cx == pytest.approx((small.width - 1) / 2) and small.cy == pytest.approx((small.height - 1) / 2)
    resized = cam.resized(320, 480)
    assert resized.fx == pytest.approx(210.0) and resized.fy == pytest.approx(410.0)
    np.testing.assert_allclose(cam.matrix(), [[420, 0, 319.5], [0, 410, 239.5], [0, 0, 1]])


def test_pinhole_camera_crop_and_contains():
    cam = PinholeCamera([500, 500, 320, 240], 640, 480)
    crop = cam.cropped(10, 20, 600, 400)
    assert crop.K == (500.0, 500.0, 310.0, 220.0) and (crop.width, crop.height) == (600, 400)
    X = torch.tensor([[0.3, -0.1, 2.0]], dtype=F64)
    shift = torch.tensor([10.0, 20.0], dtype=F64)
    torch.testing.assert_close(project(X, crop.K_tensor())[0], project(X, cam.K_tensor())[0] - shift)
    with pytest.raises(ConfigError):
        cam.cropped(100, 0, 600, 480)
    with pytest.raises(ConfigError):
        PinholeCamera((0.0, 500, 320, 240), 640, 480)
    with pytest.raises(ConfigError):
        cam.scaled(0.0)
    uv = torch.tensor([[-0.5, 0.0], [-0.51, 0.0], [639.5, 479.5], [639.6, 10.0], [5.0, 5.0]])
    assert cam.contains(uv).tolist() == [True, False, True, False, True]
    assert cam.contains(uv, margin=6.0).tolist() == [False, False, False, False, False]


def test_stereo_rig_baseline_from_extrinsics():
    rng = np.random.default_rng(4)
    left = PinholeCamera((458.0, 457.0, 367.0, 248.0), 752, 480)
    right = PinholeCamera((457.0, 456.0, 379.0, 255.0), 752, 480)
    R = gtsam.Rot3.Expmap(rng.normal(size=3) * 0.01).matrix()
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = [0.110, -0.0004, 0.0009]
    rig = StereoRig(left, right, T)
    assert rig.baseline == pytest.approx(np.linalg.norm([0.110, -0.0004, 0.0009]))
    np.testing.assert_allclose(rig.T_CRCL @ rig.T_CLCR, np.eye(4), atol=1e-12)
    assert rig.scaled(0.5).left.width == 376 and rig.scaled(0.5).baseline == rig.baseline
    bad = T.copy()
    bad[:3, :3] *= 1.01
    with pytest.raises(ConfigError):
        StereoRig(left, right, bad)
    with pytest.raises(ConfigError):
        StereoRig(left, right, np.eye(4))
    with pytest.raises(ConfigError):
        StereoRig(left, right, np.eye(3))
