"""The loop-closure service (fgslam.services.loops) through the contributor contract
(fgslam.contracts.contributor), with toy contributors instead of the patch frontend:

- a classical one that only keeps keyframe images and drifted poses and records the corrections it
  is given, driving the classical closer on a synthetic room-loop drive (the project's renderer);
- a proximity one whose "global BA" is a stand-in solve (a known pose change, released by the test),
  for the background global BA: applied only at the safe point, gated, kept over a correction that
  came in meanwhile, dropped on a new map, waited for at finish.
"""

from __future__ import annotations

import math
import threading
import time
from types import SimpleNamespace

import numpy as np
import pytest
from geometry_support import rigid, rot_y

from fgslam.contracts.contributor import Contributor, GlobalBAJob, KeyframeImage, PoseCorrection, ProximityContributor
from fgslam.services.loops import LoopService
from fgslam.core.errors import OptimizationError
from fgslam.eval.trajectory import EvalConfig, evaluate
from fgslam.io.trajectory import Trajectory
from fgslam.loop.records import LoopClosureConfig

RATE_HZ = 4.0
EXTRA_FRAMES = 19  # past the first return to the start
REVISIT_M = 0.6  # an accepted loop joins keyframes at most this far apart (ground truth) ...
MIN_GAP_S = 10.0  # ... and at least this far apart in time
SCALE_DRIFT_TOTAL = 0.4  # log scale drift of the odometry at the end
HEADING_DRIFT_DEG = 10.0  # heading drift of the odometry at the end
WAIT_S = 30.0  # longest wait for a background solve in these tests


# ----------------------------------------------------------------------------------- classical

class ToyKeyframes:
    """A second contributor: keyframe images and poses, nothing else; records the corrections.
    Monocular: the scale of a correction is folded into its odometry unit (its "structure")."""

    name = "toy"

    def __init__(self, K: np.ndarray):
        self.K = np.asarray(K, np.float64)
        self.images: dict[int, tuple[np.ndarray, float]] = {}
        self.poses: dict[int, np.ndarray] = {}
        self.corrections: list[PoseCorrection] = []
        self.unit = 1.0

    def keyframe_image(self, kf_id):
        kept = self.images.get(kf_id)
        return None if kept is None else KeyframeImage(kept[0], self.K, kept[1])

    def keyframe_pose(self, kf_id):
        return self.poses.get(kf_id)

    def apply_correction(self, correction):
        self.corrections.append(correction)
        newest = max(self.poses)
        for k, T in list(self.poses.items()):
            self.poses[k], s = correction.apply_pose(k, T)
            if k == newest:
                self.unit *= s

    def long_range_edges(self, query_kf_id, candidate_kf_id):
        return None


@pytest.fixture(scope="module")
def room(room_loop_clip):
    import cv2

    root, seq = room_loop_clip(RATE_HZ, EXTRA_FRAMES)  # rendered once per session (conftest.py)
    n = seq.cfg.frames
    t = np.arange(n) / RATE_HZ
    T_gt = seq.camera_poses(t)
    images = [cv2.imread(str(path), cv2.IMREAD_UNCHANGED) for path in sorted((root / "mav0" / "cam0" / "data").iterdir())]
    assert len(images) == n and images[0].shape == (240, 320) and images[0].dtype == np.uint8
    rate, yaw = SCALE_DRIFT_TOTAL / n, math.radians(HEADING_DRIFT_DEG) / n
    steps = []  # drifted odometry T_Ck-1Ck
    for k in range(1, n):
        D = np.linalg.inv(T_gt[k - 1]) @ T_gt[k]
        S = np.eye(4)
        S[:3, :3] = rot_y(yaw) @ D[:3, :3]
        S[:3, 3] = math.exp(rate * (k - 1)) * D[:3, 3]
        steps.append(S)
    return dict(K=np.array(seq.K, np.float64), t=t, T_gt=T_gt, images=images, steps=steps)


@pytest.fixture(scope="module")
def classical_run(room):
    """The toy contributor fed frame by frame (odometry continued in the corrected units), the
    service polled at each safe point; keyframe ``blind`` has no image (the contributor dropped it)."""
    n = len(room["t"])
    blind = 3
    toy = ToyKeyframes(room["K"])
    service = LoopService(toy, LoopClosureConfig(mode="classical", run_in_thread=False))
    drifted = [room["T_gt"][0].copy()]
    for k in range(n):
        if k:
            step = room["steps"][k - 1].copy()
            drifted.append(drifted[-1] @ step)
            step[:3, 3] *= toy.unit
            toy.poses[k] = toy.poses[k - 1] @ step
        else:
            toy.poses[0] = room["T_gt"][0].copy()
        if k != blind:
            toy.images[k] = (room["images"][k], float(room["t"][k]))
        service.poll()
        service.add_keyframe(k, neighbours=[k - 1] if k else [])
        service.update_poses({k: toy.poses[k]})
    service.finish()
    return dict(toy=toy, service=service, drifted=drifted, blind=blind, n=n)


