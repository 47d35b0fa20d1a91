"""The backend: one GTSAM graph per run that every frontend feeds (docs/architecture.md section 8).

:class:`Backend` is the run's :class:`~fgslam.backend.store.GraphStore` (keyframe poses with their
timestamps, other variables, keys attached to keyframes, keyframe callbacks) with its parts:

- ``factors`` (:class:`~fgslam.backend.store.FactorTable`): built-in gtsam factors
  (``BetweenFactorSimilarity3`` loops, plugin priors, IMU...) added by handle with
  :meth:`Backend.add_factor`, each with an ``owner``, until removed (or until a key they touch is
  removed); contributors' measurement blocks (:class:`fgslam.factors.blocks.Block`, e.g. the patch
  frontend's Schur-reduced :class:`~fgslam.frontends.patch.ba.PatchBlock`), set per owner with
  :meth:`Backend.set_blocks`; blocks of different owners on the same keys add up;
- ``gauge`` (:class:`~fgslam.backend.gauge.Gauge`): the gauge factors the backend maintains itself
  (anchor prior, world-scale range, held scales), on keyframes :meth:`Backend.set_gauge` chooses;
- ``optimizer`` (:class:`~fgslam.backend.optimizer.Optimizer`): the solves (window, global,
  pose-graph correction, marginalisation), all through the one LM loop
  (:func:`fgslam.backend.solver.levenberg_marquardt`); the problem of one optimisation is
  :mod:`fgslam.backend.window`'s;
- ``contributors``: the factor plugins' correction route, the contributors (frontends) that take the
  corrections a plugin makes (set with :meth:`Backend.set_contributors` by the plugins' service; loop closure and the IMU keep their own; used by the
  plugins' :func:`fgslam.services.plugins.apply_correction`): each moves its keyframes, whose poses
  live here, and folds the scale into its structure; with none, :meth:`Backend.move_keyframes` sets
  every keyframe pose (scales included: nothing to fold into).

Tangents are gtsam's ``[w, u, lambda]`` with right perturbation.
"""

from __future__ import annotations

from typing import Callable, Iterable, Protocol

import numpy as np

from ..core.lie import sim3_rigid
from .config import BackendConfig
from .gauge import Gauge
from .optimizer import OptimizeReport, Optimizer
from .store import GraphStore, as_similarity3

__all__ = ["Backend", "CorrectionTarget", "KeyframeCorrection", "OptimizeReport", "as_similarity3"]


class KeyframeCorrection(Protocol):
    """A correction of keyframe poses as the backend applies it (:meth:`Backend.move_keyframes`;
    :class:`fgslam.loop.records.PoseCorrection` is one)."""

    def apply_pose(self, kf_id: int, T_WC: np.ndarray) -> tuple[np.ndarray, float]:
        """The corrected (4, 4) pose of keyframe ``kf_id`` from its current ``T_WC``, and its depth factor."""
        ...


class CorrectionTarget(Protocol):
    """A contributor on the factor plugins' correction route (:attr:`Backend.contributors`): it moves its
    keyframes and folds the correction's scale into its structure (the contributor contract's
    :meth:`~fgslam.contracts.contributor.Contributor.apply_correction`)."""

    def apply_correction(self, correction: KeyframeCorrection) -> None: ...


