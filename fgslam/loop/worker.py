"""The classical loop closer's jobs and the worker that runs them (:mod:`fgslam.loop.closure`,
"Reproducible"): every piece of work is a :class:`ClosureJob` carrying a snapshot of the caller's pose
table; :class:`JobWorker` runs the jobs in submission order, in a thread of its own or at once in the
caller's thread, and keeps the first failure for the caller.
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from dataclasses import dataclass, field
from typing import Callable, Literal

from ..core.errors import OptimizationError
from .records import PoseCorrection

logger = logging.getLogger(__name__)

_IDLE_POLL_S = 0.005  # wait_idle's polling interval (seconds)


@dataclass
class ClosureJob:
    """Work handed to the closer's worker at tick ``tick`` (:mod:`fgslam.loop.closure`, "Reproducible"):
    ``keyframe`` (describe, detect, verify, maybe solve), ``fold`` (rescale the loop measurements by
    ``factors``), ``solve`` (a re-solve), ``close`` (the final solve); ``poses`` and ``epoch`` are the
    caller's pose table and corrections applied at submission."""

    kind: Literal["keyframe", "fold", "solve", "close"]
    tick: int
    kf_id: int | None
    poses: dict
    epoch: int
    factors: dict | None = None
    correction: PoseCorrection | None = None
    done: threading.Event = field(default_factory=threading.Event)


class JobWorker:
    """Runs :class:`ClosureJob` s in submission order with ``run_job``: in a daemon thread named
    ``name`` (``threaded``) or at once in the caller's thread. A failure is kept (:attr:`error`), no
    further job runs, and :meth:`raise_error` raises it in the caller's thread."""

    def __init__(self, run_job: Callable[[ClosureJob], None], threaded: bool, name: str):
        self._run_job = run_job
        self.error: BaseException | None = None
        self._queue: queue.Queue = queue.Queue()
        self._thread: threading.Thread | None = None
        if threaded:
            self._thread = threading.Thread(target=self._loop, name=name, daemon=True)
            self._thread.start()

    def raise_error(self) -> None:
        """Raise the kept failure of a job (as :class:`~fgslam.core.errors.OptimizationError`)."""
        if self.error is not None:
            raise OptimizationError(f"loop closure worker failed: {self.error!r}") from self.error

    def submit(self, job: ClosureJob) -> None:
        """Queue ``job`` for the thread, or run it now (synchronous: nothing runs after a failed job)."""
        if self._thread is not None:
            self._queue.put(job)
        else:
            self.raise_error()
            self.run(job)
            self.raise_error()

    def run(self, job: ClosureJob) -> None:
        """One job, in the thread (or the caller's thread when synchronous); a failure is kept for the
        caller (raised at its next call)."""
        try:
            self._run_job(job)
        except BaseException as exc:                  # surfaced in the frontend thread
            logger.exception("loop closure worker failed on a %s job", job.kind)
            self.error = exc
        finally:
            job.done.set()

    def _loop(self) -> None:
        while True:
            job = self._queue.get()
            try:
                if job is None:                       # stop()
                    return
                if self.error is None:
                    self.run(job)
            finally:
                job_done = job.done if job is not None else None
                if job_done is not None:
                    job_done.set()
                self._queue.task_done()

    def wait_idle(self, timeout: float | None = None) -> bool:
        """Block until every queued job is done; False on timeout."""
        if self._thread is None:
            return True
        t_end = None if timeout is None else time.monotonic() + timeout
        while self._queue.unfinished_tasks:
            if self.error is not None or (t_end is not None and time.monotonic() > t_end):
                break
            time.sleep(_IDLE_POLL_S)
        self.raise_error()
        return not self._queue.unfinished_tasks

    def stop(self) -> None:
        """Run the queued jobs, then end the thread."""
        if self._thread is not None:
            self._queue.put(None)
            self._thread.join()
            self._thread = None

    def cancel(self) -> None:
        """End the thread after its current job without running the queued ones (they are marked done)."""
        if self._thread is None:
            return
        while True:
            try:
                job = self._queue.get_nowait()
            except queue.Empty:
                break
            if job is not None:
                job.done.set()
            self._queue.task_done()
        self.stop()
