"""Position prior and planar-motion residuals: values, Jacobians against finite differences, and
the gtsam factors built from them (whitening, linearisation, use in an optimisation)."""

import gtsam
import numpy as np
import pytest

from fgslam.factors.planar import (
    fit_plane,
    planar_factor,
    planar_residual,
    planar_residual_relative,
    plane_in_keyframe,
    plane_in_world,
    plane_of_keyframe,
    tilt_basis,
    unit_up,
)
from fgslam.factors.position import camera_centre, position_noise, position_prior_factor, position_residual


def random_similarity(rng: np.random.Generator, log_scale: float = 0.7) -> gtsam.Similarity3:
    w = rng.normal(size=3)
    R = gtsam.Rot3.Expmap(w / np.linalg.norm(w) * rng.uniform(0.1, 3.0))
    return gtsam.Similarity3(R, rng.normal(scale=3.0, size=3), float(np.exp(rng.uniform(-log_scale, log_scale))))


def numeric_jacobian(f, T: gtsam.Similarity3, eps: float = 1e-6) -> np.ndarray:
    """Central differences of f(T Exp(d)) at d = 0 (right perturbation, gtsam's retract)."""
    cols = []
    for k in range(7):
        d = np.zeros(7)
        d[k] = eps
        cols.append((f(T.retract(d)) - f(T.retract(-d))) / (2 * eps))
    return np.stack(cols, axis=1)


def test_camera_centre_is_the_image_of_the_camera_origin():
    rng = np.random.default_rng(0)
    for _ in range(5):
        T = random_similarity(rng)
        np.testing.assert_allclose(camera_centre(T), T.transformFrom(np.zeros(3)), atol=1e-12)


def test_position_residual_and_jacobian_match_finite_differences():
    rng = np.random.default_rng(1)
    for _ in range(20):
        T = random_similarity(rng)
        p = rng.normal(scale=5.0, size=3)
        r, J = position_residual(T, p)
        np.testing.assert_allclose(r, T.transformFrom(np.zeros(3)) - p, atol=1e-12)
        J_num = numeric_jacobian(lambda X: position_residual(X, p)[0], T)
        np.testing.assert_allclose(J, J_num, atol=1e-7 * max(1.0, np.abs(J_num).max()))
        assert np.all(J[:, :3] == 0) and np.all(J[:, 6] == 0)


@pytest.mark.parametrize("sigma", [0.5, [0.5, 1.0, 2.0]])
def test_position_prior_factor_whitens_and_linearises(sigma):
    rng = np.random.default_rng(2)
    T = random_similarity(rng)
    p = rng.normal(size=3)
    factor = position_prior_factor(7, p, sigma)
    values = gtsam.Values()
    values.insert(7, T)
    r, J = position_residual(T, p)
    sig = np.broadcast_to(np.asarray(sigma, float), (3,))
    assert factor.error(values) == pytest.approx(0.5 * np.sum((r / sig) ** 2), rel=1e-12)
    A, b = factor.linearize(values).jacobian()
    np.testing.assert_allclose(A, J / sig[:, None], atol=1e-12)
    np.testing.assert_allclose(b, -r / sig, atol=1e-12)


def test_position_prior_factor_huber_downweights_outliers():
    T = gtsam.Similarity3(gtsam.Rot3(), np.zeros(3), 1.0)
    values = gtsam.Values()
    values.insert(0, T)
    far = np.array([100.0, 0.0, 0.0])
    plain = position_prior_factor(0, far, 1.0).error(values)
    robust = position_prior_factor(0, far, 1.0, huber_k=2.0).error(values)
    assert plain == pytest.approx(5000.0)
    assert robust < 0.05 * plain


@pytest.mark.parametrize("bad", [0.0, -1.0, float("nan"), [1.0, 2.0], [1.0, 0.0, 1.0]])
def test_position_noise_rejects_bad_sigmas(bad):
    with pytest.raises(ValueError, match="sigma"):
        position_noise(bad)


def test_position_priors_pin_a_similarity_in_an_optimisation():
    """Three keyframes with position priors and a between factor: LM moves the centres to the
    measured positions (the priors fix translation; the centres are what is measured)."""
    rng = np.random.default_rng(3)
    graph = gtsam.NonlinearFactorGraph()
    values = gtsam.Values()
    targets = rng.normal(scale=10.0, size=(3, 3))
    for k in range(3):
        values.insert(k, random_similarity(rng, log_scale=0.3))
        graph.add(position_prior_factor(k, targets[k], 0.01))
    result = gtsam.LevenbergMarquardtOptimizer(graph, values).optimize()
    for k in range(3):
        np.testing.assert_allclose(camera_centre(result.atSimilarity3(k)), targets[k], atol=1e-6)


# ----------------------------------------------------------------------------------------- planar


