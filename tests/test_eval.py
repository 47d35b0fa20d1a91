"""Trajectory evaluation: association, alignment, ATE, RPE, KITTI errors, plots and the eval CLI."""

import json

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from fgslam.core.errors import ConfigError, DataError, EvaluationError
from fgslam.eval.trajectory import (
    EvalConfig,
    associate_timestamps,
    compute_alignment,
    evaluate,
    kitti_relative_errors,
    rotation_angle,
)
from fgslam.core.geometry import umeyama
from fgslam.io.plot import plot_trajectories
from fgslam.io.trajectory import Trajectory, read_trajectory, write_trajectory

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def poses(R_WC, t_WC):
    T = np.tile(np.eye(4), (len(t_WC), 1, 1))
    T[:, :3, :3] = R_WC
    T[:, :3, 3] = t_WC
    return T


def random_walk(rng, n=200, dt=0.1):
    R_WC = Rotation.random(n, random_state=rng).as_matrix()
    t_WC = np.cumsum(rng.normal(scale=0.5, size=(n, 3)), axis=0)
    return Trajectory(dt * np.arange(n), poses(R_WC, t_WC))


def straight_line(n, spacing=1.0):
    """Camera moving along its optical axis z (KITTI camera convention), one pose per frame."""
    t_WC = np.zeros((n, 3))
    t_WC[:, 2] = spacing * np.arange(n)
    return Trajectory(np.arange(n, dtype=float), poses(np.eye(3), t_WC))


def transformed(traj, s, R, t, timestamps=None):
    """Apply X -> s R X + t to the world of ``traj`` (positions scaled, rotations R R_WC)."""
    T = np.array(traj.T_WC)
    T[:, :3, :3] = R @ T[:, :3, :3]
    T[:, :3, 3] = s * traj.t_WC @ R.T + t
    return Trajectory(traj.timestamps if timestamps is None else timestamps, T)


# ---------------------------------------------------------------- alignment


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_umeyama_recovers_known_similarity(seed):
    rng = np.random.default_rng(seed)
    X = rng.normal(size=(30, 3)) * [5.0, 2.0, 1.0]
    R = Rotation.random(random_state=rng).as_matrix()
    s, t = rng.uniform(0.2, 5.0), rng.normal(size=3) * 10
    Y = s * X @ R.T + t
    sim = umeyama(X, Y, with_scale=True)
    np.testing.assert_allclose(sim.R, R, atol=1e-10)
    np.testing.assert_allclose(sim.t, t, atol=1e-9)
    assert sim.s == pytest.approx(s, rel=1e-12)
    rigid = umeyama(X, X @ R.T + t, with_scale=False)
    np.testing.assert_allclose(rigid.R, R, atol=1e-10)
    np.testing.assert_allclose(rigid.t, t, atol=1e-9)
    assert rigid.s == 1.0
    assert np.linalg.det(sim.R) == pytest.approx(1.0)


def test_umeyama_never_returns_a_reflection():
    rng = np.random.default_rng(3)
    X = rng.normal(size=(20, 3))
    Y = X * [1.0, 1.0, -1.0]  # mirror image: best proper rotation, not the reflection
    sim = umeyama(X, Y, with_scale=False)
    assert np.linalg.det(sim.R) == pytest.approx(1.0)


def test_umeyama_degenerate_input():
    with pytest.raises(EvaluationError, match="at least 2"):
        umeyama(np.zeros((1, 3)), np.zeros((1, 3)), with_scale=False)
    with pytest.raises(EvaluationError, match="no spread"):
        umeyama(np.ones((5, 3)), np.zeros((5, 3)), with_scale=True)


@pytest.mark.parametrize("align", ["se3", "sim3", "first-pose"])
def test_evaluate_undoes_a_known_transform(align):
    rng = np.random.default_rng(4)
    gt = random_walk(rng)
    R = Rotation.random(random_state=rng).as_matrix()
    s = 1.0 if align != "sim3" else 0.37
    # the estimate lives in W' with X_W = s R X_W' + t  ->  X_W' = R^T (X_W - t) / s
    est = transformed(gt, 1.0 / s, R.T, -(R.T @ np.array([3.0, -1.0, 2.0])) / s)
    result = evaluate(gt, est, EvalConfig(align=align))
    assert result.ate.rmse < 1e-9
    assert result.alignment.s == pytest.approx(s, rel=1e-10)
    np.testing.assert_allclose(result.alignment.R, R, atol=1e-10)
    np.testing.assert_allclose(result.aligned_est.T_WC, gt.T_WC, atol=1e-9)
    assert result.rpe_frames.rot_deg.max < 1e-6


