"""Localisation that keeps its pose between relocalisations: the sequence's own odometry anchored to
the map.

A localiser (:mod:`fgslam.localize.localizer`) poses only the frames whose features verify against
the map; between them it has nothing, and each relocalisation carries its own error (a bias of a few
centimetres that the next one does not share). The odometry of the map's own SLAM configuration run on
the sequence (``fgslam localize``: :mod:`fgslam.commands.localize`) poses every frame, smoothly, in a
frame ``V`` of its own. :class:`OdometryAnchor` keeps the transform ``T_MV`` from that frame to the
map's ``M``, fitted causally to every frame that both posed:

- rotation: the chordal mean of the pairs' ``R_MC R_VC^T``;
- translation (and, for a monocular map, scale ``s``): least squares of the camera positions
  ``p_M = s R p_V + t`` given that rotation;
- robust: pairs farther than ``trim`` times the median distance from the fit are left out and the fit
  is repeated (``TRIM_ROUNDS`` times); a wrong relocalisation then moves nothing;
- a monocular odometry's scale is trusted only once the localised positions spread at least
  ``min_spread_ratio`` times their median distance from the fit (a few frames a centimetre apart
  with centimetres of error each determine no scale);
- refitted at every new pair while there are few, then once the pairs have grown by ``REFIT_GROWTH``
  (the cost stays linear in the sequence's length).

Every frame with an odometry pose then gets ``T_MV T_VC`` once ``min_pairs`` pairs exist: the frames
between localisations (up to ``max_gap_s`` after the last localised one, when set), and the localised
ones too (the fit averages the localisations' errors, where a single localisation keeps its own).
Before that, a localised frame keeps its localiser pose.
Pure numpy: the odometry is given from outside (the localisation package runs no SLAM).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional, Protocol

import numpy as np

from ..core.config import MAX_COUNT, MAX_SCALAR, ranged

#: fit, trim, fit again: rounds of trimming (the second sees the inliers of the first)
TRIM_ROUNDS = 2
#: a trimming round that would leave fewer pairs than this keeps the previous round's
MIN_KEPT_PAIRS = 3
#: positions that spread less than this relative to their distance from the origin do not spread (rounding)
MIN_RELATIVE_SPREAD = 1e-9
#: refit once the pairs have grown by this share of those fitted (at every pair while fewer than 2 / REFIT_GROWTH)
REFIT_GROWTH = 0.02


@dataclass
class OdometryConfig:
    """The sequence's own odometry, anchored to the map's localisations (module docstring)."""

    enabled: bool = True  # run the map's SLAM config on the sequence beside the localiser: every frame it poses gets a pose in the map's frame
    min_pairs: int = ranged(3, ge=1, le=MAX_COUNT)  # localised frames with an odometry pose before the anchored poses are given
    trim: float = ranged(2.0, ge=1, le=MAX_SCALAR)  # pairs farther from the fit than this times the median distance are left out
    min_spread_ratio: float = ranged(5.0, ge=0, le=MAX_SCALAR)  # monocular: the localised positions must spread this many times their median distance from the fit before the odometry's scale is used
    window: int = ranged(0, ge=0, le=MAX_COUNT)  # the most recent pairs fitted (0: all of them)
    max_gap_s: float = ranged(0.0, ge=0, le=MAX_SCALAR)  # odometry poses at most this long (s) after the last localised frame (0: no limit; a monocular odometry's scale drifts)


class Odometry(Protocol):
    """The sequence's odometry as :func:`fgslam.localize.sequence.run_localization` drives it."""

    def track(self, frame) -> Optional[np.ndarray]:
        """The pose ``T_VC`` ``(4, 4)`` of a loader's frame in the odometry's own frame (None: none yet)."""

    def close(self) -> None:
        """Stop its background work (no final optimisation: the poses given are the ones used)."""


class OdometryFactory(Protocol):
    """What builds the sequence's odometry from the map run's config (a dict, as stored in the map)."""

    def dataset_streams(self, map_config: dict) -> dict[str, bool]:
        """The ``DatasetConfig`` stream switches (``load_rgb``, ``load_depth``, ...) the odometry needs."""

    def __call__(self, map_config: dict, calibration) -> Odometry:
        """The odometry of a sequence seen with ``calibration``."""


def mean_rotation(R: np.ndarray) -> np.ndarray:
    """Chordal mean of rotations ``(n, 3, 3)``: the rotation nearest their sum (SVD)."""
    U, _, Vt = np.linalg.svd(R.sum(axis=0))
    D = np.diag([1.0, 1.0, float(np.sign(np.linalg.det(U @ Vt)))])
    return U @ D @ Vt


def scale_translation(R: np.ndarray, p_V: np.ndarray, p_M: np.ndarray, with_scale: bool) -> tuple[float, np.ndarray]:
    """Least squares ``s``, ``t`` of ``p_M = s R p_V + t`` for positions ``(n, 3)`` and the rotation ``R``;
    ``s = 1.0`` exactly without ``with_scale`` or when the positions do not spread (``s`` may come out
    <= 0: the caller decides)."""
    q = p_V @ R.T
    q_mean, m_mean = q.mean(axis=0), p_M.mean(axis=0)
    s = 1.0
    if with_scale:
        den = float(((q - q_mean) ** 2).sum())
        if den > len(q) * (MIN_RELATIVE_SPREAD * (1.0 + float(np.abs(q_mean).max()))) ** 2:
            s = float(((q - q_mean) * (p_M - m_mean)).sum()) / den
    return s, m_mean - s * q_mean


