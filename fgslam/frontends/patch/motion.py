"""The patch frontend's motion model (:class:`MotionModel`): DPVO's damped constant velocity
``T_WCn = T_WCn-1 Exp(damping Log(V))`` with ``V = T_WCn-2^-1 T_WCn-1`` per frame, an optional
motion prior (the IMU service's prediction) and the reference of the implausible-motion check."""

from __future__ import annotations

import numpy as np

from ...contracts.contributor import PoseCorrection
from ..base import MotionPrior
from ..records import per_frame_motion
from ..records import rigid as _rigid
from ..records import sim3_power as _sim3_power
from .state import PatchState


#: sensor modes whose depths are metric in each camera's own units (their keyframes' scale is 1)
METRIC_SENSOR_MODES = ("stereo", "rgbd")


class MotionModel:
    """The motion of the last posed frame (``last_fid``) on the shared :class:`~.state.PatchState`.

    Attributes:
        velocity: per-frame motion (Sim(3) 4x4) of the constant-velocity model.
        last_fid: the last frame with a pose (None before the first / after a re-initialisation).
        reference: per-frame motion that a frame rejected as implausible motion contradicted, held as
            the reference of the motion check until a frame is tracked again, though stationary
            frames after that frame restart the motion model from rest (None: ``velocity`` is the reference).
        prior: optional pose prediction at a timestamp (4x4 ``T_WC`` or None), set by the run's IMU
            service (fgslam/services/imu.py): the motion prior of tracking, and the pose of a frame
            whose visual tracking fails (pose_source ``imu``: bridged, not a failure).
    """

    def __init__(self, state: PatchState):
        self.state = state
        self.velocity = np.eye(4)
        self.last_fid: int | None = None
        self.reference: np.ndarray | None = None
        self.prior: MotionPrior | None = None

    def predict(self, timestamp: float | None = None, velocity: np.ndarray | None = None,
                damping: float | None = None) -> np.ndarray:
        """The motion prior's pose at ``timestamp`` when it gives one, else the damped constant-velocity
        prediction ``T_WC`` from the last posed frame (per-frame motion ``velocity``, None: the motion
        model's; ``damping``, None: ``tracking.motion_damping``)."""
        if self.prior is not None and timestamp is not None:
            T_WC_prior = self.prior(float(timestamp))
            if T_WC_prior is not None:
                return T_WC_prior
        T_WC_last = self.state.pose_of(self.last_fid)
        damping = self.state.config.tracking.motion_damping if damping is None else damping
        T_WC = T_WC_last @ _sim3_power(self.velocity if velocity is None else velocity, damping)
        # a metric sensor (stereo baseline, RGB-D depth) measures its patches' depths in metric camera
        # units, so a keyframe's Sim(3) scale is 1: the new frame enters the BA at scale 1, where the
        # scale prior holds it. Extrapolating the last frames' scale change (the velocity's) instead
        # fed every BA's small scale step into the next frame's prior: the stereo kitti00-drive grew
        # its scale by 1.3x in 300 frames with every stereo row fitting (docs/architecture.md section 4).
        return _rigid(T_WC) if self.state.sensor_mode in METRIC_SENSOR_MODES else T_WC

    def update(self, fid: int) -> None:
        """Frame ``fid`` is the newest posed frame: the velocity from the last one's pose to its pose."""
        if self.last_fid is not None:
            T_WC_prev, T_WC_new = self.state.pose_of(self.last_fid), self.state.pose_of(fid)
            if T_WC_prev is not None and T_WC_new is not None:
                self.velocity = per_frame_motion(T_WC_prev, T_WC_new, fid - self.last_fid)
        self.last_fid = fid

    def rest(self, fid: int) -> None:
        """Stationary frame ``fid``: the motion model restarts from rest there."""
        self.velocity = np.eye(4)
        self.last_fid = fid

    def fold(self, correction: PoseCorrection) -> None:
        """A loop correction that folds a scale: the velocity (and the held reference) in the folded
        units of the last posed frame."""
        if self.last_fid is not None and correction.fold_scale:
            update = correction.update_for(self.last_fid)[1]
            self.velocity = PoseCorrection.fold_relative(self.velocity, update)
            if self.reference is not None:
                self.reference = PoseCorrection.fold_relative(self.reference, update)