def test_tilt_basis_is_orthonormal_and_orthogonal_to_up():
    for up in ([0, -1, 0], [0, 0, 1], [1, 1, 1], [0.1, -0.9, 0.2]):
        a = unit_up(up)
        B = tilt_basis(a)
        np.testing.assert_allclose(B.T @ B, np.eye(2), atol=1e-12)
        np.testing.assert_allclose(a @ B, 0.0, atol=1e-12)
    np.testing.assert_allclose(tilt_basis(np.array([0.0, -1.0, 0.0])), [[0, -1], [0, 0], [1, 0]], atol=1e-12)


@pytest.mark.parametrize("bad", [[0, 0, 0], [1, 2], [np.nan, 1, 0]])
def test_unit_up_rejects_bad_axes(bad):
    with pytest.raises(ValueError, match="up axis"):
        unit_up(bad)


def test_planar_residual_zero_on_the_plane_and_measures_height_and_tilt():
    up = np.array([0.0, -1.0, 0.0])  # camera y points down
    # world z up; a forward-looking camera: x_C = -y_W, y_C = -z_W, z_C = x_W
    R0 = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
    ref = gtsam.Similarity3(gtsam.Rot3(R0), np.array([0.0, 0.0, 1.5]), 1.0)
    n, d = plane_of_keyframe(ref, up)
    np.testing.assert_allclose(n, [0, 0, 1], atol=1e-12)
    assert d == pytest.approx(-1.5)
    yaw = gtsam.Rot3.Rz(0.7).matrix()
    on_plane = gtsam.Similarity3(gtsam.Rot3(yaw @ R0), np.array([12.0, -4.0, 0.75]), 2.0)  # centre (24, -8, 1.5)
    np.testing.assert_allclose(planar_residual(on_plane, n, d, up)[0], 0.0, atol=1e-12)
    lifted = gtsam.Similarity3(gtsam.Rot3(yaw @ R0), np.array([12.0, -4.0, 0.85]), 2.0)  # 0.2 higher
    assert planar_residual(lifted, n, d, up)[0][0] == pytest.approx(0.2)
    pitch = 0.05  # about the camera x axis: the ground normal seen by the camera leans along z
    tilted = gtsam.Similarity3(gtsam.Rot3(yaw @ R0 @ gtsam.Rot3.Rx(pitch).matrix()), np.array([12.0, -4.0, 0.75]), 2.0)
    r = planar_residual(tilted, n, d, up)[0]
    assert abs(r[1]) == pytest.approx(np.sin(pitch), rel=1e-9) and abs(r[2]) < 1e-12
    roll = 0.03  # about the camera z axis: the normal leans along x
    rolled = gtsam.Similarity3(gtsam.Rot3(yaw @ R0 @ gtsam.Rot3.Rz(roll).matrix()), np.array([12.0, -4.0, 0.75]), 2.0)
    r = planar_residual(rolled, n, d, up)[0]
    assert abs(r[2]) == pytest.approx(np.sin(roll), rel=1e-9) and abs(r[1]) < 1e-12


@pytest.mark.parametrize("up", [[0, -1, 0], [0.2, -1.0, 0.1], [0, 0, 1]])
def test_planar_jacobian_matches_finite_differences(up):
    rng = np.random.default_rng(4)
    a = unit_up(up)
    for _ in range(20):
        T = random_similarity(rng)
        n, d = unit_up(rng.normal(size=3)), float(rng.normal(scale=3.0))
        r, J = planar_residual(T, n, d, a)
        num = numeric_jacobian(lambda X: planar_residual(X, n, d, a)[0], T)
        np.testing.assert_allclose(J, num, atol=1e-7 * max(1.0, np.abs(num).max()))
        assert np.all(J[0, :3] == 0) and np.all(J[1:, 3:] == 0)


def test_fit_plane_recovers_the_plane_of_noisy_level_keyframes():
    """Keyframes on a tilted camera plane with a wobble of their attitude and height: the fit finds the
    plane to well below the wobble (it averages), where a single keyframe's plane is off by its wobble."""
    rng = np.random.default_rng(6)
    up = unit_up([0.02, -1.0, 0.03])  # a mount with small roll and pitch
    R_tilt = gtsam.Rot3.Expmap(np.array([0.1, -0.05, 0.0])).matrix()  # the ground plane's attitude in the world
    # camera attitude: a level camera has up_C along the plane normal: R_WC up = n_true
    n_true = R_tilt @ np.array([0.0, 0.0, 1.0])
    d_true = -2.0
    # a level camera maps its up axis onto the plane normal: R_level up = n_true
    z = np.array([0.0, 0.0, 1.0])
    axis = np.cross(up, z)
    R_level = R_tilt @ gtsam.Rot3.AxisAngle(axis / np.linalg.norm(axis), np.arccos(up @ z)).matrix()
    centres, rotations = [], []
    for k in range(200):
        yaw = gtsam.Rot3.AxisAngle(n_true, rng.uniform(-np.pi, np.pi)).matrix()
        R = yaw @ R_level @ gtsam.Rot3.Expmap(rng.normal(scale=0.01, size=3)).matrix()
        np.testing.assert_allclose(yaw @ R_level @ up, n_true, atol=1e-9)
        in_plane = rng.normal(scale=50.0, size=3)
        in_plane -= (in_plane @ n_true) * n_true
        centres.append(in_plane - d_true * n_true + rng.normal(scale=0.02) * n_true)
        rotations.append(R)
    n, d = fit_plane(np.array(centres), np.array(rotations), up, height_sigma=0.02, tilt_sigma=0.01)
    assert np.degrees(np.arccos(min(1.0, n @ n_true))) < 0.01
    assert d == pytest.approx(d_true, abs=0.01)
    n1, _ = plane_of_keyframe(gtsam.Similarity3(gtsam.Rot3(rotations[0]), centres[0], 1.0), up)
    assert np.degrees(np.arccos(min(1.0, n1 @ n_true))) > 0.05  # one keyframe: off by its wobble


