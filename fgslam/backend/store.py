"""What the backend holds (docs/architecture.md section 8): keyframe poses, other variables, built-in
factors with owners and handles, and the contributors' blocks.

Keyframe ``kf`` has the gtsam key :func:`~fgslam.backend.keys.pose_key` ``= gtsam.symbol('x', kf)``
holding a ``gtsam.Similarity3`` T_WC (camera-to-world; fgslam.core.lie's ``Sim3(R, t, s)`` maps to
``Similarity3(Rot3(R), t / s, s)``), and a timestamp. Other variables (velocities, biases, plugin
variables) are added by key, optionally attached to a keyframe (:meth:`GraphStore.attach_key`: free,
fixed, marginalised and removed with it). :class:`FactorTable` holds the built-in gtsam factors (each
with an ``owner``, until removed or until a key it touches is removed) and the blocks per owner.
"""

from __future__ import annotations

from typing import Callable, Iterable

import numpy as np

from ..core.errors import OptimizationError
from ..core.lie import Sim3, gtsam_matrix, gtsam_sim3
from .keys import key_name, pose_key


def as_similarity3(T_WC):
    """``gtsam.Similarity3`` of a pose given as one, as an unbatched :class:`fgslam.core.lie.Sim3` or as a
    (4, 4) Sim(3) matrix ``[[s R, t], [0, 1]]`` (R projected onto SO(3))."""
    import gtsam  # deferred: gtsam

    if isinstance(T_WC, gtsam.Similarity3):
        return T_WC
    if isinstance(T_WC, Sim3):
        return T_WC.to_gtsam()
    M = np.asarray(T_WC, dtype=np.float64)
    if M.shape != (4, 4) or not np.isfinite(M).all():
        raise OptimizationError(f"a pose must be a finite 4x4 Sim(3) matrix, a Sim3 or a gtsam.Similarity3, got shape {M.shape}")
    return gtsam_sim3(M)


class FactorTable:
    """Built-in gtsam factors by handle (with their keys and owner) and the contributors' blocks by
    owner (blocks of different owners on the same keys add up)."""

    def __init__(self, has_key: Callable[[int], bool]):
        self._has_key = has_key
        self.entries: dict[int, tuple[object, tuple[int, ...], str]] = {}  # handle -> (factor, keys, owner)
        self._next_handle = 0
        self._blocks: dict[str, list] = {}

    def add(self, factor, owner: str = "user") -> int:
        """Add a gtsam nonlinear factor on existing keys; returns its handle.

        Raises:
            OptimizationError: a key of the factor is not in the backend (named, e.g. ``x12``).
        """
        keys = tuple(int(k) for k in factor.keys())
        for key in keys:
            if not self._has_key(key):
                raise OptimizationError(f"factor of '{owner}' on unknown key {key_name(key)}: add the keyframe or variable first")
        handle = self._next_handle
        self._next_handle += 1
        self.entries[handle] = (factor, keys, str(owner))
        return handle

    def remove(self, handle: int) -> None:
        if handle not in self.entries:
            raise OptimizationError(f"no factor with handle {handle}")
        del self.entries[handle]

    def handles(self, owner: str) -> list[int]:
        """Handles of the factors ``owner`` added (in order)."""
        return [h for h, (_, _, o) in self.entries.items() if o == owner]

    def factor(self, handle: int):
        return self.entries[handle][0]

    def drop_key(self, key: int, blocks: bool) -> None:
        """Remove every factor on ``key`` (and with ``blocks`` every block on it)."""
        for handle in [h for h, (_, keys, _) in self.entries.items() if key in keys]:
            del self.entries[handle]
        if blocks:
            for owner, owned in self._blocks.items():
                self._blocks[owner] = [b for b in owned if key not in b.keys]

    def set_blocks(self, owner: str, blocks: list) -> None:
        """Replace contributor ``owner``'s blocks (an empty list removes them). Blocks of different
        owners on the same keys add up.

        Raises:
            OptimizationError: a block touches a key that is not in the backend (named).
        """
        blocks = list(blocks)
        for block in blocks:
            for key in block.keys:
                if not self._has_key(int(key)):
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


