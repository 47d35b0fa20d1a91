"""The TUM-VI loader (fgslam/io/datasets/tumvi.py) on a synthetic room loop written in the TUM-VI layout
(fgslam/io/synth/writer.py ``write_tumvi_sequence``: equidistant fisheye images, Kalibr camchain, mocap
ground truth), read back and run stereo-inertial."""

import numpy as np
import pytest

pytest.importorskip("gtsam")

from fgslam.core.errors import DataError
from fgslam.io.datasets import DatasetConfig, detect_format, open_dataset

from eval_support import assert_beats_doing_nothing, evaluate_tum_rows, run_preset

FRAMES = 100
# a mild Kannala-Brandt fisheye, as TUM-VI's (k1..k4 of the order 1e-3); hfov 80: rays up to ~60 deg
FISHEYE = [0.02, -0.01, 0.004, -0.001]
OVERRIDES = [f"frames={FRAMES}", "camera.width=320", "camera.height=240", "camera.hfov_deg=80",
             "camera.distortion_model=equidistant", f"camera.distortion=[{', '.join(str(c) for c in FISHEYE)}]"]


@pytest.fixture(scope="module")
def tumvi(tmp_path_factory):
    from fgslam.io.synth import SynthSequence, write_tumvi_sequence
    from fgslam.io.synth.scenarios import load_synth_config

    seq = SynthSequence(load_synth_config("room-loop", overrides=OVERRIDES))
    root = tmp_path_factory.mktemp("tumvi") / "dataset-synthroom_512_16"
    write_tumvi_sequence(seq, root)
    return seq, root


def test_layout_is_detected_and_calibration_read_back(tumvi):
    seq, root = tumvi
    assert (root / "dso" / "camchain.yaml").is_file() and (root / "mav0" / "mocap0" / "data.csv").is_file()
    assert not (root / "mav0" / "cam0" / "sensor.yaml").exists()  # TUM-VI: the calibration is the camchain only
    assert detect_format(root) == "tumvi" and detect_format(root / "mav0") == "tumvi"
    ds = open_dataset(root, config=DatasetConfig(crop_multiple=1))
    raw = ds.raw_calibration
    assert ds.format == "tumvi" and ds.has_stereo and ds.has_imu and len(ds) == FRAMES
    assert raw.distortion_model == "equidistant" and np.allclose(raw.distortion, FISHEYE)
    assert np.allclose(raw.T_BC, seq.T_BS0, atol=1e-9)
    assert np.allclose(raw.T_CLCR, np.linalg.inv(seq.T_BS0) @ seq.T_BS1, atol=1e-9)
    assert ds.imu_noise["gyroscope_noise_density"] == pytest.approx(seq.cfg.imu.gyroscope_noise_density, rel=1e-5)
    assert np.allclose(ds.imu.gyro, seq.imu.gyro, atol=1e-9) and np.allclose(ds.imu.accel, seq.imu.accel, atol=1e-9)
    # ground truth (mocap T_WB) through T_BC: the output camera's pose at the frame times
    T_WC_true = seq.camera_poses(seq.frame_times())
    gt = ds.groundtruth
    assert gt is not None and len(gt.timestamps) == FRAMES
    # rectification rotates the output camera about its optical centre: the positions are the same
    assert np.allclose(gt.T_WC[:, :3, 3], T_WC_true[:, :3, 3], atol=1e-6)
    # the frames: rectified pinhole (no black fisheye border inside: alpha 0 keeps only valid pixels)
    frame = ds[0]
    assert frame.image.dtype == np.uint8 and frame.image_right is not None
    assert (frame.image == 0).mean() < 0.01


def test_rectified_pair_is_row_aligned(tumvi):
    """Fisheye undistortion and stereo rectification: ground-truth depth points project to the same row
    of both rectified images (checked through LK matches of the rectified pair)."""
    import cv2

    _, root = tumvi
    ds = open_dataset(root, config=DatasetConfig(crop_multiple=1))
    frame = ds[10]
    pts = cv2.goodFeaturesToTrack(frame.image, 200, 0.01, 8)
    right, status, _ = cv2.calcOpticalFlowPyrLK(frame.image, frame.image_right, pts, None)
    ok = status.ravel() == 1
    dv = (right - pts).reshape(-1, 2)[ok, 1]
    assert ok.sum() > 50
    assert np.median(np.abs(dv)) < 0.3  # pixels: the rows agree (unrectified fisheye pairs are off by several)


def test_missing_camchain_camera_is_a_clear_error(tumvi, tmp_path):
    import shutil

    _, root = tumvi
    clip = tmp_path / "dataset-broken_512_16"
    shutil.copytree(root / "dso", clip / "dso")
    (clip / "mav0" / "cam0").mkdir(parents=True)
    shutil.copy(root / "mav0" / "cam0" / "data.csv", clip / "mav0" / "cam0" / "data.csv")
    (clip / "dso" / "camchain.yaml").write_text("cam1: {}\n")
    with pytest.raises(DataError, match="missing camera 'cam0'"):
        open_dataset(clip)


def test_stereo_inertial_runs_on_the_tumvi_layout(tumvi, tmp_path):
    _, root = tumvi
    ds, summary, est = run_preset(root, "patch_stereo_inertial", tmp_path / "out", ["patch.graph.patches_per_frame=64"])
    assert summary.failures["tracking"] == 0 and summary.frames_with_pose == FRAMES
    assert summary.dataset["format"] == "tumvi" and summary.inertial["initialized"]
    assert summary.inertial["input_warnings"] == []  # the stream passes the IMU checks (units, axes, clock)
    res = evaluate_tum_rows(ds.groundtruth, est, "se3")
    assert_beats_doing_nothing(res.ate.rmse, ds.groundtruth, est[:, 0], "se3")
    assert res.ate.rmse < 0.01 * res.gt_path_length_m
