"""Visual-inertial runs of the dense and pointmap families (issue 26; the patch family's are in
test_imu_runs.py) on the synthetic room loop with simulated IMU: stereo-inertial with a stretch of black
frames bridged by the IMU prediction (the families' motion-prior hook), and (dense) monocular-inertial
initialisation with the metric rescale through the family's ``apply_correction``."""

import shutil

import numpy as np
import pytest

pytest.importorskip("gtsam")


from eval_support import assert_beats_doing_nothing, evaluate_tum_rows, run_preset
from patch_support import render_room

FRAMES = 120
BLACK = range(60, 80)  # 20 frames at 20 Hz: 1 s without an image
FAMILIES = ("dense", "pointmap")
FAST = {"pointmap": ["pointmap.image_width=160"]}  # the suite's time: half the matching work


@pytest.fixture(scope="module")
def room(tmp_path_factory):
    return render_room(tmp_path_factory, "room_imu", [f"frames={FRAMES}", "camera.width=320", "camera.height=240"])


@pytest.fixture(scope="module")
def black_room(room, tmp_path_factory):
    import cv2

    clip = tmp_path_factory.mktemp("room_imu_black") / "clip"
    shutil.copytree(room, clip)
    for cam in ("cam0", "cam1"):
        names = sorted((clip / "mav0" / cam / "data").iterdir())
        for k in BLACK:
            img = cv2.imread(str(names[k]), cv2.IMREAD_UNCHANGED)
            cv2.imwrite(str(names[k]), np.zeros_like(img))
    return clip


@pytest.mark.parametrize("family", FAMILIES)
def test_stereo_inertial_bridges_black_frames(family, black_room, tmp_path):
    ds, summary, est = run_preset(black_room, f"{family}_stereo_inertial", tmp_path / "vi", FAST.get(family, ()))
    inertial = summary.inertial
    assert inertial["initialized"] and inertial["links"] > 0 and abs(inertial["gravity_norm"] - 9.81) < 1e-6
    assert inertial["bias_gyro_norm"] is not None and inertial["init_after_s"] < 2.0
    # the black frames: posed by the IMU prediction, no tracking failure, no map restart
    assert summary.failures["tracking"] == 0 and summary.frames_with_pose == FRAMES
    assert summary.pose_sources.get("imu", 0) >= len(BLACK) - 2
    res = evaluate_tum_rows(ds.groundtruth, est, "se3")
    assert_beats_doing_nothing(res.ate.rmse, ds.groundtruth, est[:, 0], "se3")
    assert res.ate.rmse < 0.01 * res.gt_path_length_m  # the gap included
    steps = np.linalg.norm(np.diff(est[:, 1:4], axis=0), axis=1)
    steps_gt = np.linalg.norm(np.diff(ds.groundtruth.T_WC[:, :3, 3], axis=0), axis=1)
    assert abs(steps[BLACK[-1]] - steps_gt[BLACK[-1]]) < 0.05  # no jump where the images come back


# pointmap: its monocular two-view map of the room loop is too noisy (2.5 % of the path Sim(3)-aligned,
# 400 frames) for the linear initialisation's gates: it does not initialise there (README, issue 26)
@pytest.mark.parametrize("family", ["dense"])
def test_mono_inertial_initialises_and_rescales_to_metric(family, room, tmp_path):
    ds, summary, est = run_preset(room, f"{family}_mono_inertial", tmp_path / "mono",
                            ["imu.init.min_duration_s=2.0", "imu.init.max_scale_rel_sigma=0.1"])
    inertial = summary.inertial
    assert inertial["initialized"] and inertial["scale"] is not None
    sim = evaluate_tum_rows(ds.groundtruth, est, "sim3")  # the scale the map still needs after the rescale: 1 when metric
    assert abs(sim.alignment.s - 1.0) < 0.25
    assert_beats_doing_nothing(evaluate_tum_rows(ds.groundtruth, est, "se3").ate.rmse, ds.groundtruth, est[:, 0], "se3")
