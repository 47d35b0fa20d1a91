"""The pointmap frontend's source cache: which frames the measurement source holds (the current frame,
the previous tracked one, the newest keyframes), added on demand and released after each frame."""

from __future__ import annotations

import time
from typing import TYPE_CHECKING

from .keyframes import PointmapKeyframe

if TYPE_CHECKING:
    from .frontend import PointmapFrontend


class SourceCache:
    """The frames loaded in the source of ``frontend`` (oldest first); adding counts as ``source`` time."""

    def __init__(self, frontend: "PointmapFrontend"):
        self.fe = frontend
        self.frames: list[int] = []

    def __contains__(self, fid: int) -> bool:
        return fid in self.frames

    def add(self, fid: int, grey, depth, right) -> None:
        """Load frame ``fid`` into the source unless it is loaded."""
        fe = self.fe
        t0 = time.perf_counter()
        if fid not in self.frames:
            fe.source.add_frame(fid, grey, depth=depth, right=right)
            self.frames.append(fid)
        fe._times["source"] += time.perf_counter() - t0

    def ensure(self, kf: PointmapKeyframe) -> None:
        """Keyframe ``kf`` loaded in the source (re-added from its images when it was released)."""
        self.add(kf.fid, kf.grey, kf.depth, kf.right)

    def release(self) -> None:
        """Keep the source caches of the current frame and the newest keyframes only."""
        fe = self.fe
        keep = set(list(fe._kfs)[-fe.config.keyframe.keep_source_frames:])
        if fe._kf is not None:
            keep.add(fe._kf.fid)
        if fe._init_fid is not None:
            keep.add(fe._init_fid)
        newest = fe._fid - 1
        for fid in list(self.frames):
            if fid not in keep and fid != newest and fid != fe._prev_fid:
                fe.source.remove_frame(fid)
                self.frames.remove(fid)
        for fid, kf in fe._kfs.items():
            if fid not in keep and kf.D is not None:
                kf.release()