@dataclass(frozen=True)
class AnchorFit:
    """:func:`fit_anchor`'s result: ``T_MV`` ``(4, 4)`` ``[[s R, t], [0, 1]]``, the RMS spread of the kept
    map positions about their mean and their median distance from the fit (metres of the map)."""

    T_MV: np.ndarray
    spread: float
    residual: float
    scaled: bool  # the scale was fitted (with_scale, and the positions determined one > 0)


def fit_anchor(T_VC: np.ndarray, T_MC: np.ndarray, with_scale: bool, trim: float) -> AnchorFit:
    """The transform ``T_MV`` from pairs of poses of the same frames, odometry ``T_VC`` and map ``T_MC``
    ``(n, 4, 4)`` (rigid), robustly (module docstring); ``with_scale``: fit the scale too (a monocular
    odometry; a fit that finds none > 0 keeps 1), else ``s = 1``."""
    R_pairs = T_MC[:, :3, :3] @ np.transpose(T_VC[:, :3, :3], (0, 2, 1))
    p_V, p_M = T_VC[:, :3, 3], T_MC[:, :3, 3]
    keep = np.ones(len(T_VC), dtype=bool)
    for round_ in range(TRIM_ROUNDS + 1):
        R = mean_rotation(R_pairs[keep])
        s, t = scale_translation(R, p_V[keep], p_M[keep], with_scale)
        scaled = with_scale and s > 0 and s != 1.0
        if not s > 0:
            s, t = scale_translation(R, p_V[keep], p_M[keep], False)
        r = np.linalg.norm(p_M - (s * p_V @ R.T + t), axis=1)
        if round_ == TRIM_ROUNDS:
            break
        inliers = r <= trim * float(np.median(r))
        if inliers.sum() < min(MIN_KEPT_PAIRS, len(r)):
            break
        keep = inliers
    T = np.eye(4)
    T[:3, :3] = s * R
    T[:3, 3] = t
    kept = p_M[keep]
    spread = float(np.sqrt(((kept - kept.mean(axis=0)) ** 2).sum(axis=1).mean()))
    return AnchorFit(T, spread, float(np.median(r[keep])), scaled)


def rigid_in_map(S_MR: np.ndarray, T_RC: np.ndarray) -> np.ndarray:
    """(N, 4, 4) rigid camera poses ``T_RC`` (N, 4, 4) of another frame (a recording, an odometry) in the
    map's frame: rotation ``R R_RC``, position ``s R t_RC + t`` (``S_MR = [[s R, t], [0, 1]]``: its scale
    applies to positions only)."""
    s = float(np.cbrt(np.linalg.det(S_MR[:3, :3])))
    R = S_MR[:3, :3] / s
    out = np.array(T_RC, dtype=np.float64, copy=True).reshape(-1, 4, 4)
    out[:, :3, :3] = R[None] @ out[:, :3, :3]
    out[:, :3, 3] = s * out[:, :3, 3] @ R.T + S_MR[:3, 3]
    return out


class OdometryAnchor:
    """Frame by frame: the odometry pose and the localiser's pose of a frame in, the frame's pose in the
    map's frame out (module docstring). ``with_scale``: the odometry is monocular (its scale is its own)."""

    def __init__(self, config: OdometryConfig, with_scale: bool):
        self.config = config
        self.with_scale = with_scale
        self._T_VC: list[np.ndarray] = []  # the pairs a fit uses (the latest ``window`` when set)
        self._T_MC: list[np.ndarray] = []
        self.pairs = 0  # frames posed by both so far
        self._next_fit = config.min_pairs  # pairs at which to fit next
        self.T_MV: Optional[np.ndarray] = None  # the latest usable fit (None: none yet)
        self._t_localised: Optional[float] = None  # time of the last localised frame

    def _fit(self) -> None:
        fit = fit_anchor(np.stack(self._T_VC), np.stack(self._T_MC), self.with_scale, self.config.trim)
        if not self.with_scale or (fit.scaled and fit.spread > 0
                                   and fit.spread >= self.config.min_spread_ratio * fit.residual):
            self.T_MV = fit.T_MV
        self._next_fit = self.pairs + max(1, int(len(self._T_VC) * REFIT_GROWTH))  # the pairs fitted: the window's

    def add(self, t: float, T_VC: Optional[np.ndarray], T_MC: Optional[np.ndarray]) -> Optional[np.ndarray]:
        """The pose in the map's frame of the frame at time ``t`` (seconds) with odometry pose ``T_VC`` and
        localiser pose ``T_MC`` (either None when it has none): ``T_MV T_VC`` once anchored (and within
        ``max_gap_s`` of the last localised frame), else ``T_MC``."""
        if T_MC is not None:
            self._t_localised = float(t)
        if T_VC is not None and T_MC is not None:
            self._T_VC.append(np.asarray(T_VC, dtype=np.float64))
            self._T_MC.append(np.asarray(T_MC, dtype=np.float64))
            self.pairs += 1
            if self.config.window and len(self._T_VC) > self.config.window:
                del self._T_VC[0], self._T_MC[0]
            if self.pairs >= self._next_fit:
                self._fit()
        gap = self.config.max_gap_s
        in_reach = T_MC is not None or not gap or (self._t_localised is not None and t - self._t_localised <= gap)
        if T_VC is not None and self.T_MV is not None and in_reach:
            return rigid_in_map(self.T_MV, T_VC)[0]
        return None if T_MC is None else np.asarray(T_MC, dtype=np.float64)
