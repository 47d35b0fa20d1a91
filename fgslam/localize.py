"""Localisation in a stored map (``fgslam localize MAP --data SEQ --out DIR``): every frame of a new
sequence gets a pose in the map's frame or "not localised"; the map never grows.

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
   frames for accuracy, README "Maps");
4. else the frame is "not localised": no pose is made up (no motion model).

Outputs (``DIR``): ``trajectory_tum.txt`` (localised frames only, map frame), ``localization.csv``
(every frame: raw (source) frame index, as ``--start`` counts, timestamp, status ``tracked`` / ``relocalised`` / ``not_localised``, keyframe id,
inliers, ``position_std``: :func:`relative_position_std` of the pose, empty without one) and ``summary.json`` (counts, CPU time per frame, the map, and, when the sequence has ground
truth and the map its run's alignment to ground truth, the ATE of the localised poses with that
alignment applied unchanged, beside the ATE of holding the first localised pose: doing nothing).
A sequence where no frame localises writes the CSV and summary and raises :class:`NotLocalisedError`.
"""

from __future__ import annotations

import csv
import json
import logging
import os
import resource
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np

from .config import MAX_COUNT, MAX_ITERATIONS, MAX_KEYFRAMES, MAX_SCALAR, check_ranges, from_dict, ranged, to_dict
from .errors import FGSlamError
from .export.mapfile import DESCRIPTOR_BYTES, MapMergeConfig, StoredMap, check_map_camera, feature_image, load_stored_map
from .io.datasets import DatasetConfig, open_dataset
from .io.run_files import LOCALIZATION_FILE, SUMMARY_FILE, TUM_FILE
from .loop.records import RelocalizationConfig

logger = logging.getLogger(__name__)

TRAJECTORY_FILE = TUM_FILE
STATUS_FILE = LOCALIZATION_FILE  # also in fgslam.outputs.RUN_OUTPUT_FILES (a previous run's outputs)
STATUSES = ("tracked", "relocalised", "not_localised")


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


class NotLocalisedError(FGSlamError):
    """No frame of the sequence localised in the map (outputs written; no trajectory)."""


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
    #: dataset settings (:class:`fgslam.io.datasets.DatasetConfig` keys) merged over the map run's,
    #: e.g. ``-o dataset.calibration_file=cam.yaml -o dataset.groundtruth_file=gt.txt`` (a map keeps no paths)
    dataset: dict[str, Any] = field(default_factory=dict)

    def validate(self) -> None:
        check_ranges(self)
        from .errors import ConfigError

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
        from .loop.bow import BowDatabase
        from .loop.features import OrbConfig, OrbExtractor
        from .loop.vocabulary import BowVector, load_vocabulary

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
        from .loop.verification import match_descriptors, solve_pnp

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
        from scipy.spatial import cKDTree

        from .loop.verification import solve_pnp

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


# ----------------------------------------------------------------------------------- the command

def _ate(positions: np.ndarray, gt: np.ndarray, A: np.ndarray) -> float:
    aligned = positions @ A[:3, :3].T + A[:3, 3]
    return float(np.sqrt(np.mean(np.sum((aligned - gt) ** 2, axis=1))))


