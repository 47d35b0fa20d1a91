"""The problem of one optimisation of the backend (docs/architecture.md section 8): an
:class:`~fgslam.backend.solver.LMProblem` over the free keys, its iSAM2 step provider, and the one
elimination of keys out of the backend's linearised graph.

Keys outside the problem's free set keep their value: factors and blocks that reach one are
conditioned on it (their linear pieces restricted to the free keys; for a Schur-reduced block this
equals eliminating its structure in the problem with those poses fixed). With ``isam2`` the step of
each LM iteration comes from a ``gtsam.ISAM2`` (relinearise threshold 0, skip 1, wildfire 0, so each
step is the exact Gauss-Newton step) that holds the built-in factors over the free keys and whose
block pieces are swapped at every iteration. One iSAM2 instance serves one optimisation call: a
window slides and the blocks are relinearised at every iteration, so every clique is re-eliminated
anyway.
"""

from __future__ import annotations

import numpy as np

from ..core.errors import OptimizationError
from ..factors.schur import POSE_DIM, jacobian_factor
from .keys import key_name

NAMED_KEYS = 5  # keys an elimination error names


def restricted_factor(gf, keys: tuple[int, ...], free: set, dims: dict):
    """The linear factor ``gf`` on ``keys`` conditioned on a zero step of its non-free keys (their
    columns dropped); None when no key is free."""
    import gtsam  # deferred: gtsam

    keep = [i for i, k in enumerate(keys) if k in free]
    if not keep:
        return None
    A, b = gf.jacobian()  # whitened, columns in key order
    offsets = np.cumsum([0] + [dims[k] for k in keys])
    cols = np.concatenate([np.arange(offsets[i], offsets[i + 1]) for i in keep])
    A = np.asarray(A)[:, cols]
    b = np.asarray(b)
    fkeys = [keys[i] for i in keep]
    fdims = [dims[k] for k in fkeys]
    unit = gtsam.noiseModel.Unit.Create(A.shape[0])
    blocks = np.split(A, np.cumsum(fdims)[:-1], axis=1)
    if len(fkeys) == 1:
        return gtsam.JacobianFactor(fkeys[0], blocks[0], b, unit)
    if len(fkeys) == 2:
        return gtsam.JacobianFactor(fkeys[0], blocks[0], fkeys[1], blocks[1], b, unit)
    if len(fkeys) == 3:
        return gtsam.JacobianFactor(fkeys[0], blocks[0], fkeys[1], blocks[1], fkeys[2], blocks[2], b, unit)
    return jacobian_factor(fkeys, A, b, fdims)


def eliminate_keys(gfg, keys: list[int], dims: dict[int, int], regularization: float, hint: str = ""):
    """The linear graph ``gfg`` with ``keys`` eliminated (their Gaussian marginal on the keys they reach,
    as the remaining factors): the one Schur elimination of variables out of the backend's linearised
    graph (window marginal priors, marginalised attached keys). ``regularization > 0`` adds
    ``regularization |dx|^2`` on each eliminated key first (directions no factor observes).

    Raises:
        OptimizationError: the system is indeterminate (names up to ``NAMED_KEYS`` keys; ``hint`` appended).
    """
    import gtsam  # deferred: gtsam

    if regularization > 0:
        for key in keys:
            gfg.push_back(gtsam.JacobianFactor(key, np.sqrt(regularization) * np.eye(dims[key]), np.zeros(dims[key]),
                                               gtsam.noiseModel.Unit.Create(dims[key])))
    ordering = gtsam.Ordering()
    for key in keys:
        ordering.push_back(key)
    try:
        _, remaining = gfg.eliminatePartialSequential(ordering)
    except RuntimeError as exc:  # gtsam's IndeterminateLinearSystemException
        names = ", ".join(key_name(k) for k in keys[:NAMED_KEYS])
        more = ", ..." if len(keys) > NAMED_KEYS else ""
        raise OptimizationError(f"marginalising {names}{more} failed ({exc}){hint}") from exc
    return remaining