def test_no_alignment_reports_raw_offset():
    gt = random_walk(np.random.default_rng(5))
    est = transformed(gt, 1.0, np.eye(3), np.array([3.0, 4.0, 0.0]))
    result = evaluate(gt, est, EvalConfig(align="none"))
    assert result.ate.rmse == pytest.approx(5.0)
    assert result.ate.std == pytest.approx(0.0, abs=1e-12)
    assert result.rpe_frames.trans.max < 1e-12  # relative errors ignore a global offset


def test_align_num_poses_uses_only_the_first_poses():
    gt = random_walk(np.random.default_rng(6), n=50)
    est_T = np.array(gt.T_WC)
    est_T[25:, :3, 3] += [10.0, 0.0, 0.0]  # the second half jumps; the first half is perfect
    est = Trajectory(gt.timestamps, est_T)
    alignment = compute_alignment(gt, est, "se3", num_poses=25)
    np.testing.assert_allclose(alignment.matrix(), np.eye(4), atol=1e-10)
    result = evaluate(gt, est, EvalConfig(align="se3", align_num_poses=25))
    assert result.ate.max == pytest.approx(10.0)
    assert result.ate.median == pytest.approx(5.0)  # 25 zeros and 25 tens


# ---------------------------------------------------------------- association


def test_association_nearest_within_max_diff_with_offset():
    t_gt = np.arange(0.0, 10.0, 0.01)  # 100 Hz ground truth
    t_est = np.arange(0.0, 9.0, 1 / 30) + 0.5 + 0.003  # 30 Hz, 0.5 s late + 3 ms jitter
    idx_gt, idx_est = associate_timestamps(t_gt, t_est, max_diff=0.006, offset=-0.5)
    assert idx_est.size == t_est.size
    np.testing.assert_array_less(np.abs(t_gt[idx_gt] - (t_est[idx_est] - 0.5)), 0.006)
    np.testing.assert_array_equal(idx_gt, np.round((t_est - 0.5) / 0.01).astype(int))
    # without the offset nothing beyond 9.5 s - 0.5 s... only the overlap within 6 ms matches
    idx_gt0, idx_est0 = associate_timestamps(t_gt, t_est, max_diff=0.006)
    assert np.all(t_est[idx_est0] < 10.0 + 0.006)


def test_association_is_one_to_one():
    t_gt = np.array([1.0, 2.0, 3.0])
    t_est = np.array([1.9, 1.99, 2.05, 3.5])
    idx_gt, idx_est = associate_timestamps(t_gt, t_est, max_diff=0.2)
    # 1.99 takes gt 2.0 (closest pair); 1.9 and 2.05 may not reuse it; 3.5 is too far.
    np.testing.assert_array_equal(idx_est, [1])
    np.testing.assert_array_equal(idx_gt, [1])
    assert len(set(idx_gt)) == len(idx_gt)


def test_association_second_choice_when_nearest_is_taken():
    t_gt = np.array([1.0, 1.1])
    t_est = np.array([1.02, 1.04])
    idx_gt, idx_est = associate_timestamps(t_gt, t_est, max_diff=0.1)
    # (1.02, 1.0) is the closest pair; 1.04 then takes 1.1 (0.06 <= 0.1)
    np.testing.assert_array_equal(idx_gt, [0, 1])
    np.testing.assert_array_equal(idx_est, [0, 1])


def test_association_never_crosses():
    # (0.9, 1.0) is the closest pair; (1.15, 0.0) is within max_diff but would cross it.
    idx_gt, idx_est = associate_timestamps(np.array([0.0, 1.0]), np.array([0.9, 1.15]), max_diff=1.2)
    np.testing.assert_array_equal(idx_gt, [1])
    np.testing.assert_array_equal(idx_est, [0])
    rng = np.random.default_rng(14)
    t_gt = np.sort(rng.uniform(0, 10, 300))
    t_est = np.sort(rng.uniform(0, 10, 200))
    idx_gt, idx_est = associate_timestamps(t_gt, t_est, max_diff=0.5)
    assert np.all(np.diff(idx_gt) > 0) and np.all(np.diff(idx_est) > 0)
    assert np.all(np.abs(t_gt[idx_gt] - t_est[idx_est]) <= 0.5)


