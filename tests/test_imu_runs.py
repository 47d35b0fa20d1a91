"""Visual-inertial runs of the patch frontend on moving synthetic data with simulated IMU
(fgslam/services/imu.py through the runner): stereo-inertial, a 2 s stretch of black frames bridged by
the IMU, monocular-inertial initialisation and metric rescale."""

import shutil

import numpy as np
import pytest

pytest.importorskip("gtsam")


from eval_support import BEAT_FACTOR, assert_beats_doing_nothing, evaluate_tum_rows, run_preset
from patch_support import render_room

FRAMES = 120
BLACK = range(50, 90)  # 40 frames at 20 Hz: 2 s


@pytest.fixture(scope="module")
def room(tmp_path_factory):
    return render_room(tmp_path_factory, "room_imu", [f"frames={FRAMES}", "camera.width=320", "camera.height=240"])


def _run(root, preset, out, overrides=()):
    return run_preset(root, preset, out, list(overrides) + ["patch.graph.patches_per_frame=64"])


def test_stereo_inertial_run_initialises_and_tracks(room, tmp_path):
    ds, summary, est = _run(room, "patch_stereo_inertial", tmp_path / "vi")
    assert summary.failures["tracking"] == 0 and summary.frames_with_pose == FRAMES
    res = evaluate_tum_rows(ds.groundtruth, est, "se3")
    assert res.ate.rmse < 0.005 * res.gt_path_length_m  # measured 0.16 % at 120 frames


def test_black_frames_are_bridged_by_the_imu(room, tmp_path):
    clip = tmp_path / "black"
    shutil.copytree(room, clip)
    import cv2

    for cam in ("cam0", "cam1"):
        names = sorted((clip / "mav0" / cam / "data").iterdir())
        for k in BLACK:
            img = cv2.imread(str(names[k]), cv2.IMREAD_UNCHANGED)
            cv2.imwrite(str(names[k]), np.zeros_like(img))
    ds, summary, est = _run(clip, "patch_stereo_inertial", tmp_path / "out")
    assert summary.failures["tracking"] == 0  # no motion-model pose, no re-initialisation
    assert summary.pose_sources.get("imu", 0) >= len(BLACK) - 2
    gt = ds.groundtruth
    P_gt = gt.T_WC[:, :3, 3]
    res = evaluate_tum_rows(ds.groundtruth, est, "se3")
    # no jump: the step across the end of the gap is as large as the true step (within IMU drift)
    steps = np.linalg.norm(np.diff(est[:, 1:4], axis=0), axis=1)
    steps_gt = np.linalg.norm(np.diff(P_gt, axis=0), axis=1)
    end = BLACK[-1]
    assert abs(steps[end] - steps_gt[end]) < 0.05
    assert res.ate.rmse < 0.05  # metres over the whole clip, the gap included


def test_mono_inertial_initialises_and_rescales_to_metric(room, tmp_path, caplog):
    import logging

    caplog.set_level(logging.INFO, logger="fgslam.services.imu")
    ds, summary, est = _run(room, "patch_mono_inertial", tmp_path / "mono",
                            ["imu.init.min_duration_s=2.0", "imu.init.max_scale_rel_sigma=0.1"])
    assert "initialised (visual-inertial)" in caplog.text
    res = evaluate_tum_rows(ds.groundtruth, est, "sim3")  # the scale the map needs after the rescale: 1 when metric
    vision = evaluate_tum_rows(ds.groundtruth, _run(room, "patch_mono", tmp_path / "v")[2], "sim3")
    # the rescale brings the map from its arbitrary scale (vision only: Sim(3) scale 0.11 here) to within
    # a factor 2.2 of metric (measured 2.15 on this 6 s clip: the linear initialisation underestimates the
    # scale with little acceleration, and the window BA does not correct it yet; README, IMU section)
    assert abs(np.log(vision.alignment.s)) > 1.5
    assert abs(np.log(res.alignment.s)) < 0.8
    # doing nothing (no rescale) leaves the vision-only scale error: the rescale must at least halve it
    # (measured: log scale error 2.18 -> 0.77), and the Sim(3) trajectory must beat a stationary one
    # (measured 0.0054 m against 0.60 m)
    assert abs(np.log(res.alignment.s)) < BEAT_FACTOR * abs(np.log(vision.alignment.s))
    assert_beats_doing_nothing(res.ate.rmse, ds.groundtruth, est[:, 0], "sim3")
