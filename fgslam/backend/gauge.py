"""The backend's gauge factors (docs/architecture.md section 4, :class:`~fgslam.backend.config.GaugeConfig`).

A 7-dof prior on the anchor keyframe and a range constraint between the scale pair (monocular world
scale), both at the poses they had when :meth:`Gauge.set` chose them (default: the oldest keyframe
and the oldest two, when they became so), and with ``hold_scale`` a log-scale prior on every free
keyframe at its scale when the optimisation starts (inverse-depth frontends, where a keyframe's
scale is a pure gauge).
"""

from __future__ import annotations

from typing import Iterable

import numpy as np

from ..core.errors import OptimizationError
from ..factors.range import camera_centre, range_factor
from ..factors.sim3 import SIM3_DOF
from .config import GaugeConfig
from .keys import pose_key
from .store import GraphStore

LOG_SCALE_ROW = SIM3_DOF - 1  # lambda, the last component of the tangent [w, u, lambda]


class Gauge:
    """The anchor and scale pair of one backend, and the gauge factors they carry."""

    def __init__(self, config: GaugeConfig, store: GraphStore):
        self.config = config
        self.store = store
        self._explicit = False  # chosen by set(); else the default (oldest keyframe, oldest two)
        self._anchor: tuple[int, object] | None = None  # (kf, prior pose)
        self._range: tuple[int, int, float] | None = None  # (kf_a, kf_b, distance)
        store.on_keyframe(self._keyframe_added)
        store.on_keyframe_removed(self._keyframe_removed)

    def set(self, anchor: int | None = None, scale_pair: tuple[int, int] | None = None) -> None:
        """Choose the keyframes that carry the configured gauge factors, at their current poses:
        ``anchor`` the 7-dof prior (None: none), ``scale_pair`` the world-scale range (None: none).
        Until called (or after a chosen keyframe is removed) the gauge is the default one: the oldest
        keyframe and the oldest two, at their poses when they became so."""
        self._explicit = True
        self._anchor = None
        self._range = None
        if anchor is not None:
            self.store.check_keyframe(anchor)
            self._anchor = (int(anchor), self.store.pose(anchor))
        if scale_pair is not None:
            self._range = self._make_range(*scale_pair)

    def _make_range(self, kf_a: int, kf_b: int) -> tuple[int, int, float]:
        self.store.check_keyframe(kf_a)
        self.store.check_keyframe(kf_b)
        distance = self._distance(kf_a, kf_b)
        if not distance > 0.0:
            raise OptimizationError(f"world-scale range gauge: keyframes {kf_a} and {kf_b} have the same centre")
        return int(kf_a), int(kf_b), distance

    def _distance(self, kf_a: int, kf_b: int) -> float:
        """Distance between the camera centres of keyframes ``kf_a`` and ``kf_b`` (current poses)."""
        pose = self.store.pose
        return float(np.linalg.norm(camera_centre(pose(kf_b)) - camera_centre(pose(kf_a))))

    def _keyframe_added(self, kf_id: int, timestamp: float, key: int) -> None:
        self._default()

    def _keyframe_removed(self, kf_id: int) -> None:
        if self._anchor is not None and self._anchor[0] == kf_id:
            self._anchor = None
            self._explicit = False  # the chosen anchor is gone: back to the default gauge
        if self._range is not None and kf_id in self._range[:2]:
            self._range = None
            self._explicit = False
        self._default()

    def _default(self) -> None:
        if self._explicit:
            return
        kfs = self.store.keyframe_ids
        if kfs and self._anchor is None:
            self._anchor = (kfs[0], self.store.pose(kfs[0]))
        if len(kfs) >= 2 and self._range is None:
            distance = self._distance(kfs[0], kfs[1])
            if distance > 0.0:  # else no range yet (retried at the next keyframe)
                self._range = (kfs[0], kfs[1], distance)

    def factors(self, free_kfs: Iterable[int]) -> list:
        """The gauge factors of an optimisation whose free keyframes are ``free_kfs``."""
        import gtsam  # deferred: gtsam

        gauge = self.config
        out = []
        if gauge.fix_anchor and self._anchor is not None:
            kf, prior = self._anchor
            noise = gtsam.noiseModel.Isotropic.Sigma(SIM3_DOF, gauge.anchor_sigma)
            out.append(gtsam.PriorFactorSimilarity3(pose_key(kf), prior, noise))
        if gauge.world_scale_range and self._range is not None:
            a, b, distance = self._range
            out.append(range_factor(pose_key(a), pose_key(b), distance, gauge.range_sigma * distance))
        if gauge.hold_scale:
            precisions = np.zeros(SIM3_DOF)
            precisions[LOG_SCALE_ROW] = 1.0 / gauge.scale_sigma**2
            noise = gtsam.noiseModel.Diagonal.Precisions(precisions)
            # The prior's rotation/translation rows have zero precision, so it constrains only
            # lambda = log(s / s_held) of Logmap(prior^-1 T) (scale composes independently).
            for kf in free_kfs:
                held = gtsam.Similarity3(gtsam.Rot3(), np.zeros(3), float(self.store.pose(kf).scale()))
                out.append(gtsam.PriorFactorSimilarity3(pose_key(kf), held, noise))
        return out
