"""Loop closure of the patch frontend: the classical closer's glue (:mod:`fgslam.loop.closure`) and
proximity loop closure with the global bundle adjustment (DPV-SLAM sections 3.3 and 3.2).

:class:`PatchLoopClosure` is a mixin of :class:`fgslam.frontends.patch.PatchFrontend`; it works on
the host's state: ``config`` (:class:`~.config.PatchConfig`), ``graph`` (:class:`~.graph.PatchGraph`),
``source``, ``K`` / ``K_right`` / ``T_CRCL`` / ``width`` / ``height``, ``sensor_mode``, ``_reproj``,
``_records`` (pose records), ``_final`` (finalised keyframes), ``_inputs``, ``_last_fid``,
``_velocity``, ``_map_start_fid``, ``_times`` and the helpers ``_reproject_frame`` / ``_inside``. The host calls ``_loop_init`` once, then per frame
``_loop_poll_and_apply`` (before tracking), ``_loop_keep_image``, ``_loop_feed_keyframes`` and
``_prox_step`` (after), ``_loop_relocalize`` on a lost track and ``_loop_finish`` at the end.

Classical (``loop_config.mode`` classical or both): keyframes that can no longer be removed (graph
positions below ``len - 1 - keyframe_index``) go to a :class:`~fgslam.loop.closure.LoopCloser` with
their image and pose (``metric`` for stereo / RGB-D); its corrections are applied before a frame is
tracked (no BA running): graph and finalised poses ``T_WC <- U_k T_WC`` with the Sim(3) scale folded
into patch inverse depths (``d <- d / s_k``), relative pose records and the velocity re-expressed.
A lost track is relocalised on the keyframe database before a re-initialisation, whose anchor it
becomes (monocular: the new map gets a scale of its own).

Proximity (``mode`` proximity or both; ``patch.proximity``): every keyframe that settles is stored
(its source features, packed) and becomes a query; the best older keyframe that is close in the
current estimate (distance, viewing angle, mean reprojected displacement of its patches:
:mod:`.proximity`) gets long-range edges between its neighbourhood and the query's, measured by the
source (from the reprojection and from zero motion) and verified by a fundamental-matrix RANSAC;
then :func:`.global_ba.global_bundle_adjustment` optimises every keyframe pose of the current map
(held scale; held: keyframes known only through loop edges, and the gauge, the oldest one,
monocular two) and every patch depth over the active, inactive and loop edges. The result is
discarded when too few loop edges survive its robust weighting; otherwise the loop edges join the
inactive store, so later global BAs keep them.
"""

from __future__ import annotations

import logging
import time

import numpy as np

from ...factors.depth import depth_priors
from ...loop.closure import LoopCloser, LoopClosureConfig, LoopCorrection
from .global_ba import GlobalBAProblem, global_bundle_adjustment
from .graph import GraphFrame
from .proximity import Candidate, KeyframeStore, fundamental_inliers, held_frames, pose_filter

logger = logging.getLogger(__name__)


