"""Patches of the patch frontend: patch selection (:func:`select_patches`), new graph frames
with their initial inverse depths, sensor depth look-ups, and edge measurement with the source
started from the current reprojection (:class:`PatchMeasurer`)."""

from __future__ import annotations

import time
import warnings

import numpy as np
import torch

from ...factors.reprojection import reproject_edges
from ...factors.robust import kernel_weight
from ...core.lie import sim3_matrix_components
from .graph import GraphFrame
from .state import BackendFrame, PatchState

#: inverse depth of new patches when no patch or sensor reading gives one
FALLBACK_INV_DEPTH = 1.0


def select_patches(image: np.ndarray, count: int, border: int, grid: list[int], method: str,
                   rng: np.random.Generator, block: int = 8, score_width: int = 0) -> np.ndarray:
    """Patch centres (count, 2) float64 in a grey image.

    ``corners``: the strongest local maxima (one per ``block`` x ``block`` pixels) of the min-eigenvalue corner
    response, an equal share per cell of a ``grid[0] x grid[1]`` grid, topped up with the best
    remaining ones; ``random``: uniform (DPVO). Centres keep ``border`` pixels from the edges.
    ``score_width`` > 0: the response is computed on the image resized to at most that width
    (centres are mapped back to full-resolution pixels).
    """
    import cv2  # deferred: cv2

    h, w = image.shape
    if method == "random":
        u = rng.uniform(border, w - 1 - border, count)
        v = rng.uniform(border, h - 1 - border, count)
        return np.stack([np.round(u), np.round(v)], 1)
    if 0 < score_width < w:
        a = score_width / w
        small = cv2.resize(image, (score_width, max(1, round(h * a))), interpolation=cv2.INTER_AREA)
        block_s = max(2, round(block * a))
        border_s = int(np.ceil((border + 0.5) * a))
        uv = select_patches(small, count, border_s, grid, method, rng, block_s)
        uv = np.round((uv + 0.5) / a - 0.5)
        uv[:, 0] = uv[:, 0].clip(border, w - 1 - border)
        uv[:, 1] = uv[:, 1].clip(border, h - 1 - border)
        return uv
    from .select_jit import select_corners  # deferred: numba (compiled kernel, core/jit.py)

    score = cv2.cornerMinEigenVal(image, 3)
    blocks = max(0, (h - 2 * border) // block) * max(0, (w - 2 * border) // block)
    # small random jitter breaks ties between equal scores (flat regions)
    jitter = rng.uniform(0, 1e-9, blocks)
    chosen, u, v = select_corners(score, border, block, w, h, grid[0], grid[1], jitter, count)
    uv = np.stack([u[chosen], v[chosen]], 1).astype(np.float64)
    if uv.shape[0] < count:  # tiny image: pad with random centres
        extra = count - uv.shape[0]
        uv = np.concatenate([uv, np.stack([rng.uniform(border, w - 1 - border, extra),
                                            rng.uniform(border, h - 1 - border, extra)], 1).round()])
    return uv


def row_nanmedian(x: np.ndarray) -> np.ndarray:
    """``np.nanmedian(x, axis=1)`` of a 2-D float array, the same values (NaN for a row without a
    number), without numpy's per-row Python loop: each row sorted (NaN last), the middle of its numbers."""
    if x.shape[1] == 0:
        return np.full(x.shape[0], np.nan, dtype=x.dtype)
    n = np.count_nonzero(~np.isnan(x), axis=1)
    s = np.sort(x, axis=1)
    rows = np.arange(x.shape[0])
    med = (s[rows, np.maximum(n - 1, 0) // 2] + s[rows, n // 2]) / 2 + 0.0  # + 0.0: numpy's median of zeros is +0.0
    return np.where(n > 0, med, np.nan)


class PatchMeasurer:
    """New graph frames and edge measurements on the shared :class:`~.state.PatchState`."""

    def __init__(self, state: PatchState):
        self.state = state

    def prepare(self, frame, left: bool = True, right: bool = True):
        """The source's features of the frame's left image (``left``) and, for stereo, right image (``right``)."""
        st = self.state
        t0 = time.perf_counter()
        colour = st.source.colour
        feats = st.source.prepare(frame.colour_or_grey() if colour else frame.image) if left else None
        feats_right = None
        if right and st.sensor_mode == "stereo":
            feats_right = st.source.prepare(frame.colour_or_grey(right=True) if colour else frame.image_right)
        st.times["flow"] += time.perf_counter() - t0
        return feats, feats_right

    def select(self, image: np.ndarray) -> np.ndarray:
        """Patch centres (K, 2) of a new frame's grey ``image`` under the ``graph`` settings."""
        gcfg, st = self.state.config.graph, self.state
        return select_patches(image, gcfg.patches_per_frame, st.border, gcfg.selection_grid, gcfg.selection, st.rng,
                              gcfg.candidate_block, gcfg.score_width)

    def sensor_inv_depth(self, frame, uv: np.ndarray) -> np.ndarray:
        """RGB-D: inverse sensor depth (n,) at pixels ``uv`` (:meth:`depth_lookup`); else NaN."""
        if self.state.sensor_mode != "rgbd" or frame.depth is None:
            return np.full(len(uv), np.nan)
        return self.depth_lookup(frame.depth, uv)

    def depth_lookup(self, depth: np.ndarray, uv: np.ndarray) -> np.ndarray:
        """Inverse sensor depth (n,) at pixels uv (n, 2): median of the valid readings in a window,
        NaN where most are invalid or the window spans a depth discontinuity."""
        out = np.full(len(uv), np.nan)
        h, w = depth.shape
        ba = self.state.config.ba
        r = ba.depth_window
        offs = np.arange(-r, r + 1)
        us = (uv[:, 0:1].round().astype(int) + offs[None, :]).clip(0, w - 1)
        vs = (uv[:, 1:2].round().astype(int) + offs[None, :]).clip(0, h - 1)
        win = depth[vs[:, :, None], us[:, None, :]].reshape(len(uv), -1).astype(np.float64)
        valid = (win > ba.depth_min) & (win <= ba.depth_max)
        win = np.where(valid, win, np.nan)
        with np.errstate(all="ignore"), warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN windows: no reading there
            med = row_nanmedian(win)
            spread = (np.nanmax(win, axis=1) - np.nanmin(win, axis=1)) / med
        good = (valid.sum(1) > valid.shape[1] // 2) & np.isfinite(med) & (spread < ba.depth_max_spread)
        out[good] = 1.0 / med[good]
        return out

    def new_graph_frame(self, fid: int, frame, T_WC: np.ndarray, features, features_right, surface=None) -> GraphFrame:
        """A graph frame of ``frame`` at pose ``T_WC`` with new patches: inverse depth from the sensor
        where it reads one, else the median of the newest graph frame's (measured) patches. ``surface``:
        the frame's depth surface when the caller made it already (RGB-D depth alignment)."""
        st = self.state
        uv = self.select(frame.image)
        ui, vi = uv[:, 0].astype(int), uv[:, 1].astype(int)
        if frame.rgb is not None:
            colour = frame.rgb[vi, ui].astype(np.uint8)
        else:
            colour = np.repeat(frame.image[vi, ui][:, None], 3, 1).astype(np.uint8)
        sensor = self.sensor_inv_depth(frame, uv)
        if len(st.graph):
            prev = st.graph.frames[-1].inv_depth
            if st.config.tracking.median_of_measured:
                prev = self.measured_inv_depths(st.graph.frames[-1])
            median = float(np.median(prev[prev > 0])) if (prev > 0).any() else FALLBACK_INV_DEPTH
        else:  # the first graph frame: stereo starts its right-image search from a configured depth
            start = st.config.ba.stereo_init_inv_depth if st.sensor_mode == "stereo" else FALLBACK_INV_DEPTH
            median = float(np.nanmedian(sensor)) if np.isfinite(sensor).any() else start
        inv_depth = np.where(np.isfinite(sensor), sensor, median)
        keep_depth = st.sensor_mode == "rgbd" and st.config.ba.depth_model == "observation"
        return BackendFrame(fid=fid, index=int(frame.index), timestamp=float(frame.timestamp), T_WC=np.array(T_WC, dtype=np.float64),
                            uv=uv, inv_depth=inv_depth, sensor_inv_depth=sensor, colour=colour,
                            features=features, features_right=features_right, depth=frame.depth if keep_depth else None,
                            surface=surface if surface is not None else st.depth.surface(frame.depth))

    def measured_inv_depths(self, f: GraphFrame) -> np.ndarray:
        """Inverse depths of graph frame ``f``'s patches that have a BA-inlier measurement (source ``f``);
        all of them when fewer than ``tracking.min_measured_patches`` have one. The others still
        hold the value they were created with, which would otherwise become the median forever."""
        g = self.state.graph
        seen = np.zeros(len(f.inv_depth), bool)
        seen[g.patch[(g.confidence > 0) & (g.robust > 0) & (g.src == f.fid)]] = True
        measured = f.inv_depth[seen & (f.inv_depth > 0)]
        return measured if len(measured) >= self.state.config.tracking.min_measured_patches else f.inv_depth

    def predict_edges(self, idx: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Source pixels (n, 2), current reprojections (n, 2) and validity (n,) of edges ``idx``."""
        st = self.state
        g = st.graph
        src, tgt, patch, right = g.src[idx], g.tgt[idx], g.patch[idx], g.right[idx]
        pos_s, pos_t = g.positions(src), g.positions(tgt)
        uv_all = np.stack([f.uv for f in g.frames])
        d_all = np.stack([f.inv_depth for f in g.frames])
        uv_src = uv_all[pos_s, patch]
        d = d_all[pos_s, patch]
        R, t, s = sim3_matrix_components(np.stack([f.T_WC for f in g.frames]))
        ps, pt = torch.as_tensor(pos_s), torch.as_tensor(pos_t)
        uv, valid = reproject_edges(torch.as_tensor(uv_src), torch.as_tensor(d), (R[ps], t[ps], s[ps]),
                                    (R[pt], t[pt], s[pt]), st.K, right=torch.as_tensor(right), K_right=st.K_right,
                                    T_CRCL=st.T_CRCL, config=st.reproj)
        uv_pred = uv.numpy()
        return uv_src, uv_pred, valid.numpy() & st.inside(uv_pred)

    def measure(self, idx: np.ndarray, huber: bool = False) -> None:
        """Measure edges ``idx`` with the source, started from their current reprojection; ``huber``:
        their robust weights from the distance to it (:meth:`huber_from`), else 1."""
        if idx.size == 0:
            return
        st = self.state
        t0 = time.perf_counter()
        g = st.graph
        uv_src, uv_pred, ok = self.predict_edges(idx)
        g.confidence[idx] = 0.0
        g.robust[idx] = 1.0
        frames = {f.fid: f for f in g.frames}
        key = (g.src[idx] * (g.tgt.max() + 1) + g.tgt[idx]) * 2 + g.right[idx]
        requests, selections = [], []
        for k in np.unique(key[ok]):
            sel = np.nonzero(ok & (key == k))[0]
            e0 = idx[sel[0]]
            fs, ft = frames[int(g.src[e0])], frames[int(g.tgt[e0])]
            tgt_feats = ft.features_right if g.right[e0] else ft.features
            if fs.features is None or tgt_feats is None:
                continue
            requests.append((fs.features, tgt_feats, uv_src[sel], uv_pred[sel]))
            selections.append(idx[sel])
        for edges, m in zip(selections, st.source.measure_batch(requests)):
            g.uv[edges] = m.uv
            g.confidence[edges] = m.confidence
        if huber:
            self.huber_from(idx, uv_pred)
        st.times["flow"] += time.perf_counter() - t0

    def huber_from(self, idx: np.ndarray, uv_pred: np.ndarray) -> None:
        """``ba.measured_huber``: robust weights of freshly measured edges ``idx`` from their distance to
        the reprojections ``uv_pred`` (n, 2) they were measured from: a track far from where the current
        estimate puts it (a wrong lock, an occlusion edge) enters the next BA with a Huber weight
        instead of full weight, so one LM step cannot follow a few gross outliers."""
        g = self.state.graph
        r = np.nan_to_num(np.linalg.norm(g.uv[idx] - uv_pred, axis=1), nan=0.0)
        g.robust[idx] = self.huber_weights(g.confidence[idx], r)

    def huber_weights(self, confidence: np.ndarray, residual_px: np.ndarray) -> np.ndarray:
        """Huber weights (``ba.huber_delta``) of pixel residual norms whitened by ``ba.pixel_sigma``
        and the measurements' confidences."""
        ba = self.state.config.ba
        white = np.sqrt(confidence) * residual_px / ba.pixel_sigma
        return kernel_weight(torch.as_tensor(white), "huber", ba.huber_delta).numpy()
