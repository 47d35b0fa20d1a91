"""Trajectory dataclass, quaternion conventions and the TUM / KITTI / EuRoC readers and writers."""

import re

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from fgslam.core.errors import DataError, FormatError
from fgslam.io.trajectory import (
    Trajectory,
    quaternion_xyzw_to_rotation,
    read_trajectory,
    rotation_to_quaternion_xyzw,
    write_trajectory,
)


def random_trajectory(rng, n=20, t0=1311868163.8697, dt=0.0333):
    R_WC = Rotation.random(n, random_state=rng).as_matrix()
    T_WC = np.tile(np.eye(4), (n, 1, 1))
    T_WC[:, :3, :3] = R_WC
    T_WC[:, :3, 3] = rng.normal(scale=5.0, size=(n, 3))
    timestamps = t0 + dt * np.arange(n) + rng.uniform(0, 0.3 * dt, size=n)
    return Trajectory(timestamps, T_WC)


# ---------------------------------------------------------------- quaternions


def test_quaternion_to_rotation_matches_scipy():
    rng = np.random.default_rng(0)
    q = rng.normal(size=(50, 4))  # not normalised on purpose
    R = quaternion_xyzw_to_rotation(q)
    np.testing.assert_allclose(R, Rotation.from_quat(q).as_matrix(), atol=1e-12)


def test_quaternion_sign_and_scale_do_not_matter():
    rng = np.random.default_rng(1)
    q = rng.normal(size=(10, 4))
    R = quaternion_xyzw_to_rotation(q)
    np.testing.assert_allclose(quaternion_xyzw_to_rotation(-q), R, atol=1e-14)
    np.testing.assert_allclose(quaternion_xyzw_to_rotation(3.7 * q), R, atol=1e-14)


def test_quaternion_is_hamilton_camera_to_world():
    # 90 deg about z: x axis of the camera maps to the world y axis.
    q = np.array([0.0, 0.0, np.sin(np.pi / 4), np.cos(np.pi / 4)])
    R = quaternion_xyzw_to_rotation(q)
    np.testing.assert_allclose(R @ np.array([1.0, 0.0, 0.0]), [0.0, 1.0, 0.0], atol=1e-15)


def test_rotation_to_quaternion_round_trip_and_positive_w():
    rng = np.random.default_rng(2)
    R = Rotation.random(200, random_state=rng).as_matrix()
    q = rotation_to_quaternion_xyzw(R)
    assert np.all(q[:, 3] >= 0)
    np.testing.assert_allclose(np.linalg.norm(q, axis=1), 1.0, atol=1e-15)
    np.testing.assert_allclose(quaternion_xyzw_to_rotation(q), R, atol=1e-14)
    q_ref = Rotation.from_matrix(R).as_quat()
    q_ref[q_ref[:, 3] < 0] *= -1
    np.testing.assert_allclose(q, q_ref, atol=1e-12)


@pytest.mark.parametrize("axis", [0, 1, 2])
def test_rotation_to_quaternion_near_pi_uses_stable_branch(axis):
    rotvec = np.zeros(3)
    rotvec[axis] = np.pi - 1e-9
    R = Rotation.from_rotvec(rotvec).as_matrix()
    q = rotation_to_quaternion_xyzw(R)
    np.testing.assert_allclose(quaternion_xyzw_to_rotation(q), R, atol=1e-14)
    assert abs(q[axis]) == pytest.approx(1.0, abs=1e-9)


def test_rotation_to_quaternion_keeps_batch_shape():
    R = np.tile(np.eye(3), (2, 3, 1, 1))
    q = rotation_to_quaternion_xyzw(R)
    assert q.shape == (2, 3, 4)
    np.testing.assert_array_equal(q[..., 3], 1.0)


def test_zero_quaternion_is_rejected():
    with pytest.raises(DataError):
        quaternion_xyzw_to_rotation(np.zeros(4))


# ---------------------------------------------------------------- Trajectory validation


