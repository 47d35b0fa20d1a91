"""Proximity loops closed by a global bundle adjustment (DPV-SLAM section 3.2): the part of the
loop-closure service (:class:`fgslam.services.loops.LoopService`) that searches them and runs, gates
and applies their global BAs, through the contributor contract (:mod:`fgslam.contracts.contributor`).

Proximity (``mode`` proximity or both): the newest settled keyframe is a query unless the
``cooldown`` of the last verified loop lasts; the contributor picks the best candidate among the
keyframes settled at least ``min_gap`` before it (``proximity_candidate``) and measures and verifies
long-range edges (``long_range_edges``: None rejects the loop). A verified loop waits while a global
BA runs; then the contributor hands over a snapshot of its map with every stored edge and the loop
edges of every waiting loop (``global_ba_job``). The global BA runs in the background
(``run_in_thread``; else at once): a job whose solve is a picklable function (``in_process``, the
patch family's) in a worker process of its own (spawned once per service: in a thread of the tracking
process, the two would take turns on the interpreter lock and both slow down, the global BA about
10x on the street drive), others in a thread. Its result is applied at the safe point
``global_ba_delay_frames`` polls (or the job's own ``delay_frames``, when more) after the one before
its start (waiting for it there when it is not ready, so that a run gives the same bytes however fast
the worker is; the classical closer's corrections likewise arrive ``correction_delay_frames`` polls
after their keyframe). A contributor's periodic global BA without loops (:meth:`ProximityLoops.start_global_ba`,
the dense family's) is run and applied the same way:

1. when the frontend started a new map since the snapshot, it is dropped (a correction applied
   since the snapshot, e.g. the classical closer's, is kept: the result is applied on top of it, as
   a classical correction is applied on top of a global BA's result);
2. *gate*: when less than ``min_ba_inlier_ratio`` of the loop edges keep a non-zero robust weight the
   result is discarded (its loops are "undone", and their cooldown is lifted);
3. otherwise ``contributor.apply_global_ba`` takes the structure of the keyframes that did not change
   since the snapshot and the surviving loop edges, and every keyframe gets the correction
   ``U_k = T_new_k T_snapshot_k^-1`` applied to its *current* pose (local refinements since the snapshot
   are kept; keyframes newer than the snapshot take the update of the newest snapshot keyframe; older
   maps' keyframes stay). The global BA holds every pose's scale, so the correction folds nothing.
"""

from __future__ import annotations

import logging
import multiprocessing
import threading
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field
from typing import Optional

import numpy as np

from ..core.errors import OptimizationError
from ..loop.closure import LoopCloser
from ..loop.records import LoopClosureConfig
from ..contracts.contributor import (GlobalBAJob, ProximityContributor, ProximityGates, SolvedGlobalBA,
                                     apply_global_ba_result)

logger = logging.getLogger(__name__)

# numerical trouble in a global BA (gtsam/torch/numpy): the loop is undone, the run goes on
_SOLVER_ERRORS = (OptimizationError, RuntimeError, np.linalg.LinAlgError)


def _warm_up() -> None:
    """Runs first in the worker process: it starts (spawn, imports) before the first global BA needs it."""


@dataclass
class _Running:
    """A global BA handed to the solver: its job, the loops it closes, and the map it was taken from."""

    job: GlobalBAJob
    loops: list  # (query id, candidate id) of the loops whose edges it holds
    map_epoch: int
    due_tick: int  # the safe point at which its result is applied (waiting for it there)
    started: float = field(default_factory=time.perf_counter)
    thread: Optional[threading.Thread] = None
    result: Optional[SolvedGlobalBA] = None
    error: Optional[BaseException] = None
    seconds: float = 0.0