def _ate(room, poses) -> float:
    res = evaluate(Trajectory(room["t"], room["T_gt"]), Trajectory(room["t"], rigid(np.stack(poses))),
                   EvalConfig(align="sim3", rpe_delta_meters=None))
    return float(res.ate.rmse)


def test_toy_contributor_satisfies_the_contract(classical_run):
    assert isinstance(classical_run["toy"], Contributor)
    assert not isinstance(classical_run["toy"], ProximityContributor)  # no proximity part: classical only


def test_toy_contributor_closes_the_room_loop(room, classical_run):
    toy, service, n = classical_run["toy"], classical_run["service"], classical_run["n"]
    summary = service.summary({k: k for k in range(n)})
    assert summary["mode"] == "classical" and "proximity" not in summary
    assert summary["keyframes_added"] == n - 1  # the keyframe without an image is skipped
    assert summary["accepted_loops"] > 0
    assert summary["corrections_applied"] == len(toy.corrections) > 0
    for q, c, status in summary["loop_frames"]:
        if status == "accepted":
            assert (q - c) / RATE_HZ >= MIN_GAP_S, (q, c)
            assert np.linalg.norm(room["T_gt"][q][:3, 3] - room["T_gt"][c][:3, 3]) <= REVISIT_M, (q, c)
    assert all(corr.fold_scale for corr in toy.corrections)  # monocular: scale folded into the contributor
    assert toy.unit != 1.0
    ate_on, ate_off = _ate(room, [toy.poses[k] for k in range(n)]), _ate(room, classical_run["drifted"])
    assert ate_on < 0.5 * ate_off, f"ATE {ate_on:.4f} with the service vs {ate_off:.4f} without"


def test_service_off_does_nothing(room):
    toy = ToyKeyframes(room["K"])
    toy.images[0] = (room["images"][0], 0.0)
    toy.poses[0] = np.eye(4)
    service = LoopService(toy, LoopClosureConfig(mode="off"))
    assert not service.enabled and service.closer is None and service.summary() is None
    assert service.add_keyframe(0) is False and service.relocalize(room["images"][0], room["K"]) is None
    service.search(0)
    service.poll()
    service.finish()
    assert service.stage_times() == {}


# ----------------------------------------------------------------------------------- global BA

class ToyMap(ToyKeyframes):
    """A proximity contributor: keyframes 0..n-1 (those below ``map_start`` belong to an older map);
    its global BA is a stand-in: released by ``gate`` (an Event), it returns the snapshot poses moved
    by a known per-keyframe transform and ``robust_loop`` as the loop edges' weight."""

    def __init__(self, n: int, map_start: int = 0):
        super().__init__(np.array([300.0, 300.0, 160.0, 120.0]))
        self.map_start = map_start
        for k in range(n):
            T = np.eye(4)
            T[:3, :3] = rot_y(0.05 * k)
            T[:3, 3] = [0.5 * k, 0.0, 0.1 * k]
            self.poses[k] = T
        self.gate = threading.Event()
        self.robust_loop = 1.0
        self.fail = False
        self.jobs: list[GlobalBAJob] = []
        self.events: list[str] = []
        self.handed: list[np.ndarray] = []

    @staticmethod
    def moved(k: int, T: np.ndarray) -> np.ndarray:
        A = np.eye(4)
        A[:3, :3] = rot_y(0.01 * k)
        A[:3, 3] = [0.0, 0.02 * k, -0.03 * k]
        return A @ T

    def proximity_candidate(self, query_kf_id, candidate_kf_ids):
        return SimpleNamespace(fid=candidate_kf_ids[0], flow=0.0) if candidate_kf_ids else None

    def long_range_edges(self, query_kf_id, candidate_kf_id):
        return {"src": np.array([query_kf_id, candidate_kf_id]), "tgt": np.array([candidate_kf_id, query_kf_id])}

    def global_ba_job(self, loop_edges):
        ids = np.array([k for k in sorted(self.poses) if k >= self.map_start])
        T_snap = np.stack([self.poses[k] for k in ids])
        n_loop = 0 if loop_edges is None else len(loop_edges["src"])
        is_loop = np.r_[np.zeros(3, bool), np.ones(n_loop, bool)]  # three map edges, then the loop edges

        def solve():
            if not self.gate.wait(WAIT_S):
                raise AssertionError("the test never released the global BA")
            if self.fail:
                raise OptimizationError("stand-in failure")
            robust = np.where(is_loop, self.robust_loop, 1.0)
            return SimpleNamespace(T_WC=np.stack([self.moved(int(k), T) for k, T in zip(ids, T_snap)]), robust=robust)

        job = GlobalBAJob(solve=solve, kf_ids=ids, T_WC=T_snap.copy(), is_loop=is_loop, loop_edges=loop_edges)
        self.jobs.append(job)
        return job

    def apply_global_ba(self, job, result, keep_loop):
        self.events.append("global_ba")
        self.handed.append(keep_loop.copy())

    def apply_correction(self, correction):
        self.events.append("correction")
        super().apply_correction(correction)


