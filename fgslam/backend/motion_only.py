"""Motion-only optimisation: one pose against measurement blocks whose other poses stay fixed.

Frame-to-keyframe tracking in the dense and pointmap families (DROID-SLAM section 3.4's motion-only
filler, MASt3R-SLAM section 3.3's tracking) is a small problem: one free ``Similarity3`` key, every other
key of the blocks held at its value. It runs on the one Levenberg-Marquardt loop of
:mod:`fgslam.backend.solver` like every other solve; this module is only the :class:`LMProblem` for it.

A block (:class:`fgslam.factors.blocks.Block`) linearises into pieces over all of its keys; the problem
keeps each piece's rows and columns of the free key (the other keys are fixed, so their tangents are
zero) and hands GTSAM one ``HessianFactor`` on the free key. Blocks with structure (the dense block's
inverse depths) are used with their structure held by the block itself: the caller builds them so.

``hold`` adds information on tangent components of the free key that the measurements do not fix or
that the caller keeps (e.g. the log-scale of a frame tracked against a metric map: ``[0]*6 + [big]``);
an infinite entry fixes its component exactly (its step is zero: SE(3) tracking on a Sim(3) key).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np

from .solver import LMReport, LMSettings, levenberg_marquardt

__all__ = ["MotionOnlyProblem", "optimize_pose"]


class MotionOnlyProblem:
    """An :class:`~fgslam.backend.solver.LMProblem` over the single key ``key`` of ``values`` (the other
    keys of ``blocks`` are read from ``values`` and never change). ``values`` holds the current state."""

    def __init__(self, blocks: Sequence, values, key: int, hold: np.ndarray | None = None):
        self.blocks = list(blocks)
        if not self.blocks:
            raise ValueError("motion-only optimisation needs at least one block")
        for block in self.blocks:
            if int(key) not in (int(k) for k in block.keys):
                raise ValueError(f"a block of the motion-only problem does not touch the free key {int(key)}")
        self.values = values
        self.key = int(key)
        self.dim = int(values.atSimilarity3(self.key).dim()) if values.exists(self.key) else 0
        if self.dim == 0:
            raise ValueError(f"motion-only optimisation: key {int(key)} has no Similarity3 value")
        self.hold = None if hold is None else np.asarray(hold, dtype=np.float64).reshape(self.dim)
        self._diag = np.zeros(self.dim)

    def cost(self) -> float:
        return float(sum(block.cost(self.values) for block in self.blocks))

    def reduced_system(self) -> tuple[np.ndarray, np.ndarray, float]:
        """``(H, g, c)`` of the free key at the current state (fixed keys' rows and columns dropped)."""
        d = self.dim
        H = np.zeros((d, d))
        g = np.zeros(d)
        c = 0.0
        for block in self.blocks:
            for piece in block.linearize(self.values):
                keys = [int(k) for k in piece.keys]
                c += float(piece.c)
                if self.key not in keys:
                    continue
                at = keys.index(self.key) * d
                H += piece.H[at:at + d, at:at + d]
                g += piece.g[at:at + d]
        if self.hold is not None:
            fixed = np.isinf(self.hold)
            H = H + np.diag(np.where(fixed, 0.0, self.hold))
            if fixed.any():  # exactly fixed components: their step is zero
                H[fixed, :] = 0.0
                H[:, fixed] = 0.0
                H[fixed, fixed] = 1.0
                g[fixed] = 0.0
        return H, g, c

    def linearize(self):
        import gtsam  # deferred: gtsam

        H, g, c = self.reduced_system()
        self._diag = np.diag(H).copy()
        gfg = gtsam.GaussianFactorGraph()
        gfg.push_back(gtsam.HessianFactor(self.key, H, -g, c))
        return gfg

    def hessian_diagonal(self) -> dict[int, np.ndarray]:
        return {self.key: self._diag}

    def trial(self, delta) -> tuple[float, object]:
        values = self.values.retract(delta)
        cost = float(sum(block.cost(values) for block in self.blocks))
        return (cost if np.isfinite(cost) else float("inf")), values

    def accept(self, state, cost: float) -> float:
        self.values = state
        return cost


@dataclass
class MotionOnlyResult:
    """The optimised ``values`` (only ``key`` changed) and the LM report."""

    values: object
    report: LMReport


def optimize_pose(blocks: Sequence, values, key: int, settings: LMSettings,
                  hold: np.ndarray | None = None) -> MotionOnlyResult:
    """Minimise the blocks' cost over ``key`` alone, starting from ``values`` (module docstring)."""
    problem = MotionOnlyProblem(blocks, values, key, hold)
    report = levenberg_marquardt(problem, settings)
    return MotionOnlyResult(problem.values, report)