class ProximityLoops:
    """Proximity loops and their global BAs beside one contributor (module docstring).

    Args:
        contributor: the frontend (a :class:`~fgslam.contracts.contributor.ProximityContributor`).
        config: ``loop_closure``.
        gates: the family's proximity gates (None: no proximity loops; :meth:`run_global_ba` still works).
        closer: the classical closer (or None), whose pose table follows every applied global BA.
    """

    def __init__(self, contributor: ProximityContributor, config: LoopClosureConfig, gates: ProximityGates | None,
                 closer: LoopCloser | None):
        self.contributor = contributor
        self.config = config
        self.gates = gates
        self.closer = closer
        self.seconds = 0.0  # spent in the caller's thread (the service's ``proximity`` stage)
        self._map_epoch = 0  # maps started by the contributor so far
        self._tick = 0  # safe points (poll calls) so far
        self._running: Optional[_Running] = None
        self._pool: Optional[ProcessPoolExecutor] = None  # the global BA's worker process (in_process jobs)
        if gates is not None:
            self._settled: dict[int, int] = {}  # keyframe id -> ordinal among settled keyframes
            self._order: list[int] = []
            self._cooldown_until = -1  # ordinal before which no loop is searched
            self._pending: list[tuple[int, int, dict]] = []  # verified loops waiting for the running global BA
            self.counts = {"queries": 0, "candidates": 0, "verified": 0, "accepted": 0, "undone": 0,
                           "global_ba_runs": 0, "global_ba_s": 0.0}
            self.loops: list[tuple[int, int, str]] = []  # (query id, candidate id, status)

    @property
    def busy(self) -> bool:
        """Whether a global BA is running (or waits to be applied)."""
        return self._running is not None

    def poll(self) -> None:
        """One safe point: apply the global BA due now (waiting for it when it is not ready)."""
        self._tick += 1
        run = self._running
        if run is not None and self._tick >= run.due_tick:
            t0 = time.perf_counter()
            if run.thread is not None:
                run.thread.join()
            self._finish_global_ba(run)
            self.seconds += time.perf_counter() - t0

    def map_reset(self) -> None:
        """The contributor starts a new map: a running global BA of the old one is dropped."""
        self._map_epoch += 1

    def keyframe_settled(self, kf_id: int) -> None:
        """Keyframe ``kf_id`` can no longer be removed (ids increase): a future candidate."""
        if self.gates is None or kf_id in self._settled:
            return
        self._settled[kf_id] = len(self._order)
        self._order.append(kf_id)

    def eligible_candidates(self, query: int) -> list[int]:
        """Keyframes settled at least ``min_gap`` keyframes before settled keyframe ``query``."""
        limit = self._settled[query] - self.gates.min_gap
        return self._order[: limit + 1] if limit >= 0 else []

    def search(self, query: int) -> None:
        """Search a proximity loop for settled keyframe ``query`` and start its global BA (module docstring)."""
        if self.gates is None or query not in self._settled:
            return
        t0 = time.perf_counter()
        try:
            self._search(query)
        finally:
            self.seconds += time.perf_counter() - t0

    def _search(self, query: int) -> None:
        ordinal = self._settled[query]
        if ordinal < self._cooldown_until:
            return
        counts = self.counts
        counts["queries"] += 1
        eligible = self.eligible_candidates(query)
        if not eligible:
            return
        self.prepare()  # loops are possible from now on
        cand = self.contributor.proximity_candidate(query, eligible)
        if cand is None:
            return
        counts["candidates"] += 1
        edges = self.contributor.long_range_edges(query, cand.fid)
        if edges is None:
            self.loops.append((query, cand.fid, "rejected: verification"))
            return
        counts["verified"] += 1
        self._cooldown_until = ordinal + self.gates.cooldown  # lifted again if the loop is undone
        self._pending.append((query, cand.fid, edges))
        if not self.busy:
            self._start_pending()

    def _start_pending(self) -> None:
        """A global BA with the loop edges of the oldest pending loop (the others wait for the next
        one: one global BA per loop, as when each ran at once)."""
        loops, self._pending = self._pending[:1], self._pending[1:]
        edges = {k: np.concatenate([np.asarray(e[k]) for _, _, e in loops]) for k in loops[0][2]}
        job = self.contributor.global_ba_job(edges)
        if job is None:
            self._undo([(q, c) for q, c, _ in loops], "undone: no map for the global BA")
            return
        self._start(_Running(job, [(q, c) for q, c, _ in loops], self._map_epoch, self._due(job)))

    def _due(self, job: GlobalBAJob) -> int:
        """The safe point at which a job started now is applied (``global_ba_delay_frames`` or the job's own delay)."""
        return self._tick + max(self.config.global_ba_delay_frames, int(job.delay_frames))

    def _undo(self, loops: list, status: str) -> None:
        if not loops:
            return
        for q, c in loops:
            self.loops.append((q, c, status))
            self.counts["undone"] += 1
        # the provisional cooldown of undone loops is lifted (loops still pending keep theirs)
        self._cooldown_until = max([self._settled[q] + self.gates.cooldown for q, _, _ in self._pending], default=-1)

    def prepare(self) -> None:
        """Start the worker process (``run_in_thread``), once, ahead of the first global BA that needs it
        (its start, imports included, takes seconds)."""
        if self.config.run_in_thread and self._pool is None:
            self._pool = ProcessPoolExecutor(max_workers=1, mp_context=multiprocessing.get_context("spawn"))
            self._pool.submit(_warm_up)

    def start_global_ba(self) -> bool:
        """A global BA without loop edges (a contributor's periodic one) in the background, applied at
        the safe point ``global_ba_delay_frames`` polls from now (as a loop's); False when one runs
        already or the contributor has no map."""
        if self.busy:
            return False
        job = self.contributor.global_ba_job(None)
        if job is None:
            return False
        self._start(_Running(job, [], self._map_epoch, self._due(job)))
        return True

    def run_global_ba(self, loop_edges: dict | None = None) -> bool:
        """A global BA with ``loop_edges`` now, in the caller's thread (tests, maintenance): applied
        when it passes the gate. Returns whether it was applied."""
        if self.busy:
            self.wait()
        job = self.contributor.global_ba_job(loop_edges)
        if job is None:
            return False
        run = _Running(job, [], self._map_epoch, self._tick)
        self._solve(run)
        self._running = run
        return self._finish_global_ba(run)

    def _start(self, run: _Running) -> None:
        """Solve in the background (``run_in_thread``) or at once; either way the result is applied at
        the safe point ``run.due_tick``."""
        self._running = run
        if self.config.run_in_thread:
            if run.job.in_process and self._pool is None:  # (a search created it already)
                self._pool = ProcessPoolExecutor(max_workers=1, mp_context=multiprocessing.get_context("spawn"))
            run.thread = threading.Thread(target=self._solve, args=(run,), name="fgslam-global-ba", daemon=True)
            run.thread.start()
        else:
            self._solve(run)

    def _solve(self, run: _Running) -> None:
        """Solve the job (worker thread or caller); an exception is kept for the safe point."""
        t0 = time.perf_counter()
        try:
            if run.thread is not None and run.job.in_process:
                run.result = self._pool.submit(run.job.solve).result()
            else:
                run.result = run.job.solve()
        except BaseException as exc:  # noqa: BLE001 - surfaced at the safe point
            run.error = exc
        run.seconds = time.perf_counter() - t0

    def wait(self) -> None:
        """Wait for a running global BA and apply it (reruns included)."""
        t0 = time.perf_counter()
        while self._running is not None:
            run = self._running
            if run.thread is not None:
                run.thread.join()
            self._finish_global_ba(run)
        if self.gates is not None:
            self.seconds += time.perf_counter() - t0

    def _finish_global_ba(self, run: _Running) -> bool:
        """Apply a solved global BA at the safe point (module docstring, steps 1-3); returns whether it
        was applied."""
        self._running = None
        counts = self.counts if self.gates is not None else None
        if counts is not None:
            counts["global_ba_runs"] += 1
            counts["global_ba_s"] += run.seconds
        status = None
        if run.error is not None:
            if not isinstance(run.error, _SOLVER_ERRORS):
                raise run.error
            logger.warning("global BA failed: %s; loop undone", run.error)
            status = "undone: global BA failed"
        elif run.map_epoch != self._map_epoch:
            status = "undone: a new map started during the global BA"
        job, res = run.job, run.result
        if status is None:
            keep = res.robust[job.is_loop] > 0
            if keep.size:
                kept = float(keep.mean())
                ratio = self.gates.min_ba_inlier_ratio if self.gates is not None else 0.0
                if kept < ratio:
                    logger.info("global BA undone: %.0f %% of the loop edges kept a weight (< %.0f %%)",
                                100 * kept, 100 * ratio)
                    status = "undone: loop edges inconsistent after global BA"
        if status is not None:
            self._undo(run.loops, status)
            self._next()
            return False
        ids = [int(k) for k in job.kf_ids]
        apply_global_ba_result(self.contributor, job, res, keep, run.seconds)
        if self.closer is not None:
            poses = {k: self.contributor.keyframe_pose(k) for k in ids}
            self.closer.update_poses({k: T for k, T in poses.items() if T is not None})
        for q, c in run.loops:
            self.loops.append((q, c, "accepted"))
            counts["accepted"] += 1
            logger.info("proximity loop closed: keyframe %d <-> keyframe %d (global BA %.2f s over %d loop edges, "
                        "applied %.2f s after its start)", q, c, run.seconds, int(keep.size), time.perf_counter() - run.started)
        self._next()
        return True

    def _next(self) -> None:
        """Start the global BA of the loops verified while the last one ran."""
        if self.gates is not None and self._pending and not self.busy:
            self._start_pending()

    def finish(self) -> None:
        """Wait for a running global BA and apply it; end the worker process."""
        self.wait()
        if self._pool is not None:
            self._pool.shutdown()
            self._pool = None

    def cancel(self) -> None:
        """Stop at once (an interrupted or failed run): a running global BA is dropped and its worker
        process ended; nothing more is applied."""
        if self._running is not None:
            self._undo(self._running.loops, "undone: the run stopped")
            self._running = None
        if self._pool is not None:
            # a running solve is not waited for: SIGKILL, which a worker cannot ignore or block (a worker
            # once outlived SIGTERM for 30 s in the suite under load, cause not found); its result is
            # dropped anyway, and a solve writes nothing
            for process in list(getattr(self._pool, "_processes", {}).values()):
                process.kill()
            self._pool.shutdown(wait=False, cancel_futures=True)
            self._pool = None

    def summary(self, index: dict[int, int]) -> dict:
        """Proximity counts for the run summary; ``index`` maps keyframe ids to input frame indices (-1: unknown)."""
        return {**self.counts, "settled_keyframes": len(self._order),
                "loop_frames": [[index.get(q, -1), index.get(c, -1), status] for q, c, status in self.loops]}
