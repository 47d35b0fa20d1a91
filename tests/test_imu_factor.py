"""The Sim(3) -> Pose3 IMU adapter (fgslam/factors/imu.py): Jacobians against finite differences,
the wrapped CombinedImuFactor against gtsam's own factor on Pose3 keys, preintegration pieces."""

import numpy as np
import pytest

gtsam = pytest.importorskip("gtsam")

from fgslam.factors.imu import (ImuNoise, body_pose, body_pose_jacobian, combined_params, imu_factor_on_sim3,
                                integration_steps, preintegrate, sim3_from_body_pose)

from factor_support import assert_jacobians_match_central_differences

NOISE = ImuNoise(1.7e-4, 2.0e-3, 1.9e-5, 3.0e-3)


def random_sim3(rng):
    return gtsam.Similarity3(gtsam.Rot3.Expmap(rng.normal(size=3)), rng.normal(size=3), float(np.exp(rng.normal(0, 0.3))))


def random_pose(rng):
    return gtsam.Pose3(gtsam.Rot3.Expmap(rng.normal(size=3) * 0.5), rng.normal(size=3) * 0.2)


def test_body_pose_jacobian_matches_finite_differences():
    rng = np.random.default_rng(0)
    for _ in range(20):
        S, T_CB = random_sim3(rng), random_pose(rng)
        J = body_pose_jacobian(S, T_CB)
        P0 = body_pose(S, T_CB)
        eps = 1e-6
        num = np.zeros((6, 7))
        for k in range(7):
            d = np.zeros(7)
            d[k] = eps
            plus = P0.localCoordinates(body_pose(S.retract(d), T_CB))
            minus = P0.localCoordinates(body_pose(S.retract(-d), T_CB))
            num[:, k] = (plus - minus) / (2 * eps)
        np.testing.assert_allclose(J, num, atol=1e-7)
        assert np.abs(J[:, 6]).max() == 0.0  # the keyframe scale is a gauge: the body pose ignores it


def test_sim3_from_body_pose_inverts_body_pose():
    rng = np.random.default_rng(1)
    T_WB, T_CB = random_pose(rng), random_pose(rng)
    S = sim3_from_body_pose(T_WB, T_CB, scale=1.7)
    assert S.scale() == pytest.approx(1.7)
    assert body_pose(S, T_CB).equals(T_WB, 1e-12)


def _imu_problem(rng):
    params = combined_params(np.array([0.0, 0.0, -9.81]), NOISE)
    bias = gtsam.imuBias.ConstantBias(rng.normal(0, 0.05, 3), rng.normal(0, 0.01, 3))
    t = np.arange(0, 0.5, 0.005)
    pim = preintegrate(params, bias, t, rng.normal(0, 0.3, (t.size, 3)), rng.normal(0, 1.0, (t.size, 3)) + [0, 0, 9.81],
                       0.0, 0.5)
    return pim


def test_wrapped_factor_error_and_jacobians():
    rng = np.random.default_rng(2)
    pim = _imu_problem(rng)
    T_CB = random_pose(rng)
    keys = (gtsam.symbol("x", 0), gtsam.symbol("v", 0), gtsam.symbol("x", 1), gtsam.symbol("v", 1),
            gtsam.symbol("b", 0), gtsam.symbol("b", 1))
    values = gtsam.Values()
    Si, Sj = random_sim3(rng), random_sim3(rng)
    values.insert(keys[0], Si)
    values.insert(keys[1], rng.normal(size=3))
    values.insert(keys[2], Sj)
    values.insert(keys[3], rng.normal(size=3))
    values.insert(keys[4], gtsam.imuBias.ConstantBias(rng.normal(0, 0.1, 3), rng.normal(0, 0.01, 3)))
    values.insert(keys[5], gtsam.imuBias.ConstantBias(rng.normal(0, 0.1, 3), rng.normal(0, 0.01, 3)))
    factor = imu_factor_on_sim3(keys, pim, T_CB)

    # same error as gtsam's CombinedImuFactor on the body poses
    ref = gtsam.CombinedImuFactor(*range(6), pim)
    local = gtsam.Values()
    local.insert(0, body_pose(Si, T_CB))
    local.insert(1, values.atPoint3(keys[1]))
    local.insert(2, body_pose(Sj, T_CB))
    local.insert(3, values.atPoint3(keys[3]))
    local.insert(4, values.atConstantBias(keys[4]))
    local.insert(5, values.atConstantBias(keys[5]))
    assert factor.error(values) == pytest.approx(ref.error(local), rel=1e-12)
    assert factor.error(values) > 0

    # Jacobians of the whitened error against central differences in every key's tangent
    assert_jacobians_match_central_differences(factor, values, keys, [7, 3, 7, 3, 6, 6])