class Backend(GraphStore):
    """The run's store of keyframes and variables (it is one) with its ``factors``, ``gauge`` and
    ``optimizer`` (module docstring); the methods below are theirs, kept on the backend for callers,
    and the map's correction route (``contributors``).

    Typical use by a frontend::

        backend = Backend(BackendConfig())
        backend.add_keyframe(0, T_WC0, t0); backend.add_keyframe(1, T_WC1, t1)
        backend.set_blocks("patch", [PatchBlock(keys=(pose_key(1),), ...)])
        report = backend.optimize_window([1], iterations=2)
        T_WC = backend.pose_matrix(1)
    """

    def __init__(self, config: BackendConfig | None = None):
        super().__init__()
        self.config = config or BackendConfig()
        self.config.validate()
        self.gauge = Gauge(self.config.gauge, self)  # registered first: the default gauge follows every keyframe
        self.optimizer = Optimizer(self.config, self, self.gauge)
        self.contributors: tuple[CorrectionTarget, ...] = ()  # the correction route (module docstring)

    # ------------------------------------------------------------------ factors and blocks
    def add_factor(self, factor, owner: str = "user") -> int:
        """:meth:`FactorTable.add <fgslam.backend.store.FactorTable.add>`: a gtsam factor on existing
        keys; returns its handle."""
        return self.factors.add(factor, owner)

    def remove_factor(self, handle: int) -> None:
        self.factors.remove(handle)

    def factor_handles(self, owner: str) -> list[int]:
        """Handles of the factors ``owner`` added (in order)."""
        return self.factors.handles(owner)

    def factor(self, handle: int):
        return self.factors.factor(handle)

    def set_blocks(self, owner: str, blocks: list) -> None:
        """:meth:`FactorTable.set_blocks <fgslam.backend.store.FactorTable.set_blocks>`: replace
        contributor ``owner``'s blocks."""
        self.factors.set_blocks(owner, blocks)

    def blocks(self, owner: str | None = None) -> list:
        """Blocks of ``owner`` (default: every owner's, in owner order)."""
        return self.factors.blocks(owner)

    def set_gauge(self, anchor: int | None = None, scale_pair: tuple[int, int] | None = None) -> None:
        """:meth:`Gauge.set <fgslam.backend.gauge.Gauge.set>`: the keyframes that carry the gauge factors."""
        self.gauge.set(anchor, scale_pair)

    # ------------------------------------------------------------------ map corrections
    def set_contributors(self, contributors: Iterable[CorrectionTarget]) -> None:
        """The correction route: the contributors that take the corrections a service makes (the
        factor plugins' service sets it before the plugins attach; none: :meth:`move_keyframes`)."""
        self.contributors = tuple(contributors)

    def move_keyframes(self, correction: KeyframeCorrection) -> None:
        """Every keyframe to its corrected pose, scale included (the correction without a contributor
        on the route: nothing folds the scale into structure, which a Sim(3) map absorbs)."""
        for kf_id in self.keyframe_ids:
            T_new, _ = correction.apply_pose(kf_id, self.pose_matrix(kf_id))
            self.set_pose(kf_id, T_new)

    # ------------------------------------------------------------------ solves (Optimizer's)
    def on_window(self, hook: Callable[[list[int]], Iterable[int]]) -> None:
        """:meth:`Optimizer.on_window <fgslam.backend.optimizer.Optimizer.on_window>`."""
        self.optimizer.on_window(hook)

    def optimize_pose(self, blocks, values, key: int, iterations: int | None = None, hold=None,
                      step_tolerance: float | None = None):
        """:meth:`Optimizer.optimize_pose <fgslam.backend.optimizer.Optimizer.optimize_pose>`."""
        return self.optimizer.optimize_pose(blocks, values, key, iterations, hold, step_tolerance)

    def optimize_window(self, free_kf_ids: Iterable[int], iterations: int | None = None,
                        extra_free_keys: Iterable[int] = ()) -> OptimizeReport:
        """:meth:`Optimizer.optimize_window <fgslam.backend.optimizer.Optimizer.optimize_window>`."""
        return self.optimizer.optimize_window(free_kf_ids, iterations, extra_free_keys)

    def write_back_rigid(self, kf_ids: Iterable[int]) -> None:
        """Keyframes ``kf_ids`` set to the rigid part of their poses (a metric map after an optimisation: its
        sensor depths or fixed scale observe no Sim(3) scale, which the solver holds at 1 only to its
        convergence)."""
        for k in kf_ids:
            self.set_pose(k, sim3_rigid(self.pose_matrix(k)))

    def optimize_global(self, iterations: int | None = None) -> OptimizeReport:
        """:meth:`Optimizer.optimize_global <fgslam.backend.optimizer.Optimizer.optimize_global>`."""
        return self.optimizer.optimize_global(iterations)

    def correct_pose_graph(self, kf_ids: Iterable[int] | None = None, iterations: int | None = None) -> dict[int, np.ndarray]:
        """:meth:`Optimizer.correct_pose_graph <fgslam.backend.optimizer.Optimizer.correct_pose_graph>`."""
        return self.optimizer.correct_pose_graph(kf_ids, iterations)

    def pose_graph_problem(self, kf_ids: Iterable[int] | None = None):
        """:meth:`Optimizer.pose_graph_problem <fgslam.backend.optimizer.Optimizer.pose_graph_problem>`."""
        return self.optimizer.pose_graph_problem(kf_ids)

    def marginalize_variables(self, keys: Iterable[int], condition_on: Iterable[int] = (), owner: str = "marginal") -> list[int]:
        """:meth:`Optimizer.marginalize_variables <fgslam.backend.optimizer.Optimizer.marginalize_variables>`."""
        return self.optimizer.marginalize_variables(keys, condition_on, owner)

    def nonlinear_graph(self, include_gauge: bool = True):
        """:meth:`Optimizer.nonlinear_graph <fgslam.backend.optimizer.Optimizer.nonlinear_graph>`."""
        return self.optimizer.nonlinear_graph(include_gauge)

    def cost(self) -> float:
        """:meth:`Optimizer.cost <fgslam.backend.optimizer.Optimizer.cost>`."""
        return self.optimizer.cost()

    def linearize(self):
        """:meth:`Optimizer.linearize <fgslam.backend.optimizer.Optimizer.linearize>`."""
        return self.optimizer.linearize()

    def marginal_covariances(self, kf_ids: list[int] | None = None) -> dict[int, np.ndarray]:
        """:meth:`Optimizer.marginal_covariances <fgslam.backend.optimizer.Optimizer.marginal_covariances>`."""
        return self.optimizer.marginal_covariances(kf_ids)
