"""Shared helpers of the dense-family tests (importable because pytest puts tests/ on the path): a
tiny LMProblem adapter that drives a dense block through the backend's one LM loop, and the gauge of
inverse-depth Sim(3) bundle adjustment. (The backend's own Backend will replace the adapter.)"""

from __future__ import annotations

import gtsam
import numpy as np

from fgslam.backend.solver import LMSettings, levenberg_marquardt
from fgslam.factors.schur import to_gaussian_factor


class BlockProblem:
    """LMProblem of fgslam.backend.solver over gauge priors (gtsam factors) plus one dense block."""

    def __init__(self, block, graph, values):
        self.block, self.graph, self.values = block, graph, values

    def cost(self) -> float:
        return float(self.graph.error(self.values)) + self.block.cost(self.values)

    def linearize(self):
        gfg = self.graph.linearize(self.values)
        for piece in self.block.linearize(self.values):
            gfg.push_back(to_gaussian_factor(piece.keys, piece.H, piece.g, piece.c))
        return gfg

    def trial(self, delta):
        values = self.values.retract(delta)
        structure = self.block.clamp_structure(self.block.structure + self.block.back_substitute(delta))
        return float(self.graph.error(values)) + self.block.cost(values, structure), (values, structure)

    def accept(self, state, cost):
        self.values, structure = state
        self.block.set_structure(structure)
        return cost


def gauge_graph(poses, keys, fix_first=True):
    """Gauge of inverse-depth Sim(3) BA: the first pose (``fix_first``), and every keyframe's scale
    (lambda) held at the value in ``poses``; the other components of those priors carry no weight."""
    graph = gtsam.NonlinearFactorGraph()
    tight = gtsam.noiseModel.Isotropic.Sigma(7, 1e-6)
    scale_only = gtsam.noiseModel.Diagonal.Sigmas(np.array([1e6] * 6 + [1e-6]))
    for n, (key, T) in enumerate(zip(keys, poses)):
        noise = tight if (n == 0 and fix_first) else scale_only
        graph.add(gtsam.PriorFactorSimilarity3(key, T.to_gtsam(), noise))
    return graph


def solve(block, graph, values, max_iterations: int = 60):
    """LM from ``values`` (gtsam.Values of Similarity3) and the block's structure; (problem, LMReport)."""
    problem = BlockProblem(block, graph, values)
    report = levenberg_marquardt(problem, LMSettings(max_iterations=max_iterations, lambda_initial=1e-4, lambda_factor=10.0,
                                                     lambda_max=1e12, absolute_tolerance=1e-24,
                                                     relative_tolerance=1e-14))
    return problem, report
