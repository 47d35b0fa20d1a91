"""The sequence's odometry anchored to a map's localisations (fgslam/localize/anchor.py): the robust
fit of the map-from-odometry transform, the poses it gives, and when it gives none."""

import numpy as np
import pytest

from fgslam.core.config import check_ranges
from fgslam.core.errors import ConfigError
from fgslam.localize.anchor import OdometryAnchor, OdometryConfig, fit_anchor, rigid_in_map


def _rotation(rng) -> np.ndarray:
    Q, R = np.linalg.qr(rng.normal(size=(3, 3)))
    Q = Q @ np.diag(np.sign(np.diag(R)))
    return Q if np.linalg.det(Q) > 0 else -Q


def _poses(rng, n: int) -> np.ndarray:
    """``n`` rigid camera poses along a wavy path."""
    T = np.tile(np.eye(4), (n, 1, 1))
    for i in range(n):
        T[i, :3, :3] = _rotation(rng)
        T[i, :3, 3] = [np.sin(0.3 * i), 0.1 * i, np.cos(0.2 * i)]
    return T


def _sim3(rng, s: float) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = s * _rotation(rng)
    T[:3, 3] = rng.normal(size=3)
    return T


def _map_poses(T_MV: np.ndarray, T_VC: np.ndarray) -> np.ndarray:
    """The rigid poses ``T_VC`` seen from the map's frame, written out (not by the code under test): a
    point ``X`` of camera C lies at ``s R (R_VC X + t_VC) + t`` in the map, so ``R_MC = R R_VC`` and
    ``t_MC = s R t_VC + t``."""
    s = np.cbrt(np.linalg.det(T_MV[:3, :3]))
    R, t = T_MV[:3, :3] / s, T_MV[:3, 3]
    out = np.tile(np.eye(4), (len(T_VC), 1, 1))
    out[:, :3, :3] = R @ T_VC[:, :3, :3]
    out[:, :3, 3] = s * T_VC[:, :3, 3] @ R.T + t
    return out


@pytest.mark.parametrize("with_scale, s", [(False, 1.0), (True, 2.5)])
def test_the_fit_recovers_the_transform_of_exact_pairs(with_scale, s):
    rng = np.random.default_rng(1)
    T_VC = _poses(rng, 12)
    T_MV = _sim3(rng, s)
    T_MC = _map_poses(T_MV, T_VC)
    np.testing.assert_allclose(fit_anchor(T_VC, T_MC, with_scale, trim=2.0).T_MV, T_MV, atol=1e-9)
    np.testing.assert_allclose(rigid_in_map(T_MV, T_VC), T_MC, atol=1e-12)
    for a in rigid_in_map(T_MV, T_VC):  # rigid poses, whatever the scale of T_MV
        np.testing.assert_allclose(a[:3, :3] @ a[:3, :3].T, np.eye(3), atol=1e-12)


def test_a_rigid_fit_keeps_scale_one_and_a_scaled_fit_finds_it():
    rng = np.random.default_rng(2)
    T_VC = _poses(rng, 10)
    T_MC = _map_poses(_sim3(rng, 3.0), T_VC)
    assert np.cbrt(np.linalg.det(fit_anchor(T_VC, T_MC, False, 2.0).T_MV[:3, :3])) == pytest.approx(1.0)
    assert np.cbrt(np.linalg.det(fit_anchor(T_VC, T_MC, True, 2.0).T_MV[:3, :3])) == pytest.approx(3.0)
    still = np.tile(T_VC[:1], (5, 1, 1))  # an odometry that has not moved determines no scale: 1 is kept
    assert np.cbrt(np.linalg.det(fit_anchor(still, T_MC[:5], True, 2.0).T_MV[:3, :3])) == pytest.approx(1.0)
    mirrored = T_MC.copy()  # positions that a negative scale would fit best: 1 is kept
    mirrored[:, :3, 3] = -(T_MC[:, :3, 3] - T_MC[:, :3, 3].mean(axis=0))
    assert np.cbrt(np.linalg.det(fit_anchor(T_VC, mirrored, True, 2.0).T_MV[:3, :3])) == pytest.approx(1.0)


