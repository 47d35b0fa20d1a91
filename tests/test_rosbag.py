"""ROS 1 / ROS 2 bags as datasets (fgslam.io.datasets.rosbag) and trajectories exported to bags
(fgslam.export.bag). Skipped without the optional rosbags package (``pip install 'fgslam[bag]'``)."""

from __future__ import annotations

import json
import logging
import pickle
import sys

import numpy as np
import pytest

pytest.importorskip("rosbags", reason="rosbags is an optional extra (pip install 'fgslam[bag]')")

from tool_support import load_tool  # noqa: E402

from fgslam.cli import main  # noqa: E402
from fgslam.core.errors import DataError  # noqa: E402
from fgslam.io.datasets import DatasetConfig, detect_format, open_dataset  # noqa: E402
from fgslam.io.datasets.common import BagTopicsConfig  # noqa: E402
from fgslam.io.datasets.ros_messages import calibration_from_camera_info  # noqa: E402

_clips = load_tool("bench_rosbag")  # the clip-to-bag writers shared with the benchmark
write_7scenes_bag, write_euroc_bag, write_small_bag = _clips.write_7scenes_bag, _clips.write_euroc_bag, _clips.write_small_bag
TRAJECTORY_FILES = ("trajectory_tum.txt", "trajectory_kitti.txt", "trajectory_kitti_times.txt")
EUROC_END = 40  # frames of the EuRoC clip run (of 95): keeps the three runs fast
SEVEN_SCENES_END = 40


def _run(data, out, preset, *overrides):
    args = ["-q", "run", preset, "--data", str(data), "--out", str(out), "--no-progress"]
    for o in overrides:
        args += ["-o", o]
    assert main(args) == 0
    return {name: (out / name).read_bytes() for name in TRAJECTORY_FILES}


# ------------------------------------------------------------------------------- round trips on real clips
@pytest.mark.shared_data
def test_euroc_clip_from_ros1_and_ros2_bags_gives_byte_identical_trajectories(shared_data, tmp_path):
    root = shared_data / "euroc_v101_micro"
    ros1, ros2 = tmp_path / "euroc.bag", tmp_path / "euroc_mcap"
    T_BC = write_euroc_bag(root, ros1, end=EUROC_END)["T_BC"]
    write_euroc_bag(root, ros2, storage="mcap", end=EUROC_END)
    assert detect_format(ros1) == detect_format(ros2) == "rosbag"
    overrides = (f"dataset.end={EUROC_END}", "dataset.T_BC=" + json.dumps(T_BC.reshape(-1).tolist()))
    folder = _run(root, tmp_path / "folder", "patch_euroc_stereo", *overrides)
    assert len(folder["trajectory_tum.txt"].splitlines()) >= EUROC_END // 2
    assert _run(ros1, tmp_path / "ros1", "patch_euroc_stereo", *overrides) == folder
    assert _run(ros2, tmp_path / "ros2", "patch_euroc_stereo", *overrides) == folder
    ds = open_dataset(ros1, config=DatasetConfig(T_BC=T_BC.reshape(-1).tolist()))
    assert ds.has_stereo and ds.has_imu and np.array_equal(ds.raw_calibration.T_BC, T_BC)


@pytest.mark.shared_data
def test_7scenes_clip_from_ros1_and_ros2_bags_gives_identical_poses(shared_data, tmp_path):
    """CompressedImage JPEG + 16UC1 depth. The folder's frame times are i / 30 s, a bag's integer
    nanoseconds: the pose files are byte-identical, the stamps agree to the nanosecond."""
    root = shared_data / "7scenes_redkitchen_0-599"
    ros1, ros2 = tmp_path / "7s.bag", tmp_path / "7s_sqlite"
    write_7scenes_bag(root, ros1, end=SEVEN_SCENES_END)
    write_7scenes_bag(root, ros2, storage="sqlite3", end=SEVEN_SCENES_END)
    folder = _run(root, tmp_path / "folder", "patch_7scenes_rgbd", f"dataset.end={SEVEN_SCENES_END}")
    for bag in (ros1, ros2):
        got = _run(bag, tmp_path / f"out_{bag.name}", "patch_7scenes_rgbd")
        assert got["trajectory_kitti.txt"] == folder["trajectory_kitti.txt"]
        rows_bag = [ln.split() for ln in got["trajectory_tum.txt"].decode().splitlines() if not ln.startswith("#")]
        rows_folder = [ln.split() for ln in folder["trajectory_tum.txt"].decode().splitlines() if not ln.startswith("#")]
        assert len(rows_bag) == len(rows_folder) >= SEVEN_SCENES_END // 2
        assert [r[1:] for r in rows_bag] == [r[1:] for r in rows_folder]
        assert max(abs(float(a[0]) - float(b[0])) for a, b in zip(rows_bag, rows_folder)) <= 1e-9


