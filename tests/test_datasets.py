"""Tests of the dataset loaders (fgslam.io.datasets), the frame type and ``fgslam info``.

Every loader runs on a tiny fixture written here into tmp_path; EuRoC, KITTI and 7-Scenes also run
on the real clips in ../shared/data (skipped when absent).
"""

import argparse
import json
import logging
import re
import tracemalloc
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml
from scipy.spatial.transform import Rotation

from fgslam.commands import info as info_cmd
from fgslam.core.errors import DataError
from fgslam.core.config import load_config
from fgslam.io.datasets import DatasetConfig, EurocDataset, detect_format, open_dataset
from fgslam.io.frame import FrameReadError
from fgslam.io.trajectory import read_trajectory

NO_CROP = DatasetConfig(crop_multiple=1)


def _texture(h, w, seed, colour=False):
    rng = np.random.default_rng(seed)
    img = cv2.resize(rng.integers(0, 255, (h // 4 + 1, w // 4 + 1), dtype=np.uint8), (w, h))
    if colour:
        return np.dstack([img, 255 - img, img // 2])
    return img


def _T(rotvec, t):
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(rotvec).as_matrix()
    T[:3, 3] = t
    return T


# ---------------------------------------------------------------------------- fixture writers
def write_euroc(root, n=12, w=64, h=48, stereo=True, imu=True, depth=False, gt=True, n_right=None, t0_ns=10**18):
    """EuRoC layout per TEAM.md (20 Hz camera, 200 Hz IMU, ground truth from frame 3 on)."""
    mav = root / "mav0"
    period_ns = 50_000_000
    stamps = [t0_ns + i * period_ns for i in range(n)]
    T_BS0 = _T([0.0, 0.0, np.pi / 2], [0.02, -0.06, 0.01])
    T_BS1 = T_BS0 @ _T([0, 0, 0], [0.1, 0, 0])
    for cam, T_BS, count in (("cam0", T_BS0, n), ("cam1", T_BS1, n_right or n)):
        if cam == "cam1" and not stereo:
            continue
        (mav / cam / "data").mkdir(parents=True)
        lines = ["#timestamp [ns],filename"]
        for i, ts in enumerate(stamps[:count]):
            cv2.imwrite(str(mav / cam / "data" / f"{ts}.png"), _texture(h, w, i))
            lines.append(f"{ts},{ts}.png")
        (mav / cam / "data.csv").write_text("\n".join(lines) + "\n")
        sensor = {"sensor_type": "camera", "T_BS": {"rows": 4, "cols": 4, "data": T_BS.ravel().tolist()},
                  "rate_hz": 20, "resolution": [w, h], "camera_model": "pinhole",
                  "intrinsics": [50.0, 50.0, w / 2 - 0.5, h / 2 - 0.5],
                  "distortion_model": "radial-tangential", "distortion_coefficients": [0.0, 0.0, 0.0, 0.0]}
        (mav / cam / "sensor.yaml").write_text("%YAML:1.0\n" + yaml.safe_dump(sensor))
    if imu:
        (mav / "imu0").mkdir(parents=True)
        lines = ["#timestamp [ns],w_RS_S_x [rad s^-1],w_RS_S_y,w_RS_S_z,a_RS_S_x [m s^-2],a_RS_S_y,a_RS_S_z"]
        for k in range(-20, 10 * n + 20):
            lines.append(f"{t0_ns + k * 5_000_000},0.01,0.02,{k * 1e-4},0.1,0.2,9.81")
        (mav / "imu0" / "data.csv").write_text("\n".join(lines) + "\n")
        (mav / "imu0" / "sensor.yaml").write_text(yaml.safe_dump(
            {"T_BS": {"rows": 4, "cols": 4, "data": np.eye(4).ravel().tolist()}, "rate_hz": 200}))
    if depth:
        (mav / "depth0" / "data").mkdir(parents=True)
        lines = ["#timestamp [ns],filename"]
        for i, ts in enumerate(stamps):
            d = np.full((h, w), 2000 + 100 * i, dtype=np.uint16)
            d[0, 0] = 0
            cv2.imwrite(str(mav / "depth0" / "data" / f"{ts}.png"), d)
            lines.append(f"{ts},{ts}.png")
        (mav / "depth0" / "data.csv").write_text("\n".join(lines) + "\n")
        (mav / "depth0" / "sensor.yaml").write_text(yaml.safe_dump({"depth_scale": 1000}))
    gt_poses = {}
    if gt:
        (mav / "state_groundtruth_estimate0").mkdir(parents=True)
        lines = ["#timestamp, p_RS_R_x [m], p_RS_R_y [m], p_RS_R_z [m], q_RS_w [], q_RS_x [], q_RS_y [], q_RS_z []"]
        for i in range(3, n):
            T = _T([0.1 * i, -0.05 * i, 0.02], [0.3 * i, 0.1, -0.2 * i])
            q = Rotation.from_matrix(T[:3, :3]).as_quat()  # x y z w
            lines.append(f"{stamps[i]},{T[0, 3]},{T[1, 3]},{T[2, 3]},{q[3]},{q[0]},{q[1]},{q[2]},0,0,0,0,0,0,0,0,0")
            gt_poses[i] = T
        (mav / "state_groundtruth_estimate0" / "data.csv").write_text("\n".join(lines) + "\n")
    return {"stamps": stamps, "T_BS0": T_BS0, "T_BS1": T_BS1, "gt": gt_poses}


def write_kitti(root, n=6, w=70, h=40, n_right=None, poses=True):
    (root / "image_0").mkdir(parents=True)
    for i in range(n):
        cv2.imwrite(str(root / "image_0" / f"{i:06d}.png"), _texture(h, w, i))
    if n_right is not None:
        (root / "image_1").mkdir()
        for i in range(n_right):
            cv2.imwrite(str(root / "image_1" / f"{i:06d}.png"), _texture(h, w, 100 + i))
    fx, b = 718.856, 0.54
    P0 = [fx, 0, 35.0, 0, 0, fx, 20.0, 0, 0, 0, 1, 0]
    P1 = [fx, 0, 35.0, -fx * b, 0, fx, 20.0, 0, 0, 0, 1, 0]
    (root / "calib.txt").write_text("P0: " + " ".join(map(str, P0)) + "\nP1: " + " ".join(map(str, P1)) + "\n")
    (root / "times.txt").write_text("".join(f"{0.1 * i:.6e}\n" for i in range(n)))
    if poses:
        rows = [_T([0, 0.01 * i, 0], [0, 0, 0.8 * i])[:3].ravel() for i in range(n)]
        (root / "poses.txt").write_text("".join(" ".join(f"{v:.9e}" for v in r) + "\n" for r in rows))
    return fx, b


def write_tum(root, n=8):
    (root / "rgb").mkdir(parents=True)
    (root / "depth").mkdir()
    rgb_lines, depth_lines = ["# color images"], ["# depth maps"]
    for i in range(n):
        t = 100.0 + i / 30.0
        cv2.imwrite(str(root / "rgb" / f"{t:.6f}.png"), _texture(480, 640, i, colour=True))
        rgb_lines.append(f"{t:.6f} rgb/{t:.6f}.png")
        if i != 4:  # frame 4 gets a depth image 50 ms away: no association
            td = t + 0.01
        else:
            td = t + 0.05
        d = np.full((480, 640), 5000 + 500 * i, dtype=np.uint16)
        d[:10] = 0
        cv2.imwrite(str(root / "depth" / f"{td:.6f}.png"), d)
        depth_lines.append(f"{td:.6f} depth/{td:.6f}.png")
    (root / "rgb.txt").write_text("\n".join(rgb_lines) + "\n")
    (root / "depth.txt").write_text("\n".join(depth_lines) + "\n")
    # ground truth at 100 Hz, linear motion x = 0.5 t, rotation about z at 0.2 rad/s, from t=100.05
    lines = ["# timestamp tx ty tz qx qy qz qw"]
    for k in range(5, 40):
        t = 100.0 + k / 100.0
        q = Rotation.from_rotvec([0, 0, 0.2 * (t - 100.0)]).as_quat()
        lines.append(f"{t:.4f} {0.5 * (t - 100):.6f} 0 1 {q[0]:.9f} {q[1]:.9f} {q[2]:.9f} {q[3]:.9f}")
    (root / "groundtruth.txt").write_text("\n".join(lines) + "\n")


def write_tartanair(root, n=3, nan_depth=True):
    for d in ("image_left", "image_right", "depth_left"):
        (root / d).mkdir(parents=True)
    poses = []
    for i in range(n):
        cv2.imwrite(str(root / "image_left" / f"{i:06d}_left.png"), _texture(480, 640, i, colour=True))
        cv2.imwrite(str(root / "image_right" / f"{i:06d}_right.png"), _texture(480, 640, 50 + i, colour=True))
        depth = np.full((480, 640), 3.0 + i, dtype=np.float32)
        if nan_depth:
            depth[0, :5] = [np.nan, 0.0, -1.0, np.inf, 2.0]
        np.save(root / "depth_left" / f"{i:06d}_left_depth.npy", depth)
        q = Rotation.from_rotvec([0, 0, 0.3 * i]).as_quat()  # yaw about NED down
        poses.append(f"{1.0 * i} {0.5 * i} {-0.1 * i} {q[0]} {q[1]} {q[2]} {q[3]}")
    (root / "pose_left.txt").write_text("\n".join(poses) + "\n")


def write_7scenes(root, n=3, intrinsics=False):
    seq = root / "seq-01"
    seq.mkdir(parents=True)
    for i in range(n):
        cv2.imwrite(str(seq / f"frame-{i:06d}.color.png"), _texture(480, 640, i, colour=True))
        d = np.full((480, 640), 1500 + i, dtype=np.uint16)
        d[:, :20] = 0
        d[:5, 100:] = 65535
        cv2.imwrite(str(seq / f"frame-{i:06d}.depth.png"), d)
        np.savetxt(seq / f"frame-{i:06d}.pose.txt", _T([0, 0.1 * i, 0], [0.1 * i, 0, 0]))
    if intrinsics:
        np.savetxt(root / "camera-intrinsics.txt", np.array([[600.0, 0, 321], [0, 601, 239], [0, 0, 1]]))


def write_folder(root, n=5, w=64, h=48, calib_size=None, timestamps=False, ext=".png"):
    root.mkdir(parents=True, exist_ok=True)
    for i in range(n):
        cv2.imwrite(str(root / f"img_{i:04d}{ext}"), _texture(h, w, i))
    cw, ch = calib_size or (w, h)
    (root / "calibration.yaml").write_text(yaml.safe_dump(
        {"width": cw, "height": ch, "intrinsics": [40.0, 40.0, cw / 2, ch / 2], "rate_hz": 15}))
    if timestamps:
        (root / "timestamps.txt").write_text("".join(f"{5.0 + 0.25 * i}\n" for i in range(n)))


def _corrupt(path):
    path.write_bytes(b"not an image at all")


# ---------------------------------------------------------------------------- loaders on fixtures
def test_euroc_fixture_stereo_imu_gt(tmp_path):
    meta = write_euroc(tmp_path / "seq")
    ds = open_dataset(tmp_path / "seq", config=NO_CROP)
    assert ds.format == "euroc" and detect_format(tmp_path / "seq") == "euroc"
    assert len(ds) == 12 and ds.has_stereo and ds.has_imu and not ds.has_depth
    assert ds.rate == pytest.approx(20.0)
    frames = list(ds)
    assert [f.index for f in frames] == list(range(12))
    assert frames[0].image.dtype == np.uint8 and frames[0].image.shape == (48, 64)
    assert frames[0].image_right.shape == (48, 64)
    # identical ideal cameras: rectification is the identity up to round-off
    T_BC = meta["T_BS0"]
    assert len(frames[0].imu) == 0
    for f in frames[1:]:
        assert len(f.imu) == 10  # 200 Hz IMU, 20 Hz camera
        assert np.all(f.imu.timestamps > frames[f.index - 1].timestamp) and np.all(f.imu.timestamps <= f.timestamp)
    for i, f in enumerate(frames):
        if i < 3:
            assert f.T_WC_gt is None  # before the ground truth starts: none, never invented
        else:
            np.testing.assert_allclose(f.T_WC_gt, meta["gt"][i] @ T_BC @ ds._undistorter.T_C_Cout, atol=1e-7)
            np.testing.assert_allclose(ds._undistorter.T_C_Cout, np.eye(4), atol=1e-9)
    assert len(ds.groundtruth) == 9
    assert ds.calibration.baseline == pytest.approx(0.1, abs=1e-9)
    # the same folder opened through mav0 directly, and with the loader's default config
    assert len(open_dataset(tmp_path / "seq" / "mav0", "euroc", NO_CROP)) == 12
    strided = EurocDataset(tmp_path / "seq" / "mav0")
    assert strided.name == "seq" and len(strided) == 12
    strided = open_dataset(tmp_path / "seq", config=DatasetConfig(stride=3, start=1))
    assert [f.source_index for f in strided] == [1, 4, 7, 10] and strided.rate == pytest.approx(20.0 / 3)
    assert len(strided[1].imu) == 30  # IMU since the previous frame of the dataset


def test_euroc_depth0_extension(tmp_path):
    write_euroc(tmp_path / "syn", n=4, depth=True, stereo=False, imu=False, gt=False)
    ds = open_dataset(tmp_path / "syn", config=NO_CROP)
    assert ds.has_depth and not ds.has_stereo and not ds.has_imu and ds.groundtruth is None
    f = ds[2]
    assert f.depth.dtype == np.float32
    assert f.depth[10, 10] == pytest.approx(2.2)
    assert f.depth[0, 0] == 0.0  # invalid stays 0
    assert f.imu is None and f.image_right is None


def test_kitti_fixture_baseline_and_poses(tmp_path):
    fx, b = write_kitti(tmp_path / "00", n=6, n_right=6)
    ds = open_dataset(tmp_path / "00")
    assert ds.format == "kitti" and len(ds) == 6 and ds.has_stereo
    assert ds.raw_calibration.baseline == pytest.approx(b, rel=1e-12)
    np.testing.assert_allclose(ds.raw_calibration.T_CLCR[:3, 3], [b, 0, 0], atol=1e-12)
    assert ds.calibration.width == 64 and ds.calibration.height == 40  # 70 -> cropped to a multiple of 8
    assert ds.calibration.K[2] == pytest.approx(35.0 - 3)
    f = ds[5]
    assert f.image.shape == (40, 64) and f.image_right.shape == (40, 64)
    assert f.timestamp == pytest.approx(0.5)
    np.testing.assert_allclose(f.T_WC_gt[:3, 3], [0, 0, 4.0], atol=1e-9)


def test_kitti_poses_from_benchmark_layout(tmp_path):
    seq = tmp_path / "dataset" / "sequences" / "07"
    write_kitti(seq, n=4, poses=False)
    (tmp_path / "dataset" / "poses").mkdir()
    rows = [_T([0, 0, 0], [i, 0, 0])[:3].ravel() for i in range(10)]
    (tmp_path / "dataset" / "poses" / "07.txt").write_text("".join(" ".join(map(str, r)) + "\n" for r in rows))
    ds = open_dataset(seq, config=DatasetConfig(stride=2))
    assert len(ds) == 2 and [f.source_index for f in ds] == [0, 2]
    np.testing.assert_allclose(ds.groundtruth.t_WC[:, 0], [0.0, 2.0])


def test_tum_fixture_association_depth_gt(tmp_path):
    root = tmp_path / "rgbd_dataset_freiburg3_fixture"
    write_tum(root)
    ds = open_dataset(root)
    assert ds.format == "tum" and ds.has_depth and not ds.has_stereo
    assert len(ds) == 7  # frame 4 has no depth within 0.02 s
    np.testing.assert_allclose(ds.raw_calibration.K, [535.4, 539.2, 320.1, 247.6])
    frames = list(ds)
    f = frames[4]  # raw rgb frame 5
    assert f.source_index == 4
    assert f.rgb.shape == (480, 640, 3) and f.rgb.dtype == np.uint8
    assert f.depth[100, 100] == pytest.approx((5000 + 500 * 5) / 5000.0)
    assert f.depth[0, 0] == 0.0
    # ground truth interpolated at the frame time (starts at t=100.05: frames 0, 1 have none)
    assert frames[0].T_WC_gt is None and frames[1].T_WC_gt is None
    for fr in frames[2:]:
        t = fr.timestamp - 100.0
        assert fr.T_WC_gt[0, 3] == pytest.approx(0.5 * t, abs=1e-5)
        R = Rotation.from_rotvec([0, 0, 0.2 * t]).as_matrix()
        np.testing.assert_allclose(fr.T_WC_gt[:3, :3], R, atol=1e-6)
    # camera detection from the folder name and the override
    fr1 = tmp_path / "rgbd_dataset_freiburg1_xyz"
    write_tum(fr1, n=2)
    assert open_dataset(fr1).raw_calibration.distortion_model == "radtan"
    np.testing.assert_allclose(open_dataset(fr1, config=DatasetConfig(tum_camera="fr2")).raw_calibration.K,
                               [520.9, 521.0, 325.1, 249.7])


def test_tartanair_fixture_ned_conversion_and_bad_depth(tmp_path):
    write_tartanair(tmp_path / "P000")
    ds = open_dataset(tmp_path / "P000")
    assert ds.format == "tartanair" and ds.has_stereo and ds.has_depth
    assert ds.calibration.baseline == pytest.approx(0.25)
    np.testing.assert_allclose(ds.calibration.K, [320, 320, 320, 240])
    f = ds[2]
    # NaN, 0, negative and inf depths become 0 (invalid); valid ones are kept
    assert np.all(np.isfinite(f.depth)) and f.depth.min() == 0.0
    np.testing.assert_array_equal(f.depth[0, :5], [0, 0, 0, 0, 2.0])
    assert f.depth[100, 100] == pytest.approx(5.0)
    # NED body axes (x fwd, y right, z down) -> optical axes (x right, y down, z fwd)
    P = np.array([[0, 0, 1], [1, 0, 0], [0, 1, 0]], dtype=float)
    R_ned = Rotation.from_rotvec([0, 0, 0.6]).as_matrix()
    T = f.T_WC_gt
    np.testing.assert_allclose(T[:3, 3], P.T @ [2.0, 1.0, -0.2], atol=1e-9)
    np.testing.assert_allclose(T[:3, 2], P.T @ R_ned[:, 0], atol=1e-9)  # optical z = body forward
    np.testing.assert_allclose(T[:3, 1], P.T @ R_ned[:, 2], atol=1e-9)  # optical y = body down


def test_7scenes_fixture_depth_invalid_and_intrinsics(tmp_path):
    write_7scenes(tmp_path / "chess", n=3)
    ds = open_dataset(tmp_path / "chess")
    assert ds.format == "7scenes" and len(ds) == 3 and ds.has_depth
    np.testing.assert_allclose(ds.calibration.K, [585, 585, 320, 240])
    f = ds[1]
    assert f.depth[100, 10] == 0.0 and f.depth[2, 200] == 0.0  # 0 and 65535 invalid
    assert f.depth[100, 200] == pytest.approx(1.501)
    assert f.timestamp == pytest.approx(1 / 30)
    np.testing.assert_allclose(f.T_WC_gt[:3, 3], [0.1, 0, 0])
    write_7scenes(tmp_path / "other", n=1, intrinsics=True)
    np.testing.assert_allclose(open_dataset(tmp_path / "other").calibration.K, [600, 601, 321, 239])


def test_folder_and_timestamps(tmp_path):
    write_folder(tmp_path / "imgs", n=5)
    ds = open_dataset(tmp_path / "imgs")
    assert ds.format == "folder" and len(ds) == 5 and ds.rate == pytest.approx(15.0)
    write_folder(tmp_path / "timed", n=5, timestamps=True)
    ds = open_dataset(tmp_path / "timed", config=DatasetConfig(start=1, end=4))
    assert [f.timestamp for f in ds] == pytest.approx([5.25, 5.5, 5.75])


def test_video_loader(tmp_path):
    path = tmp_path / "clip.avi"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 10.0, (64, 48))
    if not writer.isOpened():
        pytest.skip("this OpenCV build cannot write MJPG video")
    for i in range(10):
        img = np.full((48, 64, 3), 20 * i, dtype=np.uint8)
        writer.write(img)
    writer.release()
    (tmp_path / "clip.yaml").write_text(yaml.safe_dump({"width": 64, "height": 48, "intrinsics": [50, 50, 32, 24]}))
    ds = open_dataset(path)
    assert ds.format == "video" and len(ds) == 10 and ds.rate == pytest.approx(10.0)
    frames = list(ds)
    assert len(frames) == 10 and frames[3].timestamp == pytest.approx(0.3)
    assert frames[3].rgb.shape == (48, 64, 3)
    # random access after sequential reads gives the same frame
    assert abs(int(ds[6].image.mean()) - 120) <= 3 and abs(int(ds[2].image.mean()) - 40) <= 3
    ds.close()


def test_resize_config_adjusts_frames(tmp_path):
    write_folder(tmp_path / "imgs", n=2, w=64, h=48)
    ds = open_dataset(tmp_path / "imgs", config=DatasetConfig(resize_scale=0.5, crop_multiple=8))
    f = ds[0]
    assert f.image.shape == (24, 32) and (f.calibration.width, f.calibration.height) == (32, 24)
    np.testing.assert_allclose(f.calibration.K, [20, 20, (32 + 0.5) * 0.5 - 0.5, (24 + 0.5) * 0.5 - 0.5])


def test_lazy_loading_memory_does_not_grow(tmp_path):
    write_folder(tmp_path / "long", n=300, w=64, h=48)
    ds = open_dataset(tmp_path / "long")
    tracemalloc.start()
    try:
        it = iter(ds)
        for _ in range(30):
            next(it)
        after_30, _ = tracemalloc.get_traced_memory()
        count = 30 + sum(1 for _ in it)
        after_all, _ = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert count == 300
    # 270 more frames of 3 KB each would add ~830 KB if anything kept them
    assert after_all - after_30 < 64 * 1024


# ---------------------------------------------------------------------------- bad input
def test_missing_paths_and_files(tmp_path):
    with pytest.raises(DataError, match="nope.*no such file or folder"):
        open_dataset(tmp_path / "nope")
    with pytest.raises(DataError, match="unknown dataset layout"):
        (tmp_path / "empty").mkdir()
        open_dataset(tmp_path / "empty")
    write_euroc(tmp_path / "e", n=3)
    (tmp_path / "e" / "mav0" / "cam0" / "data.csv").unlink()
    with pytest.raises(DataError, match=r"cam0/data\.csv: missing"):
        open_dataset(tmp_path / "e")
    write_kitti(tmp_path / "k", n=3)
    (tmp_path / "k" / "calib.txt").unlink()
    with pytest.raises(DataError, match=r"calib\.txt: missing"):
        open_dataset(tmp_path / "k", "kitti")
    write_folder(tmp_path / "f", n=2)
    (tmp_path / "f" / "calibration.yaml").unlink()
    with pytest.raises(DataError, match="missing calibration YAML"):
        open_dataset(tmp_path / "f")
    with pytest.raises(DataError, match="unknown dataset format 'tumm'"):
        open_dataset(tmp_path / "f", "tumm")


def test_corrupt_frames_are_skipped_and_counted(tmp_path):
    write_folder(tmp_path / "seq", n=30)
    _corrupt(tmp_path / "seq" / "img_0007.png")
    (tmp_path / "seq" / "img_0020.png").write_bytes(b"")
    ds = open_dataset(tmp_path / "seq")
    frames = list(ds)
    assert len(frames) == 28
    assert [i for i, _ in ds.skipped_frames] == [7, 20]
    assert "img_0007.png" in ds.skipped_frames[0][1]
    with pytest.raises(FrameReadError, match="img_0007.png"):
        ds[7]
    list(ds)  # a second pass does not double-count
    assert len(ds.skipped_frames) == 2


def test_truncated_images_are_corrupt_frames(tmp_path):
    # OpenCV decodes a JPEG cut in half as a half-grey frame (only warning on stderr): it must be
    # skipped and counted like any corrupt frame, with the reason naming the file
    write_folder(tmp_path / "seq", n=12, ext=".jpg")
    cut = tmp_path / "seq" / "img_0005.jpg"
    cut.write_bytes(cut.read_bytes()[: cut.stat().st_size // 2])
    padded = tmp_path / "seq" / "img_0006.jpg"  # bytes after the end-of-image marker: complete
    padded.write_bytes(padded.read_bytes() + b"\0" * 16)
    ds = open_dataset(tmp_path / "seq")
    frames = list(ds)
    assert [f.index for f in frames] == [i for i in range(12) if i != 5]
    assert [i for i, _ in ds.skipped_frames] == [5]
    assert "img_0005.jpg: truncated JPEG" in ds.skipped_frames[0][1]
    with pytest.raises(FrameReadError, match=r"img_0005\.jpg: truncated JPEG"):
        ds[5]
    write_folder(tmp_path / "png", n=12)
    cut = tmp_path / "png" / "img_0003.png"
    cut.write_bytes(cut.read_bytes()[: cut.stat().st_size * 9 // 10])
    ds = open_dataset(tmp_path / "png")
    assert len(list(ds)) == 11 and ds.skipped_frames[0][0] == 3


def _zero_depth_7scenes(root, n, keep=()):
    """7-Scenes fixture whose depth maps hold no valid pixel, except frames in ``keep``."""
    write_7scenes(root, n=n)
    for i in range(n):
        if i not in keep:
            cv2.imwrite(str(root / "seq-01" / f"frame-{i:06d}.depth.png"), np.zeros((480, 640), np.uint16))


def test_all_invalid_depth_stream_is_reported_once(tmp_path, caplog):
    _zero_depth_7scenes(tmp_path / "zero", n=4)
    with caplog.at_level(logging.INFO, logger="fgslam"):
        assert len(list(open_dataset(tmp_path / "zero"))) == 4
    warned = [r for r in caplog.records if r.levelno == logging.WARNING and "RGB-D: no valid depth" in r.getMessage()]
    assert len(warned) == 1 and "no valid depth in 4 frames" in warned[0].getMessage()
    # some valid depth: an info line with the count, no warning
    caplog.clear()
    _zero_depth_7scenes(tmp_path / "some", n=4, keep=(1,))
    with caplog.at_level(logging.INFO, logger="fgslam"):
        list(open_dataset(tmp_path / "some"))
    lines = [(r.levelno, r.getMessage()) for r in caplog.records if "RGB-D" in r.getMessage()]
    assert len(lines) == 1 and lines[0][0] == logging.INFO and "no valid depth in 3 of 4 frames" in lines[0][1]
    caplog.clear()
    write_7scenes(tmp_path / "valid", n=3)
    with caplog.at_level(logging.INFO, logger="fgslam"):
        list(open_dataset(tmp_path / "valid"))
    assert not [r for r in caplog.records if "RGB-D" in r.getMessage()]


def test_all_invalid_depth_is_on_the_console_of_a_run(tmp_path, capsys):
    from fgslam import cli

    _zero_depth_7scenes(tmp_path / "zero", n=3)
    rc = cli.main(["run", "patch_7scenes_rgbd", "--data", str(tmp_path / "zero"), "--out", str(tmp_path / "out")])
    assert rc == 2  # no frame got a pose: no result (issue 21)
    err = capsys.readouterr().err
    assert "RGB-D: no valid depth in 3 frames" in err
    assert err.strip().splitlines()[-1].startswith("fgslam: error: no frame got a pose")


def test_too_many_corrupt_frames_fail(tmp_path):
    write_folder(tmp_path / "seq", n=10)
    for i in range(1, 4):
        _corrupt(tmp_path / "seq" / f"img_{i:04d}.png")
    ds = open_dataset(tmp_path / "seq")
    with pytest.raises(DataError, match="unreadable"):
        list(ds)


def test_stereo_streams_of_different_lengths(tmp_path):
    write_kitti(tmp_path / "k", n=5, n_right=4)
    with pytest.raises(DataError, match="image_0 has 5 images, image_1 has 4"):
        open_dataset(tmp_path / "k")
    write_euroc(tmp_path / "e", n=6, n_right=4)
    with pytest.raises(DataError, match="2 cam0 frames have no cam1 partner"):
        open_dataset(tmp_path / "e")
    write_tartanair(tmp_path / "t", n=2)
    (tmp_path / "t" / "image_right" / "000001_right.png").unlink()
    with pytest.raises(DataError, match="image_left has 2, image_right has 1"):
        open_dataset(tmp_path / "t")


def test_calibration_not_matching_image_size(tmp_path):
    write_folder(tmp_path / "f", n=3, w=64, h=48, calib_size=(100, 48))
    with pytest.raises(DataError, match=r"calibration\.yaml: calibration is for 100x48 images but .*img_0000\.png is 64x48"):
        open_dataset(tmp_path / "f")
    # a single frame of the wrong size in a sequence is a corrupt frame
    write_folder(tmp_path / "g", n=12, w=64, h=48)
    cv2.imwrite(str(tmp_path / "g" / "img_0005.png"), _texture(40, 64, 0))
    ds = open_dataset(tmp_path / "g")
    with pytest.raises(FrameReadError, match=r"img_0005.png: frame 5 is 64x40, expected 64x48 \(the calibration's size\)"):
        ds[5]
    assert len(list(ds)) == 11 and ds.skipped_frames[0][0] == 5


def test_kitti_calib_without_labels(tmp_path, caplog):
    fx, b = write_kitti(tmp_path / "k", n=3, n_right=3)
    labelled = (tmp_path / "k" / "calib.txt").read_text().splitlines()
    rows = [line.split(":", 1)[1].strip() for line in labelled]
    (tmp_path / "k" / "calib.txt").write_text("\n".join(rows) + "\n")
    with caplog.at_level(logging.INFO, logger="fgslam"):
        ds = open_dataset(tmp_path / "k")
    assert ds.calibration.K[0] == pytest.approx(fx) and ds.calibration.baseline == pytest.approx(b)
    assert any("no 'P0:' labels; reading the 2 rows in order as P0, P1" in r.getMessage() for r in caplog.records)
    calib = tmp_path / "k" / "calib.txt"
    calib.write_text(f"{labelled[0]}\n{rows[1]}\n")  # labels on some lines only
    with pytest.raises(DataError, match=re.escape(f"{calib}:2: line has no label")):
        open_dataset(tmp_path / "k")
    calib.write_text(f"{rows[0]}\n{rows[1]} 7\n")  # malformed unlabelled row
    with pytest.raises(DataError, match=re.escape(f"{calib}:2: P1 must have 12 values, got 13")):
        open_dataset(tmp_path / "k")
    calib.write_text(f"P0 {rows[0]}\n")  # a label without its colon
    with pytest.raises(DataError, match=re.escape(f"{calib}:1: not a number") + r".*a label needs a colon: 'P0: \.\.\.'"):
        open_dataset(tmp_path / "k")


def test_unsorted_times_name_file_and_line(tmp_path):
    write_kitti(tmp_path / "k", n=6)
    times = tmp_path / "k" / "times.txt"
    times.write_text("0\n0.1\n0.3\n0.2\n0.4\n0.5\n")
    with pytest.raises(DataError, match=re.escape(f"{times}:4: time 0.2 is not after the previous one (0.3 on line 3)")):
        open_dataset(tmp_path / "k")
    write_folder(tmp_path / "f", n=3, timestamps=True)
    times = tmp_path / "f" / "timestamps.txt"
    times.write_text("# t\n1.0\n1.0\n2.0\n")
    with pytest.raises(DataError, match=re.escape(f"{times}:3: time 1.0 is not after")):
        open_dataset(tmp_path / "f")


def test_empty_sequences(tmp_path):
    write_euroc(tmp_path / "e", n=2, stereo=False, imu=False, gt=False)
    (tmp_path / "e" / "mav0" / "cam0" / "data.csv").write_text("#timestamp [ns],filename\n")
    with pytest.raises(DataError, match="empty sequence"):
        open_dataset(tmp_path / "e")
    (tmp_path / "f").mkdir()
    (tmp_path / "f" / "calibration.yaml").write_text("width: 4\nheight: 4\nintrinsics: [1, 1, 2, 2]\n")
    with pytest.raises(DataError, match="empty sequence"):
        open_dataset(tmp_path / "f", "folder")
    write_folder(tmp_path / "g", n=3)
    with pytest.raises(DataError, match="empty selection"):
        open_dataset(tmp_path / "g", config=DatasetConfig(start=5))


# ---------------------------------------------------------------------------- shared real data
def _body_T_BS(sensor_yaml):
    text = "\n".join(ln for ln in Path(sensor_yaml).read_text().splitlines() if not ln.startswith("%"))
    return np.asarray(yaml.safe_load(text)["T_BS"]["data"], dtype=float).reshape(4, 4)


def test_shared_euroc(shared_data):
    root = shared_data / "euroc_v101_micro"
    ds = open_dataset(root, config=DatasetConfig(rectify_stereo=False))
    assert ds.format == "euroc" and len(ds) == 95 and ds.has_stereo and ds.has_imu
    assert ds.imu_count == 29120
    assert ds.rate == pytest.approx(20.0, rel=1e-4)
    assert ds.calibration.width == 752 and ds.calibration.height == 480
    # ground truth: the 74 last frames, camera pose = body pose * T_BS(cam0)
    gt = ds.groundtruth
    assert len(gt) == 74
    body = read_trajectory(root / "groundtruth.txt", "euroc")
    T_BS = _body_T_BS(root / "mav0" / "cam0" / "sensor.yaml")
    idx = np.searchsorted(body.timestamps, gt.timestamps - 1e-6)
    np.testing.assert_allclose(body.timestamps[idx], gt.timestamps, atol=1e-6)
    np.testing.assert_allclose(gt.T_WC, body.T_WC[idx] @ T_BS, atol=1e-6)
    assert ds[20].T_WC_gt is None and ds[21].T_WC_gt is not None
    # IMU between frames: 10 samples at 200 Hz per 20 Hz frame interval, in (t_prev, t]
    prev = None
    total = 0
    for i in range(0, 95, 7):
        f = ds[i]
        if i > 0:
            prev = ds.timestamps[i - 1]
            assert len(f.imu) == 10
            assert f.imu.timestamps[0] > prev and f.imu.timestamps[-1] <= f.timestamp
            total += 1
    assert total > 10
    # the rectified default: rows aligned, GT follows the rectified camera
    rect = open_dataset(root)
    R = rect._undistorter.T_C_Cout
    np.testing.assert_allclose(rect.groundtruth.T_WC, gt.T_WC @ R, atol=1e-9)
    assert rect.calibration.baseline == pytest.approx(0.110, abs=2e-3)
    f = rect[40]
    assert f.image.shape == f.image_right.shape == (480, 752)


def test_shared_kitti(shared_data):
    root = shared_data / "kitti00_0-199"
    ds = open_dataset(root)
    assert ds.format == "kitti" and len(ds) == 200
    assert not ds.has_stereo and not ds.has_depth and not ds.has_imu  # image_0 only
    assert ds.raw_calibration.width == 1241 and ds.raw_calibration.height == 376
    assert ds.calibration.width == 1240
    np.testing.assert_allclose(ds.raw_calibration.K, [718.856, 718.856, 607.1928, 185.2157])
    poses = np.loadtxt(root / "poses.txt").reshape(-1, 3, 4)
    np.testing.assert_allclose(ds.groundtruth.T_WC[:, :3, :], poses, atol=1e-6)
    times = np.loadtxt(root / "times.txt")
    np.testing.assert_allclose(ds.timestamps, times)
    # P1 of the same calib.txt gives the stereo baseline: 386.1448 / 718.856 m
    P1 = [float(v) for v in (root / "calib.txt").read_text().splitlines()[1].split()[1:]]
    assert -P1[3] / P1[0] == pytest.approx(0.5371657, abs=1e-6)
    f = ds[199]
    assert f.image.shape == (376, 1240) and f.timestamp == pytest.approx(times[199])


def test_shared_7scenes(shared_data):
    root = shared_data / "7scenes_redkitchen_0-599"
    ds = open_dataset(root)
    assert ds.format == "7scenes" and len(ds) == 600 and ds.has_depth
    np.testing.assert_allclose(ds.calibration.K, [585, 585, 320, 240])
    for i in (0, 311, 599):
        f = ds[i]
        raw = cv2.imread(str(root / "seq-01" / f"frame-{i:06d}.depth.png"), cv2.IMREAD_UNCHANGED)
        valid = (raw > 0) & (raw != 65535)
        assert np.all(np.isfinite(f.depth))
        np.testing.assert_array_equal(f.depth > 0, valid)
        np.testing.assert_allclose(f.depth[valid], raw[valid] / 1000.0, rtol=1e-6)
        assert 0.02 < 1 - valid.mean() < 0.4  # README: ~11% invalid
        pose = np.loadtxt(root / "seq-01" / f"frame-{i:06d}.pose.txt")
        np.testing.assert_allclose(f.T_WC_gt, pose, atol=1e-3)
        np.testing.assert_allclose(f.T_WC_gt[:3, :3].T @ f.T_WC_gt[:3, :3], np.eye(3), atol=1e-9)
        assert f.rgb.shape == (480, 640, 3)
    assert len(ds.groundtruth) == 600


# ---------------------------------------------------------------------------- CLI
def _info(argv):
    parser = argparse.ArgumentParser()
    info_cmd.add_arguments(parser)
    return info_cmd.run(parser.parse_args(argv))


def test_dataset_config_yaml(repo_root, tmp_path):
    cfg = load_config(DatasetConfig, repo_root / "fgslam" / "configs" / "dataset.yaml", ["stride=2", "end=10"])
    assert cfg.stride == 2 and cfg.end == 10 and cfg.crop_multiple == DatasetConfig().crop_multiple
    write_folder(tmp_path / "f", n=12)
    assert len(open_dataset(tmp_path / "f", config=cfg)) == 5


def test_info_command(tmp_path, capsys):
    write_euroc(tmp_path / "seq", n=8)
    assert _info([str(tmp_path / "seq"), "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["format"] == "euroc" and out["frames"] == 8 and out["stereo"] and out["imu"]
    assert out["imu_samples"] == 10 * 8 + 40 and out["imu_samples_in_span"] == 70
    assert out["groundtruth_poses"] == 5 and out["resolution"] == [64, 48]
    assert _info([str(tmp_path / "seq"), "--format", "euroc", "-o", "stride=2"]) == 0
    text = capsys.readouterr().out
    assert "frames:       4" in text and "fx=" in text and "ground truth: yes" in text
    with pytest.raises(DataError):
        _info([str(tmp_path / "missing")])


def test_synthetic_sequence_from_generator_loads(tmp_path):
    """Engineer H's generator writes the EuRoC layout + depth0; this loader must read it exactly."""
    synth = pytest.importorskip("fgslam.io.synth")
    from fgslam.io.synth.scenarios import load_synth_config

    cfg = load_synth_config("room-loop", None, ["frames=4", "camera.width=96", "camera.height=64"])
    seq = synth.SynthSequence(cfg)
    synth.write_sequence(seq, tmp_path / "syn")
    ds = open_dataset(tmp_path / "syn")
    assert ds.format == "euroc" and len(ds) == 4 and ds.has_stereo and ds.has_depth and ds.has_imu
    frames = list(ds)
    T_expected = seq.camera_poses(seq.frame_times())  # synthetic times start at 0, files at an epoch
    T_expected = T_expected @ ds._undistorter.T_C_Cout
    np.testing.assert_allclose(np.stack([f.T_WC_gt for f in frames]), T_expected, atol=1e-6)
    assert all(f.depth.dtype == np.float32 and f.depth.max() > 0 for f in frames)


def test_info_on_a_folder_of_unreadable_images_says_so_and_fails(tmp_path, capsys):
    """Images that all fail to decode: ``fgslam info`` says they cannot be read (one line, exit 2)
    instead of describing the calibration's resolution."""
    from fgslam.cli import main

    write_folder(tmp_path / "f", n=7)
    for path in (tmp_path / "f").glob("*.png"):
        _corrupt(path)
    assert main(["info", str(tmp_path / "f")]) == 2
    captured = capsys.readouterr()
    assert "resolution" not in captured.out
    error = [line for line in captured.err.splitlines() if line.startswith("fgslam: error:")]
    assert captured.err.strip().splitlines() == error and len(error) == 1  # the one line, no warning before it
    assert "the images cannot be read (none of the 5 frames tried (of 7, first to last)" in error[0]
    assert "img_0000.png: unreadable or corrupt image" in error[0]
    # one readable image among them is enough: described as before, the first frame's failure a warning
    cv2.imwrite(str(tmp_path / "f" / "img_0006.png"), _texture(48, 64, 6))
    assert main(["info", str(tmp_path / "f")]) == 0
    captured = capsys.readouterr()
    assert "resolution:   64x48" in captured.out
    assert "first frame of" in captured.err and "image size not checked at open" in captured.err


def test_unknown_layout_lists_the_bag_layout_among_those_tried(tmp_path):
    (tmp_path / "empty").mkdir()
    with pytest.raises(DataError, match=r"unknown dataset layout \(looked for metadata.yaml \(ROS 2 bag\), "):
        detect_format(tmp_path / "empty")
    (tmp_path / "empty" / "rec_0.db3").write_bytes(b"")  # a ROS 2 bag's storage without its metadata.yaml
    with pytest.raises(DataError, match=r"looks like a ROS 2 bag \(rec_0.db3\) but its metadata.yaml is missing"):
        open_dataset(tmp_path / "empty")


def test_a_stray_ros2_storage_file_never_hides_another_layout(tmp_path):
    """A *.db3 / *.mcap beside an image folder's or a EuRoC sequence's files (a recording kept next to them)
    leaves the folder its layout; only a folder of no other layout is named a ROS 2 bag without metadata.yaml."""
    write_folder(tmp_path / "images", n=3)
    write_euroc(tmp_path / "euroc", n=4, stereo=False, imu=False)
    for root, fmt in ((tmp_path / "images", "folder"), (tmp_path / "euroc", "euroc")):
        (root / "recording_0.db3").write_bytes(b"")
        (root / "recording_1.mcap").write_bytes(b"")
        assert detect_format(root) == fmt
        assert open_dataset(root).format == fmt
    (tmp_path / "images" / "recording_0.db3").unlink()
    (tmp_path / "images" / "recording_1.mcap").unlink()
    for image in (tmp_path / "images").glob("*.png"):  # no layout left: the storage file is named
        image.unlink()
    (tmp_path / "images" / "recording_0.db3").write_bytes(b"")
    with pytest.raises(DataError, match=r"looks like a ROS 2 bag \(recording_0.db3\) but its metadata.yaml"):
        detect_format(tmp_path / "images")
    with pytest.raises(DataError, match=r"a ROS 2 bag's storage file: give the bag's folder"):
        detect_format(tmp_path / "images" / "recording_0.db3")


def test_calibration_messages_give_the_exact_override(tmp_path, capsys):
    """A missing or unusable calibration names the override to give, -o dataset.calibration_file=PATH, which
    fgslam info takes as fgslam run does."""
    from types import SimpleNamespace

    from fgslam.cli import main
    from fgslam.io.datasets.ros_messages import calibration_from_camera_info

    write_folder(tmp_path / "f", n=3)
    calib = tmp_path / "cam.yaml"
    (tmp_path / "f" / "calibration.yaml").rename(calib)
    with pytest.raises(DataError, match=r"missing calibration YAML .*or give one with -o dataset\.calibration_file=PATH\)$"):
        open_dataset(tmp_path / "f")
    assert main(["info", str(tmp_path / "f"), "-o", f"dataset.calibration_file={calib}"]) == 0
    assert "resolution:   64x48" in capsys.readouterr().out
    info = SimpleNamespace(distortion_model="fisheye62", D=[0.1, 0.0, 0.0, 0.0], K=[40, 0, 32, 0, 40, 24, 0, 0, 1])
    with pytest.raises(DataError, match=r"give a calibration YAML with -o dataset\.calibration_file=PATH$"):
        calibration_from_camera_info(info, "/cam/camera_info")
    info = SimpleNamespace(distortion_model="plumb_bob", D=[0.0] * 5, K=[0.0] * 9)
    with pytest.raises(DataError, match=r"give a calibration YAML with -o dataset\.calibration_file=PATH$"):
        calibration_from_camera_info(info, "/cam/camera_info")


def test_a_calibration_file_for_a_loader_that_does_not_read_it_is_refused(tmp_path, capsys):
    """KITTI, EuRoC, 7-Scenes ... take the calibration of their own files: a calibration YAML given for
    them would be ignored, so it is an error naming the loaders that read it (not a run with the wrong one)."""
    from fgslam.cli import main
    from fgslam.io.datasets import CALIBRATION_FILE_FORMATS

    write_kitti(tmp_path / "k")
    write_7scenes(tmp_path / "s")
    calib = tmp_path / "cam.yaml"
    calib.write_text("width: 70\nheight: 40\nintrinsics: [50, 50, 35, 20]\n")
    for root, fmt in ((tmp_path / "k", "kitti"), (tmp_path / "s", "7scenes")):
        assert fmt not in CALIBRATION_FILE_FORMATS
        with pytest.raises(DataError, match=rf"dataset\.calibration_file is read by the tum, .* loaders; the {fmt} loader"):
            open_dataset(root, config=DatasetConfig(calibration_file=str(calib)))
        open_dataset(root)  # without the key: its own calibration
    assert main(["run", "patch_mono", "--data", str(tmp_path / "k"), "--out", str(tmp_path / "out"),
                 "-o", f"dataset.calibration_file={calib}"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert "kitti loader takes the calibration of its own files" in err[-1] and "Traceback" not in "\n".join(err)
    assert not (tmp_path / "out" / "summary.json").exists()


def test_a_non_finite_imu_value_names_its_line_in_the_file(tmp_path):
    """The line number counts the header and comment lines (the file's own line, not the data row)."""
    write_euroc(tmp_path / "seq", n=3)
    csv = tmp_path / "seq" / "mav0" / "imu0" / "data.csv"
    lines = csv.read_text().splitlines()
    lines.insert(3, "# a comment line")
    lines[6] = lines[6].rsplit(",", 1)[0] + ",nan"  # line 7 of the file, data row 5 (0-based 4)
    csv.write_text("\n".join(lines) + "\n")
    with pytest.raises(DataError, match=re.escape(f"{csv}:7: non-finite IMU value (")):
        open_dataset(tmp_path / "seq")