def test_wrong_localisations_move_the_fit_little():
    """A fifth of the pairs 1 m and a random rotation off (wrong relocalisations), the rest with 1 cm of
    noise: the robust fit stays within centimetres; a plain least-squares fit is several times farther off."""
    rng = np.random.default_rng(3)
    n = 40
    T_VC = _poses(rng, n)
    T_MV = _sim3(rng, 1.0)
    T_MC = _map_poses(T_MV, T_VC)
    T_MC[:, :3, 3] += 0.01 * rng.normal(size=(n, 3))
    bad = rng.choice(n, n // 5, replace=False)
    T_MC[bad, :3, 3] += rng.normal(size=(len(bad), 3)) * (1.0 / np.sqrt(3))
    for i in bad:
        T_MC[i, :3, :3] = _rotation(rng) @ T_MC[i, :3, :3]
    robust = fit_anchor(T_VC, T_MC, False, trim=2.0).T_MV
    plain = fit_anchor(T_VC, T_MC, False, trim=1e9).T_MV  # trims nothing
    err = lambda T: np.abs(_map_poses(T, T_VC)[:, :3, 3] - _map_poses(T_MV, T_VC)[:, :3, 3]).max()  # noqa: E731
    assert err(robust) < 0.03 and err(plain) > 3 * err(robust)


def test_the_anchor_gives_poses_once_it_has_its_pairs_and_within_the_gap():
    rng = np.random.default_rng(4)
    T_VC = _poses(rng, 8)
    T_MV = _sim3(rng, 1.0)
    T_MC = _map_poses(T_MV, T_VC)
    anchor = OdometryAnchor(OdometryConfig(min_pairs=2, max_gap_s=1.5), with_scale=False)
    assert anchor.add(0.0, T_VC[0], None) is None  # nothing anchors the odometry yet
    np.testing.assert_array_equal(anchor.add(1.0, T_VC[1], T_MC[1]), T_MC[1])  # one pair: the localiser's pose
    assert anchor.add(2.0, T_VC[2], None) is None
    np.testing.assert_allclose(anchor.add(3.0, T_VC[3], T_MC[3]), T_MC[3], atol=1e-12)  # two pairs: anchored
    np.testing.assert_allclose(anchor.add(4.0, T_VC[4], None), T_MC[4], atol=1e-12)  # between localisations
    np.testing.assert_allclose(anchor.add(4.5, T_VC[5], None), T_MC[5], atol=1e-12)
    assert anchor.add(4.6, T_VC[6], None) is None  # 1.6 s after the last localised frame: past max_gap_s
    assert anchor.add(5.0, None, None) is None  # no odometry pose, no localisation
    np.testing.assert_array_equal(anchor.add(6.0, None, T_MC[7]), T_MC[7])  # localised without odometry
    assert anchor.pairs == 2


def test_the_window_fits_the_latest_pairs_only():
    """The odometry's frame jumps half-way (a new map): with a window of the latest 3 pairs the fit
    follows it; with all pairs it cannot."""
    rng = np.random.default_rng(5)
    T_VC = _poses(rng, 12)
    first, second = _sim3(rng, 1.0), _sim3(rng, 1.0)
    T_MC = np.concatenate([_map_poses(first, T_VC[:6]), _map_poses(second, T_VC[6:])])
    windowed = OdometryAnchor(OdometryConfig(window=3), with_scale=False)
    whole = OdometryAnchor(OdometryConfig(), with_scale=False)
    for i in range(12):
        windowed.add(float(i), T_VC[i], T_MC[i])
        whole.add(float(i), T_VC[i], T_MC[i])
    np.testing.assert_allclose(windowed.T_MV, second, atol=1e-9)
    assert np.abs(whole.T_MV - second).max() > 0.1


def test_trim_below_one_is_refused_and_a_fit_never_trims_to_nothing():
    with pytest.raises(ConfigError, match="trim"):
        check_ranges(OdometryConfig(trim=0.5))
    rng = np.random.default_rng(6)
    T_VC = _poses(rng, 2)
    T_MC = _map_poses(_sim3(rng, 1.0), T_VC)
    T_MC[:, :3, 3] += 0.01 * rng.normal(size=(2, 3))
    fit = fit_anchor(T_VC, T_MC, False, trim=1.0)  # two pairs: equal residuals, one of them may fall out
    assert np.isfinite(fit.T_MV).all()


def test_a_monocular_scale_waits_for_positions_that_spread():
    """Localised frames a millimetre apart with a centimetre of error determine no scale: no anchored pose
    yet; once the frames spread over a metre they do."""
    rng = np.random.default_rng(7)
    n = 30
    T_VC = _poses(rng, n)
    T_VC[:10, :3, 3] = T_VC[0, :3, 3] + 0.001 * rng.normal(size=(10, 3))
    T_MV = _sim3(rng, 2.0)
    T_MC = _map_poses(T_MV, T_VC)
    T_MC[:, :3, 3] += 0.01 * rng.normal(size=(n, 3))
    anchor = OdometryAnchor(OdometryConfig(), with_scale=True)
    for i in range(10):
        np.testing.assert_array_equal(anchor.add(float(i), T_VC[i], T_MC[i]), T_MC[i])  # the localiser's pose
    assert anchor.T_MV is None and anchor.add(10.5, T_VC[10], None) is None
    for i in range(10, n):
        anchor.add(float(i), T_VC[i], T_MC[i])
    assert anchor.T_MV is not None
    assert np.cbrt(np.linalg.det(anchor.T_MV[:3, :3])) == pytest.approx(2.0, rel=0.02)


def test_a_window_refits_at_every_pair_however_many_came_before():
    """With a window of 3, the fit follows a jump of the odometry's frame within 3 pairs also after 2,000
    pairs (the refit schedule counts the pairs fitted, not all pairs seen)."""
    rng = np.random.default_rng(8)
    n = 2000
    T_VC = _poses(rng, n)
    first, second = _sim3(rng, 1.0), _sim3(rng, 1.0)
    T_MC = np.concatenate([_map_poses(first, T_VC[:n - 10]), _map_poses(second, T_VC[n - 10:])])
    anchor = OdometryAnchor(OdometryConfig(window=3), with_scale=False)
    for i in range(n - 7):
        anchor.add(float(i), T_VC[i], T_MC[i])
    np.testing.assert_allclose(anchor.T_MV, second, atol=1e-9)


def test_a_monocular_anchor_needs_a_fitted_scale():
    """One pair, or pairs whose odometry positions coincide, fit no scale: no anchored pose from them."""
    rng = np.random.default_rng(9)
    T_VC = _poses(rng, 4)
    T_MC = _map_poses(_sim3(rng, 2.0), T_VC)
    single = OdometryAnchor(OdometryConfig(min_pairs=1), with_scale=True)
    np.testing.assert_array_equal(single.add(0.0, T_VC[0], T_MC[0]), T_MC[0])
    assert single.T_MV is None and single.add(1.0, T_VC[1], None) is None
    still = OdometryAnchor(OdometryConfig(min_pairs=2), with_scale=True)
    for i in range(4):
        still.add(float(i), T_VC[0], T_MC[i])  # the odometry has not moved
    assert still.T_MV is None
