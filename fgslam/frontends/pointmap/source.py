"""Two-view pointmap sources of the pointmap frontend (MASt3R-SLAM section 3.1).

For images i and j a source returns a :class:`PointmapPair`: the pointmaps ``X_i^i`` (i's pixels in
i's camera frame) and ``X_j^i`` (j's pixels in i's frame), ``X_j^j`` (j's pixels in its own frame),
confidences ``C_i`` / ``C_j`` in [0, 1] (0: no point), per-pixel descriptors ``D_i`` / ``D_j`` with
confidences ``Q_i`` / ``Q_j`` (:mod:`.descriptors`), and the relative pose ``T_CiCj`` that links
``X_j^j`` to ``X_j^i`` when the source knows one. Per-frame work (descriptors, depth) is cached by
:meth:`PointmapSource.add_frame` and dropped by :meth:`PointmapSource.remove_frame`.

Built-in sources (no learned weights):

- :class:`DepthPointmapSource` (``rgbd``): ``X^i`` from the sensor depth (confidence 1 where the depth
  is valid).
- :class:`StereoPointmapSource` (``stereo``): the depth from OpenCV's semi-global block matching on the
  rectified pair (confidence 1 where the disparity is valid and above ``min_disparity``).
- :class:`TwoViewPointmapSource` (``mono``): dense flow both ways, the essential matrix (RANSAC), the
  relative pose, and every pixel triangulated (midpoint of the two rays) with confidence
  ``flow confidence x (1 - exp(-(angle / angle_sigma)^2))`` from the triangulation angle; the pair's
  scale is arbitrary (the median depth of ``X_i^i`` is set to ``median_depth``), as with MASt3R. Given
  ``T_CiCj`` (the pose the monocular features measured, :mod:`.features`) it triangulates with that pose
  instead, in the caller's scale.

For the metric sources ``X_j^i = T_CiCj X_j^j`` with ``T_CiCj`` given by the caller (e.g. the tracker's
prediction) or estimated by PnP (RANSAC) on the dense flow's confident correspondences with i's
depth. The dense flow is :class:`fgslam.frontends.flow.DenseFlowSource` at full resolution
(stride 1: no pooling), with its forward-backward, photometric and aperture confidences.

- :class:`Mast3rPointmapSource` (``mast3r``): the slot of MASt3R itself; it needs the ``mast3r``
  package and a checkpoint, neither shipped: a ConfigError / DataError naming
  ``pointmap.source.checkpoint`` and the built-in alternatives otherwise. fgslam downloads nothing.

Pairs with no overlap, failed pose estimates, pure rotation (mono: no triangulation angle) give a
pair with zero confidence where nothing was measured and a logged warning, never an exception.
"""

from __future__ import annotations

import abc
import logging
from dataclasses import dataclass

import cv2
import numpy as np

from ...core.arrays import min_rows
from ...core.errors import ConfigError, DataError
from ..checkpoints import LearnedSlot, require_checkpoint
from ..flow import DenseFlowSource
# the configs: in .config, torch- and OpenCV-free (a run's config loads without them)
from .config import PointmapSourceConfig, RelativePoseConfig, StereoMatchConfig, TriangulationConfig
from .descriptors import dense_descriptors

logger = logging.getLogger(__name__)

__all__ = ["DepthPointmapSource", "Mast3rPointmapSource", "PointmapPair", "PointmapSource", "PointmapSourceConfig",
           "RelativePoseConfig", "StereoMatchConfig", "StereoPointmapSource", "TriangulationConfig",
           "TwoViewPointmapSource", "make_pointmap_source", "unproject_depth"]


