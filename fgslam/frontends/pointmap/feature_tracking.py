"""The pointmap frontend's per-frame pose of monocular frames by the features (issue 28, ``features.mode:
features``; :mod:`.features`): the current keyframe's corners tracked by KLT and ``T_CkCf`` by PnP against
its canonical pointmap; a new keyframe when the tracks thin out (its pointmap triangulated from the dense
flow with the measured pose, refined and joined to the previous keyframe); a frame the corners cannot pose
is tried with the two-view pair, then relocalised, else it is a :class:`~.tracker.TrackingLost` (never
the prediction)."""

from __future__ import annotations

import logging
import time
from dataclasses import replace

import numpy as np
import torch

from ...core.errors import DataError
from ..base import FrameStatus
from ..records import RelativePose
from .cache import SourceCache
from .edges import PointmapGraph
from .features import carry_pointmap
from .keyframes import PointmapKeyframe
from .mapping import PointmapKeyframing
from .relocalization import relocalize
from .state import PointmapState
from .tracker import PointmapTracker, TrackingLost, matrix_of
from .tracking import fuse_pointmap

logger = logging.getLogger(__name__)


def _maps(kf: PointmapKeyframe) -> tuple[np.ndarray, np.ndarray]:
    """Keyframe ``kf``'s canonical pointmap ``(H, W, 3)`` and confidence ``(H, W)`` (numpy views)."""
    return kf.X.view(kf.H, kf.W, 3).numpy(), kf.C.view(kf.H, kf.W).numpy()


