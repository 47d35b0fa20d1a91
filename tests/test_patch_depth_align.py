"""Depth alignment in the patch family's RGB-D tracking (``patch.depth_align``): a synthetic room whose
images carry no texture at all (every pixel the same grey) but whose depth is valid is tracked by the
depth alone, where the image-only frontend loses every frame. Doing nothing (a camera that stays where it
started) is the bar the run must clear by far. (That the depth blocks keep a textured run accurate is
checked on 7-Scenes by tests/test_sensor_presets.py: ``handheld_rgbd`` turns them on.)"""

from __future__ import annotations


from fgslam.backend import Backend, BackendConfig
from fgslam.frontends.patch import PatchFrontend
from depth_support import FRAMES, assert_beats_stationary, room_frames
from patch_support import light_patch_config


def _run(frames, depth_align: bool, prealign: bool = False):
    cfg = light_patch_config()
    cfg.depth_align.enabled = depth_align
    cfg.depth_align.prealign = prealign
    fe = PatchFrontend(cfg, sensor_mode="rgbd", backend=Backend(BackendConfig()))
    for frame in frames:
        fe.process(frame)
    fe.finish()
    return fe


def test_texture_free_room_is_tracked_by_depth_alone(depth_room):
    ds, frames = room_frames(depth_room, blank=True)
    image_only = _run(frames, depth_align=False)
    assert image_only.num_failures >= FRAMES // 2  # the failure this fixes: nothing to track in the images
    fe = _run(frames, depth_align=True)
    stamps, _, _ = fe.trajectory()
    assert len(stamps) == FRAMES and fe.num_failures == 0
    assert_beats_stationary(ds, fe, path_share=0.02, still_share=0.1)