@dataclass
class PointmapPair:
    """What a source predicts for images i and j (module docstring). Pointmaps ``(H, W, 3)`` float32
    (zero where the confidence is 0), confidences ``(H, W)`` float32 in [0, 1], descriptors
    ``(H, W, d)`` float32 unit norm, ``T_CiCj`` ``(4, 4)`` (a Sim(3) for ``mono``: its translation is in
    the pair's scale) or None."""

    i: int
    j: int
    X_i_in_i: np.ndarray
    X_j_in_i: np.ndarray
    X_j_in_j: np.ndarray
    C_i: np.ndarray
    C_j: np.ndarray
    D_i: np.ndarray
    D_j: np.ndarray
    Q_i: np.ndarray
    Q_j: np.ndarray
    T_CiCj: np.ndarray | None = None


def unproject_depth(depth: np.ndarray, K) -> np.ndarray:
    """``(H, W, 3)`` camera-frame points of a z-depth map (pixel centres at integers)."""
    fx, fy, cx, cy = (float(k) for k in K)
    H, W = depth.shape
    u, v = np.meshgrid(np.arange(W, dtype=np.float32), np.arange(H, dtype=np.float32))
    z = depth.astype(np.float32)
    return np.stack(((u - cx) / fx * z, (v - cy) / fy * z, z), -1)


def _transform(T: np.ndarray, X: np.ndarray) -> np.ndarray:
    """``T X`` for points ``(..., 3)`` as nine float32 multiply-adds (numpy's ``(N, 3) @ (3, 3)`` matmul
    took ~100x longer: measured 177 ms for 320x240 points under load)."""
    M = np.asarray(T, np.float32)
    x, y, z = X[..., 0], X[..., 1], X[..., 2]
    return np.stack([M[r, 0] * x + M[r, 1] * y + M[r, 2] * z + M[r, 3] for r in range(3)], -1)


def _grey(image: np.ndarray, frame_id: int, what: str = "image") -> np.ndarray:
    image = np.asarray(image)
    if image.ndim == 3 and image.shape[2] in (3, 4):
        image = cv2.cvtColor(np.clip(image, 0, 255).astype(np.uint8), cv2.COLOR_RGB2GRAY)
    if image.ndim != 2:
        raise DataError(f"pointmap source: frame {frame_id} {what} must be (H, W) grey or (H, W, 3), got {image.shape}")
    if image.dtype != np.uint8:
        image = np.clip(np.rint(image), 0, 255).astype(np.uint8)
    return np.ascontiguousarray(image)


@dataclass
class _Frame:
    grey: np.ndarray
    D: np.ndarray
    Q: np.ndarray
    X: np.ndarray | None = None  # (H, W, 3) metric points (rgbd, stereo)
    C: np.ndarray | None = None  # (H, W) their confidence


class PointmapSource(abc.ABC):
    """Where the pointmaps come from (module docstring)."""

    name: str = ""

    @abc.abstractmethod
    def add_frame(self, frame_id: int, image: np.ndarray, depth: np.ndarray | None = None,
                  right: np.ndarray | None = None) -> None:
        """Cache per-frame work: ``image`` grey (or RGB) ``(H, W)``; ``depth`` z-depth in metres (0 / NaN:
        no reading; rgbd); ``right`` the rectified right image (stereo)."""

    @abc.abstractmethod
    def remove_frame(self, frame_id: int) -> None:
        """Drop what :meth:`add_frame` cached."""

    @abc.abstractmethod
    def predict(self, i: int, j: int, T_CiCj: np.ndarray | None = None) -> PointmapPair:
        """Pointmaps of the pair (i, j) (frames added before). ``T_CiCj`` ``(4, 4)``: a known relative pose
        (metric sources use it instead of estimating one; others ignore it)."""


