"""Trajectory evaluation: association, Umeyama alignment, ATE, RPE and KITTI relative errors (numpy).

Conventions
-----------
- ``gt`` and ``est`` are :class:`~fgslam.io.trajectory.Trajectory` objects of camera-to-world
  poses ``T_WC``; the estimate lives in its own world frame ``W'`` and alignment finds the
  similarity ``S_WW' = [s R_WW' | t_WW']`` with ``t_WC_gt ~ s R_WW' t_W'C_est + t_WW'``.
- Aligned estimate poses are ``T_WC = [R_WW' R_W'C | s R_WW' t_W'C + t_WW']`` (still rigid, with
  scaled translation).
- ATE: per-pose translation error ``|t_WC_gt - t_WC_aligned|`` in metres.
- RPE (TUM definition): for a pair ``(i, j)``, ``E_ij = (Q_i^-1 Q_j)^-1 (P_i^-1 P_j)`` with ``Q``
  ground truth and ``P`` the aligned estimate; translation error ``|t(E_ij)|`` (m), rotation error
  the angle of ``R(E_ij)`` (deg). Pairs are ``(i, i + delta)`` per frame, or per distance
  ``(i, j)`` with ``j`` the first frame whose ground-truth path distance from ``i`` is at least
  ``delta`` metres. RPE is invariant to SE(3) alignment; with Sim(3) it is scale corrected.
- KITTI (devkit ``evaluate_odometry``): every 10th frame starts segments of 100, 200, ..., 800 m
  of ground-truth path; the end frame is the first one strictly beyond the length; the pose
  error ``(P_i^-1 P_j)^-1 (Q_i^-1 Q_j)`` gives translation / length and angle / length, averaged
  over all segments. Reported as t_rel in % and r_rel in deg per 100 m. Computed on the aligned
  estimate, which equals the devkit's raw numbers for ``se3``/``none``/``first-pose`` alignment.
"""

from __future__ import annotations

import bisect
import logging
from dataclasses import asdict, dataclass, field
from typing import Literal

import numpy as np

from ..core.config import MAX_FRAMES, MAX_SCALAR, MAX_TIME_OFFSET_S, check_ranges, ranged
from ..core.errors import ConfigError, EvaluationError
from ..core.geometry import Alignment, umeyama
from ..io.trajectory import Trajectory

logger = logging.getLogger(__name__)

ALIGN_METHODS = ("se3", "sim3", "none", "first-pose")
ASSOCIATION_METHODS = ("timestamp", "index")

# KITTI odometry benchmark definitions (devkit evaluate_odometry.cpp).
KITTI_SEGMENT_LENGTHS_M = (100.0, 200.0, 300.0, 400.0, 500.0, 600.0, 700.0, 800.0)
KITTI_STEP_FRAMES = 10


@dataclass
class EvalConfig:
    """Tunables of :func:`evaluate`."""

    association: Literal["timestamp", "index"] = "timestamp"  # nearest one-to-one | index (KITTI, same length)
    max_time_diff: float = ranged(0.02, ge=0, le=MAX_SCALAR)  # s, largest |t_gt - (t_est + time_offset)| accepted as a match
    time_offset: float = ranged(0.0, ge=-MAX_TIME_OFFSET_S, le=MAX_TIME_OFFSET_S)  # s, added to the estimate's timestamps before association
    align: Literal["se3", "sim3", "none", "first-pose"] = "se3"  # alignment of the estimate to the ground truth
    align_num_poses: int | None = ranged(None, ge=1, le=MAX_FRAMES)  # align on the first n associated poses only (None: all)
    rpe_delta_frames: int = ranged(1, ge=1, le=MAX_FRAMES)  # frame step of the per-frame RPE
    rpe_delta_meters: float | None = ranged(1.0, gt=0, le=MAX_SCALAR)  # path distance (m) of the per-distance RPE; None: skip
    kitti_metrics: bool = False  # also compute KITTI t_rel / r_rel over the 100..800 m segments

    def validate(self) -> None:
        """Raise ``ConfigError`` naming the first invalid field."""
        if self.association not in ASSOCIATION_METHODS:
            raise ConfigError(f"EvalConfig.association={self.association!r}: expected one of {ASSOCIATION_METHODS}")
        if self.align not in ALIGN_METHODS:
            raise ConfigError(f"EvalConfig.align={self.align!r}: expected one of {ALIGN_METHODS}")
        check_ranges(self, "EvalConfig.")


# --------------------------------------------------------------------------------------------- association