def test_association_boundary_is_inclusive():
    idx_gt, _ = associate_timestamps(np.array([0.0, 1.0]), np.array([0.25]), max_diff=0.25)
    np.testing.assert_array_equal(idx_gt, [0])


def test_no_common_timestamps_is_an_error():
    gt = random_walk(np.random.default_rng(7), n=10)
    est = Trajectory(gt.timestamps + 100.0, gt.T_WC)
    with pytest.raises(EvaluationError, match="no common timestamps"):
        evaluate(gt, est, EvalConfig())
    # ... unless the known offset is given
    assert evaluate(gt, est, EvalConfig(time_offset=-100.0)).n_matched == 10


def test_tum_groundtruth_with_repeated_stamp_associates(shared_data):
    # fr2/desk ground truth repeats one rounded timestamp (line 10863)
    gt = read_trajectory(shared_data / "trajectories" / "fr2_desk_groundtruth.txt", "tum")
    est = gt.subset(np.arange(0, len(gt), 10))  # a 30 Hz-like subsample
    result = evaluate(gt, est, EvalConfig(max_time_diff=0.0))
    assert result.n_matched == len(est)
    assert result.ate.rmse < 1e-12


def test_index_association_refuses_to_truncate():
    gt = random_walk(np.random.default_rng(8), n=10)
    with pytest.raises(EvaluationError, match="10 poses, estimate 9"):
        evaluate(gt, gt.subset(np.arange(9)), EvalConfig(association="index"))


def test_timestamp_association_drops_unmatched_poses():
    gt = random_walk(np.random.default_rng(9), n=100, dt=0.01)
    est = gt.subset(np.arange(0, 100, 3))
    result = evaluate(gt, est, EvalConfig(max_time_diff=0.001))
    assert result.n_matched == 34 and result.n_gt == 100 and result.n_est == 34
    assert result.ate.rmse < 1e-12


def test_empty_trajectory_is_an_error():
    gt = random_walk(np.random.default_rng(15), n=5)
    empty = Trajectory(np.zeros(0), np.zeros((0, 4, 4)))
    with pytest.raises(EvaluationError, match="empty"):
        evaluate(gt, empty, EvalConfig(association="index"))


def test_invalid_config_is_rejected():
    gt = random_walk(np.random.default_rng(10), n=5)
    for bad in (
        EvalConfig(align="scale"),
        EvalConfig(association="nearest"),
        EvalConfig(max_time_diff=-1.0),
        EvalConfig(rpe_delta_frames=0),
        EvalConfig(rpe_delta_meters=0.0),
        EvalConfig(align_num_poses=0),
    ):
        with pytest.raises(ConfigError, match="EvalConfig"):
            evaluate(gt, gt, bad)


# ---------------------------------------------------------------- RPE


def test_rotation_angle_matches_scipy():
    rng = np.random.default_rng(11)
    rotvec = Rotation.random(100, random_state=rng).as_rotvec()
    rotvec[:3] *= [1e-9, 1e-5, 1.0]
    R = Rotation.from_rotvec(rotvec).as_matrix()
    np.testing.assert_allclose(rotation_angle(R), np.linalg.norm(rotvec, axis=1), rtol=1e-7, atol=1e-15)


