"""The pointmap frontend's tracking of a frame against a keyframe (steps 1-3 of :mod:`.frontend`): the
pair of pointmaps from the source, projective matching, the relative pose ``T_CkCf`` by
:func:`.tracking.track_pose`, and the PnP fallback of monocular frames without a two-view pointmap."""

from __future__ import annotations

import logging
import time
from dataclasses import replace
from typing import TYPE_CHECKING

import numpy as np
import torch

from ...errors import DataError
from ...lie import Sim3
from ..base import FrameStatus
from ..records import RelativePose, rigid
from .features import carry_pointmap
from .keyframes import PointmapKeyframe, even_subset, match_frame
from .relocalization import relocalize
from ..depth_tracking import pose_information
from .tracking import TRACK_KEYS, fuse_pointmap, track_pose

if TYPE_CHECKING:
    from .frontend import PointmapFrontend

logger = logging.getLogger(__name__)


def sim3_of(M: np.ndarray) -> Sim3:
    """The :class:`~fgslam.lie.Sim3` of a 4x4 matrix."""
    return Sim3.from_matrix(torch.as_tensor(np.asarray(M, np.float64)))


def matrix_of(T: Sim3) -> np.ndarray:
    """The 4x4 float64 matrix of a :class:`~fgslam.lie.Sim3`."""
    return T.matrix().numpy().astype(np.float64)