def test_trajectory_is_validated_and_read_only():
    traj = random_trajectory(np.random.default_rng(3), n=5)
    assert len(traj) == 5 and traj.t_WC.shape == (5, 3) and traj.R_WC.shape == (5, 3, 3)
    with pytest.raises(ValueError):
        traj.T_WC[0, 0, 3] = 1.0
    T = traj.T_WC.copy()
    with pytest.raises(DataError, match="shape"):
        Trajectory(traj.timestamps[:4], T)
    with pytest.raises(DataError, match="shape"):
        Trajectory(traj.timestamps, T[:, :3, :])
    bad = T.copy()
    bad[2, 0, 3] = np.nan
    with pytest.raises(DataError, match="non-finite pose at index 2"):
        Trajectory(traj.timestamps, bad)
    bad = T.copy()
    bad[1, :3, :3] *= 1.01
    with pytest.raises(DataError, match="pose 1 .*not a rotation"):
        Trajectory(traj.timestamps, bad)
    bad = T.copy()
    bad[3, :3, 0] *= -1  # reflection: orthonormal but det -1
    with pytest.raises(DataError, match="pose 3"):
        Trajectory(traj.timestamps, bad)
    with pytest.raises(DataError, match="sorted"):
        Trajectory(traj.timestamps[::-1], T)
    repeated = traj.timestamps.copy()
    repeated[2] = repeated[1]
    assert len(Trajectory(repeated, T)) == 5  # real TUM ground truth repeats rounded stamps


def test_path_length_and_subset():
    T = np.tile(np.eye(4), (4, 1, 1))
    T[:, :3, 3] = [[0, 0, 0], [3, 4, 0], [3, 4, 1], [3, 4, 3]]
    traj = Trajectory(np.arange(4.0), T)
    assert traj.path_length() == pytest.approx(8.0)
    sub = traj.subset(np.array([0, 2]))
    np.testing.assert_array_equal(sub.timestamps, [0.0, 2.0])


# ---------------------------------------------------------------- round trips


@pytest.mark.parametrize("fmt", ["tum", "euroc", "kitti"])
def test_write_read_round_trip(tmp_path, fmt):
    traj = random_trajectory(np.random.default_rng(4))
    path = tmp_path / f"traj.{fmt}"
    times = tmp_path / "times.txt" if fmt == "kitti" else None
    write_trajectory(path, traj, fmt, times_path=times)
    back = read_trajectory(path, fmt, times_path=times)
    np.testing.assert_allclose(back.T_WC, traj.T_WC, atol=1e-14)
    # EuRoC stores integer nanoseconds; float64 seconds near 1.3e9 resolve ~0.24 us.
    time_tol = 1e-6 if fmt == "euroc" else 0.0
    np.testing.assert_allclose(back.timestamps, traj.timestamps, rtol=0, atol=time_tol)


def test_written_quaternions_have_positive_w(tmp_path):
    traj = random_trajectory(np.random.default_rng(5), n=50)
    write_trajectory(tmp_path / "t.txt", traj, "tum")
    values = np.loadtxt(tmp_path / "t.txt")
    assert np.all(values[:, 7] >= 0)
    np.testing.assert_allclose(np.linalg.norm(values[:, 4:8], axis=1), 1.0, atol=1e-15)


def test_kitti_without_times_uses_frame_index(tmp_path):
    traj = random_trajectory(np.random.default_rng(6), n=7)
    write_trajectory(tmp_path / "k.txt", traj, "kitti")
    back = read_trajectory(tmp_path / "k.txt", "kitti")
    np.testing.assert_array_equal(back.timestamps, np.arange(7.0))


# ---------------------------------------------------------------- reading conventions


def test_tum_reader_skips_comments_and_normalises(tmp_path):
    path = tmp_path / "gt.txt"
    q = np.array([0.1, -0.2, 0.3, 0.9])
    path.write_text(
        "# ground truth\n\n"
        f"1.0 1 2 3 {q[0]} {q[1]} {q[2]} {q[3]}\n"
        "   \n"
        f"2.5 4 5 6 {-2 * q[0]} {-2 * q[1]} {-2 * q[2]} {-2 * q[3]}\n"
    )
    traj = read_trajectory(path, "tum")
    np.testing.assert_array_equal(traj.timestamps, [1.0, 2.5])
    np.testing.assert_array_equal(traj.t_WC, [[1, 2, 3], [4, 5, 6]])
    R = Rotation.from_quat(q).as_matrix()
    np.testing.assert_allclose(traj.R_WC[0], R, atol=1e-15)
    np.testing.assert_allclose(traj.R_WC[1], R, atol=1e-15)


