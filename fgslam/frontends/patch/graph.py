"""Patch graph bookkeeping (DPV-SLAM section 3.1): frames, patches with inverse depth, edges.

- Every graph frame holds K patches (centre ``uv`` in pixels, one inverse depth each, in the frame's
  metric camera frame) and its pose ``T_WC`` as a 4x4 Sim(3) matrix ``[[s R, t], [0, 1]]``.
- Frames are ordered by arrival; a frame's *position* is its index in that order (DPVO's buffer
  index). Windows are counted in positions: removing a redundant frame closes the gap.
- An edge ``(i, k, j)`` says: patch ``k`` of frame ``i`` is observed in frame ``j`` (left image, or
  the right image when ``right``), at ``uv`` with ``confidence`` (0: not measured or rejected) and a
  robust weight from the last optimisation. New frames get edges from the patches of the frames at
  most ``patch_lifetime`` positions older, and edges from their own patches into those frames.
- Edges whose source frame is more than ``removal_window`` positions old become *inactive*: they
  leave the local problem and move, compressed, into a bounded store for later global optimisation
  (loop closure). Frames older than every active edge's reach are popped by the frontend.

Pure numpy bookkeeping: no images, no optimisation. All edge operations are vectorised.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Optional

import numpy as np

from .config import PatchGraphConfig

if TYPE_CHECKING:
    from ...factors.depth_align import DepthSurface


@dataclass
class GraphFrame:
    """One frame of the patch graph.

    Attributes:
        fid: frontend frame id (order of arrival of input frames, unique).
        index, timestamp: the input frame's ``Frame.index`` and time (s).
        T_WC: (4, 4) float64 Sim(3) camera-to-world ``[[s R, t], [0, 1]]``.
        uv: (K, 2) float64 patch centres (pixels).
        inv_depth: (K,) float64 patch inverse depths (camera frame units).
        sensor_inv_depth: (K,) float64 inverse sensor depth at the patch centre (NaN: none).
        colour: (K, 3) uint8 colour of the patch centres (for point export).
        features, features_right: the measurement source's per-frame cache (None once released).
        depth: (H, W) sensor depth map in metres (RGB-D observation model only; None once released).
        surface: the depth's :class:`~fgslam.factors.depth_align.DepthSurface` (RGB-D depth alignment
            only; None once the frame leaves the graph).
    """

    fid: int
    index: int
    timestamp: float
    T_WC: np.ndarray
    uv: np.ndarray
    inv_depth: np.ndarray
    sensor_inv_depth: np.ndarray
    colour: np.ndarray
    features: object = None  # the source's own (MeasurementSource.prepare), opaque here
    features_right: object = None
    depth: Optional[np.ndarray] = None
    surface: Optional[DepthSurface] = None


@dataclass
class InactiveEdges:
    """Bounded store of inactive edges for global optimisation (oldest dropped first).

    Each edge keeps what a later bundle adjustment needs without the images: source/target frame
    ids, right-image flag, source pixel, observed pixel, confidence, and the patch's inverse depth
    when it became inactive. ``chunks`` is a list of dicts of equal-length arrays.
    """

    max_edges: int
    chunks: list = field(default_factory=list)
    count: int = 0
    dropped: int = 0

    def add(self, chunk: dict) -> None:
        n = int(chunk["src"].shape[0])
        if n == 0 or self.max_edges <= 0:
            self.dropped += n
            return
        self.chunks.append(chunk)
        self.count += n
        while self.count > self.max_edges and self.chunks:
            old = self.chunks.pop(0)
            m = int(old["src"].shape[0])
            self.count -= m
            self.dropped += m

    def arrays(self) -> dict:
        """All stored edges as one dict of arrays (empty arrays when none)."""
        if not self.chunks:
            return {}
        return {key: np.concatenate([c[key] for c in self.chunks]) for key in self.chunks[0]}


class PatchGraph:
    """Frames, patches and active edges (see module docstring)."""

    def __init__(self, config: PatchGraphConfig, max_inactive_edges: int):
        self.config = config
        self.frames: list[GraphFrame] = []
        self.inactive = InactiveEdges(max_inactive_edges)
        self._clear_edges()

    def _clear_edges(self) -> None:
        self.src = np.zeros(0, np.int64)  # source frame id
        self.patch = np.zeros(0, np.int64)  # patch index within the source frame
        self.tgt = np.zeros(0, np.int64)  # target frame id
        self.right = np.zeros(0, bool)  # target is the right image
        self.uv = np.zeros((0, 2))  # observed pixel in the target image
        self.confidence = np.zeros(0)  # measurement confidence in [0, 1]; 0: unmeasured / rejected
        self.robust = np.zeros(0)  # robust (IRLS) weight from the last optimisation
        self.created = np.zeros(0, np.int64)  # fid of the newest frame when the edge was created

    # ------------------------------------------------------------------ frames
    def __len__(self) -> int:
        return len(self.frames)

    @property
    def fids(self) -> np.ndarray:
        return np.array([f.fid for f in self.frames], dtype=np.int64)

    def position(self, fid: int) -> int:
        for pos, f in enumerate(self.frames):
            if f.fid == fid:
                return pos
        raise KeyError(f"frame {fid} is not in the patch graph")

    def frame(self, fid: int) -> GraphFrame:
        return self.frames[self.position(fid)]

    def positions(self, fids: np.ndarray) -> np.ndarray:
        """Positions of frame ids (all must be in the graph), vectorised."""
        all_fids = self.fids
        pos = np.searchsorted(all_fids, fids)
        return pos

    def add_frame(self, frame: GraphFrame) -> None:
        if self.frames and frame.fid <= self.frames[-1].fid:
            raise ValueError(f"frame ids must increase ({frame.fid} after {self.frames[-1].fid})")
        self.frames.append(frame)

    def remove_frame(self, fid: int) -> GraphFrame:
        """Drop a frame with its patches and every edge from or into it."""
        frame = self.frames.pop(self.position(fid))
        keep = (self.src != fid) & (self.tgt != fid)
        self._select(keep)
        return frame

    def poses(self, fids: np.ndarray) -> np.ndarray:
        """(n, 4, 4) T_WC of the given frame ids."""
        return np.stack([self.frames[p].T_WC for p in self.positions(fids)]) if len(fids) else np.zeros((0, 4, 4))

    # ------------------------------------------------------------------ edges
    @property
    def num_edges(self) -> int:
        return int(self.src.shape[0])

    def _select(self, keep: np.ndarray) -> None:
        for name in ("src", "patch", "tgt", "right", "uv", "confidence", "robust", "created"):
            setattr(self, name, getattr(self, name)[keep])

    def add_edges(self, src: np.ndarray, patch: np.ndarray, tgt: np.ndarray, right: np.ndarray) -> np.ndarray:
        """Append unmeasured edges; returns their indices."""
        n = int(src.shape[0])
        start = self.num_edges
        newest = self.frames[-1].fid if self.frames else -1
        self.src = np.concatenate([self.src, src.astype(np.int64)])
        self.patch = np.concatenate([self.patch, patch.astype(np.int64)])
        self.tgt = np.concatenate([self.tgt, tgt.astype(np.int64)])
        self.right = np.concatenate([self.right, right.astype(bool)])
        self.uv = np.concatenate([self.uv, np.full((n, 2), np.nan)])
        self.confidence = np.concatenate([self.confidence, np.zeros(n)])
        self.robust = np.concatenate([self.robust, np.ones(n)])
        self.created = np.concatenate([self.created, np.full(n, newest, np.int64)])
        return np.arange(start, start + n)

    def _patch_edges(self, sources: list[int], targets: list[int]) -> tuple[np.ndarray, ...]:
        """Every patch of each source frame to each target frame: ``(src, patch, tgt)`` arrays."""
        K = self.config.patches_per_frame
        pairs = np.array([(s, t) for s in sources for t in targets], dtype=np.int64).reshape(-1, 2)
        src = np.repeat(pairs[:, 0], K)
        tgt = np.repeat(pairs[:, 1], K)
        return src, np.tile(np.arange(K), len(pairs)), tgt

    def connect_new_frame(self, stereo: bool, stereo_cross: bool) -> np.ndarray:
        """Edges of the newest frame n: patches of the frames at most ``patch_lifetime`` positions
        older into n and n's patches into them (left images); with ``stereo`` also n's patches into
        its own right image (and, with ``stereo_cross``, the older patches into n's right image).
        Returns the new edges' indices."""
        n = len(self.frames) - 1
        new = self.frames[n].fid
        old = [f.fid for f in self.frames[max(0, n - self.config.patch_lifetime): n]]
        parts = [self._patch_edges(old, [new]), self._patch_edges([new], old)]
        if stereo:
            parts.append(self._patch_edges([new] + (old if stereo_cross else []), [new]))
        src = np.concatenate([p[0] for p in parts])
        patch = np.concatenate([p[1] for p in parts])
        tgt = np.concatenate([p[2] for p in parts])
        right = np.concatenate([np.zeros(len(parts[0][0]) + len(parts[1][0]), bool)] + (
            [np.ones(len(parts[2][0]), bool)] if stereo else []))
        return self.add_edges(src, patch, tgt, right)

    def connect_all(self, stereo: bool) -> np.ndarray:
        """Edges between every pair of graph frames at most ``patch_lifetime`` positions apart (both
        directions), plus own right-image edges with ``stereo`` (initialisation)."""
        fids = [f.fid for f in self.frames]
        L = self.config.patch_lifetime
        srcs, patches, tgts, rights = [], [], [], []
        for a, fa in enumerate(fids):
            near = [fb for b, fb in enumerate(fids) if b != a and abs(a - b) <= L]
            s, p, t = self._patch_edges([fa], near)
            srcs.append(s), patches.append(p), tgts.append(t), rights.append(np.zeros(len(s), bool))
            if stereo:
                s, p, t = self._patch_edges([fa], [fa])
                srcs.append(s), patches.append(p), tgts.append(t), rights.append(np.ones(len(s), bool))
        return self.add_edges(np.concatenate(srcs), np.concatenate(patches), np.concatenate(tgts), np.concatenate(rights))

    def deactivate_old_edges(self) -> int:
        """Move edges whose source is more than ``removal_window`` positions older than the newest
        frame to the inactive store (measured ones only); returns how many left the active set."""
        if not self.frames:
            return 0
        n = len(self.frames) - 1
        oldest_active = n - self.config.removal_window
        if oldest_active <= 0:
            return 0
        old_fids = self.fids[:oldest_active]
        old = np.isin(self.src, old_fids)
        if not old.any():
            return 0
        measured = old & (self.confidence > 0)
        if measured.any():
            src = self.src[measured]
            pos, patch = self.positions(src), self.patch[measured]
            uv_src = np.stack([f.uv for f in self.frames])[pos, patch]
            inv_depth = np.stack([f.inv_depth for f in self.frames])[pos, patch]
            self.inactive.add({
                "src": src.copy(), "patch": self.patch[measured].copy(), "tgt": self.tgt[measured].copy(),
                "right": self.right[measured].copy(), "uv_src": uv_src.astype(np.float32),
                "uv": self.uv[measured].astype(np.float32), "confidence": self.confidence[measured].astype(np.float32),
                "inv_depth": inv_depth.astype(np.float32),
            })
        count = int(old.sum())
        self._select(~old)
        return count

    def pop_frames_before(self, position: int) -> list[GraphFrame]:
        """Remove and return the frames at positions ``< position`` (they must have no active edges)."""
        if position <= 0:
            return []
        popped = self.frames[:position]
        self.frames = self.frames[position:]
        gone = np.array([f.fid for f in popped])
        keep = ~(np.isin(self.src, gone) | np.isin(self.tgt, gone))
        self._select(keep)
        return popped

    def clear(self) -> list[GraphFrame]:
        """Remove every frame and edge (re-initialisation); returns the frames."""
        popped, self.frames = self.frames, []
        self._clear_edges()
        return popped