def run_localization(map_path: str | Path, data: str | Path, out_dir: str | Path, config: LocalizeConfig | None = None,
                     fmt: str = "auto", start: int | None = None, end: int | None = None, stride: int = 1,
                     prepare_out: Callable[[Path], Any] | None = None) -> dict[str, Any]:
    """Localise the sequence ``data`` (raw frames ``start`` .. ``end``, every ``stride``-th; the
    other dataset settings, e.g. the image size, are the map run's, with ``config.dataset`` merged
    over them) in the map at ``map_path``; writes
    the outputs (module docstring) to ``out_dir`` and returns the summary. ``prepare_out(out_dir)``
    is called once the map, the sequence and their cameras are checked, before anything is written
    (the CLI: ``fgslam run``'s rule for a previous run's outputs, :func:`fgslam.outputs.clear_previous_outputs`).
    Raises :class:`NotLocalisedError` (after writing) when no frame localised."""
    from .io.trajectory import Trajectory, write_trajectory

    config = config or LocalizeConfig()
    config.validate()
    cpu0, wall0 = time.process_time(), time.perf_counter()
    stored = load_stored_map(map_path)
    ds_dict = dict((stored.meta.get("config") or {}).get("dataset") or {})
    ds_dict.update(load_rgb=False, load_depth=False, load_right=False, load_imu=False, start=0, end=None,
                   stride=int(stride))
    ds_dict.update(config.dataset)  # the command's dataset section: e.g. a calibration or ground-truth file
    if start is not None:
        ds_dict["start"] = int(start)
    if end is not None:
        ds_dict["end"] = int(end)
    dataset = open_dataset(data, fmt, from_dict(DatasetConfig, ds_dict, f"{map_path} (dataset settings)"))
    c = dataset.calibration
    check_map_camera(stored, c.K, c.width, c.height, map_path, data)
    out = Path(out_dir)
    if prepare_out is not None:
        prepare_out(out)
    out.mkdir(parents=True, exist_ok=True)
    localizer = MapLocalizer(stored, config)
    setup_cpu = time.process_time() - cpu0
    rows: list[tuple[int, float, str, int, int, float]] = []
    stamps, poses, gt_pos, has_gt = [], [], [], []
    loop_cpu0 = time.process_time()
    for frame in dataset:
        res = localizer.localize(frame.image)
        rows.append((int(frame.source_index), float(frame.timestamp), res.status, res.kf_id, res.inliers, res.position_std))
        if res.T_WC is not None:
            stamps.append(frame.timestamp)
            poses.append(res.T_WC)
            has_gt.append(frame.T_WC_gt is not None)
            gt_pos.append(frame.T_WC_gt[:3, 3] if frame.T_WC_gt is not None else np.full(3, np.nan))
    loop_cpu = time.process_time() - loop_cpu0
    counts = {s: sum(1 for r in rows if r[2] == s) for s in STATUSES}
    n = len(rows)
    with open(out / STATUS_FILE, "w", newline="", encoding="utf-8") as f:
        w = csv.writer(f)
        w.writerow(("frame", "timestamp", "status", "keyframe", "inliers", "position_std"))
        for r in rows:
            w.writerow((r[0], f"{r[1]:.17g}", r[2], r[3], r[4], "" if np.isnan(r[5]) else f"{r[5]:.6g}"))
    localised = n - counts["not_localised"]
    summary: dict[str, Any] = {
        "map": str(map_path), "data": str(data), "frames": n, "localised": localised,
        "not_localised": counts["not_localised"], "tracked": counts["tracked"], "relocalised": counts["relocalised"],
        "localised_fraction": localised / n if n else 0.0, "map_keyframes": stored.num_keyframes,
        "map_family": stored.meta.get("family"), "map_sensor": stored.meta.get("sensor"),
        "cpu_s": time.process_time() - cpu0, "setup_cpu_s": setup_cpu, "wall_s": time.perf_counter() - wall0,
        "cpu_ms_per_frame": 1000.0 * loop_cpu / n if n else None,
        "frames_per_cpu_s": n / loop_cpu if loop_cpu > 0 else None,
        "load_average": list(os.getloadavg()), "max_rss_mib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
        "evaluation": None, "config": to_dict(config), "outputs": [STATUS_FILE, SUMMARY_FILE],
    }
    alignment = stored.meta.get("groundtruth_alignment")
    if poses and alignment and any(has_gt):
        sel = np.array(has_gt)
        A = np.asarray(alignment["matrix"], np.float64)
        P = np.stack([T[:3, 3] for T in poses])[sel]
        G = np.stack(gt_pos)[sel]
        summary["evaluation"] = {
            "align": f"the map run's own ({alignment['align']}), applied unchanged",
            "n_matched": int(sel.sum()),
            "ate_rmse_m": _ate(P, G, A),
            "stationary_ate_rmse_m": _ate(np.repeat(P[:1], len(P), axis=0), G, A),
        }
    if poses:
        write_trajectory(out / TRAJECTORY_FILE, Trajectory(np.array(stamps), np.stack(poses)), "tum")
        summary["outputs"].insert(0, TRAJECTORY_FILE)
    else:
        (out / TRAJECTORY_FILE).unlink(missing_ok=True)
    tmp = out / f".{SUMMARY_FILE}.tmp"
    tmp.write_text(json.dumps(summary, indent=2) + "\n", encoding="utf-8")
    os.replace(tmp, out / SUMMARY_FILE)
    if not poses:
        raise NotLocalisedError(f"{data}: none of the {n} frames localised in the map {map_path} "
                                f"(every frame 'not localised' in {out / STATUS_FILE}; no trajectory written)")
    return summary


