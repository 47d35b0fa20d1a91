"""The backend: one GTSAM graph per run that every frontend feeds (docs/design.md section 8).

Keyframe ``kf`` has the gtsam key :func:`~fgslam.backend.keys.pose_key` ``= gtsam.symbol('x', kf)``
holding a ``gtsam.Similarity3`` T_WC (camera-to-world; fgslam.lie's ``Sim3(R, t, s)`` maps to
``Similarity3(Rot3(R), t / s, s)``), and a timestamp. Tangents are gtsam's ``[w, u, lambda]`` with
right perturbation. Other variables (velocities, biases, plugin variables) are added by key, optionally
attached to a keyframe (:meth:`Backend.attach_key`: free, fixed, marginalised and removed with it).

Contents of the optimisation problem:

- built-in gtsam factors (``BetweenFactorSimilarity3`` loops, plugin priors, IMU...) added by handle
  with :meth:`Backend.add_factor`, each with an ``owner``; they persist until removed (or until a
  keyframe they touch is removed);
- contributors' measurement blocks (:class:`fgslam.factors.blocks.Block`, e.g. the patch frontend's
  Schur-reduced :class:`~fgslam.frontends.patch.ba.PatchBlock`), set per owner with
  :meth:`Backend.set_blocks`; blocks of different owners on the same keys add up;
- gauge factors the backend maintains itself (docs/design.md section 4, :class:`GaugeConfig`): a
  7-dof prior on the anchor keyframe, a range constraint between the scale pair (monocular world
  scale), both at the poses they had when :meth:`Backend.set_gauge` chose them (default: the oldest
  keyframe and the oldest two, when they became so), and with ``hold_scale`` a log-scale prior on
  every free keyframe at its scale when the optimisation starts (inverse-depth frontends, where a
  keyframe's scale is a pure gauge).

Optimisation (all through the one LM loop, :func:`fgslam.backend.solver.levenberg_marquardt`):

- :meth:`Backend.optimize_window`: the given keyframes are free (LM settings of ``map.window``: a
  window runs the frontend's few iterations per frame). With ``map.window.leaving: fixed``
  every other key keeps its value: factors and blocks that reach it are conditioned on it (their
  linear pieces restricted to the free keys; for a Schur-reduced block this equals eliminating its
  structure in the problem with those poses fixed). With ``marginalize`` the persistent built-in
  factors over keys outside the window are linearised at the current estimate and the outside keys
  eliminated (GTSAM's partial elimination), which leaves a linear prior
  (``gtsam.LinearContainerFactor``) on the window keys they connect to. Not marginalised: the gauge
  and the contributors' blocks (a frontend rebuilds its blocks, with the frames it holds fixed, for
  every optimisation, so it decides what its measurements of old frames still say).
- :meth:`Backend.optimize_global`: every key.
- :meth:`Backend.correct_pose_graph`: Sim(3) between factors from the current estimate between
  consecutive keyframes plus the persistent factors over them; returns the new poses.

Solvers (``map.solver``): ``lm`` (``python_lm`` is an alias): damped GTSAM elimination of the
linearised graph (built-in factors linearised by gtsam, block pieces as ``HessianFactor``s);
``isam2``: the step of each LM iteration comes from a ``gtsam.ISAM2`` (relinearise threshold 0,
skip 1, wildfire 0, so each step is the exact Gauss-Newton step) that holds the built-in factors
over the free keys and whose block pieces are swapped at every iteration; a step that raises the
true cost is halved. One iSAM2 instance serves one optimisation call: a window slides and the blocks
are relinearised at every iteration, so every clique is re-eliminated anyway.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from typing import Callable, Iterable

import numpy as np

from ..errors import OptimizationError
from ..factors.range import camera_centre, range_factor
from ..factors.schur import POSE_DIM, torch_threads
from ..lie import Sim3, gtsam_matrix, gtsam_sim3
from .config import BackendConfig, GaugeConfig
from .keys import key_name, pose_key
from .pose_graph import anchor_prior, diagonal_model
from .solver import LMSettings, NonlinearProblem, levenberg_marquardt

logger = logging.getLogger(__name__)

@dataclass
class OptimizeReport:
    """What one optimisation of :class:`Backend` did."""

    solver: str
    initial_cost: float
    final_cost: float
    iterations: int
    converged: bool
    seconds: float
    free_keys: int = 0


def as_similarity3(T_WC):
    """``gtsam.Similarity3`` of a pose given as one, as an unbatched :class:`fgslam.lie.Sim3` or as a
    (4, 4) Sim(3) matrix ``[[s R, t], [0, 1]]`` (R projected onto SO(3))."""
    import gtsam

    if isinstance(T_WC, gtsam.Similarity3):
        return T_WC
    if isinstance(T_WC, Sim3):
        return T_WC.to_gtsam()
    M = np.asarray(T_WC, dtype=np.float64)
    if M.shape != (4, 4) or not np.isfinite(M).all():
        raise OptimizationError(f"a pose must be a finite 4x4 Sim(3) matrix, a Sim3 or a gtsam.Similarity3, got shape {M.shape}")
    return gtsam_sim3(M)




def _restricted_factor(gf, keys: tuple[int, ...], free: set, dims: dict):
    """The linear factor ``gf`` on ``keys`` conditioned on a zero step of its non-free keys (their
    columns dropped); None when no key is free."""
    import gtsam

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
    return jacobian_on(fkeys, fdims, A, b)


def jacobian_on(keys: list[int], dims: list[int], A: np.ndarray, b: np.ndarray):
    """The linear factor ``0.5 |A dx - b|^2`` on ``keys`` of dimensions ``dims`` (any number, mixed
    dimensions: a ``gtsam.GaussianConditional`` from a ``VerticalBlockMatrix`` is a JacobianFactor on
    any number of keys, docs/design.md section 6)."""
    import gtsam

    Ab = np.empty((A.shape[0], A.shape[1] + 1))
    Ab[:, :-1] = A
    Ab[:, -1] = b
    return gtsam.GaussianConditional([int(k) for k in keys], len(keys),
                                     gtsam.VerticalBlockMatrix([int(d) for d in dims], Ab, True))


def _eliminate_keys(gfg, keys: list[int], dims: dict[int, int], regularization: float, hint: str = ""):
    """The linear graph ``gfg`` with ``keys`` eliminated (their Gaussian marginal on the keys they reach,
    as the remaining factors): the one Schur elimination of variables out of the backend's linearised
    graph (window marginal priors, marginalised attached keys). ``regularization > 0`` adds
    ``regularization |dx|^2`` on each eliminated key first (directions no factor observes).

    Raises:
        OptimizationError: the system is indeterminate (names up to five keys; ``hint`` appended).
    """
    import gtsam

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
        names = ", ".join(key_name(k) for k in keys[:5])
        raise OptimizationError(f"marginalising {names}{', ...' if len(keys) > 5 else ''} failed ({exc}){hint}") from exc
    return remaining


class _Isam2Stepper:
    """Step provider of one optimisation: a ``gtsam.ISAM2`` holding the problem's built-in factors over
    the free keys; the linear extras (block pieces, restricted boundary factors) are swapped in as
    ``LinearContainerFactor``s at every iteration (see module docstring)."""

    def __init__(self, problem: "_WindowProblem"):
        import gtsam

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
        import gtsam

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


class _WindowProblem:
    """An :class:`~fgslam.backend.solver.LMProblem` over the free keys of one optimisation: built-in
    and gauge factors that touch a free key (``inner``: only free keys; ``cross``: conditioned on
    their fixed keys) and the blocks that touch one (pieces restricted to the free keys)."""

    def __init__(self, values, free: list[int], inner, cross: list, blocks: list, refine_steps: int,
                 refine_each_iteration: bool):
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

    def free_values(self):
        import gtsam

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
        import gtsam

        gfg = self.inner.linearize(self.values)
        extras = []
        for factor in self.cross:
            restricted = _restricted_factor(factor.linearize(self.values), tuple(int(k) for k in factor.keys()),
                                            self.free_set, self.dims)
            if restricted is not None:
                extras.append(restricted)
        extras.extend(self._block_pieces())
        for factor in extras:
            gfg.push_back(factor)
        self.last_extras = extras
        return gfg

    def _block_pieces(self) -> list:
        """Every block linearised and restricted to the free keys, summed per key (diagonal blocks) and
        per key pair (off-diagonal blocks) into ``HessianFactor`` pieces."""
        import gtsam

        diag: dict[int, np.ndarray] = {}
        grad: dict[int, np.ndarray] = {}
        off: dict[tuple[int, int], np.ndarray] = {}
        constant = 0.0
        d = POSE_DIM
        free = self.free_set
        for block in self.blocks:
            for piece in block.linearize(self.values):
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
        import gtsam

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


class Backend:
    """Keyframe poses, variables, factors, blocks, gauge and the optimisations (module docstring).

    Typical use by a frontend::

        backend = Backend(BackendConfig())
        backend.add_keyframe(0, T_WC0, t0); backend.add_keyframe(1, T_WC1, t1)
        backend.set_blocks("patch", [PatchBlock(keys=(pose_key(1),), ...)])
        report = backend.optimize_window([1], iterations=2)
        T_WC = backend.pose_matrix(1)
    """

    def __init__(self, config: BackendConfig | None = None):
        import gtsam

        self.config = config or BackendConfig()
        self.config.validate()
        self._values = gtsam.Values()
        self._keyframes: dict[int, float] = {}  # kf_id -> timestamp, in insertion order
        self._factors: dict[int, tuple[object, tuple[int, ...], str]] = {}  # handle -> (factor, keys, owner)
        self._next_handle = 0
        self._blocks: dict[str, list] = {}
        self._callbacks: list[Callable] = []
        self._removed_callbacks: list[Callable] = []
        self._window_hooks: list[Callable] = []  # free keyframes -> extra keys freed with a window
        self._attached: dict[int, list[int]] = {}  # kf_id -> keys attached to it (velocity, bias, ...)
        self._attached_kf: dict[int, int] = {}  # attached key -> kf_id
        self._key_kf: dict[int, int] = {}  # pose key -> kf_id
        self._versions: dict[int, int] = {}  # kf_id -> version of its pose (changes on every update)
        self._version = 0
        # gauge: explicit choice (set_gauge) or the default (oldest keyframe, oldest two)
        self._gauge_explicit = False
        self._anchor: tuple[int, object] | None = None  # (kf, prior pose)
        self._range: tuple[int, int, float] | None = None  # (kf_a, kf_b, distance)

    # ------------------------------------------------------------------ keyframes and variables
    @property
    def keyframe_ids(self) -> list[int]:
        return list(self._keyframes)

    def has_keyframe(self, kf_id: int) -> bool:
        return int(kf_id) in self._keyframes

    def has_key(self, key: int) -> bool:
        return bool(self._values.exists(int(key)))

    def timestamp(self, kf_id: int) -> float:
        self._check_keyframe(kf_id)
        return self._keyframes[int(kf_id)]

    def _check_keyframe(self, kf_id: int) -> None:
        if int(kf_id) not in self._keyframes:
            raise OptimizationError(f"keyframe {kf_id} ({key_name(pose_key(kf_id))}) is not in the backend")

    def _bump(self, kf_id: int) -> None:
        self._version += 1
        self._versions[kf_id] = self._version

    def pose_version(self, kf_id: int) -> int:
        """A number that changes whenever keyframe ``kf_id``'s pose changes (readers' caches)."""
        return self._versions[int(kf_id)]

    def add_keyframe(self, kf_id: int, T_WC, timestamp: float = float("nan")) -> int:
        """Add keyframe ``kf_id`` with initial pose ``T_WC`` (4x4 Sim(3) matrix, fgslam Sim3 or
        gtsam.Similarity3) and its timestamp; returns its gtsam key. Calls the ``on_keyframe`` callbacks."""
        kf_id = int(kf_id)
        key = pose_key(kf_id)
        if self._values.exists(key):
            raise OptimizationError(f"keyframe {kf_id} ({key_name(key)}) is already in the backend")
        self._values.insert(key, as_similarity3(T_WC))
        self._keyframes[kf_id] = float(timestamp)
        self._key_kf[key] = kf_id
        self._bump(kf_id)
        self._default_gauge()
        for callback in self._callbacks:
            callback(kf_id, float(timestamp), key)
        return key

    def remove_keyframe(self, kf_id: int) -> None:
        """Remove keyframe ``kf_id``, every factor and every block that involves it (no marginalisation;
        no callback)."""
        self._check_keyframe(kf_id)
        kf_id = int(kf_id)
        key = pose_key(kf_id)
        for handle in [h for h, (_, keys, _) in self._factors.items() if key in keys]:
            del self._factors[handle]
        for owner, blocks in self._blocks.items():
            self._blocks[owner] = [b for b in blocks if key not in b.keys]
        for attached in self._attached.pop(kf_id, []):  # keys attached to the keyframe go with it
            self.remove_variable(attached)
        self._values.erase(key)
        del self._keyframes[kf_id]
        del self._versions[kf_id]
        del self._key_kf[key]
        if self._anchor is not None and self._anchor[0] == kf_id:
            self._anchor = None
            self._gauge_explicit = False  # the chosen anchor is gone: back to the default gauge
        if self._range is not None and kf_id in self._range[:2]:
            self._range = None
            self._gauge_explicit = False
        self._default_gauge()
        for callback in self._removed_callbacks:
            callback(kf_id)

    def add_variable(self, key: int, value, attach_to: int | None = None) -> None:
        """Add a non-keyframe variable (velocity, bias, plugin variable) with its initial value;
        ``attach_to``: a keyframe the variable belongs to (:meth:`attach_key`)."""
        key = int(key)
        if self._values.exists(key):
            raise OptimizationError(f"variable {key_name(key)} is already in the backend")
        if attach_to is not None:
            self._check_keyframe(attach_to)
        self._values.insert(key, value)
        if attach_to is not None:
            self.attach_key(key, attach_to)

    def attach_key(self, key: int, kf_id: int) -> None:
        """Attach variable ``key`` to keyframe ``kf_id``: it is free in every window where the keyframe
        is (:meth:`optimize_window`), outside it where the keyframe is (held fixed or marginalised
        with it), and removed with the keyframe (:meth:`remove_keyframe`)."""
        key, kf_id = int(key), int(kf_id)
        self._check_keyframe(kf_id)
        if not self._values.exists(key) or key in self._key_kf:
            raise OptimizationError(f"only an existing non-keyframe variable can be attached, not {key_name(key)}")
        previous = self._attached_kf.get(key)
        if previous is not None:
            self._attached[previous].remove(key)
        self._attached_kf[key] = kf_id
        self._attached.setdefault(kf_id, []).append(key)

    def attached_keys(self, kf_id: int) -> list[int]:
        """Variables attached to keyframe ``kf_id`` (:meth:`attach_key`)."""
        return list(self._attached.get(int(kf_id), []))

    def remove_variable(self, key: int) -> None:
        """Remove a non-keyframe variable and every factor on it."""
        key = int(key)
        if not self._values.exists(key):
            raise OptimizationError(f"variable {key_name(key)} is not in the backend")
        for handle in [h for h, (_, keys, _) in self._factors.items() if key in keys]:
            del self._factors[handle]
        self._values.erase(key)
        kf_id = self._attached_kf.pop(key, None)
        if kf_id is not None and key in self._attached.get(kf_id, []):
            self._attached[kf_id].remove(key)

    def marginalize_variables(self, keys: Iterable[int], condition_on: Iterable[int] = (), owner: str = "marginal") -> list[int]:
        """Remove the non-keyframe variables ``keys`` and every persistent factor on them, keeping what
        those factors said about the other keys they reach as a linear prior (their Gaussian marginal at
        the current estimate: the factors linearised, ``keys`` eliminated, the rest as
        ``gtsam.LinearContainerFactor``s owned by ``owner``). Keys in ``condition_on`` are held at their
        current value instead (their columns dropped: the prior then does not touch them; e.g. a
        keyframe pose that stays in the map, fixed outside the window). Returns the new factors' handles."""
        import gtsam

        keys = [int(k) for k in keys]
        for key in keys:
            if not self._values.exists(key) or key in self._key_kf:
                raise OptimizationError(f"only existing non-keyframe variables can be marginalised, not {key_name(key)}")
        drop = set(keys)
        held = {int(k) for k in condition_on}
        touching = [(h, f, fkeys) for h, (f, fkeys, _) in self._factors.items() if any(k in drop for k in fkeys)]
        dims = {int(k): int(d) for k, d in self._values.dims().items()}
        gfg = gtsam.GaussianFactorGraph()
        reached: set[int] = set()
        for _, factor, fkeys in touching:
            free = {k for k in fkeys if k not in held}
            restricted = _restricted_factor(factor.linearize(self._values), fkeys, free, dims)
            if restricted is not None:
                gfg.push_back(restricted)
                reached.update(k for k in free if k not in drop)
        # directions no factor observes stay determinate: always a (tiny) regularisation here
        remaining = _eliminate_keys(gfg, keys, dims, max(self.config.window.marginal_regularization, 1e-12))
        for handle, _, _ in touching:
            del self._factors[handle]
        for key in keys:
            self.remove_variable(key)
        lin_point = self._subset(reached) if reached else gtsam.Values()
        handles = []
        for i in range(remaining.size()):
            factor = remaining.at(i)
            if factor is None or len(factor.keys()) == 0:
                continue
            handles.append(self.add_factor(gtsam.LinearContainerFactor(factor, lin_point), owner))
        return handles

    def pose(self, kf_id: int):
        """Current T_WC of keyframe ``kf_id`` (gtsam.Similarity3)."""
        self._check_keyframe(kf_id)
        return self._values.atSimilarity3(pose_key(kf_id))

    def pose_matrix(self, kf_id: int) -> np.ndarray:
        """Current T_WC of keyframe ``kf_id`` as a (4, 4) Sim(3) matrix."""
        return gtsam_matrix(self.pose(kf_id))

    def poses(self, kf_ids: Iterable[int] | None = None) -> Sim3:
        """Current T_WC of ``kf_ids`` (default all, in insertion order) as a batched fgslam Sim3."""
        ids = self.keyframe_ids if kf_ids is None else list(kf_ids)
        return Sim3.from_gtsam([self.pose(k) for k in ids])

    def set_pose(self, kf_id: int, T_WC) -> None:
        """Overwrite keyframe ``kf_id``'s pose (a pose-graph correction, a frontend's restore)."""
        self._check_keyframe(kf_id)
        self._values.update(pose_key(kf_id), as_similarity3(T_WC))
        self._bump(int(kf_id))

    def set_value(self, key: int, value) -> None:
        """Overwrite a non-keyframe variable's value (e.g. velocities rescaled with the map)."""
        key = int(key)
        if not self._values.exists(key) or key in self._key_kf:
            raise OptimizationError(f"set_value: {key_name(key)} is not a non-keyframe variable of the backend")
        self._values.update(key, value)

    def values_of(self, keys: Iterable[int]):
        """A gtsam.Values with the current values of ``keys`` (e.g. a block's keys)."""
        keys = {int(k) for k in keys}
        for key in keys:
            if not self._values.exists(key):
                raise OptimizationError(f"unknown key {key_name(key)}")
        return self._subset(keys)

    @property
    def values(self):
        """A copy of the current gtsam.Values."""
        import gtsam

        return gtsam.Values(self._values)

    def on_keyframe(self, callback: Callable[[int, float, int], None]) -> None:
        """Register ``callback(kf_id, timestamp, key)``, called after every :meth:`add_keyframe`."""
        self._callbacks.append(callback)

    def on_window(self, hook: Callable[[list[int]], Iterable[int]]) -> None:
        """Register ``hook(free_kf_ids) -> keys``: non-keyframe variables that every
        :meth:`optimize_window` frees besides the window's own (e.g. the velocities and biases of the IMU's
        fixed-lag window, which no visual factor holds once their keyframe's pose is fixed)."""
        self._window_hooks.append(hook)

    def on_keyframe_removed(self, callback: Callable[[int], None]) -> None:
        """Register ``callback(kf_id)``, called after every :meth:`remove_keyframe` (its factors and
        attached keys are gone already)."""
        self._removed_callbacks.append(callback)

    # ------------------------------------------------------------------ factors and blocks
    def add_factor(self, factor, owner: str = "user") -> int:
        """Add a gtsam nonlinear factor on existing keys; returns its handle.

        Raises:
            OptimizationError: a key of the factor is not in the backend (named, e.g. ``x12``).
        """
        keys = tuple(int(k) for k in factor.keys())
        for key in keys:
            if not self._values.exists(key):
                raise OptimizationError(f"factor of '{owner}' on unknown key {key_name(key)}: add the keyframe or variable first")
        handle = self._next_handle
        self._next_handle += 1
        self._factors[handle] = (factor, keys, str(owner))
        return handle

    def remove_factor(self, handle: int) -> None:
        if handle not in self._factors:
            raise OptimizationError(f"no factor with handle {handle}")
        del self._factors[handle]

    def factor_handles(self, owner: str) -> list[int]:
        """Handles of the factors ``owner`` added (in order)."""
        return [h for h, (_, _, o) in self._factors.items() if o == owner]

    def factor(self, handle: int):
        return self._factors[handle][0]

    def set_blocks(self, owner: str, blocks: list) -> None:
        """Replace contributor ``owner``'s blocks (an empty list removes them). Blocks of different
        owners on the same keys add up.

        Raises:
            OptimizationError: a block touches a key that is not in the backend (named).
        """
        blocks = list(blocks)
        for block in blocks:
            for key in block.keys:
                if not self._values.exists(int(key)):
                    raise OptimizationError(f"block of '{owner}' on unknown key {key_name(int(key))}: add the keyframe first")
        if blocks:
            self._blocks[str(owner)] = blocks
        else:
            self._blocks.pop(str(owner), None)

    def blocks(self, owner: str | None = None) -> list:
        """Blocks of ``owner`` (default: every owner's, in owner order)."""
        if owner is not None:
            return list(self._blocks.get(owner, []))
        return [b for blocks in self._blocks.values() for b in blocks]

    # ------------------------------------------------------------------ gauge
    def set_gauge(self, anchor: int | None = None, scale_pair: tuple[int, int] | None = None) -> None:
        """Choose the keyframes that carry the configured gauge factors, at their current poses:
        ``anchor`` the 7-dof prior (None: none), ``scale_pair`` the world-scale range (None: none).
        Until called (or after a chosen keyframe is removed) the gauge is the default one: the oldest
        keyframe and the oldest two, at their poses when they became so."""
        self._gauge_explicit = True
        self._anchor = None
        self._range = None
        if anchor is not None:
            self._check_keyframe(anchor)
            self._anchor = (int(anchor), self.pose(anchor))
        if scale_pair is not None:
            self._range = self._make_range(*scale_pair)

    def _make_range(self, kf_a: int, kf_b: int) -> tuple[int, int, float]:
        self._check_keyframe(kf_a)
        self._check_keyframe(kf_b)
        distance = float(np.linalg.norm(camera_centre(self.pose(kf_b)) - camera_centre(self.pose(kf_a))))
        if not distance > 0.0:
            raise OptimizationError(f"world-scale range gauge: keyframes {kf_a} and {kf_b} have the same centre")
        return int(kf_a), int(kf_b), distance

    def _default_gauge(self) -> None:
        if self._gauge_explicit:
            return
        kfs = list(self._keyframes)
        if kfs and self._anchor is None:
            self._anchor = (kfs[0], self.pose(kfs[0]))
        if len(kfs) >= 2 and self._range is None:
            distance = float(np.linalg.norm(camera_centre(self.pose(kfs[1])) - camera_centre(self.pose(kfs[0]))))
            if distance > 0.0:  # else no range yet (retried at the next keyframe)
                self._range = (kfs[0], kfs[1], distance)

    def _gauge_factors(self, free_kfs: Iterable[int]) -> list:
        """The gauge factors of an optimisation whose free keyframes are ``free_kfs``."""
        import gtsam

        gauge: GaugeConfig = self.config.gauge
        out = []
        if gauge.fix_anchor and self._anchor is not None:
            kf, prior = self._anchor
            noise = gtsam.noiseModel.Isotropic.Sigma(POSE_DIM, gauge.anchor_sigma)
            out.append(gtsam.PriorFactorSimilarity3(pose_key(kf), prior, noise))
        if gauge.world_scale_range and self._range is not None:
            a, b, distance = self._range
            out.append(range_factor(pose_key(a), pose_key(b), distance, gauge.range_sigma * distance))
        if gauge.hold_scale:
            precisions = np.zeros(POSE_DIM)
            precisions[6] = 1.0 / gauge.scale_sigma**2
            noise = gtsam.noiseModel.Diagonal.Precisions(precisions)
            # The prior's rotation/translation rows have zero precision, so it constrains only
            # lambda = log(s / s_held) of Logmap(prior^-1 T) (scale composes independently).
            for kf in free_kfs:
                held = gtsam.Similarity3(gtsam.Rot3(), np.zeros(3), float(self.pose(kf).scale()))
                out.append(gtsam.PriorFactorSimilarity3(pose_key(kf), held, noise))
        return out

    # ------------------------------------------------------------------ evaluation
    def nonlinear_graph(self, include_gauge: bool = True):
        """Built-in factors (and the gauge factors of a global optimisation) as a NonlinearFactorGraph
        (blocks excluded)."""
        import gtsam

        graph = gtsam.NonlinearFactorGraph()
        for factor, _, _ in self._factors.values():
            graph.add(factor)
        if include_gauge:
            for factor in self._gauge_factors(self._keyframes):
                graph.add(factor)
        return graph

    def _problem(self, free_keys: list[int], refine_steps: int | None = None) -> _WindowProblem:
        """The optimisation problem over ``free_keys`` (module docstring)."""
        import gtsam

        free = set(free_keys)
        free_kfs = [self._key_kf[k] for k in free_keys if k in self._key_kf]
        factors = [(f, keys) for f, keys, _ in self._factors.values()]
        factors += [(f, tuple(int(k) for k in f.keys())) for f in self._gauge_factors(free_kfs)]
        factors = [(f, keys) for f, keys in factors if any(k in free for k in keys)]
        if self.config.window.leaving == "marginalize" and any(any(k not in free for k in keys) for _, keys in factors):
            factors = [(f, keys) for f, keys in factors if all(k in free for k in keys)] + self._marginal_prior(free)
        inner = gtsam.NonlinearFactorGraph()
        cross = []
        for factor, keys in factors:
            if all(k in free for k in keys):
                inner.add(factor)
            elif any(k in free for k in keys):
                cross.append(factor)
        blocks = [b for b in self.blocks() if any(int(k) in free for k in b.keys)]
        needed = set(free)
        for factor in cross:
            needed.update(int(k) for k in factor.keys())
        for block in blocks:
            needed.update(int(k) for k in block.keys)
        steps = self.config.refine_steps if refine_steps is None else refine_steps
        return _WindowProblem(self._subset(needed), sorted(free), inner, cross, blocks, steps,
                              self.config.refine_each_iteration)

    def _subset(self, keys: set):
        """A gtsam.Values with the current values of ``keys``."""
        import gtsam

        if len(keys) == self._values.size():
            return gtsam.Values(self._values)
        if all(k in self._key_kf for k in keys):  # poses only: insert them (cheap for a small window)
            values = gtsam.Values()
            for key in keys:
                values.insert(key, self._values.atSimilarity3(key))
            return values
        values = gtsam.Values(self._values)  # other variable types: copy all, erase the rest
        for key in self._values.keys():
            if int(key) not in keys:
                values.erase(key)
        return values

    def _marginal_prior(self, free: set) -> list:
        """``window.leaving: marginalize``: the persistent built-in factors (and the anchor prior and
        range) that reach a key outside ``free``, linearised at the current estimate, the outside keys
        eliminated; the remaining linear factors on free keys as ``LinearContainerFactor``s (the
        prior they leave on the window)."""
        import gtsam

        outside_factors = [(f, keys) for f, keys, _ in self._factors.values() if any(k not in free for k in keys)]
        outside_factors += [(f, tuple(int(k) for k in f.keys())) for f in self._gauge_factors(())
                            if any(int(k) not in free for k in f.keys())]  # the anchor and the range
        if not outside_factors:
            return []
        gfg = gtsam.GaussianFactorGraph()
        outside = []
        for factor, keys in outside_factors:
            gfg.push_back(factor.linearize(self._values))
            outside.extend(k for k in keys if k not in free and k not in outside)
        reg = self.config.window.marginal_regularization
        dims = {int(k): int(d) for k, d in self._values.dims().items()}
        remaining = _eliminate_keys(gfg, outside, dims, reg, hint="; set map.window.marginal_regularization > 0")
        lin_point = gtsam.Values(self._values)
        for key in self._values.keys():
            if int(key) not in free:
                lin_point.erase(key)
        out = []
        for i in range(remaining.size()):
            factor = remaining.at(i)
            if factor is None or len(factor.keys()) == 0:
                continue
            out.append((gtsam.LinearContainerFactor(factor, lin_point), tuple(int(k) for k in factor.keys())))
        return out

    def cost(self) -> float:
        """GTSAM-convention total cost at the current estimate (global gauge, blocks' current structure)."""
        return self._problem([int(k) for k in self._values.keys()]).cost()

    def linearize(self):
        """gtsam.GaussianFactorGraph of the whole problem at the current estimate (global optimisation's)."""
        return self._problem([int(k) for k in self._values.keys()]).linearize()

    def marginal_covariances(self, kf_ids: list[int] | None = None) -> dict[int, np.ndarray]:
        """Marginal covariances (7, 7) of keyframe poses in the tangent ``[w, u, lambda]`` at the
        current estimate (Laplace approximation of the linearised problem, blocks included)."""
        import gtsam

        with torch_threads(self.config.threads):
            marginals = gtsam.Marginals(self.linearize(), self._values)
        ids = self.keyframe_ids if kf_ids is None else kf_ids
        return {kf: np.asarray(marginals.marginalCovariance(pose_key(kf))) for kf in ids}

    # ------------------------------------------------------------------ optimisation
    def _settings(self, iterations: int | None, window: bool = False) -> LMSettings:
        cfg = self.config
        return LMSettings(
            max_iterations=cfg.max_iterations if iterations is None else int(iterations),
            lambda_initial=cfg.lambda_initial,
            lambda_factor=cfg.window.lambda_factor if window else cfg.lambda_factor, lambda_max=cfg.lambda_max,
            lambda_min=cfg.lambda_min, relative_tolerance=cfg.relative_tolerance,
            absolute_tolerance=cfg.absolute_tolerance, step_tolerance=cfg.step_tolerance,
            max_backtracks=cfg.max_backtracks,
        )

    def optimize_pose(self, blocks, values, key: int, iterations: int | None = None, hold=None):
        """Motion-only optimisation of ``key`` against ``blocks`` whose other keys are held at ``values``
        (a frame tracked against its keyframe; :mod:`fgslam.backend.motion_only`), with the map's LM
        settings. The backend's own graph is not touched; returns a ``MotionOnlyResult``."""
        from .motion_only import optimize_pose

        return optimize_pose(blocks, values, key, self._settings(iterations), hold)

    def optimize_window(self, free_kf_ids: Iterable[int], iterations: int | None = None,
                        extra_free_keys: Iterable[int] = ()) -> OptimizeReport:
        """Optimise the poses of ``free_kf_ids`` (and ``extra_free_keys``, other variables) with every
        other key held fixed or marginalised (``map.window.leaving``; module docstring);
        ``iterations``: LM iterations (default ``map.max_iterations``). Updates the free poses and
        the blocks' structure."""
        free_kf_ids = list(free_kf_ids)
        free = []
        for kf in free_kf_ids:
            self._check_keyframe(kf)
            free.append(pose_key(kf))
            free.extend(self._attached.get(int(kf), ()))  # keys attached to a free keyframe are free
        kfs = [int(kf) for kf in free_kf_ids] if self._window_hooks else []
        extra_free_keys = list(extra_free_keys) + [k for hook in self._window_hooks for k in hook(kfs)]
        for key in extra_free_keys:
            if not self._values.exists(int(key)):
                raise OptimizationError(f"unknown key {key_name(int(key))}")
            free.append(int(key))
        return self._optimize(list(dict.fromkeys(free)), iterations, window=True)

    def optimize_global(self, iterations: int | None = None) -> OptimizeReport:
        """Optimise every key (``iterations``: default ``map.max_iterations``)."""
        return self._optimize([int(k) for k in self._values.keys()], iterations)

    def _optimize(self, free: list[int], iterations: int | None, window: bool = False) -> OptimizeReport:
        start = time.perf_counter()
        kind = self.config.solver_kind
        refine_steps = self.config.window.refine_steps if window else self.config.refine_steps
        with torch_threads(self.config.threads):
            problem = self._problem(free, refine_steps)
            initial = problem.refine(refine_steps)
            propose = _Isam2Stepper(problem) if kind == "isam2" else None
            lm = levenberg_marquardt(problem, self._settings(iterations, window), propose=propose,
                                     initial_cost=initial)  # the cost refine() just evaluated
            final = problem.refine(refine_steps) if refine_steps > 0 else lm.final_cost
        self._write_back(problem)
        report = OptimizeReport(kind, initial, final, lm.iterations, lm.converged, time.perf_counter() - start,
                                len(free))
        logger.debug("optimize: %s", report)
        return report

    def _write_back(self, problem: _WindowProblem) -> None:
        self._values.update(problem.free_values())
        for key in problem.free:
            kf = self._key_kf.get(key)
            if kf is not None:
                self._bump(kf)

    # ------------------------------------------------------------------ pose graph
    def correct_pose_graph(self, kf_ids: Iterable[int] | None = None, iterations: int | None = None) -> dict[int, np.ndarray]:
        """Sim(3) pose-graph correction over ``kf_ids`` (default every keyframe; in insertion order):
        the graph of :meth:`pose_graph_problem`, solved by the one LM loop (or iSAM2 steps). Returns
        the new T_WC (4x4) per keyframe; does not apply them (:meth:`set_pose` does)."""
        graph, values, ids = self.pose_graph_problem(kf_ids)
        if not ids:
            return {}
        problem = NonlinearProblem(graph, values)
        propose = _PoseGraphIsam2(graph, values).bind(problem) if self.config.solver_kind == "isam2" else None
        report = levenberg_marquardt(problem, self._settings(iterations), propose=propose)
        logger.debug("pose graph over %d keyframes: cost %.6g -> %.6g in %d iterations", len(ids),
                     report.initial_cost, report.final_cost, report.iterations)
        at = problem.values.atSimilarity3
        return {kf: gtsam_matrix(at(pose_key(kf))) for kf in ids}

    def pose_graph_problem(self, kf_ids: Iterable[int] | None = None):
        """``(graph, values, ids)`` of the pose-graph correction over ``kf_ids``:
        ``BetweenFactorSimilarity3`` between consecutive keyframes from the current estimate (sigmas
        ``map.pose_graph``), the persistent factors whose keys are all among them (loops, user
        factors), a 7-dof prior (``gauge.anchor_sigma``) on the first at its current pose; ``values``
        a copy of their current poses; ``ids`` the keyframes in insertion order."""
        import gtsam

        ids = self.keyframe_ids if kf_ids is None else [int(k) for k in kf_ids]
        for kf in ids:
            self._check_keyframe(kf)
        order = {kf: i for i, kf in enumerate(self._keyframes)}
        ids = sorted(set(ids), key=order.__getitem__)
        graph = gtsam.NonlinearFactorGraph()
        values = gtsam.Values()
        if not ids:
            return graph, values, ids
        pg = self.config.pose_graph
        sigmas = np.array([pg.rotation_sigma] * 3 + [pg.translation_sigma] * 3 + [pg.log_scale_sigma])
        odometry = diagonal_model(sigmas)
        keys = [pose_key(kf) for kf in ids]
        poses = [self._values.atSimilarity3(key) for key in keys]
        if len(ids) == len(self._keyframes) and self._values.size() == len(ids):
            values = gtsam.Values(self._values)  # one C++ copy (4,541 poses: 2 ms against 0.1 s insert by insert)
        else:
            for key, pose in zip(keys, poses):
                values.insert(key, pose)
        add, between = graph.add, gtsam.BetweenFactorSimilarity3
        for a in range(len(keys) - 1):
            add(between(keys[a], keys[a + 1], poses[a].between(poses[a + 1]), odometry))
        key_set = set(keys)
        for factor, fkeys, _ in self._factors.values():
            if all(k in key_set for k in fkeys):
                add(factor)
        add(anchor_prior(keys[0], poses[0], self.config.gauge.anchor_sigma))
        return graph, values, ids


class _PoseGraphIsam2:
    """iSAM2 step provider of a pose graph (only built-in factors: iSAM2 relinearises them itself)."""

    def __init__(self, graph, values):
        import gtsam

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
