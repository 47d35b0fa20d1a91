"""The monocular pointmap source's per-frame pose measurement (issue 28): corners of the current keyframe,
tracked frame to frame by pyramidal Lucas-Kanade (forward-backward checked), and the pose ``T_CkCf`` by PnP
RANSAC against the keyframe's canonical pointmap, so that the scale is the map's (no per-pair scale).

Why features and not the dense flow: the dense flow's confidence collapses on plain surfaces and over more
than about 25 frames of 7-Scenes, so the flow-based two-view pose (the essential matrix) is missing on
most frames there and projective matching only confirms the prediction (docs/architecture.md section 12).
Corners are where the image has texture, and a track chained frame to frame never spans more than one
frame of motion. A frame whose tracks or PnP fall short is *not* posed here: the frontend relocalises
it or reports the failure (``motion_model``), never the silently confirmed prediction.

New keyframes get their pointmap from :meth:`fgslam.frontends.pointmap.source.TwoViewPointmapSource.predict`
with the measured pose (every pixel triangulated from the dense flow, confidence from the flow and the
triangulation angle); :func:`carry_pointmap` fills the pixels the triangulation leaves unconfident with the
previous keyframe's canonical points seen from the new keyframe (little parallax, plain surfaces).

The patch family's :class:`LKSource` cannot be imported here (the families are independent,
``[tool.importlinter]``); this module calls OpenCV's ``calcOpticalFlowPyrLK`` and ``solvePnPRansac``
directly (no residual or solver of fgslam's own).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import cv2
import numpy as np

from .config import FeaturePoseConfig  # the config: in .config, torch- and OpenCV-free (a run's config loads without them)

logger = logging.getLogger(__name__)

__all__ = ["FeaturePose", "FeaturePoseConfig", "FeatureTracks", "carry_pointmap"]


@dataclass
class FeaturePose:
    """One frame's measurement: ``T_CkCf`` (4x4, the map's scale) or None, PnP inliers, their share of the
    keyframe's corners, and why it failed (empty when measured)."""

    T_CkCf: np.ndarray | None
    inliers: int
    fraction: float
    why: str = ""


