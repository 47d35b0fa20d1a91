"""The pointmap frontend's source cache: which frames the measurement source holds (the current frame,
the previous tracked one, the newest keyframes), added on demand and released after each frame."""

from __future__ import annotations

import time

from .keyframes import PointmapKeyframe
from .state import PointmapState


class SourceCache:
    """The frames loaded in the shared state's source (oldest first); adding counts as ``source`` time."""

    def __init__(self, state: PointmapState):
        self.state = state
        self.frames: list[int] = []

    def __contains__(self, fid: int) -> bool:
        return fid in self.frames

    def add(self, fid: int, grey, depth, right) -> None:
        """Load frame ``fid`` into the source unless it is loaded."""
        st = self.state
        t0 = time.perf_counter()
        if fid not in self.frames:
            st.source.add_frame(fid, grey, depth=depth, right=right)
            self.frames.append(fid)
        st.times["source"] += time.perf_counter() - t0

    def ensure(self, kf: PointmapKeyframe) -> None:
        """Keyframe ``kf`` loaded in the source (re-added from its images when it was released)."""
        self.add(kf.fid, kf.grey, kf.depth, kf.right)

    def release(self, newest: int) -> None:
        """Keep the source caches of the current frame ``newest``, the previous tracked one and the newest
        keyframes only."""
        st = self.state
        keep = set(list(st.kfs)[-st.config.keyframe.keep_source_frames:])
        if st.kf is not None:
            keep.add(st.kf.fid)
        if st.init_fid is not None:
            keep.add(st.init_fid)
        for fid in list(self.frames):
            if fid not in keep and fid != newest and fid != st.prev_fid:
                st.source.remove_frame(fid)
                self.frames.remove(fid)
        for fid, kf in st.kfs.items():
            if fid not in keep and kf.D is not None:
                kf.release()
