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
- *global optimisation*: :meth:`DenseLoopContributor.global_ba` runs it (the periodic one handed to the
  loop service's worker, the final one at once) on :meth:`.ba.DenseBA.global_job` (the snapshot) and
  :meth:`.ba.DenseBA.apply_global` (the hand-over).
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from typing import Optional

import numpy as np

from ...core.lie import sim3_matrix_parts
from ...contracts.contributor import GlobalBAJob, KeyframeImage, PoseCorrection, apply_global_ba_result
from .ba import DenseBA, DenseGlobalResult
from .state import DenseState

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
    """Keyframes, images and poses of the shared ``state`` for the loop service, its corrections applied,
    and the global optimisation (through ``ba``); ``name`` is the family's (the contract's)."""

    def __init__(self, state: DenseState, ba: DenseBA, name: str):
        self.state = state
        self.ba = ba
        self.name = name
        self._settled = -1  # newest keyframe id handed to the loop port as settled

    # ------------------------------------------------------------------ proximity loops
    def proximity_step(self) -> None:
        """Hand the newly settled keyframes (all but the newest two, ids increasing) to the loop port and
        search a proximity loop for the newest of them."""
        st = self.state
        if (st.background_global_ba or st.loops.proximity is not None) and self.ba.jobs_in_process:
            st.loops.prepare_global_ba()  # the worker process (jobs that run in a thread need none)
        if st.loops.proximity is None or st.graph is None:
            return
        query = None
        for fid in st.graph.order()[:-2]:
            if fid > self._settled:
                st.loops.keyframe_settled(fid)
                self._settled = query = fid
        if query is not None:
            st.loops.search(query)

    def proximity_candidate(self, query_kf_id: int, candidate_kf_ids: list[int]) -> Optional[DenseCandidate]:
        """The best proximity candidate of ``query_kf_id`` among ``candidate_kf_ids`` (module docstring)."""
        st = self.state
        g = st.graph
        pc = st.config.proximity
        q = g.keyframes.get(query_kf_id) if g is not None else None
        if q is None or q.image is None:
            return None
        good = q.inv_depth > 0
        if not good.any():
            return None
        T_q = st.backend.pose_matrix(query_kf_id)
        R_q, t_q, s_q = sim3_matrix_parts(T_q)
        reach = pc.radius * float(np.median(1.0 / q.inv_depth[good])) * s_q  # median depth in map units
        best = None
        for fid in candidate_kf_ids:
            kf = g.keyframes.get(fid)
            if kf is None or kf.image is None or not st.backend.has_keyframe(fid):
                continue
            R_c, t_c, _ = sim3_matrix_parts(st.backend.pose_matrix(fid))
            dist = float(np.linalg.norm(t_c - t_q))
            angle = float(np.degrees(np.arccos(np.clip(R_q[:, 2] @ R_c[:, 2], -1.0, 1.0))))
            if dist > reach or angle > pc.max_angle_deg:
                continue
            flow = g.distance(query_kf_id, fid, st.config.graph.distance_stride)
            if flow <= pc.max_flow_px and (best is None or flow < best.flow):
                best = DenseCandidate(int(fid), flow, dist, angle)
        return best

    def long_range_edges(self, query_kf_id: int, candidate_kf_id: int) -> Optional[dict]:
        """Loop edges both ways between the candidate's neighbourhood and the query's, measured and
        verified (module docstring): ``src``, ``tgt`` (L,), ``target``, ``weight`` (L, h, w, 2); None
        when fewer than ``min_loop_edges`` pass."""
        st = self.state
        g = st.graph
        pc = st.config.proximity
        order = [f for f in g.order() if g.keyframes[f].image is not None]
        if query_kf_id not in order or candidate_kf_id not in order:
            return None
        pq, pcand = order.index(query_kf_id), order.index(candidate_kf_id)
        old = order[max(0, pcand - pc.old_neighbours): pcand + pc.old_neighbours + 1]
        new = order[max(0, pq - pc.new_neighbours): pq + pc.new_neighbours + 1]
        edges = [e for o in old for n in new if o != n for e in ((o, n), (n, o))]
        t0 = time.perf_counter()
        induced, _ = g.induced(edges)
        revs = st.source.revise(edges, induced)
        st.times["flow"] += time.perf_counter() - t0
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

    # ------------------------------------------------------------------ global optimisation
    def global_ba(self, background: bool = False) -> None:
        """The global optimisation of the map (step 5 of :mod:`.frontend`): a snapshot
        (:meth:`.ba.DenseBA.global_job`) solved by :func:`.ba.solve_dense_global`. ``background`` (the
        periodic one, ``global_ba.background`` on and a loop service connected): handed to the loop
        service, which solves it in its worker and applies it at a later safe point (skipped while one
        runs: tried again at the next keyframe); else solved and applied now (the final one)."""
        st = self.state
        t0 = time.perf_counter()
        loops = st.loops
        if background and st.config.global_ba.background and loops.runs_global_ba:
            if not loops.busy:
                st.new_since_global = 0
                loops.start_global_ba()
            st.times["global"] += time.perf_counter() - t0
            return
        st.new_since_global = 0
        job = self.ba.global_job(None)
        if job is None:
            return
        result = job.solve()
        apply_global_ba_result(self, job, result, np.zeros(0, bool), time.perf_counter() - t0)
        st.times["global"] += time.perf_counter() - t0
        logger.info("dense global optimisation: %d keyframes, %d edges, %.2f s", len(job.kf_ids), result.num_edges,
                    time.perf_counter() - t0)

    def global_ba_job(self, loop_edges: Optional[dict] = None) -> Optional[GlobalBAJob]:
        """The global optimisation's snapshot (:meth:`.ba.DenseBA.global_job`)."""
        return self.ba.global_job(loop_edges)

    def apply_global_ba(self, job: GlobalBAJob, result: DenseGlobalResult, keep_loop: np.ndarray) -> None:
        """Its hand-over before the pose correction (:meth:`.ba.DenseBA.apply_global`)."""
        self.ba.apply_global(job, result, keep_loop)

    # ------------------------------------------------------------------ classical loops
    def feed(self, all_keyframes: bool = False) -> None:
        """Hand the keyframes that left the active graph (``all_keyframes``: every keyframe) to the
        loop port (the classical closer, a loaded map) with their neighbours, and every keyframe's pose."""
        st = self.state
        if not all_keyframes:
            self.proximity_step()
        if not st.loops.relocalizes or st.graph is None:
            return
        g = st.graph
        active = set(g.active)
        order = g.order()
        for p, fid in enumerate(order):
            if all_keyframes or fid not in active:
                st.loops.add_keyframe(fid, [order[q] for q in (p - 1, p + 1) if 0 <= q < len(order)])
        st.loops.update_poses({f: st.keyframe_T_WC(f) for f in order})

    def keyframe_image(self, kf_id: int) -> Optional[KeyframeImage]:
        st = self.state
        kf = st.graph.keyframes.get(kf_id) if st.graph is not None else None
        if kf is None or kf.image is None:
            return None
        return KeyframeImage(kf.image, st.K.copy(), kf.timestamp, kf.depth_image)

    def keyframe_pose(self, kf_id: int) -> Optional[np.ndarray]:
        backend = self.state.backend
        return backend.pose_matrix(kf_id) if backend.has_keyframe(kf_id) else None

    def apply_correction(self, correction: PoseCorrection) -> None:
        """Keyframe poses ``T_WC <- U_k T_WC`` (the folded scale into their inverse depths), pose records
        re-expressed."""
        st = self.state
        for kf in st.all_keyframes():
            if not st.backend.has_keyframe(kf.fid):
                continue
            T_WC, s = correction.apply_pose(kf.fid, st.backend.pose_matrix(kf.fid))
            st.backend.set_pose(kf.fid, T_WC)
            if s != 1.0:
                kf.inv_depth = kf.inv_depth / s
        for fid, rec in list(st.records.items()):
            if rec is not None:
                st.records[fid] = rec.corrected(fid, correction)