class FeatureTracks:
    """Corners of one keyframe tracked through the following frames (module docstring). ``K`` ``(4,)``
    ``[fx, fy, cx, cy]`` of the working resolution."""

    def __init__(self, config: FeaturePoseConfig, K):
        self.config = config
        fx, fy, cx, cy = (float(k) for k in K)
        self.K_matrix = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1]], np.float64)
        self.kf_fid: int | None = None
        self._criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, config.lk_iterations, config.lk_epsilon)
        self._clear()

    def _clear(self) -> None:
        self.X_k = np.zeros((0, 3))  # corners' canonical points in the keyframe's frame
        self.uv_k = np.zeros((0, 2))  # ... and their keyframe pixels
        self.uv = np.zeros((0, 2), np.float32)  # their pixels in the last committed image
        self.prev: np.ndarray | None = None  # the last committed grey image
        self.count = 0  # corners at the keyframe

    def reset(self, kf_fid: int, grey: np.ndarray, X: np.ndarray, C: np.ndarray) -> int:
        """Start from keyframe ``kf_fid``: its grey image ``(H, W)`` and canonical pointmap ``X (H, W, 3)`` /
        ``C (H, W)``; corners where the confidence reaches ``min_point_confidence``. Returns their number."""
        cfg = self.config
        self._clear()
        self.kf_fid = int(kf_fid)
        ok = (C >= cfg.min_point_confidence) & np.isfinite(X).all(-1) & (X[..., 2] > 0)
        mask = ok.astype(np.uint8) * 255
        corners = cv2.goodFeaturesToTrack(grey, cfg.max_corners, cfg.corner_quality, cfg.corner_min_distance,
                                          mask=mask)
        if corners is None:
            logger.info("pointmap features: keyframe %d has no corner with a confident point", kf_fid)
            self.prev = grey
            return 0
        uv = corners.reshape(-1, 2)
        px = np.rint(uv).astype(np.int64)
        px[:, 0] = np.clip(px[:, 0], 0, grey.shape[1] - 1)
        px[:, 1] = np.clip(px[:, 1], 0, grey.shape[0] - 1)
        keep = ok[px[:, 1], px[:, 0]]
        self.X_k = X[px[keep, 1], px[keep, 0]].astype(np.float64)
        self.uv_k = px[keep].astype(np.float64)
        self.uv = px[keep].astype(np.float32)  # tracked from the pixel whose canonical point it carries
        self.prev = grey
        self.count = int(keep.sum())
        logger.debug("pointmap features: keyframe %d: %d corners with a confident point", kf_fid, self.count)
        return self.count

    def _klt(self, a: np.ndarray, b: np.ndarray, uv: np.ndarray, init: np.ndarray | None = None):
        cfg = self.config
        flags = 0 if init is None else cv2.OPTFLOW_USE_INITIAL_FLOW
        guess = uv.copy() if init is None else np.ascontiguousarray(init, np.float32).copy()
        out, st, _ = cv2.calcOpticalFlowPyrLK(a, b, uv.reshape(-1, 1, 2), guess.reshape(-1, 1, 2),
                                              winSize=(cfg.lk_window, cfg.lk_window), maxLevel=cfg.lk_levels,
                                              criteria=self._criteria, flags=flags)
        return out.reshape(-1, 2), st.reshape(-1).astype(bool)

    def track(self, grey: np.ndarray, init_uv: np.ndarray | None = None) -> tuple[FeaturePose, np.ndarray, np.ndarray]:
        """Measure ``T_CkCf`` of the image ``grey`` from the last committed image: KLT both ways, PnP RANSAC.
        ``init_uv``: start of the forward KLT (default: the tracks' last pixels). Returns the measurement,
        the tracks' pixels in ``grey`` and which of them are PnP inliers (for :meth:`commit`)."""
        cfg = self.config
        n = len(self.uv)
        none = np.zeros(n, bool)
        if n < cfg.min_inliers or self.prev is None:
            return FeaturePose(None, 0, 0.0, f"{n} tracks (< {cfg.min_inliers})"), self.uv, none
        fwd, ok_f = self._klt(self.prev, grey, self.uv, init_uv)
        back, ok_b = self._klt(grey, self.prev, fwd, self.uv)
        H, W = grey.shape
        fb = np.linalg.norm(back - self.uv, axis=1)
        inside = (fwd[:, 0] >= 0) & (fwd[:, 0] <= W - 1) & (fwd[:, 1] >= 0) & (fwd[:, 1] <= H - 1)
        good = ok_f & ok_b & inside & np.isfinite(fwd).all(1) & (fb <= cfg.fb_threshold)
        m = int(good.sum())
        if m < cfg.min_inliers:
            return FeaturePose(None, 0, 0.0, f"{m} tracks survive KLT (< {cfg.min_inliers})"), fwd, none
        idx = np.nonzero(good)[0]
        obj, img = self.X_k[idx], fwd[idx].astype(np.float64)
        ok, rvec, tvec, inl = cv2.solvePnPRansac(obj, img, self.K_matrix, None, iterationsCount=cfg.ransac_iterations,
                                                 reprojectionError=cfg.ransac_threshold,
                                                 confidence=cfg.ransac_confidence, flags=cv2.SOLVEPNP_EPNP)
        n_in = 0 if inl is None else len(inl)
        need = max(cfg.min_inliers, int(np.ceil(cfg.min_inlier_ratio * m)))
        if not ok or n_in < need:
            return FeaturePose(None, n_in, 0.0, f"PnP: {n_in} inliers of {m} tracks (< {need})"), fwd, none
        sel = inl[:, 0]
        ok, rvec, tvec = cv2.solvePnP(obj[sel], img[sel], self.K_matrix, None, rvec, tvec, useExtrinsicGuess=True,
                                      flags=cv2.SOLVEPNP_ITERATIVE)
        R = cv2.Rodrigues(rvec)[0]
        if not ok or not np.isfinite(R).all() or not np.isfinite(tvec).all():
            return FeaturePose(None, 0, 0.0, "PnP refinement failed"), fwd, none
        # inliers at the refined pose (the RANSAC set, re-checked)
        Xc = obj @ R.T + tvec[:, 0]
        with np.errstate(divide="ignore", invalid="ignore"):
            proj = Xc[:, :2] / Xc[:, 2:3] * self.K_matrix[[0, 1], [0, 1]] + self.K_matrix[[0, 1], [2, 2]]
        err = np.linalg.norm(proj - img, axis=1)
        inlier = (Xc[:, 2] > 0) & (err <= cfg.ransac_threshold)
        n_in = int(inlier.sum())
        if n_in < need:
            return FeaturePose(None, n_in, 0.0, f"PnP: {n_in} inliers at the refined pose (< {need})"), fwd, none
        T_CfCk = np.eye(4)
        T_CfCk[:3, :3] = R
        T_CfCk[:3, 3] = tvec[:, 0]
        mask = np.zeros(n, bool)
        mask[idx[inlier]] = True
        return FeaturePose(np.linalg.inv(T_CfCk), n_in, n_in / max(self.count, 1)), fwd, mask

    def commit(self, grey: np.ndarray, uv: np.ndarray, keep: np.ndarray) -> None:
        """The measured frame becomes the tracks' last image; only the PnP inliers ``keep`` go on."""
        self.X_k, self.uv_k, self.prev = self.X_k[keep], self.uv_k[keep], grey
        self.uv = np.ascontiguousarray(uv[keep], np.float32)

    def pixels(self, W: int) -> np.ndarray:
        """Flat (row-major) keyframe pixel index of each corner, ``W`` the image width."""
        px = np.rint(self.uv_k).astype(np.int64)
        return px[:, 1] * W + px[:, 0]

    def project(self, T_CkCf: np.ndarray) -> np.ndarray:
        """The corners' pixels in a frame at ``T_CkCf`` (4x4 Sim(3))."""
        T = np.linalg.inv(np.asarray(T_CkCf, np.float64))
        Xc = self.X_k @ T[:3, :3].T + T[:3, 3]
        z = np.where(Xc[:, 2] > 0, Xc[:, 2], np.nan)
        return np.stack((self.K_matrix[0, 0] * Xc[:, 0] / z + self.K_matrix[0, 2],
                         self.K_matrix[1, 1] * Xc[:, 1] / z + self.K_matrix[1, 2]), -1).astype(np.float32)

    def rebase(self, kf_fid: int, kf_grey: np.ndarray, X: np.ndarray, C: np.ndarray, grey: np.ndarray,
               T_CkCf: np.ndarray) -> FeaturePose:
        """After relocalisation on keyframe ``kf_fid`` at ``T_CkCf``: its corners tracked from its image into
        ``grey`` (KLT started at their projections) and the pose measured; committed when measured."""
        self.reset(kf_fid, kf_grey, X, C)
        meas, uv, keep = self.track(grey, self.project(T_CkCf))
        if meas.T_CkCf is not None:
            self.commit(grey, uv, keep)
        return meas