class Gates:
    min_gap = 5
    cooldown = 3
    min_ba_inlier_ratio = 0.6


def _proximity_service(toy: ToyMap, mode: str = "proximity") -> LoopService:
    service = LoopService(toy, LoopClosureConfig(mode=mode, run_in_thread=True), proximity=Gates())
    for k in sorted(toy.poses):
        if k >= toy.map_start:
            service.keyframe_settled(k)
    return service


def _poll_until_idle(service: LoopService) -> None:
    deadline = time.monotonic() + WAIT_S
    while service.busy and time.monotonic() < deadline:
        time.sleep(0.01)
        service.poll()
    assert not service.busy


def test_global_ba_runs_in_the_background_and_is_applied_at_the_safe_point():
    toy = ToyMap(12, map_start=2)  # keyframes 0, 1: an older map
    assert isinstance(toy, ProximityContributor)
    service = _proximity_service(toy)
    query = 11
    service.search(query)
    assert service.busy and len(toy.jobs) == 1
    job = toy.jobs[0]
    assert job.kf_ids.tolist() == list(range(2, 12))
    before = {k: T.copy() for k, T in toy.poses.items()}
    # tracking goes on while it solves: nothing is applied, the newest keyframe is refined, a new one added
    for _ in range(3):
        service.poll()
    assert toy.events == [] and all(np.array_equal(toy.poses[k], before[k]) for k in before)
    refine = np.eye(4)
    refine[:3, 3] = [0.01, -0.02, 0.005]
    toy.poses[query] = toy.poses[query] @ refine
    toy.poses[12] = toy.poses[query] @ refine
    current = {k: T.copy() for k, T in toy.poses.items()}
    toy.gate.set()
    _poll_until_idle(service)
    assert toy.events == ["global_ba", "correction"]  # structure hand-over first, then the poses
    assert toy.handed[0].tolist() == [True, True]
    U = {int(k): ToyMap.moved(int(k), T) @ np.linalg.inv(T) for k, T in zip(job.kf_ids, job.T_WC)}
    for k in range(2, 11):  # unchanged since the snapshot: exactly the solved pose
        np.testing.assert_allclose(toy.poses[k], ToyMap.moved(k, before[k]), atol=1e-12)
    np.testing.assert_allclose(toy.poses[query], U[query] @ current[query], atol=1e-12)  # refined meanwhile
    np.testing.assert_allclose(toy.poses[12], U[11] @ current[12], atol=1e-12)  # newer: the newest update
    for k in (0, 1):  # the older map stays
        np.testing.assert_array_equal(toy.poses[k], before[k])
    counts = service.proximity_counts
    assert counts["accepted"] == 1 and counts["global_ba_runs"] == 1 and counts["undone"] == 0
    assert service.proximity_loops == [(query, 2, "accepted")]
    # cooldown: the next queries within it search nothing
    toy.poses[13] = toy.poses[12].copy()
    service.keyframe_settled(13)
    service.search(13)
    assert not service.busy and counts["queries"] == 1


def test_global_ba_whose_loop_edges_lose_their_weight_is_undone():
    toy = ToyMap(10)
    toy.robust_loop = 0.0
    service = _proximity_service(toy)
    before = {k: T.copy() for k, T in toy.poses.items()}
    service.search(9)
    toy.gate.set()
    _poll_until_idle(service)
    assert toy.events == [] and all(np.array_equal(toy.poses[k], before[k]) for k in before)
    assert service.proximity_loops == [(9, 0, "undone: loop edges inconsistent after global BA")]
    assert service.proximity_counts["undone"] == 1


