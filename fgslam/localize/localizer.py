"""Localisation in a stored map, one frame at a time (:class:`MapLocalizer`): every frame gets a pose
in the map's frame or "not localised"; the map never grows. ``fgslam localize`` runs it over a
sequence (:mod:`fgslam.localize.sequence`); merging a recording into a map uses it on the
recording's keyframes (:mod:`fgslam.localize.merge`).

Per frame, on the map's feature image (the run's image scaled by the map's ``image_scale``; ORB with
the map's settings, :mod:`fgslam.export.mapfile`):

1. tracking: while the previous frame was localised, its ORB features are matched
   (:func:`fgslam.loop.verification.match_descriptors`) to the features with a 3-D point of the
   ``tracking.candidates`` map keyframes nearest to the previous pose (position, among those whose
   viewing direction is within ``tracking.max_angle_deg``), and the pose is solved by PnP RANSAC on
   the map points in the world frame (:func:`fgslam.loop.verification.solve_pnp`), accepted with
   at least ``tracking.min_inliers`` inliers;
2. relocalisation: otherwise (the first frame, after a loss) the frame's bag-of-words vector is
   queried in the map's keyframe database (:class:`fgslam.loop.bow.BowDatabase`) and the best
   ``relocalization.max_candidates`` keyframes are verified one by one by matching and PnP with the
   stricter ``relocalization`` thresholds (the loop closer's);
3. a tracked or relocalised pose is kept only when it is well conditioned: the standard deviation
   of its position for 1 px of pixel noise, from its inliers' geometry
   (:func:`relative_position_std`), over their median depth is at most ``max_position_std`` (a
   quality gate; the default, 1.0, gates nothing in practice: on 7-Scenes it trades localised
   frames for accuracy, docs/benchmarks/maps.md);
4. else the frame is "not localised": no pose is made up (no motion model).

Over a sequence, ``fgslam localize`` also runs the map's own SLAM configuration on it and anchors that
odometry to these poses (:mod:`fgslam.localize.anchor`, ``odometry``): every frame the odometry poses
gets a pose in the map's frame, between localisations too (status ``odometry``).
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..core.config import MAX_COUNT, MAX_ITERATIONS, MAX_KEYFRAMES, MAX_SCALAR, check_ranges, from_dict, ranged
from ..core.errors import ConfigError, DataError
from ..core.tracking import Keyframes, TrackResult
from ..export.mapfile import DESCRIPTOR_BYTES, MapMergeConfig, StoredMap, feature_image
from ..io.datasets import DatasetConfig
from ..loop.bow import BowDatabase
from ..loop.features import OrbConfig, OrbExtractor
from ..loop.records import RelocalizationConfig
from ..loop.verification import match_descriptors, solve_pnp
from ..loop.vocabulary import BowVector, load_vocabulary
from .anchor import OdometryConfig

logger = logging.getLogger(__name__)

_NOT_LOCALISED = "not localised: no map keyframe verified the frame"
#: What :class:`FrameLocalization` says of a frame.
STATUSES = ("tracked", "relocalised", "not_localised")
#: What ``fgslam localize`` says of a frame: the localiser's statuses, and ``odometry`` for a frame posed by
#: the anchored odometry alone (:mod:`fgslam.localize.anchor`)
SEQUENCE_STATUSES = ("tracked", "relocalised", "odometry", "not_localised")


def relative_position_std(T_WC: np.ndarray, X_W: np.ndarray, K: np.ndarray) -> float:
    """Conditioning of a pose solved from the points ``X_W`` (N, 3, world) seen by the camera
    ``T_WC`` (intrinsics ``K`` = fx, fy, cx, cy): the standard deviation of the camera position
    (root of the trace of its covariance) when every pixel has 1 px of noise, from the Gauss-Newton
    information of the reprojection residuals (6-dof, right perturbation of ``T_WC``), divided by
    the points' median depth (scale-free: the same for a monocular map of any scale). Infinite when
    the pose is not determined (fewer than 3 points in front, or a singular information)."""
    T_CW = np.linalg.inv(T_WC)
    X_C = X_W @ T_CW[:3, :3].T + T_CW[:3, 3]
    X_C = X_C[X_C[:, 2] > 0]
    if len(X_C) < 3:
        return float("inf")
    x, y, z = X_C.T
    J_proj = np.zeros((len(X_C), 2, 3))               # d(pixel) / d(X_C)
    J_proj[:, 0, 0] = K[0] / z
    J_proj[:, 0, 2] = -K[0] * x / z ** 2
    J_proj[:, 1, 1] = K[1] / z
    J_proj[:, 1, 2] = -K[1] * y / z ** 2
    skew = np.zeros((len(X_C), 3, 3))                 # [X_C]x
    skew[:, 0, 1], skew[:, 0, 2], skew[:, 1, 2] = -z, y, -x
    skew[:, 1, 0], skew[:, 2, 0], skew[:, 2, 1] = z, -y, x
    J = np.concatenate([-J_proj, J_proj @ skew], axis=2).reshape(-1, 6)  # X_C' = X_C - dt + [X_C]x dw
    try:
        cov = np.linalg.inv(J.T @ J)
    except np.linalg.LinAlgError:
        return float("inf")
    var = float(np.trace(cov[:3, :3]))
    return float(np.sqrt(var) / np.median(z)) if var > 0 and np.isfinite(var) else float("inf")


@dataclass
class MapTrackingConfig:
    """Frame-to-map tracking while localised (module docstring, step 1)."""

    local_keyframes: int = ranged(10, ge=1, le=MAX_KEYFRAMES)  # map keyframes nearest the predicted pose: the local map
    search_radius_px: float = ranged(10.0, gt=0, le=MAX_SCALAR)  # local map points projected this near a feature are its candidates
    search_neighbours: int = ranged(8, ge=1, le=MAX_COUNT)  # ... at most this many (nearest first)
    guided_ratio: float = ranged(0.9, gt=0, le=1)  # ratio test among a feature's projected candidates
    candidates: int = ranged(3, ge=1, le=MAX_KEYFRAMES)  # fallback without projection: keyframes matched by descriptor alone
    max_angle_deg: float = ranged(60.0, gt=0, le=180)  # ... among those viewing within this angle of it
    max_hamming: int = ranged(64, ge=1, le=256)  # ORB match: largest Hamming distance (of 256 bits)
    ratio: float = ranged(0.8, gt=0, le=1)  # Lowe ratio test
    min_inliers: int = ranged(25, ge=4, le=MAX_COUNT)  # PnP RANSAC inliers to accept a tracked pose
    pnp_reprojection_px: float = ranged(2.0, gt=0, le=MAX_SCALAR)  # PnP inlier threshold (feature-image pixels)
    pnp_iterations: int = ranged(100, ge=1, le=MAX_ITERATIONS)  # PnP RANSAC hypotheses
    pnp_confidence: float = ranged(0.99, gt=0, lt=1)  # PnP RANSAC early-stop confidence


@dataclass
class LocalizeConfig:
    """``fgslam localize`` (preset ``fgslam/configs/localize.yaml``)."""

    tracking: MapTrackingConfig = field(default_factory=MapTrackingConfig)
    relocalization: RelocalizationConfig = field(
        default_factory=lambda: RelocalizationConfig(min_inliers=30, pnp_reprojection_px=2.0))
    confirm_inliers: int = ranged(100, ge=4, le=MAX_COUNT)  # a relocalised pose needs this many local-map inliers at it
    max_position_std: float = ranged(1.0, gt=0, le=MAX_SCALAR)  # quality gate: largest position std of a pose (1 px noise, its inliers) / their median depth (1.0: none in practice)
    merge: MapMergeConfig = field(default_factory=MapMergeConfig)
    odometry: OdometryConfig = field(default_factory=OdometryConfig)  # fgslam localize: the sequence's own odometry, anchored to the map
    #: dataset settings (:class:`fgslam.io.datasets.DatasetConfig` keys) merged over the map run's,
    #: e.g. ``-o dataset.calibration_file=cam.yaml -o dataset.groundtruth_file=gt.txt`` (a map keeps no paths)
    dataset: dict[str, Any] = field(default_factory=dict)

    def validate(self) -> None:
        check_ranges(self)
        unknown = sorted(set(self.dataset) - set(DatasetConfig.__dataclass_fields__))
        if unknown:
            raise ConfigError(f"dataset: unknown key(s) {', '.join(unknown)} (DatasetConfig fields)")


@dataclass
class FrameLocalization:
    """One frame's result: ``status`` (:data:`STATUSES`), ``T_WC`` (4x4 in the map frame) or None,
    the map keyframe it was verified against (-1: none) and the PnP inliers."""

    status: str
    T_WC: np.ndarray | None = None
    kf_id: int = -1
    inliers: int = 0
    position_std: float = float("nan")  # :func:`relative_position_std` of the pose (NaN: no pose)


class MapLocalizer:
    """Tracks frames against a :class:`StoredMap` (module docstring); one frame at a time."""

    def __init__(self, stored: StoredMap, config: LocalizeConfig | None = None):
        self.cfg = config or LocalizeConfig()
        self.cfg.validate()
        self.map = stored
        feat = stored.meta["features"]
        self.K = np.asarray(feat["K"], np.float64)
        self.size = (int(feat["width"]), int(feat["height"]))
        self.extractor = OrbExtractor(from_dict(OrbConfig, feat["orb"], "map features.orb"))
        self.vocabulary = load_vocabulary(feat["vocabulary"])
        self.database = BowDatabase(self.vocabulary.n_words)
        for k in range(stored.num_keyframes):
            words, weights = stored.bow(k)
            self.database.add(int(stored.kf_ids[k]), BowVector(words, weights), float(stored.kf_timestamps[k]))
        self._pos = {int(i): k for k, i in enumerate(stored.kf_ids)}
        self.centres = stored.T_WC[:, :3, 3]
        R = stored.T_WC[:, :3, :3]
        self.views = R[:, :, 2] / np.linalg.norm(R[:, :, 2], axis=1, keepdims=True)
        # per keyframe: descriptors and world points of the features with a 3-D point
        self._desc: list[np.ndarray] = []
        self._X_W: list[np.ndarray] = []
        for k in range(stored.num_keyframes):
            _, desc, X_C = stored.features(k)
            ok = np.isfinite(X_C).all(axis=1)
            T = stored.T_WC[k]
            self._desc.append(np.ascontiguousarray(desc[ok]))
            self._X_W.append(X_C[ok].astype(np.float64) @ T[:3, :3].T + T[:3, 3])
        self.last: np.ndarray | None = None      # pose of the previous frame when it was localised
        self.prev: np.ndarray | None = None      # ... and of the one before (constant-velocity prediction)

    def nearest_keyframes(self, T_WC: np.ndarray) -> list[int]:
        """Positions of the ``tracking.candidates`` keyframes nearest to ``T_WC`` among those viewing
        within ``max_angle_deg`` of it (the nearest overall when none does)."""
        tc = self.cfg.tracking
        d = np.linalg.norm(self.centres - T_WC[:3, 3], axis=1)
        view = T_WC[:3, 2] / np.linalg.norm(T_WC[:3, 2])
        ok = self.views @ view >= np.cos(np.deg2rad(tc.max_angle_deg))
        d = np.where(ok, d, np.inf) if ok.any() else d
        order = np.argsort(d, kind="stable")[:tc.candidates]
        return [int(k) for k in order if np.isfinite(d[k])]

    def _verify(self, positions: list[int], uv: np.ndarray, desc: np.ndarray, max_hamming: int, ratio: float,
                min_matches: int, min_inliers: int, px: float, iterations: int, confidence: float
                ) -> tuple[np.ndarray, int, int, float] | None:
        """``(T_WC, kf_id, inliers, position_std)`` of the frame matched to the keyframes ``positions`` (each query
        feature kept with its first keyframe), or None."""
        taken = np.zeros(len(uv), bool)
        X, px_uv, owner = [], [], []
        for k in positions:
            if len(self._desc[k]) == 0:
                continue
            ia, ib = match_descriptors(desc, self._desc[k], max_hamming, ratio)
            keep = ~taken[ia]
            ia, ib = ia[keep], ib[keep]
            taken[ia] = True
            X.append(self._X_W[k][ib])
            px_uv.append(uv[ia])
            owner.append(np.full(len(ia), k))
        n = sum(len(x) for x in X)
        if n < min_matches:
            return None
        pnp = solve_pnp(np.concatenate(X), np.concatenate(px_uv), self.K, px, iterations, confidence, min_inliers)
        if pnp is None:
            return None
        T_WC, inl = pnp
        best = int(np.bincount(np.concatenate(owner)[inl]).argmax())
        return T_WC, int(self.map.kf_ids[best]), len(inl), relative_position_std(T_WC, np.concatenate(X)[inl], self.K)

    def nearest_local_points(self, T_WC: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(X_W, descriptors, keyframe position)`` of the local map around ``T_WC``: the points of
        its ``local_keyframes`` nearest keyframes (:meth:`nearest_keyframes`' choice)."""
        tc = self.cfg.tracking
        d = np.linalg.norm(self.centres - T_WC[:3, 3], axis=1)
        view = T_WC[:3, 2] / np.linalg.norm(T_WC[:3, 2])
        d = np.where(self.views @ view >= np.cos(np.deg2rad(tc.max_angle_deg)), d, np.inf)
        chosen = [int(k) for k in np.argsort(d, kind="stable")[:tc.local_keyframes] if np.isfinite(d[k])]
        if not chosen:
            return np.zeros((0, 3)), np.zeros((0, DESCRIPTOR_BYTES), np.uint8), np.zeros(0, np.int64)
        return (np.concatenate([self._X_W[k] for k in chosen]), np.concatenate([self._desc[k] for k in chosen]),
                np.concatenate([np.full(len(self._X_W[k]), k) for k in chosen]))

    def _guided(self, T_pred: np.ndarray, uv: np.ndarray, desc: np.ndarray, min_inliers: int
                ) -> tuple[np.ndarray, int, int, float] | None:
        """Matches by projection: the local map around ``T_pred`` projected into it, each feature
        matched to the best of the projected points within ``search_radius_px`` (ratio test), one
        feature per map point; then PnP RANSAC. ``(T_WC, kf_id, inliers, position_std)`` or None."""
        from scipy.spatial import cKDTree  # deferred: scipy

        tc = self.cfg.tracking
        X_W, mdesc, owner = self.nearest_local_points(T_pred)
        if len(X_W) < min_inliers or len(uv) < min_inliers:
            return None
        T_CW = np.linalg.inv(T_pred)
        X_C = X_W @ T_CW[:3, :3].T + T_CW[:3, 3]
        z = X_C[:, 2]
        front = z > 0
        with np.errstate(divide="ignore", invalid="ignore"):
            proj = np.stack([self.K[0] * X_C[:, 0] / z + self.K[2], self.K[1] * X_C[:, 1] / z + self.K[3]], 1)
        w, h = self.size
        vis = front & (proj[:, 0] >= 0) & (proj[:, 0] < w) & (proj[:, 1] >= 0) & (proj[:, 1] < h)
        idx_vis = np.flatnonzero(vis)
        if len(idx_vis) < min_inliers:
            return None
        k = min(tc.search_neighbours, len(idx_vis))
        dist_px, nn = cKDTree(proj[idx_vis]).query(uv, k=k, distance_upper_bound=tc.search_radius_px)
        dist_px, nn = dist_px.reshape(len(uv), k), nn.reshape(len(uv), k)
        valid = np.isfinite(dist_px)
        cand = idx_vis[np.where(valid, nn, 0)]
        # Hamming distance of each feature to its projected candidates only (as loop.vocabulary.hamming_matrix)
        ham = np.bitwise_count(np.bitwise_xor(desc[:, None, :], mdesc[cand])).sum(axis=2, dtype=np.int64)
        ham = np.where(valid, ham, 1 << 16)
        order = np.argsort(ham, axis=1, kind="stable")
        best = np.take_along_axis(ham, order[:, :1], 1)[:, 0]
        second = np.take_along_axis(ham, order[:, 1:2], 1)[:, 0] if k > 1 else np.full(len(uv), 1 << 16)
        ok = (best <= tc.max_hamming) & (best < tc.guided_ratio * second)
        qi = np.flatnonzero(ok)
        mi = cand[qi, order[qi, 0]]
        # one feature per map point: the one with the smallest distance
        srt = np.lexsort((best[qi], mi))
        first = np.ones(len(srt), bool)
        first[1:] = mi[srt][1:] != mi[srt][:-1]
        qi, mi = qi[srt[first]], mi[srt[first]]
        if len(qi) < min_inliers:
            return None
        pnp = solve_pnp(X_W[mi], uv[qi], self.K, tc.pnp_reprojection_px, tc.pnp_iterations, tc.pnp_confidence,
                        min_inliers)
        if pnp is None:
            return None
        T_WC, inl = pnp
        kf = int(np.bincount(owner[mi[inl]]).argmax())
        return T_WC, int(self.map.kf_ids[kf]), len(inl), relative_position_std(T_WC, X_W[mi[inl]], self.K)

    def localize(self, image: np.ndarray) -> FrameLocalization:
        """One frame (grey or RGB at the map's camera resolution): track, else relocalise, else
        not localised (module docstring)."""
        uv, desc = self.extractor(feature_image(image, *self.size))
        return self.localize_features(uv, desc)

    def localize_features(self, uv: np.ndarray, desc: np.ndarray) -> FrameLocalization:
        """:meth:`localize` on a frame's ORB features (feature-image pixels ``uv``, descriptors)."""
        tc, rc = self.cfg.tracking, self.cfg.relocalization
        if self.last is not None and len(uv):
            T_pred = self.last if self.prev is None else self.last @ np.linalg.inv(self.prev) @ self.last
            res = self._guided(T_pred, uv, desc, tc.min_inliers)
            if res is None:
                res = self._verify(self.nearest_keyframes(self.last), uv, desc, tc.max_hamming, tc.ratio,
                                   tc.min_inliers, tc.min_inliers, tc.pnp_reprojection_px, tc.pnp_iterations,
                                   tc.pnp_confidence)
            if res is not None and res[3] <= self.cfg.max_position_std:
                self.prev, self.last = self.last, res[0]
                return FrameLocalization("tracked", *res)
        self.prev = self.last = None
        if len(uv) >= rc.min_matches:
            bow, _ = self.vocabulary.transform(desc)
            for cand in self.database.query(bow, rc.max_candidates, min_score=rc.min_score):
                res = self._verify([self._pos[cand.kf_id]], uv, desc, tc.max_hamming, tc.ratio, rc.min_matches,
                                   rc.min_inliers, rc.pnp_reprojection_px, rc.pnp_iterations, rc.pnp_confidence)
                if res is None:
                    continue
                # verified again against the local map at that pose (a wrong pose finds no support there)
                res = self._guided(res[0], uv, desc, self.cfg.confirm_inliers)
                if res is not None and res[3] <= self.cfg.max_position_std:
                    self.last = res[0]
                    return FrameLocalization("relocalised", *res)
        return FrameLocalization("not_localised")


