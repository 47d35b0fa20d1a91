"""The dense family's global optimisation in the background and its proximity loops (issue 24 item 2).

- Periodic global optimisations (``dense.global_ba.every``) are handed to the loop service's worker
  process (a service with loop closure off, inert but for them) and applied at a fixed safe point: a
  run whose worker is slowed down on purpose writes the same trajectory bytes and summary, and every
  result is taken exactly at its due safe point in both runs.
- Proximity loops on a there-and-back clip (the room loop's first frames, then the same frames
  backwards: the camera returns over its own path): loops are found between true revisits, their
  edges measured by the dense source, verified, closed by a global optimisation and kept; a far
  keyframe pair is rejected by the verification.
"""

from __future__ import annotations

import dataclasses
import json
import time

import numpy as np
import pytest

from fgslam.backend import Backend, BackendConfig
from fgslam.eval.trajectory import EvalConfig, evaluate
from fgslam.frontends.dense import DenseConfig, DenseFrontend
from fgslam.io.trajectory import Trajectory
from fgslam.loop.records import LoopClosureConfig
from fgslam.services.proximity import ProximityLoops
from fgslam.io.run_files import SUMMARY_FILE
from fgslam.run.config import load_slam_config
from fgslam.run.prepare import open_slam_dataset
from fgslam.run.runner import run_slam
from fgslam.run.system import SlamSystem
from eval_support import assert_beats_doing_nothing, timeless
from patch_support import open_frames, render_room

FRAMES = 26
GLOBAL_EVERY = 2  # keyframes between periodic global optimisations
DELAY_FRAMES = 3  # loop_closure.global_ba_delay_frames
SLOW_S = 1.5  # injected: each background solve starts this late (several frames' time)
TRAJECTORIES = ("trajectory_tum.txt", "trajectory_kitti.txt")


@pytest.fixture(scope="module")
def room(tmp_path_factory):
    return render_room(tmp_path_factory, "dense_room", [f"frames={FRAMES}", "camera.width=320", "camera.height=240"])


def _run(root, folder, applied: list):
    cfg = load_slam_config("dense_rgbd", ["output.plot=false", f"dense.global_ba.every={GLOBAL_EVERY}",
                                          f"loop_closure.global_ba_delay_frames={DELAY_FRAMES}",
                                          "dense.global_ba.delay_frames_per_keyframe=0.5"])
    assert cfg.loop_closure.mode == "off" and cfg.loop_closure.run_in_thread
    finish = ProximityLoops._finish_global_ba

    def recorded(self, run):
        applied.append((self._tick, run.due_tick))
        return finish(self, run)

    mp = pytest.MonkeyPatch()
    mp.setattr(ProximityLoops, "_finish_global_ba", recorded)
    try:
        run_slam(open_slam_dataset(root, cfg), cfg, folder, progress=False)
    finally:
        mp.undo()
    summary = json.loads((folder / SUMMARY_FILE).read_text())
    return {name: (folder / name).read_bytes() for name in TRAJECTORIES}, summary


@pytest.fixture(scope="module")
def runs(room, tmp_path_factory):
    out = {"fast": _run(room, tmp_path_factory.mktemp("dense_bg_fast"), applied := []) + (applied,)}
    solve = ProximityLoops._solve

    def slow_solve(self, run):
        time.sleep(SLOW_S)
        solve(self, run)

    mp = pytest.MonkeyPatch()
    mp.setattr(ProximityLoops, "_solve", slow_solve)
    try:
        out["slow"] = _run(room, tmp_path_factory.mktemp("dense_bg_slow"), applied := []) + (applied,)
    finally:
        mp.undo()
    return out


def test_background_global_optimisations_are_applied_at_their_safe_point(runs):
    for name in ("fast", "slow"):
        _, summary, applied = runs[name]
        assert len(applied) >= 2, name  # several periodic ones ran in the background (plus the final one)
        assert all(tick == due for tick, due in applied[:-1]), applied  # each at its due safe point
        assert summary.get("loop") is None  # loop closure itself stays off
    assert runs["fast"][2] == runs["slow"][2]