class PatchLoopClosure:
    """Loop-closure methods of the patch frontend (see the module docstring)."""

    # ------------------------------------------------------------------ global optimisation hooks
    def inactive_edges(self) -> dict:
        """The bounded store of inactive edges (see :class:`~.graph.InactiveEdges`)."""
        return self.graph.inactive.arrays()


    # ------------------------------------------------------------------ loop closure (fgslam.loop.closure)
    def _loop_init(self, loop_config: LoopClosureConfig | None) -> None:
        """A :class:`LoopCloser` when ``loop_config.mode`` is ``classical`` or ``both``; the proximity
        state (keyframe store, counters) when it is ``proximity`` or ``both``."""
        self.loop_config = loop_config if loop_config is not None else LoopClosureConfig()
        self.loop_config.validate()
        # stereo / RGB-D maps are metric (every pose scale 1): loop corrections are then SE(3)
        metric = self.sensor_mode != "mono"
        self.closer = LoopCloser(self.loop_config, metric=metric) if self.loop_config.classical else None
        self._prox_init()
        self._loop_images: dict[int, np.ndarray] = {}  # fid -> image, while the frame may become a loop keyframe
        self._loop_last_added = -1  # newest fid handed to the closer (ids must increase)
        self._loop_counts = {"corrections_applied": 0, "keyframes_added": 0, "relocalization_attempts": 0,
                             "relocalized": 0}
        if self.closer is not None:
            self._times["loop"] = 0.0

    def _loop_keep_image(self, fid: int, frame) -> None:
        """Keep the image of frame ``fid`` while it is in the graph (or buffered for initialisation)."""
        if self.closer is None:
            return
        self._loop_images[fid] = frame.image
        if self._init is not None:
            keep = {self._init.ref_fid} | {b[0] for b in self._init.buffer}
        else:
            keep = {f.fid for f in self.graph.frames}
        for old in [k for k in self._loop_images if k not in keep]:
            del self._loop_images[old]

    def _loop_poll_and_apply(self) -> None:
        """Apply the closer's newest correction, if any (called where no BA runs)."""
        if self.closer is None:
            return
        t0 = time.perf_counter()
        self._loop_apply(self.closer.poll())
        self._times["loop"] += time.perf_counter() - t0

    def _loop_apply(self, corr: LoopCorrection | None) -> None:
        """Apply a pose-graph correction (``fgslam.loop.closure`` module docstring): graph frames
        ``T_WC <- U_k T_WC`` with the scale folded into their patch inverse depths (sensor depths stay
        as measured), final poses (``abs`` records) likewise, poses relative to a reference (``rel``)
        and the motion model's velocity re-expressed in their reference's folded units; ``interp``
        records follow their two end poses."""
        if corr is None:
            return
        for f in list(self.graph.frames) + list(self._final.values()):
            f.T_WC, s = corr.apply_pose(f.fid, f.T_WC)
            f.inv_depth = f.inv_depth / s
        for fid, rec in list(self._records.items()):
            if rec is None:
                continue
            if rec[0] == "abs":
                self._records[fid] = ("abs", corr.apply_pose(fid, rec[1])[0]) + tuple(rec[2:])
            elif rec[0] == "rel" and corr.fold_scale:
                T_rel = LoopCorrection.fold_relative(rec[2], corr.update_for(rec[1])[1])
                self._records[fid] = ("rel", rec[1], T_rel) + tuple(rec[3:])
        if self._last_fid is not None and corr.fold_scale:
            self._velocity = LoopCorrection.fold_relative(self._velocity, corr.update_for(self._last_fid)[1])
        self._loop_counts["corrections_applied"] += 1
        logger.info("loop correction applied (%d loops accepted, %d keyframes in the pose graph)",
                    corr.n_accepted, len(corr.T_update))

    def _loop_add(self, positions) -> None:
        """Hand the graph frames at ``positions`` (poses final or about to be) to the closer, once each."""
        g = self.graph
        for p in positions:
            f = g.frames[p]
            image = self._loop_images.pop(f.fid, None)
            if f.fid <= self._loop_last_added or image is None:
                continue
            neighbours = [g.frames[q].fid for q in (p - 1, p + 1) if 0 <= q < len(g)]
            self.closer.add_keyframe(f.fid, f.timestamp, image, self.K.numpy(), f.T_WC, neighbours=neighbours)
            self._loop_last_added = f.fid
            self._loop_counts["keyframes_added"] += 1

    def _loop_feed_keyframes(self, all_frames: bool = False) -> None:
        """Feed keyframes that can no longer be removed (graph positions below
        ``len - 1 - keyframe_index``; every graph frame with ``all_frames``) and the latest graph poses."""
        if self.closer is None:
            return
        t0 = time.perf_counter()
        g = self.graph
        final = len(g) if all_frames else len(g) - 1 - self.config.tracking.keyframe_index
        self._loop_add(range(max(final, 0)))
        self.closer.update_poses({f.fid: f.T_WC for f in g.frames})
        self._times["loop"] += time.perf_counter() - t0

    def _loop_relocalize(self, fid: int, frame) -> np.ndarray | None:
        """Pose of a lost frame from the closer's keyframe database (``T_WC`` 4x4 in the map's units) or
        None; on success it becomes frame ``fid``'s pose, the anchor of the re-initialisation."""
        if self.closer is None:
            return None
        t0 = time.perf_counter()
        self._loop_counts["relocalization_attempts"] += 1
        found = self.closer.relocalize(frame.image, self.K.numpy())
        self._times["loop"] += time.perf_counter() - t0
        if found is None:
            return None
        kf_id, T_WC = found
        self._records[fid] = ("abs", np.asarray(T_WC, dtype=np.float64))
        self._loop_counts["relocalized"] += 1
        if self.sensor_mode == "mono":
            logger.info("frame %d relocalised on keyframe %d; monocular: the re-initialised map starts at this "
                        "pose but gets a scale of its own (not tied to the old map's)", frame.index, kf_id)
        else:
            logger.info("frame %d relocalised on keyframe %d", frame.index, kf_id)
        return T_WC

    def _loop_finish(self) -> None:
        """Feed the remaining graph frames, stop the closer and apply its last correction."""
        if self.closer is None:
            return
        self._loop_feed_keyframes(all_frames=True)
        t0 = time.perf_counter()
        self.closer.close()
        self._loop_apply(self.closer.poll())
        self._times["loop"] += time.perf_counter() - t0

    def loop_summary(self) -> dict | None:
        if self.closer is None and self._prox is None:
            return None
        index = {fid: idx for fid, _, idx in self._inputs}
        out: dict = {"mode": self.loop_config.mode}
        if self.closer is not None:
            loops = self.closer.loops
            out.update({**self._loop_counts,
                        "verifications": len(self.closer.verifications), "verified_loops": len(loops),
                        "accepted_loops": sum(rec.status == "accepted" for rec in loops),
                        "loop_frames": [[index.get(rec.query_id, -1), index.get(rec.candidate_id, -1), rec.status]
                                        for rec in loops],
                        "closer_s": self.closer.stage_times(), "closer_counts": self.closer.counts})
        if self._prox is not None:
            out["proximity"] = {**self._prox_counts,
                                "stored_keyframes": len(self._prox.order) - self._prox.dropped,
                                "loop_frames": [[index.get(q, -1), index.get(c, -1), status]
                                                for q, c, status in self._prox_loops]}
        return out

    # ------------------------------------------------------------------ proximity loop closure (DPV-SLAM 3.2)
    def _prox_init(self) -> None:
        self._prox: KeyframeStore | None = None
        if not self.loop_config.proximity:
            return
        self._prox = KeyframeStore(self.config.proximity.max_stored_keyframes)
        self._prox_counts = {"queries": 0, "candidates": 0, "verified": 0, "accepted": 0, "undone": 0,
                             "global_ba_runs": 0, "global_ba_s": 0.0}
        self._prox_loops: list[tuple[int, int, str]] = []  # (query fid, candidate fid, status)
        self._prox_cooldown_until = -1  # keyframe ordinal before which no loop is searched
        self._times["proximity"] = 0.0

    def _prox_frame(self, fid: int) -> GraphFrame | None:
        """The keyframe ``fid`` (in the graph or finalised), or None."""
        f = self._final.get(fid)
        if f is not None:
            return f
        try:
            return self.graph.frame(fid)
        except KeyError:
            return None

    def _prox_step(self) -> None:
        """Store newly settled keyframes; search a loop for the newest one (module docstring)."""
        if self._prox is None:
            return
        t0 = time.perf_counter()
        g = self.graph
        settled = len(g) - 1 - self.config.tracking.keyframe_index
        query = None
        for p in range(max(settled, 0)):
            f = g.frames[p]
            last = self._prox.last
            if (last is not None and f.fid <= last) or f.features is None:
                continue
            self._prox.add(f.fid, self.source.pack(f.features))
            query = f
        if query is not None and self._prox.ordinal(query.fid) >= self._prox_cooldown_until:
            self._prox_counts["queries"] += 1
            cand = self._prox_candidate(query)
            if cand is not None:
                self._prox_counts["candidates"] += 1
                self._prox_close(query, cand)
        self._times["proximity"] += time.perf_counter() - t0

    def _prox_candidate(self, q: GraphFrame) -> Candidate | None:
        """The best proximity candidate of settled keyframe ``q`` (pose, angle and flow tests), or None."""
        pc = self.config.proximity
        store = self._prox
        limit = store.ordinal(q.fid) - pc.min_gap
        if limit < 0:
            return None
        fids = [fid for fid in store.order[: limit + 1]
                if fid in store and fid >= (self._map_start_fid or 0)]
        frames = [f for f in (self._prox_frame(fid) for fid in fids) if f is not None]
        if not frames:
            return None
        good = q.inv_depth > 0
        if not good.any():
            return None
        depth = float(np.median(1.0 / q.inv_depth[good]))
        T_c = np.stack([f.T_WC for f in frames])
        ok, dist, angle = pose_filter(q.T_WC, T_c, pc.radius * depth, pc.max_angle_deg)
        best = None
        for i in np.nonzero(ok)[0]:
            f = frames[i]
            uv, valid = self._reproject_patches(f, q)
            if valid.mean() < pc.min_overlap:
                continue
            flow = float(np.linalg.norm(uv[valid] - f.uv[valid], axis=1).mean())
            if flow <= pc.max_flow_px and (best is None or flow < best.flow):
                best = Candidate(f.fid, float(dist[i]), float(angle[i]), flow, float(valid.mean()))
        return best

    def _reproject_patches(self, a: GraphFrame, b: GraphFrame) -> tuple[np.ndarray, np.ndarray]:
        """Frame a's patch centres reprojected into frame b's left image at the current poses and
        depths: (K, 2) pixels and validity (in front, inside the image with the patch margin)."""
        uv, ok = self._reproject_frame(a, b)
        return uv, ok & self._inside(uv)

    def _prox_measure(self, q: GraphFrame, cand: Candidate) -> dict | None:
        """Loop edges between the candidate's neighbourhood (stored keyframes) and the query's (graph
        frames with features), measured from two starts (current reprojection and zero motion; the
        more confident wins) and verified per frame pair by a fundamental-matrix RANSAC. Returns
        the verified edges as an inactive-edge chunk, or None."""
        pc = self.config.proximity
        store = self._prox
        old = [cand.fid] + store.neighbours(cand.fid, pc.old_neighbours)
        old = [f for f in (self._prox_frame(fid) for fid in old) if f is not None]
        pq = self.graph.position(q.fid)
        new = [f for f in self.graph.frames[max(0, pq - pc.new_neighbours): pq + pc.new_neighbours + 1]
               if f.features is not None]
        feats_old = {f.fid: self.source.unpack(store.get(f.fid)) for f in old}
        groups = []  # (src frame, tgt frame, src feats, tgt feats, pair id)
        for pair, (o, n) in enumerate((o, n) for o in old for n in new):
            groups.append((o, n, feats_old[o.fid], n.features, pair))
            groups.append((n, o, n.features, feats_old[o.fid], pair))
        requests, starts = [], []
        for a, b, fa, fb, _ in groups:
            pred, _ = self._reproject_patches(a, b)
            requests.append((fa, fb, a.uv, pred))
            starts.append((fa, fb, a.uv, a.uv.copy()))
        t0 = time.perf_counter()
        from_pred = self.source.measure_batch(requests)
        from_zero = self.source.measure_batch(starts)
        self._times["flow"] += time.perf_counter() - t0
        chunks, valid_total, inlier_total = [], 0, 0
        by_pair: dict[int, list] = {}
        for (a, b, _, _, pair), m1, m0 in zip(groups, from_pred, from_zero):
            use0 = m0.confidence > m1.confidence
            uv = np.where(use0[:, None], m0.uv, m1.uv)
            conf = np.where(use0, m0.confidence, m1.confidence)
            by_pair.setdefault(pair, []).append((a, b, uv, conf))
        for pair, parts in by_pair.items():
            # one fundamental matrix per frame pair: both directions as (old pixel, new pixel)
            pts_o, pts_n, owners = [], [], []
            for k, (a, b, uv, conf) in enumerate(parts):
                ok = conf > 0
                if k == 0:
                    pts_o.append(a.uv[ok]); pts_n.append(uv[ok])
                else:
                    pts_o.append(uv[ok]); pts_n.append(a.uv[ok])
                owners.append(np.nonzero(ok)[0])
            counts = [len(o) for o in owners]
            valid_total += sum(counts)
            inl = fundamental_inliers(np.concatenate(pts_o), np.concatenate(pts_n), pc.ransac_threshold_px)
            inlier_total += int(inl.sum())
            offset = 0
            for (a, b, uv, conf), idx, cnt in zip(parts, owners, counts):
                keep = idx[inl[offset: offset + cnt]]
                offset += cnt
                if keep.size:
                    chunks.append({"src": np.full(keep.size, a.fid, np.int64), "patch": keep.astype(np.int64),
                                   "tgt": np.full(keep.size, b.fid, np.int64), "right": np.zeros(keep.size, bool),
                                   "uv_src": a.uv[keep].astype(np.float32), "uv": uv[keep].astype(np.float32),
                                   "confidence": conf[keep].astype(np.float32),
                                   "inv_depth": a.inv_depth[keep].astype(np.float32)})
        ratio = inlier_total / max(valid_total, 1)
        if inlier_total < pc.min_loop_edges or ratio < pc.min_inlier_ratio:
            logger.info("proximity loop %d -> %d rejected: %d verified of %d measured loop edges",
                        q.index, self._prox_frame(cand.fid).index, inlier_total, valid_total)
            return None
        return {key: np.concatenate([c[key] for c in chunks]) for key in chunks[0]}

    def _prox_close(self, q: GraphFrame, cand: Candidate) -> None:
        """Measure, verify, and close a proximity loop with a global bundle adjustment."""
        edges = self._prox_measure(q, cand)
        if edges is None:
            self._prox_loops.append((q.fid, cand.fid, "rejected: verification"))
            return
        self._prox_counts["verified"] += 1
        accepted = self._global_ba(edges)
        status = "accepted" if accepted else "undone: loop edges inconsistent after global BA"
        self._prox_loops.append((q.fid, cand.fid, status))
        if accepted:
            self._prox_counts["accepted"] += 1
            self._prox_cooldown_until = self._prox.ordinal(q.fid) + self.config.proximity.cooldown
            logger.info("proximity loop closed: frame %d <-> frame %d (%d loop edges, flow %.1f px)",
                        q.index, self._prox_frame(cand.fid).index, len(edges["src"]), cand.flow)
        else:
            self._prox_counts["undone"] += 1

    def _global_ba(self, loop_edges: dict | None = None) -> bool:
        """Global BA over the current map's keyframes with every active, inactive and (given) loop
        edge. With loop edges, the result is kept only when at least ``min_ba_inlier_ratio`` of them
        keep a non-zero weight; kept loop edges join the inactive store. Returns whether it was kept."""
        pc = self.config.proximity
        t0 = time.perf_counter()
        g = self.graph
        start = self._map_start_fid or 0
        frames = sorted([f for f in self._final.values() if f.fid >= start] + list(g.frames), key=lambda f: f.fid)
        fids = np.array([f.fid for f in frames], np.int64)
        parts = []
        inactive = g.inactive.arrays()
        if inactive:
            parts.append({k: inactive[k] for k in ("src", "patch", "tgt", "right", "uv", "confidence")})
        active = g.confidence > 0
        parts.append({"src": g.src[active], "patch": g.patch[active], "tgt": g.tgt[active], "right": g.right[active],
                      "uv": g.uv[active], "confidence": g.confidence[active]})
        n_loop = 0
        if loop_edges is not None:
            parts.append({k: loop_edges[k] for k in ("src", "patch", "tgt", "right", "uv", "confidence")})
            n_loop = len(loop_edges["src"])
        e = {k: np.concatenate([np.asarray(p[k]) for p in parts]) for k in parts[0]}
        is_loop = np.zeros(len(e["src"]), bool)
        if n_loop:
            is_loop[-n_loop:] = True
        known = np.isin(e["src"], fids) & np.isin(e["tgt"], fids) & (e["confidence"] > 0)
        e = {k: v[known] for k, v in e.items()}
        is_loop = is_loop[known]
        src_i, tgt_i = np.searchsorted(fids, e["src"]), np.searchsorted(fids, e["tgt"])
        Kp = self.config.graph.patches_per_frame
        ukeys, struct_idx = np.unique(src_i * Kp + e["patch"], return_inverse=True)
        owner, patch = ukeys // Kp, ukeys % Kp
        uv_all = np.stack([f.uv for f in frames])
        d_all = np.stack([f.inv_depth for f in frames])
        prior = {}
        if self.sensor_mode == "rgbd":
            sens = np.stack([f.sensor_inv_depth for f in frames])[owner, patch]
            prior = depth_priors(sens, self.config.ba.depth_noise_model()).kwargs()
        fixed = held_frames(len(frames), src_i, tgt_i, is_loop, 2 if self.sensor_mode == "mono" else 1)
        problem = GlobalBAProblem(
            T_WC=np.stack([f.T_WC for f in frames]), fixed=fixed, src=src_i, tgt=tgt_i, right=e["right"].astype(bool),
            uv_src=uv_all[src_i, e["patch"]], uv=e["uv"].astype(np.float64),
            weight=e["confidence"].astype(np.float64) / self.config.ba.pixel_sigma ** 2, struct_idx=struct_idx,
            inv_depth=d_all[owner, patch], K=self.K.numpy(),
            K_right=None if self.K_right is None else self.K_right.numpy(), T_CRCL=self.T_CRCL, **prior)
        res = global_bundle_adjustment(problem, pc.ba, self._reproj)
        self._prox_counts["global_ba_runs"] += 1
        self._prox_counts["global_ba_s"] += time.perf_counter() - t0
        if is_loop.any():
            kept = float((res.robust[is_loop] > 0).mean())
            if kept < pc.min_ba_inlier_ratio:
                logger.info("global BA undone: %.0f %% of the loop edges kept a weight (< %.0f %%)",
                            100 * kept, 100 * pc.min_ba_inlier_ratio)
                return False
        for i, f in enumerate(frames):
            f.T_WC = res.T_WC[i].copy()
        for pos in np.unique(owner):
            sel = owner == pos
            frames[pos].inv_depth = frames[pos].inv_depth.copy()
            frames[pos].inv_depth[patch[sel]] = res.inv_depth[sel]
        if n_loop:
            keep = np.zeros(n_loop, bool)
            keep[known[-n_loop:]] = res.robust[is_loop] > 0
            if keep.any():
                g.inactive.add({k: v[keep] for k, v in loop_edges.items()})
        if self.closer is not None:
            self.closer.update_poses({f.fid: f.T_WC for f in frames})
        return True
