"""Loop corrections with the IMU in the graph and the inertial-only optimisation (issue 26;
fgslam/services/imu.py, imu_init.py): velocities and marginal priors follow a correction, the IMU
factors stay consistent; the inertial-only factor's Jacobians; scale and gravity recovered."""

import numpy as np
import pytest

gtsam = pytest.importorskip("gtsam")

from fgslam.backend import Backend
from fgslam.backend.keys import velocity_key
from fgslam.io.frame import ImuSamples
from fgslam.core.lie import gtsam_sim3
from fgslam.loop.records import PoseCorrection
from fgslam.services.corrections import ObservedContributor
from fgslam.services.imu import ImuService
from fgslam.services.imu_chain import OWNER
from fgslam.services.imu_init import inertial_only_factor, rotation_to_gravity_frame, solve_inertial_only
from fgslam.services.imu_samples import ImuBuffer, ImuServiceConfig, ImuStats
from fgslam.factors.imu import ImuNoise, combined_params

from factor_support import assert_jacobians_match_central_differences

G_W = np.array([0.0, 0.0, -9.81])
RATE = 200.0
FRAME_DT = 0.05
NOISE = ImuNoise(1.7e-4, 2e-3, 1.9e-5, 3e-3)


def _rot(axis, angle):
    return np.asarray(gtsam.Rot3.Rodrigues(np.asarray(axis, float) * angle).matrix())


def _gt(t):
    """A loop with accelerations in every direction: body pose (R_WB, p) and velocity at time t."""
    w = 0.6
    p = np.array([2.0 * np.cos(w * t), 1.5 * np.sin(w * t), 0.3 * np.sin(2 * w * t)])
    v = np.array([-2.0 * w * np.sin(w * t), 1.5 * w * np.cos(w * t), 0.6 * w * np.cos(2 * w * t)])
    R = _rot([0, 0, 1], w * t + 0.5) @ _rot([1, 0, 0], 0.2 * np.sin(1.3 * t))
    return R, p, v


def _samples(t0, t1):
    """Noise-free samples on (t0, t1] at RATE: gyro the exact zero-order-hold rotation increment,
    accel the specific force (mid-step acceleration by central differences of the velocity)."""
    ts = np.arange(int(round(t0 * RATE)) + 1, int(round(t1 * RATE)) + 1) / RATE
    dt = 1.0 / RATE
    gyro, accel = [], []
    for t in ts:
        R0, _, v0 = _gt(t)
        R1, _, v1 = _gt(t + dt)
        gyro.append(np.asarray(gtsam.Rot3.Logmap(gtsam.Rot3(R0.T @ R1))) / dt)
        accel.append(R0.T @ ((v1 - v0) / dt - G_W))
    return ImuSamples(ts, np.array(gyro), np.array(accel))


def _T_WC(t, D=np.eye(4)):
    R, p, _ = _gt(t)
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, p
    return D @ T  # T_BC = I


def _drift(yaw_deg=8.0):
    D = np.eye(4)
    D[:3, :3] = _rot([0, 0, 1], np.radians(yaw_deg))
    D[:3, 3] = [0.4, -0.3, 0.0]
    return D


def _imu_errors(backend):
    graph = gtsam.NonlinearFactorGraph()
    for h in backend.factor_handles(OWNER):
        graph.add(backend.factor(h))
    values = backend.values_of([int(k) for k in graph.keyVector()])
    return graph.error(values)


def _marginal_priors(backend):
    return sum(isinstance(backend.factor(h), gtsam.LinearContainerFactor) for h in backend.factor_handles(OWNER))


def _drifted_run(D, seconds=3.0, window_keyframes=8):
    """A metric map whose keyframes (every 0.1 s) lie in the drifted frame ``D`` (a yaw about gravity
    and a shift), the IMU service initialised on it (visual-inertial: moving start)."""
    backend = Backend()
    cfg = ImuServiceConfig(enabled=True, window_keyframes=window_keyframes)
    cfg.init.static_metric_start = False
    service = ImuService(cfg, backend, np.eye(4), metric=True, dataset_noise=None)
    for k in range(1, int(round(seconds / FRAME_DT)) + 1):
        t0, t1 = (k - 1) * FRAME_DT, k * FRAME_DT
        service.feed(_samples(t0, t1), t1)
        if k % 2 == 0:
            backend.add_keyframe(k, _T_WC(t1, D), t1)
        service.poll()
    return backend, service


def test_loop_correction_turns_velocities_and_keeps_imu_factors_consistent():
    D = _drift()
    backend, service = _drifted_run(D)
    assert service.initialized and service.stats.marginalised > 0  # window: marginal priors exist
    before = _imu_errors(backend)
    n_marginal = _marginal_priors(backend)
    assert n_marginal > 0
    v_drift = {kf: service.velocity(kf) for kf in service.chain.linked}
    # the loop correction takes the drifted keyframes back to the ground truth (as a pose graph would)
    ids = backend.keyframe_ids
    corr = PoseCorrection.between({k: backend.pose_matrix(k) for k in ids}, {k: _T_WC(backend.timestamp(k)) for k in ids})

    class Moves:  # a contributor: moves its keyframes in the backend
        def apply_correction(self, c):
            for k in backend.keyframe_ids:
                backend.set_pose(k, c.apply_pose(k, backend.pose_matrix(k))[0])

    observed = ObservedContributor(Moves(), service.adapt_correction, (service.on_correction,))
    observed.apply_correction(corr)
    after = _imu_errors(backend)
    for kf in service.chain.linked:
        v_gt = _gt(backend.timestamp(kf))[2]
        np.testing.assert_allclose(service.velocity(kf), v_gt, atol=0.02)  # corrected frame = ground truth
        assert np.linalg.norm(v_drift[kf] - v_gt) > 0.1  # they were in the drifted frame
    assert after == pytest.approx(before, rel=0.05, abs=1e-4)  # marginal priors re-anchored, not dropped:
    assert _marginal_priors(backend) == n_marginal
    # control: the old behaviour (velocities not turned) makes the IMU factors explode
    for kf, v in v_drift.items():
        backend.set_value(velocity_key(kf), v)
    assert _imu_errors(backend) > 1e4 * max(before, 1e-3)