class Isam2Stepper:
    """Step provider of one optimisation: a ``gtsam.ISAM2`` holding the problem's built-in factors over
    the free keys; the linear extras (block pieces, restricted boundary factors) are swapped in as
    ``LinearContainerFactor``s at every iteration (module docstring)."""

    def __init__(self, problem: "WindowProblem"):
        import gtsam  # deferred: gtsam

        params = gtsam.ISAM2Params()
        params.setRelinearizeThreshold(0.0)
        params.relinearizeSkip = 1
        gn = gtsam.ISAM2GaussNewtonParams()
        gn.setWildfireThreshold(0.0)
        params.setOptimizationParams(gn)
        self.isam = gtsam.ISAM2(params)
        self.problem = problem
        self.slots: list[int] = []
        self.started = False

    def __call__(self, gfg):
        import gtsam  # deferred: gtsam

        prob = self.problem
        containers = gtsam.NonlinearFactorGraph()
        free_values = prob.free_values()
        for factor in prob.last_extras:
            containers.add(gtsam.LinearContainerFactor(factor, free_values))
        if not self.started:
            new = gtsam.NonlinearFactorGraph(prob.inner)
            new.push_back(containers)
            result = self.isam.update(new, free_values, [])
            self.started = True
        else:
            result = self.isam.update(containers, gtsam.Values(), self.slots)
        indices = list(result.getNewFactorsIndices())
        self.slots = indices[len(indices) - int(containers.size()):] if containers.size() else []
        return free_values.localCoordinates(self.isam.calculateEstimate())


def _copy(gfg):
    """A new ``gtsam.GaussianFactorGraph`` sharing ``gfg``'s factors (pushing onto it leaves ``gfg`` as it is)."""
    import gtsam  # deferred: gtsam

    out = gtsam.GaussianFactorGraph()
    out.push_back(gfg)
    return out


