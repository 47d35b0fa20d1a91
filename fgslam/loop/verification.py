"""Geometric verification of a retrieved keyframe pair for the classical loop closer
(:mod:`fgslam.loop.closure`), and the ORB matching and triangulation it is built from.

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
unsupported Sim(3)s reject the pair with a logged reason (:class:`~fgslam.loop.records.Verification`).

Conventions: poses are camera-to-world Sim(3) ``T_WC`` (4x4 ``[[s R, t], [0, 1]]``); camera-frame
points are in the units of their keyframe's pose; intrinsics ``K = (fx, fy, cx, cy)`` of an
undistorted pinhole image.
"""

from __future__ import annotations

import functools
import math
import threading
from dataclasses import dataclass
from typing import Callable

import numpy as np
import torch

from ..core.lie import sim3_matrix_parts
from .bow import KeyframeFeatures
from .records import Verification, VerificationConfig
from .sim3_estimation import estimate_sim3_ransac

_NO_MATCH = np.iinfo(np.int32).max  # Hamming distance of a missing (masked-out) neighbour


@dataclass
class LoopKeyframe:
    """A keyframe handed to the closer: its image until described, then its ORB features."""

    kf_id: int
    timestamp: float
    image: np.ndarray | None              # dropped once described
    K: np.ndarray                         # (4,) fx, fy, cx, cy
    neighbours: tuple[int, ...]
    features: KeyframeFeatures | None = None


# ----------------------------------------------------------------------------------- geometry

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
    import cv2  # deferred: cv2

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


def solve_pnp(X: np.ndarray, uv: np.ndarray, K: np.ndarray, reprojection_px: float, iterations: int,
              confidence: float, min_inliers: int, refine: bool = True) -> tuple[np.ndarray, np.ndarray] | None:
    """Pose of a camera that sees the points ``X`` (N, 3, in a frame A) at pixels ``uv`` (N, 2):
    ``(T_AC 4x4 rigid camera-to-A, inlier indices)`` by EPnP RANSAC (``refine``: then refined on the
    inliers by Levenberg-Marquardt), or None with fewer than ``min_inliers`` inliers. ``K`` = (fx, fy, cx, cy)."""
    import cv2  # deferred: cv2

    if len(X) < max(min_inliers, 4):
        return None
    Kmat = np.array([[K[0], 0.0, K[2]], [0.0, K[1], K[3]], [0.0, 0.0, 1.0]])
    obj = np.ascontiguousarray(X, dtype=np.float64)
    img = np.ascontiguousarray(uv, dtype=np.float64)
    found, rvec, tvec, inl = cv2.solvePnPRansac(obj, img, Kmat, None, iterationsCount=iterations,
                                                reprojectionError=reprojection_px, confidence=confidence,
                                                flags=cv2.SOLVEPNP_EPNP)
    if not found or inl is None or len(inl) < min_inliers:
        return None
    inl = inl.reshape(-1)
    if refine:
        rvec, tvec = cv2.solvePnPRefineLM(obj[inl], img[inl], Kmat, None, rvec, tvec)
    R_CA = cv2.Rodrigues(rvec)[0]                                  # X_C = R X_A + t
    T_AC = np.eye(4)
    T_AC[:3, :3] = R_CA.T
    T_AC[:3, 3] = -R_CA.T @ tvec.reshape(3)
    return T_AC, inl