def test_rescale_scales_velocities_and_sim3_corrections_become_se3_once_scale_is_fixed():
    backend, service = _drifted_run(np.eye(4), seconds=2.0)
    v0 = {kf: service.velocity(kf) for kf in service.chain.linked}
    service._rescale(2.0)  # no contributor: the keyframe poses scale (centres x2)
    for kf, v in v0.items():
        np.testing.assert_allclose(service.velocity(kf), 2.0 * v, rtol=1e-9)
    assert not any(isinstance(backend.factor(h), gtsam.LinearContainerFactor) for h in backend.factor_handles(OWNER))
    # a monocular map whose scale the IMU fixed: a folded Sim(3) correction is taken as SE(3)
    service.metric = False
    ids = backend.keyframe_ids
    U = np.eye(4)
    U[:3, :3] = 1.1 * _rot([0, 0, 1], 0.1)
    U[:3, 3] = [1.0, 0.0, 0.0]
    corr = PoseCorrection.between({k: backend.pose_matrix(k) for k in ids}, {k: U @ backend.pose_matrix(k) for k in ids},
                                  fold_scale=True)
    rigid = service.adapt_correction(corr)
    assert not rigid.fold_scale and all(s == pytest.approx(1.0) for s in rigid.scale.values())
    for k in ids:
        T_new, _ = rigid.apply_pose(k, backend.pose_matrix(k))
        np.testing.assert_allclose(T_new[:3, 3], (U @ backend.pose_matrix(k))[:3, 3], atol=1e-9)  # centres kept
        np.testing.assert_allclose(np.linalg.det(T_new[:3, :3]) ** (1 / 3), np.linalg.det(backend.pose_matrix(k)[:3, :3]) ** (1 / 3))
    service.initialized = False  # before the scale is fixed: unchanged
    assert service.adapt_correction(corr) is corr


def _window(n=12, dt=0.25, t0=0.3):
    ts = [t0 + i * dt for i in range(n)]
    buffer = ImuBuffer(0.05, ImuStats())
    prev = ts[0] - 0.5
    buffer.feed(_samples(prev - FRAME_DT, prev), prev)
    for t in ts:
        buffer.feed(_samples(prev, t), t)
        prev = t
    return ts, buffer


def test_inertial_only_factor_jacobians_match_finite_differences():
    rng = np.random.default_rng(4)
    ts, buffer = _window(n=2, dt=0.4)
    params = combined_params(G_W, NOISE)
    bias = gtsam.imuBias.ConstantBias(rng.normal(0, 0.05, 3), rng.normal(0, 0.01, 3))
    pim = buffer.preintegrate(params, ts[0], ts[1], bias)
    T = [gtsam.Pose3(gtsam.Rot3(_gt(t)[0]), _gt(t)[1] + rng.normal(0, 0.1, 3)) for t in ts]
    centres = [rng.normal(size=3), rng.normal(size=3)]
    keys = (gtsam.symbol("l", 0), gtsam.symbol("g", 0), gtsam.symbol("v", 0), gtsam.symbol("v", 1), gtsam.symbol("b", 0))
    factor = inertial_only_factor(keys, pim, T[0], T[1], centres)
    values = gtsam.Values()
    values.insert(keys[0], np.array([0.2]))
    values.insert(keys[1], gtsam.Rot3.Rodrigues(rng.normal(0, 0.2, 3)))
    values.insert(keys[2], rng.normal(size=3))
    values.insert(keys[3], rng.normal(size=3))
    values.insert(keys[4], gtsam.imuBias.ConstantBias(rng.normal(0, 0.1, 3), rng.normal(0, 0.01, 3)))
    assert factor.error(values) > 0
    assert_jacobians_match_central_differences(factor, values, keys, [1, 3, 3, 3, 6])


def test_inertial_only_recovers_scale_gravity_and_velocities():
    ts, buffer = _window()
    scale = 1.3  # map units: metres / 1.3
    poses = [gtsam_sim3(_scaled(_T_WC(t), 1 / scale)) for t in ts]
    tilt = _rot([1, 0, 0], np.radians(4.0))
    g_start = tilt @ G_W
    cfg = ImuServiceConfig(enabled=True)
    settings = Backend().optimizer.settings(20)
    start_v = np.zeros((len(ts), 3))
    res = solve_inertial_only(list(zip(ts, range(len(ts)))), poses, gtsam.Pose3(), buffer, cfg, NOISE, False, g_start,
                              start_v, gtsam.imuBias.ConstantBias(), settings)
    assert res is not None
    assert res.scale == pytest.approx(scale, rel=0.005)
    assert 0 < res.log_scale_sigma < 0.01
    angle = np.degrees(np.arccos(np.clip(res.gravity_W @ G_W / 9.81 ** 2, -1, 1)))
    assert angle < 0.2  # from 4 deg
    for t, v in zip(ts, res.velocities):
        np.testing.assert_allclose(v, _gt(t)[2], atol=0.02)
    assert res.final_cost < 1e-3 * res.initial_cost
    np.testing.assert_allclose(rotation_to_gravity_frame(g_start) @ g_start, G_W, atol=1e-12)


def _scaled(T, s):
    out = T.copy()
    out[:3, 3] *= s
    return out
