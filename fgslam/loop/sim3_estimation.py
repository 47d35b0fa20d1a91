"""Robust Sim(3) between two keyframe neighbourhoods from 3-D-3-D correspondences (DPV-SLAM sec. 3.3).

Input: points ``X_a`` (N, 3) triangulated around keyframe a, expressed in camera frame a, and their
matches ``X_b`` (N, 3) triangulated around keyframe b, in camera frame b; each side has its own
(monocular, arbitrary) scale. Output: the similarity ``T_ab`` (``X_a = s R X_b + t``, the standard
convention of :class:`fgslam.core.lie.Sim3`, i.e. ``T_CaCb``) estimated by RANSAC over minimal 3-point
samples with Umeyama's closed form (:func:`fgslam.core.geometry.umeyama`, with scale), refined on all inliers.
With ``with_scale=False`` (metric maps: stereo, RGB-D, where both sides are in metres) the fit is
rigid (Umeyama without scale): ``T_ab`` has ``s = 1`` exactly and a scale difference between the two
point sets shows as residuals instead of being absorbed.

Inlier test (``Sim3RansacConfig.error_metric``):

* ``"relative"`` (default): symmetric relative 3-D error
  ``e_k = max(|X_a - T_ab X_b| / |X_a|, |X_b - T_ab^-1 X_a| / |X_b|)``; dividing by the point's
  distance to its own camera makes it unit-free (each side has its own scale) and tolerant of the
  larger triangulation error of distant points.
* ``"absolute"``: ``e_k = |X_a - T_ab X_b|`` in units of frame a.

A point is an inlier when ``e_k < inlier_threshold``. A 3-point sample is degenerate (skipped) when,
on either side, its spread (largest singular value of the centred points) is below
``min_sample_spread`` times the median point range of that side (coincident points), or its second
singular value is below ``min_sample_collinearity`` times the first (collinear points).

The result is never an exception for bad geometry: too few points, all samples degenerate, or fewer
than ``min_inliers`` inliers give ``Sim3Estimate.success = False`` with a ``reason``.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field

import numpy as np
import torch

from ..core.errors import EvaluationError
from ..core.geometry import umeyama
from ..core.lie import Sim3
from .records import MINIMAL_SAMPLE, Sim3RansacConfig  # the config lives with loop closure's: torch-free (a run's config loads without torch)

logger = logging.getLogger(__name__)


@dataclass
class Sim3Estimate:
    """Outcome of :func:`estimate_sim3_ransac`.

    ``T_ab`` is the Sim(3) with ``X_a = s R X_b + t`` (float64, shape ()) or ``None`` when
    ``success`` is False. ``inlier_mask`` (N,) marks the inliers of the final model (all False
    without a solution). Quality: ``inlier_ratio`` = inliers / N and ``rms_error`` = RMS inlier
    error in the units of ``error_metric``.
    """

    success: bool
    T_ab: Sim3 | None
    inlier_mask: np.ndarray
    n_inliers: int
    inlier_ratio: float
    rms_error: float
    iterations: int  # hypotheses drawn
    n_degenerate: int  # samples skipped as degenerate
    reason: str = ""  # why there is no solution (empty on success)
    extra: dict = field(default_factory=dict)


def _as_points(name: str, X) -> np.ndarray:
    X = np.asarray(X.detach().cpu().numpy() if isinstance(X, torch.Tensor) else X, dtype=np.float64)
    if X.ndim != 2 or X.shape[1] != 3:
        raise ValueError(f"estimate_sim3_ransac: {name} must be (N, 3), got {X.shape}")
    return X


def _degenerate(P: np.ndarray, ref_range: float, cfg: Sim3RansacConfig) -> np.ndarray:
    """(M,) bool: samples ``P`` (M, k, 3) that are coincident or collinear (see module docstring)."""
    sv = np.linalg.svd(P - P.mean(axis=1, keepdims=True), compute_uv=False)  # (M, 3) descending
    coincident = sv[:, 0] <= cfg.min_sample_spread * ref_range
    collinear = sv[:, 1] <= cfg.min_sample_collinearity * sv[:, 0]
    return coincident | collinear


def sim3_errors(T_ab: Sim3, X_a: np.ndarray, X_b: np.ndarray, metric: str) -> np.ndarray:
    """Per-correspondence error (N,) of ``T_ab`` under ``metric`` (see the module docstring)."""
    M = T_ab.matrix().detach().to(torch.float64).numpy()
    sR, t = M[:3, :3], M[:3, 3]
    d_a = np.linalg.norm(X_a - (X_b @ sR.T + t), axis=1)
    if metric == "absolute":
        return d_a
    s = float(T_ab.s)
    X_b_pred = ((X_a - t) @ sR) / (s * s)  # T_ab^-1 X_a = R^T (X_a - t) / s
    d_b = np.linalg.norm(X_b - X_b_pred, axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        rel = np.maximum(d_a / np.linalg.norm(X_a, axis=1), d_b / np.linalg.norm(X_b, axis=1))
    return np.where(np.isfinite(rel), rel, np.inf)


def _fit(X_a: np.ndarray, X_b: np.ndarray, with_scale: bool) -> Sim3 | None:
    """Umeyama Sim(3) with X_a = s R X_b + t (s = 1 without ``with_scale``), or None when it is
    undetermined or not finite."""
    try:
        al = umeyama(X_b, X_a, with_scale=with_scale)
    except EvaluationError:
        return None
    if not (np.isfinite(al.R).all() and np.isfinite(al.t).all() and np.isfinite(al.s) and al.s > 0):
        return None
    return Sim3(torch.from_numpy(al.R), torch.from_numpy(al.t), torch.tensor(al.s, dtype=torch.float64))


def _needed_iterations(inlier_ratio: float, confidence: float, cap: int) -> int:
    p_good = inlier_ratio**MINIMAL_SAMPLE
    if p_good >= 1.0:
        return 1
    if p_good <= 0.0:
        return cap
    return min(cap, int(math.ceil(math.log(1.0 - confidence) / math.log(1.0 - p_good))))


def _failure(n: int, iterations: int, n_degenerate: int, reason: str, **extra) -> Sim3Estimate:
    logger.info("Sim(3) RANSAC: no solution (%s)", reason)
    return Sim3Estimate(
        success=False,
        T_ab=None,
        inlier_mask=np.zeros(n, dtype=bool),
        n_inliers=0,
        inlier_ratio=0.0,
        rms_error=float("inf"),
        iterations=iterations,
        n_degenerate=n_degenerate,
        reason=reason,
        extra=dict(extra),
    )


def estimate_sim3_ransac(X_a, X_b, config: Sim3RansacConfig | None = None, with_scale: bool = True) -> Sim3Estimate:
    """RANSAC + Umeyama Sim(3) ``T_ab`` with ``X_a ~ T_ab X_b`` from matched points (N, 3) each.

    ``with_scale=False``: rigid fit, ``T_ab.s`` is exactly 1 (both sides in the same metric units);
    minimal samples and degeneracy tests are the same (3 non-collinear points).

    ``X_a``/``X_b``: numpy arrays or torch tensors, rows are correspondences; rows with non-finite
    values are ignored (never inliers). Returns a :class:`Sim3Estimate`; ``success`` is False (with a
    ``reason``) when fewer than ``config.min_inliers`` correspondences support the best model or no
    non-degenerate sample exists. Raises ValueError only for arrays of the wrong shape.
    """
    cfg = Sim3RansacConfig() if config is None else config
    cfg.validate()
    X_a, X_b = _as_points("X_a", X_a), _as_points("X_b", X_b)
    if X_a.shape != X_b.shape:
        raise ValueError(f"estimate_sim3_ransac: X_a {X_a.shape} and X_b {X_b.shape} differ")
    n = X_a.shape[0]
    valid = np.isfinite(X_a).all(axis=1) & np.isfinite(X_b).all(axis=1)
    if cfg.error_metric == "relative":
        valid &= (np.linalg.norm(X_a, axis=1) > 0) & (np.linalg.norm(X_b, axis=1) > 0)
    idx_valid = np.flatnonzero(valid)
    if idx_valid.size < max(cfg.min_inliers, MINIMAL_SAMPLE):
        return _failure(n, 0, 0, f"{idx_valid.size} valid correspondences < min_inliers {cfg.min_inliers}")
    A, B = X_a[idx_valid], X_b[idx_valid]
    m = idx_valid.size
    range_a = float(np.median(np.linalg.norm(A - np.median(A, axis=0), axis=1)))
    range_b = float(np.median(np.linalg.norm(B - np.median(B, axis=0), axis=1)))

    rng = np.random.default_rng(cfg.seed)
    # All samples at once (3 distinct indices each), degeneracy tested in one batch.
    samples = np.stack([rng.choice(m, MINIMAL_SAMPLE, replace=False) for _ in range(cfg.max_iterations)])
    degenerate = _degenerate(A[samples], range_a, cfg) | _degenerate(B[samples], range_b, cfg)

    best_count, best_err_sum, best_mask, best_T = 0, np.inf, None, None
    needed, it, n_degenerate = cfg.max_iterations, 0, 0
    while it < needed:
        sample, is_degenerate = samples[it], degenerate[it]
        it += 1
        if is_degenerate:
            n_degenerate += 1
            continue
        T = _fit(A[sample], B[sample], with_scale)
        if T is None:
            n_degenerate += 1
            continue
        err = sim3_errors(T, A, B, cfg.error_metric)
        mask = err < cfg.inlier_threshold
        count = int(mask.sum())
        err_sum = float(err[mask].sum())
        if count > best_count or (count == best_count and count > 0 and err_sum < best_err_sum):
            best_count, best_err_sum, best_mask, best_T = count, err_sum, mask, T
            needed = _needed_iterations(count / m, cfg.confidence, cfg.max_iterations)
    if best_T is None:
        return _failure(n, it, n_degenerate, f"all {it} samples degenerate (coincident or collinear points)")
    if best_count < cfg.min_inliers:
        return _failure(
            n, it, n_degenerate, f"best model has {best_count} inliers < min_inliers {cfg.min_inliers}",
            best_inliers=best_count,
        )

    # Refinement: Umeyama on all inliers, re-classify, until the inlier set is stable.
    T, mask = best_T, best_mask
    for _ in range(cfg.refine_iterations):
        if _degenerate(A[mask][None], range_a, cfg)[0] or _degenerate(B[mask][None], range_b, cfg)[0]:
            break
        T_ref = _fit(A[mask], B[mask], with_scale)
        if T_ref is None:
            break
        mask_ref = sim3_errors(T_ref, A, B, cfg.error_metric) < cfg.inlier_threshold
        if mask_ref.sum() < mask.sum():
            break
        stable = np.array_equal(mask_ref, mask)
        T, mask = T_ref, mask_ref
        if stable:
            break
    if _degenerate(A[mask][None], range_a, cfg)[0] or _degenerate(B[mask][None], range_b, cfg)[0]:
        return _failure(n, it, n_degenerate, "inlier set is degenerate (coincident or collinear points)")
    err = sim3_errors(T, A, B, cfg.error_metric)
    count = int(mask.sum())
    if count < cfg.min_inliers:
        return _failure(n, it, n_degenerate, f"refined model has {count} inliers < min_inliers {cfg.min_inliers}")
    full_mask = np.zeros(n, dtype=bool)
    full_mask[idx_valid[mask]] = True
    return Sim3Estimate(
        success=True,
        T_ab=T,
        inlier_mask=full_mask,
        n_inliers=count,
        inlier_ratio=count / n,
        rms_error=float(np.sqrt(np.mean(err[mask] ** 2))),
        iterations=it,
        n_degenerate=n_degenerate,
    )