@pytest.mark.shared_data
def test_info_on_a_bag_lists_topics_with_counts_and_rates(shared_data, tmp_path, capsys):
    bag = tmp_path / "7s.bag"
    write_7scenes_bag(shared_data / "7scenes_redkitchen_0-599", bag, end=10)
    assert main(["info", str(bag), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    rows = {r["topic"]: r for r in info["topics"]}
    assert info["format"] == "rosbag" and info["frames"] == 10 and info["depth"] and info["ros_version"] == 1
    assert rows["/camera/color/image_raw/compressed"] == {
        "topic": "/camera/color/image_raw/compressed", "type": "sensor_msgs/msg/CompressedImage", "kind": "image",
        "role": "left", "messages": 10, "rate_hz": 30.0}
    assert rows["/camera/depth/image_raw"]["kind"] == "depth" and rows["/camera/depth/image_raw"]["role"] == "depth"
    assert rows["/camera/color/camera_info"]["kind"] == "camera_info"
    assert rows["/camera/color/camera_info"]["messages"] == 10 and rows["/camera/color/camera_info"]["rate_hz"] == 30.0
    assert main(["info", str(bag)]) == 0
    assert "topic:        /camera/depth/image_raw  depth, 10 messages, 30.000 Hz  (used as depth)" in capsys.readouterr().out


# ------------------------------------------------------------------------------- decoding and laziness
@pytest.mark.parametrize("ros", ["ros1", "ros2"])
def test_encodings_decode_to_the_same_pixels(tmp_path, ros):
    images = {"/mono/image": "mono8", "/bgr/image": "bgr8", "/rgb/image": "rgb8", "/png/image/compressed": "compressed-png"}
    bag = tmp_path / ("b.bag" if ros == "ros1" else "b")
    base = write_small_bag(bag, {**images, "/d16/depth": "16UC1"}, {"/mono/camera_info": (64, 48),
                           "/bgr/camera_info": (64, 48), "/rgb/camera_info": (64, 48), "/png/camera_info": (64, 48)},
                           imu="/imu")
    frames = {}
    for topic in images:
        ds = open_dataset(bag, config=DatasetConfig(crop_multiple=1, topics=BagTopicsConfig(left=topic)))
        assert ds.has_depth and ds.has_imu and len(ds) == 6
        frames[topic] = list(ds)
        assert np.array_equal(frames[topic][2].image, np.roll(base, 2, axis=1)), topic
        assert np.allclose(frames[topic][2].depth, (np.roll(base, 2, axis=1).astype(np.float64) * 10 + 500) / 1000.0)
        assert frames[topic][0].imu is not None and len(frames[topic][1].imu) == 20  # 200 Hz IMU, 10 Hz frames
    assert np.array_equal(frames["/rgb/image"][3].rgb, frames["/bgr/image"][3].rgb)
    ds32 = open_dataset(write_and(tmp_path / "f32.bag", {"/cam/image": "mono8", "/cam/depth": "32FC1"}),
                        config=DatasetConfig(crop_multiple=1))
    assert np.allclose(ds32[1].depth, np.roll(base, 1, axis=1).astype(np.float32) / 100 + 0.5)


def write_and(path, images):
    write_small_bag(path, images, {"/cam/camera_info": (64, 48)})
    return path


def test_frames_are_read_lazily_in_any_order(tmp_path):
    bag = write_and(tmp_path / "lazy.bag", {"/cam/image": "mono8"})
    ds = open_dataset(bag, config=DatasetConfig(crop_multiple=1))
    seq = [f.image for f in ds]
    for i in (4, 1, 2, 5, 0, 0, 3):  # backward jumps restart the cursor, forward ones skip
        assert np.array_equal(ds[i].image, seq[i])
    assert ds.timestamps[1] - ds.timestamps[0] == pytest.approx(0.1)
    copy = pickle.loads(pickle.dumps(ds))  # the reader is opened again
    assert np.array_equal(copy[3].image, seq[3]) and np.array_equal(ds[3].image, seq[3])


def test_stereo_pair_from_two_camera_infos(tmp_path):
    """Rectified camera_infos (ROS convention P_right[0, 3] = -fx * baseline) give the pair; the
    automatic roles put the ``right`` topic on the right; camera_infos without a baseline are an error."""
    from fgslam.export.bag import BagWriter
    from fgslam.io.calibration import Calibration

    cal = Calibration(64, 48, [50.0, 50.0, 31.5, 23.5])
    baseline = 0.12
    P_left = np.hstack([cal.K_matrix(), np.zeros((3, 1))])
    P_right = P_left.copy()
    P_right[0, 3] = -50.0 * baseline
    bag = tmp_path / "stereo.bag"
    rng = np.random.default_rng(1)
    with BagWriter(bag) as w:
        for i in range(5):
            ts = 10**9 + i * 10**8
            for side, P in (("left", P_left), ("right", P_right)):
                img = rng.integers(0, 255, (48, 64), dtype=np.uint8)
                w.write(f"/{side}/image_raw", "sensor_msgs/msg/Image", ts, _clips.image_msg(w, ts, side, img, "mono8"))
                w.write(f"/{side}/camera_info", "sensor_msgs/msg/CameraInfo", ts,
                        _clips.camera_info(w, ts, side, cal, np.eye(3), P))
    ds = open_dataset(bag, config=DatasetConfig(crop_multiple=1))
    assert ds.roles == {"left": "/left/image_raw", "right": "/right/image_raw"} and ds.has_stereo
    assert ds.calibration.baseline == pytest.approx(baseline, abs=1e-12)
    np.testing.assert_allclose(ds.raw_calibration.T_CLCR[:3, 3], [baseline, 0, 0], atol=1e-12)
    assert ds[2].image_right is not None and ds[2].image_right.shape == (48, 64)
    flat = tmp_path / "flat.bag"
    write_small_bag(flat, {"/left/image_raw": "mono8", "/right/image_raw": "mono8"},
                    {"/left/camera_info": (64, 48), "/right/camera_info": (64, 48)})
    with pytest.raises(DataError, match="/right/camera_info: CameraInfo P has no baseline"):
        open_dataset(flat)
    assert not open_dataset(flat, config=DatasetConfig(load_right=False, crop_multiple=1)).has_stereo


def test_camera_info_distortion_models():
    from types import SimpleNamespace as NS

    def info(model, D):
        return NS(distortion_model=model, D=D, K=[400, 0, 320, 0, 401, 240, 0, 0, 1], width=640, height=480)

    c = calibration_from_camera_info(info("plumb_bob", [0.1, -0.2, 0.001, 0.002, 0.0]), "/c")
    assert c.distortion_model == "radtan" and c.distortion.tolist() == [0.1, -0.2, 0.001, 0.002]
    assert c.K.tolist() == [400, 401, 320, 240]
    c = calibration_from_camera_info(info("plumb_bob", [0.1, -0.2, 0.001, 0.002, 0.05]), "/c")
    assert c.distortion.size == 5
    c = calibration_from_camera_info(info("rational_polynomial", [0.1, -0.2, 0.001, 0.002, 0.05, 0, 0, 0]), "/c")
    assert c.distortion_model == "radtan" and c.distortion.size == 5
    with pytest.raises(DataError, match="/c: rational_polynomial with non-zero k4"):
        calibration_from_camera_info(info("rational_polynomial", [0.1, -0.2, 0, 0, 0, 0.3, 0, 0]), "/c")
    c = calibration_from_camera_info(info("equidistant", [0.01, 0.02, 0.003, 0.004]), "/c")
    assert c.distortion_model == "equidistant" and c.distortion.size == 4
    assert calibration_from_camera_info(info("plumb_bob", [0.0] * 5), "/c").distortion_model == "none"
    with pytest.raises(DataError, match="/c: CameraInfo distortion_model 'weird'"):
        calibration_from_camera_info(info("weird", [0.1]), "/c")


def test_calibration_yaml_when_the_bag_has_no_camera_info(tmp_path):
    bag = tmp_path / "nocal.bag"
    write_small_bag(bag, {"/cam/image": "mono8"})
    with pytest.raises(DataError, match="no CameraInfo topic for /cam/image.*dataset.calibration_file"):
        open_dataset(bag)
    yaml = tmp_path / "cal.yaml"
    yaml.write_text("width: 64\nheight: 48\nintrinsics: [60.0, 60.0, 31.5, 23.5]\n")
    ds = open_dataset(bag, config=DatasetConfig(calibration_file=str(yaml), crop_multiple=1))
    assert ds.raw_calibration.K.tolist() == [60.0, 60.0, 31.5, 23.5] and ds.calibration_source == str(yaml)


# ------------------------------------------------------------------------------- bad input
def test_bag_without_image_topics(tmp_path):
    bag = tmp_path / "imu_only.bag"
    write_small_bag(bag, {}, imu="/imu")
    with pytest.raises(DataError, match=r"no image topics .* topics: /imu \(sensor_msgs/msg/Imu\)"):
        open_dataset(bag)


def test_two_candidates_for_one_role_need_a_choice(tmp_path):
    bag = tmp_path / "two.bag"
    write_small_bag(bag, {"/a/image": "mono8", "/b/image": "mono8"}, {"/a/camera_info": (64, 48), "/b/camera_info": (64, 48)})
    with pytest.raises(DataError, match="2 candidate topics for the left images \\(/a/image, /b/image\\); choose one "
                                        "with dataset.topics.left"):
        open_dataset(bag)
    assert len(open_dataset(bag, config=DatasetConfig(topics=BagTopicsConfig(left="/b/image"), crop_multiple=1))) == 6
    with pytest.raises(DataError, match="dataset.topics.left=/c/image is not a topic of the bag"):
        open_dataset(bag, config=DatasetConfig(topics=BagTopicsConfig(left="/c/image")))


def test_image_size_disagreeing_with_camera_info(tmp_path):
    bag = tmp_path / "size.bag"
    write_small_bag(bag, {"/cam/image": "mono8"}, {"/cam/camera_info": (80, 48)})
    with pytest.raises(DataError, match="images of topic /cam/image are 64x48 but the calibration .*camera_info.* is "
                                        "for 80x48"):
        open_dataset(bag)


def test_a_frame_of_another_size_is_skipped_naming_the_topic(tmp_path, caplog):
    from fgslam.export.bag import BagWriter
    from fgslam.io.calibration import Calibration

    bag = tmp_path / "resized.bag"
    cal = Calibration(64, 48, [50.0, 50.0, 31.5, 23.5])
    with BagWriter(bag) as w:
        for i in range(12):
            ts = 10**9 + i * 10**8
            img = np.full((40, 64) if i == 7 else (48, 64), 100 + i, np.uint8)
            w.write("/cam/image", "sensor_msgs/msg/Image", ts, _clips.image_msg(w, ts, "cam", img, "mono8"))
            w.write("/cam/camera_info", "sensor_msgs/msg/CameraInfo", ts, _clips.camera_info(w, ts, "cam", cal))
    ds = open_dataset(bag, config=DatasetConfig(crop_multiple=1))
    with caplog.at_level(logging.WARNING):
        assert len(list(ds)) == 11
    assert ds.skipped_frames == [(7, "/cam/image: message 7 is 64x40, expected 64x48 (the calibration's size, "
                                     f"{bag} topic /cam/camera_info)")]


def test_unknown_encoding(tmp_path):
    bag = tmp_path / "enc.bag"
    write_small_bag(bag, {"/cam/image": "yuv422"}, {"/cam/camera_info": (64, 48)})
    with pytest.raises(DataError, match="/cam/image: unknown image encoding 'yuv422'"):
        open_dataset(bag)


@pytest.mark.parametrize("name", ["cut.bag", "cut_mcap"])
def test_truncated_bag(tmp_path, name):
    bag = tmp_path / name
    write_small_bag(bag, {"/cam/image": "mono8"}, {"/cam/camera_info": (64, 48)}, frames=20, storage="mcap")
    data_file = bag if bag.is_file() else next(bag.glob("*.mcap"))
    data = data_file.read_bytes()
    data_file.write_bytes(data[: len(data) // 2])
    with pytest.raises(DataError, match=f"{bag}.*(truncated or corrupt bag|cannot open)"):
        open_dataset(bag)


@pytest.mark.parametrize("storage", ["sqlite3", "mcap"])
def test_a_ros2_bag_without_its_metadata_yaml_is_named_so(tmp_path, storage, capsys):
    """A ROS 2 bag folder that lost its metadata.yaml: said so (not "unknown dataset layout"), detected
    or with --format rosbag, and one of its storage files given alone is named as such."""
    bag = tmp_path / "bag2"
    write_small_bag(bag, {"/cam/image": "mono8"}, {"/cam/camera_info": (64, 48)}, frames=4, storage=storage)
    (bag / "metadata.yaml").unlink()
    storage_file = next(p for p in bag.iterdir() if p.suffix in (".db3", ".mcap"))
    expected = f"{bag}: looks like a ROS 2 bag ({storage_file.name}) but its metadata.yaml is missing"
    for fmt in ("auto", "rosbag"):
        with pytest.raises(DataError) as info:
            open_dataset(bag, fmt)
        assert str(info.value).startswith(expected), str(info.value)
    assert main(["info", str(bag)]) == 2
    err = capsys.readouterr().err
    assert "metadata.yaml is missing" in err and "unknown dataset layout" not in err and "Traceback" not in err
    with pytest.raises(DataError, match="a ROS 2 bag's storage file: give the bag's folder"):
        detect_format(storage_file)


def test_unsorted_stamps(tmp_path):
    bag = tmp_path / "unsorted.bag"
    stamps = [10**9 + k * 10**8 for k in (0, 1, 3, 2, 4)]
    write_small_bag(bag, {"/cam/image": "mono8"}, {"/cam/camera_info": (64, 48)}, stamps_ns=stamps)
    with pytest.raises(DataError, match="topic /cam/image: header stamp of message 3 .* is not after the previous one"):
        open_dataset(bag)


def test_corrupt_frame_is_skipped_naming_the_topic(tmp_path, caplog):
    bag = tmp_path / "corrupt.bag"
    write_small_bag(bag, {"/cam/image/compressed": "compressed-png"}, {"/cam/camera_info": (64, 48)}, frames=12)
    ds = open_dataset(bag, config=DatasetConfig(crop_multiple=1, max_skipped_fraction=0.2))
    import fgslam.io.datasets.rosbag as rosbag

    real = rosbag.image_from_message

    def broken(msg, msgtype, topic, depth):
        if int(msg.header.stamp.nanosec) == 5 * 10**8:
            raise rosbag.FrameReadError(f"{topic}: truncated PNG (no IEND chunk)")
        return real(msg, msgtype, topic, depth)

    rosbag.image_from_message = broken
    try:
        with caplog.at_level(logging.WARNING):
            frames = list(ds)
    finally:
        rosbag.image_from_message = real
    assert len(frames) == 11 and ds.skipped_frames == [(5, "/cam/image/compressed: truncated PNG (no IEND chunk)")]
    assert "skipping frame 5: /cam/image/compressed" in caplog.text


def test_missing_rosbags_names_the_extra(tmp_path, monkeypatch):
    bag = write_and(tmp_path / "x.bag", {"/cam/image": "mono8"})
    monkeypatch.setitem(sys.modules, "rosbags.highlevel", None)
    with pytest.raises(DataError, match=r"pip install 'fgslam\[bag\]'"):
        open_dataset(bag)


# ------------------------------------------------------------------------------- export to a bag
@pytest.mark.parametrize("out_name", ["traj.bag", "traj_ros2"])
def test_export_trajectory_to_a_bag_reads_back(tmp_path, out_name, capsys):
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore
    from scipy.spatial.transform import Rotation

    from fgslam.io.trajectory import read_trajectory

    run = tmp_path / "run"
    run.mkdir()
    rng = np.random.default_rng(3)
    lines = []
    for k in range(7):
        q = Rotation.from_rotvec(rng.normal(size=3) * 0.3).as_quat()
        lines.append(f"{100 + 0.05 * k:.9f} {k * 0.1} {-0.2 * k} {0.3} {q[0]} {q[1]} {q[2]} {q[3]}")
    (run / "trajectory_tum.txt").write_text("\n".join(lines) + "\n")
    traj = read_trajectory(run / "trajectory_tum.txt", "tum")
    out = tmp_path / out_name
    assert main(["export", str(run), "--bag", str(out), "--json"]) == 0
    result = json.loads(capsys.readouterr().out)
    assert result["poses"] == 7 and result["ros_version"] == (1 if out_name.endswith(".bag") else 2)
    with AnyReader([out], default_typestore=get_typestore(Stores.ROS2_HUMBLE)) as reader:
        msgs: dict[str, list] = {}
        for conn, log_ns, raw in reader.messages():
            msgs.setdefault(conn.topic, []).append((log_ns, reader.deserialize(raw, conn.msgtype)))
    assert {t: len(v) for t, v in msgs.items()} == {"/fgslam/pose": 7, "/tf": 7, "/fgslam/path": 1}
    path = msgs["/fgslam/path"][0][1]
    assert path.header.frame_id == "map" and len(path.poses) == 7
    for k, (log_ns, pose) in enumerate(msgs["/fgslam/pose"]):
        stamp = pose.header.stamp.sec + pose.header.stamp.nanosec * 1e-9
        assert stamp == pytest.approx(traj.timestamps[k], abs=1e-9) and log_ns == round(traj.timestamps[k] * 1e9)
        p, q = pose.pose.position, pose.pose.orientation
        T = np.eye(4)
        T[:3, :3] = Rotation.from_quat([q.x, q.y, q.z, q.w]).as_matrix()
        T[:3, 3] = (p.x, p.y, p.z)
        assert np.allclose(T, traj.T_WC[k], atol=1e-12)
        tf = msgs["/tf"][k][1].transforms[0]
        assert tf.child_frame_id == "fgslam_camera" and tf.transform.translation.x == p.x
        assert path.poses[k].pose.position.z == p.z
    assert main(["export", str(run), "--bag", str(out)]) == 2  # exists: refused without --overwrite (a data error)
    assert "exists (use --overwrite" in capsys.readouterr().err
    assert main(["export", str(run), "--bag", str(out), "--overwrite"]) == 0


def test_export_overwrite_replaces_only_a_bag(tmp_path, capsys):
    """``export --bag OUT --overwrite`` replaces a bag, never another folder or file (those are left
    untouched with a clear error), and leaves no temporary file; a failed write keeps the old bag."""
    from unittest import mock

    import fgslam.export.bag as bag_export

    run = tmp_path / "run"
    run.mkdir()
    (run / "trajectory_tum.txt").write_text("100.0 0 0 0 0 0 0 1\n100.1 0.1 0 0 0 0 0 1\n")
    folder = tmp_path / "results"
    folder.mkdir()
    (folder / "precious.txt").write_text("keep\n")
    for target in (folder, tmp_path / "notes.txt"):
        if not target.exists():
            target.write_text("keep\n")
        assert main(["export", str(run), "--bag", str(target), "--overwrite"]) == 2
        assert "is not a ROS bag" in capsys.readouterr().err
    assert (folder / "precious.txt").read_text() == "keep\n" and (tmp_path / "notes.txt").read_text() == "keep\n"
    for name in ("traj.bag", "traj_ros2"):
        out = tmp_path / name
        assert main(["export", str(run), "--bag", str(out)]) == 0
        before = sorted(p.read_bytes() for p in ([out] if out.is_file() else out.iterdir()))
        with mock.patch.object(bag_export, "write_trajectory_bag", side_effect=OSError("disk full")):
            with pytest.raises(OSError):
                bag_export.export_bag(run, out, overwrite=True)
        assert sorted(p.read_bytes() for p in ([out] if out.is_file() else out.iterdir())) == before
        assert main(["export", str(run), "--bag", str(out), "--overwrite"]) == 0
        assert bag_export.is_bag(out)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["notes.txt", "results", "run", "traj.bag", "traj_ros2"]