class WindowProblem:
    """An :class:`~fgslam.backend.solver.LMProblem` over the free keys of one optimisation: built-in
    and gauge factors that touch a free key (``inner``: only free keys; ``cross``: conditioned on
    their fixed keys) and the blocks that touch one (pieces restricted to the free keys)."""

    def __init__(self, values, free: list[int], inner, cross: list, blocks: list, refine_steps: int,
                 refine_each_iteration: bool, damp_structure: bool = False):
        self.values = values  # gtsam.Values of every key the problem reads (free and fixed)
        self.free = list(free)
        self.free_set = set(free)
        self.inner = inner
        self.cross = cross  # nonlinear factors with a fixed key
        self.blocks = blocks
        self.structured = [b for b in blocks if getattr(b, "has_structure", True)]
        self._has_structure = {id(b) for b in self.structured}
        self.refine_steps = refine_steps
        self.refine_each_iteration = refine_each_iteration
        self.dims = {int(k): int(d) for k, d in values.dims().items()}
        self.fixed_of_blocks = sorted({k for b in self.structured for k in b.keys if k not in self.free_set})
        self.last_extras: list = []
        # the LM damping covers the blocks' structure too (structure_damped); map.damp_structure
        self.damps_structure = bool(damp_structure) and any(hasattr(b, "linearize_damped") for b in self.structured)
        self._linear: tuple | None = None  # the last linearisation: (its factor graph, the cross factors, {id(block): pieces})

    def free_values(self):
        import gtsam  # deferred: gtsam

        sub = gtsam.Values(self.values)
        for key in self.values.keys():
            if int(key) not in self.free_set:
                sub.erase(key)
        return sub

    def _graph_cost(self, values) -> float:
        cost = float(self.inner.error(values))
        for factor in self.cross:
            cost += float(factor.error(values))
        return cost

    def cost(self) -> float:
        return self._graph_cost(self.values) + sum(float(b.cost(self.values)) for b in self.blocks)

    def refine(self, steps: int) -> float:
        graph_cost = self._graph_cost(self.values)
        if steps <= 0:
            return graph_cost + sum(float(b.cost(self.values)) for b in self.blocks)
        return graph_cost + sum(
            float(b.refine_structure(self.values, steps)) if id(b) in self._has_structure else float(b.cost(self.values))
            for b in self.blocks
        )

    def linearize(self):
        gfg = self.inner.linearize(self.values)
        extras = []
        for factor in self.cross:
            restricted = restricted_factor(factor.linearize(self.values), tuple(int(k) for k in factor.keys()),
                                            self.free_set, self.dims)
            if restricted is not None:
                extras.append(restricted)
        pieces = {id(block): block.linearize(self.values) for block in self.blocks}
        if self.damps_structure:
            self._linear = (_copy(gfg), list(extras), pieces)
        extras.extend(self._block_pieces(pieces))
        for factor in extras:
            gfg.push_back(factor)
        self.last_extras = extras
        return gfg

    def structure_damped(self, lam: float):
        """The last linearisation with ``lam`` added to the information of every structure variable of the
        structured blocks (their ``linearize_damped``), the other factors as they were: with the LM's
        damping of the poses, the damping of the joint system of poses and structure, whose
        back-substitution (:meth:`trial`) then shrinks the structure's step as the damping rises."""
        if self._linear is None:
            raise OptimizationError("structure_damped() called before linearize() (or without damps_structure)")
        graph, extras, pieces = self._linear
        pieces = dict(pieces)
        for block in self.structured:
            if hasattr(block, "linearize_damped"):
                pieces[id(block)] = block.linearize_damped(lam)
        gfg = _copy(graph)
        for factor in extras + self._block_pieces(pieces):
            gfg.push_back(factor)
        return gfg

    def end_damping(self) -> None:
        """The optimisation has ended: the blocks back-substitute through their own last linearisation
        again, not through the damped one of the last solve."""
        if self.damps_structure:
            for block in self.structured:
                if hasattr(block, "clear_damping"):
                    block.clear_damping()
            self._linear = None

    def _block_pieces(self, pieces_of: dict) -> list:
        """Every block's linear pieces (``pieces_of``: by ``id(block)``) restricted to the free keys, summed
        per key (diagonal blocks) and per key pair (off-diagonal blocks) into ``HessianFactor`` pieces."""
        import gtsam  # deferred: gtsam

        diag: dict[int, np.ndarray] = {}
        grad: dict[int, np.ndarray] = {}
        off: dict[tuple[int, int], np.ndarray] = {}
        constant = 0.0
        d = POSE_DIM
        free = self.free_set
        for block in self.blocks:
            for piece in pieces_of[id(block)]:
                keys, H, g = piece.keys, piece.H, piece.g
                constant += float(piece.c)
                for a, ka in enumerate(keys):
                    if ka not in free:
                        continue
                    sa = slice(d * a, d * a + d)
                    diag[ka] = diag.get(ka, 0.0) + H[sa, sa]
                    grad[ka] = grad.get(ka, 0.0) + g[sa]
                    for b, kb in enumerate(keys):
                        if kb <= ka or kb not in free:
                            continue
                        off[(ka, kb)] = off.get((ka, kb), 0.0) + H[sa, slice(d * b, d * b + d)]
        out = []
        first = True
        for key, block in diag.items():
            out.append(gtsam.HessianFactor(key, block, -grad[key], constant if first else 0.0))
            first = False
        zero_block, zero_vec = np.zeros((d, d)), np.zeros(d)
        for (ka, kb), block in off.items():
            out.append(gtsam.HessianFactor(ka, kb, zero_block, block, zero_vec, zero_block, zero_vec, 0.0))
        return out

    def _full_delta(self, delta):
        """``delta`` with zero steps for the fixed keys of structured blocks (their back-substitution)."""
        if not self.fixed_of_blocks:
            return delta
        import gtsam  # deferred: gtsam

        full = gtsam.VectorValues(delta)
        for key in self.fixed_of_blocks:
            full.insert(key, np.zeros(self.dims[key]))
        return full

    def trial(self, delta):
        values = self.values.retract(delta)  # keys without a step keep their value
        full = self._full_delta(delta) if self.structured else delta
        structures = [b.clamp_structure(b.structure + b.back_substitute(full)) for b in self.structured]
        trial_of = {id(b): s for b, s in zip(self.structured, structures)}
        cost = self._graph_cost(values) + sum(float(b.cost(values, trial_of[id(b)])) if id(b) in trial_of
                                              else float(b.cost(values)) for b in self.blocks)
        return cost, (values, structures)

    def accept(self, state, cost: float) -> float:
        values, structures = state
        self.values = values
        for b, s in zip(self.structured, structures):
            b.set_structure(s)
        if self.refine_each_iteration and self.refine_steps > 0:
            return self.refine(self.refine_steps)
        return cost
