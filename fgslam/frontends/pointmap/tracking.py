"""Frame-to-keyframe tracking of the pointmap frontend (MASt3R-SLAM section 3.3), and pointmap fusion (eq. 9).

:func:`track_pose` estimates the relative pose ``T_CkCf`` of a frame f to its keyframe k from N matches
(the frame's own points ``X_f^f`` at the query pixels, the keyframe's canonical points ``X_k^k`` at the
matched pixels). The matches are one edge of the backend's pose-only
:class:`~fgslam.factors.pointmap_block.PointmapBlock` between the keyframe (held at the identity) and
the frame, so the residuals, their whitening by ``sqrt(q) / sigma`` (eq. 6) and the robust kernel
(Huber) on each row group are the block's, one implementation each:

- ``ray`` mode: the unit-ray rows and the weak distance row (eqs. 7-8; the distance row keeps a pure
  rotation well posed); ``calibrated`` mode (section 3.7): pixel rows and the log-depth row;
- the pose is solved by the one Levenberg-Marquardt loop (:meth:`fgslam.backend.Backend.optimize_pose`'s
  problem, :mod:`fgslam.backend.motion_only`) with Marquardt damping; each linearisation takes the
  kernel's weights at the current residuals, which is the iteratively reweighted least squares of the
  paper;
- Sim(3) (7 dof) or, for metric pointmaps, SE(3) (the scale component held exactly).

:func:`fuse_pointmap` is eq. 9: the keyframe's canonical pointmap becomes the confidence-weighted
running average of its own points and the tracked frame's points moved into it (``T_CkCf X_f^f``) at the
matched pixels (several queries matched to one pixel all count).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
import torch

from ...backend.keys import pose_key
from ...backend.motion_only import optimize_pose
from ...backend.solver import LMSettings
from ...factors.pointmap_block import PointmapBlock, PointmapBlockConfig, PointmapEdge
from ...factors.schur import POSE_DIM
from ...core.lie import Sim3
from .config import PointmapTrackingConfig

logger = logging.getLogger(__name__)

__all__ = ["TRACK_KEYS", "TrackResult", "fuse_pointmap", "track_pose"]

#: the keyframe's and the frame's keys in the two-key tracking problem
_KEY_K, _KEY_F = pose_key(0), pose_key(1)
#: ... public: other blocks of the tracking problem (RGB-D depth alignment) join these two keys
TRACK_KEYS = (_KEY_K, _KEY_F)
#: SE(3) tracking: the log-scale component of the frame's tangent held exactly
_FIXED_SCALE = np.array([0.0] * (POSE_DIM - 1) + [np.inf])


@dataclass
class TrackResult:
    """Outcome of :func:`track_pose`: the relative pose, per-match inlier flags (the whitened norm of the
    ray / pixel rows at most ``tracking.inlier_threshold``), the cost ``sum rho`` before and after, the
    iterations run and whether the loop converged."""

    T_CkCf: Sim3
    inlier: torch.Tensor
    initial_cost: float
    final_cost: float
    iterations: int
    converged: bool

    @property
    def num_inliers(self) -> int:
        return int(self.inlier.sum())


def _settings(config: PointmapTrackingConfig) -> LMSettings:
    return LMSettings(max_iterations=config.iterations, lambda_initial=config.damping,
                      lambda_factor=config.lambda_factor, lambda_max=config.lambda_max,
                      step_tolerance=config.step_tolerance, damping="marquardt")


def track_pose(T_init: Sim3, X_f_in_f: torch.Tensor, X_k_in_k: torch.Tensor, weight: torch.Tensor,
               block: PointmapBlockConfig, config: PointmapTrackingConfig, fixed_scale: bool,
               uv_k: torch.Tensor | None = None, K: torch.Tensor | None = None, extra_blocks=()) -> TrackResult:
    """``T_CkCf`` from N matches (module docstring). ``X_f_in_f`` / ``X_k_in_k`` ``(N, 3)``, ``weight``
    ``(N,)`` match confidences q, ``uv_k`` ``(N, 2)`` matched keyframe pixels and ``K`` ``(4,)`` for the
    calibrated mode; all float64. ``fixed_scale``: SE(3) (the scale of ``T_init`` is kept).
    ``extra_blocks``: other blocks over :data:`TRACK_KEYS` solved with the matches (RGB-D depth alignment)."""
    import gtsam  # deferred: gtsam

    edge = PointmapEdge(_KEY_K, _KEY_F, X_k_in_k, X_f_in_f, weight, uv_k if block.mode == "calibrated" else None)
    pm = PointmapBlock([edge], block, None if K is None else K.numpy())
    values = gtsam.Values()
    values.insert(_KEY_K, gtsam.Similarity3())
    values.insert(_KEY_F, T_init.to_gtsam())
    result = optimize_pose([pm, *extra_blocks], values, _KEY_F, _settings(config), _FIXED_SCALE if fixed_scale else None)
    report = result.report
    T = Sim3.from_gtsam(result.values.atSimilarity3(_KEY_F))
    (inlier,) = pm.inliers(result.values, config.inlier_threshold)
    return TrackResult(T, inlier, report.initial_cost, report.final_cost, report.iterations, report.converged)


def fuse_pointmap(X_canon: torch.Tensor, C_canon: torch.Tensor, index: torch.Tensor, X_new: torch.Tensor,
                  C_new: torch.Tensor, max_confidence: float) -> None:
    """Eq. 9 in place: ``X <- (C X + sum c x) / (C + sum c)``, ``C <- min(C + sum c, max_confidence)`` at the
    flat pixel ``index (M,)`` of ``X_canon (H W, 3)`` / ``C_canon (H W,)`` (float32 views of the keyframe's
    canonical pointmap), with the new points ``X_new (M, 3)`` (in the keyframe's frame) and confidences
    ``C_new (M,)``; non-finite new points are skipped."""
    ok = torch.isfinite(X_new).all(-1) & torch.isfinite(C_new) & (C_new > 0)
    index, X_new, C_new = index[ok], X_new[ok].to(X_canon.dtype), C_new[ok].to(C_canon.dtype)
    if index.numel() == 0:
        return
    num = torch.zeros_like(X_canon).index_add_(0, index, C_new[:, None] * X_new)
    den = torch.zeros_like(C_canon).index_add_(0, index, C_new)
    hit = den > 0
    total = C_canon[hit] + den[hit]
    X_canon[hit] = (C_canon[hit, None] * X_canon[hit] + num[hit]) / total[:, None]
    C_canon[hit] = total.clamp(max=max_confidence)
