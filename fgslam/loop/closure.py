"""Classical loop closure (DPV-SLAM sec. 3.3) and relocalisation, frontend-agnostic.

Pipeline per keyframe (in a worker thread, or synchronously): ORB features + BoW vector
(:class:`fgslam.loop.bow.PlaceRecognizer`), DBoW2 loop detection (gap, islands, temporal
consistency), geometric verification of the best candidates, Sim(3) pose graph over every keyframe
(:func:`fgslam.loop.pose_graph.optimize_sim3_pose_graph`: smoothness from the current relative
Sim(3)s + every verified loop so far, plausibility gate, pairwise consistency, chi-square test), and a
:class:`PoseCorrection` handed to the frontend through :meth:`LoopCloser.poll`.

Pose-graph throttle: on a return, consecutive keyframes each verify a loop. Loops form clusters (a
loop whose query comes more than ``LoopClosureConfig.cluster_gap`` described keyframes after the
previous loop's query starts a new one). While the current cluster has no accepted loop, each new
loop is solved at once (the first correction of a return is not delayed); afterwards the loops that
keep arriving are solved at most every ``solve_every`` described keyframes, and at the latest when the
cluster ends or at :meth:`LoopCloser.close` (then :meth:`LoopCloser.poll` returns the final
correction). Every solve uses every verified loop so far, so no loop is lost.

Metric mode (``LoopCloser(metric=True)``: stereo, RGB-D): the map's scale is metric and every keyframe
pose keeps its Sim(3) scale (1), since depth priors and stereo edges are in metres. Verification then
fits a rigid ``T_CqCc`` (``s = 1``, :func:`~fgslam.loop.sim3_estimation.estimate_sim3_ransac` with
``with_scale=False``), the pose graph holds every keyframe's scale (``hold_scale``: an SE(3) pose
graph), and each :class:`PoseCorrection` is SE(3): all ``scale`` are 1 and ``fold_scale`` is False
(nothing to fold). Relocalisation returns the metric PnP pose in both modes.

Conventions: poses are camera-to-world Sim(3) ``T_WC`` (``X_W = s R X_C + t``, 4x4
``[[s R, t], [0, 1]]`` or :class:`fgslam.lie.Sim3`); camera-frame points are in the units of their
keyframe's pose (``X_C = T_WC^-1 X_W``); intrinsics ``K = (fx, fy, cx, cy)`` of an undistorted
pinhole image; keyframe ids are the caller's integers, increasing in insertion order. In metric mode
every keyframe shares one scale (1), so both keyframes of a loop are in the same (metric) units.

Geometric verification of a pair (query q, candidate c):

1. ORB matches q <-> c: Hamming nearest neighbour, Lowe ratio test, mutual check, max distance;
2. triangulation in each keyframe's neighbourhood: q's features are matched to a neighbour n's
   (descriptor + epipolar constraint from the current relative pose ``T_CqCn``) and triangulated by
   the midpoint method in camera q (positive depths, minimum parallax, reprojection error bound), the
   same for c; neighbours are tried in order until enough points are triangulated;
3. ``X_q = T_CqCc X_c`` by RANSAC + Umeyama (:func:`fgslam.loop.sim3_estimation.estimate_sim3_ransac`;
   rigid in metric mode) on the matches with a 3-D point on both sides; the loop measurement is
   ``T_CqCc``.

Too few matches, too few triangulated points (no texture, too little parallax) and degenerate or
unsupported Sim(3)s reject the pair with a logged reason (:class:`Verification`).

Corrections: a :class:`PoseCorrection` holds, for every keyframe of the pose-graph snapshot, the
world-frame update ``U_k = T_WC_new_k T_WC_old_k^-1`` (Sim(3)). The frontend applies it at a safe
point as ``T_WC <- U_k T_WC`` to its *current* pose of keyframe k (local refinements since the
snapshot are kept) and, for keyframes added after the snapshot, with the update of the nearest
corrected keyframe id (:meth:`PoseCorrection.update_for`). With ``fold_scale`` (frontends whose pose
scale is a fixed gauge: patch, dense) the scale part ``s_k`` of ``U_k`` is folded into the depths
(DPV-SLAM: ``d <- d / s_k``) and the pose keeps its old scale (:meth:`PoseCorrection.apply`); the
closer then assumes that every correction handed out by :meth:`LoopCloser.poll` is applied (it
rescales its stored loop measurements and applies the correction to its own pose table).

Reproducible: the worker never reads the caller's live state. Every piece of work (a keyframe, a
re-solve, the final solve, and the folding of the loop measurements after a correction was applied)
is a job that carries the caller's pose table and the count of corrections applied when it was
handed over, and the worker runs the jobs in that order. Each :meth:`LoopCloser.poll` is a tick; a
job handed over at tick t is taken at tick ``t + correction_delay_frames`` (waiting for it there),
its correction applied unless a later due job supersedes it. A correction solved before another one
was applied is stale (it would correct twice): it is solved again on the current poses, as a new job.
So the corrections, and the ticks at which they arrive, depend on the caller's calls alone, and
``run_in_thread`` false (everything at once in the caller's thread) gives the same results.
"""

from __future__ import annotations

import logging
import math
import queue
import threading
from collections import deque
import time
from dataclasses import dataclass, field
from typing import Literal, Sequence

import numpy as np
import torch

from ..config import MAX_COUNT, MAX_FRAMES, MAX_ITERATIONS, MAX_KEYFRAMES, MAX_SCALAR, check_ranges, ranged
from ..errors import ConfigError, DataError, OptimizationError
from ..lie import Sim3, sim3_matrix_parts
from .bow import BowConfig, KeyframeFeatures, PlaceRecognizer
from .pose_graph import PoseGraphConfig, optimize_sim3_pose_graph
from .sim3_estimation import Sim3RansacConfig, estimate_sim3_ransac

logger = logging.getLogger(__name__)

LOOP_MODES = ("off", "proximity", "classical", "both")
_IDLE_POLL_S = 0.005  # wait_idle's polling interval (seconds)
_NO_MATCH = np.iinfo(np.int32).max  # Hamming distance of a missing (masked-out) neighbour


# ----------------------------------------------------------------------------------- configs

