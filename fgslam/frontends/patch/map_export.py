"""The patch frontend's map for PLY and ``fgslam export``: one point per patch of positive inverse
depth of every keyframe (graph and finalised), with its track in :func:`export_map`."""

from __future__ import annotations

import numpy as np

from ...core.mapdata import MapExport, rigid_poses

from .graph import GraphFrame
from .state import PatchState


def frame_points(K: np.ndarray, f: GraphFrame) -> tuple[np.ndarray, np.ndarray]:
    """World points ``X_W`` (M, 3) and colours (M, 3) of keyframe ``f``'s patches of positive inverse
    depth (intrinsics ``K`` = fx, fy, cx, cy)."""
    ok = f.inv_depth > 0
    rays = np.stack([(f.uv[:, 0] - K[2]) / K[0], (f.uv[:, 1] - K[3]) / K[1], np.ones(len(f.uv))], 1)
    X_C = rays[ok] / f.inv_depth[ok, None]
    X_W = X_C @ f.T_WC[:3, :3].T + f.T_WC[:3, 3]
    return X_W, f.colour[ok]


def keyframe_points(state: PatchState) -> tuple[np.ndarray, np.ndarray] | None:
    """Points and colours of every keyframe (finalised, then graph), or None without keyframes."""
    K = state.K.numpy()
    chunks = [frame_points(K, f) for f in list(state.final.values()) + state.graph.frames]
    if not chunks:
        return None
    return np.concatenate([c[0] for c in chunks]), np.concatenate([c[1] for c in chunks])


def export_map(state: PatchState):
    """Keyframes (graph and finalised) and one point per patch of positive inverse depth, with
    its track: the source keyframe's patch centre plus every measured left-image edge of the
    patch into another keyframe (active and inactive edges; pixel where the source measured it)."""
    frames = sorted(list(state.final.values()) + state.graph.frames, key=lambda f: f.fid)
    if not frames:
        return None
    K = state.K.numpy()
    fids = np.array([f.fid for f in frames], dtype=np.int64)
    X_W, colour, src_fid, src_patch, src_uv = [], [], [], [], []
    for f in frames:
        X, c = frame_points(K, f)
        ok = np.flatnonzero(f.inv_depth > 0)
        X_W.append(X), colour.append(c), src_fid.append(np.full(len(ok), f.fid)), src_patch.append(ok)
        src_uv.append(f.uv[ok])
    src_fid, src_patch = np.concatenate(src_fid), np.concatenate(src_patch)
    # point index of (source fid, patch): lexicographic search over the sorted (fid, patch) pairs
    stride = state.config.graph.patches_per_frame + 1
    order_key = src_fid * stride + src_patch
    g, inactive = state.graph, state.graph.inactive.arrays()
    e_src = np.concatenate([g.src, inactive.get("src", np.zeros(0, np.int64))])
    e_patch = np.concatenate([g.patch, inactive.get("patch", np.zeros(0, np.int64))])
    e_tgt = np.concatenate([g.tgt, inactive.get("tgt", np.zeros(0, np.int64))])
    e_uv = np.concatenate([g.uv, inactive.get("uv", np.zeros((0, 2)))]).astype(np.float64)
    e_ok = np.concatenate([~g.right & (g.confidence > 0), ~inactive.get("right", np.zeros(0, bool))])
    e_ok &= np.isin(e_tgt, fids) & (e_tgt != e_src) & np.all(np.isfinite(e_uv), axis=1)
    e_key = e_src * stride + e_patch
    pos = np.clip(np.searchsorted(order_key, e_key), 0, max(len(order_key) - 1, 0))
    e_ok &= order_key[pos] == e_key if len(order_key) else np.zeros_like(e_ok)
    n = len(order_key)
    return MapExport(
        fids, [f.timestamp for f in frames], rigid_poses(np.stack([f.T_WC for f in frames])),
        np.concatenate(X_W), np.concatenate(colour),
        track_point=np.concatenate([np.arange(n), pos[e_ok]]),
        track_kf=np.concatenate([src_fid, e_tgt[e_ok]]),
        track_uv=np.concatenate([np.concatenate(src_uv), e_uv[e_ok]]),
    )