def match_cosine(desc_a: np.ndarray, desc_b: np.ndarray, min_cossim: float,
                 allowed: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Float-descriptor matches ``(ia, ib)`` (XFeat's rule): mutual nearest neighbours by cosine
    similarity (dot product of unit descriptors) among ``allowed`` (Na, Nb) pairs, similarity >
    ``min_cossim``."""
    empty = np.zeros(0, np.int64), np.zeros(0, np.int64)
    if len(desc_a) == 0 or len(desc_b) == 0:
        return empty
    sim = np.asarray(desc_a, np.float32) @ np.asarray(desc_b, np.float32).T
    if allowed is not None:
        sim = np.where(allowed, sim, -np.inf)
    ab = np.argmax(sim, axis=1)
    ba = np.argmax(sim, axis=0)
    rows = np.arange(len(desc_a))
    ok = (ba[ab] == rows) & (sim[rows, ab] > min_cossim)
    ia = np.flatnonzero(ok)
    return ia, ab[ia]


def descriptor_matcher(cfg) -> Callable[..., tuple[np.ndarray, np.ndarray]]:
    """``match(desc_a, desc_b, allowed=None) -> (ia, ib)`` for the closer's features
    (``cfg``: :class:`~fgslam.loop.records.LoopClosureConfig`): ORB by Hamming distance with the
    ratio test (``verification``), XFeat by mutual cosine nearest neighbours (``features.xfeat``)."""
    if cfg.features.kind == "xfeat":
        return functools.partial(match_cosine, min_cossim=cfg.features.xfeat.min_cossim)
    return functools.partial(match_descriptors, max_hamming=cfg.verification.max_hamming,
                             ratio=cfg.verification.ratio)


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


# ----------------------------------------------------------------------------------- the verifier

class Verifier:
    """Geometric verification of keyframe pairs (module docstring) on the closer's keyframe table.

    ``keyframes`` (id -> :class:`LoopKeyframe`) is read behind ``lock`` (the closer adds to it from its
    caller's thread); ``metric``: rigid fits (``s = 1``) instead of Sim(3) ones."""

    def __init__(self, cfg: VerificationConfig, keyframes: dict[int, LoopKeyframe], lock: threading.RLock,
                 metric: bool, match: Callable[..., tuple[np.ndarray, np.ndarray]] | None = None):
        self.cfg = cfg
        # descriptor matching (descriptor_matcher); default: ORB with this config's Hamming and ratio
        self.match = match or functools.partial(match_descriptors, max_hamming=cfg.max_hamming, ratio=cfg.ratio)
        self.metric = metric
        self._keyframes = keyframes
        self._lock = lock

    def neighbour_ids(self, kf: LoopKeyframe, order: list[int]) -> list[int]:
        """Triangulation partners: the caller's neighbours, then temporal ones (-1, +1, -2, +2, ...)."""
        out = [n for n in kf.neighbours if n != kf.kf_id]
        pos = order.index(kf.kf_id) if kf.kf_id in order else -1
        if pos >= 0:
            for step in range(1, len(order)):
                for p in (pos - step, pos + step):
                    if 0 <= p < len(order):
                        out.append(order[p])
                if len(out) >= 2 * self.cfg.max_neighbours:
                    break
        seen, unique = set(), []
        for n in out:
            if n not in seen:
                seen.add(n)
                unique.append(n)
        return unique

    def triangulate(self, kf: LoopKeyframe, order: list[int], poses: dict,
                     subset: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """3-D points (N, 3) in camera ``kf`` for its N features and a validity mask. Only the
        features ``subset`` (indices; None: all) are triangulated, each with the first of up to
        ``max_neighbours`` neighbours (:meth:`neighbour_ids`) that triangulates it."""
        vc = self.cfg
        feats = kf.features
        X = np.full((len(feats.uv), 3), np.nan)
        ok = np.zeros(len(feats.uv), bool)
        todo = np.arange(len(feats.uv)) if subset is None else np.unique(subset)
        tried = 0
        for n_id in self.neighbour_ids(kf, order):
            if tried >= vc.max_neighbours or todo.size == 0:
                break
            with self._lock:
                nb = self._keyframes.get(n_id)
            if nb is None or nb.features is None or len(nb.features.uv) == 0 or n_id not in poses:
                continue
            tried += 1
            T_CaCb = np.linalg.inv(poses[kf.kf_id]) @ poses[n_id]
            allowed = epipolar_mask(feats.uv[todo], nb.features.uv, kf.K, nb.K, T_CaCb, vc.max_epipolar_px)
            ia, ib = self.match(feats.descriptors[todo], nb.features.descriptors, allowed=allowed)
            if len(ia) == 0:
                continue
            Xa, good = triangulate_pair(feats.uv[todo[ia]], nb.features.uv[ib], kf.K, nb.K, T_CaCb,
                                        vc.min_parallax_deg, vc.max_reprojection_px)
            X[todo[ia[good]]] = Xa[good]
            ok[todo[ia[good]]] = True
            todo = todo[~ok[todo]]
        return X, ok

    def verify(self, q: LoopKeyframe, c: LoopKeyframe, order: list[int], poses: dict, bow_score: float) -> Verification:
        vc = self.cfg
        qf, cf = q.features, c.features

        def reject(reason: str, **kw) -> Verification:
            return Verification(q.kf_id, c.kf_id, False, reason, bow_score=bow_score, **kw)

        if qf is None or cf is None or len(qf.uv) == 0 or len(cf.uv) == 0:
            return reject("no features")
        ia, ib = self.match(qf.descriptors, cf.descriptors)
        if len(ia) < vc.min_matches:
            return reject(f"{len(ia)} descriptor matches < {vc.min_matches}", n_matches=len(ia))
        X_q, ok_q = self.triangulate(q, order, poses, ia)
        X_c, ok_c = self.triangulate(c, order, poses, ib)
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