@dataclass
class VerificationConfig:
    """Geometric verification of a retrieved keyframe pair."""

    max_hamming: int = ranged(64, ge=1, le=256)  # ORB match: largest Hamming distance (of 256 bits)
    ratio: float = ranged(0.8, gt=0, le=1)  # Lowe ratio test: best < ratio x second best
    min_matches: int = ranged(40, ge=1, le=MAX_COUNT)  # ORB matches q <-> c needed before triangulation
    max_epipolar_px: float = ranged(2.0, gt=0, le=MAX_SCALAR)  # neighbour matches: distance to the epipolar line (pixels)
    min_parallax_deg: float = ranged(2.0, gt=0, lt=180)  # triangulation: smallest angle between the two rays
    max_reprojection_px: float = ranged(2.0, gt=0, le=MAX_SCALAR)  # triangulation: largest reprojection error in either view
    min_triangulated: int = ranged(30, ge=1, le=MAX_COUNT)  # matched features with a 3-D point needed per side
    max_neighbours: int = ranged(4, ge=1, le=MAX_KEYFRAMES)  # neighbours tried per keyframe for triangulation
    min_points: int = ranged(25, ge=1, le=MAX_COUNT)  # q <-> c matches with a 3-D point on both sides
    ransac: Sim3RansacConfig = field(default_factory=Sim3RansacConfig)

    def validate(self) -> None:
        self.ransac.validate()


@dataclass
class RelocalizationConfig:
    """Relocalisation of a lost frame against the keyframe database (stricter than loop detection)."""

    min_score: float = ranged(0.05, ge=0, le=1)  # raw DBoW2 L1 score a candidate needs
    max_candidates: int = ranged(5, ge=1, le=MAX_KEYFRAMES)  # best-scored keyframes verified at most
    min_matches: int = ranged(50, ge=4, le=MAX_COUNT)  # ORB matches image <-> keyframe
    min_inliers: int = ranged(40, ge=4, le=MAX_COUNT)  # PnP RANSAC inliers
    pnp_reprojection_px: float = ranged(3.0, gt=0, le=MAX_SCALAR)  # PnP RANSAC inlier threshold
    pnp_iterations: int = ranged(200, ge=1, le=MAX_ITERATIONS)  # PnP RANSAC hypotheses
    pnp_confidence: float = ranged(0.999, gt=0, lt=1)  # PnP RANSAC early-stop confidence


@dataclass
class LoopClosureConfig:
    """Loop closure switches and tunables (``mode``: the frontend implements ``proximity``, this
    module ``classical``; ``both`` runs both, ``off`` neither)."""

    mode: Literal["off", "proximity", "classical", "both"] = "off"  # loop closure is opt-in
    bow: BowConfig = field(default_factory=BowConfig)
    verification: VerificationConfig = field(default_factory=VerificationConfig)
    pose_graph: PoseGraphConfig = field(default_factory=PoseGraphConfig)
    relocalization: RelocalizationConfig = field(default_factory=RelocalizationConfig)
    run_in_thread: bool = True            # worker threads (classical closer, global BA); False: synchronous (same results)
    # Reproducible runs: a background result is taken this many frames (safe points) after the frame
    # that handed over its work, waiting there when it is not ready (never "when it happens to finish")
    correction_delay_frames: int = ranged(3, ge=1, le=MAX_FRAMES)  # classical closer: keyframe -> its correction
    # proximity loop -> its global BA's result; street drive (1,100 frames, low load): 10 -> ATE 0.284 m and
    # 10 s stalls, 60 -> 0.255 m (0.266 m before, results applied when ready); a global BA takes 3-11 s there
    global_ba_delay_frames: int = ranged(60, ge=1, le=MAX_FRAMES)
    max_candidates: int = ranged(2, ge=1, le=MAX_KEYFRAMES)  # accepted BoW candidates verified per query keyframe
    fold_scale: bool = True               # frontend folds the scale correction into depths
    max_pose_graph_retries: int = ranged(3, ge=1, le=MAX_ITERATIONS)  # re-solves of a correction computed before another was applied
    # Pose-graph throttle (module docstring): once a loop cluster has a correction, its further loops
    # are solved at most every solve_every described keyframes (1: after every verified loop) ...
    solve_every: int = ranged(5, ge=1, le=MAX_KEYFRAMES)
    cluster_gap: int = ranged(10, ge=1, le=MAX_KEYFRAMES)  # ... a loop > this many keyframes after the last one: new cluster

    def validate(self) -> None:
        if self.mode not in LOOP_MODES:
            raise ConfigError(f"loop_closure.mode={self.mode!r}: expected one of {', '.join(LOOP_MODES)}")
        check_ranges(self, "loop_closure.")
        self.verification.validate()
        self.pose_graph.validate()

    @property
    def classical(self) -> bool:
        return self.mode in ("classical", "both")

    @property
    def proximity(self) -> bool:
        return self.mode in ("proximity", "both")


# ----------------------------------------------------------------------------------- results

@dataclass
class Verification:
    """Outcome of the geometric verification of (query, candidate). ``T_CqCc`` (4x4 Sim(3),
    ``X_Cq = T_CqCc X_Cc``) only when ``accepted``; ``reason`` says why not."""

    query_id: int
    candidate_id: int
    accepted: bool
    reason: str
    n_matches: int = 0
    n_points: int = 0                     # matches with a 3-D point on both sides
    n_inliers: int = 0
    rms_error: float = math.inf
    T_CqCc: np.ndarray | None = None
    bow_score: float = 0.0


@dataclass
class LoopRecord:
    """A verified loop and what the pose graph made of it (``status``: ``pending`` before any
    solve, ``accepted`` or the pose graph's rejection reason)."""

    query_id: int
    candidate_id: int
    T_CqCc: np.ndarray                    # 4x4 Sim(3) in the keyframes' current units
    n_inliers: int
    status: str = "pending"


