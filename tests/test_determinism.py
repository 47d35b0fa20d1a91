"""Reproducible runs (issue 21): the same config on the same data gives the same bytes, however fast
the background work is. Loop closure ``both`` on the 4 Hz room loop, RGB-D (classical corrections and
a proximity global BA are both applied): a threaded run and a threaded run whose workers are slowed
down on purpose write byte-identical trajectories and the same summary (times aside). The threaded
run is shared with tests/test_patch_loop.py (conftest.py: ``room_loop_rgbd_both``). (The
synchronous mode, ``run_in_thread: false``, takes the results at the same frames and gives the same
bytes too: tests/test_loop_closure.py compares the closer's two modes.)"""

from __future__ import annotations

import json
import time

import pytest

from fgslam.loop.closure import LoopCloser
from fgslam.services.proximity import ProximityLoops
from fgslam.io.run_files import SUMMARY_FILE
from fgslam.run.prepare import open_slam_dataset
from fgslam.run.runner import run_slam
from eval_support import timeless
from patch_support import room_loop_slam_config

RATE_HZ = 4.0
EXTRA_FRAMES = 19  # frames past the first return to the start
CLOSER_DELAY_S = 0.1  # injected: each job of the classical closer's worker starts this late (a frame takes about as long)
GLOBAL_BA_DELAY_S = 2.0  # injected: each global BA starts this late
TRAJECTORIES = ("trajectory_tum.txt", "trajectory_kitti.txt")


@pytest.fixture(scope="module")
def room(room_loop_clip):
    return room_loop_clip(RATE_HZ, EXTRA_FRAMES)[0]  # rendered once per session (conftest.py)


def _outputs(folder):
    summary = json.loads((folder / SUMMARY_FILE).read_text())
    return {name: (folder / name).read_bytes() for name in TRAJECTORIES}, summary


def _run(root, folder, threaded: bool):
    cfg = room_loop_slam_config("both", sensor="rgbd", threaded=threaded)  # the config of room_loop_rgbd_both
    run_slam(open_slam_dataset(root, cfg), cfg, folder, progress=False)
    return _outputs(folder)


@pytest.fixture(scope="module")
def runs(room, room_loop_rgbd_both, tmp_path_factory, request):
    out = {"threaded": _outputs(room_loop_rgbd_both[0])}
    mp = pytest.MonkeyPatch()
    run_job, solve = LoopCloser._run_job, ProximityLoops._solve

    def slow_job(self, job):
        time.sleep(CLOSER_DELAY_S)
        run_job(self, job)

    def slow_solve(self, run):
        time.sleep(GLOBAL_BA_DELAY_S)
        solve(self, run)

    mp.setattr(LoopCloser, "_run_job", slow_job)
    mp.setattr(ProximityLoops, "_solve", slow_solve)
    try:
        out["slowed"] = _run(room, tmp_path_factory.mktemp("det_slowed"), True)
    finally:
        mp.undo()
    return out


def test_the_loops_of_the_clip_are_closed(runs):
    """The comparison means something: both kinds of background result reach the estimate."""
    loop = runs["threaded"][1]["loop"]
    assert loop["mode"] == "both"
    assert loop["corrections_applied"] >= 1
    assert loop["proximity"]["global_ba_runs"] >= 1


def test_a_slowed_worker_gives_the_same_bytes(runs):
    fast, slow = runs["threaded"], runs["slowed"]
    for name in TRAJECTORIES:
        assert fast[0][name] == slow[0][name], name
    assert timeless(fast[1]) == timeless(slow[1])
