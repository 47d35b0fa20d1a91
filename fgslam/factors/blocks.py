"""The contract of a measurement block that a frontend hands to the backend.

A block owns its measurements (and, for inverse-depth frontends, their structure, eliminated by a
Schur complement when linearised: docs/architecture.md section 5) and touches a set of pose keys. The
backend adds the blocks' linear pieces to the linearised GTSAM graph, so two contributors may add
blocks on the same keys. A pose-only block (the pointmap family's ray factors) has no structure.

:class:`fgslam.factors.visual_block.VisualBlock` satisfies :class:`Block` with structure.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol, runtime_checkable

import numpy as np


@dataclass
class LinearPiece:
    """One Gaussian contribution in GTSAM's cost convention: ``0.5 (dx^T H dx + 2 g^T dx + c)`` over
    the tangents of ``keys`` (in order, each of its variable's dimension)."""

    keys: tuple[int, ...]
    H: np.ndarray
    g: np.ndarray
    c: float

    def __iter__(self):
        """``keys, H, g, c = piece``."""
        return iter((self.keys, self.H, self.g, self.c))


def weighted_piece(keys: tuple[int, ...], J, e, row_weight, cost: float) -> LinearPiece:
    """The :class:`LinearPiece` of robustly weighted rows over ``keys``: ``H = J^T W J``,
    ``g = J^T W e``, ``c = 2 cost`` (IRLS weights ``W``; GTSAM's ``0.5 (dx^T H dx + 2 g^T dx + c)``
    then is the kernel's Gauss-Newton model of ``cost``). ``J``: ``(N, m, D)`` whitened Jacobian over
    the keys' tangents in order; ``e``, ``row_weight``: ``(N, m)`` whitened residuals and their
    weights (numpy arrays or CPU torch tensors, computed in their own library); ``cost``: the kernel
    cost at ``e``."""
    D = J.shape[-1]
    Jr = J.reshape(-1, D)
    wr = row_weight.reshape(-1)
    H = Jr.T @ (wr[:, None] * Jr)
    g = Jr.T @ (wr * e.reshape(-1))
    return LinearPiece(tuple(keys), np.asarray(H), np.asarray(g), 2.0 * float(cost))


@runtime_checkable
class Block(Protocol):
    """A contributor's measurement block (module docstring)."""

    keys: tuple[int, ...]  # pose keys it touches (all must exist in the backend)
    has_structure: bool  # False: a pose-only block

    def linearize(self, values) -> list[LinearPiece]:
        """Linear pieces at ``values`` (one for a window block, many for a global one)."""

    def cost(self, values, structure=None) -> float:
        """GTSAM-convention cost at ``values`` (and ``structure``, default: the current one)."""


@runtime_checkable
class StructureBlock(Block, Protocol):
    """A block with its own structure, eliminated in :meth:`linearize`."""

    @property
    def structure(self): ...

    def set_structure(self, structure) -> None: ...

    def clamp_structure(self, structure): ...

    def back_substitute(self, delta):
        """Structure update for the pose update ``delta`` at the last linearisation point."""

    def refine_structure(self, values, steps: int | None = None) -> float: ...
