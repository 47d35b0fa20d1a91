"""The pointmap frontend's per-frame tracking by the pair of pointmaps (steps 1-5 and 7 of :mod:`.frontend`):
the frame tracked against the current keyframe (:class:`~.tracker.PointmapTracker`); when it falls short,
the look-back keyframe (:meth:`~.mapping.PointmapKeyframing.promote_last`), then for monocular frames PnP
on the source's flow, for RGB-D depth alignment the depth alone, then relocalisation
(:func:`~.relocalization.relocalize`); a tracked frame is fused into its keyframe and may become a new
keyframe. A frame nothing poses is a :class:`~.tracker.TrackingLost` (the frontend gives it the motion
model's pose)."""

from __future__ import annotations

import time

import numpy as np

from ..base import FrameStatus
from ..records import RelativePose
from .keyframes import PointmapKeyframe
from .mapping import PointmapKeyframing
from .relocalization import relocalize
from .source import PointmapPair
from .state import PointmapState
from .tracker import PointmapTracker, TrackingLost, matrix_of


class PairTracking:
    """Tracks each frame of the shared state by the pair of pointmaps (module docstring), against its
    keyframes through ``tracker``; new keyframes and fusion through ``keyframing``."""

    def __init__(self, state: PointmapState, tracker: PointmapTracker, keyframing: PointmapKeyframing):
        self.state = state
        self.tracker = tracker
        self.keyframing = keyframing

    def track(self, fid: int, frame, inputs, pair: PointmapPair | None = None) -> FrameStatus | TrackingLost:
        """Track frame ``fid`` (``inputs``: its working-resolution images) against the current keyframe;
        ``pair``: the pair to track it with (the monocular map's start), else the source's."""
        st = self.state
        kf = st.kf
        st.T_WC_imu = st.prior_T_WC(frame.timestamp)
        surface = st.frame_surface
        res = self.tracker.track_against(kf, fid, st.T_CkCf, st.uv_prev, pair, surface)
        events = []
        if res is not None and res.get("held") is not None:  # no confident flow, the depth holds it
            return self._track_by_depth(kf, fid, frame, inputs, res, res["held"], events, "no confident flow")
        min_fraction = st.config.tracking.min_valid_fraction
        if not self.tracker.ok(res, min_fraction) and self.keyframing.promote_last():
            events.append(f"keyframe {st.kf.fid} (look-back)")  # the last good frame became the keyframe
            kf = st.kf
            res = self.tracker.track_against(kf, fid, st.T_CkCf, None, surface=surface)
        if not self.tracker.ok(res, min_fraction) and st.kind == "mono":
            tracked = self._track_pnp(fid, frame)  # no (usable) two-view pointmap: pose by PnP
            tracked.events[:0] = events
            return tracked
        if not self.tracker.ok(res, min_fraction) and st.depth.enabled:
            held = self.tracker.by_depth(kf, res, surface)
            if held is not None:  # the matches lost it, the depth holds it
                return self._track_by_depth(kf, fid, frame, inputs, res, held, events, f"{res['n_valid']} valid matches")
        if not self.tracker.ok(res, min_fraction):
            found = relocalize(st, self.tracker, fid, frame)
            if found is None:
                why = "no pair" if res is None else (f"{res['n_valid']} valid matches ({100 * res['fraction']:.0f} %), "
                                                     f"{res['inliers']} inliers")
                return TrackingLost(f"tracking lost: {why}")
            kf, res = found
            st.kf, st.uv_prev, st.since_kf = kf, None, 0
            source = "relocalized"
        else:
            source = "tracked"
            st.uv_prev = res["matches"].uv_lm
        T_CkCf = res["T"]
        st.T_CkCf = matrix_of(T_CkCf)
        self.keyframing.fuse(kf, T_CkCf, res)
        st.since_kf += 1
        new_kf = res["fraction"] < st.config.keyframe.new_fraction or (
            st.config.keyframe.max_gap > 0 and st.since_kf >= st.config.keyframe.max_gap)
        st.last_good = None
        if new_kf:
            self.keyframing.make_keyframe(kf, fid, frame, inputs, res)
            events.append(f"keyframe {fid}")
        else:
            st.records[fid] = RelativePose(kf.fid, st.T_CkCf.copy())
            if source == "tracked":  # a keyframe candidate when the next frame no longer tracks against kf
                st.last_good = (fid, frame, inputs, res, st.T_CkCf.copy())
        return st.status(fid, frame, source, new_kf, res["inliers"], events)

    def _track_by_depth(self, kf: PointmapKeyframe, fid: int, frame, inputs, res, held, events,
                        why: str) -> FrameStatus:
        """Frame ``fid`` tracked against ``kf`` by depth alone (``held``: its ``T_CkCf`` and the share of its
        depth points paired): nothing fused; a new keyframe (joined to ``kf`` by its depth block) when that
        share falls below ``keyframe.new_fraction`` (or after ``keyframe.max_gap`` frames)."""
        st = self.state
        T_CkCf, share = held
        st.T_CkCf = T_CkCf
        st.uv_prev = None
        st.last_good = None
        st.since_kf += 1
        st.counts["depth_tracked"] += 1
        events.append(f"tracked by depth ({why}, {100 * share:.0f} % of the depth paired)")
        new_kf = share < st.config.keyframe.new_fraction or (
            st.config.keyframe.max_gap > 0 and st.since_kf >= st.config.keyframe.max_gap)
        if new_kf:
            res = {**res, "inlier": None}
            self.keyframing.make_keyframe(kf, fid, frame, inputs, res)
            events.append(f"keyframe {fid}")
        else:
            st.records[fid] = RelativePose(kf.fid, st.T_CkCf.copy())
        return st.status(fid, frame, "tracked", new_kf, 0, events)

    def _track_pnp(self, fid: int, frame) -> FrameStatus | TrackingLost:
        """Monocular frame without a two-view pointmap: PnP on the flow against the canonical pointmap,
        else relocalisation."""
        st = self.state
        kf = st.kf
        t0 = time.perf_counter()
        T_CkCf = st.source.pnp_pose(kf.fid, fid, kf.X.view(kf.H, kf.W, 3).numpy(), kf.C.view(kf.H, kf.W).numpy())
        st.times["tracking"] += time.perf_counter() - t0
        if T_CkCf is None:
            found = relocalize(st, self.tracker, fid, frame)
            if found is None:
                return TrackingLost("tracking lost: no two-view pointmap and no PnP pose")
            kf, res = found
            st.kf, st.uv_prev, st.since_kf = kf, None, 0
            st.T_CkCf = matrix_of(res["T"])
            st.records[fid] = RelativePose(kf.fid, st.T_CkCf.copy())
            return st.status(fid, frame, "relocalized", num_valid=res["inliers"])
        st.T_CkCf = np.asarray(T_CkCf, np.float64)
        st.uv_prev = None
        st.records[fid] = RelativePose(kf.fid, st.T_CkCf.copy())
        st.counts["pnp_tracked"] += 1
        return st.status(fid, frame, "tracked", events=["pnp: little parallax"])