def test_plane_in_world_and_in_keyframe_are_inverse_and_follow_the_map():
    rng = np.random.default_rng(7)
    T_ref = random_similarity(rng)
    n_C, d_C = unit_up(rng.normal(size=3)), 1.7
    n_W, d_W = plane_in_world(T_ref, n_C, d_C)
    n_back, d_back = plane_in_keyframe(T_ref, n_W, d_W)
    np.testing.assert_allclose(n_back, n_C, atol=1e-12)
    assert d_back == pytest.approx(d_C)
    # a point on the plane in the reference camera lies on the world plane
    x_C = rng.normal(size=3)
    x_C -= (n_C @ x_C + d_C) * n_C
    assert n_W @ T_ref.transformFrom(x_C) + d_W == pytest.approx(0.0, abs=1e-9)
    # moving the whole map by a similarity leaves the relative residual as it is, heights times its scale
    T_k = random_similarity(rng)
    U = gtsam.Similarity3(gtsam.Rot3.Expmap(np.array([0.3, -0.2, 1.0])), np.array([5.0, -3.0, 2.0]), 2.5)
    up = unit_up([0.0, -1.0, 0.0])
    r = planar_residual_relative(T_ref, T_k, n_C, d_C, up)[0]
    r_moved = planar_residual_relative(U * T_ref, U * T_k, n_C, d_C, up)[0]
    np.testing.assert_allclose(r_moved, r * np.array([2.5, 1.0, 1.0]), atol=1e-9)


@pytest.mark.parametrize("up", [[0, -1, 0], [0.2, -1.0, 0.1]])
def test_relative_planar_jacobians_match_finite_differences(up):
    rng = np.random.default_rng(8)
    a = unit_up(up)
    for _ in range(20):
        T_ref, T_k = random_similarity(rng), random_similarity(rng)
        n_C, d_C = unit_up(rng.normal(size=3)), float(rng.normal(scale=3.0))
        r, J_ref, J_k = planar_residual_relative(T_ref, T_k, n_C, d_C, a)
        n_W, d_W = plane_in_world(T_ref, n_C, d_C)
        np.testing.assert_allclose(r, planar_residual(T_k, n_W, d_W, a)[0], atol=1e-12)
        num_ref = numeric_jacobian(lambda X: planar_residual_relative(X, T_k, n_C, d_C, a)[0], T_ref)
        num_k = numeric_jacobian(lambda X: planar_residual_relative(T_ref, X, n_C, d_C, a)[0], T_k)
        scale = max(1.0, np.abs(num_ref).max(), np.abs(num_k).max())
        np.testing.assert_allclose(J_ref, num_ref, atol=1e-7 * scale)
        np.testing.assert_allclose(J_k, num_k, atol=1e-7 * scale)


def test_planar_factor_whitens_and_linearises():
    rng = np.random.default_rng(5)
    T_ref, T = random_similarity(rng), random_similarity(rng)
    up = [0.0, -1.0, 0.0]
    n, d = unit_up([0.1, 0.2, 1.0]), 0.7
    factor = planar_factor(1, 2, n, d, up, height_sigma=0.05, tilt_sigma=0.01)
    values = gtsam.Values()
    values.insert(1, T_ref)
    values.insert(2, T)
    r, J_ref, J = planar_residual_relative(T_ref, T, n, d, unit_up(up))
    sig = np.array([0.05, 0.01, 0.01])
    assert factor.error(values) == pytest.approx(0.5 * np.sum((r / sig) ** 2), rel=1e-12)
    A, b = factor.linearize(values).jacobian()
    np.testing.assert_allclose(A, np.hstack([J_ref, J]) / sig[:, None], atol=1e-9)
    np.testing.assert_allclose(b, -r / sig, atol=1e-12)
    with pytest.raises(ValueError, match="sigmas"):
        planar_factor(1, 2, n, d, up, 0.0, 0.01)
    with pytest.raises(ValueError, match="offset"):
        planar_factor(1, 2, n, float("nan"), up, 0.05, 0.01)
    with pytest.raises(ValueError, match="same key"):
        planar_factor(3, 3, n, d, up, 0.05, 0.01)