def test_rpe_per_frame_on_constant_drift():
    """Each estimated step moves 0.02 m too far along the camera's x axis and turns 0.1 deg too much
    about it: every per-frame relative error is exactly that step error."""
    n = 60
    yaw_rate = np.radians(2.0)
    R_gt = Rotation.from_euler("y", yaw_rate * np.arange(n)[:, None]).as_matrix()
    step_gt = np.array([0.0, 0.0, 0.5])  # forward in the camera frame
    drift_t, drift_angle = np.array([0.02, 0.0, 0.0]), np.radians(0.1)
    drift_R = Rotation.from_euler("x", drift_angle).as_matrix()
    step_R = Rotation.from_euler("y", yaw_rate).as_matrix()
    T_gt = [np.eye(4)]
    T_est = [np.eye(4)]
    D_gt = np.eye(4)
    D_gt[:3, :3], D_gt[:3, 3] = step_R, step_gt
    D_err = np.eye(4)
    D_err[:3, :3], D_err[:3, 3] = drift_R, drift_t
    for _ in range(n - 1):
        T_gt.append(T_gt[-1] @ D_gt)
        T_est.append(T_est[-1] @ D_gt @ D_err)
    gt = Trajectory(np.arange(n, dtype=float), np.array(T_gt))
    est = Trajectory(np.arange(n, dtype=float), np.array(T_est))
    np.testing.assert_allclose(gt.R_WC, R_gt, atol=1e-12)
    result = evaluate(gt, est, EvalConfig(align="none", rpe_delta_meters=None))
    rpe = result.rpe_frames
    assert rpe.trans.n == n - 1
    assert rpe.trans.min == pytest.approx(0.02, abs=1e-12) and rpe.trans.max == pytest.approx(0.02, abs=1e-12)
    assert rpe.rot_deg.min == pytest.approx(0.1, abs=1e-9) and rpe.rot_deg.max == pytest.approx(0.1, abs=1e-9)
    assert result.rpe_meters is None
    # with a 2-frame delta the drift compounds: E = (D D)^-1 (D E_d D E_d)
    two = evaluate(gt, est, EvalConfig(align="none", rpe_delta_frames=2, rpe_delta_meters=None)).rpe_frames
    E = np.linalg.inv(D_gt @ D_gt) @ (D_gt @ D_err @ D_gt @ D_err)
    assert two.trans.mean == pytest.approx(np.linalg.norm(E[:3, 3]), abs=1e-12)
    assert two.rot_deg.mean == pytest.approx(np.degrees(Rotation.from_matrix(E[:3, :3]).magnitude()), abs=1e-9)


def test_rpe_per_distance_on_scale_error():
    gt = straight_line(50, spacing=0.5)
    est = transformed(gt, 1.03, np.eye(3), np.zeros(3))
    result = evaluate(gt, est, EvalConfig(align="none", rpe_delta_meters=2.0))
    rpe = result.rpe_meters
    assert rpe.unit == "m" and rpe.delta == 2.0
    assert rpe.trans.n == 50 - 4  # pairs (i, i + 4): 2 m at 0.5 m spacing
    assert rpe.trans.min == pytest.approx(0.06, abs=1e-12) and rpe.trans.max == pytest.approx(0.06, abs=1e-12)
    # Sim(3) alignment removes the scale error completely
    assert evaluate(gt, est, EvalConfig(align="sim3", rpe_delta_meters=2.0)).rpe_meters.trans.max < 1e-12


# ---------------------------------------------------------------- KITTI t_rel / r_rel


def expected_kitti_straight_line(n, per_segment_error):
    """Devkit loop for a 1 m-spaced straight line: segment of length L from frame i ends at
    frame i + L + 1 (first frame strictly beyond L); returns the mean of error(L) / L."""
    errors = []
    for first in range(0, n, 10):
        for length in range(100, 900, 100):
            last = first + length + 1
            if last < n:
                errors.append(per_segment_error(length + 1) / length)
    return float(np.mean(errors)), len(errors)


def test_kitti_t_rel_of_a_constant_scale_error():
    gt = straight_line(1000)
    est = transformed(gt, 1.01, np.eye(3), np.zeros(3))
    errors = kitti_relative_errors(gt.T_WC, est.T_WC)
    expected, count = expected_kitti_straight_line(1000, lambda frames: 0.01 * frames)
    assert errors.n_segments == count
    assert errors.t_rel_percent == pytest.approx(100 * expected, rel=1e-10)
    assert errors.t_rel_percent == pytest.approx(1.0, abs=0.01)  # 1 % scale error = 1 % t_rel
    assert errors.r_rel_deg_per_100m == pytest.approx(0.0, abs=1e-9)


def test_kitti_r_rel_of_a_constant_rotation_drift():
    n, rate = 1000, np.radians(0.002)  # extra roll about the optical axis per frame (= per metre)
    gt = straight_line(n)
    R_est = Rotation.from_euler("z", rate * np.arange(n)[:, None]).as_matrix()
    est = Trajectory(gt.timestamps, poses(R_est, gt.t_WC))
    errors = kitti_relative_errors(gt.T_WC, est.T_WC)
    expected, _ = expected_kitti_straight_line(n, lambda frames: rate * frames)
    assert errors.r_rel_deg_per_100m == pytest.approx(np.degrees(expected) * 100, rel=1e-8)
    assert errors.t_rel_percent == pytest.approx(0.0, abs=1e-9)  # roll about the motion axis: no translation error