class _GeometricSource(PointmapSource):
    """Shared machinery of the built-in sources: frames, descriptors, dense flow, relative pose."""

    def __init__(self, K, config: PointmapSourceConfig | None = None):
        self.config = config or PointmapSourceConfig()
        K = tuple(float(k) for k in K)
        if len(K) != 4 or not all(np.isfinite(K)) or K[0] <= 0 or K[1] <= 0:
            raise ConfigError(f"pointmap source: K must be finite [fx, fy, cx, cy] with fx, fy > 0, got {K}")
        self.K = K
        self._frames: dict[int, _Frame] = {}
        self._shape: tuple[int, int] | None = None
        self._flow = DenseFlowSource(self.config.pose.flow, stride=1)

    @property
    def K_matrix(self) -> np.ndarray:
        fx, fy, cx, cy = self.K
        return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])

    def _add(self, frame_id: int, image: np.ndarray) -> _Frame:
        grey = _grey(image, frame_id)
        if self._shape is not None and grey.shape != self._shape:
            raise DataError(f"pointmap source: frame {frame_id} is {grey.shape[1]}x{grey.shape[0]}, earlier frames "
                            f"{self._shape[1]}x{self._shape[0]}")
        self._shape = grey.shape
        D, Q = dense_descriptors(grey, self.config.descriptor)
        self._flow.add_frame(int(frame_id), grey)
        frame = _Frame(grey, D, Q)
        self._frames[int(frame_id)] = frame
        return frame

    def remove_frame(self, frame_id: int) -> None:
        self._frames.pop(int(frame_id), None)
        self._flow.remove_frame(int(frame_id))

    def _frame(self, frame_id: int) -> _Frame:
        try:
            return self._frames[int(frame_id)]
        except KeyError:
            raise DataError(f"pointmap source: frame {frame_id} was not added (add_frame) or was removed") from None

    def _flows(self, edges: list[tuple[int, int]]) -> list[tuple[np.ndarray, np.ndarray]]:
        """Per edge: the target pixel of every pixel ``(H, W, 2)`` and its confidence ``(H, W)`` (the
        smaller of the two axes' confidences)."""
        H, W = self._shape
        nan = np.full((len(edges), H, W, 2), np.nan)
        return [(rev.target, min_rows(rev.weight)) for rev in self._flow.revise(edges, nan)]

    def _overlap(self, i: int, j: int, *confs: np.ndarray) -> bool:
        """Enough pixels with a confident flow in every given direction (else: logged, no overlap)."""
        cfg = self.config.pose
        frac = min(float((c >= cfg.min_flow_confidence).mean()) for c in confs)
        if frac < cfg.min_overlap:
            logger.warning("pointmap source: pair (%d, %d): %.1f %% of the pixels have a confident flow (< %.1f %%); "
                           "no overlap", i, j, 100 * frac, 100 * cfg.min_overlap)
            return False
        return True

    def _samples(self, conf: np.ndarray, extra: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Row and column indices of one confident pixel per ``sample_stride`` cell (the cell's top-left)."""
        s = self.config.pose.sample_stride
        ok = conf >= self.config.pose.min_flow_confidence
        if extra is not None:
            ok &= extra
        sub = np.zeros_like(ok)
        sub[::s, ::s] = True
        return np.nonzero(ok & sub)

    def pnp_pose(self, i: int, j: int, X_i_in_i: np.ndarray, C_i: np.ndarray) -> np.ndarray | None:
        """``T_CiCj`` (4x4, in the units of ``X_i_in_i``) by PnP RANSAC on the dense flow i -> j: the points
        ``X_i_in_i (H, W, 3)`` of i where ``C_i > 0`` and their flow targets in j; None (logged) without
        enough overlap or inliers. Frames i and j must have been added. The metric sources' pose when the
        caller gives none; the pointmap frontend's monocular tracking of frames with too little parallax
        for a two-view pointmap (against the keyframe's canonical pointmap)."""
        self._frame(i), self._frame(j)
        return self._metric_pose(_Frame(None, None, None, np.asarray(X_i_in_i), np.asarray(C_i)), i, j)

    def _metric_pose(self, fi: _Frame, i: int, j: int) -> np.ndarray | None:
        """``T_CiCj`` by PnP RANSAC: i's metric points and their flow targets in j."""
        cfg = self.config.pose
        (target, conf), = self._flows([(i, j)])
        if not self._overlap(i, j, conf):
            return None
        H, W = self._shape
        inside = ((target[..., 0] >= 0) & (target[..., 0] <= W - 1) & (target[..., 1] >= 0)
                  & (target[..., 1] <= H - 1))
        rows, cols = self._samples(conf, (fi.C > 0) & inside)
        if rows.size < cfg.min_inliers:
            logger.warning("pointmap source: pair (%d, %d): %d confident correspondences, fewer than %d; no pose",
                           i, j, rows.size, cfg.min_inliers)
            return None
        obj = fi.X[rows, cols].astype(np.float64)
        img = target[rows, cols].astype(np.float64)
        ok, rvec, tvec, inliers = cv2.solvePnPRansac(
            obj, img, self.K_matrix, None, iterationsCount=cfg.ransac_iterations,
            reprojectionError=cfg.ransac_threshold, confidence=cfg.ransac_confidence, flags=cv2.SOLVEPNP_EPNP)
        n_in = 0 if inliers is None else len(inliers)
        if not ok or n_in < max(cfg.min_inliers, cfg.min_inlier_ratio * rows.size):
            logger.warning("pointmap source: pair (%d, %d): PnP found %d inliers (< %d); no pose", i, j, n_in,
                           cfg.min_inliers)
            return None
        inl = inliers[:, 0]
        ok, rvec, tvec = cv2.solvePnP(obj[inl], img[inl], self.K_matrix, None, rvec, tvec, useExtrinsicGuess=True,
                                      flags=cv2.SOLVEPNP_ITERATIVE)
        T_CjCi = np.eye(4)
        T_CjCi[:3, :3] = cv2.Rodrigues(rvec)[0]
        T_CjCi[:3, 3] = tvec[:, 0]
        return np.linalg.inv(T_CjCi)

    def _metric_pair(self, i: int, j: int, T_CiCj: np.ndarray | None) -> PointmapPair:
        fi, fj = self._frame(i), self._frame(j)
        if T_CiCj is None:
            T_CiCj = self._metric_pose(fi, i, j)
        else:
            T_CiCj = np.asarray(T_CiCj, np.float64)
            if T_CiCj.shape != (4, 4) or not np.isfinite(T_CiCj).all():
                raise DataError(f"pointmap source: T_CiCj must be a finite 4x4 matrix, got shape {T_CiCj.shape}")
        if T_CiCj is None:
            X_j_in_i = np.zeros_like(fj.X)
            C_j = np.zeros_like(fj.C)
        else:
            X_j_in_i = _transform(T_CiCj, fj.X) * (fj.C > 0)[..., None]
            C_j = fj.C
        return PointmapPair(i, j, fi.X, X_j_in_i, fj.X, fi.C, C_j, fi.D, fj.D, fi.Q, fj.Q, T_CiCj)

    def predict(self, i: int, j: int, T_CiCj: np.ndarray | None = None) -> PointmapPair:
        return self._metric_pair(i, j, T_CiCj)

    def _depth_frame(self, frame: _Frame, depth: np.ndarray) -> None:
        depth = np.asarray(depth, np.float32)
        ok = np.isfinite(depth) & (depth > self.config.min_depth)
        depth = np.where(ok, depth, 0.0).astype(np.float32)
        frame.X = unproject_depth(depth, self.K)
        frame.C = ok.astype(np.float32)


class DepthPointmapSource(_GeometricSource):
    """Pointmaps from RGB-D depth (module docstring)."""

    name = "rgbd"

    def add_frame(self, frame_id, image, depth=None, right=None) -> None:
        if depth is None:
            raise DataError(f"pointmap source rgbd: frame {frame_id} has no depth image (pointmap.source.kind=rgbd "
                            "needs an RGB-D dataset)")
        depth = np.asarray(depth)
        if depth.shape != np.asarray(image).shape[:2]:
            raise DataError(f"pointmap source rgbd: frame {frame_id} depth {depth.shape} and image "
                            f"{np.asarray(image).shape[:2]} differ in size")
        frame = self._add(frame_id, image)
        self._depth_frame(frame, depth)


class StereoPointmapSource(_GeometricSource):
    """Pointmaps from the rectified stereo pair by OpenCV SGBM (module docstring); ``baseline`` in metres."""

    name = "stereo"

    def __init__(self, K, baseline: float, config: PointmapSourceConfig | None = None):
        super().__init__(K, config)
        if not (np.isfinite(baseline) and baseline > 0):
            raise ConfigError(f"pointmap source stereo: the baseline must be positive, got {baseline!r}")
        self.baseline = float(baseline)
        sc = self.config.stereo
        nd = int(np.ceil(sc.num_disparities / 16.0) * 16)
        bs = sc.block_size | 1
        self._sgbm = cv2.StereoSGBM_create(
            minDisparity=0, numDisparities=nd, blockSize=bs, P1=8 * bs * bs, P2=32 * bs * bs,
            disp12MaxDiff=sc.disp12_max_diff, uniquenessRatio=sc.uniqueness, speckleWindowSize=sc.speckle_window,
            speckleRange=sc.speckle_range, mode=cv2.STEREO_SGBM_MODE_SGBM_3WAY)

    def depth(self, left: np.ndarray, right: np.ndarray) -> np.ndarray:
        """z-depth (m) of the left image from SGBM (0 where the disparity is invalid)."""
        disp = self._sgbm.compute(left, right).astype(np.float32) / 16.0
        ok = disp >= self.config.stereo.min_disparity
        return np.where(ok, self.K[0] * self.baseline / np.where(ok, disp, 1.0), 0.0).astype(np.float32)

    def add_frame(self, frame_id, image, depth=None, right=None) -> None:
        if right is None:
            raise DataError(f"pointmap source stereo: frame {frame_id} has no right image (pointmap.source.kind=stereo "
                            "needs a stereo dataset)")
        frame = self._add(frame_id, image)
        right = _grey(right, frame_id, "right image")
        if right.shape != frame.grey.shape:
            raise DataError(f"pointmap source stereo: frame {frame_id} right image {right.shape} and left "
                            f"{frame.grey.shape} differ in size")
        self._depth_frame(frame, self.depth(frame.grey, right))


class TwoViewPointmapSource(_GeometricSource):
    """Monocular two-view reconstruction (module docstring)."""

    name = "mono"

    def add_frame(self, frame_id, image, depth=None, right=None) -> None:
        self._add(frame_id, image)

    def triangulate(self, uv_i: np.ndarray, uv_j: np.ndarray, T_CiCj: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Pixels ``uv_i`` of i and ``uv_j`` of j (``(N, 2)``) with the pose ``T_CiCj`` (4x4 Sim(3)): the points
        in i's frame (units of ``T_CiCj``'s translation; zero where invalid) and their confidence
        ``1 - exp(-(angle / angle_sigma)^2)`` (0 where invalid): the same triangulation as :meth:`predict`."""
        T = np.asarray(T_CiCj, np.float64)
        s = float(np.cbrt(np.linalg.det(T[:3, :3])))
        X, angle, ok = self._triangulate(np.asarray(uv_i, np.float64), np.asarray(uv_j, np.float64), T[:3, :3] / s,
                                         T[:3, 3])
        sig = np.deg2rad(self.config.triangulation.angle_sigma_deg)
        return X, np.where(ok, 1 - np.exp(-(angle / sig) ** 2), 0.0)

    def _triangulate(self, uv_a: np.ndarray, uv_b: np.ndarray, R_CiCj: np.ndarray, c_j: np.ndarray):
        """Midpoint triangulation of pixels ``uv_a`` of i and ``uv_b`` of j (both ``(..., 2)``); returns the
        point in frame i, the triangulation angle (rad) and validity (in front of both cameras)."""
        fx, fy, cx, cy = self.K
        a = np.stack(((uv_a[..., 0] - cx) / fx, (uv_a[..., 1] - cy) / fy, np.ones(uv_a.shape[:-1])), -1)
        b_j = np.stack(((uv_b[..., 0] - cx) / fx, (uv_b[..., 1] - cy) / fy, np.ones(uv_b.shape[:-1])), -1)
        b = b_j @ R_CiCj.T
        aa, bb, ab = (a * a).sum(-1), (b * b).sum(-1), (a * b).sum(-1)
        ac, bc = a @ c_j, b @ c_j
        det = aa * bb - ab * ab
        with np.errstate(divide="ignore", invalid="ignore"):
            s = (ac * bb - ab * bc) / det
            t = (ab * ac - aa * bc) / det
            X = 0.5 * (s[..., None] * a + c_j + t[..., None] * b)
            angle = np.arccos(np.clip(ab / np.sqrt(aa * bb), -1.0, 1.0))
        ok = np.isfinite(X).all(-1) & (s > 0) & (t > 0) & (det > 0)
        return np.where(ok[..., None], X, 0.0), np.where(ok, angle, 0.0), ok

    def predict(self, i: int, j: int, T_CiCj: np.ndarray | None = None) -> PointmapPair:
        """The two-view pair (module docstring); with ``T_CiCj`` (4x4 Sim(3) in the caller's map scale: the
        pose measured by :mod:`.features`) the essential matrix is skipped, every pixel is triangulated
        with that pose and the pair is in the caller's scale (no median-depth normalisation)."""
        cfg, tc = self.config.pose, self.config.triangulation
        fi, fj = self._frame(i), self._frame(j)
        H, W = self._shape
        (t_ij, c_ij), (t_ji, c_ji) = self._flows([(i, j), (j, i)])
        empty = np.zeros((H, W, 3), np.float32)
        zero = np.zeros((H, W), np.float32)
        rows, cols = self._samples(c_ij)
        pose = None
        known = T_CiCj is not None
        if known:
            T_CiCj = np.asarray(T_CiCj, np.float64)
            if T_CiCj.shape != (4, 4) or not np.isfinite(T_CiCj).all():
                raise DataError(f"pointmap source: T_CiCj must be a finite 4x4 matrix, got shape {T_CiCj.shape}")
            s = float(np.cbrt(np.linalg.det(T_CiCj[:3, :3])))
            R_CiCj = T_CiCj[:3, :3] / s
            pose = (R_CiCj.T, -R_CiCj.T @ T_CiCj[:3, 3])  # (R_CjCi, t_CjCi): c_j below is T_CiCj's translation
        elif not self._overlap(i, j, c_ij, c_ji):
            pass
        elif rows.size >= cfg.min_inliers:
            pts_i = np.stack((cols, rows), -1).astype(np.float64)
            pts_j = t_ij[rows, cols].astype(np.float64)
            E, mask = cv2.findEssentialMat(pts_i, pts_j, self.K_matrix, cv2.RANSAC, cfg.ransac_confidence,
                                           cfg.ransac_threshold)
            if E is not None and E.shape == (3, 3):
                n_in, R, t, mask = cv2.recoverPose(E, pts_i, pts_j, self.K_matrix, mask=mask)
                need = max(cfg.min_inliers, int(np.ceil(cfg.min_inlier_ratio * rows.size)))
                if n_in >= need:
                    pose = (R, t[:, 0])
                else:
                    logger.warning("pointmap source mono: pair (%d, %d): %d pose inliers (< %d)", i, j, n_in, need)
        else:
            logger.warning("pointmap source mono: pair (%d, %d): %d confident correspondences (< %d)", i, j,
                           rows.size, cfg.min_inliers)
        if pose is None:
            return PointmapPair(i, j, empty, empty, empty.copy(), zero, zero.copy(), fi.D, fj.D, fi.Q, fj.Q, None)
        R_CjCi, t_CjCi = pose
        R_CiCj = R_CjCi.T
        c_j = -R_CiCj @ t_CjCi  # j's centre in frame i (|t| = 1)
        v, u = np.mgrid[0:H, 0:W].astype(np.float64)
        grid = np.stack((u, v), -1)
        X_i, ang_i, ok_i = self._triangulate(grid, t_ij, R_CiCj, c_j)
        X_j, ang_j, ok_j = self._triangulate(t_ji, grid, R_CiCj, c_j)
        sig = np.deg2rad(tc.angle_sigma_deg)
        C_i = np.where(ok_i, c_ij * (1 - np.exp(-(ang_i / sig) ** 2)), 0.0)
        C_j = np.where(ok_j, c_ji * (1 - np.exp(-(ang_j / sig) ** 2)), 0.0)
        good = C_i > 0.5
        if good.sum() < cfg.min_inliers:
            logger.warning("pointmap source mono: pair (%d, %d): too little parallax (%d confident points); "
                           "zero confidence", i, j, int(good.sum()))
            return PointmapPair(i, j, empty, empty, empty.copy(), zero, zero.copy(), fi.D, fj.D, fi.Q, fj.Q,
                                T_CiCj if known else None)
        scale = 1.0 if known else tc.median_depth / float(np.median(X_i[good][:, 2]))
        X_i *= scale
        X_j *= scale
        c_j = c_j * scale
        limit = tc.max_depth_ratio * (float(np.median(X_i[good][:, 2])) if known else tc.median_depth)
        C_i = np.where(X_i[..., 2] <= limit, C_i, 0.0)
        C_j = np.where(X_j[..., 2] <= limit, C_j, 0.0)
        X_i = np.where((C_i > 0)[..., None], X_i, 0.0)
        X_j = np.where((C_j > 0)[..., None], X_j, 0.0)
        T = np.eye(4)
        T[:3, :3] = R_CiCj
        T[:3, 3] = c_j
        if known:
            T = T_CiCj  # X_j^j in j's own units (its Sim(3) scale)
        X_j_in_j = _transform(np.linalg.inv(T), X_j.astype(np.float32)) * (C_j > 0)[..., None]
        return PointmapPair(i, j, X_i.astype(np.float32), X_j.astype(np.float32), X_j_in_j.astype(np.float32),
                            C_i.astype(np.float32), C_j.astype(np.float32), fi.D, fj.D, fi.Q, fj.Q, T)


class Mast3rPointmapSource(PointmapSource):
    """Slot of MASt3R's two-view network (module docstring): needs the ``mast3r`` package and a checkpoint;
    fgslam ships neither and downloads nothing."""

    name = "mast3r"

    def __init__(self, checkpoint: str | None):
        require_checkpoint(LearnedSlot("MASt3R", "a MASt3R checkpoint", "pointmap.source.kind=mast3r",
                                       "pointmap.source.checkpoint", "pointmap.source.kind=rgbd, stereo or mono",
                                       package="mast3r"), checkpoint)

    def add_frame(self, frame_id, image, depth=None, right=None):  # pragma: no cover - construction always fails
        raise NotImplementedError

    def remove_frame(self, frame_id):  # pragma: no cover
        raise NotImplementedError

    def predict(self, i, j, T_CiCj=None):  # pragma: no cover
        raise NotImplementedError


def make_pointmap_source(config: PointmapSourceConfig, K, baseline: float | None = None) -> PointmapSource:
    """The pointmap source selected by ``config.kind`` (``baseline`` in metres: stereo only)."""
    if config.kind == "rgbd":
        return DepthPointmapSource(K, config)
    if config.kind == "stereo":
        if baseline is None:
            raise ConfigError("pointmap.source.kind=stereo needs a stereo rig (the dataset has no right camera)")
        return StereoPointmapSource(K, baseline, config)
    if config.kind == "mono":
        return TwoViewPointmapSource(K, config)
    if config.kind == "mast3r":
        return Mast3rPointmapSource(config.checkpoint)
    if config.kind == "auto":
        raise ConfigError("pointmap.source.kind=auto is resolved from the sensor mode by the pointmap frontend; "
                          "give rgbd, stereo, mono or mast3r here")
    raise ConfigError(f"pointmap.source.kind: unknown source {config.kind!r} (expected rgbd, stereo, mono or mast3r)")
