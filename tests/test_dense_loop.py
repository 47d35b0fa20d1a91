"""The shared loop-closure service with the dense frontend as its contributor: the synthetic room
loop at 4 Hz past its return to the start (monocular, classical retrieval + Sim(3) pose graph)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from fgslam.eval.trajectory import EvalConfig, evaluate
from fgslam.io.trajectory import read_trajectory
from fgslam.io.run_files import SUMMARY_FILE, TUM_FILE
from fgslam.run.config import load_slam_config
from fgslam.run.prepare import open_slam_dataset
from fgslam.run.runner import run_slam
from eval_support import assert_beats_doing_nothing

RATE_HZ = 4.0
EXTRA_FRAMES = 19  # frames past the first return to the start
REVISIT_M = 0.6  # an accepted loop joins frames whose true positions are at most this far apart
MIN_GAP_S = 10.0
# Loops do not help this clip (the final global optimisation closes the loop too), and at the return they
# can hurt. Measured under 1-ppm focal changes and another CPU's kernels (tools/bench_stability.py's
# perturbations), ATE with loops / without: 0.012175 / 0.011964, 0.012004 / 0.012121, 0.012018 / 0.012199,
# 0.012175 / 0.011964 m (ratios 0.985-1.018; each run's own spread 1.4-2.0 %); RMS error over the frames
# from the return: 0.01489 / 0.01223, 0.01232 / 0.01236, 0.01276 / 0.01237, 0.01489 / 0.01223 m (ratios
# 0.996-1.217: in two of the four the loop correction leaves the return 22 % worse). What the loops reliably
# do is close at the return and stay within those ratios of the loop-less run, with margins of 2.5 times
# the ATE spread and 7 % over the worst return ratio.
ATE_TOLERANCE = 1.05  # the loop run's ATE may exceed the loop-less run's by this factor
RETURN_TOLERANCE = 1.3  # the loop run's error at the return may exceed the loop-less run's by this factor


@pytest.fixture(scope="module")
def room(room_loop_clip):
    return room_loop_clip(RATE_HZ, EXTRA_FRAMES)  # (root, seq), rendered once per session (conftest.py)


def _run(root, out, overrides):
    config = load_slam_config("dense_mono", ["loop_closure.run_in_thread=false", "output.plot=false", *overrides])
    dataset = open_slam_dataset(root, config)
    run_slam(dataset, config, out, progress=False)
    return dataset, json.loads((out / SUMMARY_FILE).read_text())


def _errors(dataset, out):
    """(ATE RMSE, RMS position error over the frames from the return to the start on) of a run's
    trajectory, after the Sim(3) alignment of the whole trajectory."""
    res = evaluate(dataset.groundtruth, read_trajectory(out / TUM_FILE, "tum"), EvalConfig(align="sim3"))
    e = np.linalg.norm(res.aligned_est.t_WC - res.matched_gt.t_WC, axis=1)
    return float(res.ate.rmse), float(np.sqrt(np.mean(e[-(EXTRA_FRAMES + 1):] ** 2)))


@pytest.fixture(scope="module")
def loop_run(room, tmp_path_factory):
    out = tmp_path_factory.mktemp("dense_loop_on")
    dataset, summary = _run(room[0], out, ["loop_closure.mode=classical"])
    return dataset, summary, out


def test_classical_loops_close_at_the_return(room, loop_run):
    root, seq = room
    dataset, s, _ = loop_run
    loop = s["loop"]
    assert loop["mode"] == "classical" and loop["keyframes_added"] == s["keyframes"]
    assert loop["accepted_loops"] > 0 and loop["corrections_applied"] > 0
    T = seq.camera_poses(np.arange(seq.cfg.frames) / RATE_HZ)
    accepted = [(q, c) for q, c, status in loop["loop_frames"] if status == "accepted"]
    for q, c in accepted:  # every accepted loop joins the return to the start, nowhere else
        assert (q - c) / RATE_HZ >= MIN_GAP_S and np.linalg.norm(T[q][:3, 3] - T[c][:3, 3]) <= REVISIT_M, (q, c)
    assert s["frames_with_pose"] == seq.cfg.frames and s["failures"]["tracking"] == 0
    assert s["evaluation"]["ate"]["rmse"] <= 0.02
    assert_beats_doing_nothing(s["evaluation"]["ate"]["rmse"], dataset.groundtruth, dataset.groundtruth.timestamps, "sim3")


@pytest.mark.slow
def test_classical_loops_stay_within_the_loopless_run(room, loop_run, tmp_path):
    """The same clip with loop closure off (a second ~110 s run, hence slow). Loops do not help here and
    can leave the return worse (the comment above ATE_TOLERANCE: measured under perturbations): with its
    correction applied, the loop run stays within the measured ratios of the loop-less run overall and at
    the return."""
    dataset, s, out = loop_run
    _, s_off = _run(room[0], tmp_path, ["loop_closure.mode=off"])
    assert s["loop"]["corrections_applied"] > 0 and not (s_off.get("loop") or {}).get("corrections_applied")
    (ate_on, return_on), (ate_off, return_off) = _errors(dataset, out), _errors(dataset, tmp_path)
    assert ate_on <= ATE_TOLERANCE * ate_off, (ate_on, ate_off)
    assert return_on <= RETURN_TOLERANCE * return_off, (return_on, return_off)
