"""Depth alignment: a pose-only block of point-to-plane residuals between two depth images.

KinectFusion (Newcombe et al., ISMAR 2011, section 3.5) and ElasticFusion track RGB-D frames by the
geometry of their depth alone. Here the same term is a measurement block
(:class:`fgslam.factors.blocks.Block`, no structure) on two Sim(3) pose keys that the backend optimises
beside the visual blocks, in motion-only tracking and in the window:

- each image's depth is turned into a :class:`DepthSurface`: per pyramid level (every ``stride``-th
  pixel, coarse to fine), its camera-frame vertices and unit normals (central differences of the
  vertices, pointing to the camera; invalid at depth discontinuities and missing depth);
- the frame f's vertices ``X_f`` are moved into the reference k by ``T_CkCf = T_WCk^-1 T_WCf`` and
  projected into k's level (projective data association, nearest pixel); a pair counts when k has a
  vertex ``X_k`` there, ``|T_CkCf X_f - X_k| <= max_distance`` (wider on coarser levels) and the normals agree within
  ``max_normal_angle_deg``;
- residual ``r = n_k . (T_CkCf X_f - X_k)`` (:func:`point_to_plane`, with its analytic Jacobians
  w.r.t. both poses), whitened by the depth noise ``sigma_z = sigma * z_f^2`` (structured-light and
  stereo depth: the error grows with the square of the depth) and robustified by ``robust``;
- the cost is consistent across re-associations: a frame vertex that lands on a reference vertex
  but fails the gates costs what a residual at the gate costs, so moving a point out of the gate
  never lowers the cost; a vertex that lands outside k's view or on a pixel without depth costs
  nothing (charging it would pull the pose towards more overlap).

Re-association at every linearisation and cost evaluation makes one Levenberg-Marquardt iteration one
ICP iteration. :meth:`DepthAlignBlock.at_level` gives the block of a coarser level (coarse-to-fine).
The block is evaluated in numpy on a few thousand points per level: at that size the fixed cost per
array operation dominates, and numpy's is several times lower than torch's.

Tangent conventions as in :mod:`fgslam.factors.reprojection`: right perturbation ``T <- T Exp(xi)``,
gtsam ``Similarity3`` order ``xi = [w, u, lambda]``.

Degeneracy: :func:`depth_constraint` counts the rigid-motion directions that the pairs constrain:
the eigenvectors of the frame pose's 6x6 information, with rotations expressed as displacements at the
median depth (so that rotations and translations compare in metres), whose standard deviation is below
``max_direction_sigma``. Three non-parallel planes (two walls and a floor) constrain all six; a single
plane constrains three (two tilts and the distance). Other measurements of the frame (a few image
tracks) can add their information to the count.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from ..core.errors import DataError
from ..core.lie import gtsam_matrix
from .blocks import LinearPiece, weighted_piece
from .configs import DepthAlignConfig  # the config: torch-free (a run's config loads without torch)
from .robust import kernel_cost, kernel_weight
from .schur import POSE_DIM

__all__ = ["DepthAlignBlock", "DepthAlignConfig", "DepthConstraint", "DepthSurface", "depth_constraint",
           "point_to_plane", "relative_transform"]

RIGID_DIM = 6  # rotation and translation of a Sim(3) tangent [w, u, lambda]


@dataclass(frozen=True)
class SurfaceLevel:
    """One pyramid level: ``(h, w)`` grid, vertices and unit normals ``(h * w, 3)`` in the camera frame
    (zero where invalid), ``valid`` ``(h * w,)``, intrinsics ``K = [fx, fy, cx, cy]`` of the grid
    (numpy float64 / bool)."""

    shape: tuple[int, int]
    vertices: np.ndarray
    normals: np.ndarray
    valid: np.ndarray
    K: tuple[float, float, float, float]

    @property
    def points(self) -> tuple[np.ndarray, np.ndarray]:
        """The valid vertices and their normals, ``(M, 3)`` each."""
        return self.vertices[self.valid], self.normals[self.valid]


@dataclass(frozen=True)
class DepthSurface:
    """The depth image of one camera as surface levels (coarse to fine, ``config.strides``), and the
    pixel step of each."""

    levels: tuple[SurfaceLevel, ...]
    strides: tuple[int, ...]

    @staticmethod
    def from_depth(depth: np.ndarray, K, config: DepthAlignConfig) -> DepthSurface:
        """Surface of a metric depth image ``depth`` ``(H, W)`` (0, NaN or out of range: no depth)
        seen with intrinsics ``K = [fx, fy, cx, cy]`` (pixel centres at integer coordinates)."""
        depth = np.asarray(depth)
        if depth.ndim != 2:
            raise DataError(f"depth alignment: a depth image must be 2-D, got shape {depth.shape}")
        from .depth_align_jit import surface_rows  # deferred: numba (compiled kernel, core/jit.py)

        fx, fy, cx, cy = (float(k) for k in K)
        levels = []
        strides = config.strides(depth.shape[1])
        for stride in strides:
            off = stride // 2
            # grid pixel (a, b) is image pixel (off + stride b, off + stride a)
            Kl = (fx / stride, fy / stride, (cx - off) / stride, (cy - off) / stride)
            V, N, n_ok = surface_rows(depth, off, stride, np.array(Kl), float(config.min_depth),
                                      float(config.max_depth), float(config.max_discontinuity * stride))
            levels.append(SurfaceLevel(V.shape[:2], V.reshape(-1, 3), N.reshape(-1, 3), n_ok.reshape(-1), Kl))
        return DepthSurface(tuple(levels), strides)


@dataclass(frozen=True)
class DepthConstraint:
    """What the depth pairs constrain: ``pairs`` associated (``fraction`` of the frame's vertices),
    ``directions`` of the six rigid ones constrained, the scaled information's eigenvalues (ascending),
    and whether that is all six with enough pairs (``ok``)."""

    pairs: int
    fraction: float
    directions: int
    eigenvalues: np.ndarray
    ok: bool


def depth_constraint(H_rigid: np.ndarray, pairs: int, points: int, median_depth: float,
                     config: DepthAlignConfig) -> DepthConstraint:
    """Constrained rigid directions of a 6x6 pose information ``H_rigid`` (tangent ``[w, u]``) from
    ``pairs`` pairs of ``points`` frame vertices at ``median_depth`` (module docstring)."""
    D = np.diag([max(median_depth, config.min_depth)] * 3 + [1.0] * 3)
    Hs = np.linalg.inv(D) @ H_rigid @ np.linalg.inv(D)
    eig = np.linalg.eigvalsh(0.5 * (Hs + Hs.T))
    directions = int((eig * config.max_direction_sigma ** 2 > 1.0).sum())
    fraction = pairs / points if points else 0.0
    ok = directions == RIGID_DIM and pairs >= config.min_pairs and fraction >= config.min_pair_fraction
    return DepthConstraint(int(pairs), fraction, directions, eig, ok)


def relative_transform(T_WCk: np.ndarray, T_WCf: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(A, b)`` of ``T_CkCf = T_WCk^-1 T_WCf`` acting as ``Y = A X + b`` (``A`` = scaled rotation),
    from two 4x4 Sim(3) matrices ``[[s R, t], [0, 1]]``."""
    sR_k, t_k = T_WCk[:3, :3], T_WCk[:3, 3]
    s_k2 = float(np.cbrt(np.linalg.det(sR_k))) ** 2
    return sR_k.T @ T_WCf[:3, :3] / s_k2, sR_k.T @ (T_WCf[:3, 3] - t_k) / s_k2


def point_to_plane(A: np.ndarray, X_f: np.ndarray, Y: np.ndarray, X_k: np.ndarray, n_k: np.ndarray,
                   jacobians: bool = True) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
    """Point-to-plane residuals ``r = n_k . (Y - X_k)`` ``(N,)`` of frame points ``X_f`` ``(N, 3)`` at
    ``Y = T_CkCf X_f`` (``A``: the scaled rotation of ``T_CkCf``, :func:`relative_transform`) against
    reference points ``X_k`` with unit normals ``n_k``, and (with ``jacobians``) ``J_k``, ``J_f``
    ``(N, 7)``: the Jacobians w.r.t. right perturbations of ``T_WCk`` and ``T_WCf``::

        dY/dxi_f = A [-[X_f]x, I, X_f]   ->  J_f = [X_f x a, a, a . X_f]  with  a = A^T n_k
        dY/dxi_k = [[Y]x, -I, -Y]         ->  J_k = [n_k x Y, -n_k, -n_k . Y]
    """
    from .depth_align_jit import point_to_plane_rows  # deferred: numba (compiled kernel, core/jit.py)

    f64 = lambda x: np.ascontiguousarray(x, dtype=np.float64)  # noqa: E731 - one dtype for the kernel
    r, J = point_to_plane_rows(f64(A), f64(X_f), f64(Y), f64(X_k), f64(n_k), bool(jacobians))
    if not jacobians:
        return r, None, None
    return r, J[:, :POSE_DIM], J[:, POSE_DIM:]


class DepthAlignBlock:
    """Point-to-plane depth alignment of frame ``key_f`` against reference ``key_k`` (module docstring):
    the backend's block contract with ``has_structure = False``, one linear piece over ``(key_k, key_f)``.
    ``level``: the pyramid level used (default the finest)."""

    has_structure = False

    def __init__(self, key_k: int, key_f: int, reference: DepthSurface, frame: DepthSurface,
                 config: DepthAlignConfig | None = None, level: int = -1):
        self.config = config or DepthAlignConfig()
        if int(key_k) == int(key_f):
            raise DataError(f"depth alignment: a block joins key {int(key_k)} to itself")
        if reference.strides != frame.strides:
            raise DataError("depth alignment: the two surfaces have different pyramids")
        self.key_k, self.key_f = int(key_k), int(key_f)
        self.keys = (self.key_k, self.key_f)
        self.reference, self.frame = reference, frame
        self.level = level % len(reference.levels)
        self._ref = reference.levels[self.level]
        self._X_f, self._n_f = frame.levels[self.level].points
        z = self._X_f[:, 2]
        self._sqrt_w = 1.0 / np.maximum(z, self.config.min_depth) ** 2  # sigma_z = sigma z^2
        self._cos = float(np.cos(np.radians(self.config.max_normal_angle_deg)))
        strides = reference.strides
        self.max_distance = self.config.max_distance * strides[self.level] / strides[-1]
        rb = self.config.robust
        gate = torch.from_numpy(self._sqrt_w * (self.max_distance / self.config.sigma))
        self._gate = gate.numpy()
        self._gate_cost = kernel_cost(gate, rb.kind, rb.delta).numpy()  # the cost of a vertex that fails the gates
        self._memo: tuple | None = None  # (A, b, jacobians, terms) of the last evaluation

    def at_level(self, level: int) -> DepthAlignBlock:
        """The same block on pyramid ``level`` (0: coarsest)."""
        return DepthAlignBlock(self.key_k, self.key_f, self.reference, self.frame, self.config, level)

    @property
    def num_points(self) -> int:
        """Frame vertices with a normal on this level."""
        return int(self._X_f.shape[0])

    def _transform(self, values) -> tuple[np.ndarray, np.ndarray]:
        return relative_transform(gtsam_matrix(values.atSimilarity3(self.key_k)), gtsam_matrix(values.atSimilarity3(self.key_f)))

    def _terms(self, values, jacobians: bool):
        """Whitened residuals, kernel costs (gate cost for seen unpaired vertices), IRLS weights (0
        unpaired) and the whitened Jacobian ``(M, 14)`` (or None) of the paired vertices, the pair mask."""
        cfg = self.config
        rb = cfg.robust
        A, b = self._transform(values)
        memo = self._memo
        if memo is not None and (memo[2] or not jacobians) and np.array_equal(memo[0], A) and np.array_equal(memo[1], b):
            return memo[3]  # the same poses as the last evaluation (a cost, then a linearisation there)
        from .depth_align_jit import associate_rows  # deferred: numba (compiled kernel, core/jit.py)

        ref = self._ref
        seen, paired, r_all, J_all = associate_rows(
            A, b, self._X_f, self._n_f, ref.vertices, ref.normals, ref.valid, np.asarray(ref.K, dtype=np.float64),
            np.asarray(ref.shape, dtype=np.int64), float(cfg.min_depth), float(self.max_distance),
            self._cos * float(np.cbrt(np.linalg.det(A))), bool(jacobians))
        r = r_all[paired]
        scale = self._sqrt_w[paired] / cfg.sigma
        e = r * scale
        norms = torch.from_numpy(np.minimum(np.abs(e), self._gate[paired]))
        cost = float(kernel_cost(norms, rb.kind, rb.delta).sum()) + float(self._gate_cost[seen & ~paired].sum())
        weight = kernel_weight(norms, rb.kind, rb.delta).numpy()
        J = None
        if jacobians:
            J = J_all[paired] * scale[:, None]
        self._memo = (A, b, jacobians, (e, cost, weight, J, paired))
        return e, cost, weight, J, paired

    def cost(self, values, structure=None) -> float:
        """GTSAM-convention cost ``sum rho(e)`` at ``values`` (re-associated; no structure). The Jacobian
        comes with it (the compiled association takes no longer for it), so that a linearisation at the
        same poses, as the window's LM does right after its first cost, reuses the association."""
        return self._terms(values, True)[1]

    def linearize(self, values) -> list[LinearPiece]:
        """One :class:`LinearPiece` over ``(key_k, key_f)`` at ``values`` (re-associated)."""
        e, cost, weight, J, _ = self._terms(values, True)
        return [weighted_piece(self.keys, J[:, None, :], e[:, None], weight[:, None], cost)]

    def constraint(self, values, H_other: np.ndarray | None = None) -> DepthConstraint:
        """What the pairs at ``values`` constrain of the frame's rigid motion (:func:`depth_constraint`),
        together with ``H_other``, the 6x6 information of other measurements on the frame's pose
        (rotation, translation; e.g. the few image measurements of a texture-poor frame)."""
        e, _, weight, J, paired = self._terms(values, True)
        piece = weighted_piece(self.keys, J[:, None, :], e[:, None], weight[:, None], 0.0)
        H_f = piece.H[POSE_DIM:POSE_DIM + RIGID_DIM, POSE_DIM:POSE_DIM + RIGID_DIM]
        if H_other is not None:
            H_f = H_f + H_other
        z = self._X_f[paired, 2]
        median = float(np.median(z)) if z.size else self.config.min_depth
        return depth_constraint(H_f, int(paired.sum()), self.num_points, median, self.config)
