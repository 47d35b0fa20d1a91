"""A recommended preset's figure must not jump when the images change by a decoder's rounding.

The texture-poor panel room (``fgslam synth --preset panel-room``) once did: its first frames have
almost no image measurements, the depth holds them along a direction it barely constrains, and a few
wrong Lucas-Kanade locks entering the window at full weight pulled them along it in one LM step.
Decoding the same colour PNGs straight to grey (libpng's conversion, one grey level off OpenCV's on
about 40 % of the pixels) moved ``handheld_rgbd``'s 40-frame ATE from 0.040 to 0.099 m (0.096 to 0.581 m
over the whole room). With fresh tracks Huber-weighted by their distance from the prediction
(``patch.ba.measured_huber``) the same inputs give 0.040-0.042 m (docs/benchmarks/stability.md)."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from eval_support import assert_beats_doing_nothing
from tool_support import load_tool

from fgslam.io.run_files import SUMMARY_FILE

FRAMES = 40
PANEL = ["camera.width=320", "camera.height=240", f"frames={FRAMES}"]  # the class benchmark's clip, its first 40 frames
MAX_RATIO = 1.25  # the stability target of a recommended preset (docs/benchmarks/stability.md); measured 1.04
FLIP_SHARE = 0.4  # pixel values moved by one grey level in the seeded variant (the decoders differ on about 40 %)


def _copy_with(src: Path, dst: Path, change) -> Path:
    """The sequence at ``src`` with every cam0 image replaced by ``change(path)`` (a uint8 image)."""
    shutil.copytree(src, dst)
    for f in sorted((dst / "mav0" / "cam0" / "data").glob("*.png")):
        assert cv2.imwrite(str(f), change(f))
    return dst


def _grey_decoded(f: Path) -> np.ndarray:
    g = cv2.imread(str(f), cv2.IMREAD_GRAYSCALE)  # libpng's colour-to-grey, not OpenCV's cvtColor
    return cv2.merge([g, g, g])


@pytest.fixture(scope="module")
def panel_rooms(tmp_path_factory) -> dict[str, Path]:
    from fgslam.io.synth import SynthSequence, write_sequence
    from fgslam.io.synth.scenarios import load_synth_config

    base = tmp_path_factory.mktemp("panel_room")
    root = base / "as_rendered"
    write_sequence(SynthSequence(load_synth_config("panel-room", None, PANEL)), root)
    return {"as rendered": root,
            "decoded to grey": _copy_with(root, base / "grey", _grey_decoded),
            "one level on 40 %": load_tool("bench_stability").pixels_copy(root, base / "flips", share=FLIP_SHARE)}


def _ate(root: Path, out: Path) -> float:
    from fgslam.run.config import load_slam_config
    from fgslam.run.prepare import open_slam_dataset
    from fgslam.run.runner import run_slam

    config = load_slam_config("handheld_rgbd", ["output.plot=false", "output.write_map=false"])
    dataset = open_slam_dataset(root, config)
    run_slam(dataset, config, out, progress=False)
    summary = json.loads((out / SUMMARY_FILE).read_text())
    assert summary["frames_with_pose"] == FRAMES, summary["failures"]
    ate = summary["evaluation"]["ate"]["rmse"]
    assert_beats_doing_nothing(ate, dataset.groundtruth, dataset.timestamps, "se3")
    return ate


def test_handheld_rgbd_on_the_panel_room_does_not_move_with_a_grey_level(panel_rooms, tmp_path):
    ates = {name: _ate(root, tmp_path / name.replace(" ", "_")) for name, root in panel_rooms.items()}
    assert max(ates.values()) / min(ates.values()) <= MAX_RATIO, ates