def test_kitti_metrics_need_100_m():
    gt = straight_line(100)
    assert kitti_relative_errors(gt.T_WC, gt.T_WC) is None
    assert evaluate(gt, gt, EvalConfig(association="index", kitti_metrics=True)).kitti is None


# ---------------------------------------------------------------- published figures on KITTI 00


@pytest.fixture(scope="module")
def kitti00(shared_data):
    gt = read_trajectory(shared_data / "kitti_gt" / "00.txt", "kitti")
    orb = read_trajectory(shared_data / "trajectories" / "KITTI_00_ORB.txt", "kitti")
    sptam = read_trajectory(shared_data / "trajectories" / "KITTI_00_SPTAM.txt", "kitti")
    return gt, orb, sptam


@pytest.mark.parametrize(
    "which, align, rmse, scale",
    [
        # ../shared/data/README.md (values of the evo tool's result files): translation APE RMSE
        ("orb", "se3", 1.3034, 1.0),
        ("orb", "sim3", 0.9377, 1.0047),
        ("orb", "none", 7.790, 1.0),
        ("sptam", "se3", 3.7385, 1.0),
    ],
)
def test_kitti00_published_ape(kitti00, which, align, rmse, scale):
    gt, orb, sptam = kitti00
    est = orb if which == "orb" else sptam
    result = evaluate(gt, est, EvalConfig(association="index", align=align, rpe_delta_meters=None))
    print(f"KITTI 00 {which} {align}: APE RMSE {result.ate.rmse:.4f} m, scale {result.alignment.s:.4f}")
    assert result.n_matched == 4541
    assert result.ate.rmse == pytest.approx(rmse, abs=1e-3)
    assert result.alignment.s == pytest.approx(scale, abs=1e-3)


def test_kitti00_orb_relative_errors(kitti00):
    gt, orb, _ = kitti00
    result = evaluate(gt, orb, EvalConfig(association="index", kitti_metrics=True, rpe_delta_meters=None))
    kitti = result.kitti
    print(f"KITTI 00 orb: t_rel {kitti.t_rel_percent:.4f} %, r_rel {kitti.r_rel_deg_per_100m:.4f} deg/100m")
    # Consistent with the ORB-SLAM2 paper (Mur-Artal & Tardos 2017, Table II, stereo, KITTI 00):
    # 0.70 % and 0.25 deg/100 m (the paper rounds to 2 decimals).
    assert result.kitti.t_rel_percent == pytest.approx(0.70, abs=0.01)
    assert result.kitti.r_rel_deg_per_100m == pytest.approx(0.25, abs=0.01)


# ---------------------------------------------------------------- plot


def test_plot_writes_a_png(tmp_path):
    import matplotlib.image

    gt = random_walk(np.random.default_rng(12), n=30)
    est = transformed(gt, 1.0, np.eye(3), np.array([0.1, 0.0, 0.0]))
    out = plot_trajectories(tmp_path / "sub" / "traj.png", gt, est, title="test", plane="xy")
    assert out.read_bytes()[:8] == PNG_MAGIC
    image = matplotlib.image.imread(out)
    assert image.ndim == 3 and image.shape[0] > 100 and image.shape[1] > 100
    only_est = plot_trajectories(tmp_path / "est.png", None, est, plane="yz")
    assert only_est.read_bytes()[:8] == PNG_MAGIC
    with pytest.raises(DataError, match="unknown plane"):
        plot_trajectories(tmp_path / "x.png", gt, est, plane="ab")


# ---------------------------------------------------------------- CLI


@pytest.fixture
def run_cli():
    """``fgslam eval ARGV`` through the real dispatcher ``fgslam.cli.main``."""
    from fgslam import cli

    return lambda argv: cli.main(["eval", *argv])


