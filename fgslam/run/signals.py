"""Stopping on a signal: :class:`StopOnSignal`, the handlers of a run (:mod:`fgslam.run.runner`) and
of a batch of runs (:mod:`fgslam.run.batch`) while they work."""

from __future__ import annotations

import logging
import signal
import threading
from types import FrameType
from typing import Callable, Optional, Union

from ..core.errors import Interrupted

logger = logging.getLogger(__name__)

#: a signal's handler as ``signal.signal`` returns it (a callable, SIG_DFL / SIG_IGN, or None)
_Handler = Union[Callable[[int, Optional[FrameType]], object], int, None]


class StopOnSignal:
    """While active (a ``with`` block in the main thread), the given signals raise
    :class:`~fgslam.core.errors.Interrupted` (a ``KeyboardInterrupt``); once ``finishing`` is set (the
    loop has stopped: the outputs and the report are being written), a further one, a second
    Ctrl-C included, is logged and ignored so that they are completed. The previous handlers are
    restored on exit (none is installed outside the main thread, where Python cannot)."""

    def __init__(self, signums: tuple[int, ...]) -> None:
        self.signums = signums
        self.finishing = False
        self._previous: dict[int, _Handler] = {}

    def __enter__(self) -> "StopOnSignal":
        if threading.current_thread() is not threading.main_thread():
            logger.debug("not in the main thread: no handler for %s", [signal.Signals(s).name for s in self.signums])
            return self
        for signum in self.signums:
            self._previous[signum] = signal.signal(signum, self._handle)
        return self

    def _handle(self, signum: int, frame: Optional[FrameType]) -> None:
        name = signal.Signals(signum).name
        if self.finishing:
            logger.warning("%s received again: still stopping: writing outputs, please wait", name)
            return
        self.finishing = True  # set before raising: a second signal, however soon, never cuts the stop short
        logger.warning("%s received: stopping: writing outputs, please wait", name)
        raise Interrupted(name, signum)

    def __exit__(self, *exc_info: object) -> None:
        for signum, previous in self._previous.items():
            signal.signal(signum, signal.SIG_DFL if previous is None else previous)
        self._previous.clear()
