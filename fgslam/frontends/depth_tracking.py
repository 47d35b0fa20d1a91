"""Depth alignment for every family's RGB-D tracking (:mod:`fgslam.factors.depth_align`).

Where a sensor depth is valid, RGB-D tracking must not depend on image texture alone. A frontend holds
one :class:`DepthTracking`: it turns a frame's depth into a surface once (kept with the frame), builds
the point-to-plane blocks between two frames' pose keys, aligns a new frame's predicted pose to its
reference by depth alone (coarse to fine, through the backend's motion-only solve, rigid), and says
whether the depth constrains all six degrees of freedom of a frame (so that a frame without usable image
measurements but with three non-parallel planes in view is still tracked, and a single wall is not).
The blocks go to the backend beside the family's visual blocks (``backend.set_blocks``), in the window
as in tracking; the frontend never solves anything itself.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Callable, Sequence

import numpy as np

from ..core.config import MAX_ITERATIONS, MAX_WINDOW, ranged
from ..factors.configs import MAX_LEVELS, DepthAlignConfig

if TYPE_CHECKING:  # the alignment pulls torch and gtsam: imported in the functions that run it
    from ..factors.depth_align import DepthAlignBlock, DepthConstraint, DepthSurface

logger = logging.getLogger(__name__)

__all__ = ["DepthTracking", "DepthTrackingConfig", "pose_information"]

#: Hold of a rigid (metric RGB-D) pose in the motion-only solve: rotation and translation free, scale fixed.
RIGID_HOLD = np.array([0.0] * 6 + [np.inf])


def pose_information(blocks, values, key: int) -> np.ndarray:
    """6x6 information (rotation, translation) on pose ``key`` of the measurement ``blocks`` at ``values``
    (their linear pieces' diagonal blocks of that key, summed): what a frame's image measurements add to
    its depth's count of constrained directions (:meth:`DepthTracking.hold`)."""
    from ..factors.depth_align import RIGID_DIM  # deferred: torch (DepthTrackingConfig loads without it)
    from ..factors.schur import POSE_DIM  # deferred: torch (DepthTrackingConfig loads without it)

    H = np.zeros((RIGID_DIM, RIGID_DIM))
    for block in blocks:
        for piece in block.linearize(values):
            keys = [int(k) for k in piece.keys]
            if int(key) in keys:
                at = keys.index(int(key)) * POSE_DIM
                H += np.asarray(piece.H)[at:at + RIGID_DIM, at:at + RIGID_DIM]
    return H


@dataclass
class DepthTrackingConfig:
    """Depth alignment in RGB-D tracking (module docstring); off by default."""

    enabled: bool = False  # RGB-D: point-to-plane depth blocks in tracking and in the window
    prealign: bool = False  # align a new frame's predicted pose to its reference by depth before measuring the image
    prealign_iterations: int = ranged(6, ge=1, le=MAX_ITERATIONS)  # LM iterations per pyramid level of every depth alignment (prealign, and a frame the image lost)
    window_pairs: int = ranged(0, ge=0, le=MAX_WINDOW)  # depth blocks in the window: between the newest this many pairs of consecutive frames (0: every pair that touches a free frame)
    window_level: int = ranged(1, ge=0, le=MAX_LEVELS - 1)  # pyramid level of the window's depth blocks (0: coarsest; past the finest: the finest)
    align: DepthAlignConfig = field(default_factory=DepthAlignConfig)  # the residual, pyramid and gates

    def validate(self) -> None:
        self.align.validate()


class DepthTracking:
    """Surfaces, blocks and checks of depth alignment for one frontend (module docstring).

    Args:
        config: the frontend's depth-tracking section.
        backend: the run's backend (motion-only alignment of a new frame).
        active: the sensor has depth (RGB-D); otherwise the alignment stays off whatever the config says.
    """

    def __init__(self, config: DepthTrackingConfig, backend, active: bool = True):
        config.validate()
        self.config = config
        self.backend = backend
        self.active = bool(active)
        self.K: tuple[float, float, float, float] | None = None
        if config.enabled and not self.active:
            logger.warning("depth_align.enabled has no effect without depth images (sensor mode is not rgbd)")

    @property
    def enabled(self) -> bool:
        """Depth alignment is on (configured, and the sensor has depth)."""
        return self.config.enabled and self.active

    def set_intrinsics(self, K) -> None:
        """``K = [fx, fy, cx, cy]`` of the depth images (registered to the tracked image)."""
        self.K = tuple(float(k) for k in np.asarray(K, dtype=np.float64).reshape(-1)[:4])

    def surface(self, depth: np.ndarray | None) -> DepthSurface | None:
        """The surface of a depth image (None without depth or when disabled)."""
        from ..factors.depth_align import DepthSurface  # deferred: torch (DepthTrackingConfig loads without it)

        if not self.enabled or depth is None or self.K is None:
            return None
        return DepthSurface.from_depth(depth, self.K, self.config.align)

    def block(self, key_k: int, key_f: int, surface_k: DepthSurface, surface_f: DepthSurface,
              window: bool = False) -> DepthAlignBlock:
        """Point-to-plane block aligning ``key_f``'s surface to ``key_k``'s: on the finest level, or
        with ``window`` on the window's level (``window_level``)."""
        from ..factors.depth_align import DepthAlignBlock  # deferred: torch (DepthTrackingConfig loads without it)

        level = min(self.config.window_level, len(surface_k.levels) - 1) if window else -1
        return DepthAlignBlock(key_k, key_f, surface_k, surface_f, self.config.align, level)

    @staticmethod
    def _values(block: DepthAlignBlock, T_WCk: np.ndarray, T_WCf: np.ndarray):
        import gtsam  # deferred: gtsam

        from ..core.lie import gtsam_sim3  # deferred: torch (DepthTrackingConfig loads without it)

        values = gtsam.Values()
        values.insert(block.key_k, gtsam_sim3(T_WCk))
        values.insert(block.key_f, gtsam_sim3(T_WCf))
        return values

    def check(self, block: DepthAlignBlock, T_WCk: np.ndarray, T_WCf: np.ndarray,
              H_image: np.ndarray | None = None) -> DepthConstraint:
        """What the block's pairs constrain with the two frames at ``T_WCk`` and ``T_WCf``, together with
        ``H_image`` (6x6 information of the frame's image measurements on its rotation and translation)."""
        return block.constraint(self._values(block, T_WCk, T_WCf), H_image)

    def align(self, block: DepthAlignBlock, T_WCk: np.ndarray, T_WCf: np.ndarray) -> tuple[np.ndarray, DepthConstraint]:
        """The frame's pose ``T_WCf`` (4x4, the block's ``key_f``) aligned by depth alone to the reference
        at ``T_WCk`` (held), coarse to fine and rigid (the backend's motion-only solve), and what the depth
        constrains there. A pose that does not come out finite is returned unchanged."""
        from ..core.lie import gtsam_matrix  # deferred: torch (DepthTrackingConfig loads without it)

        values = self._values(block, T_WCk, T_WCf)
        for level in range(len(block.reference.levels)):
            result = self.backend.optimize_pose([block.at_level(level)], values, block.key_f,
                                                iterations=self.config.prealign_iterations, hold=RIGID_HOLD)
            values = result.values
        T = gtsam_matrix(values.atSimilarity3(block.key_f))
        if not np.isfinite(T).all():
            logger.warning("depth alignment gave a non-finite pose; the prediction is kept")
            return T_WCf, block.constraint(values)
        return T, block.constraint(values)

    def hold(self, block: DepthAlignBlock, T_WCk: np.ndarray, T_WCf: np.ndarray,
             H_image: np.ndarray | Callable[[np.ndarray], np.ndarray] | None = None) -> tuple[np.ndarray, DepthConstraint]:
        """A frame whose image measurements fell short: its pose ``T_WCf`` (the prediction) aligned by
        depth to the reference at ``T_WCk`` (:meth:`align`), and what the depth constrains there with the
        frame's image information ``H_image`` at the aligned pose (a 6x6 matrix, a callable of the aligned
        4x4 pose, or None: depth alone; :meth:`check`). When that is all six rigid directions
        (``constraint.ok``) the frame is tracked by depth; otherwise it fails as without depth."""
        T, constraint = self.align(block, T_WCk, T_WCf)
        if callable(H_image):
            H_image = H_image(T)
        if H_image is not None:
            constraint = self.check(block, T_WCk, T, H_image)
        return T, constraint

    def chain(self, frames: Sequence[tuple[int, DepthSurface | None]], free: set[int] | None = None,
              limit: int | None = None, usable: Callable[[int, int], bool] | None = None) -> list[DepthAlignBlock]:
        """The window's depth blocks along ``frames`` (``(key, surface)`` in time order): one between each
        two consecutive frames that both have a surface and at least one of whose keys is in ``free``
        (None: every pair), the newest ``limit`` of them (None: ``window_pairs``; 0: all), oldest first.
        ``usable(key_a, key_b)``: a further condition on a pair (a pair that fails it counts as none)."""
        limit = self.config.window_pairs if limit is None else limit
        frames = list(frames)
        blocks = []
        for (key_a, surf_a), (key_b, surf_b) in zip(reversed(frames[:-1]), reversed(frames[1:])):
            if limit and len(blocks) == limit:
                break
            if surf_a is None or surf_b is None or (free is not None and key_a not in free and key_b not in free):
                continue
            if usable is None or usable(key_a, key_b):
                blocks.append(self.block(key_a, key_b, surf_a, surf_b, window=True))
        return blocks[::-1]
