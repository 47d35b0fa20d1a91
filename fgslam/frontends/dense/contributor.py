"""The dense frontend's side of loop closure: the hand-over of settled keyframes to the loop port, and
the contributor contract (:mod:`fgslam.contracts.contributor`) the frontend delegates to, proximity
loops and the global optimisation's hand-over included (:class:`~fgslam.contracts.contributor.ProximityContributor`):

- *proximity candidates*: settled keyframes of the map with images, at least ``proximity.min_gap``
  keyframes before the query, near it in pose (camera centre within ``radius`` median query depths,
  optical axes within ``max_angle_deg``) and in flow distance (below ``max_flow_px``): the nearest by
  flow;
- *long-range edges*: both ways between the candidate's neighbourhood and the query's, measured by the
  frontend's dense source from the field the estimate induces (its confidence as weight: the drift the
  loop corrects makes large revisions, which the local BA's Huber weight would cut), kept when
  ``min_confident`` of the grid is confident, the loop verified with ``min_loop_edges`` of them;
- *global optimisation*: :meth:`.ba.DenseBA.global_job` (the snapshot) and :meth:`.ba.DenseBA.apply_global`.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING, Optional

import numpy as np

from ...lie import sim3_matrix_parts
from ...contracts.contributor import GlobalBAJob, KeyframeImage, PoseCorrection

if TYPE_CHECKING:
    from .frontend import DenseFrontend

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class DenseCandidate:
    """A proximity candidate: keyframe ``fid``, its flow distance to the query (image px), camera
    centre distance (map units) and optical-axis angle (degrees)."""

    fid: int
    flow: float
    distance: float
    angle_deg: float


class DenseLoopContributor:
    """Keyframes, images and poses of ``frontend`` for the loop service, and its corrections applied."""

    def __init__(self, frontend: "DenseFrontend"):
        self.fe = frontend
        self.name = frontend.name
        self._settled = -1  # newest keyframe id handed to the loop port as settled

    # ------------------------------------------------------------------ proximity loops
    def proximity_step(self) -> None:
        """Hand the newly settled keyframes (all but the newest two, ids increasing) to the loop port and
        search a proximity loop for the newest of them."""
        fe = self.fe
        if (fe.background_global_ba or fe.loops.proximity is not None) and fe.ba.jobs_in_process:
            fe.loops.prepare_global_ba()  # the worker process (jobs that run in a thread need none)
        if fe.loops.proximity is None or fe.graph is None:
            return
        query = None
        for fid in fe.graph.order()[:-2]:
            if fid > self._settled:
                fe.loops.keyframe_settled(fid)
                self._settled = query = fid
        if query is not None:
            fe.loops.search(query)

    def proximity_candidate(self, query_kf_id: int, candidate_kf_ids: list[int]) -> Optional[DenseCandidate]:
        """The best proximity candidate of ``query_kf_id`` among ``candidate_kf_ids`` (module docstring)."""
        fe = self.fe
        g = fe.graph
        pc = fe.config.proximity
        q = g.keyframes.get(query_kf_id) if g is not None else None
        if q is None or q.image is None:
            return None
        good = q.inv_depth > 0
        if not good.any():
            return None
        T_q = fe.backend.pose_matrix(query_kf_id)
        R_q, t_q, s_q = sim3_matrix_parts(T_q)
        reach = pc.radius * float(np.median(1.0 / q.inv_depth[good])) * s_q  # median depth in map units
        best = None
        for fid in candidate_kf_ids:
            kf = g.keyframes.get(fid)
            if kf is None or kf.image is None or not fe.backend.has_keyframe(fid):
                continue
            R_c, t_c, _ = sim3_matrix_parts(fe.backend.pose_matrix(fid))
            dist = float(np.linalg.norm(t_c - t_q))
            angle = float(np.degrees(np.arccos(np.clip(R_q[:, 2] @ R_c[:, 2], -1.0, 1.0))))
            if dist > reach or angle > pc.max_angle_deg:
                continue
            flow = g.distance(query_kf_id, fid, fe.config.graph.distance_stride)
            if flow <= pc.max_flow_px and (best is None or flow < best.flow):
                best = DenseCandidate(int(fid), flow, dist, angle)
        return best

    def long_range_edges(self, query_kf_id: int, candidate_kf_id: int) -> Optional[dict]:
        """Loop edges both ways between the candidate's neighbourhood and the query's, measured and
        verified (module docstring): ``src``, ``tgt`` (L,), ``target``, ``weight`` (L, h, w, 2); None
        when fewer than ``min_loop_edges`` pass."""
        fe = self.fe
        g = fe.graph
        pc = fe.config.proximity
        order = [f for f in g.order() if g.keyframes[f].image is not None]
        if query_kf_id not in order or candidate_kf_id not in order:
            return None
        pq, pcand = order.index(query_kf_id), order.index(candidate_kf_id)
        old = order[max(0, pcand - pc.old_neighbours): pcand + pc.old_neighbours + 1]
        new = order[max(0, pq - pc.new_neighbours): pq + pc.new_neighbours + 1]
        edges = [e for o in old for n in new if o != n for e in ((o, n), (n, o))]
        t0 = time.perf_counter()
        induced, _ = g.induced(edges)
        revs = fe.source.revise(edges, induced)
        fe._times["flow"] += time.perf_counter() - t0
        kept = []
        for e, rev in zip(edges, revs):
            weight = np.nan_to_num(np.asarray(rev.weight, np.float64), nan=0.0)
            confident = float((weight.mean(-1) > pc.confident_weight).mean())
            if confident >= pc.min_confident:
                kept.append((e, np.asarray(rev.target, np.float64), weight))
        if len(kept) < pc.min_loop_edges:
            logger.info("dense proximity loop %d -> %d rejected: %d of %d loop edges confident", query_kf_id,
                        candidate_kf_id, len(kept), len(edges))
            return None
        return {"src": np.array([e[0] for e, _, _ in kept], np.int64), "tgt": np.array([e[1] for e, _, _ in kept], np.int64),
                "target": np.stack([t for _, t, _ in kept]), "weight": np.stack([w for _, _, w in kept])}

    def global_ba_job(self, loop_edges: Optional[dict] = None) -> Optional[GlobalBAJob]:
        """The global optimisation's snapshot (:meth:`.ba.DenseBA.global_job`)."""
        return self.fe.ba.global_job(loop_edges)

    def apply_global_ba(self, job: GlobalBAJob, result, keep_loop: np.ndarray) -> None:
        """Its hand-over before the pose correction (:meth:`.ba.DenseBA.apply_global`)."""
        self.fe.ba.apply_global(job, result, keep_loop)

    # ------------------------------------------------------------------ classical loops
    def feed(self, all_keyframes: bool = False) -> None:
        """Hand the keyframes that left the active graph (``all_keyframes``: every keyframe) to the
        classical closer with their neighbours, and every keyframe's pose."""
        fe = self.fe
        if not all_keyframes:
            self.proximity_step()
        if not fe.loops.classical or fe.graph is None:
            return
        g = fe.graph
        active = set(g.active)
        order = g.order()
        for p, fid in enumerate(order):
            if all_keyframes or fid not in active:
                fe.loops.add_keyframe(fid, [order[q] for q in (p - 1, p + 1) if 0 <= q < len(order)])
        fe.loops.update_poses({f: fe._keyframe_T_WC(f) for f in order})

    def keyframe_image(self, kf_id: int) -> Optional[KeyframeImage]:
        fe = self.fe
        kf = fe.graph.keyframes.get(kf_id) if fe.graph is not None else None
        if kf is None or kf.image is None:
            return None
        return KeyframeImage(kf.image, fe.K.copy(), kf.timestamp, kf.depth_image)

    def keyframe_pose(self, kf_id: int) -> Optional[np.ndarray]:
        backend = self.fe.backend
        return backend.pose_matrix(kf_id) if backend.has_keyframe(kf_id) else None

    def apply_correction(self, correction: PoseCorrection) -> None:
        """Keyframe poses ``T_WC <- U_k T_WC`` (the folded scale into their inverse depths), pose records
        re-expressed."""
        fe = self.fe
        for kf in fe._all_keyframes():
            if not fe.backend.has_keyframe(kf.fid):
                continue
            T_WC, s = correction.apply_pose(kf.fid, fe.backend.pose_matrix(kf.fid))
            fe.backend.set_pose(kf.fid, T_WC)
            if s != 1.0:
                kf.inv_depth = kf.inv_depth / s
        for fid, rec in list(fe._records.items()):
            if rec is not None:
                fe._records[fid] = rec.corrected(fid, correction)