def test_loops_verified_during_a_global_ba_wait_for_the_next_one():
    toy = ToyMap(20)
    service = _proximity_service(toy)
    service.search(10)
    service.search(12)  # within the cooldown of the loop of 10
    service.search(14)  # verified while the first global BA runs: waits
    assert len(toy.jobs) == 1 and service.busy
    toy.gate.set()
    _poll_until_idle(service)
    assert len(toy.jobs) == 2 and toy.jobs[1].loop_edges["src"].tolist() == [14, 0]
    assert service.proximity_loops == [(10, 0, "accepted"), (14, 0, "accepted")]
    assert service.proximity_counts["queries"] == 2 and toy.events == ["global_ba", "correction"] * 2


def test_failed_global_ba_undoes_its_loop_and_lifts_the_cooldown():
    toy = ToyMap(10)
    toy.fail = True
    service = _proximity_service(toy)
    service.search(8)
    toy.gate.set()
    _poll_until_idle(service)
    assert toy.events == [] and service.proximity_loops == [(8, 0, "undone: global BA failed")]
    toy.fail = False
    service.search(9)  # right after: no cooldown from an undone loop
    _poll_until_idle(service)
    assert service.proximity_loops[-1] == (9, 0, "accepted") and toy.events == ["global_ba", "correction"]


def test_correction_during_a_global_ba_is_kept_and_a_new_map_drops_it(monkeypatch):
    """A classical correction applied while the global BA solves stays: the result's update is applied
    on top of it (as a classical correction is applied on top of a global BA's result)."""
    toy = ToyMap(10)
    service = _proximity_service(toy, mode="both")
    C = np.eye(4)
    C[:3, 3] = [1.0, 0.0, 0.0]
    pending = [PoseCorrection({k: C for k in toy.poses}, {k: 1.0 for k in toy.poses}, {}, [], False, 1, 0.0)]
    monkeypatch.setattr(service.closer, "poll", lambda: pending.pop() if pending else None)
    service.search(9)
    before = {k: T.copy() for k, T in toy.poses.items()}
    service.poll()
    assert toy.events == ["correction"]  # the classical one
    toy.gate.set()
    _poll_until_idle(service)
    assert len(toy.jobs) == 1 and toy.events == ["correction", "global_ba", "correction"]
    for k in range(10):
        U = ToyMap.moved(k, before[k]) @ np.linalg.inv(before[k])
        np.testing.assert_allclose(toy.poses[k], U @ C @ before[k], atol=1e-12)
    assert service.proximity_loops == [(9, 0, "accepted")]
    service.finish()
    # a new map while a global BA runs: dropped
    toy2 = ToyMap(10)
    service2 = _proximity_service(toy2)
    service2.search(9)
    service2.map_reset()
    toy2.gate.set()
    _poll_until_idle(service2)
    assert toy2.events == [] and service2.proximity_loops == [(9, 0, "undone: a new map started during the global BA")]


def test_a_map_moved_by_its_frontend_reaches_the_contributor_and_drops_a_running_global_ba():
    """``move_map`` (a restarted map rejoining the one before it): the correction goes through the
    contributor, the closer's pose table takes the moved poses and a solve made before is solved again
    (its epoch), and a global BA started on the poses before the move is dropped."""
    toy = ToyMap(10)
    service = _proximity_service(toy, mode="both")
    service.search(9)
    C = np.eye(4)
    C[:3, 3] = [0.0, 2.0, 0.0]
    moved = {k: C @ toy.poses[k] for k in range(5, 10)}
    correction = PoseCorrection.between({k: toy.poses[k] for k in moved}, moved, hold_older=True)
    service.closer._poses.update({k: toy.poses[k] for k in range(10)})  # as if handed to the closer
    epoch = service.closer._epoch
    assert service.move_map(correction, moved) is True
    assert toy.events == ["correction"] and service.closer._epoch == epoch + 1
    for k in range(10):
        np.testing.assert_allclose(service.closer._poses[k], moved.get(k, toy.poses[k]), atol=1e-12)
    toy.gate.set()
    _poll_until_idle(service)
    assert toy.events == ["correction"]  # the global BA from before the move was not applied
    assert service.proximity_loops == [(9, 0, "undone: a new map started during the global BA")]
    service.finish()


def test_finish_waits_for_the_running_global_ba():
    toy = ToyMap(10)
    service = _proximity_service(toy)
    service.search(9)
    threading.Timer(0.2, toy.gate.set).start()
    service.finish()
    assert not service.busy and toy.events == ["global_ba", "correction"]
    assert service.summary({})["proximity"]["accepted"] == 1