class GraphStore:
    """Keyframes (pose keys, timestamps, pose versions), other variables and the keys attached to
    keyframes, the :class:`FactorTable` (``factors``) and the keyframe callbacks.

    ``estimate`` is the live ``gtsam.Values`` (the solves read and update it), ``keyframe_of`` maps a
    pose key to its keyframe, ``attached`` a keyframe to its attached keys.
    """

    def __init__(self):
        import gtsam  # deferred: gtsam

        self.estimate = gtsam.Values()
        self.factors = FactorTable(self.has_key)
        self._keyframes: dict[int, float] = {}  # kf_id -> timestamp, in insertion order
        self._callbacks: list[Callable] = []
        self._removed_callbacks: list[Callable] = []
        self.attached: dict[int, list[int]] = {}  # kf_id -> keys attached to it (velocity, bias, ...)
        self._attached_kf: dict[int, int] = {}  # attached key -> kf_id
        self.keyframe_of: dict[int, int] = {}  # pose key -> kf_id
        self._versions: dict[int, int] = {}  # kf_id -> version of its pose (changes on every update)
        self._version = 0

    # ------------------------------------------------------------------ keyframes
    @property
    def keyframe_ids(self) -> list[int]:
        return list(self._keyframes)

    def has_keyframe(self, kf_id: int) -> bool:
        return int(kf_id) in self._keyframes

    def has_key(self, key: int) -> bool:
        return bool(self.estimate.exists(int(key)))

    def timestamp(self, kf_id: int) -> float:
        self.check_keyframe(kf_id)
        return self._keyframes[int(kf_id)]

    def check_keyframe(self, kf_id: int) -> None:
        """Raises ``OptimizationError`` (naming the key) unless ``kf_id`` is a keyframe of the backend."""
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
        if self.estimate.exists(key):
            raise OptimizationError(f"keyframe {kf_id} ({key_name(key)}) is already in the backend")
        self.estimate.insert(key, as_similarity3(T_WC))
        self._keyframes[kf_id] = float(timestamp)
        self.keyframe_of[key] = kf_id
        self._bump(kf_id)
        for callback in self._callbacks:
            callback(kf_id, float(timestamp), key)
        return key

    def remove_keyframe(self, kf_id: int) -> None:
        """Remove keyframe ``kf_id``, every factor and every block that involves it (no marginalisation)
        and the keys attached to it; calls the ``on_keyframe_removed`` callbacks."""
        self.check_keyframe(kf_id)
        kf_id = int(kf_id)
        key = pose_key(kf_id)
        self.factors.drop_key(key, blocks=True)
        for attached in self.attached.pop(kf_id, []):  # keys attached to the keyframe go with it
            self.remove_variable(attached)
        self.estimate.erase(key)
        del self._keyframes[kf_id]
        del self._versions[kf_id]
        del self.keyframe_of[key]
        for callback in self._removed_callbacks:
            callback(kf_id)

    def on_keyframe(self, callback: Callable[[int, float, int], None]) -> None:
        """Register ``callback(kf_id, timestamp, key)``, called after every :meth:`add_keyframe`."""
        self._callbacks.append(callback)

    def on_keyframe_removed(self, callback: Callable[[int], None]) -> None:
        """Register ``callback(kf_id)``, called after every :meth:`remove_keyframe` (its factors and
        attached keys are gone already)."""
        self._removed_callbacks.append(callback)

    # ------------------------------------------------------------------ other variables
    def add_variable(self, key: int, value, attach_to: int | None = None) -> None:
        """Add a non-keyframe variable (velocity, bias, plugin variable) with its initial value;
        ``attach_to``: a keyframe the variable belongs to (:meth:`attach_key`)."""
        key = int(key)
        if self.estimate.exists(key):
            raise OptimizationError(f"variable {key_name(key)} is already in the backend")
        if attach_to is not None:
            self.check_keyframe(attach_to)
        self.estimate.insert(key, value)
        if attach_to is not None:
            self.attach_key(key, attach_to)

    def attach_key(self, key: int, kf_id: int) -> None:
        """Attach variable ``key`` to keyframe ``kf_id``: it is free in every window where the keyframe
        is (``optimize_window``), outside it where the keyframe is (held fixed or marginalised
        with it), and removed with the keyframe (:meth:`remove_keyframe`)."""
        key, kf_id = int(key), int(kf_id)
        self.check_keyframe(kf_id)
        self.check_variable(key, "only an existing non-keyframe variable can be attached, not {}")
        previous = self._attached_kf.get(key)
        if previous is not None:
            self.attached[previous].remove(key)
        self._attached_kf[key] = kf_id
        self.attached.setdefault(kf_id, []).append(key)

    def attached_keys(self, kf_id: int) -> list[int]:
        """Variables attached to keyframe ``kf_id`` (:meth:`attach_key`)."""
        return list(self.attached.get(int(kf_id), []))

    def check_variable(self, key: int, message: str) -> None:
        """Raises ``OptimizationError`` (``message`` with the key's name for ``{}``) unless ``key`` is
        an existing non-keyframe variable."""
        if not self.estimate.exists(key) or key in self.keyframe_of:
            raise OptimizationError(message.format(key_name(key)))

    def remove_variable(self, key: int) -> None:
        """Remove a non-keyframe variable and every factor on it."""
        key = int(key)
        if not self.estimate.exists(key):
            raise OptimizationError(f"variable {key_name(key)} is not in the backend")
        self.factors.drop_key(key, blocks=False)
        self.estimate.erase(key)
        kf_id = self._attached_kf.pop(key, None)
        if kf_id is not None and key in self.attached.get(kf_id, []):
            self.attached[kf_id].remove(key)

    # ------------------------------------------------------------------ values
    def pose(self, kf_id: int):
        """Current T_WC of keyframe ``kf_id`` (gtsam.Similarity3)."""
        self.check_keyframe(kf_id)
        return self.estimate.atSimilarity3(pose_key(kf_id))

    def pose_matrix(self, kf_id: int) -> np.ndarray:
        """Current T_WC of keyframe ``kf_id`` as a (4, 4) Sim(3) matrix."""
        return gtsam_matrix(self.pose(kf_id))

    def poses(self, kf_ids: Iterable[int] | None = None) -> Sim3:
        """Current T_WC of ``kf_ids`` (default all, in insertion order) as a batched fgslam Sim3."""
        ids = self.keyframe_ids if kf_ids is None else list(kf_ids)
        return Sim3.from_gtsam([self.pose(k) for k in ids])

    def set_pose(self, kf_id: int, T_WC) -> None:
        """Overwrite keyframe ``kf_id``'s pose (a pose-graph correction, a frontend's restore)."""
        self.check_keyframe(kf_id)
        self.estimate.update(pose_key(kf_id), as_similarity3(T_WC))
        self._bump(int(kf_id))

    def set_value(self, key: int, value) -> None:
        """Overwrite a non-keyframe variable's value (e.g. velocities rescaled with the map)."""
        key = int(key)
        self.check_variable(key, "set_value: {} is not a non-keyframe variable of the backend")
        self.estimate.update(key, value)

    def update(self, values, keys: Iterable[int]) -> None:
        """Write ``values`` (a solve's result) into the estimate; ``keys``: those it changed (their
        keyframes' pose versions move on)."""
        self.estimate.update(values)
        for key in keys:
            kf = self.keyframe_of.get(key)
            if kf is not None:
                self._bump(kf)

    def values_of(self, keys: Iterable[int]):
        """A gtsam.Values with the current values of ``keys`` (e.g. a block's keys)."""
        import gtsam  # deferred: gtsam

        keys = {int(k) for k in keys}
        for key in keys:
            if not self.estimate.exists(key):
                raise OptimizationError(f"unknown key {key_name(key)}")
        if len(keys) == self.estimate.size():
            return gtsam.Values(self.estimate)
        if all(k in self.keyframe_of for k in keys):  # poses only: insert them (cheap for a small window)
            values = gtsam.Values()
            for key in keys:
                values.insert(key, self.estimate.atSimilarity3(key))
            return values
        values = gtsam.Values(self.estimate)  # other variable types: copy all, erase the rest
        for key in self.estimate.keys():
            if int(key) not in keys:
                values.erase(key)
        return values

    @property
    def values(self):
        """A copy of the current gtsam.Values."""
        import gtsam  # deferred: gtsam

        return gtsam.Values(self.estimate)
