"""The patch frontend's local bundle adjustment (:class:`LocalBA`): measure / optimise rounds, the
optimisation window assembled as one :class:`~.ba.PatchBlock` solved through the run's backend
(:meth:`fgslam.backend.Backend.optimize_window`), the RGB-D observation model, and the per-patch
depth refinement of stereo initialisation."""

from __future__ import annotations

import time

import numpy as np
import torch

from ...backend.keys import pose_key
from ...factors.depth import depth_priors, inv_depth_sigma
from ...factors.visual_block import BlockConfig
from ...core.lie import sim3_matrix_components
from ..records import rigid as _rigid
from .ba import PatchBlock
from .keyframes import Keyframes
from .patches import PatchMeasurer
from .state import BackendFrame, PatchState

#: the gtsam key cache is trimmed to the graph's frames when it outgrows this many times the graph
KEY_CACHE_GROWTH = 4


class LocalBA:
    """Local BA of the patch graph on the shared :class:`~.state.PatchState`.

    Args:
        state: the shared state.
        measurer: measures the edges of each round.
        keyframes: makes every window frame a backend keyframe.
        block_name: the contributor name the window's block is set under (``backend.set_blocks``).

    ``last_residual``: per graph edge, the residual norm (px) after the last BA (inf: not in it).
    """

    def __init__(self, state: PatchState, measurer: PatchMeasurer, keyframes: Keyframes, block_name: str):
        self.state = state
        self.measurer = measurer
        self.keyframes = keyframes
        self.block_name = block_name
        self.last_residual = np.zeros(0)
        self.keys: dict[int, int] = {}  # fid -> gtsam key cache (bounded to about the graph size)
        self.depth_block_name = f"{block_name}.depth"  # the contributor name of the depth-alignment blocks

    def key(self, fid: int) -> int:
        """gtsam key of graph frame ``fid`` (``fgslam.backend.keys.pose_key``), cached."""
        key = self.keys.get(fid)
        if key is None:
            graph = self.state.graph
            if len(self.keys) > KEY_CACHE_GROWTH * (len(graph) + 1):
                self.keys = {f.fid: self.keys[f.fid] for f in graph.frames if f.fid in self.keys}
            key = self.keys[fid] = pose_key(fid)
        return key

    def rounds(self, new_edges: np.ndarray, rounds: int, iterations: int, init: bool, new_fid: int | None,
               premeasured: np.ndarray | None = None, held_by_depth=None) -> int:
        """Measure / optimise rounds; returns the number of valid new measurements of ``new_fid``.
        ``premeasured``: new edges already measured (skipped in the first round). ``held_by_depth``: None,
        or a callable saying whether the depth constrains the new frame (then it is optimised even with
        too few image measurements)."""
        st = self.state
        g = st.graph
        every_edge = st.config.ba.remeasure == "window"  # DPVO: each update measures all active edges
        first = np.arange(g.num_edges) if every_edge else new_edges
        to_measure = first if premeasured is None else np.setdiff1d(first, premeasured)
        valid_new = 0
        for r in range(rounds):
            self.measurer.measure(to_measure, huber=not init and st.config.ba.measured_huber)
            if new_fid is not None:
                valid_new = self.valid_into(new_fid)
                if valid_new < st.config.tracking.min_valid_edges and not (held_by_depth is not None and held_by_depth()):
                    return valid_new
            self.optimize(iterations, init)
            if r + 1 < rounds and every_edge:
                to_measure = np.arange(g.num_edges)
            elif r + 1 < rounds:
                created = np.arange(g.num_edges) if init else np.nonzero(g.created == new_fid)[0]
                res = self.last_residual[created]
                redo = (g.confidence[created] <= 0) | (res > st.config.ba.retrack_threshold)
                to_measure = created[redo]
        # drop edges that never got a valid measurement
        t0 = time.perf_counter()
        g._select(g.confidence > 0)
        st.times["bookkeeping"] += time.perf_counter() - t0
        if new_fid is not None:
            valid_new = self.valid_into(new_fid)
        return valid_new

    def valid_into(self, fid: int) -> int:
        """Measured BA-inlier left-image edges into and from frame ``fid``."""
        g = self.state.graph
        ok = (g.confidence > 0) & (g.robust > 0) & ~g.right
        return int((ok & ((g.tgt == fid) | (g.src == fid))).sum())

    def optimize(self, iterations: int, init: bool) -> dict:
        """Local BA over the optimisation window (all graph frames with ``init``); updates poses,
        depths and robust weights. Returns a small report dict."""
        t0 = time.perf_counter()
        st = self.state
        g = st.graph
        cfg = st.config
        fids = g.fids
        n = len(fids)
        K = cfg.graph.patches_per_frame
        if init:
            var = fids.copy()
        else:
            nvar = max(1, min(cfg.graph.optimization_window, n - st.gauge_frames))
            var = fids[n - nvar:]
        measured = g.confidence > 0
        touch = measured & (np.isin(g.src, var) | np.isin(g.tgt, var))
        pkey = g.src * K + g.patch
        use = measured & np.isin(pkey, np.unique(pkey[touch]))
        e = np.nonzero(use)[0]
        self.last_residual = np.full(g.num_edges, np.inf)
        depth_blocks = self.depth_blocks(var) if st.depth.enabled else []
        if e.size == 0 and not depth_blocks:
            st.times["ba"] += time.perf_counter() - t0
            return {"edges": 0}
        if e.size == 0:  # RGB-D frames without image measurements: the depth alone holds them
            report, _ = self._solve(list(var), None, depth_blocks, None, None, iterations)
            st.times["ba"] += time.perf_counter() - t0
            return {"edges": 0, "initial_cost": report.initial_cost, "final_cost": report.final_cost,
                    "iterations": report.iterations}
        used_frames = np.union1d(np.union1d(g.src[e], g.tgt[e]), var)
        fixed = np.setdiff1d(used_frames, var)
        order = list(var) + list(fixed)
        if init and st.sensor_mode == "mono" and len(var) >= 2:
            # the range gauge acts between the first two keyframes: use the widest baseline
            order = [var[0], var[-1]] + list(var[1:-1])
            var_order = order
        else:
            var_order = list(var)
        local_fids = np.array(var_order + list(fixed), dtype=np.int64)
        sorter = np.argsort(local_fids)
        src_l = sorter[np.searchsorted(local_fids, g.src[e], sorter=sorter)]
        tgt_l = sorter[np.searchsorted(local_fids, g.tgt[e], sorter=sorter)]
        ukeys, struct_idx = np.unique(pkey[e], return_inverse=True)
        pos_src = g.positions(ukeys // K)
        d_all = np.stack([f.inv_depth for f in g.frames])
        uv_all = np.stack([f.uv for f in g.frames])
        depth0 = d_all[pos_src, ukeys % K]
        uv_src = uv_all[g.positions(g.src[e]), g.patch[e]]
        weights = g.confidence[e] * g.robust[e] / cfg.ba.pixel_sigma ** 2
        prior = {}
        right, uv_tgt, K_right, T_CRCL = g.right[e], g.uv[e], st.K_right, st.T_CRCL
        if st.sensor_mode == "rgbd":
            sens = np.stack([f.sensor_inv_depth for f in g.frames])[pos_src, ukeys % K]
            has = np.isfinite(sens) & (sens > 0)
            if cfg.ba.depth_model == "prior":
                prior = depth_priors(sens, cfg.ba.depth_noise_model()).kwargs()
            else:
                src_l, tgt_l, right, uv_src, uv_tgt, weights, struct_idx, K_right, T_CRCL = self.depth_observations(
                    e, src_l, tgt_l, uv_src, struct_idx, weights, sens, has)
        fixed_T = g.poses(fixed) if len(fixed) else np.zeros((0, 4, 4))
        fR, ft, fs = sim3_matrix_components(fixed_T)
        block = PatchBlock(
            [self.key(int(f)) for f in var_order], fR, ft, fs, src_l, tgt_l, right, uv_src, uv_tgt, weights,
            struct_idx, st.K, depth0, K_right=K_right, T_CRCL=T_CRCL,
            config=BlockConfig(threads=cfg.ba.threads), reprojection=st.reproj, **prior,
        )
        mono_init = init and st.sensor_mode == "mono"
        # gauge: the oldest window frame anchored when nothing outside the window holds the poses;
        # at monocular initialisation the range between the first and last frame is the world scale
        anchor = int(var_order[0]) if mono_init or len(fixed) == 0 else None
        pair = (int(var_order[0]), int(var_order[1])) if mono_init and len(var_order) >= 2 else None
        report, final = self._solve(var_order, block, depth_blocks, anchor, pair, iterations)
        self._write_depths(pos_src, ukeys, block.structure.numpy())
        r, valid = final
        r, valid = r[: e.size], valid[: e.size]  # the edges' own rows come first in the block
        rn = torch.linalg.vector_norm(r, dim=1).numpy()
        robust = np.where(valid.numpy() & (rn <= cfg.ba.outlier_threshold), self.measurer.huber_weights(g.confidence[e], rn), 0.0)
        g.robust[e] = robust
        self.last_residual[e] = np.where(valid.numpy(), rn, np.inf)
        st.times["ba"] += time.perf_counter() - t0
        return {"edges": int(e.size), "initial_cost": report.initial_cost, "final_cost": report.final_cost,
                "iterations": report.iterations}

    def _solve(self, var_order: list, block, depth_blocks: list, anchor: int | None, pair, iterations: int | None = None):
        """The window solve through the backend: ``block`` (the visual block, None without image
        measurements) and the depth-alignment blocks over the free frames ``var_order``; poses written
        back (RGB-D rigid). Returns the backend's report and ``block``'s final residuals (None without it)."""
        st = self.state
        g = st.graph
        backend = st.backend
        for f in var_order:
            self.keyframes.ensure(g.frame(int(f)))
        if depth_blocks and any(k not in {self.key(int(f)) for f in var_order} for b in depth_blocks for k in b.keys):
            anchor = None  # a frame outside the window holds the poses through the depth
        elif anchor is None and block is None:
            anchor = int(var_order[0])
        backend.set_gauge(anchor=anchor, scale_pair=pair)
        backend.set_blocks(self.block_name, [block] if block is not None else [])
        if st.depth.enabled:
            backend.set_blocks(self.depth_block_name, depth_blocks)
        report = backend.optimize_window([int(f) for f in var_order], iterations)
        final = None
        if block is not None:
            # robust weights from the final residuals at the optimised poses, before the RGB-D rigid
            # write-back below (the block answers from its memo of the last accepted step)
            final = block.residuals(backend.values_of(block.keys))
        # RGB-D poses are written back rigid (scale exactly 1): its depth priors act on inverse depths
        # in the source camera and observe no Sim(3) scale, and the scale prior only holds each BA
        # near its starting scale, so kept scales drifted from BA to BA (7-Scenes: s fell to 0.87
        # within 200 frames and the trajectory shrank; see docs/benchmarks/presets.md). Stereo observes the scale through
        # the metric baseline (resetting it there moved the EuRoC static clip by 2.6 mm instead of 0.8 mm).
        rigid = st.sensor_mode == "rgbd"
        for f in var_order:
            frame = g.frame(int(f))
            if rigid:
                frame.T_WC = _rigid(frame.T_WC)
            elif not isinstance(frame, BackendFrame):  # a frame built outside the frontend (tests)
                frame.T_WC = backend.pose_matrix(int(f))
        return report, final

    def depth_blocks(self, var) -> list:
        """Depth-alignment blocks between consecutive graph frames with surfaces, at least one of
        them free (in ``var``) and both backend keyframes (or about to be: free); the newest
        ``depth_align.window_pairs`` of them (:meth:`~fgslam.frontends.depth_tracking.DepthTracking.chain`)."""
        st = self.state
        free = {int(f) for f in var}
        fid_of = {self.key(int(f.fid)): int(f.fid) for f in st.graph.frames}

        def usable(key_a: int, key_b: int) -> bool:
            return all(fid_of[k] in free or st.backend.has_keyframe(fid_of[k]) for k in (key_a, key_b))

        return st.depth.chain([(self.key(int(f.fid)), f.surface) for f in st.graph.frames],
                              {self.key(f) for f in free}, usable=usable)

    def _write_depths(self, pos_src: np.ndarray, ukeys: np.ndarray, depth: np.ndarray) -> None:
        """Solved inverse depths ``depth`` of the patches ``ukeys`` (``src fid * K + patch``, source
        frames at graph positions ``pos_src``) back into their graph frames."""
        g = self.state.graph
        K = self.state.config.graph.patches_per_frame
        for pos in np.unique(pos_src):
            sel = pos_src == pos
            g.frames[pos].inv_depth[ukeys[sel] % K] = depth[sel]

    def _inv_depth_sigma(self, inv_depth: np.ndarray) -> np.ndarray:
        """Standard deviation of sensor inverse depths (1/m) under ``ba.depth_noise``."""
        return inv_depth_sigma(inv_depth, self.state.config.ba.depth_noise_model())

    def depth_observations(self, e, src_l, tgt_l, uv_src, struct_idx, weights, sens, has):
        """RGB-D observation model (ORB-SLAM3's RGB-D mode): every observation with a sensor depth
        also observes a virtual right camera ``depth_virtual_baseline`` to the right, at
        ``u_R = u - f b / z`` (the u row only; v would repeat the left image's). Sources observe
        themselves there (a pose-free inverse-depth term), targets at the measured pixel with the
        target frame's own depth reading. Returns the block's edge arrays (edges ``e`` first, in
        their order) extended with these rows, which go through the calibrated stereo residual:
        ``(src, tgt, right, uv_src, uv_tgt, weights (n, 2), struct_idx, K_right, T_CRCL)``."""
        st = self.state
        g = st.graph
        ba = st.config.ba
        fx = float(st.K[0])
        b = ba.depth_virtual_baseline
        T_CRCL = np.eye(4)
        T_CRCL[0, 3] = -b
        pos_t = g.positions(g.tgt[e])
        d_tgt = np.full(e.size, np.nan)
        left = ~g.right[e]
        for pos in np.unique(pos_t[left]):
            depth = g.frames[pos].depth
            if depth is None:
                continue
            sel = np.nonzero(left & (pos_t == pos))[0]
            d_tgt[sel] = self.measurer.depth_lookup(depth, g.uv[e][sel])
        ok_t = np.isfinite(d_tgt) & (d_tgt > 0)
        # source self-observations: one per patch with a reading
        ps = np.nonzero(has)[0]
        first = np.zeros(len(sens), np.int64)
        first[struct_idx[::-1]] = np.arange(e.size)[::-1]  # an edge of each patch (its source frame)
        src_self = src_l[first[ps]]
        uv_self = uv_src[first[ps]]
        uv_self_R = uv_self - np.stack([fx * b * sens[ps], np.zeros(ps.size)], 1)
        uv_t = g.uv[e][ok_t]
        uv_t_R = uv_t - np.stack([fx * b * d_tgt[ok_t], np.zeros(int(ok_t.sum()))], 1)
        sigma_px2 = ba.pixel_sigma ** 2
        # u_R rows: the left observation's pixel variance (sigma^2 / confidence, times its robust
        # weight) plus the depth noise in pixels; sources: a full-confidence pixel plus depth noise
        w_t, conf = weights[ok_t], g.confidence[e][ok_t]
        m = (w_t > 0) & (conf > 0)
        px_var = sigma_px2 / conf[m]
        w_R_t = np.zeros(w_t.size)
        w_R_t[m] = w_t[m] * px_var / (px_var + (fx * b * self._inv_depth_sigma(d_tgt[ok_t][m])) ** 2)
        var_s = sigma_px2 + (fx * b * self._inv_depth_sigma(sens[ps])) ** 2
        w_all = np.concatenate([np.stack([weights, weights], 1), np.stack([1.0 / var_s, np.zeros(ps.size)], 1),
                                np.stack([w_R_t, np.zeros(w_R_t.size)], 1)])
        n_new = ps.size + int(ok_t.sum())
        return (np.concatenate([src_l, src_self, src_l[ok_t]]), np.concatenate([tgt_l, src_self, tgt_l[ok_t]]),
                np.concatenate([g.right[e], np.ones(n_new, bool)]),
                np.concatenate([uv_src, uv_self, uv_src[ok_t]]), np.concatenate([g.uv[e], uv_self_R, uv_t_R]),
                w_all, np.concatenate([struct_idx, ps, struct_idx[ok_t]]), st.K, T_CRCL)

    def refine_depths_fixed(self, idx: np.ndarray, steps: int) -> None:
        """Per-patch Gauss-Newton on inverse depth with every pose fixed (stereo initial depths)."""
        if idx.size == 0:
            return
        st = self.state
        g = st.graph
        K = st.config.graph.patches_per_frame
        pkey = g.src[idx] * K + g.patch[idx]
        ukeys, struct_idx = np.unique(pkey, return_inverse=True)
        frames_used = np.union1d(g.src[idx], g.tgt[idx])
        R, t, s = sim3_matrix_components(g.poses(frames_used))
        pos_src = g.positions(ukeys // K)
        d0 = np.stack([f.inv_depth for f in g.frames])[pos_src, ukeys % K]
        uv_src = np.stack([f.uv for f in g.frames])[g.positions(g.src[idx]), g.patch[idx]]
        block = PatchBlock([], R, t, s, np.searchsorted(frames_used, g.src[idx]), np.searchsorted(frames_used, g.tgt[idx]),
                           g.right[idx], uv_src, g.uv[idx], g.confidence[idx], struct_idx, st.K, d0,
                           K_right=st.K_right, T_CRCL=st.T_CRCL, reprojection=st.reproj)
        block.refine_structure(None, steps)
        self._write_depths(pos_src, ukeys, block.structure.numpy())
