"""The patch frontend as loop-closure contributor (:class:`PatchContributor`).

Loop closure, classical and proximity with the global bundle adjustment, is the shared service
:class:`fgslam.services.loops.LoopService` that the system owns and connects as the frontend's loop
port; this collaborator keeps what it needs (keyframe images while a frame may become a loop
keyframe, settled keyframes' packed source features in a :class:`~.proximity.KeyframeStore`), feeds
it keyframes, and implements the contract of :mod:`fgslam.contracts.contributor`: keyframe images and
poses, pose corrections, proximity candidates, long-range edges, the global BA's snapshot
(:meth:`PatchContributor.global_ba_job`, solved by :func:`.global_ba.global_bundle_adjustment`) and
its hand-over. Finalised keyframes (out of the graph) keep their pose and patches for it."""

from __future__ import annotations

import logging
import time
from functools import partial

import numpy as np

from ...contracts.contributor import GlobalBAJob, KeyframeImage, PoseCorrection
from ...factors.depth import depth_priors
from ..base import NO_LOOPS, LoopPort
from ..records import AbsolutePose
from ...backend.global_ba import GlobalBAProblem, global_bundle_adjustment
from .motion import MotionModel
from .proximity import Candidate, KeyframeStore, fundamental_inliers, held_frames, pose_filter
from .state import PatchState

logger = logging.getLogger(__name__)

#: the edge arrays a global BA takes from every edge store (active, inactive, loop)
_EDGE_FIELDS = ("src", "patch", "tgt", "right", "uv", "confidence")


