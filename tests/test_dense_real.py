"""The dense frontend on short slices of the shared real sequences, with the dense presets (half
resolution for 7-Scenes and EuRoC).

Bounds are the issue's targets for the full sequences applied to the slices: 7-Scenes RGB-D SE(3)
ATE <= 0.04 m and monocular Sim(3) ATE <= 0.04 m, EuRoC static clip stereo: <= 0.01 m of estimated
motion; KITTI's start: see its test. On the 60-frame 7-Scenes slices a stationary estimate scores
0.079 m, so the slices also have bounds of their own, measured with a 2.5x margin (RGB-D 0.0057 m,
monocular 0.0112 m), and every estimate must beat doing nothing (tests/eval_support.py). A frontend that
never moves passes the static EuRoC clip: the same frontend on a moving stereo clip must beat doing
nothing in tests/test_dense_frontend.py::test_room_loop_accuracy_and_keyframe_depth.
"""

from __future__ import annotations

import numpy as np

from fgslam.eval.trajectory import EvalConfig, evaluate
from fgslam.io.trajectory import Trajectory
from fgslam.run.config import load_slam_config
from fgslam.run.prepare import open_slam_dataset
from fgslam.run.system import SlamSystem, run_frames
from eval_support import assert_beats_doing_nothing

RGBD_SLICE_M = 0.015  # SE(3) ATE bound of the 60-frame RGB-D slice (measured 0.0057 m)
MONO_SLICE_M = 0.025  # Sim(3) ATE bound of the 60-frame monocular slice (measured 0.0112 m)


def run(path, preset, end):
    config = load_slam_config(preset, ["dataset.load_rgb=false"] + ([f"dataset.end={end}"] if end else []))
    ds = open_slam_dataset(path, config)
    system = SlamSystem.build(config, ds.calibration)
    statuses = run_frames(system, ds)
    return ds, system.frontend, statuses


def ate(ds, fe, align):
    stamps, poses, _ = fe.trajectory()
    return evaluate(ds.groundtruth, Trajectory(stamps, poses), EvalConfig(align=align)), len(stamps)


def test_sevenscenes_rgbd_slice(shared_data):
    ds, fe, statuses = run(shared_data / "7scenes_redkitchen_0-599", "dense_7scenes_rgbd", 60)
    res, n = ate(ds, fe, "se3")
    assert fe.num_failures == 0 and n == 60
    assert res.ate.rmse <= 0.04, res.ate.rmse
    assert res.ate.rmse <= RGBD_SLICE_M, res.ate.rmse
    assert_beats_doing_nothing(res.ate.rmse, ds.groundtruth, fe.trajectory()[0], "se3")
    depths = fe.keyframe_depths()
    assert depths and all(d.shape == (240, 320) for _, d, _ in depths.values())


def test_sevenscenes_mono_slice(shared_data):
    ds, fe, statuses = run(shared_data / "7scenes_redkitchen_0-599", "dense_7scenes_mono", 60)
    res, n = ate(ds, fe, "sim3")
    assert fe.num_failures == 0 and n == 60
    assert res.ate.rmse <= 0.04, res.ate.rmse
    assert res.ate.rmse <= MONO_SLICE_M, res.ate.rmse
    assert_beats_doing_nothing(res.ate.rmse, ds.groundtruth, fe.trajectory()[0], "sim3")


def test_kitti_mono_slice_tracks_the_drive(shared_data):
    """The first 30 frames (26 m) of KITTI 00: every frame posed without failure. Not the 1 % target:
    the monocular scale drifts over this start (measured 4.2 % of the path, a bow-shaped error; the
    full 200 frames reach the target, see tools/bench_dense_run.py), so the bound is 5 %."""
    ds, fe, statuses = run(shared_data / "kitti00_0-199", "dense_kitti_mono", 30)
    res, n = ate(ds, fe, "sim3")
    assert fe.num_failures == 0 and n == 30
    assert_beats_doing_nothing(res.ate.rmse, ds.groundtruth, fe.trajectory()[0], "sim3")  # 0.19 m against 7.6 m
    assert res.ate.rmse <= 0.05 * res.gt_path_length_m, (res.ate.rmse, res.gt_path_length_m)


def test_euroc_static_stereo(shared_data):
    ds, fe, statuses = run(shared_data / "euroc_v101_micro", "dense_euroc_stereo", None)
    stamps, poses, _ = fe.trajectory()
    assert len(stamps) == len(statuses) and fe.num_failures == 0
    motion = np.linalg.norm(poses[:, :3, 3] - poses[0, :3, 3], axis=1).max()
    assert motion <= 0.01, motion
    assert fe.num_keyframes() <= 3  # the motion filter keeps a still camera out of the graph
