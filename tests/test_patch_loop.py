"""Classical loop closure inside the patch frontend (fgslam.loop.closure through PatchFrontend and the
runner): a synthetic room-loop clip that goes once round the room and on past its start, run with
loop closure on (synchronous closer, deterministic) and off.

The clip is rendered at 4 Hz so that one loop (20 s) is 81 frames and the file stays fast; the
default 20 Hz would give the same revisit after 401 frames.
"""

from __future__ import annotations

import json
import threading
from pathlib import Path

import numpy as np
import pytest

from fgslam.errors import ConfigError
from fgslam.frontends import make_frontend
from fgslam.frontends.patch import PatchFrontend
from fgslam.loop.closure import LoopClosureConfig
from fgslam.presets import config_class_for, load_preset_file
from fgslam.slam import SUMMARY_FILE, SlamConfig, load_slam_config, open_slam_dataset, run_slam
from patch_support import light_patch_config

RATE_HZ = 4.0
EXTRA_FRAMES = 19  # frames past the first return to the start (about 20 % of the loop)
REVISIT_M = 0.6  # an accepted loop joins frames whose true positions are at most this far apart
MIN_GAP_S = 10.0  # ... and at least this far apart in time (half the loop)


@pytest.fixture(scope="module")
def room(tmp_path_factory):
    from fgslam.io.synth import SynthSequence, write_sequence
    from fgslam.io.synth.presets import load_synth_config

    cfg = load_synth_config("room-loop", overrides=[f"camera.rate_hz={RATE_HZ}", "camera.width=320",
                                                    "camera.height=240"])
    cfg.frames = int(round(cfg.loop_duration_s() * RATE_HZ)) + 1 + EXTRA_FRAMES
    seq = SynthSequence(cfg)
    root = tmp_path_factory.mktemp("room_loop") / "seq"
    write_sequence(seq, root)
    return root, seq


def slam_config(mode: str) -> SlamConfig:
    cfg = SlamConfig(sensor="mono", patch=light_patch_config())
    cfg.loop_closure = LoopClosureConfig(mode=mode, run_in_thread=False)
    cfg.output.plot = False
    cfg.validate()
    return cfg


@pytest.fixture(scope="module")
def runs(room, tmp_path_factory):
    """summary.json of the runner with loop closure classical and off."""
    root, _ = room
    out = {}
    for mode in ("classical", "off"):
        cfg = slam_config(mode)
        folder = tmp_path_factory.mktemp(f"run_{mode}")
        run_slam(open_slam_dataset(root, cfg), cfg, folder, progress=False)
        out[mode] = json.loads((folder / SUMMARY_FILE).read_text())
    return out


def test_loop_closed_at_the_return_and_ate_not_worse(room, runs):
    _, seq = room
    on, off = runs["classical"], runs["off"]
    loop = on["loop"]
    assert loop is not None and loop["mode"] == "classical"
    assert loop["accepted_loops"] > 0 and loop["corrections_applied"] > 0
    assert on["stage_s"]["loop"] > 0
    # every accepted loop joins the return to the start of the drive, nowhere else
    T = seq.camera_poses(np.arange(seq.cfg.frames) / RATE_HZ)
    accepted = [(q, c) for q, c, status in loop["loop_frames"] if status == "accepted"]
    assert accepted
    for q, c in accepted:
        assert (q - c) / RATE_HZ >= MIN_GAP_S, (q, c)
        assert np.linalg.norm(T[q][:3, 3] - T[c][:3, 3]) <= REVISIT_M, (q, c)
    ate_on, ate_off = on["evaluation"]["ate"]["rmse"], off["evaluation"]["ate"]["rmse"]
    assert on["frames_with_pose"] >= off["frames_with_pose"] - 1
    assert ate_on <= ate_off, f"ATE with loop closure {ate_on:.4f} m > without {ate_off:.4f} m"


def test_runner_summary_loop_counts(runs):
    on, off = runs["classical"], runs["off"]
    loop = on["loop"]
    for key in ("corrections_applied", "keyframes_added", "verified_loops", "accepted_loops", "verifications",
                "relocalization_attempts", "relocalized"):
        assert isinstance(loop[key], int) and loop[key] >= 0, key
    assert loop["keyframes_added"] > 0 and loop["verified_loops"] >= loop["accepted_loops"]
    assert set(loop["closer_s"]) >= {"describe", "detect", "verify", "pose_graph"}
    assert on["config"]["loop_closure"]["mode"] == "classical"
    assert off["loop"] is None and "loop" not in off["stage_s"]
    assert off["config"]["loop_closure"]["mode"] == "off"