@dataclass
class PoseCorrection:
    """A Sim(3) correction of keyframe poses (see the module docstring for how to apply it): from the
    classical closer's pose graph, or from a global bundle adjustment that ran on a snapshot
    (:mod:`fgslam.services.loops`). ``LoopCorrection`` is its former name.

    ``T_update[k]`` = ``T_WC_new_k T_WC_old_k^-1`` (4x4 Sim(3), world frame) for every keyframe of
    the snapshot; ``scale[k]`` = its scale ``s_new_k / s_old_k``; ``T_WC_new[k]`` the corrected
    pose of the snapshot (before folding). ``loops`` lists every verified loop with its status. From a
    metric closer every ``scale`` is 1 and ``fold_scale`` is False.
    """

    T_update: dict[int, np.ndarray]
    scale: dict[int, float]
    T_WC_new: dict[int, np.ndarray]
    loops: list[LoopRecord]
    fold_scale: bool
    n_accepted: int
    solve_time_s: float
    hold_older: bool = False  # keyframes older than every listed one keep their pose (a global BA of the current map)
    _ids: np.ndarray = field(init=False, repr=False)

    def __post_init__(self) -> None:
        self._ids = np.array(sorted(self.T_update), dtype=np.int64)

    @classmethod
    def between(cls, T_WC_old: dict[int, np.ndarray], T_WC_new: dict[int, np.ndarray], solve_time_s: float = 0.0,
                fold_scale: bool = False, loops: Sequence[LoopRecord] = (), n_accepted: int = 0,
                hold_older: bool = False) -> "PoseCorrection":
        """The correction that takes every keyframe from ``T_WC_old[k]`` to ``T_WC_new[k]`` (4x4 Sim(3)
        each, same keys): ``U_k = T_new T_old^-1``, ``scale[k] = s_new / s_old``."""
        updates, scale = {}, {}
        for k, T_old in T_WC_old.items():
            T_new = np.asarray(T_WC_new[k], np.float64)
            updates[k] = T_new @ np.linalg.inv(T_old)
            scale[k] = float(sim3_matrix_parts(T_new)[2] / sim3_matrix_parts(T_old)[2])
        return cls(updates, scale, {k: np.asarray(T, np.float64) for k, T in T_WC_new.items()}, list(loops),
                   fold_scale, n_accepted, solve_time_s, hold_older)

    def update_for(self, kf_id: int) -> tuple[np.ndarray, float]:
        """``(U (4, 4), s)`` of keyframe ``kf_id``: its own update, or that of the corrected
        keyframe with the nearest id (ties: the older one) for keyframes outside the snapshot
        (with ``hold_older``, the identity for ids below every listed one)."""
        if kf_id in self.T_update:
            return self.T_update[kf_id], self.scale[kf_id]
        if self.hold_older and (len(self._ids) == 0 or kf_id < self._ids[0]):
            return np.eye(4), 1.0
        pos = int(np.searchsorted(self._ids, kf_id))
        near = [self._ids[p] for p in (pos - 1, pos) if 0 <= p < len(self._ids)]
        best = int(min(near, key=lambda k: (abs(int(k) - kf_id), k)))
        return self.T_update[best], self.scale[best]

    def apply_pose(self, kf_id: int, T_WC: np.ndarray) -> tuple[np.ndarray, float]:
        """Corrected 4x4 pose of keyframe ``kf_id`` from its current pose ``T_WC`` and the depth
        factor ``s`` (``inv_depth <- inv_depth / s``; 1 without ``fold_scale``)."""
        U, s = self.update_for(kf_id)
        T_new = _project_sim3(U @ np.asarray(T_WC, np.float64))
        if not self.fold_scale:
            return T_new, 1.0
        T_new[:3, :3] /= s                 # keep the old scale: T_new S(s)^-1
        return T_new, s

    def apply(self, T_WC_by_id: dict[int, np.ndarray]) -> tuple[dict[int, np.ndarray], dict[int, float]]:
        """:meth:`apply_pose` for every keyframe of a pose table; returns (poses, depth factors)."""
        poses, factors = {}, {}
        for k, T in T_WC_by_id.items():
            poses[k], factors[k] = self.apply_pose(int(k), T)
        return poses, factors

    @staticmethod
    def fold_relative(T_KF: np.ndarray, s: float) -> np.ndarray:
        """A frame's pose relative to its anchor keyframe after the anchor's scale ``s`` was folded
        into depths: ``S(s) T_KF S(s)^-1`` (translation times ``s``)."""
        out = np.array(T_KF, dtype=np.float64, copy=True)
        out[:3, 3] *= s
        return out


LoopCorrection = PoseCorrection  # former name


@dataclass
class _Keyframe:
    kf_id: int
    timestamp: float
    image: np.ndarray | None              # dropped once described
    K: np.ndarray                         # (4,) fx, fy, cx, cy
    neighbours: tuple[int, ...]
    features: KeyframeFeatures | None = None


@dataclass
class _Job:
    """Work handed to the closer's worker at tick ``tick`` (module docstring, "Reproducible"):
    ``keyframe`` (describe, detect, verify, maybe solve), ``fold`` (rescale the loop measurements by
    ``factors``), ``solve`` (a re-solve), ``close`` (the final solve); ``poses`` and ``epoch`` are the
    caller's pose table and corrections applied at submission."""

    kind: Literal["keyframe", "fold", "solve", "close"]
    tick: int
    kf_id: int | None
    poses: dict
    epoch: int
    factors: dict | None = None
    correction: "PoseCorrection | None" = None
    done: threading.Event = field(default_factory=threading.Event)


# ----------------------------------------------------------------------------------- geometry

def _as_matrix(T) -> np.ndarray:
    if isinstance(T, Sim3):
        M = T.matrix().detach().to(torch.float64).numpy()
    else:
        M = np.asarray(T, dtype=np.float64)
    if M.shape != (4, 4) or not np.isfinite(M).all():
        raise DataError(f"loop closure: pose must be a finite 4x4 Sim(3) matrix or a Sim3, got {M.shape}")
    return M.copy()


def _project_sim3(M: np.ndarray) -> np.ndarray:
    """The nearest ``[[s R, t], [0, 1]]`` (R in SO(3)): repeated corrections must not let rounding
    errors grow."""
    R, t, s = sim3_matrix_parts(M, project=True)
    out = np.eye(4)
    out[:3, :3], out[:3, 3] = s * R, t
    return out