def test_euroc_simple_csv_orders_quaternion_w_first(tmp_path):
    path = tmp_path / "est.csv"
    q_xyzw = np.array([0.1, -0.2, 0.3, 0.9])
    path.write_text(
        "#timestamp,tx,ty,tz,qw,qx,qy,qz\n"
        f"1403715524907143168,1,2,3,{q_xyzw[3]},{q_xyzw[0]},{q_xyzw[1]},{q_xyzw[2]}\n"
        "1403715524912143104,1,2,3,1,0,0,0\n"
    )
    traj = read_trajectory(path, "euroc")
    np.testing.assert_allclose(traj.R_WC[0], Rotation.from_quat(q_xyzw).as_matrix(), atol=1e-15)
    # float64 seconds near 1.4e9 resolve ~2.4e-7 s
    np.testing.assert_allclose(np.diff(traj.timestamps), [0.004999936], rtol=0, atol=5e-7)
    assert traj.timestamps[0] == pytest.approx(1403715524.907143168, abs=1e-6)


def test_euroc_groundtruth_state_csv(shared_data):
    path = shared_data / "trajectories" / "V102_groundtruth.csv"
    traj = read_trajectory(path, "euroc")
    first = path.read_text().splitlines()[1].split(",")
    assert len(traj) == sum(1 for line in path.read_text().splitlines() if line and not line.startswith("#"))
    assert traj.timestamps[0] == pytest.approx(int(first[0]) * 1e-9, abs=1e-6)
    np.testing.assert_allclose(traj.t_WC[0], [float(v) for v in first[1:4]], atol=0)
    qw, qx, qy, qz = (float(v) for v in first[4:8])
    np.testing.assert_allclose(traj.R_WC[0], Rotation.from_quat([qx, qy, qz, qw]).as_matrix(), atol=1e-12)


def test_euroc_whitespace_file_with_fractional_ns(shared_data):
    # groundtruth.txt writes "1403715274312143104.0000000000 x y z qw qx qy qz"
    traj = read_trajectory(shared_data / "euroc_v101_micro" / "groundtruth.txt", "euroc")
    assert traj.timestamps[0] == pytest.approx(1403715274.312143104, abs=1e-6)
    assert np.all(np.diff(traj.timestamps) > 0.04)


def test_tum_shared_groundtruth(shared_data):
    path = shared_data / "trajectories" / "freiburg1_xyz-groundtruth.txt"
    traj = read_trajectory(path, "tum")
    data = np.loadtxt(path)
    assert len(traj) == data.shape[0]
    np.testing.assert_array_equal(traj.timestamps, data[:, 0])
    np.testing.assert_allclose(traj.R_WC, Rotation.from_quat(data[:, 4:8]).as_matrix(), atol=1e-12)


def test_kitti_shared_groundtruth_with_times(shared_data):
    traj = read_trajectory(shared_data / "kitti_gt" / "00.txt", "kitti", shared_data / "kitti_gt" / "00_times.txt")
    assert len(traj) == 4541
    assert traj.timestamps[1] == pytest.approx(0.1037359)
    np.testing.assert_allclose(traj.t_WC[1], [-4.690294e-02, -2.839928e-02, 8.586941e-01])


# ---------------------------------------------------------------- malformed input


@pytest.mark.parametrize(
    "fmt, content, line, pattern",
    [
        ("tum", "# c\n1 0 0 0 0 0 0 1\n2 0 0 0 0 0 1\n", 3, "expected 8 numbers"),
        ("tum", "1 0 0 0 0 0 0 1\n2 0 0 x 0 0 0 1\n", 2, "not a number"),
        ("tum", "1 0 0 0 0 0 0 1\n2 0 0 nan 0 0 0 1\n", 2, "non-finite"),
        ("tum", "1 0 0 0 0 0 0 1\n2 0 0 0 0 0 0 0\n", 2, "zero norm"),
        ("tum", "2 0 0 0 0 0 0 1\n\n1 0 0 0 0 0 0 1\n", 3, "must be sorted"),
        ("kitti", "1 0 0 0 0 1 0 0 0 0 1 0\n1 0 0 0 0 1 0 0 0 0 1\n", 2, "expected 12 numbers"),
        ("kitti", "1 0 0 0 0 1 0 0 0 0 1 0\n2 0 0 0 0 1 0 0 0 0 1 0\n", 2, "not a rotation"),
        ("euroc", "#timestamp\n100,0,0,0,1,0,0\n", 2, "at least 8 numbers"),
        ("euroc", "100,0,0,0,1,0,0,0\n90,0,0,0,1,0,0,0\n", 2, "must be sorted"),
    ],
)
def test_malformed_line_names_file_and_line(tmp_path, fmt, content, line, pattern):
    path = tmp_path / "bad.txt"
    path.write_text(content)
    with pytest.raises(FormatError, match=pattern) as info:
        read_trajectory(path, fmt)
    assert f"{path}:{line}:" in str(info.value)