def test_integration_steps_cover_the_interval():
    t = np.array([0.0, 0.1, 0.2, 0.3])
    idx, dt = integration_steps(t, 0.05, 0.25)
    np.testing.assert_array_equal(idx, [0, 1, 2])
    np.testing.assert_allclose(dt, [0.05, 0.1, 0.05])
    idx, dt = integration_steps(t, -0.1, 0.45)  # before the first sample: held by it; after the last: the last
    assert dt.sum() == pytest.approx(0.55)
    assert integration_steps(t, 0.2, 0.2)[0].size == 0


def test_preintegrated_factor_against_synthetic_ground_truth():
    """The synthetic generator's noisy, biased IMU between two body states 0.25 s apart: the wrapped
    factor at the true poses (as Sim(3) camera poses with an arbitrary keyframe scale), velocities and
    biases is chi-square consistent (15 dof), and a 5 cm position error is not."""
    from fgslam.io.synth import SynthSequence
    from fgslam.io.synth.scenarios import load_synth_config

    seq = SynthSequence(load_synth_config("room-loop", overrides=["frames=21"]))
    imu = seq.imu
    params = combined_params(np.array([0.0, 0.0, -seq.cfg.imu.gravity]),
                             ImuNoise(seq.cfg.imu.gyroscope_noise_density, seq.cfg.imu.accelerometer_noise_density,
                                      seq.cfg.imu.gyroscope_random_walk, seq.cfg.imu.accelerometer_random_walk))
    rng = np.random.default_rng(3)
    T_CB = random_pose(rng)
    chi2 = []
    for t0 in (0.1, 0.35, 0.6):
        t1 = t0 + 0.25
        k0, k1 = (int(np.argmin(np.abs(imu.t - t))) for t in (t0, t1))
        t0, t1 = float(imu.t[k0]), float(imu.t[k1])
        states = seq.states(np.array([t0, t1]))
        bias = [gtsam.imuBias.ConstantBias(imu.bias_accel[k], imu.bias_gyro[k]) for k in (k0, k1)]
        pim = preintegrate(params, bias[0], imu.t, imu.gyro, imu.accel, t0, t1)
        keys = tuple(range(10, 16))
        factor = imu_factor_on_sim3(keys, pim, T_CB)
        values = gtsam.Values()
        for i, (kx, kv) in enumerate(((keys[0], keys[1]), (keys[2], keys[3]))):
            T_WB = gtsam.Pose3(gtsam.Rot3(states.R_WB[i]), states.p_WB[i])
            values.insert(kx, sim3_from_body_pose(T_WB, T_CB, scale=float(rng.uniform(0.5, 2.0))))
            values.insert(kv, states.v_WB[i])
        values.insert(keys[4], bias[0])
        values.insert(keys[5], bias[1])
        chi2.append(2 * factor.error(values))
        shifted = gtsam.Values(values)
        S = values.atSimilarity3(keys[2])
        shifted.update(keys[2], gtsam.Similarity3(S.rotation(), np.asarray(S.translation()) + 0.05 / S.scale(), S.scale()))
        assert 2 * factor.error(shifted) > 1000
    assert np.mean(chi2) < 3 * 15, chi2  # chi-square with 15 dof: mean 15