def _rays(uv: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Unit-depth rays (N, 3) of pixels (N, 2)."""
    return np.stack([(uv[:, 0] - K[2]) / K[0], (uv[:, 1] - K[3]) / K[1], np.ones(len(uv))], 1)


def _project(X: np.ndarray, K: np.ndarray) -> np.ndarray:
    z = np.where(X[:, 2] > 0, X[:, 2], np.nan)
    return np.stack([K[0] * X[:, 0] / z + K[2], K[1] * X[:, 1] / z + K[3]], 1)


def _knn(matcher, desc_a: np.ndarray, desc_b: np.ndarray, mask: np.ndarray | None, k: int) -> np.ndarray:
    """(Na, k) int64 Hamming distances and (Na, k) indices of a's k nearest b's (OpenCV brute
    force; missing neighbours: distance ``_NO_MATCH``, index -1)."""
    dist = np.full((len(desc_a), k), _NO_MATCH, np.int64)
    idx = np.full((len(desc_a), k), -1, np.int64)
    for row in matcher.knnMatch(desc_a, desc_b, k=k, mask=mask):
        for j, m in enumerate(row[:k]):
            dist[m.queryIdx, j] = int(m.distance)
            idx[m.queryIdx, j] = m.trainIdx
    return dist, idx


def match_descriptors(desc_a: np.ndarray, desc_b: np.ndarray, max_hamming: int, ratio: float,
                      allowed: np.ndarray | None = None, mutual: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """ORB matches ``(ia, ib)``: nearest neighbour in Hamming distance among ``allowed`` (Na, Nb)
    pairs, best < ``ratio`` x second best, best <= ``max_hamming``, and (``mutual``) a's feature is
    also b's nearest. OpenCV's brute-force matcher (it releases the GIL)."""
    import cv2

    empty = np.zeros(0, np.int64), np.zeros(0, np.int64)
    if len(desc_a) == 0 or len(desc_b) == 0:
        return empty
    matcher = cv2.BFMatcher(cv2.NORM_HAMMING)
    mask = None if allowed is None else np.ascontiguousarray(allowed, dtype=np.uint8)
    dist, idx = _knn(matcher, desc_a, desc_b, mask, 2)
    ok = (idx[:, 0] >= 0) & (dist[:, 0] <= max_hamming) & (dist[:, 0] < ratio * dist[:, 1])
    if mutual:
        _, back = _knn(matcher, desc_b, desc_a, None if mask is None else np.ascontiguousarray(mask.T), 1)
        ok &= back[np.where(ok, idx[:, 0], 0), 0] == np.arange(len(desc_a))
    ia = np.flatnonzero(ok)
    return ia, idx[ia, 0]


def triangulate_pair(uv_a: np.ndarray, uv_b: np.ndarray, K_a: np.ndarray, K_b: np.ndarray,
                     T_CaCb: np.ndarray, min_parallax_deg: float, max_reprojection_px: float
                     ) -> tuple[np.ndarray, np.ndarray]:
    """Midpoint triangulation of matched pixels (N, 2) in cameras a and b, ``T_CaCb`` Sim(3) 4x4.
    Returns ``(X_a (N, 3) in camera a, ok (N,))``: both depths positive, ray angle >=
    ``min_parallax_deg``, reprojection error <= ``max_reprojection_px`` in both images."""
    R, t, s = sim3_matrix_parts(T_CaCb)
    d_a = _rays(uv_a, K_a)
    d_a /= np.linalg.norm(d_a, axis=1, keepdims=True)
    d_b = _rays(uv_b, K_b) @ R.T
    d_b /= np.linalg.norm(d_b, axis=1, keepdims=True)
    b = np.sum(d_a * d_b, axis=1)
    d = d_a @ t
    e = d_b @ t
    denom = 1.0 - b * b
    with np.errstate(divide="ignore", invalid="ignore"):
        lam_a = (d - b * e) / denom
        lam_b = (b * d - e) / denom
    X_a = 0.5 * (lam_a[:, None] * d_a + t + lam_b[:, None] * d_b)
    parallax_ok = b <= math.cos(math.radians(min_parallax_deg))
    X_b = ((X_a - t) @ R) / s                                  # T_CaCb^-1 X_a
    err_a = np.linalg.norm(_project(X_a, K_a) - uv_a, axis=1)
    err_b = np.linalg.norm(_project(X_b, K_b) - uv_b, axis=1)
    with np.errstate(invalid="ignore"):
        ok = (parallax_ok & (lam_a > 0) & (lam_b > 0) & (X_a[:, 2] > 0) & (X_b[:, 2] > 0)
              & (err_a <= max_reprojection_px) & (err_b <= max_reprojection_px))
    ok &= np.isfinite(X_a).all(axis=1)
    return X_a, ok


def epipolar_mask(uv_a: np.ndarray, uv_b: np.ndarray, K_a: np.ndarray, K_b: np.ndarray,
                  T_CaCb: np.ndarray, max_px: float) -> np.ndarray:
    """(Na, Nb) bool: pixel pairs within ``max_px`` of each other's epipolar line in both images
    (distances in pixels via each image's fx) under the relative pose ``T_CaCb``."""
    R, t, _ = sim3_matrix_parts(T_CaCb)
    tn = np.linalg.norm(t)
    if not tn > 0:
        return np.zeros((len(uv_a), len(uv_b)), bool)
    tx = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]]) / tn
    E = tx @ R                                                   # x_a^T E x_b = 0
    x_a, x_b = _rays(uv_a, K_a), _rays(uv_b, K_b)
    l_a = x_b @ E.T                                              # lines in image a: E x_b  (Nb, 3)
    l_b = x_a @ E                                                # lines in image b: E^T x_a (Na, 3)
    num = x_a @ l_a.T                                            # (Na, Nb) = x_a^T E x_b
    with np.errstate(divide="ignore", invalid="ignore"):
        dist_a = np.abs(num) / np.linalg.norm(l_a[:, :2], axis=1)[None, :] * K_a[0]
        dist_b = np.abs(num) / np.linalg.norm(l_b[:, :2], axis=1)[:, None] * K_b[0]
    return (np.maximum(dist_a, dist_b) <= max_px)


# ----------------------------------------------------------------------------------- the closer