def test_cli_text_and_json_on_kitti00(run_cli, shared_data, tmp_path, capsys):
    gt = str(shared_data / "kitti_gt" / "00.txt")
    est = str(shared_data / "trajectories" / "KITTI_00_ORB.txt")
    png = tmp_path / "plot.png"
    assert run_cli([gt, est, "--format", "kitti", "--plot", str(png)]) == 0
    text = capsys.readouterr().out
    assert "ATE trans [m]          rmse 1.3034" in text and "KITTI t_rel" in text
    assert png.read_bytes()[:8] == PNG_MAGIC
    assert run_cli([gt, est, "--format", "kitti", "--align", "sim3", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["ate"]["rmse"] == pytest.approx(0.9377, abs=1e-3)
    assert out["scale"] == pytest.approx(1.0047, abs=1e-3)
    assert out["config"]["association"] == "index" and out["kitti"]["n_segments"] > 0


def test_cli_tum_vs_euroc_with_overrides(run_cli, tmp_path, capsys):
    gt = random_walk(np.random.default_rng(13), n=40)
    est = Trajectory(gt.timestamps + 0.25, gt.T_WC)
    write_trajectory(tmp_path / "gt.txt", gt, "tum")
    write_trajectory(tmp_path / "est.csv", est, "euroc")
    config = tmp_path / "eval.yaml"
    config.write_text("align: sim3\nmax_time_diff: 0.001\n")
    argv = [str(tmp_path / "gt.txt"), str(tmp_path / "est.csv"), "--format", "tum", "--est-format", "euroc"]
    assert run_cli([*argv, "--config", str(config), "--offset", "-0.25", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["n_matched"] == 40 and out["align"] == "sim3" and out["kitti"] is None
    assert out["ate"]["rmse"] < 1e-6
    assert out["config"]["max_time_diff"] == 0.001


def test_cli_header_names_the_path_length_of_the_matched_ground_truth(run_cli, tmp_path, capsys):
    """The estimate covers the first half of a 20 m straight line: the length printed (9 m between the
    first and the tenth pose) is the ground truth's over the matched poses, and the header says so."""
    gt = straight_line(20)
    write_trajectory(tmp_path / "gt.txt", gt, "tum")
    write_trajectory(tmp_path / "est.txt", gt.subset(np.arange(10)), "tum")
    assert run_cli([str(tmp_path / "gt.txt"), str(tmp_path / "est.txt"), "--format", "tum"]) == 0
    header = capsys.readouterr().out.splitlines()[0]
    assert header == f"ground truth: {tmp_path / 'gt.txt'} (20 poses; path length over the 10 matched poses 9.00 m)"


def test_cli_errors_exit_2(run_cli, tmp_path, capsys):
    gt = straight_line(10)
    write_trajectory(tmp_path / "gt.txt", gt, "kitti")
    write_trajectory(tmp_path / "est.txt", gt.subset(np.arange(8)), "kitti")
    assert run_cli([str(tmp_path / "gt.txt"), str(tmp_path / "est.txt"), "--format", "kitti"]) == 2
    assert "fgslam: error: index association needs trajectories of the same length" in capsys.readouterr().err
    (tmp_path / "bad.txt").write_text("1 2 3\n")
    assert run_cli([str(tmp_path / "bad.txt"), str(tmp_path / "est.txt"), "--format", "tum"]) == 2
    assert f"{tmp_path / 'bad.txt'}:1: expected 8 numbers" in capsys.readouterr().err
    assert run_cli([str(tmp_path / "gt.txt"), str(tmp_path / "est.txt"), "--format", "kitti", "-o", "align=bad"]) == 2
    assert "align" in capsys.readouterr().err


def _tum_pair(tmp_path, n=30):
    """Ground truth and a shifted estimate in TUM format with Unix-time stamps (seconds, 30 Hz)."""
    gt = random_walk(np.random.default_rng(21), n=n, dt=1 / 30)
    gt = Trajectory(1305031102.175304 + gt.timestamps, gt.T_WC)
    write_trajectory(tmp_path / "gt.txt", gt, "tum")
    write_trajectory(tmp_path / "est.txt", transformed(gt, 1.0, np.eye(3), np.array([0.1, 0.0, 0.0])), "tum")
    return str(tmp_path / "gt.txt"), str(tmp_path / "est.txt")


def test_cli_euroc_format_on_tum_files_is_refused(run_cli, tmp_path, capsys):
    gt, est = _tum_pair(tmp_path)
    assert run_cli([gt, est, "--format", "euroc"]) == 2
    err = capsys.readouterr().err
    assert f"fgslam: error: {gt}: the euroc format has nanosecond timestamps" in err and "--format tum" in err
    assert run_cli([gt, est, "--format", "tum"]) == 0


def test_cli_repeated_estimate_timestamp_names_the_line(run_cli, tmp_path, capsys):
    gt, est = _tum_pair(tmp_path)
    lines = (tmp_path / "est.txt").read_text().splitlines()
    stamp = lines[6].split()[0]  # line 7: the 6th pose (line 1 is the header)
    lines[7] = " ".join([stamp, *lines[7].split()[1:]])
    (tmp_path / "est.txt").write_text("\n".join(lines) + "\n")
    assert run_cli([gt, est, "--format", "tum"]) == 2
    assert f"fgslam: error: {est}:8: timestamp {float(stamp):.9f} repeats the one on line 7" in capsys.readouterr().err
    # the same repeat in the ground truth is only warned about (TUM fr2/desk has some)
    assert run_cli([est, gt, "--format", "tum"]) == 0


def test_cli_plot_creates_only_its_own_folder(run_cli, tmp_path, capsys):
    gt, est = _tum_pair(tmp_path)
    deep = tmp_path / "typo" / "plots" / "traj.png"
    assert run_cli([gt, est, "--format", "tum", "--plot", str(deep)]) == 2
    err = capsys.readouterr().err
    assert f"fgslam: error: {deep}: cannot write the plot: folder {tmp_path / 'typo'} does not exist" in err
    assert not (tmp_path / "typo").exists()
    own = tmp_path / "plots" / "traj.png"
    assert run_cli([gt, est, "--format", "tum", "--plot", str(own)]) == 0
    assert own.read_bytes()[:8] == PNG_MAGIC
    assert f"created folder {own.parent} for the plot" in capsys.readouterr().err
    assert run_cli([gt, est, "--format", "tum", "--plot", str(tmp_path / "plots")]) == 2
    assert "is a folder; give the plot's file name" in capsys.readouterr().err


def test_cli_results_are_printed_when_the_plot_fails(run_cli, tmp_path, capsys, monkeypatch):
    import fgslam.io.plot

    def disk_full(path, *args, **kwargs):
        raise DataError(f"{path}: cannot write plot: [Errno 28] No space left on device")

    monkeypatch.setattr(fgslam.io.plot, "plot_trajectories", disk_full)
    gt, est = _tum_pair(tmp_path)
    assert run_cli([gt, est, "--format", "tum", "--plot", str(tmp_path / "p.png")]) == 2
    captured = capsys.readouterr()
    assert "ATE trans [m]" in captured.out and "plot:" not in captured.out
    assert "No space left on device" in captured.err


def test_shipped_config_matches_the_defaults(repo_root):
    from fgslam.core.config import load_config

    assert load_config(EvalConfig, repo_root / "fgslam" / "configs" / "eval.yaml") == EvalConfig()


def test_do_nothing_baseline_of_the_trajectory_tests():
    """tests/eval_support.py: a stationary estimate scores the positions' RMS spread about their centroid
    under SE(3) and Sim(3) alignment, and never beats itself."""
    from eval_support import assert_beats_doing_nothing, do_nothing_ate, stationary

    n = 30
    T = np.tile(np.eye(4), (n, 1, 1))
    T[:, 0, 3], T[:, 2, 3] = np.linspace(0, 3, n), np.sin(np.linspace(0, 3, n))
    gt = Trajectory(np.arange(n) * 0.1, T)
    spread = float(np.sqrt(np.mean(np.sum((T[:, :3, 3] - T[:, :3, 3].mean(0)) ** 2, axis=1))))
    for align in ("se3", "sim3"):
        assert do_nothing_ate(gt, gt.timestamps, align) == pytest.approx(spread, rel=1e-9)
    assert do_nothing_ate(gt, gt.timestamps, "none") == pytest.approx(
        float(np.sqrt(np.mean(np.sum((T[:, :3, 3] - T[0, :3, 3]) ** 2, axis=1)))), rel=1e-9)
    still = stationary(gt, gt.timestamps)
    ate = evaluate(gt, still, EvalConfig(align="se3")).ate.rmse
    with pytest.raises(AssertionError, match="does not beat doing nothing"):
        assert_beats_doing_nothing(ate, gt, gt.timestamps, "se3")
    assert assert_beats_doing_nothing(0.1 * spread, gt, gt.timestamps, "se3") == pytest.approx(spread)
