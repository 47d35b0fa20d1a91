"""One optimisation of a snapshot of keyframe poses and measurement blocks, away from the run's
backend: a frontend's global optimisation solved in the background (a worker process or thread of the
loop service, :mod:`fgslam.services.proximity`) while tracking goes on with the run's backend.

:func:`optimize_snapshot` builds a scratch :class:`~fgslam.backend.graph.Backend` of the snapshot's
keyframes (same ``map`` config), chooses its gauge, sets the blocks per owner and runs
:meth:`~fgslam.backend.graph.Backend.optimize_window` over the free keyframes: the same problem,
solver loop and elimination as the run's backend would use on the same keyframes and blocks. Built-in
factors of the run's backend (plugin priors, loop Sim(3) edges) are not part of a snapshot; its result
reaches the run's backend as a pose correction at the loop service's safe point. The function is
top-level and its arguments plain data, so it pickles into a worker process.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .config import BackendConfig
from .graph import Backend

__all__ = ["SnapshotProblem", "optimize_snapshot"]


@dataclass
class SnapshotProblem:
    """Keyframes ``kf_ids`` (in order) at poses ``T_WC`` (K, 4, 4 Sim(3)) with ``timestamps``; the
    blocks of each owner (their keys among the keyframes' pose keys); ``free`` the keyframes optimised
    (the others held); the gauge (``anchor`` keyframe held at its pose, ``scale_pair`` the world-scale
    range between two keyframes; None: none); ``iterations`` LM iterations."""

    config: BackendConfig
    kf_ids: list[int]
    T_WC: np.ndarray
    timestamps: list[float]
    blocks: dict[str, list]
    free: list[int]
    iterations: int
    anchor: int | None = None
    scale_pair: tuple[int, int] | None = None


def optimize_snapshot(problem: SnapshotProblem) -> np.ndarray:
    """Optimise the snapshot (module docstring); returns the (K, 4, 4) poses of ``problem.kf_ids``
    (the blocks' structure is updated in place, as by the run's backend)."""
    backend = Backend(problem.config)
    for kf, T, t in zip(problem.kf_ids, problem.T_WC, problem.timestamps):
        backend.add_keyframe(int(kf), np.asarray(T, np.float64), float(t))
    backend.set_gauge(anchor=problem.anchor, scale_pair=problem.scale_pair)
    for owner, blocks in problem.blocks.items():
        backend.set_blocks(owner, blocks)
    backend.optimize_window(problem.free, problem.iterations)
    return np.stack([backend.pose_matrix(kf) for kf in problem.kf_ids])