def associate_timestamps(
    t_gt: np.ndarray, t_est: np.ndarray, max_diff: float, offset: float = 0.0
) -> tuple[np.ndarray, np.ndarray]:
    """One-to-one nearest-timestamp matching.

    All pairs with ``|t_gt[i] - (t_est[j] + offset)| <= max_diff`` are candidates; they are taken
    greedily in order of increasing time difference (ties: earlier estimate, then earlier ground
    truth), skipping any pair whose ground-truth or estimate stamp is already used (as TUM's
    ``associate.py``) or that would cross an accepted pair (possible when ``max_diff`` exceeds
    the stamp spacing), so both index arrays increase together. Inputs must be sorted.

    Returns:
        ``(idx_gt, idx_est)`` int arrays of equal length, both increasing.

    Raises:
        EvaluationError: no pair within ``max_diff``.
    """
    t_gt = np.asarray(t_gt, dtype=np.float64)
    t_est_shifted = np.asarray(t_est, dtype=np.float64) + offset
    lo = np.searchsorted(t_gt, t_est_shifted - max_diff, side="left")
    hi = np.searchsorted(t_gt, t_est_shifted + max_diff, side="right")
    counts = hi - lo
    total = int(counts.sum())
    cand_est = np.repeat(np.arange(t_est_shifted.shape[0]), counts)
    cand_gt = np.arange(total) - np.repeat(np.cumsum(counts) - counts, counts) + np.repeat(lo, counts)
    diff = np.abs(t_gt[cand_gt] - t_est_shifted[cand_est])
    keep = diff <= max_diff
    cand_est, cand_gt, diff = cand_est[keep], cand_gt[keep], diff[keep]
    if cand_est.size == 0:
        raise EvaluationError(
            f"no common timestamps: no estimate stamp (offset {offset} s) is within {max_diff} s of a "
            f"ground-truth stamp (ground truth spans [{_span(t_gt)}], estimate [{_span(t_est_shifted)}])"
        )
    order = np.lexsort((cand_gt, cand_est, diff))
    used_gt = np.zeros(t_gt.shape[0], dtype=bool)
    accepted_est: list[int] = []  # sorted estimate indices of accepted pairs
    gt_of_est: dict[int, int] = {}
    for k in order:
        g, e = int(cand_gt[k]), int(cand_est[k])
        if used_gt[g] or e in gt_of_est:
            continue
        pos = bisect.bisect_left(accepted_est, e)
        if pos > 0 and gt_of_est[accepted_est[pos - 1]] > g:
            continue  # would cross the accepted pair of an earlier estimate stamp
        if pos < len(accepted_est) and gt_of_est[accepted_est[pos]] < g:
            continue  # would cross the accepted pair of a later estimate stamp
        accepted_est.insert(pos, e)
        gt_of_est[e] = g
        used_gt[g] = True
    idx_est = np.array(accepted_est, dtype=np.int64)
    idx_gt = np.array([gt_of_est[e] for e in accepted_est], dtype=np.int64)
    return idx_gt, idx_est


def _span(t: np.ndarray) -> str:
    return f"{t[0]:.6f}, {t[-1]:.6f}" if t.size else "empty"


def associate(gt: Trajectory, est: Trajectory, config: EvalConfig) -> tuple[Trajectory, Trajectory]:
    """Matched sub-trajectories ``(gt_matched, est_matched)`` of equal length, pose k matching pose k.

    ``association="index"`` (KITTI) pairs pose k with pose k and requires equal lengths;
    ``"timestamp"`` uses :func:`associate_timestamps`. The returned ``est_matched`` keeps the
    estimate's own timestamps.
    """
    if config.association == "index":
        if len(gt) != len(est):
            raise EvaluationError(
                f"index association needs trajectories of the same length: ground truth has {len(gt)} "
                f"poses, estimate {len(est)} (refusing to truncate)"
            )
        return gt, est
    idx_gt, idx_est = associate_timestamps(gt.timestamps, est.timestamps, config.max_time_diff, config.time_offset)
    logger.info("associated %d of %d estimate poses with ground truth", idx_est.size, len(est))
    return gt.subset(idx_gt), est.subset(idx_est)


# --------------------------------------------------------------------------------------------- alignment


def compute_alignment(gt: Trajectory, est: Trajectory, method: str, num_poses: int | None = None) -> Alignment:
    """Alignment of associated trajectories (same length) by ``method`` (see :data:`ALIGN_METHODS`).

    ``num_poses`` restricts se3/sim3 to the first n poses. ``first-pose`` maps the first estimate
    pose onto the first ground-truth pose (``S = T_WC_gt[0] T_W'C_est[0]^-1``, no scale).
    """
    if method == "none":
        return Alignment.identity()
    if method == "first-pose":
        T = gt.T_WC[0] @ np.linalg.inv(est.T_WC[0])
        return Alignment(T[:3, :3], T[:3, 3], 1.0)
    if method not in ("se3", "sim3"):
        raise EvaluationError(f"unknown alignment {method!r}: expected one of {ALIGN_METHODS}")
    n = len(gt) if num_poses is None else min(num_poses, len(gt))
    return umeyama(est.t_WC[:n], gt.t_WC[:n], with_scale=method == "sim3")


