"""Live input: frames that come at their own pace, to a consumer that may be slower (:class:`LiveFrames`).

A reader thread takes the frames of a source (a camera capture, a stream, or a recorded sequence
replayed at its own rate: ``LiveConfig.speed`` times its timestamps) and hands them over through a
queue of at most ``LiveConfig.queue`` frames; when the queue is full the **oldest** waiting frame is
dropped and counted, so the consumer always gets the newest frames and never falls behind without
bound. A dropped frame's IMU samples go with the next frame, so that the inertial stream has no gap.
Each frame's arrival time is kept, so the consumer can report its latency (arrival to result): for a
replayed recording, the time the frame was due (a reader slower than the recording counts as latency
too); for a live source, the time the reader had it. Closing the frames (or leaving a ``with`` block)
stops the reader.

A recorded run that is not live reads ahead instead (:class:`ReadAhead`): a reader thread decodes the next
frame while the consumer works on this one, and no frame is dropped.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import deque
from dataclasses import dataclass
from typing import Iterable, Iterator, Optional

import numpy as np

from ..core.config import MAX_COUNT, MAX_SCALAR, check_ranges, ranged
from .frame import Frame, ImuSamples

logger = logging.getLogger(__name__)

_POLL_S = 0.05  # how often a waiting consumer or a pacing reader looks for a stop request
_JOIN_S = 2.0  # how long close() waits for the reader (a capture blocked in its read is left to end on its own)


@dataclass
class LiveConfig:
    """How a live run takes its frames (``fgslam run --live``)."""

    speed: float = ranged(1.0, gt=0, le=MAX_SCALAR)  # a recorded source replays at this many times its own rate (0 < speed)
    queue: int = ranged(1, ge=1, le=MAX_COUNT)  # frames waiting at most; a newer frame drops the oldest
    paced: bool = True  # replay a recorded source at its timestamps (false: as fast as it reads, a camera's own pace)


class _ThreadedReader:
    """A source read by a background thread into a queue that the consumer takes from; iterate once.
    Subclasses say how a frame is put in (:meth:`_put`) and what taking one records (:meth:`_taken`).
    An exception that stops the source reaches the consumer after the frames queued before it.
    ``cpu_s``: the reader thread's own CPU time (work OpenCV hands to its pool threads is not in it),
    set when the thread ends; 0 before that (a reader that did not end when closed)."""

    _thread_name = "fgslam-reader"

    def __init__(self, source: Iterable[Frame]) -> None:
        self.source = source
        self.error: Optional[BaseException] = None
        self._queue: deque = deque()
        self._cond = threading.Condition()
        self._stop = threading.Event()
        self._done = False
        self._thread: Optional[threading.Thread] = None
        self.cpu_s = 0.0  # CPU time of the reader thread alone (decoding the frames), set when it ends (0 until then)

    def _read(self) -> None:
        start = time.thread_time()
        try:
            for frame in self.source:
                if self._stop.is_set():
                    break
                self._put(frame)
        except BaseException as exc:  # noqa: BLE001 - handed to the consumer, which raises it
            self.error = exc
        finally:
            self.cpu_s = time.thread_time() - start
            with self._cond:
                self._done = True
                self._cond.notify_all()

    def _put(self, frame: Frame) -> None:  # pragma: no cover - every reader defines it
        raise NotImplementedError

    def _taken(self, item) -> Frame:
        """The frame of a queued item, as the consumer takes it."""
        return item

    def __iter__(self) -> Iterator[Frame]:
        if self._thread is not None:
            raise RuntimeError(f"{type(self).__name__} can be iterated once")
        self._thread = threading.Thread(target=self._read, name=self._thread_name, daemon=True)
        self._thread.start()
        try:
            while True:
                with self._cond:
                    while not self._queue and not self._done:
                        self._cond.wait(_POLL_S)
                    if not self._queue:
                        break
                    item = self._queue.popleft()
                    self._cond.notify_all()
                yield self._taken(item)
        finally:
            self.close()
        if self.error is not None:
            raise self.error

    def close(self) -> None:
        """Stop the reader: its frame in progress is read, then it ends (waited for up to ``_JOIN_S``, again
        on a second call, so that nothing reads the source after the consumer's last close)."""
        self._stop.set()
        with self._cond:
            self._cond.notify_all()
        if self._thread is not None and self._thread is not threading.current_thread() and self._thread.is_alive():
            self._thread.join(timeout=_JOIN_S)

    def __enter__(self):
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class LiveFrames(_ThreadedReader):
    """The frames of ``source`` as a live feed (module docstring); iterate once.

    Args:
        source: any iterable of frames (a dataset, a capture).
        config: speed, queue size, pacing.

    Attributes:
        dropped: frames dropped because the consumer was behind (the oldest waiting ones).
        delivered: frames handed to the consumer.
        arrival_s: ``perf_counter`` time each delivered frame arrived, by frame index.
        error: the exception that stopped the reader early (None: it ran to the source's end, or was closed).

    Raises:
        ConfigError: a config value out of its range (naming ``live.<key>``).
    """

    _thread_name = "fgslam-live-reader"

    def __init__(self, source: Iterable[Frame], config: Optional[LiveConfig] = None) -> None:
        super().__init__(source)
        self.config = config or LiveConfig()
        check_ranges(self.config, "live.", "the live options")
        self.dropped = 0
        self.delivered = 0
        self.arrival_s: dict[int, float] = {}
        self._t_wall0 = 0.0  # the wall time of the first frame
        self._t_src0: Optional[float] = None  # ... and its source time

    def _put(self, frame: Frame) -> None:
        cfg = self.config
        arrival = time.perf_counter()
        if cfg.paced:
            if self._t_src0 is None:
                self._t_wall0, self._t_src0 = arrival, frame.timestamp
            arrival = self._t_wall0 + (frame.timestamp - self._t_src0) / cfg.speed  # when the frame was due
            while not self._stop.is_set() and time.perf_counter() < arrival:
                time.sleep(min(_POLL_S, max(arrival - time.perf_counter(), 0.0)))
        with self._cond:
            while len(self._queue) >= cfg.queue:
                old, _ = self._queue.popleft()
                self.dropped += 1
                logger.debug("live: frame %d dropped (the system is behind)", old.index)
                after = self._queue[0][0] if self._queue else frame
                after.imu = _joined(old.imu, after.imu)
            self._queue.append((frame, arrival))
            self._cond.notify_all()

    def _taken(self, item: tuple[Frame, float]) -> Frame:
        frame, arrival = item
        self.arrival_s[frame.index] = arrival
        self.delivered += 1
        return frame


class ReadAhead(_ThreadedReader):
    """The frames of ``source`` read ahead by a background thread: ``ahead`` frames wait in the queue and
    the reader holds one more until there is room; none is dropped (the reader waits for the consumer).
    Decoding the next frame (OpenCV and numpy release the GIL) overlaps the consumer's work on this one;
    the frames, their order, and an exception that stops the source (raised after the frames read before
    it) are those of iterating ``source`` directly. Iterate once; closing (or leaving a ``with`` block, or
    the loop) stops the reader."""

    _thread_name = "fgslam-read-ahead"

    def __init__(self, source: Iterable[Frame], ahead: int = 1) -> None:
        if ahead < 1:
            raise ValueError(f"ReadAhead: ahead must be >= 1, got {ahead}")
        super().__init__(source)
        self.ahead = ahead

    def _put(self, frame: Frame) -> None:
        with self._cond:
            while len(self._queue) >= self.ahead and not self._stop.is_set():
                self._cond.wait(_POLL_S)
            if not self._stop.is_set():
                self._queue.append(frame)
                self._cond.notify_all()


def _joined(first: Optional[ImuSamples], then: Optional[ImuSamples]) -> Optional[ImuSamples]:
    """The IMU samples of a dropped frame put before those of the frame after it."""
    if first is None or len(first) == 0:
        return then
    if then is None:
        return first
    return ImuSamples(np.concatenate([first.timestamps, then.timestamps]), np.concatenate([first.gyro, then.gyro]),
                      np.concatenate([first.accel, then.accel]))