class FeatureTracking:
    """Poses the monocular frames of the shared state by its feature tracks (module docstring): frames
    loaded through ``cache``, the two-view fallback and refinement through ``tracker``, new keyframes
    through ``keyframing``, their extra edges through ``graph``."""

    def __init__(self, state: PointmapState, cache: SourceCache, tracker: PointmapTracker,
                 keyframing: PointmapKeyframing, graph: PointmapGraph):
        self.state = state
        self.cache = cache
        self.tracker = tracker
        self.keyframing = keyframing
        self.graph = graph

    def start(self, fid: int, grey: np.ndarray) -> None:
        """After the map's start (or any keyframe change outside :meth:`track`): corners of the current
        keyframe, and frame ``fid`` (posed at ``T_CkCf``) joined to their tracks when it is not the
        keyframe."""
        st = self.state
        kf = st.kf
        st.features.reset(kf.fid, kf.grey, *_maps(kf))
        if kf.fid != fid:
            meas, uv, keep = st.features.track(grey, st.features.project(st.T_CkCf))
            if meas.T_CkCf is not None:
                st.features.commit(grey, uv, keep)

    def track(self, fid: int, frame, inputs) -> FrameStatus | TrackingLost:
        """Monocular frame posed by the features: ``T_CkCf`` by KLT and PnP against the keyframe's canonical
        pointmap; a new keyframe (:meth:`_keyframe`) when the inliers fall below
        ``features.new_keyframe_fraction`` of the keyframe's corners; when unmeasured: the two-view pair
        against the keyframe, relocalisation, else lost (never the prediction)."""
        st = self.state
        kf = st.kf
        grey = inputs[0]
        ft = st.features
        if ft.kf_fid != kf.fid:
            self.start(kf.fid, grey)
        t0 = time.perf_counter()
        meas, uv, keep = ft.track(grey)
        st.times["tracking"] += time.perf_counter() - t0
        if meas.T_CkCf is None:
            return self._lost(fid, frame, inputs, meas.why)
        ft.commit(grey, uv, keep)
        st.T_CkCf = np.asarray(meas.T_CkCf, np.float64)
        st.since_kf += 1
        if st.config.features.fuse_corners:
            self._fuse_corners(kf, st.T_CkCf)
        kc = st.config.keyframe
        fc = st.config.features
        # the absolute rule asks the tracks to have *fallen* below new_keyframe_inliers: a keyframe born with
        # fewer corners (a poor view) is kept until the fractional rule, else every next frame, one frame of
        # parallax away, would become a keyframe (a cascade that one corner more or less at birth decides)
        fell = ft.count >= fc.new_keyframe_inliers and meas.inliers < fc.new_keyframe_inliers
        new_kf = (meas.fraction < fc.new_keyframe_fraction or fell
                  or (kc.max_gap > 0 and st.since_kf >= kc.max_gap))
        if not new_kf:
            st.records[fid] = RelativePose(kf.fid, st.T_CkCf.copy())
            st.counts["feature_tracked"] += 1
            return st.status(fid, frame, "tracked", num_valid=meas.inliers)
        events = self._keyframe(kf, fid, frame, inputs, st.T_CkCf)
        return st.status(fid, frame, "tracked", True, meas.inliers, events)

    def _fuse_corners(self, kf: PointmapKeyframe, T_CkCf: np.ndarray) -> None:
        """Eq. 9 on the corners: each tracked corner triangulated from its keyframe pixel and its pixel in the
        frame at ``T_CkCf`` (confidence from the triangulation angle), fused into ``kf``'s canonical
        pointmap; the corners' points follow (``bookkeeping`` time)."""
        st = self.state
        ft = st.features
        t0 = time.perf_counter()
        X, conf = st.source.triangulate(ft.uv_k, ft.uv, T_CkCf)
        index = torch.from_numpy(ft.pixels(kf.W))
        fuse_pointmap(kf.X, kf.C, index, torch.from_numpy(X.astype(np.float32)), torch.from_numpy(conf.astype(np.float32)),
                      st.config.keyframe.max_confidence)
        kf.changed()
        ft.X_k = kf.X[index].numpy().astype(np.float64)
        st.times["bookkeeping"] += time.perf_counter() - t0

    def _keyframe(self, kf: PointmapKeyframe, fid: int, frame, inputs, T_CkCf: np.ndarray) -> list[str]:
        """Frame ``fid``, measured at ``T_CkCf``, becomes a keyframe: its pointmap triangulated from the dense
        flow with that pose (where confident; elsewhere ``kf``'s canonical points seen from it, confidence
        times ``features.carried_confidence``); projective matching and the tracking solve refine the pose
        and give the edge to ``kf``; when they fall short, the edge is made of the corners' PnP inliers."""
        st = self.state
        fc = st.config.features
        grey = inputs[0]
        t0 = time.perf_counter()
        self.cache.ensure(kf)
        self.cache.add(fid, grey, None, None)
        pair = st.source.predict(kf.fid, fid, T_CkCf)
        X_k, C_k = _maps(kf)
        X_c, C_c = carry_pointmap(X_k, C_k, T_CkCf, st.cam.K)
        C_c = np.minimum(C_c, 1.0) * fc.carried_confidence
        fill = C_c > pair.C_j
        X_ff = np.where(fill[..., None], X_c, pair.X_j_in_j).astype(np.float32)
        C_f = np.where(fill, C_c, pair.C_j).astype(np.float32)
        X_fk = (X_ff.reshape(-1, 3) @ T_CkCf[:3, :3].T.astype(np.float32) + T_CkCf[:3, 3].astype(np.float32))
        X_fk = X_fk.reshape(X_ff.shape) * (C_f > 0)[..., None]
        # the pair's pointmap of k is k's canonical one: the pose is in the map's scale (no pair scale)
        pair = replace(pair, X_i_in_i=X_k, C_i=np.minimum(C_k, 1.0), X_j_in_j=X_ff, X_j_in_i=X_fk, C_j=C_f,
                       T_CiCj=T_CkCf)
        st.times["source"] += time.perf_counter() - t0
        refine = fc.keyframe_refine
        res = None if refine == "off" else self.tracker.track_against(kf, fid, T_CkCf, None, pair=pair,
                                                                      fixed_scale=refine == "se3")
        events = [f"keyframe {fid}"]
        if self.tracker.ok(res, st.config.tracking.min_valid_fraction):
            st.T_CkCf = matrix_of(res["T"])
            self.keyframing.fuse(kf, res["T"], res)
        else:
            res = self._edge(pair, T_CkCf)
            events.append("edge from the corners")
        st.last_good = None
        self.keyframing.make_keyframe(kf, fid, frame, inputs, res)
        st.features.reset(fid, grey, *_maps(st.kf))
        added = self.graph.window_edges(st.kf, list(st.kfs)[-2 - fc.extra_edges:-2])
        if added:
            events.append(f"{added} window edges")
        return events

    def _edge(self, pair, T_CkCf: np.ndarray) -> dict:
        """The tracking result of a new keyframe whose matches fell short: its pointmap from ``pair`` and the
        edge of the corners' PnP inliers (their canonical points and the same points in the frame)."""
        st = self.state
        ft = st.features
        n = st.cam.H * st.cam.W
        X_k = torch.from_numpy(ft.X_k)
        T_CfCk = np.linalg.inv(T_CkCf)
        X_f = torch.from_numpy(ft.X_k @ T_CfCk[:3, :3].T + T_CfCk[:3, 3])
        return {"X_ff": torch.from_numpy(np.ascontiguousarray(pair.X_j_in_j, np.float32)).reshape(n, 3),
                "C_f": torch.from_numpy(np.ascontiguousarray(pair.C_j, np.float32)).reshape(n),
                "D_f": torch.from_numpy(np.ascontiguousarray(pair.D_j, np.float32)).reshape(n, -1),
                "X_k": X_k, "X_f": X_f, "w": torch.ones(len(X_k), dtype=torch.float64),
                "uv": torch.from_numpy(ft.uv_k), "inlier": torch.ones(len(X_k), dtype=torch.bool),
                "surface": None}

    def _lost(self, fid: int, frame, inputs, why: str) -> FrameStatus | TrackingLost:
        """The features measured no pose: the two-view pair against the current keyframe (the essential
        matrix on the dense flow, independent of the prediction), then relocalisation; otherwise lost."""
        st = self.state
        self.cache.add(fid, inputs[0], None, None)
        kf = st.kf
        res = None
        try:
            res = self.tracker.track_against(kf, fid, st.T_CkCf, None)
        except DataError as exc:  # pragma: no cover - the frames are loaded above
            logger.info("pointmap frame %d: two-view pair failed: %s", frame.index, exc)
        if self.tracker.ok(res, st.config.relocalization.min_valid_fraction):
            source, event = "tracked", f"features lost ({why}); two-view pair"
        else:
            found = relocalize(st, self.tracker, fid, frame)
            if found is None:
                return TrackingLost(f"tracking lost: {why}; no two-view pose, not relocalised")
            (kf, res), source, event = found, "relocalized", f"features lost ({why}); relocalised"
            st.kf, st.since_kf = kf, 0
        st.uv_prev = None
        st.T_CkCf = matrix_of(res["T"])
        st.records[fid] = RelativePose(kf.fid, st.T_CkCf.copy())
        st.features.rebase(kf.fid, kf.grey, *_maps(kf), inputs[0], st.T_CkCf)
        return st.status(fid, frame, source, num_valid=res["inliers"], events=[event])
