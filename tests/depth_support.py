"""Shared pieces of the depth-alignment tests of the three families (tests/test_*_depth_align.py): the
synthetic room clip they share, its frames with the images blanked to one grey, and the ATE of a run next
to that of a camera that never moves."""

from __future__ import annotations

import dataclasses

import numpy as np

from fgslam.eval.trajectory import EvalConfig, evaluate
from fgslam.io.trajectory import Trajectory
from patch_support import render_room

FRAMES = 48
GREY = 128
#: the room-loop clip of tests/test_patch_rgbd.py (render_room renders it once per session)
ROOM_OVERRIDES = [f"frames={FRAMES}", "camera.width=320", "camera.height=240"]


def render_depth_room(tmp_path_factory):
    """Root of the shared RGB-D room clip (the ``depth_room`` fixture of tests/conftest.py)."""
    return render_room(tmp_path_factory, "room", ROOM_OVERRIDES)


def room_frames(root, blank: bool):
    """The clip opened for RGB-D and its frames; with ``blank`` every image one grey (no texture at
    all, the depth unchanged)."""
    from fgslam.io.datasets import DatasetConfig, open_dataset

    ds = open_dataset(root, config=DatasetConfig(load_right=False, load_depth=True, load_imu=False))
    frames = list(ds)
    if blank:
        frames = [dataclasses.replace(f, image=np.full_like(f.image, GREY), rgb=None) for f in frames]
    return ds, frames


def ate_against_stationary(ds, fe) -> tuple[float, float, float]:
    """(ATE of the frontend's run, ATE of a camera that never moves over the same frames, path length),
    SE(3)-aligned."""
    stamps, poses, _ = fe.trajectory()
    gt = ds.groundtruth
    res = evaluate(gt, Trajectory(stamps, poses), EvalConfig(align="se3"))
    still = np.repeat(gt.T_WC[:1], len(stamps), axis=0)
    res_still = evaluate(gt, Trajectory(np.asarray(stamps), still), EvalConfig(align="se3"))
    return res.ate.rmse, res_still.ate.rmse, res.gt_path_length_m


def assert_beats_stationary(ds, fe, path_share: float, still_share: float) -> float:
    """The frontend's ATE is at most ``path_share`` of the path and ``still_share`` of a never-moving
    camera's; returns it."""
    ate, ate_still, path = ate_against_stationary(ds, fe)
    assert ate <= path_share * path, f"ATE {ate:.4f} m on a {path:.2f} m path"
    assert ate <= still_share * ate_still, f"ATE {ate:.4f} m against {ate_still:.4f} m for a camera that never moves"
    return ate