# --------------------------------------------------------------------------------------------- metrics


@dataclass(frozen=True)
class ErrorStats:
    """Summary statistics of a set of non-negative errors (units of the errors)."""

    rmse: float
    mean: float
    median: float
    std: float
    min: float
    max: float
    n: int

    @staticmethod
    def from_errors(errors: np.ndarray) -> ErrorStats | None:
        """Statistics of ``errors`` ``(K,)``; ``None`` when ``K == 0``."""
        e = np.asarray(errors, dtype=np.float64)
        if e.size == 0:
            return None
        return ErrorStats(
            rmse=float(np.sqrt(np.mean(e**2))),
            mean=float(np.mean(e)),
            median=float(np.median(e)),
            std=float(np.std(e)),
            min=float(np.min(e)),
            max=float(np.max(e)),
            n=int(e.size),
        )


def rotation_angle(R: np.ndarray) -> np.ndarray:
    """Rotation angles in radians ``(...)`` of ``(..., 3, 3)`` rotations, accurate also near 0 and pi."""
    sin_part = 0.5 * np.linalg.norm(
        np.stack([R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]], axis=-1),
        axis=-1,
    )
    cos_part = 0.5 * (np.trace(R, axis1=-2, axis2=-1) - 1.0)
    return np.arctan2(sin_part, cos_part)


def _inverse_rigid(T: np.ndarray) -> np.ndarray:
    R_T = np.swapaxes(T[..., :3, :3], -1, -2)
    T_inv = np.array(T, copy=True)
    T_inv[..., :3, :3] = R_T
    T_inv[..., :3, 3] = -(R_T @ T[..., :3, 3, None])[..., 0]
    return T_inv