def _closer_threads() -> int:
    return sum(t.name == "fgslam-loop-closer" for t in threading.enumerate())


def test_mode_off_creates_no_closer(room):
    before = _closer_threads()
    assert PatchFrontend(light_patch_config()).closer is None  # no loop config: off
    fe = PatchFrontend(light_patch_config(), loop_config=LoopClosureConfig(mode="off"))
    assert fe.closer is None and fe.loop_summary() is None and "loop" not in fe.stage_times()
    assert _closer_threads() == before
    fe = PatchFrontend(light_patch_config(), loop_config=LoopClosureConfig(mode="classical", run_in_thread=True))
    assert fe.closer is not None and _closer_threads() == before + 1
    fe.finish()  # stops the worker
    assert _closer_threads() == before


def test_registry_and_presets_pass_the_loop_config(room):
    root, _ = room
    cfg = slam_config("classical")
    ds = open_slam_dataset(root, cfg)
    fe = make_frontend("patch", cfg, ds.calibration, "mono")
    assert fe.closer is not None and fe.loop_config is cfg.loop_closure
    assert make_frontend("patch", SlamConfig(), ds.calibration, "mono").closer is None  # default: off
    assert load_preset_file("patch_street_loop").loop_closure.mode == "classical"
    assert load_preset_file("patch_mono").loop_closure.mode == "off"
    assert config_class_for(Path("loop_street.yaml")) is LoopClosureConfig  # loop_*.yaml presets


@pytest.mark.parametrize("override", ["loop_closure.mode=sometimes", "loop_closure.mode=true",
                                      "loop_closure.bogus=1", "loop_closure.max_candidates=0"])
def test_bad_loop_config_is_rejected(override):
    with pytest.raises(ConfigError, match="loop_closure"):
        load_slam_config(None, [override])


def test_bare_yaml_off_selects_mode_off():
    # YAML 1.1 reads a bare off as false; the config loader maps it back to the "off" option
    assert load_slam_config("patch_street_loop", ["loop_closure.mode=off"]).loop_closure.mode == "off"


def test_bad_mode_in_the_frontend():
    with pytest.raises(ConfigError, match="mode"):
        PatchFrontend(light_patch_config(), loop_config=LoopClosureConfig(mode="sometimes"))
    with pytest.raises(ConfigError, match="proximity"):
        PatchFrontend(light_patch_config(), loop_config=LoopClosureConfig(mode="proximity"))


def test_relocalisation_after_a_jump_back(room):
    """Frames 0..FIRST_PASS-1, then the camera jumps back to frame JUMP_TO and goes on from there:
    tracking fails, and after ``max_motion_model_frames`` failures the lost frame is relocalised on
    the keyframes of the first pass, close to the pose estimated for the same view then."""
    from fgslam.io.calibration import Calibration
    from fgslam.io.frame import Frame

    first_pass, jump_to, after = 26, 6, 6
    _, seq = room
    cal = Calibration(seq.cfg.camera.width, seq.cfg.camera.height, np.array(seq.K))
    order = list(range(first_pass)) + list(range(jump_to, jump_to + after))
    T_gt = seq.camera_poses(np.array(order) / RATE_HZ)
    cfg = light_patch_config()
    cfg.tracking.max_motion_model_frames = 2
    fe = PatchFrontend(cfg, cal, "mono", loop_config=LoopClosureConfig(mode="classical", run_in_thread=False))
    statuses = []
    for i in range(len(order)):
        image = np.clip(seq.render_view(T_gt[i]).image, 0, 255).astype(np.uint8)
        statuses.append(fe.process(Frame(i, i, i / RATE_HZ, image, cal)))
    first_pass_T = {s.index: s.T_WC for s in statuses[:first_pass]}
    fe.finish()
    summary = fe.loop_summary()
    assert summary["relocalization_attempts"] >= 1 and summary["relocalized"] == 1
    reloc = [s for s in statuses if s.pose_source == "relocalized"]
    assert len(reloc) == 1 and "relocalised" in reloc[0].events
    same_view = order[reloc[0].index]  # the first-pass frame with the same true pose
    path = sum(np.linalg.norm(first_pass_T[k + 1][:3, 3] - first_pass_T[k][:3, 3])
               for k in range(first_pass - 1) if first_pass_T[k] is not None)
    err = np.linalg.norm(reloc[0].T_WC[:3, 3] - first_pass_T[same_view][:3, 3])
    assert err <= 0.01 * path, f"relocalised {err:.3f} from the first-pass pose (path {path:.3f})"