def test_other_read_errors(tmp_path):
    empty = tmp_path / "empty.txt"
    empty.write_text("# nothing\n\n")
    with pytest.raises(FormatError, match="no poses"):
        read_trajectory(empty, "tum")
    with pytest.raises(FormatError, match="unknown trajectory format"):
        read_trajectory(empty, "bag")
    with pytest.raises(DataError, match="cannot read"):
        read_trajectory(tmp_path / "missing.txt", "tum")
    poses = tmp_path / "k.txt"
    poses.write_text("1 0 0 0 0 1 0 0 0 0 1 0\n1 0 0 1 0 1 0 0 0 0 1 0\n")
    times = tmp_path / "times.txt"
    times.write_text("0.0\n")
    with pytest.raises(FormatError, match="1 timestamps but .* 2 poses"):
        read_trajectory(poses, "kitti", times)
    times.write_text("0.0\nabc\n")
    with pytest.raises(FormatError, match=f"{times}:2: not a number"):
        read_trajectory(poses, "kitti", times)
    with pytest.raises(FormatError, match="only used with the kitti format"):
        read_trajectory(poses, "tum", times)


# ---------------------------------------------------------------- repeated stamps and time units


def test_repeated_timestamp_is_an_error_only_for_estimates(tmp_path, caplog):
    path = tmp_path / "est.txt"
    path.write_text("# t x y z qx qy qz qw\n1.0 0 0 0 0 0 0 1\n1.5 1 0 0 0 0 0 1\n\n1.5 2 0 0 0 0 0 1\n2.0 3 0 0 0 0 0 1\n")
    with pytest.raises(FormatError, match=re.escape(f"{path}:5: timestamp 1.500000000 repeats the one on line 3")):
        read_trajectory(path, "tum", unique_timestamps=True)
    assert len(read_trajectory(path, "tum")) == 4  # ground truth may repeat a rounded stamp (warned)
    assert "1 repeated timestamp(s), first at line 5" in caplog.text
    poses = tmp_path / "k.txt"
    poses.write_text("1 0 0 0 0 1 0 0 0 0 1 0\n1 0 0 1 0 1 0 0 0 0 1 0\n")
    times = tmp_path / "times.txt"
    times.write_text("0.5\n0.5\n")
    with pytest.raises(FormatError, match=re.escape(f"{times}:2: timestamp 0.500000000 repeats the one on line 1")):
        read_trajectory(poses, "kitti", times, unique_timestamps=True)


def test_tum_file_read_as_euroc_is_refused(tmp_path):
    traj = random_trajectory(np.random.default_rng(5))  # stamps ~1.3e9 s, 30 Hz
    path = tmp_path / "traj.txt"
    write_trajectory(path, traj, "tum")
    with pytest.raises(FormatError, match=re.escape(f"{path}: the euroc format has nanosecond timestamps") +
                       r".*look like seconds.*probably in the tum format"):
        read_trajectory(path, "euroc")
    # stamps starting near 0 (seconds since the start) are refused as well
    write_trajectory(path, Trajectory(traj.timestamps - traj.timestamps[0], traj.T_WC), "tum")
    with pytest.raises(FormatError, match="look like seconds"):
        read_trajectory(path, "euroc")
    # a real EuRoC file at 1 kHz is fine
    write_trajectory(path, Trajectory(1.4e9 + 0.001 * np.arange(len(traj)), traj.T_WC), "euroc")
    assert len(read_trajectory(path, "euroc")) == len(traj)


def test_nanosecond_stamps_read_as_seconds_are_refused(tmp_path):
    path = tmp_path / "traj.txt"
    path.write_text("1403636579763555584 0 0 0 0 0 0 1\n1403636579813555456 1 0 0 0 0 0 1\n")
    with pytest.raises(FormatError, match=re.escape(f"{path}:1: timestamp 1.40364e+18 is not plausible in seconds") +
                       r".*--format euroc"):
        read_trajectory(path, "tum")
    poses = tmp_path / "k.txt"
    poses.write_text("1 0 0 0 0 1 0 0 0 0 1 0\n1 0 0 1 0 1 0 0 0 0 1 0\n")
    times = tmp_path / "times.txt"
    times.write_text("1403636579763\n1403636579813\n")  # milliseconds
    with pytest.raises(FormatError, match=re.escape(f"{times}:1: timestamp 1.40364e+12 is not plausible in seconds")):
        read_trajectory(poses, "kitti", times)