# ----------------------------------------------------------------------------------- extending a map

@dataclass
class MapMerge:
    """A recording merged into a stored map: ``S_MR`` (4x4 Sim(3), recording frame -> map frame;
    rigid for metric maps), the first keyframe localised in the map (``merge_kf_id``, at
    ``merge_time``: frames from then on are reported in the map's frame) and the keyframes that
    support it (``verified`` of ``tried``)."""

    S_MR: np.ndarray
    merge_kf_id: int
    merge_time: float
    verified: int
    consistent: int
    tried: int

    def to_dict(self) -> dict[str, Any]:
        return {"S_MR": self.S_MR.tolist(), "merge_keyframe": self.merge_kf_id, "merge_time": self.merge_time,
                "verified_keyframes": self.verified, "consistent_keyframes": self.consistent,
                "keyframes_tried": self.tried}


def _project_rotation(M: np.ndarray) -> np.ndarray:
    U, _, Vt = np.linalg.svd(M)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    return U @ D @ Vt


def merge_recording(stored: StoredMap, recording: StoredMap, config: LocalizeConfig | None = None,
                    metric: bool | None = None) -> MapMerge | None:
    """Localise the keyframes of a ``recording`` (a stored map of the new run, own frame) in
    ``stored`` one after the other (:class:`MapLocalizer`: retrieval + verification, then tracking),
    and estimate the transform between the two frames from the localised keyframes: the rotation
    from their poses (the map-from-recording rotations within ``merge.max_rotation_deg`` of the
    best-supported one, averaged), the scale (unless ``metric``: by default when both maps are metric,
    ``meta["metric"]``; a monocular map on either side has its own scale) and translation from their
    positions (least squares). None (no merge) with fewer than ``merge.min_keyframes`` consistent."""
    config = config or LocalizeConfig()
    if metric is None:
        metric = stored.metric and recording.metric
    mc = config.merge
    if stored.meta["features"] != recording.meta["features"]:
        logger.warning("map merge: the recording's keyframe features were made with other settings than the "
                       "map's (output.map_features): not merged")
        return None
    localizer = MapLocalizer(stored, config)
    pairs: list[tuple[int, np.ndarray, np.ndarray]] = []
    for k in range(recording.num_keyframes):
        uv, desc, _ = recording.features(k)
        res = localizer.localize_features(uv, desc)
        if res.T_WC is not None:
            pairs.append((k, res.T_WC, recording.T_WC[k]))
    if len(pairs) < mc.min_keyframes:
        logger.info("map merge: %d of %d recording keyframes localised in the map (< %d): not merged",
                    len(pairs), recording.num_keyframes, mc.min_keyframes)
        return None
    R_rec = [T_R[:3, :3] / np.cbrt(np.linalg.det(T_R[:3, :3])) for _, _, T_R in pairs]
    R_MR = np.stack([T_M[:3, :3] @ R.T for (_, T_M, _), R in zip(pairs, R_rec)])
    cos_max = np.cos(np.deg2rad(mc.max_rotation_deg))
    agree = (np.einsum("aij,bij->ab", R_MR, R_MR) - 1.0) / 2.0 >= cos_max   # cos of the angle between each two
    best = int(agree.sum(axis=1).argmax())
    inl = np.flatnonzero(agree[best])
    R = _project_rotation(R_MR[inl].sum(axis=0))
    p_M = np.stack([pairs[i][1][:3, 3] for i in inl])
    p_R = np.stack([pairs[i][2][:3, 3] for i in inl])
    mM, mR = p_M.mean(axis=0), p_R.mean(axis=0)
    q = (p_R - mR) @ R.T
    scale = 1.0 if metric or not np.sum(q * q) > 0 else float(np.sum((p_M - mM) * q) / np.sum(q * q))
    t = mM - scale * R @ mR
    resid = np.linalg.norm(p_M - (scale * p_R @ R.T + t), axis=1)
    extent = max(float(np.linalg.norm(p_M.max(axis=0) - p_M.min(axis=0))), float(np.finfo(float).eps))
    consistent = inl[resid <= mc.max_position_error * extent] if len(inl) > 2 else inl
    if len(consistent) < mc.min_keyframes or scale <= 0:
        logger.info("map merge: %d consistent keyframes (< %d): not merged", len(consistent), mc.min_keyframes)
        return None
    S = np.eye(4)
    S[:3, :3] = scale * R
    S[:3, 3] = t
    first = pairs[int(consistent.min())][0]
    logger.info("map merge: %d of %d recording keyframes localised, %d consistent; merged from keyframe %d "
                "(scale %.4f)", len(pairs), recording.num_keyframes, len(consistent),
                int(recording.kf_ids[first]), scale)
    return MapMerge(S, int(recording.kf_ids[first]), float(recording.kf_timestamps[first]), len(pairs),
                    len(consistent), recording.num_keyframes)