def carry_pointmap(X_k: np.ndarray, C_k: np.ndarray, T_CkCf: np.ndarray, K) -> tuple[np.ndarray, np.ndarray]:
    """Keyframe k's canonical points ``X_k (H, W, 3)`` / ``C_k (H, W)`` seen from a frame f at ``T_CkCf`` (4x4
    Sim(3)): ``(X_f (H, W, 3) in f's frame, C_f (H, W))``, the nearest point per pixel (zero where none)."""
    H, W = C_k.shape
    fx, fy, cx, cy = (float(k) for k in K)
    T = np.linalg.inv(np.asarray(T_CkCf, np.float64))
    ok = (C_k > 0) & np.isfinite(X_k).all(-1)
    P = X_k[ok].astype(np.float64) @ T[:3, :3].T + T[:3, 3]
    c = C_k[ok]
    front = P[:, 2] > 0
    P, c = P[front], c[front]
    u = np.rint(fx * P[:, 0] / P[:, 2] + cx).astype(np.int64)
    v = np.rint(fy * P[:, 1] / P[:, 2] + cy).astype(np.int64)
    inside = (u >= 0) & (u < W) & (v >= 0) & (v < H)
    P, c, u, v = P[inside], c[inside], u[inside], v[inside]
    order = np.argsort(-P[:, 2], kind="stable")  # far first: the nearest point is written last
    X_f = np.zeros((H, W, 3), np.float32)
    C_f = np.zeros((H, W), np.float32)
    X_f[v[order], u[order]] = P[order]
    C_f[v[order], u[order]] = c[order]
    return X_f, C_f
