"""Patch frontend bad input: blank frames (tracking lost, motion-model poses, counted failures,
recovery), a static camera (monocular never initialises), a sequence too short to initialise."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from fgslam.eval.trajectory import EvalConfig, evaluate
from fgslam.frontends.patch import PatchFrontend
from fgslam.io.trajectory import Trajectory
from fgslam.backend import Backend, BackendConfig
from patch_support import light_patch_config, open_frames, render_room

FRAMES = 40


@pytest.fixture(scope="module")
def room(tmp_path_factory):
    return render_room(tmp_path_factory, "room_fail", [f"frames={FRAMES}", "camera.width=200", "camera.height=150", "seed=3"])


@pytest.mark.parametrize("mode", ["rgbd", "mono"])
def test_blank_frames_use_motion_model_and_recover(room, mode):
    ds, frames = open_frames(room, mode)
    blank = set(range(22, 25))
    fed = [dataclasses.replace(f, image=np.full_like(f.image, 90)) if f.index in blank else f for f in frames]
    fe = PatchFrontend(light_patch_config(keyframe_threshold=6.0), sensor_mode=mode, backend=Backend(BackendConfig()))
    statuses = [fe.process(f) for f in fed]
    for s in statuses:
        if s.index in blank:
            assert s.pose_source == "motion_model" and s.T_WC is not None
            assert any("tracking lost" in e for e in s.events)
    assert fe.num_failures == len(blank)
    assert all(s.pose_source == "tracked" for s in statuses[26:])  # recovered
    stamps, poses, sources = fe.trajectory()
    assert sources.count("motion_model") == len(blank)
    res = evaluate(ds.groundtruth, Trajectory(stamps, poses), EvalConfig(align="se3" if mode == "rgbd" else "sim3"))
    assert res.ate.rmse < 0.02 * res.gt_path_length_m


def test_static_camera_never_initialises_mono(room):
    _, frames = open_frames(room, "mono")
    rng = np.random.default_rng(0)
    still = [
        dataclasses.replace(frames[0], index=i, timestamp=frames[0].timestamp + 0.05 * i,
                            image=np.clip(frames[0].image + rng.normal(0, 1.0, frames[0].image.shape), 0, 255).astype(np.uint8))
        for i in range(25)
    ]
    fe = PatchFrontend(light_patch_config(keyframe_threshold=6.0), sensor_mode="mono", backend=Backend(BackendConfig()))
    statuses = [fe.process(f) for f in still]
    assert all(s.pose_source == "initializing" and s.T_WC is None for s in statuses)
    assert fe.trajectory()[1].shape == (0, 4, 4)
    assert fe.num_keyframes() == 0
    # the same static input in stereo gives a pose per frame with (almost) no motion
    _, sframes = open_frames(room, "stereo")
    fe_s = PatchFrontend(light_patch_config(keyframe_threshold=6.0), sensor_mode="stereo", backend=Backend(BackendConfig()))
    for i in range(15):
        fe_s.process(dataclasses.replace(sframes[0], index=i, timestamp=sframes[0].timestamp + 0.05 * i))
    _, poses, _ = fe_s.trajectory()
    assert poses.shape[0] == 15
    assert np.linalg.norm(poses[:, :3, 3] - poses[0, :3, 3], axis=1).max() < 1e-3


def test_too_short_sequence_reports_no_poses(room):
    _, frames = open_frames(room, "mono")
    fe = PatchFrontend(light_patch_config(keyframe_threshold=6.0), sensor_mode="mono", backend=Backend(BackendConfig()))
    statuses = [fe.process(f) for f in frames[:2]]
    assert [s.pose_source for s in statuses] == ["initializing", "initializing"]
    stamps, poses, sources = fe.trajectory()
    assert stamps.size == 0 and sources == []


def test_long_loss_reinitialises_without_crash(room):
    ds, frames = open_frames(room, "rgbd")
    blank = set(range(15, 21))
    fed = [dataclasses.replace(f, image=np.full_like(f.image, 90)) if f.index in blank else f for f in frames]
    cfg = light_patch_config(keyframe_threshold=6.0)
    cfg.tracking.max_motion_model_frames = 2
    fe = PatchFrontend(cfg, sensor_mode="rgbd", backend=Backend(BackendConfig()))
    statuses = [fe.process(f) for f in fed]
    assert any("re-initialising" in e for s in statuses for e in s.events)
    assert [s.index for s in statuses if s.new_map] == [s.index for s in statuses if "re-initialising" in s.events]
    assert fe.num_failures >= 3
    assert all(s.pose_source == "tracked" for s in statuses[22:])  # a new map continues the trajectory
    stamps, poses, _ = fe.trajectory()
    assert np.isfinite(poses).all() and len(stamps) >= len(frames) - len(blank)
