"""Mixing families (issue 13 item 9): pointmap edges between another family's keyframes, in the same graph.

:class:`PointmapMix` is a factor plugin (``fgslam/services/plugins.py``), selected by config beside any
primary frontend that feeds the backend (the patch family today)::

    factors:
      - class: fgslam.frontends.pointmap.mix:PointmapMix
        options: {lag: 3, pointmap: {image_width: 320}}

It registers ``backend.on_keyframe`` and, at the safe point after every frame (``poll``), takes the
primary's keyframes that are at least ``lag`` keyframes old and still in the backend (the patch family
removes redundant keyframes a few frames after adding them), gets their images from the primary
(:meth:`~fgslam.contracts.contributor.Contributor.keyframe_image`: grey image, intrinsics, depth), builds
their pointmaps with a built-in source (``rgbd`` when the images carry depth, else the monocular
two-view source against the previous pointmap keyframe, scaled to the backend's relative translation;
images resized to ``pointmap.image_width``)
and measures a pointmap edge to the previous one (:func:`.keyframes.measure_edge`: projective matching,
the tracking solver as verification, SE(3): the primary holds the keyframe scales). Each edge is one
:class:`~fgslam.factors.pointmap_block.PointmapBlock` under the owner ``pointmap``
(``set_blocks("pointmap", ...)``), so the primary's window optimisation includes the edges touching its
free keyframes, and a keyframe the primary removes takes its edges with it.

The patch family keeps keyframe images only while its loop closure is on (``loop_closure.mode:
classical`` or ``both``); without images the plugin logs it once and adds nothing.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from types import SimpleNamespace

import numpy as np
import torch

from ...backend.graph import Backend
from ...core.config import MAX_KEYFRAMES, ranged
from ...contracts.contributor import Contributor
from ...contracts.plugins import parse_options
from ...core.errors import DataError, OptimizationError
from ...factors.pointmap_block import PointmapBlock, PointmapEdge
from .camera import WorkingCamera
from .config import PointmapConfig
from .keyframes import PointmapKeyframe, measure_edge
from .source import make_pointmap_source

logger = logging.getLogger(__name__)

__all__ = ["PointmapMix", "PointmapMixOptions"]

OWNER = "pointmap"


@dataclass
class PointmapMixOptions:
    """Options of :class:`PointmapMix` (``factors[i].options``)."""

    lag: int = ranged(3, ge=0, le=MAX_KEYFRAMES)  # a primary keyframe is used once this many newer keyframes exist (it has settled)
    min_gap: int = ranged(1, ge=1, le=MAX_KEYFRAMES)  # at least this many primary keyframes between two pointmap keyframes
    pointmap: PointmapConfig = field(default_factory=PointmapConfig)  # source (auto: rgbd with depth, else mono), matching, residuals


class PointmapMix:
    """A pointmap contributor beside the run's primary frontend (module docstring)."""

    def __init__(self, options: Mapping[str, object], key: str) -> None:
        self.key = key
        self.options = parse_options(PointmapMixOptions, options, key)
        self.options.pointmap.validate()
        self.backend: Backend | None = None
        self.primary: Contributor | None = None  # the run's frontend (the first on the backend's correction route)
        self._queue: list[int] = []
        self._kfs: dict[int, PointmapKeyframe] = {}
        self._edges: dict[tuple[int, int], PointmapEdge] = {}
        self._source = None
        self._kind: str | None = None
        self._K: np.ndarray | None = None
        self._cam: WorkingCamera | None = None
        self._warned = False
        self._seen = 0
        self.counts = {"keyframes": 0, "edges": 0, "rejected": 0, "no_image": 0}
        self.seconds = 0.0

    def attach(self, backend: Backend) -> None:
        self.backend = backend
        contributors = backend.contributors
        self.primary = contributors[0] if contributors else None
        if self.primary is None or not callable(getattr(self.primary, "keyframe_image", None)):
            logger.warning("%s: the run's frontend gives no keyframe images; no pointmap edges", self.key)
        backend.on_keyframe(self._on_keyframe)

    def _on_keyframe(self, kf_id: int, timestamp: float, key: int) -> None:
        self._queue.append(int(kf_id))

    # ------------------------------------------------------------------ safe point
    def poll(self, backend: Backend) -> None:
        if self.primary is None:
            return
        t0 = time.perf_counter()
        try:
            with torch.no_grad():
                self._step()
        except (DataError, OptimizationError, RuntimeError, np.linalg.LinAlgError) as exc:
            logger.warning("%s: pointmap edge failed (%s); skipped", self.key, exc)
        self.seconds += time.perf_counter() - t0

    def finish(self, backend: Backend) -> None:
        self.poll(backend)
        logger.info("%s: %s (%.1f s)", self.key, self.counts, self.seconds)

    def _step(self) -> None:
        b = self.backend
        for kid in [k for k in self._kfs if not b.has_keyframe(k)]:  # removed by the primary
            del self._kfs[kid]
        alive = [k for k in self._queue if b.has_keyframe(k)]
        self._queue = alive
        ready = alive[: max(len(alive) - self.options.lag, 0)]
        if not ready:
            return
        self._queue = alive[len(ready):]
        for kf_id in ready[:: self.options.min_gap]:
            self._add(kf_id)
        self._edges = {p: e for p, e in self._edges.items() if b.has_keyframe(p[0]) and b.has_keyframe(p[1])}
        cfg = self.options.pointmap
        b.set_blocks(OWNER, [PointmapBlock([e], cfg.block, self._K) for e in self._edges.values()])

    def _add(self, kf_id: int) -> None:
        img = self.primary.keyframe_image(kf_id)
        if img is None:
            self.counts["no_image"] += 1
            if not self._warned:
                logger.warning("%s: the primary frontend keeps no image of keyframe %d (the patch family keeps them "
                               "with loop_closure.mode classical or both); no pointmap edge", self.key, kf_id)
                self._warned = True
            return
        cfg = self.options.pointmap
        if self._source is None:
            self._kind = cfg.source_kind("rgbd" if img.depth is not None else "mono")
            if self._kind not in ("rgbd", "mono"):
                raise DataError(f"{self.key}: mixing supports the rgbd and mono pointmap sources, not {self._kind}")
            H0, W0 = img.image.shape[:2]
            self._cam = WorkingCamera(SimpleNamespace(width=W0, height=H0, K=img.K), cfg.image_width, self._kind)
            self._K = self._cam.K
            self._source = make_pointmap_source(replace(cfg.source, kind=self._kind), self._K)
        grey = self._cam.image(img.image)
        depth = self._cam.depth(img.depth) if self._kind == "rgbd" else None
        img = replace(img, image=grey, depth=depth, K=self._K)
        H, W = grey.shape[:2]
        self._source.add_frame(kf_id, grey, depth=depth)
        prev = next(reversed(self._kfs.values()), None)
        T_WC = self.backend.pose_matrix(kf_id)
        if self._kind == "rgbd":
            pair = self._source.predict(kf_id, kf_id, np.eye(4))
            X, C, D = pair.X_i_in_i, pair.C_i, pair.D_i
        else:
            if prev is None:
                kf = self._keyframe(kf_id, img, H, W, None, None, None)  # waits for a pair
                self._kfs[kf_id] = kf
                return
            pair = self._source.predict(prev.fid, kf_id)
            T_prev = self.backend.pose_matrix(prev.fid)
            d = np.linalg.norm((np.linalg.inv(T_prev) @ T_WC)[:3, 3])
            if pair.T_CiCj is None or not d > 0:
                self.counts["rejected"] += 1
                self._source.remove_frame(kf_id)
                return
            a = d / max(float(np.linalg.norm(pair.T_CiCj[:3, 3])), 1e-12)  # the pair in the map's scale
            X, C, D = pair.X_j_in_j * a, pair.C_j, pair.D_j
            if prev.X is None:  # the first keyframe gets its pointmap from the first pair
                prev.X = torch.from_numpy(np.ascontiguousarray(pair.X_i_in_i * a, np.float32)).reshape(-1, 3)
                prev.C = torch.from_numpy(np.ascontiguousarray(pair.C_i, np.float32)).reshape(-1)
        kf = self._keyframe(kf_id, img, H, W, X, C, D)
        self._kfs[kf_id] = kf
        self.counts["keyframes"] += 1
        if len(self._kfs) > 2:  # the source keeps the newest two frames
            old = list(self._kfs)[-3]
            self._source.remove_frame(old)
            self._kfs[old].release()
        if prev is None or prev.X is None:
            return
        T_ab = np.linalg.inv(self.backend.pose_matrix(prev.fid)) @ T_WC
        meas = measure_edge(prev, kf, T_ab, self._K, cfg.block, cfg.tracking, cfg.graph, cfg.matching,
                            cfg.source.descriptor, True, cfg.query_stride)
        if meas is None:
            self.counts["rejected"] += 1
            return
        self._edges[(prev.fid, kf_id)] = meas.edge
        self.counts["edges"] += 1

    @staticmethod
    def _keyframe(kf_id, img, H, W, X, C, D) -> PointmapKeyframe:
        t = (lambda a, shape: None if a is None else torch.from_numpy(np.ascontiguousarray(a, np.float32)).reshape(shape))
        return PointmapKeyframe(kf_id, float(img.timestamp), -1, H, W, t(X, (-1, 3)), t(C, (-1,)), img.image,
                                None, img.depth, None, t(D, (H * W, -1)))