class PatchContributor:
    """Loop-closure hooks and the contributor contract on the shared :class:`~.state.PatchState`
    (module docstring); ``motion``: its velocity follows pose corrections.

    Attributes:
        loops: the loop port (:meth:`connect`).
        store: settled keyframes' packed source features (long-range edges); None without proximity loops.
        images: fid -> (image, timestamp, depth) while the frame may become a loop keyframe.
    """

    name = "patch"

    def __init__(self, state: PatchState, motion: MotionModel):
        self.state = state
        self.motion = motion
        self.loops: LoopPort = NO_LOOPS
        self.store: KeyframeStore | None = None
        self.images: dict[int, tuple] = {}

    def connect(self, loops: LoopPort) -> None:
        """Take the loop port; with proximity loops on, keep settled keyframes' packed source features."""
        self.loops = loops
        self.store = None
        if loops.proximity is not None:
            self.store = KeyframeStore(self.state.config.proximity.max_stored_keyframes)
            self.state.times.setdefault("proximity", 0.0)

    # ------------------------------------------------------------------ the loop service's hooks
    def keep_image(self, fid: int, frame, buffered: set[int] | None) -> None:
        """Keep the image of frame ``fid`` while it is in the graph (or ``buffered`` for initialisation:
        the frames a pending initialisation holds, None when there is none)."""
        if not self.loops.relocalizes:
            return
        self.images[fid] = (frame.image, float(frame.timestamp), frame.depth)
        keep = buffered if buffered is not None else {f.fid for f in self.state.graph.frames}
        for old in [k for k in self.images if k not in keep]:
            del self.images[old]

    def feed_keyframes(self, all_frames: bool = False) -> None:
        """Hand keyframes that can no longer be removed (graph positions below
        ``len - 1 - keyframe_index``; every graph frame with ``all_frames``) to the closer, then the
        latest graph poses."""
        if not self.loops.relocalizes:
            return
        g = self.state.graph
        final = len(g) if all_frames else len(g) - 1 - self.state.config.tracking.keyframe_index
        for p in range(max(final, 0)):
            fid = g.frames[p].fid
            if fid in self.images:
                self.loops.add_keyframe(fid, [g.frames[q].fid for q in (p - 1, p + 1) if 0 <= q < len(g)])
                del self.images[fid]
        self.loops.update_poses({f.fid: f.T_WC for f in g.frames})

    def relocalize(self, fid: int, frame, before: int | None = None) -> np.ndarray | None:
        """Pose of a lost frame from the closer's keyframe database (``before``: among keyframes with a
        smaller id) or a loaded map (``T_WC`` 4x4 in the map's units), or None; on success it becomes frame
        ``fid``'s pose, the anchor of the re-initialisation."""
        st = self.state
        found = self.loops.relocalize(frame.image, st.K.numpy(), before)
        if found is None:
            return None
        kf_id, T_WC = found
        st.records[fid] = AbsolutePose(np.asarray(T_WC, dtype=np.float64))
        if st.sensor_mode == "mono":
            logger.info("frame %d relocalised on keyframe %d; monocular: the re-initialised map starts at this "
                        "pose but gets a scale of its own (not tied to the old map's)", frame.index, kf_id)
        else:
            logger.info("frame %d relocalised on keyframe %d", frame.index, kf_id)
        return T_WC

    def add_loop_counts(self, summary: dict) -> None:
        """The proximity store's size in the loop summary."""
        if self.store is not None and "proximity" in summary:
            summary["proximity"]["stored_keyframes"] = len(self.store.order) - self.store.dropped

    def proximity_step(self) -> None:
        """Store newly settled keyframes (their packed source features, for long-range edges) and search
        a proximity loop for the newest one."""
        if self.store is None:
            return
        st = self.state
        t0 = time.perf_counter()
        g = st.graph
        settled = len(g) - 1 - st.config.tracking.keyframe_index
        query = None
        for p in range(max(settled, 0)):
            f = g.frames[p]
            last = self.store.last
            if (last is not None and f.fid <= last) or f.features is None:
                continue
            self.store.add(f.fid, st.source.pack(f.features))
            self.loops.keyframe_settled(f.fid)
            query = f
        st.times["proximity"] += time.perf_counter() - t0
        if query is not None:
            self.loops.search(query.fid)

    # ------------------------------------------------------------------ contributor contract (fgslam.contracts.contributor)
    def keyframe_image(self, kf_id: int) -> KeyframeImage | None:
        kept = self.images.get(kf_id)
        if kept is None:
            return None
        image, timestamp, depth = kept
        return KeyframeImage(image, self.state.K.numpy(), timestamp, depth)

    def keyframe_pose(self, kf_id: int) -> np.ndarray | None:
        f = self.state.keyframe(kf_id)
        return None if f is None else f.T_WC

    def apply_correction(self, correction: PoseCorrection) -> None:
        """Graph and finalised keyframes ``T_WC <- U_k T_WC`` with the folded scale in their patch
        inverse depths (sensor depths stay as measured); non-keyframe records re-expressed
        (:meth:`.records.PoseRecord.corrected`) and the motion model's velocity (and the motion
        check's held reference) in its reference's folded units."""
        st = self.state
        for f in list(st.graph.frames) + list(st.final.values()):
            f.T_WC, s = correction.apply_pose(f.fid, f.T_WC)
            if s != 1.0:
                f.inv_depth = f.inv_depth / s
        for fid, rec in list(st.records.items()):
            if rec is not None:
                st.records[fid] = rec.corrected(fid, correction)
        self.motion.fold(correction)

    def proximity_candidate(self, query_kf_id: int, candidate_kf_ids: list[int]) -> Candidate | None:
        """The best proximity candidate of settled keyframe ``query_kf_id`` among ``candidate_kf_ids``
        (stored, of the current map): pose, angle and flow tests (:mod:`.proximity`), least flow wins."""
        st = self.state
        pc = st.config.proximity
        q = st.keyframe(query_kf_id)
        fids = [fid for fid in candidate_kf_ids if fid in self.store and fid >= (st.map_start_fid or 0)]
        frames = [f for f in (st.keyframe(fid) for fid in fids) if f is not None]
        if q is None or not frames:
            return None
        good = q.inv_depth > 0
        if not good.any():
            return None
        depth = float(np.median(1.0 / q.inv_depth[good]))
        T_WC_cand = np.stack([f.T_WC for f in frames])
        ok, dist, angle = pose_filter(q.T_WC, T_WC_cand, pc.radius * depth, pc.max_angle_deg)
        best = None
        for i in np.nonzero(ok)[0]:
            f = frames[i]
            uv, valid = st.reproject_patches(f, q)
            if valid.mean() < pc.min_overlap:
                continue
            flow = float(np.linalg.norm(uv[valid] - f.uv[valid], axis=1).mean())
            if flow <= pc.max_flow_px and (best is None or flow < best.flow):
                best = Candidate(f.fid, float(dist[i]), float(angle[i]), flow, float(valid.mean()))
        return best

    def long_range_edges(self, query_kf_id: int, candidate_kf_id: int) -> dict | None:
        """Loop edges between the candidate's neighbourhood (stored keyframes) and the query's (graph
        frames with features), measured from two starts (current reprojection and zero motion; the
        more confident wins) and verified per frame pair by a fundamental-matrix RANSAC. Returns
        the verified edges as an inactive-edge chunk, or None."""
        st = self.state
        pc = st.config.proximity
        store = self.store
        q = st.keyframe(query_kf_id)
        old = [candidate_kf_id] + store.neighbours(candidate_kf_id, pc.old_neighbours)
        old = [f for f in (st.keyframe(fid) for fid in old) if f is not None]
        if q is None or not old:
            return None
        pq = st.graph.position(q.fid)
        new = [f for f in st.graph.frames[max(0, pq - pc.new_neighbours): pq + pc.new_neighbours + 1]
               if f.features is not None]
        feats_old = {f.fid: st.source.unpack(store.get(f.fid)) for f in old}
        groups = []  # (src frame, tgt frame, src feats, tgt feats, pair id)
        for pair, (o, n) in enumerate((o, n) for o in old for n in new):
            groups.append((o, n, feats_old[o.fid], n.features, pair))
            groups.append((n, o, n.features, feats_old[o.fid], pair))
        requests, starts = [], []
        for a, b, fa, fb, _ in groups:
            uv_pred, _ = st.reproject_patches(a, b)
            requests.append((fa, fb, a.uv, uv_pred))
            starts.append((fa, fb, a.uv, a.uv.copy()))
        t0 = time.perf_counter()
        from_pred = st.source.measure_batch(requests)
        from_zero = st.source.measure_batch(starts)
        st.times["flow"] += time.perf_counter() - t0
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
                        q.index, st.keyframe(candidate_kf_id).index, inlier_total, valid_total)
            return None
        return {key: np.concatenate([c[key] for c in chunks]) for key in chunks[0]}

    def global_ba_job(self, loop_edges: dict | None = None) -> GlobalBAJob | None:
        """Snapshot for a global BA over the current map's keyframes with every active, inactive and
        (given) loop edge (held: keyframes known only through loop edges, and the gauge: the oldest
        one, monocular two); solved by :func:`.global_ba.global_bundle_adjustment`."""
        st = self.state
        pc = st.config.proximity
        g = st.graph
        start = st.map_start_fid or 0
        frames = sorted([f for f in st.final.values() if f.fid >= start] + list(g.frames), key=lambda f: f.fid)
        if not frames:
            return None
        fids = np.array([f.fid for f in frames], np.int64)
        parts = []
        inactive = g.inactive.arrays()
        if inactive:
            parts.append({k: inactive[k] for k in _EDGE_FIELDS})
        active = g.confidence > 0
        parts.append({"src": g.src[active], "patch": g.patch[active], "tgt": g.tgt[active], "right": g.right[active],
                      "uv": g.uv[active], "confidence": g.confidence[active]})
        n_loop = 0
        if loop_edges is not None:
            parts.append({k: loop_edges[k] for k in _EDGE_FIELDS})
            n_loop = len(loop_edges["src"])
        e = {k: np.concatenate([np.asarray(p[k]) for p in parts]) for k in parts[0]}
        is_loop = np.zeros(len(e["src"]), bool)
        if n_loop:
            is_loop[-n_loop:] = True
        known = np.isin(e["src"], fids) & np.isin(e["tgt"], fids) & (e["confidence"] > 0)
        e = {k: v[known] for k, v in e.items()}
        is_loop = is_loop[known]
        src_i, tgt_i = np.searchsorted(fids, e["src"]), np.searchsorted(fids, e["tgt"])
        Kp = st.config.graph.patches_per_frame
        ukeys, struct_idx = np.unique(src_i * Kp + e["patch"], return_inverse=True)
        owner, patch = ukeys // Kp, ukeys % Kp
        uv_all = np.stack([f.uv for f in frames])
        d_all = np.stack([f.inv_depth for f in frames])
        prior = {}
        if st.sensor_mode == "rgbd":
            sens = np.stack([f.sensor_inv_depth for f in frames])[owner, patch]
            prior = depth_priors(sens, st.config.ba.depth_noise_model()).kwargs()
        fixed = held_frames(len(frames), src_i, tgt_i, is_loop, st.gauge_frames)
        T_WC = np.stack([f.T_WC for f in frames])
        problem = GlobalBAProblem(
            T_WC=T_WC.copy(), fixed=fixed, src=src_i, tgt=tgt_i, right=e["right"].astype(bool),
            uv_src=uv_all[src_i, e["patch"]], uv=e["uv"].astype(np.float64),
            weight=e["confidence"].astype(np.float64) / st.config.ba.pixel_sigma ** 2, struct_idx=struct_idx,
            inv_depth=d_all[owner, patch], K=st.K.numpy().copy(),
            K_right=None if st.K_right is None else st.K_right.numpy().copy(), T_CRCL=st.T_CRCL, **prior)
        return GlobalBAJob(solve=partial(global_bundle_adjustment, problem, pc.ba, st.reproj), kf_ids=fids,
                           T_WC=T_WC, is_loop=is_loop, loop_edges=loop_edges, in_process=True,
                           context={"owner": owner, "patch": patch, "inv_depth": d_all, "known": known, "n_loop": n_loop})

    def apply_global_ba(self, job: GlobalBAJob, result, keep_loop: np.ndarray) -> None:
        """Hand-over of an accepted global BA (before its pose correction): the optimised patch depths
        of the keyframes whose pose and depths did not change since the snapshot (the others keep
        theirs: their pose gets the correction, and their depths are the newer local BA's); the loop
        edges that kept a weight join the inactive store."""
        ctx = job.context
        owner, patch = ctx["owner"], ctx["patch"]
        for pos in np.unique(owner):
            f = self.state.keyframe(int(job.kf_ids[pos]))
            if f is None or not (np.array_equal(f.T_WC, job.T_WC[pos]) and np.array_equal(f.inv_depth, ctx["inv_depth"][pos])):
                continue
            sel = owner == pos
            f.inv_depth = f.inv_depth.copy()
            f.inv_depth[patch[sel]] = result.inv_depth[sel]
        n_loop = ctx["n_loop"]
        if n_loop:
            keep = np.zeros(n_loop, bool)
            keep[ctx["known"][-n_loop:]] = keep_loop
            if keep.any():
                self.state.graph.inactive.add({k: v[keep] for k, v in job.loop_edges.items()})