class PointmapTracker:
    """Tracks frames against the keyframes of ``frontend`` (its source, source cache, working camera,
    query grid, motion state and stage times)."""

    def __init__(self, frontend: "PointmapFrontend"):
        self.fe = frontend
        self.held = None  # the current frame tracked by depth alone: (T_CkCf, share of its depth paired); RGB-D

    def pair_in(self, kf: PointmapKeyframe, fid: int, T_CkCf_pred: np.ndarray, pair=None, surface=None):
        """``(X_f^f (HW, 3), X_f^k (HW, 3), C_f (HW,), D_f, T_CkCf0 (4x4))`` of frame ``fid`` against keyframe
        ``kf`` (module docstring of :mod:`.frontend`, step 1); None when the two-view source found no pose.
        ``surface``: the frame's depth surface (RGB-D depth alignment): a prediction the image could not
        measure (no PnP pose on the flow; always with ``depth_align.prealign``) is aligned by depth first."""
        fe = self.fe
        t0 = time.perf_counter()
        fe.source_cache.ensure(kf)
        if fe.kind in ("rgbd", "stereo"):
            if pair is None:
                T_CkCf_pred, measured = self._measured_prediction(kf, fid, T_CkCf_pred)
                if not measured or fe.depth.config.prealign:
                    T_CkCf_pred, held = self._depth_prediction(kf, T_CkCf_pred, surface)
                    self.held = held if not measured else None
                pair = fe.source.predict(kf.fid, fid, rigid(T_CkCf_pred))
            T_CkCf0 = pair.T_CiCj
            a = 1.0
        else:
            pair = fe.source.predict(kf.fid, fid) if pair is None else pair
            if pair.T_CiCj is None:
                fe._times["source"] += time.perf_counter() - t0
                return None
            a = self._pair_scale(kf, pair)
            if a is None:
                fe._times["source"] += time.perf_counter() - t0
                return None
            T_CkCf0 = np.array(pair.T_CiCj, dtype=np.float64)
            T_CkCf0[:3, :] *= a
        fe._times["source"] += time.perf_counter() - t0
        n = fe.cam.H * fe.cam.W
        X_ff = torch.from_numpy(np.ascontiguousarray(pair.X_j_in_j, np.float32)).reshape(n, 3)
        X_fk = torch.from_numpy(np.ascontiguousarray(pair.X_j_in_i, np.float32)).reshape(n, 3) * a
        C_f = torch.from_numpy(np.ascontiguousarray(pair.C_j, np.float32)).reshape(n)
        D_f = torch.from_numpy(np.ascontiguousarray(pair.D_j, np.float32)).reshape(n, -1)
        return X_ff, X_fk, C_f, D_f, T_CkCf0

    def _measured_prediction(self, kf: PointmapKeyframe, fid: int, T_CkCf_pred: np.ndarray) -> tuple[np.ndarray, bool]:
        """Metric sources: ``T_CkCf`` with the last step measured by PnP on the dense flow from the previous
        frame (``T_CkCp T_CpCf``; from the keyframe itself right after a keyframe change), which stays
        reliable at video rate where the flow to an older keyframe fails; ``T_CkCf_pred`` when that fails.
        Second: whether the image measured it (``tracking.measure_pose`` off: counted as measured). Where
        the image measures nothing, the motion prior's (IMU) pose of the frame when there is one."""
        fe = self.fe
        # the motion prior's (IMU) pose of the frame, where the image measures none (else the last pose)
        T_CkCf_imu = fe.prior_T_CkCf(kf.fid)
        fallback = T_CkCf_pred if T_CkCf_imu is None else T_CkCf_imu
        if not fe.config.tracking.measure_pose:
            return fallback, True
        prev = fe._prev_fid
        if prev is None or prev not in fe.source_cache or prev == kf.fid or fe._prev_kf != kf.fid:
            T_CkCf = fe.source.predict(kf.fid, fid, None).T_CiCj
            return (fallback, False) if T_CkCf is None else (np.asarray(T_CkCf, np.float64), True)
        T_CpCf = fe.source.predict(prev, fid, None).T_CiCj
        return (fallback, False) if T_CpCf is None else (T_CkCf_pred @ np.asarray(T_CpCf, np.float64), True)

    def _depth_prediction(self, kf: PointmapKeyframe, T_CkCf_pred: np.ndarray, surface):
        """RGB-D depth alignment: the prediction ``T_CkCf_pred`` aligned to ``kf`` by depth when the depth
        constrains all six rigid directions there, else unchanged; second ``(T_CkCf, share of the frame's
        depth points paired)`` when it does, else None."""
        fe = self.fe
        block = self.depth_block(kf, surface)
        if block is None:
            return T_CkCf_pred, None
        t0 = time.perf_counter()
        T, constraint = fe.depth.hold(block, np.eye(4), rigid(T_CkCf_pred))
        fe._times["depth"] += time.perf_counter() - t0
        if not constraint.ok:
            return T_CkCf_pred, None
        return rigid(T), (rigid(T), constraint.pairs / max(block.num_points, 1))

    def _pair_scale(self, kf: PointmapKeyframe, pair) -> float | None:
        """Scale taking the pair's pointmap of k to k's canonical one: median ratio of the norms over the
        pixels confident in both."""
        cfg = self.fe.config.tracking
        X_pair = torch.from_numpy(np.ascontiguousarray(pair.X_i_in_i, np.float32)).reshape(-1, 3)
        C_pair = torch.from_numpy(np.ascontiguousarray(pair.C_i, np.float32)).reshape(-1)
        ok = (C_pair >= cfg.min_confidence) & (kf.C > 0)
        if int(ok.sum()) < cfg.min_matches:
            logger.info("pointmap: pair (%d, %d) shares %d confident pixels with the canonical pointmap; no scale",
                        kf.fid, pair.j, int(ok.sum()))
            return None
        ratio = torch.linalg.vector_norm(kf.X[ok], dim=-1) / torch.linalg.vector_norm(X_pair[ok], dim=-1).clamp_min(1e-9)
        return float(ratio.median())

    def depth_block(self, kf: PointmapKeyframe, surface):
        """The depth block of a frame with depth ``surface`` against ``kf`` over the tracking problem's keys
        (RGB-D depth alignment; None without it or without both surfaces)."""
        if not self.fe.depth.enabled or surface is None or kf.surface is None:
            return None
        return self.fe.depth.block(*TRACK_KEYS, kf.surface, surface)

    def track_against(self, kf: PointmapKeyframe, fid: int, T_CkCf_pred: np.ndarray, warm: torch.Tensor | None,
                      pair=None, surface=None, fixed_scale: bool | None = None):
        """Match and track frame ``fid`` against ``kf``; returns a dict with the result, or None (no pair).
        ``surface``: the frame's depth surface (RGB-D depth alignment): a depth block against the
        keyframe's joins the pose solve; kept in the result (``surface``). ``fixed_scale``: SE(3) tracking
        (None: the frontend's)."""
        fe = self.fe
        cfg = fe.config
        self.held = None
        got = self.pair_in(kf, fid, T_CkCf_pred, pair, surface)
        if got is None:
            return None
        X_ff, X_fk, C_f, D_f, T_CkCf0 = got
        if self.held is not None:  # no confident flow (the image measured nothing) but the depth holds the frame
            return {"n_valid": 0, "fraction": 0.0, "X_ff": X_ff, "C_f": C_f, "D_f": D_f, "T": None, "inliers": 0,
                    "surface": surface, "held": self.held}
        q = fe.query
        qvalid = (C_f[q] >= cfg.tracking.min_confidence) & torch.isfinite(X_fk[q]).all(-1)
        t0 = time.perf_counter()
        if cfg.tracking.warm_start == "projection":
            warm = None  # match_frame starts from the projection of the query points
        m = match_frame(kf, X_fk[q], qvalid, D_f[q], warm, fe.cam.K, cfg.matching, cfg.source.descriptor)
        t1 = time.perf_counter()
        fe._times["matching"] += t1 - t0
        n_points = max(int(qvalid.sum()), 1)
        n_valid = int(m.valid.sum())
        out = {"matches": m, "n_valid": n_valid, "fraction": n_valid / n_points, "X_ff": X_ff, "C_f": C_f,
               "D_f": D_f, "T": None, "inliers": 0, "surface": surface}
        if n_valid < cfg.tracking.min_matches:
            return out
        sel = even_subset(m.valid.nonzero().squeeze(1), cfg.tracking.max_query_points)
        qi, p = q[sel], m.index[sel]
        X_f = X_ff[qi].to(torch.float64)
        X_k = kf.X[p].to(torch.float64)
        w = torch.sqrt(C_f[qi].clamp(max=1.0) * kf.C[p].clamp(max=1.0)).to(torch.float64)
        uv = m.uv[sel].to(torch.float64)
        depth = self.depth_block(kf, surface)
        fixed = fe.fixed_scale if fixed_scale is None else fixed_scale
        tr = track_pose(sim3_of(T_CkCf0), X_f, X_k, w, cfg.block, cfg.tracking, fixed, uv, fe.K_t,
                        () if depth is None else (depth,))
        fe._times["tracking"] += time.perf_counter() - t1
        out.update(T=tr.T_CkCf, inliers=tr.num_inliers, sel=sel, qi=qi, p=p, X_f=X_f, X_k=X_k, w=w, uv=uv,
                   inlier=tr.inlier)
        return out

    def by_depth(self, kf: PointmapKeyframe, res, surface):
        """A frame whose matches fall short, tracked by depth (RGB-D depth alignment): the predicted
        ``T_CkCf`` aligned to ``kf`` by depth, with the information of the frame's matches when the
        tracking got as far as a pose; ``(T_CkCf 4x4, share of the frame's depth points paired)`` when
        that constrains all six rigid directions, else None."""
        fe = self.fe
        block = self.depth_block(kf, surface)
        if block is None or res is None:
            return None
        t0 = time.perf_counter()
        H_image = None
        if res.get("sel") is not None:
            from ...factors.pointmap_block import PointmapBlock, PointmapEdge

            edge = PointmapEdge(*TRACK_KEYS, res["X_k"], res["X_f"], res["w"],
                                res["uv"] if fe.config.block.mode == "calibrated" else None)
            image = PointmapBlock([edge], fe.config.block, fe.cam.K)

            def image_information(T):
                import gtsam

                values = gtsam.Values()
                values.insert(TRACK_KEYS[0], gtsam.Similarity3())
                values.insert(TRACK_KEYS[1], sim3_of(T).to_gtsam())
                return pose_information([image], values, TRACK_KEYS[1])

            H_image = image_information
        T, constraint = fe.depth.hold(block, np.eye(4), rigid(fe._T_CkCf), H_image)
        fe._times["depth"] += time.perf_counter() - t0
        if not constraint.ok:
            return None
        return rigid(T), constraint.pairs / max(block.num_points, 1)

    def ok(self, res, min_fraction: float) -> bool:
        """Whether the tracking result ``res`` has a pose, enough inliers and ``min_fraction`` valid matches."""
        return (res is not None and res["T"] is not None and res["inliers"] >= self.fe.config.tracking.min_matches
                and res["fraction"] >= min_fraction)

    def track_pnp(self, fid: int, frame) -> FrameStatus:
        """Monocular frame without a two-view pointmap: PnP on the flow against the canonical pointmap."""
        fe = self.fe
        kf = fe._kf
        t0 = time.perf_counter()
        T_CkCf = fe.source.pnp_pose(kf.fid, fid, kf.X.view(kf.H, kf.W, 3).numpy(), kf.C.view(kf.H, kf.W).numpy())
        fe._times["tracking"] += time.perf_counter() - t0
        if T_CkCf is None:
            found = relocalize(fe, fid, frame)
            if found is None:
                return fe._fail(fid, frame, "tracking lost: no two-view pointmap and no PnP pose")
            kf, res = found
            fe._kf, fe._uv_prev, fe._since_kf = kf, None, 0
            fe._T_CkCf = matrix_of(res["T"])
            fe._records[fid] = RelativePose(kf.fid, fe._T_CkCf.copy())
            return fe._status(fid, frame, "relocalized", num_valid=res["inliers"])
        fe._T_CkCf = np.asarray(T_CkCf, np.float64)
        fe._uv_prev = None
        fe._records[fid] = RelativePose(kf.fid, fe._T_CkCf.copy())
        fe._counts["pnp_tracked"] += 1
        return fe._status(fid, frame, "tracked", events=["pnp: little parallax"])

    # ------------------------------------------------------------------ monocular: the features' pose (issue 28)
    @staticmethod
    def _maps(kf: PointmapKeyframe) -> tuple[np.ndarray, np.ndarray]:
        """Keyframe ``kf``'s canonical pointmap ``(H, W, 3)`` and confidence ``(H, W)`` (numpy views)."""
        return kf.X.view(kf.H, kf.W, 3).numpy(), kf.C.view(kf.H, kf.W).numpy()

    def start_features(self, fid: int, grey: np.ndarray) -> None:
        """After the map's start (or any keyframe change outside :meth:`track_features`): corners of the
        current keyframe, and frame ``fid`` (posed at ``_T_CkCf``) joined to their tracks when it is not
        the keyframe."""
        fe = self.fe
        kf = fe._kf
        fe.features.reset(kf.fid, kf.grey, *self._maps(kf))
        if kf.fid != fid:
            meas, uv, keep = fe.features.track(grey, fe.features.project(fe._T_CkCf))
            if meas.T_CkCf is not None:
                fe.features.commit(grey, uv, keep)

    def track_features(self, fid: int, frame, inputs) -> FrameStatus:
        """Monocular frame posed by the features (:mod:`.features`): ``T_CkCf`` by KLT and PnP against the
        keyframe's canonical pointmap; a new keyframe (:meth:`_feature_keyframe`) when the inliers fall
        below ``features.new_keyframe_fraction`` of the keyframe's corners; when unmeasured: the two-view
        pair against the keyframe, relocalisation, else a reported failure (never the prediction)."""
        fe = self.fe
        kf = fe._kf
        grey = inputs[0]
        ft = fe.features
        if ft.kf_fid != kf.fid:
            self.start_features(kf.fid, grey)
        t0 = time.perf_counter()
        meas, uv, keep = ft.track(grey)
        fe._times["tracking"] += time.perf_counter() - t0
        if meas.T_CkCf is None:
            return self._features_lost(fid, frame, inputs, meas.why)
        ft.commit(grey, uv, keep)
        fe._T_CkCf = np.asarray(meas.T_CkCf, np.float64)
        fe._since_kf += 1
        if fe.config.features.fuse_corners:
            self._fuse_corners(kf, fe._T_CkCf)
        kc = fe.config.keyframe
        fc = fe.config.features
        # the absolute rule asks the tracks to have *fallen* below new_keyframe_inliers: a keyframe born with
        # fewer corners (a poor view) is kept until the fractional rule, else every next frame, one frame of
        # parallax away, would become a keyframe (a cascade that one corner more or less at birth decides)
        fell = ft.count >= fc.new_keyframe_inliers and meas.inliers < fc.new_keyframe_inliers
        new_kf = (meas.fraction < fc.new_keyframe_fraction or fell
                  or (kc.max_gap > 0 and fe._since_kf >= kc.max_gap))
        if not new_kf:
            fe._records[fid] = RelativePose(kf.fid, fe._T_CkCf.copy())
            fe._counts["feature_tracked"] += 1
            return fe._status(fid, frame, "tracked", num_valid=meas.inliers)
        events = self._feature_keyframe(kf, fid, frame, inputs, fe._T_CkCf)
        return fe._status(fid, frame, "tracked", True, meas.inliers, events)

    def _fuse_corners(self, kf: PointmapKeyframe, T_CkCf: np.ndarray) -> None:
        """Eq. 9 on the corners: each tracked corner triangulated from its keyframe pixel and its pixel in the
        frame at ``T_CkCf`` (confidence from the triangulation angle), fused into ``kf``'s canonical
        pointmap; the corners' points follow (``bookkeeping`` time)."""
        fe = self.fe
        ft = fe.features
        t0 = time.perf_counter()
        X, conf = fe.source.triangulate(ft.uv_k, ft.uv, T_CkCf)
        index = torch.from_numpy(ft.pixels(kf.W))
        fuse_pointmap(kf.X, kf.C, index, torch.from_numpy(X.astype(np.float32)), torch.from_numpy(conf.astype(np.float32)),
                      fe.config.keyframe.max_confidence)
        kf.changed()
        ft.X_k = kf.X[index].numpy().astype(np.float64)
        fe._times["bookkeeping"] += time.perf_counter() - t0

    def _feature_keyframe(self, kf: PointmapKeyframe, fid: int, frame, inputs, T_CkCf: np.ndarray) -> list[str]:
        """Frame ``fid``, measured at ``T_CkCf``, becomes a keyframe: its pointmap triangulated from the dense
        flow with that pose (where confident; elsewhere ``kf``'s canonical points seen from it, confidence
        times ``features.carried_confidence``); projective matching and the tracking solve refine the pose
        and give the edge to ``kf``; when they fall short, the edge is made of the corners' PnP inliers."""
        fe = self.fe
        fc = fe.config.features
        grey = inputs[0]
        t0 = time.perf_counter()
        fe.source_cache.ensure(kf)
        fe.source_cache.add(fid, grey, None, None)
        pair = fe.source.predict(kf.fid, fid, T_CkCf)
        X_k, C_k = self._maps(kf)
        X_c, C_c = carry_pointmap(X_k, C_k, T_CkCf, fe.cam.K)
        C_c = np.minimum(C_c, 1.0) * fc.carried_confidence
        fill = C_c > pair.C_j
        X_ff = np.where(fill[..., None], X_c, pair.X_j_in_j).astype(np.float32)
        C_f = np.where(fill, C_c, pair.C_j).astype(np.float32)
        X_fk = (X_ff.reshape(-1, 3) @ T_CkCf[:3, :3].T.astype(np.float32) + T_CkCf[:3, 3].astype(np.float32))
        X_fk = X_fk.reshape(X_ff.shape) * (C_f > 0)[..., None]
        # the pair's pointmap of k is k's canonical one: the pose is in the map's scale (no pair scale)
        pair = replace(pair, X_i_in_i=X_k, C_i=np.minimum(C_k, 1.0), X_j_in_j=X_ff, X_j_in_i=X_fk, C_j=C_f,
                       T_CiCj=T_CkCf)
        fe._times["source"] += time.perf_counter() - t0
        refine = fc.keyframe_refine
        res = None if refine == "off" else self.track_against(kf, fid, T_CkCf, None, pair=pair,
                                                              fixed_scale=refine == "se3")
        events = [f"keyframe {fid}"]
        if self.ok(res, fe.config.tracking.min_valid_fraction):
            fe._T_CkCf = matrix_of(res["T"])
            fe.keyframing.fuse(kf, res["T"], res)
        else:
            res = self._feature_edge(pair, T_CkCf)
            events.append("edge from the corners")
        fe._last_good = None
        fe.keyframing.make_keyframe(kf, fid, frame, inputs, res)
        fe.features.reset(fid, grey, *self._maps(fe._kf))
        added = fe.graph.window_edges(fe._kf, list(fe._kfs)[-2 - fc.extra_edges:-2])
        if added:
            events.append(f"{added} window edges")
        return events

    def _feature_edge(self, pair, T_CkCf: np.ndarray) -> dict:
        """The tracking result of a new keyframe whose matches fell short: its pointmap from ``pair`` and the
        edge of the corners' PnP inliers (their canonical points and the same points in the frame)."""
        fe = self.fe
        ft = fe.features
        n = fe.cam.H * fe.cam.W
        X_k = torch.from_numpy(ft.X_k)
        T_CfCk = np.linalg.inv(T_CkCf)
        X_f = torch.from_numpy(ft.X_k @ T_CfCk[:3, :3].T + T_CfCk[:3, 3])
        return {"X_ff": torch.from_numpy(np.ascontiguousarray(pair.X_j_in_j, np.float32)).reshape(n, 3),
                "C_f": torch.from_numpy(np.ascontiguousarray(pair.C_j, np.float32)).reshape(n),
                "D_f": torch.from_numpy(np.ascontiguousarray(pair.D_j, np.float32)).reshape(n, -1),
                "X_k": X_k, "X_f": X_f, "w": torch.ones(len(X_k), dtype=torch.float64),
                "uv": torch.from_numpy(ft.uv_k), "inlier": torch.ones(len(X_k), dtype=torch.bool),
                "surface": None}

    def _features_lost(self, fid: int, frame, inputs, why: str) -> FrameStatus:
        """The features measured no pose: the two-view pair against the current keyframe (the essential
        matrix on the dense flow, independent of the prediction), then relocalisation; otherwise a
        reported failure (``motion_model``)."""
        fe = self.fe
        fe.source_cache.add(fid, inputs[0], None, None)
        kf = fe._kf
        res = None
        try:
            res = self.track_against(kf, fid, fe._T_CkCf, None)
        except DataError as exc:  # pragma: no cover - the frames are loaded above
            logger.info("pointmap frame %d: two-view pair failed: %s", frame.index, exc)
        if self.ok(res, fe.config.relocalization.min_valid_fraction):
            source, event = "tracked", f"features lost ({why}); two-view pair"
        else:
            found = relocalize(fe, fid, frame)
            if found is None:
                return fe._fail(fid, frame, f"tracking lost: {why}; no two-view pose, not relocalised")
            (kf, res), source, event = found, "relocalized", f"features lost ({why}); relocalised"
            fe._kf, fe._since_kf = kf, 0
        fe._uv_prev = None
        fe._T_CkCf = matrix_of(res["T"])
        fe._records[fid] = RelativePose(kf.fid, fe._T_CkCf.copy())
        fe.features.rebase(kf.fid, kf.grey, *self._maps(kf), inputs[0], fe._T_CkCf)
        return fe._status(fid, frame, source, num_valid=res["inliers"], events=[event])