def combine_maps(stored: StoredMap, recording: StoredMap, S_MR: np.ndarray) -> StoredMap:
    """The merged map: ``stored`` and the ``recording``'s keyframes, structure and database moved
    into the map's frame by ``S_MR`` (Sim(3) poses ``S_MR T_WC``: camera points keep the
    recording's units), the recording's keyframe ids after the stored ones."""
    offset = int(stored.kf_ids.max()) + 1 if stored.num_keyframes else 0
    meta = dict(stored.meta)
    meta["recordings"] = int(stored.meta.get("recordings", 1)) + 1
    X_new = recording.points_X_W @ S_MR[:3, :3].T + S_MR[:3, 3]
    return StoredMap(
        meta,
        np.concatenate([stored.kf_ids, recording.kf_ids + offset]),
        np.concatenate([stored.kf_timestamps, recording.kf_timestamps]),
        np.concatenate([stored.kf_frame_index, recording.kf_frame_index]),
        np.concatenate([stored.T_WC, S_MR[None] @ recording.T_WC]),
        np.concatenate([stored.feat_ptr, recording.feat_ptr[1:] + stored.feat_ptr[-1]]),
        np.concatenate([stored.feat_uv, recording.feat_uv]),
        np.concatenate([stored.feat_desc, recording.feat_desc]),
        np.concatenate([stored.feat_X_C, recording.feat_X_C]),
        np.concatenate([stored.bow_ptr, recording.bow_ptr[1:] + stored.bow_ptr[-1]]),
        np.concatenate([stored.bow_words, recording.bow_words]),
        np.concatenate([stored.bow_weights, recording.bow_weights]),
        np.concatenate([stored.points_X_W, X_new]),
        np.concatenate([stored.points_colour, recording.points_colour]),
        np.concatenate([stored.track_point, recording.track_point + len(stored.points_X_W)]),
        np.concatenate([stored.track_kf, recording.track_kf + offset]),
        np.concatenate([stored.track_uv, recording.track_uv]))


def rigid_in_map(S_MR: np.ndarray, T_RC: np.ndarray) -> np.ndarray:
    """(N, 4, 4) rigid camera poses of a recording, ``T_RC`` (N, 4, 4) rigid, in the map's frame:
    rotation ``R R_RC``, position ``s R t_RC + t`` (``S_MR = [[s R, t], [0, 1]]``)."""
    s = float(np.cbrt(np.linalg.det(S_MR[:3, :3])))
    R = S_MR[:3, :3] / s
    out = np.array(T_RC, dtype=np.float64, copy=True).reshape(-1, 4, 4)
    out[:, :3, :3] = R[None] @ out[:, :3, :3]
    out[:, :3, 3] = s * out[:, :3, 3] @ R.T + S_MR[:3, 3]
    return out
