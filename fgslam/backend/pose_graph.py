"""Sim(3) pose graphs: the pieces every pose graph of the backend is built from, and the loop-closure
graph of :func:`fgslam.loop.pose_graph.optimize_sim3_pose_graph`.

:func:`anchor_prior` (the 7-dof prior that fixes the gauge) and :func:`diagonal_model` (diagonal
sigmas, optionally inside a robust kernel) serve both :meth:`fgslam.backend.optimizer.Optimizer.pose_graph_problem`
and :class:`LoopPoseGraph`; both solve with the one LM loop (:func:`fgslam.backend.solver.levenberg_marquardt`),
the backend's optionally with iSAM2 steps (:class:`PoseGraphIsam2`).
"""

from __future__ import annotations

import time
from typing import Literal

import numpy as np

from ..core.errors import OptimizationError
from ..factors.sim3 import SIM3_DOF, make_between_factors
from ..core.lie import Sim3
from .solver import LMSettings, NonlinearProblem, levenberg_marquardt

RobustKernel = Literal["none", "huber", "cauchy"]


def anchor_prior(key: int, pose, sigma: float):
    """``PriorFactorSimilarity3`` holding ``key`` at the ``gtsam.Similarity3`` ``pose`` (isotropic
    ``sigma`` on all 7 tangent directions)."""
    import gtsam  # deferred: gtsam

    return gtsam.PriorFactorSimilarity3(key, pose, gtsam.noiseModel.Isotropic.Sigma(SIM3_DOF, sigma))


def diagonal_model(sigmas: np.ndarray, kernel: RobustKernel = "none", kernel_param: float = 0.0):
    """Diagonal noise model of ``sigmas``, inside gtsam's ``kernel`` m-estimator (threshold
    ``kernel_param``) unless ``kernel`` is ``"none"``."""
    import gtsam  # deferred: gtsam

    base = gtsam.noiseModel.Diagonal.Sigmas(np.asarray(sigmas, dtype=np.float64))
    if kernel == "none":
        return base
    estimator = {"huber": gtsam.noiseModel.mEstimator.Huber, "cauchy": gtsam.noiseModel.mEstimator.Cauchy}
    return gtsam.noiseModel.Robust.Create(estimator[kernel].Create(kernel_param), base)


class PoseGraphIsam2:
    """iSAM2 step provider of a pose graph (only built-in factors: iSAM2 relinearises them itself)."""

    def __init__(self, graph, values):
        import gtsam  # deferred: gtsam

        params = gtsam.ISAM2Params()
        params.setRelinearizeThreshold(0.0)
        params.relinearizeSkip = 1
        self.isam = gtsam.ISAM2(params)
        self.graph, self.values = graph, values
        self.started = False
        self.problem = None

    def bind(self, problem):
        self.problem = problem
        return self

    def __call__(self, gfg):
        if not self.started:
            self.isam.update(self.graph, self.values)
            self.started = True
        else:
            self.isam.update()
        current = self.problem.values if self.problem is not None else self.values
        return current.localCoordinates(self.isam.calculateEstimate())


class LoopPoseGraph:
    """Keyframes ``0..K-1`` (gtsam keys = indices) with a prior on the first, smoothness between
    consecutive ones (measured by the poses before the correction), optionally a log-scale prior on
    every other one, and candidate loop factors (plain and robust) switched on per :meth:`solve`.

    Args:
        T_WC: (K,) keyframe poses before the correction.
        loop_i, loop_j, T_CiCj: the candidate loops (L,) (``X_Ci = T_CiCj X_Cj``).
        smooth_sigmas: (K-1, 7) sigmas of the smoothness terms.
        loop_sigmas: (7,) sigmas of a loop.
        prior_sigma: sigma of the prior on keyframe 0.
        hold_scale_sigma: log-scale sigma of the per-keyframe scale priors; None: none.
        kernel, kernel_param: robust kernel of the robust loop factors.
    """

    def __init__(self, T_WC: Sim3, loop_i, loop_j, T_CiCj: Sim3, smooth_sigmas: np.ndarray, loop_sigmas,
                 prior_sigma: float, hold_scale_sigma: float | None, kernel: RobustKernel, kernel_param: float):
        import gtsam  # deferred: gtsam

        self.K = T_WC.shape[0]
        self.loop_i, self.loop_j, self.T_CiCj = loop_i, loop_j, T_CiCj
        self.initial = gtsam.Values()
        for k, pose in enumerate(T_WC.to_gtsam()):
            self.initial.insert(k, pose)
        self.base = gtsam.NonlinearFactorGraph()
        self.base.add(anchor_prior(0, T_WC[0].to_gtsam(), prior_sigma))
        if hold_scale_sigma is not None:  # log-scale only: zero precision on rotation and translation
            precisions = np.zeros(SIM3_DOF)
            precisions[SIM3_DOF - 1] = hold_scale_sigma**-2
            scale_model = gtsam.noiseModel.Diagonal.Precisions(precisions)
            for k, pose in enumerate(T_WC.to_gtsam()):
                if k > 0:
                    self.base.add(gtsam.PriorFactorSimilarity3(k, pose, scale_model))
        if self.K > 1:
            keys = np.arange(self.K)
            Z_smooth = T_WC[:-1].inverse() @ T_WC[1:]
            for f in make_between_factors(keys[:-1], keys[1:], Z_smooth, sigmas=smooth_sigmas):
                self.base.add(f)
        Z = T_CiCj.to_gtsam() if loop_i.size else []
        self.factors = {}
        for robust in (False, True):
            model = diagonal_model(np.asarray(loop_sigmas), kernel if robust else "none", kernel_param)
            self.factors[robust] = [
                gtsam.BetweenFactorSimilarity3(int(i), int(j), z, model) for i, j, z in zip(loop_i, loop_j, Z)
            ]
        self.iterations = 0
        self.lm_time_s = 0.0

    def solve(self, active: np.ndarray, start, settings: LMSettings, robust: bool = True):
        """LM on the base graph + the ``active`` loops from ``start``; returns (graph, values)."""
        import gtsam  # deferred: gtsam

        graph = gtsam.NonlinearFactorGraph(self.base)
        for c in np.flatnonzero(active):
            graph.add(self.factors[robust][c])
        problem = NonlinearProblem(graph, start)
        t0 = time.perf_counter()
        try:
            report = levenberg_marquardt(problem, settings)
        except RuntimeError as exc:
            raise OptimizationError(f"Sim(3) pose graph: LM failed on {self.K} keyframes: {exc}") from exc
        self.lm_time_s += time.perf_counter() - t0
        self.iterations += report.iterations
        return graph, problem.values

    def poses(self, values) -> Sim3:
        """(K,) keyframe poses in ``values``."""
        return Sim3.from_gtsam([values.atSimilarity3(k) for k in range(self.K)])