class LoopCloser:
    """Classical loop closure + relocalisation beside a frontend (see the module docstring).

    ``metric``: the map has a metric scale (stereo, RGB-D): loops are verified by a rigid fit and the
    pose graph holds every keyframe's scale, so corrections are SE(3) with nothing to fold (module
    docstring).

    Determinism (module docstring, "Reproducible"): each call of :meth:`poll` is one *tick*. Work
    handed over at tick t (a keyframe, a fold of the loop measurements, a re-solve) is a job that
    carries a snapshot of the caller's pose table and the count of corrections applied so far; the
    worker runs the jobs in order on those snapshots only, and the job's result is taken at tick
    ``t + correction_delay_frames`` (waiting there for it when it is not ready). So what the caller
    sees depends on its own calls alone, never on how fast the worker ran, and the threaded and the
    synchronous mode give the same results.

    Thread safety: every method is called from the frontend thread; the worker reads the keyframe
    table behind one lock and otherwise owns its state (features, database, loops, throttle).
    """

    def __init__(self, config: LoopClosureConfig | None = None, recognizer: PlaceRecognizer | None = None,
                 metric: bool = False):
        self.cfg = config or LoopClosureConfig(mode="classical")
        self.cfg.validate()
        self.metric = bool(metric)
        self._lock = threading.RLock()
        self._enabled = self.cfg.classical
        self._recognizer = (recognizer or PlaceRecognizer(self.cfg.bow)) if self._enabled else None
        self._reloc_recognizer = None                # own ORB extractor for the caller's thread
        self._keyframes: dict[int, _Keyframe] = {}
        self._last_id: int | None = None
        # caller's side: its pose table, corrections applied, ticks, jobs whose results are not taken yet
        self._poses: dict[int, np.ndarray] = {}      # latest T_WC per keyframe (4x4)
        self._epoch = 0                              # corrections handed out so far
        self._tick = 0                               # calls of poll() so far
        self._jobs: deque[_Job] = deque()
        self._resolves = 0                           # consecutive re-solves of stale corrections
        # worker's side (the caller reads it only when the worker is idle, or under the lock)
        self._order: list[int] = []                  # described keyframes, in processing order
        self._loops: list[LoopRecord] = []
        self._log: list[Verification] = []
        self._queue: queue.Queue = queue.Queue()
        self._closed = False
        self._error: BaseException | None = None
        self._times = {"describe": 0.0, "detect": 0.0, "verify": 0.0, "pose_graph": 0.0}
        self._counts = {"pose_graph_solves": 0, "loop_clusters": 0, "corrections": 0}
        # pose-graph throttle: positions in self._order of the last loop / last solve, index in
        # self._loops where the current cluster starts, verified loops not solved with yet
        self._last_loop_pos: int | None = None
        self._last_solve_pos = -1
        self._cluster_start = 0
        self._unsolved = False
        self._worker = None
        if self._enabled and self.cfg.run_in_thread:
            self._worker = threading.Thread(target=self._run, name="fgslam-loop-closer", daemon=True)
            self._worker.start()

    # ------------------------------------------------------------------ frontend API
    @property
    def enabled(self) -> bool:
        """Whether the classical loop closure runs (``mode`` classical or both)."""
        return self._enabled

    def add_keyframe(self, kf_id: int, timestamp: float, image: np.ndarray, K: Sequence[float], T_WC,
                     neighbours: Sequence[int] = ()) -> None:
        """Queue a new keyframe (cheap). ``image`` (H, W) grey uint8 (or RGB), ``K`` (fx, fy, cx, cy),
        ``T_WC`` Sim3 or 4x4, ``neighbours``: keyframe ids to triangulate with, best first (the
        closer adds its temporal neighbours after them). Ids must increase."""
        if not self._enabled:
            return
        self._raise_worker_error()
        kf_id = int(kf_id)
        K_arr = np.asarray(K, dtype=np.float64).reshape(-1)
        if K_arr.shape != (4,) or not (np.isfinite(K_arr).all() and K_arr[0] > 0 and K_arr[1] > 0):
            raise DataError(f"loop closure: keyframe {kf_id}: K must be (fx, fy, cx, cy) with fx, fy > 0")
        kf = _Keyframe(kf_id, float(timestamp), np.array(image, copy=True), K_arr,
                       tuple(int(n) for n in neighbours))
        if self._closed:
            raise DataError("loop closure: add_keyframe after close()")
        if self._last_id is not None and kf_id <= self._last_id:
            raise DataError(f"loop closure: keyframe id {kf_id} is not new and increasing "
                            f"(last {self._last_id})")
        self._last_id = kf_id
        with self._lock:
            self._keyframes[kf_id] = kf
        self._poses[kf_id] = _as_matrix(T_WC)
        self._submit("keyframe", kf_id=kf_id)

    def update_poses(self, T_WC_by_id: dict) -> None:
        """The frontend's latest keyframe poses (Sim3 or 4x4 each); unknown ids are ignored."""
        if not self._enabled:
            return
        for k, T in T_WC_by_id.items():
            if int(k) in self._poses:
                self._poses[int(k)] = _as_matrix(T)

    def poll(self) -> PoseCorrection | None:
        """One tick: the newest correction among the jobs due now (handed over
        ``correction_delay_frames`` ticks ago or earlier; all of them after :meth:`close`), or None.
        Waits for a due job that is not finished. The caller must apply the correction (module
        docstring); the closer applies it to its own pose table and, through the worker's queue, to
        its loop measurements."""
        if not self._enabled:
            return None
        self._tick += 1
        newest: _Job | None = None
        while self._jobs and (self._closed or self._jobs[0].tick + self.cfg.correction_delay_frames <= self._tick):
            job = self._jobs.popleft()
            job.done.wait()
            self._raise_worker_error()
            if job.correction is not None:
                newest = job                          # a later solve supersedes an earlier one
        if newest is None:
            return None
        corr = newest.correction
        if newest.epoch != self._epoch:
            # solved on poses from before a correction applied since: solve again on the current ones
            if self._resolves < self.cfg.max_pose_graph_retries:
                self._resolves += 1
                logger.debug("loop correction superseded by an applied one; solving again")
                self._submit("solve")
                return self.poll() if self._closed else None
            logger.warning("pose graph: corrections kept arriving; gave up after %d tries",
                           self.cfg.max_pose_graph_retries)
            self._resolves = 0
            return None
        self._resolves = 0
        self._epoch += 1
        self._poses, factors = corr.apply(self._poses)
        if corr.fold_scale:
            self._submit("fold", factors=factors)     # loop measurements into the folded units, in order
        return corr

    def _submit(self, kind: str, kf_id: int | None = None, factors: dict | None = None) -> None:
        """Hand a job to the worker (or run it now, synchronously or after close) with a snapshot of
        the pose table and the corrections applied so far."""
        job = _Job(kind, self._tick, kf_id, dict(self._poses), self._epoch, factors)
        if kind != "fold":
            self._jobs.append(job)
        if self._worker is not None:
            self._queue.put(job)
        else:
            self._raise_worker_error()            # nothing runs after a failed job
            self._run_job(job)
            self._raise_worker_error()

    def relocalize(self, image: np.ndarray, K: Sequence[float]) -> tuple[int, np.ndarray] | None:
        """Find the keyframe an image (of a lost track) sees and its pose: ``(kf_id, T_WC 4x4)`` (the
        keyframe's Sim(3) scale) or None. Stricter than loop detection: raw score threshold, ORB
        matches and PnP RANSAC on the keyframe's triangulated points. Runs in the caller's thread
        once the worker has described every keyframe handed to it (so the result does not depend on
        the worker's speed)."""
        if not self._enabled:
            return None
        import cv2

        self.wait_idle()
        rc = self.cfg.relocalization
        K_arr = np.asarray(K, dtype=np.float64).reshape(-1)
        if self._reloc_recognizer is None:
            self._reloc_recognizer = PlaceRecognizer(self.cfg.bow, self._recognizer.vocabulary)
        recognizer = self._reloc_recognizer
        feats = recognizer.describe(image)
        if len(feats.uv) < rc.min_matches:
            logger.info("relocalisation: %d features (< %d)", len(feats.uv), rc.min_matches)
            return None
        results = self._recognizer.detector.database.query(feats.bow, rc.max_candidates, min_score=rc.min_score)
        vc = self.cfg.verification
        Kmat = np.array([[K_arr[0], 0, K_arr[2]], [0, K_arr[1], K_arr[3]], [0, 0, 1]])
        poses, order = dict(self._poses), list(self._order)
        for res in results:
            kf = self._keyframes.get(res.kf_id)
            if kf is None or kf.features is None:
                continue
            ia, ib = match_descriptors(feats.descriptors, kf.features.descriptors, vc.max_hamming, vc.ratio)
            if len(ia) < rc.min_matches:
                logger.info("relocalisation: keyframe %d (score %.3f): %d matches", res.kf_id, res.score, len(ia))
                continue
            X_k, ok_k = self._triangulate(kf, order, poses, ib)
            sel = ok_k[ib]
            if sel.sum() < rc.min_inliers:
                continue
            obj = X_k[ib[sel]]
            found, rvec, tvec, inl = cv2.solvePnPRansac(
                obj.astype(np.float64), feats.uv[ia[sel]].astype(np.float64), Kmat, None,
                iterationsCount=rc.pnp_iterations, reprojectionError=rc.pnp_reprojection_px,
                confidence=rc.pnp_confidence, flags=cv2.SOLVEPNP_EPNP)
            n_inl = 0 if inl is None else len(inl)
            if not found or n_inl < rc.min_inliers:
                logger.info("relocalisation: keyframe %d: PnP %d inliers (< %d)", res.kf_id, n_inl, rc.min_inliers)
                continue
            R_qk = cv2.Rodrigues(rvec)[0]                          # X_q = R X_k + t (keyframe units)
            T_CkCq = np.eye(4)
            T_CkCq[:3, :3] = R_qk.T
            T_CkCq[:3, 3] = -R_qk.T @ tvec.reshape(3)
            T_WC = poses[kf.kf_id] @ T_CkCq
            logger.info("relocalised on keyframe %d (score %.3f, %d PnP inliers)", res.kf_id, res.score, n_inl)
            return kf.kf_id, T_WC
        return None

    def wait_idle(self, timeout: float | None = None) -> bool:
        """Block until every job handed to the worker is done; False on timeout (tests, shutdown).
        Changes nothing of what :meth:`poll` returns when."""
        if self._worker is None:
            return True
        t_end = None if timeout is None else time.monotonic() + timeout
        while self._queue.unfinished_tasks:
            if self._error is not None or (t_end is not None and time.monotonic() > t_end):
                break
            time.sleep(_IDLE_POLL_S)
        self._raise_worker_error()
        return not self._queue.unfinished_tasks

    def close(self) -> None:
        """Process the queued keyframes, solve the pose graph with the loops verified since the last
        solve (the following :meth:`poll` returns that final correction: after close every job is
        due) and stop the worker."""
        if not self._enabled or self._closed:
            self._closed = True
            return
        try:
            self._submit("close")
        finally:
            self._closed = True
            if self._worker is not None:
                self._queue.put(None)
                self._worker.join()
                self._worker = None
        self._raise_worker_error()

    def cancel(self) -> None:
        """Stop the worker after its current job without running the queued ones (an interrupted or
        failed run); nothing more is handed out."""
        self._closed = True
        self._jobs.clear()
        if self._worker is not None:
            while True:                               # drop the queued jobs
                try:
                    job = self._queue.get_nowait()
                except queue.Empty:
                    break
                if job is not None:
                    job.done.set()
                self._queue.task_done()
            self._queue.put(None)
            self._worker.join()
            self._worker = None

    # ------------------------------------------------------------------ diagnostics
    @property
    def loops(self) -> list[LoopRecord]:
        with self._lock:
            return list(self._loops)

    @property
    def verifications(self) -> list[Verification]:
        """Every verification attempt (accepted or rejected, with the reason)."""
        with self._lock:
            return list(self._log)

    def stage_times(self) -> dict[str, float]:
        """Seconds spent per stage (describe, detect, verify, pose_graph), summed over keyframes."""
        with self._lock:
            return dict(self._times)

    @property
    def counts(self) -> dict[str, int]:
        """``pose_graph_solves`` (calls of the pose-graph optimiser), ``loop_clusters`` (runs of
        verified loops, see ``LoopClosureConfig.cluster_gap``) and ``corrections`` (corrections
        computed, superseded ones included)."""
        with self._lock:
            return dict(self._counts)

    def verify(self, query_id: int, candidate_id: int, bow_score: float = 0.0) -> Verification:
        """Geometric verification of two described keyframes at the caller's current poses (logged;
        waits for the worker first)."""
        self.wait_idle()
        return self._verify_logged(query_id, candidate_id, dict(self._poses), bow_score)

    def _verify_logged(self, query_id: int, candidate_id: int, poses: dict, bow_score: float) -> Verification:
        with self._lock:
            q, c = self._keyframes.get(int(query_id)), self._keyframes.get(int(candidate_id))
            if q is None or c is None:
                raise DataError(f"loop closure: verify({query_id}, {candidate_id}): unknown keyframe id")
            order = list(self._order)
        t0 = time.perf_counter()
        ver = self._verify(q, c, order, poses, bow_score)
        with self._lock:
            self._times["verify"] += time.perf_counter() - t0
            self._log.append(ver)
        log = logger.info if ver.accepted else logger.debug
        log("loop %d -> %d: %s (%d matches, %d points, %d inliers)", ver.query_id, ver.candidate_id,
            ver.reason, ver.n_matches, ver.n_points, ver.n_inliers)
        return ver

    # ------------------------------------------------------------------ worker
    def _raise_worker_error(self) -> None:
        if self._error is not None:
            raise OptimizationError(f"loop closure worker failed: {self._error!r}") from self._error

    def _run(self) -> None:
        while True:
            job = self._queue.get()
            try:
                if job is None:                       # close(): stop
                    return
                if self._error is None:
                    self._run_job(job)
            finally:
                job_done = job.done if job is not None else None
                if job_done is not None:
                    job_done.set()
                self._queue.task_done()

    def _run_job(self, job: "_Job") -> None:
        """One job, in the worker (or the caller's thread when synchronous); a failure is kept for the
        caller (raised at its next call)."""
        try:
            if job.kind == "keyframe":
                self._process(job)
            elif job.kind == "fold":
                self._fold_loops(job.factors)
            elif job.kind == "solve":
                job.correction = self._solve(job.poses)
            elif job.kind == "close":
                job.correction = self._solve_unsolved(job.poses)
            else:
                raise ValueError(f"loop closure: unknown job kind {job.kind!r}")
        except BaseException as exc:                  # surfaced in the frontend thread
            logger.exception("loop closure worker failed on a %s job", job.kind)
            self._error = exc
        finally:
            job.done.set()

    def _fold_loops(self, factors: dict) -> None:
        """A correction with ``fold_scale`` was applied: the loop measurements verified before it
        into the folded units of their keyframes."""
        with self._lock:
            for loop in self._loops:
                sq, sc = factors.get(loop.query_id, 1.0), factors.get(loop.candidate_id, 1.0)
                M = loop.T_CqCc.copy()
                M[:3, 3] *= sq
                M[:3, :3] *= sq / sc
                loop.T_CqCc = M

    def _process(self, job: "_Job") -> None:
        kf_id = job.kf_id
        t0 = time.perf_counter()
        with self._lock:
            kf = self._keyframes[kf_id]
            image = kf.image
        feats = self._recognizer.describe(image)
        t1 = time.perf_counter()
        with self._lock:
            kf.features, kf.image = feats, None
            self._order.append(kf_id)
            pos = len(self._order) - 1
            result = self._recognizer.detector.process(kf_id, feats.bow, kf.timestamp)
            self._times["describe"] += t1 - t0
            self._times["detect"] += time.perf_counter() - t1
        if result.status == "accepted":
            for cand in result.candidates[: self.cfg.max_candidates]:
                ver = self._verify_logged(kf_id, cand.kf_id, job.poses, cand.score)
                if ver.accepted:
                    self._add_loop(pos, LoopRecord(kf_id, cand.kf_id, ver.T_CqCc, ver.n_inliers))
                    break
        if self._solve_due(pos):
            job.correction = self._solve_unsolved(job.poses, pos)

    def _add_loop(self, pos: int, loop: LoopRecord) -> None:
        """Record a verified loop whose query is at position ``pos``; a new cluster when the previous
        loop's query is more than ``cluster_gap`` keyframes before."""
        with self._lock:
            if self._last_loop_pos is None or pos - self._last_loop_pos > self.cfg.cluster_gap:
                self._counts["loop_clusters"] += 1
                self._cluster_start = len(self._loops)
            self._loops.append(loop)
            self._last_loop_pos = pos
            self._unsolved = True

    def _solve_due(self, pos: int) -> bool:
        """Whether the loops not solved with yet are solved at position ``pos``: at once while the
        current cluster has no accepted loop; else once ``solve_every`` keyframes passed since the last
        solve or the cluster ended (``cluster_gap`` keyframes without a loop)."""
        with self._lock:
            if not self._unsolved:
                return False
            corrected = any(l.status == "accepted" for l in self._loops[self._cluster_start:])
            return (not corrected or pos - self._last_solve_pos >= self.cfg.solve_every
                    or pos - self._last_loop_pos > self.cfg.cluster_gap)

    def _solve_unsolved(self, poses: dict, pos: int | None = None) -> PoseCorrection | None:
        """Solve if verified loops wait for it (``pos``: current position; None: the last one)."""
        with self._lock:
            if not self._unsolved:
                return None
            self._unsolved = False
            self._last_solve_pos = len(self._order) - 1 if pos is None else pos
        return self._solve(poses)

    def _solve(self, poses: dict) -> PoseCorrection | None:
        """Pose graph over every described keyframe with every verified loop, from the pose table
        ``poses`` (a job's snapshot); the correction when it accepts at least one loop."""
        with self._lock:
            ids = list(self._order)
            loops = [LoopRecord(l.query_id, l.candidate_id, l.T_CqCc.copy(), l.n_inliers) for l in self._loops]
            self._counts["pose_graph_solves"] += 1
        if not ids or not loops:
            return None
        T_old = np.stack([poses[k] for k in ids])
        t0 = time.perf_counter()
        index = {k: i for i, k in enumerate(ids)}
        T_WC = Sim3.from_matrix(torch.from_numpy(T_old))
        Z = Sim3.from_matrix(torch.from_numpy(np.stack([l.T_CqCc for l in loops])))
        try:
            res = optimize_sim3_pose_graph(T_WC, [index[l.query_id] for l in loops],
                                           [index[l.candidate_id] for l in loops], Z, self.cfg.pose_graph,
                                           hold_scale=self.metric)
        except (OptimizationError, ValueError) as exc:
            # ValueError: optimize_sim3_pose_graph fails on a round that rejects every loop
            logger.warning("pose graph over %d keyframes, %d loops failed: %s", len(ids), len(loops), exc)
            return None
        dt = time.perf_counter() - t0
        with self._lock:
            self._times["pose_graph"] += dt
            for rec, dec in zip(self._loops, res.loops):
                rec.status = dec.reason
            statuses = [LoopRecord(l.query_id, l.candidate_id, l.T_CqCc.copy(), l.n_inliers, l.status)
                        for l in self._loops]
            n_acc = int(res.accepted.sum())
            if n_acc == 0:
                logger.info("pose graph: no loop accepted yet (%d verified)", len(loops))
                return None
            self._counts["corrections"] += 1
        T_new = res.T_WC.matrix().numpy()
        updates = {k: T_new[i] @ np.linalg.inv(T_old[i]) for i, k in enumerate(ids)}
        scale = {k: float(res.scale_correction[i]) for i, k in enumerate(ids)}
        logger.info("loop correction ready: %d keyframes, %d/%d loops accepted (%.3f s)",
                    len(ids), n_acc, len(loops), dt)
        return PoseCorrection(updates, scale, {k: T_new[i] for i, k in enumerate(ids)},
                              statuses, self.cfg.fold_scale and not self.metric, n_acc, dt)

    # ------------------------------------------------------------------ verification
    def _neighbour_ids(self, kf: _Keyframe, order: list[int]) -> list[int]:
        """Triangulation partners: the caller's neighbours, then temporal ones (-1, +1, -2, +2, ...)."""
        out = [n for n in kf.neighbours if n != kf.kf_id]
        pos = order.index(kf.kf_id) if kf.kf_id in order else -1
        if pos >= 0:
            for step in range(1, len(order)):
                for p in (pos - step, pos + step):
                    if 0 <= p < len(order):
                        out.append(order[p])
                if len(out) >= 2 * self.cfg.verification.max_neighbours:
                    break
        seen, unique = set(), []
        for n in out:
            if n not in seen:
                seen.add(n)
                unique.append(n)
        return unique

    def _triangulate(self, kf: _Keyframe, order: list[int], poses: dict,
                     subset: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """3-D points (N, 3) in camera ``kf`` for its N features and a validity mask. Only the
        features ``subset`` (indices; None: all) are triangulated, each with the first of up to
        ``max_neighbours`` neighbours (:meth:`_neighbour_ids`) that triangulates it."""
        vc = self.cfg.verification
        feats = kf.features
        X = np.full((len(feats.uv), 3), np.nan)
        ok = np.zeros(len(feats.uv), bool)
        todo = np.arange(len(feats.uv)) if subset is None else np.unique(subset)
        tried = 0
        for n_id in self._neighbour_ids(kf, order):
            if tried >= vc.max_neighbours or todo.size == 0:
                break
            with self._lock:
                nb = self._keyframes.get(n_id)
            if nb is None or nb.features is None or len(nb.features.uv) == 0 or n_id not in poses:
                continue
            tried += 1
            T_CaCb = np.linalg.inv(poses[kf.kf_id]) @ poses[n_id]
            allowed = epipolar_mask(feats.uv[todo], nb.features.uv, kf.K, nb.K, T_CaCb, vc.max_epipolar_px)
            ia, ib = match_descriptors(feats.descriptors[todo], nb.features.descriptors, vc.max_hamming,
                                       vc.ratio, allowed=allowed)
            if len(ia) == 0:
                continue
            Xa, good = triangulate_pair(feats.uv[todo[ia]], nb.features.uv[ib], kf.K, nb.K, T_CaCb,
                                        vc.min_parallax_deg, vc.max_reprojection_px)
            X[todo[ia[good]]] = Xa[good]
            ok[todo[ia[good]]] = True
            todo = todo[~ok[todo]]
        return X, ok

    def _verify(self, q: _Keyframe, c: _Keyframe, order: list[int], poses: dict, bow_score: float) -> Verification:
        vc = self.cfg.verification
        qf, cf = q.features, c.features

        def reject(reason: str, **kw) -> Verification:
            return Verification(q.kf_id, c.kf_id, False, reason, bow_score=bow_score, **kw)

        if qf is None or cf is None or len(qf.uv) == 0 or len(cf.uv) == 0:
            return reject("no features")
        ia, ib = match_descriptors(qf.descriptors, cf.descriptors, vc.max_hamming, vc.ratio)
        if len(ia) < vc.min_matches:
            return reject(f"{len(ia)} ORB matches < {vc.min_matches}", n_matches=len(ia))
        X_q, ok_q = self._triangulate(q, order, poses, ia)
        X_c, ok_c = self._triangulate(c, order, poses, ib)
        if ok_q.sum() < vc.min_triangulated or ok_c.sum() < vc.min_triangulated:
            return reject(f"too few triangulated points (query {ok_q.sum()}, candidate {ok_c.sum()} "
                          f"< {vc.min_triangulated}; little parallax or texture)", n_matches=len(ia))
        both = ok_q[ia] & ok_c[ib]
        n_points = int(both.sum())
        if n_points < vc.min_points:
            return reject(f"{n_points} matches with 3-D points < {vc.min_points}", n_matches=len(ia),
                          n_points=n_points)
        est = estimate_sim3_ransac(X_q[ia[both]], X_c[ib[both]], vc.ransac, with_scale=not self.metric)
        if not est.success:
            group = "SE(3)" if self.metric else "Sim(3)"
            return reject(f"{group} RANSAC: {est.reason}", n_matches=len(ia), n_points=n_points)
        T = est.T_ab.matrix().detach().to(torch.float64).numpy()
        return Verification(q.kf_id, c.kf_id, True, "verified", len(ia), n_points, est.n_inliers,
                            est.rms_error, T, bow_score)