def test_several_loops_verified_during_a_global_ba_get_one_global_ba_each():
    """Loops waiting for a running global BA are solved one per global BA, oldest first (the street
    drive: four loops merged into one global BA left 0.282 m ATE, one each 0.256 m)."""
    toy = ToyMap(24)
    service = _proximity_service(toy)
    service.search(10)
    service.search(14)  # waits
    service.search(18)  # waits too (past the cooldown of 14's verification)
    assert len(toy.jobs) == 1 and service.busy
    toy.gate.set()
    _poll_until_idle(service)
    assert [job.loop_edges["src"].tolist() for job in toy.jobs] == [[10, 0], [14, 0], [18, 0]]
    assert service.proximity_loops == [(10, 0, "accepted"), (14, 0, "accepted"), (18, 0, "accepted")]
    assert service.proximity_counts["global_ba_runs"] == 3


CANCEL_SOLVE_S = 120.0  # a global BA far longer than the test may take
REAP_POLL_S = 0.05  # between two looks at a killed worker


def _ended(process, timeout_s: float) -> bool:
    """Whether ``process`` ended within ``timeout_s``. Asked again until then: the pool's own thread
    reaps its workers too, and while it holds a worker's exit status ``is_alive()`` still answers True
    (``waitpid`` finds no child, the return code is not set yet)."""
    deadline = time.monotonic() + timeout_s
    process.join(timeout=timeout_s)
    while process.is_alive() and time.monotonic() < deadline:
        time.sleep(REAP_POLL_S)
    return not process.is_alive()


def test_cancel_ends_a_running_global_ba_in_its_worker_process_at_once(monkeypatch):
    """A stopped run (SIGTERM, a failure) does not wait for a running global BA: cancel() ends its
    worker process, drops the result and marks its loop undone."""
    import functools

    toy = ToyMap(10)
    make_job = toy.global_ba_job

    def slow_job(loop_edges):
        job = make_job(loop_edges)
        job.solve, job.in_process = functools.partial(time.sleep, CANCEL_SOLVE_S), True  # picklable: the worker process
        return job

    monkeypatch.setattr(toy, "global_ba_job", slow_job)
    service = _proximity_service(toy)
    service.search(9)
    assert service.busy
    processes = list(service.proximity_closer._pool._processes.values())
    assert processes
    t0 = time.monotonic()
    service.cancel()
    assert time.monotonic() - t0 < CANCEL_SOLVE_S / 4
    assert not service.busy and toy.events == []
    for process in processes:
        assert _ended(process, WAIT_S)
    assert service.summary({})["proximity"]["undone"] == 1


# ----------------------------------------------------------------------------------- a loaded map

class FakeLink:
    """A loaded map (services.loops.MapLink) that records what it is given and relocalises every lost frame
    at a pose read from the contributor's keyframe 0 (None: not found)."""

    def __init__(self, found: bool):
        self.found, self.keyframes, self.resets = found, [], 0

    def add_keyframe(self, kf_id, image):
        self.keyframes.append(kf_id)
        return True

    def map_reset(self):
        self.resets += 1

    def relocalize(self, image, pose_of):
        step = np.eye(4)
        step[0, 3] = 0.1
        return (7, pose_of(0) @ step) if self.found else None


@pytest.mark.parametrize("found", [True, False])
def test_without_the_closer_a_loaded_map_takes_the_keyframes_and_relocalises_lost_frames(found):
    toy = ToyKeyframes(np.array([100.0, 100.0, 32.0, 24.0]))
    toy.images[0], toy.poses[0] = (np.zeros((48, 64), np.uint8), 0.0), np.eye(4)
    toy.poses[0][:3, 3] = (1.0, 2.0, 3.0)
    link = FakeLink(found)
    service = LoopService(toy, LoopClosureConfig(mode="off"), metric=True, link=link)
    assert service.relocalizes and not service.classical and not service.enabled
    assert service.add_keyframe(0) and not service.add_keyframe(0) and link.keyframes == [0]
    result = service.relocalize(np.zeros((48, 64), np.uint8), toy.K)
    if found:  # the poses come from the contributor when asked (corrections included)
        assert result[0] == 7 and np.allclose(result[1][:3, 3], [1.1, 2.0, 3.0])
    else:
        assert result is None
    service.map_reset()
    summary = service.summary()
    assert link.resets == 1 and summary["mode"] == "off"
    assert summary["relocalization_attempts"] == 1 and summary["relocalized_in_loaded_map"] == summary["relocalized"] == int(found)
    assert LoopService(toy, LoopClosureConfig(mode="off")).summary() is None  # neither closer nor map: nothing to report
