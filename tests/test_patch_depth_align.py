"""Depth alignment in the patch family's RGB-D tracking (``patch.depth_align``): a synthetic room whose
images carry no texture at all (every pixel the same grey) but whose depth is valid is tracked by the
depth alone, where the image-only frontend loses every frame. Doing nothing (a camera that stays where it
started) is the bar the run must clear by far. (That the depth blocks keep a textured run accurate is
checked on 7-Scenes by tests/test_sensor_presets.py: ``handheld_rgbd`` turns them on.)"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from fgslam.backend import Backend, BackendConfig
from fgslam.eval import EvalConfig, evaluate
from fgslam.frontends.patch import PatchFrontend
from fgslam.io.trajectory import Trajectory
from patch_support import light_patch_config, render_room

FRAMES = 48
GREY = 128


@pytest.fixture(scope="module")
def room(tmp_path_factory):
    # the clip of tests/test_patch_rgbd.py (rendered once per session)
    return render_room(tmp_path_factory, "room", [f"frames={FRAMES}", "camera.width=320", "camera.height=240"])


def _frames(root, blank: bool):
    from fgslam.io.datasets import DatasetConfig, open_dataset

    ds = open_dataset(root, config=DatasetConfig(load_right=False, load_depth=True, load_imu=False))
    frames = list(ds)
    if blank:
        frames = [dataclasses.replace(f, image=np.full_like(f.image, GREY), rgb=None) for f in frames]
    return ds, frames


def _run(frames, depth_align: bool, prealign: bool = False):
    cfg = light_patch_config()
    cfg.depth_align.enabled = depth_align
    cfg.depth_align.prealign = prealign
    fe = PatchFrontend(cfg, sensor_mode="rgbd", backend=Backend(BackendConfig()))
    for frame in frames:
        fe.process(frame)
    fe.finish()
    return fe


def _ate(ds, fe) -> tuple[float, float, float]:
    """(ATE of the run, ATE of a camera that never moves, path length), SE(3)-aligned."""
    stamps, poses, _ = fe.trajectory()
    gt = ds.groundtruth
    res = evaluate(gt, Trajectory(stamps, poses), EvalConfig(align="se3"))
    still = np.repeat(gt.T_WC[:1], len(gt), axis=0)
    res_still = evaluate(gt, Trajectory(gt.timestamps, still), EvalConfig(align="se3"))
    return res.ate.rmse, res_still.ate.rmse, res.gt_path_length_m


def test_texture_free_room_is_tracked_by_depth_alone(room):
    ds, frames = _frames(room, blank=True)
    image_only = _run(frames, depth_align=False)
    assert image_only.num_failures >= FRAMES // 2  # the failure this fixes: nothing to track in the images
    fe = _run(frames, depth_align=True)
    stamps, _, _ = fe.trajectory()
    assert len(stamps) == FRAMES and fe.num_failures == 0
    ate, ate_still, path = _ate(ds, fe)
    assert ate <= 0.02 * path, f"ATE {ate:.4f} m on a {path:.2f} m path"
    assert ate <= 0.1 * ate_still, f"ATE {ate:.4f} m against {ate_still:.4f} m for a camera that never moves"
