"""A fourth frontend family built only from the protocol (docs/architecture.md, "Adding a fourth frontend").

:class:`ToyFrontend` measures nothing real: its odometry is each frame's ground-truth motion
(``frame.T_WC_gt``, which synthetic and most real datasets carry) with a constant yaw error per
frame, so that its trajectory drifts like a visual odometry's. Everything else is what a real
family does: it keyframes every frame on the run's backend, emits one odometry factor per
keyframe and asks the backend to optimise its window, hands its keyframe images to the loop port,
and implements the contributor contract so that loop corrections and plugin corrections reach it.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import gtsam
import numpy as np

from fgslam.backend.keys import pose_key
from fgslam.core.config import ranged
from fgslam.core.errors import ConfigError
from fgslam.frontends.base import BackendFrontend, FrameStatus
from fgslam.frontends.records import KeyframePose
from fgslam.core.lie import gtsam_sim3
from fgslam.contracts.contributor import KeyframeImage, PoseCorrection


@dataclass
class ToyConfig:
    """The toy family's section."""

    yaw_drift: float = ranged(0.003, ge=0, le=0.1)  # rad of heading error per frame
    window: int = ranged(5, ge=2, le=100)  # keyframes the backend optimises after each frame
    iterations: int = ranged(3, ge=1, le=50)  # backend iterations per frame
    sigmas: tuple = (0.01, 0.01, 0.01, 0.02, 0.02, 0.02, 1e-3)  # odometry factor: rotation (rad), translation (m), log scale

    def validate(self) -> None:
        if len(self.sigmas) != 7 or min(self.sigmas) <= 0:
            raise ConfigError("toy.sigmas: seven positive sigmas (rotation, translation, log scale)")


class ToyFrontend(BackendFrontend):
    """Dead-reckoned ground truth with a heading drift (module docstring); RGB-D, every frame a keyframe."""

    name = "toy"

    def __init__(self, config: ToyConfig | None = None, calibration=None, sensor_mode: str = "rgbd", backend=None):
        self._attach(config or ToyConfig(), sensor_mode, backend)
        self.calibration = calibration
        self._times = {"odometry": 0.0}
        self._images: dict[int, KeyframeImage] = {}
        self._T_WC_gt_prev: Optional[np.ndarray] = None
        c, s = np.cos(self.config.yaw_drift), np.sin(self.config.yaw_drift)
        self._T_drift = np.array([[c, 0, s, 0], [0, 1, 0, 0], [-s, 0, c, 0], [0, 0, 0, 1.0]])  # about the camera's y (down)
        self._noise = gtsam.noiseModel.Diagonal.Sigmas(np.asarray(self.config.sigmas, dtype=np.float64))

    # ------------------------------------------------------------------ the per-frame skeleton's hooks
    def _set_calibration(self, calibration) -> None:
        self.calibration = calibration

    def _check_frame(self, frame) -> None:
        if frame.T_WC_gt is None or frame.depth is None:
            raise ConfigError("the toy frontend needs RGB-D frames with a ground-truth pose")

    def _measure_frame(self, fid: int, frame) -> FrameStatus:
        T_WC_gt = np.asarray(frame.T_WC_gt, dtype=np.float64)
        if fid == 0:
            T_WC = T_WC_gt
            self.backend.add_keyframe(fid, T_WC, float(frame.timestamp))
        else:
            T_CpCf = np.linalg.inv(self._T_WC_gt_prev) @ T_WC_gt @ self._T_drift  # measured motion, drifting
            T_WC = self.backend.pose_matrix(fid - 1) @ T_CpCf
            self.backend.add_keyframe(fid, T_WC, float(frame.timestamp))
            self.backend.add_factor(gtsam.BetweenFactorSimilarity3(pose_key(fid - 1), pose_key(fid),
                                                                   gtsam_sim3(T_CpCf), self._noise),
                                    owner=self.name)
            self.backend.optimize_window(self.backend.keyframe_ids[-self.config.window:], self.config.iterations)
        self._T_WC_gt_prev = T_WC_gt
        self._records[fid] = KeyframePose()
        self._images[fid] = KeyframeImage(frame.image, np.asarray(self.calibration.K, dtype=np.float64),
                                          float(frame.timestamp), frame.depth)
        if fid > 0:  # the previous keyframe's pose is final: to loop closure
            self.loops.add_keyframe(fid - 1, [fid - 2] if fid > 1 else [])
            self.loops.update_poses({k: self.backend.pose_matrix(k) for k in self.backend.keyframe_ids})
        return FrameStatus(frame.index, frame.timestamp, self.backend.pose_matrix(fid), "tracked", is_keyframe=True,
                           num_valid=1)

    def _recover(self, fid: int, frame, exc: BaseException) -> FrameStatus:
        return FrameStatus(frame.index, frame.timestamp, None, "motion_model", events=[f"failed: {exc}"])

    # ------------------------------------------------------------------ what the system asks
    @property
    def map_started(self) -> bool:
        return self._fid > 0

    def num_keyframes(self) -> int:
        return len(self.backend.keyframe_ids)

    def finish(self) -> None:
        if self._fid:
            self.loops.add_keyframe(self._fid - 1, [self._fid - 2] if self._fid > 1 else [])

    def _keyframe_T_WC(self, fid: int) -> np.ndarray:
        return self.backend.pose_matrix(fid)

    # ------------------------------------------------------------------ contributor contract
    def keyframe_image(self, kf_id: int) -> Optional[KeyframeImage]:
        return self._images.get(kf_id)

    def keyframe_pose(self, kf_id: int) -> Optional[np.ndarray]:
        return self.backend.pose_matrix(kf_id) if self.backend.has_keyframe(kf_id) else None

    def apply_correction(self, correction: PoseCorrection) -> None:
        for kf_id in self.backend.keyframe_ids:
            self.backend.set_pose(kf_id, correction.apply_pose(kf_id, self.backend.pose_matrix(kf_id))[0])

    def long_range_edges(self, query_kf_id: int, candidate_kf_id: int) -> Optional[dict]:
        return None
