"""The dense frontend's keyframe policy: a new keyframe's inverse depths (RGB-D sensor, stereo disparity
or splatted from the previous keyframe) and its edges (step 2 of :mod:`.frontend`), the removal of a
redundant keyframe (step 4) and the retirement of old keyframes from the active graph (step 5)."""

from __future__ import annotations

import logging
import time

import numpy as np
import torch

from ...factors.dense import DenseStereo
from ...factors.reprojection import reproject
from ..records import KeyframePose, RelativePose
from .contributor import DenseLoopContributor
from .graph import DenseKeyframeState
from .state import DenseState
from .weights import huber_weight, information, pool

logger = logging.getLogger(__name__)


class DenseKeyframes:
    """Adds, connects, removes and retires the keyframes of the shared ``state`` (its graph, source,
    backend, pose records, counts and stage times); retired keyframes go to the loop ``contributor``."""

    def __init__(self, state: DenseState, contributor: DenseLoopContributor):
        self.state = state
        self.contributor = contributor

    def add(self, fid: int, frame, T_WC: np.ndarray, source_added: bool = False, surface=None) -> None:
        """Frame ``fid`` becomes a keyframe at ``T_WC`` (``source_added``: the source has its image;
        ``surface``: its depth surface, RGB-D depth alignment)."""
        st = self.state
        g = st.graph
        s = st.stride
        image = st.cropped(frame.image)
        if not source_added:
            st.source.add_frame(fid, st.source_image(frame))
        rgb = st.cropped(frame.rgb) if frame.rgb is not None else np.repeat(image[..., None], 3, axis=-1)
        colour = np.clip(pool(rgb.astype(np.float32), s), 0, 255).astype(np.uint8)
        sensor = None
        inv = None
        if st.sensor_mode == "rgbd":
            sensor = self._grid_depth(st.cropped(frame.depth))
            inv = 1.0 / sensor
        prev = g.keyframes[g.active[-1]] if g.active else None
        if inv is None or not np.isfinite(inv).any():
            inv = self._splat_depth(prev, T_WC) if prev is not None else np.full(g.shape, 1.0)
        else:
            fill = np.nanmedian(inv)
            inv = np.where(np.isfinite(inv), inv, fill)
        kf = DenseKeyframeState(fid=fid, index=int(frame.index), timestamp=float(frame.timestamp), image=frame.image,
                                inv_depth=inv.astype(np.float64), colour=colour, sensor_depth=sensor,
                                depth_image=frame.depth if st.sensor_mode == "rgbd" else None,
                                confidence=np.zeros(g.shape), surface=surface)
        st.backend.add_keyframe(fid, T_WC, float(frame.timestamp))
        st.records[fid] = KeyframePose()
        g.add(kf)
        st.counts["keyframes_added"] += 1
        if st.sensor_mode == "stereo":
            self._measure_stereo(kf, st.source_image(frame, right=True), init_depth=True)
        self._connect(fid)

    def _grid_depth(self, depth: np.ndarray) -> np.ndarray:
        """Sensor depth per grid block (metres; NaN where the block has too few readings, or spans a depth
        edge / misregistered boundary: relative spread of its inverse depths above ``ba.depth_edge``)."""
        s = self.state.stride
        z = np.asarray(depth, dtype=np.float64)
        ok = np.isfinite(z) & (z > 0)
        inv = np.where(ok, 1.0 / np.where(ok, z, 1.0), 0.0)
        n = pool(ok.astype(np.float64), s)
        mean = pool(inv, s) / np.maximum(n, 1e-12)
        sq = pool(inv * inv, s) / np.maximum(n, 1e-12)
        spread = np.sqrt(np.maximum(sq - mean * mean, 0.0)) / np.maximum(mean, 1e-12)
        good = (n >= 0.5) & (mean > 0)
        if self.state.config.ba.depth_edge > 0:
            good &= spread <= self.state.config.ba.depth_edge
        bad = int((~good).sum())
        if bad == good.size:
            logger.info("RGB-D keyframe: no valid sensor depth (holes / NaN); depth from the flow only")
        return np.where(good, 1.0 / np.maximum(mean, 1e-12), np.nan)

    def _splat_depth(self, prev: DenseKeyframeState, T_WC: np.ndarray) -> np.ndarray:
        """Inverse-depth map of a new keyframe at ``T_WC``: the previous keyframe's map transferred into it
        (z-buffered, nearest grid pixel), holes filled with the median."""
        st = self.state
        g = st.graph
        h, w = g.shape
        fx, fy, cx, cy = st.K_grid
        T_WCp = st.keyframe_T_WC(prev.fid)
        P = np.linalg.inv(T_WC) @ T_WCp  # prev camera -> new camera (Sim(3) matrices: metric per camera)
        z = 1.0 / np.maximum(prev.inv_depth, 1e-9)
        X = np.stack([(g.grid[..., 0] - cx) / fx * z, (g.grid[..., 1] - cy) / fy * z, z], -1).reshape(-1, 3)
        Xn = X @ P[:3, :3].T + P[:3, 3]
        zn = Xn[:, 2]
        ok = zn > st.config.ba.min_depth
        u = np.rint(fx * Xn[:, 0] / np.where(ok, zn, 1.0) + cx).astype(np.int64)
        v = np.rint(fy * Xn[:, 1] / np.where(ok, zn, 1.0) + cy).astype(np.int64)
        ok &= (u >= 0) & (u < w) & (v >= 0) & (v < h)
        out = np.zeros(h * w)
        np.maximum.at(out, v[ok] * w + u[ok], 1.0 / zn[ok])
        fill = np.median(out[out > 0]) if (out > 0).any() else float(np.median(prev.inv_depth))
        return np.where(out > 0, out, fill).reshape(h, w)

    def _measure_stereo(self, kf: DenseKeyframeState, right: np.ndarray, init_depth: bool) -> None:
        """Left-right flow of a stereo keyframe (its rows fix the metric depth through ``T_CRCL``);
        ``init_depth``: the keyframe's inverse depths from the measured disparity first."""
        st = self.state
        g = st.graph
        rid = -(kf.fid + 1)
        t0 = time.perf_counter()
        st.source.add_frame(rid, right)
        try:
            if init_depth:
                (rev,) = st.source.revise([(kf.fid, rid)], g.grid[None])
                baseline = float(np.linalg.norm(st.T_CRCL[:3, 3]))
                disparity = g.grid[..., 0] - rev.target[..., 0]
                good = (rev.weight.mean(-1) > st.config.tracking.confident_weight) & (disparity > 1e-3)
                if good.sum() >= 0.05 * good.size:
                    inv = disparity / (st.K_grid[0] * baseline)
                    kf.inv_depth = np.where(good, inv, np.median(inv[good]))
            I = (torch.eye(3, dtype=torch.float64), torch.zeros(3, dtype=torch.float64), torch.ones((), dtype=torch.float64))
            uv, ok = reproject(torch.as_tensor(g.grid.reshape(-1, 2)), torch.as_tensor(kf.inv_depth.reshape(-1)), I, I,
                               g.K, torch.as_tensor(st.K_right_grid), T_CtCj=torch.as_tensor(st.T_CRCL),
                               config=st.reproj)
            induced = uv.numpy().reshape(*g.shape, 2).copy()
            induced[~ok.numpy().reshape(g.shape)] = np.nan
            (rev,) = st.source.revise([(kf.fid, rid)], induced[None])
        finally:
            st.source.remove_frame(rid)
        st.times["flow"] += time.perf_counter() - t0
        weight = rev.weight * huber_weight(rev.target - induced, st.config, st.stride) * st.config.ba.stereo_weight
        kf.stereo = DenseStereo(rev.target, weight * information(st.config, st.stride), st.K_right_grid, st.T_CRCL)

    def _connect(self, fid: int) -> None:
        """Edges (both ways) from the new keyframe to the previous ``temporal_radius`` active keyframes
        and to the ``neighbours`` nearest others by flow distance (below ``max_edge_distance``)."""
        g = self.state.graph
        cfg = self.state.config.graph
        others = [f for f in g.active if f != fid]
        if not others:
            return
        temporal = others[-cfg.temporal_radius:]
        rest = [f for f in others if f not in temporal]
        near: list[int] = []
        if rest:
            d = g.flow_distance([(fid, f) for f in rest] + [(f, fid) for f in rest], cfg.distance_stride)
            d = 0.5 * (d[:len(rest)] + d[len(rest):])
            order = np.argsort(d, kind="stable")
            near = [rest[k] for k in order[:cfg.neighbours] if d[k] < cfg.max_edge_distance]
        for f in temporal + near:
            for e in ((fid, f), (f, fid)):
                g.ensure_edge(e)

    def connect_neighbourhood(self, radius: int) -> list[tuple[int, int]]:
        """Monocular initialisation, first phase: the edges (both ways) between active keyframes at most
        ``radius`` apart in order (DROID-SLAM's ``add_neighborhood_factors``), added where missing."""
        g = self.state.graph
        free = list(g.active)
        edges = []
        for a, fa in enumerate(free):
            for fb in free[a + 1:a + 1 + radius]:
                edges += [(fa, fb), (fb, fa)]
        for e in edges:
            g.ensure_edge(e)
        return edges

    def connect_all(self) -> None:
        """Monocular initialisation: each active keyframe connected to every other within reach (few keyframes)."""
        g = self.state.graph
        cfg = self.state.config.graph
        free = list(g.active)
        for fid in free:
            for f in free:
                if f != fid and g.distance(fid, f, cfg.distance_stride) < cfg.max_edge_distance:
                    g.ensure_edge((fid, f))

    def remove_redundant(self) -> int | None:
        """Remove the second newest keyframe when its flow distance to the one before is below
        ``graph.remove_threshold`` (its pose kept relative to it); the removed frame's index, or None."""
        st = self.state
        g = st.graph
        thr = st.config.graph.remove_threshold
        if thr <= 0 or len(g.active) < 4:
            return None
        a, b = g.active[-3], g.active[-2]
        if g.distance(a, b, st.config.graph.distance_stride) >= thr:
            return None
        kf = g.keyframes[b]
        st.records[b] = RelativePose(a, np.linalg.inv(st.keyframe_T_WC(a)) @ st.keyframe_T_WC(b))
        g.remove(b)
        st.backend.remove_keyframe(b)
        st.source.remove_frame(b)
        st.counts["keyframes_removed"] += 1
        # keep the newest keyframe connected to the older one
        new = g.active[-1]
        for e in ((new, a), (a, new)):
            g.ensure_edge(e)
        return kf.index

    def retire(self) -> None:
        """Keyframes beyond ``active_keyframes`` leave the active graph (handed to the loop closer);
        images beyond ``global_ba.max_keyframes`` are dropped (their last edges kept)."""
        st = self.state
        g = st.graph
        while len(g.active) > st.config.graph.active_keyframes:
            gone = g.active.pop(0)
            for e, m in g.edges.items():  # the local BA never re-measures it again: its induced field goes (memory)
                if gone in e:
                    m.induced = None
        self.contributor.feed()
        order = g.order()
        for fid in order[: max(0, len(order) - st.config.global_ba.max_keyframes)]:
            kf = g.keyframes[fid]
            if kf.image is not None and fid not in g.active:
                kf.image = None
                kf.surface = None
                st.source.remove_frame(fid)