def relative_pose_errors(
    T_WC_gt: np.ndarray, T_WC_est: np.ndarray, i: np.ndarray, j: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Translation (m) and rotation (rad) errors ``(K,)`` of the pairs ``(i[k], j[k])``.

    ``E = (Q_i^-1 Q_j)^-1 (P_i^-1 P_j)``, Q ground truth, P estimate (poses ``(N, 4, 4)``).
    """
    dQ = _inverse_rigid(T_WC_gt[i]) @ T_WC_gt[j]
    dP = _inverse_rigid(T_WC_est[i]) @ T_WC_est[j]
    E = _inverse_rigid(dQ) @ dP
    return np.linalg.norm(E[:, :3, 3], axis=1), rotation_angle(E[:, :3, :3])


def cumulative_distances(t_W: np.ndarray) -> np.ndarray:
    """Path distance ``(N,)`` from the first position to each position ``t_W`` ``(N, 3)``."""
    steps = np.linalg.norm(np.diff(t_W, axis=0), axis=1)
    return np.concatenate([[0.0], np.cumsum(steps)])


def frame_pairs(n: int, delta: int) -> tuple[np.ndarray, np.ndarray]:
    """All pairs ``(i, i + delta)`` within ``n`` frames."""
    i = np.arange(max(n - delta, 0))
    return i, i + delta


def distance_pairs(
    dist: np.ndarray, delta_m: float, starts: np.ndarray | None = None, strictly_beyond: bool = False
) -> tuple[np.ndarray, np.ndarray]:
    """Pairs ``(i, j)``: for each start frame i (default: every frame), the first frame j with
    ``dist[j] - dist[i] >= delta_m`` (``>`` when ``strictly_beyond``, as the KITTI devkit);
    start frames without such a j are dropped. ``dist`` is a cumulative path distance ``(N,)``."""
    i = np.arange(dist.shape[0]) if starts is None else np.asarray(starts)
    j = np.searchsorted(dist, dist[i] + delta_m, side="right" if strictly_beyond else "left")
    valid = j < dist.shape[0]
    return i[valid], j[valid]


@dataclass(frozen=True)
class KittiErrors:
    """KITTI relative errors averaged over all 100..800 m segments."""

    t_rel_percent: float  # mean translation error / segment length, %
    r_rel_deg_per_100m: float  # mean rotation error / segment length, deg per 100 m
    n_segments: int


def kitti_relative_errors(T_WC_gt: np.ndarray, T_WC_est: np.ndarray) -> KittiErrors | None:
    """KITTI devkit t_rel / r_rel of matched pose arrays ``(N, 4, 4)``; ``None`` if no segment fits.

    Start frames ``0, 10, 20, ...``; for each length L in :data:`KITTI_SEGMENT_LENGTHS_M` the end
    frame is the first with ground-truth path distance strictly greater than ``dist[start] + L``.
    """
    dist = cumulative_distances(T_WC_gt[:, :3, 3])
    starts = np.arange(0, dist.shape[0], KITTI_STEP_FRAMES)
    t_rel, r_rel = [], []
    for length in KITTI_SEGMENT_LENGTHS_M:
        i, j = distance_pairs(dist, length, starts, strictly_beyond=True)
        if i.size == 0:
            continue
        t_err, r_err = relative_pose_errors(T_WC_gt, T_WC_est, i, j)
        t_rel.append(t_err / length)
        r_rel.append(r_err / length)
    if not t_rel:
        return None
    t_all, r_all = np.concatenate(t_rel), np.concatenate(r_rel)
    return KittiErrors(
        t_rel_percent=float(100.0 * t_all.mean()),
        r_rel_deg_per_100m=float(np.degrees(r_all.mean()) * 100.0),
        n_segments=int(t_all.size),
    )


# --------------------------------------------------------------------------------------------- evaluate


@dataclass(frozen=True)
class RPEResult:
    """Relative pose error for one pair definition: translation (m) and rotation (deg) statistics."""

    delta: float
    unit: str  # "frames" or "m"
    trans: ErrorStats
    rot_deg: ErrorStats


@dataclass(frozen=True)
class EvalResult:
    """Everything :func:`evaluate` computes; ``to_dict()`` is JSON-serialisable."""

    n_gt: int
    n_est: int
    n_matched: int
    align: str
    alignment: Alignment
    ate: ErrorStats  # translation APE after alignment, metres
    rpe_frames: RPEResult | None
    rpe_meters: RPEResult | None
    kitti: KittiErrors | None
    gt_path_length_m: float
    aligned_est: Trajectory = field(repr=False)  # matched estimate after alignment (for plots)
    matched_gt: Trajectory = field(repr=False)

    def to_dict(self) -> dict:
        return {
            "n_gt": self.n_gt,
            "n_est": self.n_est,
            "n_matched": self.n_matched,
            "align": self.align,
            "scale": self.alignment.s,
            "alignment_matrix": self.alignment.matrix().tolist(),
            "gt_path_length_m": self.gt_path_length_m,
            "ate": asdict(self.ate),
            "rpe_frames": None if self.rpe_frames is None else asdict(self.rpe_frames),
            "rpe_meters": None if self.rpe_meters is None else asdict(self.rpe_meters),
            "kitti": None if self.kitti is None else asdict(self.kitti),
        }


def _rpe(gt: Trajectory, est_T: np.ndarray, i: np.ndarray, j: np.ndarray, delta: float, unit: str) -> RPEResult | None:
    if i.size == 0:
        logger.info("RPE with delta %s %s: no pair of poses that far apart", delta, unit)
        return None
    t_err, r_err = relative_pose_errors(gt.T_WC, est_T, i, j)
    return RPEResult(delta, unit, ErrorStats.from_errors(t_err), ErrorStats.from_errors(np.degrees(r_err)))


def evaluate(gt: Trajectory, est: Trajectory, config: EvalConfig | None = None) -> EvalResult:
    """Associate, align and compute ATE, RPE (per frame and per distance) and optionally KITTI errors.

    Raises ``EvaluationError`` when the trajectories cannot be associated or aligned.
    """
    config = EvalConfig() if config is None else config
    config.validate()
    if len(gt) == 0 or len(est) == 0:
        raise EvaluationError(
            f"cannot evaluate an empty trajectory (ground truth {len(gt)}, estimate {len(est)} poses)"
        )
    gt_m, est_m = associate(gt, est, config)
    alignment = compute_alignment(gt_m, est_m, config.align, config.align_num_poses)
    est_T = alignment.apply(est_m.T_WC)
    ate_err = np.linalg.norm(gt_m.t_WC - est_T[:, :3, 3], axis=1)
    n = len(gt_m)
    dist = cumulative_distances(gt_m.t_WC)
    rpe_frames = _rpe(gt_m, est_T, *frame_pairs(n, config.rpe_delta_frames), config.rpe_delta_frames, "frames")
    rpe_meters = None
    if config.rpe_delta_meters is not None:
        rpe_meters = _rpe(gt_m, est_T, *distance_pairs(dist, config.rpe_delta_meters), config.rpe_delta_meters, "m")
    kitti = kitti_relative_errors(gt_m.T_WC, est_T) if config.kitti_metrics else None
    if config.kitti_metrics and kitti is None:
        logger.info("KITTI metrics: ground-truth path (%.1f m) shorter than the shortest segment", dist[-1])
    return EvalResult(
        n_gt=len(gt),
        n_est=len(est),
        n_matched=n,
        align=config.align,
        alignment=alignment,
        ate=ErrorStats.from_errors(ate_err),
        rpe_frames=rpe_frames,
        rpe_meters=rpe_meters,
        kitti=kitti,
        gt_path_length_m=float(dist[-1]),
        aligned_est=Trajectory(est_m.timestamps, est_T),
        matched_gt=gt_m,
    )