def test_a_slowed_background_solve_gives_the_same_bytes(runs):
    fast, slow = runs["fast"], runs["slow"]
    for name in TRAJECTORIES:
        assert fast[0][name] == slow[0][name], name
    assert timeless(fast[1]) == timeless(slow[1])
    assert fast[1]["evaluation"]["ate"]["rmse"] <= 0.006 * fast[1]["evaluation"]["gt_path_length_m"] + 0.001


# ----------------------------------------------------------------------------------- proximity loops
OUT_FRAMES = 22  # frames out; the clip then returns over them backwards


@pytest.fixture(scope="module")
def there_and_back(room):
    _, frames = open_frames(room, "rgbd")
    out = frames[:OUT_FRAMES]
    dt = out[1].timestamp - out[0].timestamp
    back = [dataclasses.replace(f, index=OUT_FRAMES + k, timestamp=out[-1].timestamp + (k + 1) * dt)
            for k, f in enumerate(reversed(out[:-1]))]
    return out + back


def _proximity_run(frames, mode: str):
    cfg = DenseConfig()
    cfg.proximity.min_gap = 4
    cfg.proximity.cooldown = 2
    fe = DenseFrontend(cfg, sensor_mode="rgbd", backend=Backend(BackendConfig()))
    system = SlamSystem.around(fe, LoopClosureConfig(mode=mode, run_in_thread=False, global_ba_delay_frames=2))
    for f in frames:
        system.step(f)
    system.finish()
    return fe, system


@pytest.fixture(scope="module")
def proximity_run(there_and_back):
    return _proximity_run(there_and_back, "proximity")


def test_proximity_loops_close_the_return(there_and_back, proximity_run):
    """Measured: loops 12-0 and 18-6 on the way out (co-visible keyframes at least ``min_gap`` apart: a
    proximity loop by definition), 30-12 and 36-6 on the way back (frame 22 + k returns to frame 20 - k:
    the same places)."""
    fe, system = proximity_run
    counts = system.loops.proximity_counts
    assert counts["verified"] >= 2 and counts["accepted"] >= 2 and counts["global_ba_runs"] >= counts["accepted"], counts
    gt = {f.index: f.T_WC_gt for f in there_and_back}
    index = fe.frame_indices()
    accepted = [(index[q], index[c]) for q, c, status in system.loops.proximity_loops if status == "accepted"]
    returns = [(iq, ic) for iq, ic in accepted if iq >= OUT_FRAMES > ic]
    assert returns, accepted
    for iq, ic in returns:  # the query on the way back, its candidate on the way out, at nearly the same place
        assert np.linalg.norm(gt[iq][:3, 3] - gt[ic][:3, 3]) <= 0.05, (iq, ic)
    st = fe.state
    assert st.loop_edges and all(e[0] in st.graph.keyframes and e[1] in st.graph.keyframes for e in st.loop_edges)
    stamps, poses, _ = fe.trajectory()
    gt_traj = Trajectory(np.array([f.timestamp for f in there_and_back]), np.stack([f.T_WC_gt for f in there_and_back]))
    res = evaluate(gt_traj, Trajectory(stamps, poses), EvalConfig(align="se3"))
    assert res.ate.rmse <= 0.006 * res.gt_path_length_m + 0.001, res.ate.rmse
    assert_beats_doing_nothing(res.ate.rmse, gt_traj, stamps, "se3")


def test_unrelated_image_is_rejected_by_verification(there_and_back, proximity_run):
    """The loop edges of a true return verify; with the candidate's image replaced by noise (what the
    flow of an unrelated place looks like to the source) the same pair does not."""
    fe, _ = proximity_run
    index = fe.frame_indices()
    st = fe.state
    by_index = {index[f]: f for f in st.graph.keyframes}
    query, candidate = by_index[30], by_index[12]
    assert fe.contributor.long_range_edges(query, candidate) is not None
    noise = np.random.default_rng(0).integers(0, 256, size=st.crop, dtype=np.uint8)
    for fid in st.graph.keyframes:  # the candidate and its neighbours
        if abs(index[fid] - 12) <= 3:
            st.source.remove_frame(fid)
            st.source.add_frame(fid, noise)
    assert fe.contributor.long_range_edges(query, candidate) is None
