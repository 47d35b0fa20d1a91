"""Range residual between two Sim(3) camera centres: value, Jacobians against central finite
differences of right perturbations, and the gtsam CustomFactor built on it."""

import gtsam
import numpy as np
import pytest

from fgslam.factors.range import camera_centre, range_factor, range_residual


def random_similarity(rng, log_s=0.5) -> gtsam.Similarity3:
    xi = np.concatenate([rng.normal(size=3), rng.normal(size=3) * 2.0, rng.normal(size=1) * log_s])
    return gtsam.Similarity3.Expmap(xi)


def retract(T: gtsam.Similarity3, xi: np.ndarray) -> gtsam.Similarity3:
    return T.compose(gtsam.Similarity3.Expmap(xi))


def test_camera_centre_is_the_world_position_of_the_camera_origin():
    rng = np.random.default_rng(0)
    for _ in range(10):
        T = random_similarity(rng)
        np.testing.assert_allclose(camera_centre(T), T.transformFrom(np.zeros(3)), rtol=0, atol=1e-12)


def test_residual_is_distance_minus_measurement():
    rng = np.random.default_rng(1)
    T_a, T_b = random_similarity(rng), random_similarity(rng)
    dist = np.linalg.norm(T_b.transformFrom(np.zeros(3)) - T_a.transformFrom(np.zeros(3)))
    r, _, _ = range_residual(T_a, T_b, 1.5)
    assert r.shape == (1,)
    assert r[0] == pytest.approx(dist - 1.5, rel=1e-12)


@pytest.mark.parametrize("seed", range(5))
def test_jacobians_match_finite_differences(seed):
    rng = np.random.default_rng(seed)
    T_a, T_b = random_similarity(rng), random_similarity(rng)
    distance = rng.uniform(0.5, 3.0)
    _, J_a, J_b = range_residual(T_a, T_b, distance)
    eps = 1e-6
    fd_a, fd_b = np.zeros((1, 7)), np.zeros((1, 7))
    for k in range(7):
        e = np.zeros(7)
        e[k] = eps
        fd_a[0, k] = (range_residual(retract(T_a, e), T_b, distance)[0]
                      - range_residual(retract(T_a, -e), T_b, distance)[0])[0] / (2 * eps)
        fd_b[0, k] = (range_residual(T_a, retract(T_b, e), distance)[0]
                      - range_residual(T_a, retract(T_b, -e), distance)[0])[0] / (2 * eps)
    np.testing.assert_allclose(J_a, fd_a, rtol=0, atol=1e-7)
    np.testing.assert_allclose(J_b, fd_b, rtol=0, atol=1e-7)
    # only the translation block moves a camera's own origin, and it moves it by s R u
    assert np.abs(J_a[0, 3:6]).max() > 1e-3 and np.abs(J_b[0, 3:6]).max() > 1e-3


def test_coincident_centres_give_finite_zero_jacobians():
    rng = np.random.default_rng(7)
    T = random_similarity(rng)
    r, J_a, J_b = range_residual(T, T, 0.25)
    assert r[0] == pytest.approx(-0.25)
    assert np.isfinite(J_a).all() and np.isfinite(J_b).all()
    assert not J_a.any() and not J_b.any()


def test_custom_factor_error_and_linearisation():
    rng = np.random.default_rng(3)
    T_a, T_b = random_similarity(rng), random_similarity(rng)
    ka, kb = gtsam.symbol("x", 0), gtsam.symbol("x", 1)
    sigma, distance = 0.2, 1.2
    factor = range_factor(ka, kb, distance, sigma)
    values = gtsam.Values()
    values.insert(ka, T_a)
    values.insert(kb, T_b)
    r, J_a, J_b = range_residual(T_a, T_b, distance)
    assert factor.error(values) == pytest.approx(0.5 * (r[0] / sigma) ** 2, rel=1e-12)
    lin = factor.linearize(values)
    A, b = lin.jacobian()
    np.testing.assert_allclose(A, np.hstack([J_a, J_b]) / sigma, rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(b, -r / sigma, rtol=1e-12)