class Localizer:
    """Frames localised one at a time in a stored map without growing it (``fgslam.Slam.localize_in``, and
    ``fgslam localize`` frame by frame): :class:`MapLocalizer`'s result as a :class:`~fgslam.core.tracking.TrackResult`.

    Attributes:
        width, height: the image size the map was made at (the images given to :meth:`track`).
    """

    def __init__(self, stored: StoredMap, config: LocalizeConfig | None = None) -> None:
        self.map_localizer = MapLocalizer(stored, config)
        camera = stored.meta["camera"]
        self.width, self.height = int(camera["width"]), int(camera["height"])
        self._index = 0

    @classmethod
    def open(cls, map_path: str | Path, config: LocalizeConfig | None = None) -> "Localizer":
        """The localizer of the stored map at ``map_path`` (DataError: a missing or damaged map)."""
        from ..export.mapfile import load_stored_map

        return cls(load_stored_map(map_path), config)

    def keyframes(self) -> Keyframes:
        """The stored map's keyframes and their poses (camera-to-world in the map's frame)."""
        stored = self.map_localizer.map
        return Keyframes(np.asarray(stored.kf_ids, np.int64), np.asarray(stored.kf_timestamps, np.float64),
                         np.asarray(stored.T_WC, np.float64))

    def track(self, image: np.ndarray, t: float) -> TrackResult:
        """Localise one image (grey or colour uint8 of the map's camera and size): ``status`` is ``tracked``,
        ``relocalised`` or ``not_localised``; ``T_WC`` is in the map's frame (None: not localised). DataError: an
        image of another size."""
        image = np.asarray(image)
        if image.ndim not in (2, 3) or image.shape[:2] != (self.height, self.width):
            raise DataError(f"image of shape {image.shape}: the map was made at {self.width}x{self.height} "
                            "(grey (H, W) or colour (H, W, 3))")
        t0 = time.perf_counter()
        res = self.map_localizer.localize(image)
        index, self._index = self._index, self._index + 1
        localised = res.T_WC is not None
        return TrackResult(index, float(t), res.T_WC, res.status, False, int(res.inliers),
                           None if localised else _NOT_LOCALISED, process_s=time.perf_counter() - t0,
                           keyframe_id=int(res.kf_id) if localised else None,
                           position_std=float(res.position_std) if localised else None)
