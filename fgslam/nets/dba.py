"""The dense bundle-adjustment layer inside the training graph (DROID-SLAM section 3.3): differentiable
Gauss-Newton steps on keyframe poses and 1/8-resolution inverse depths, built from the frontends' own
pieces, so training and the dense frontend minimise the same cost:

- residuals and Jacobians: :func:`fgslam.factors.reprojection.reproject_inv_depth` (the residual of the
  dense block :mod:`fgslam.factors.dense`, DROID eq. 4), batched torch, differentiable by autograd;
- per-pixel Schur elimination of the inverse depths with DROID's damping ``eta`` on the depth block
  (eq. 5): :func:`fgslam.factors.schur.eliminate_structure` and :meth:`SchurSystem.back_substitute`;
- pose updates: :meth:`fgslam.lie.Sim3.retract` (right perturbation, tangent ``[w, u, lambda]``).

What differs from the frontend is only the assembly of ``J^T W J`` (``schur_reduce`` accumulates
into preallocated buffers with ``out=``, which autograd cannot follow; here one-hot slot matrices
and ``einsum``) and the solver (a damped Gauss-Newton step, DROID's ``H + (ep + lm diag H)``, instead
of the backend's GTSAM LM loop). Poses ``fixed`` (the first two in training: the gauge, including the
monocular scale) do not move; every pose's scale is held (6 free dof), as the monocular frontends do.
"""

from __future__ import annotations

import warnings
from collections.abc import Sequence
from dataclasses import dataclass

import torch

from ..config import MAX_LAMBDA, MAX_SCALAR, ranged
from ..factors.reprojection import ReprojectionConfig, reproject, reproject_inv_depth
from ..factors.schur import eliminate_structure
from ..lie import Sim3

__all__ = ["DenseBAStepConfig", "dense_ba_step", "dense_cost", "induced_coords"]

POSE_DOF = 6  # rotation and translation; the scale column (lambda) is held


@dataclass
class DenseBAStepConfig:
    """Damping of the differentiable dense BA step (DROID-SLAM's training BA)."""

    lm: float = ranged(1e-4, ge=0, le=MAX_LAMBDA)  # Levenberg-Marquardt: + lm * diag(H) on the poses
    ep: float = ranged(0.1, ge=0, le=MAX_SCALAR)  # + ep on every pose diagonal entry
    min_inv_depth: float = ranged(1e-3, gt=0, le=MAX_SCALAR)  # inverse depths are clamped to at least this after a step
    min_information: float = ranged(1e-9, ge=0, le=MAX_SCALAR)  # pixels with less depth information are not updated
    reprojection: ReprojectionConfig = None  # validity of reprojections (None: the frontends' default)

    def __post_init__(self) -> None:
        if self.reprojection is None:
            self.reprojection = ReprojectionConfig()


def _grid(h: int, w: int, like: torch.Tensor) -> torch.Tensor:
    y, x = torch.meshgrid(torch.arange(h, dtype=like.dtype, device=like.device),
                          torch.arange(w, dtype=like.dtype, device=like.device), indexing="ij")
    return torch.stack((x, y), -1)


def induced_coords(poses: Sim3, inv_depth: torch.Tensor, K: torch.Tensor, ii: torch.Tensor, jj: torch.Tensor,
                   config: DenseBAStepConfig | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Each grid pixel of ``i`` reprojected into ``j`` for edges ``(ii, jj)``: ``(E, h, w, 2)`` and validity."""
    config = config or DenseBAStepConfig()
    N, h, w = inv_depth.shape
    uv = _grid(h, w, inv_depth)[None].expand(len(ii), h, w, 2)
    Ti, Tj = poses[ii], poses[jj]
    return reproject(uv, inv_depth[ii], _expand(Ti), _expand(Tj), K, config=config.reprojection)


def _expand(T: Sim3) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Pose batch ``(E,)`` broadcast over an ``(E, h, w)`` pixel batch."""
    return T.R[:, None, None], T.t[:, None, None], T.s[:, None, None]


def _linearize(poses, inv_depth, K, ii, jj, target, config):
    N, h, w = inv_depth.shape
    uv = _grid(h, w, inv_depth)[None].expand(len(ii), h, w, 2)
    return reproject_inv_depth(uv, inv_depth[ii], _expand(poses[ii]), _expand(poses[jj]), K, target,
                               config=config.reprojection)


def dense_cost(poses: Sim3, inv_depth: torch.Tensor, K: torch.Tensor, ii, jj, target, weight,
               config: DenseBAStepConfig | None = None) -> torch.Tensor:
    """``0.5 sum w r^2`` (the dense block's cost, GTSAM convention)."""
    config = config or DenseBAStepConfig()
    res = _linearize(poses, inv_depth, K, ii, jj, target, config)
    w = torch.where(res.valid[..., None], weight, torch.zeros_like(weight))
    return 0.5 * (w * res.residual ** 2).sum()


def dense_ba_step(poses: Sim3, inv_depth: torch.Tensor, K: torch.Tensor, ii: torch.Tensor, jj: torch.Tensor,
                  target: torch.Tensor, weight: torch.Tensor, eta: torch.Tensor, fixed: Sequence[int],
                  config: DenseBAStepConfig | None = None) -> tuple[Sim3, torch.Tensor]:
    """One damped Gauss-Newton step (module docstring).

    ``poses`` ``(N,)`` Sim(3) ``T_WC``; ``inv_depth`` ``(N, h, w)``; ``K`` ``(4,)`` grid intrinsics;
    ``target``, ``weight`` ``(E, h, w, 2)`` (``p*_ij`` and ``w_ij``); ``eta`` ``(N, h, w)`` depth damping;
    ``fixed`` pose indices held. Returns the new poses and inverse depths (differentiable in every input).
    """
    config = config or DenseBAStepConfig()
    N, h, w = inv_depth.shape
    dt = inv_depth.dtype
    free = [n for n in range(N) if n not in set(int(f) for f in fixed)]
    slot = torch.full((N,), -1, dtype=torch.long)
    slot[free] = torch.arange(len(free))
    k = len(free)
    res = _linearize(poses, inv_depth, K, ii, jj, target, config)
    W = torch.where(res.valid[..., None], weight.to(dt), torch.zeros((), dtype=dt))  # (E, h, w, 2)
    r = res.residual
    # pose Jacobians scattered into the free slots: (E, h, w, 2, k, 6)
    onehot_i = torch.nn.functional.one_hot(slot[ii].clamp(min=0), k).to(dt) * (slot[ii] >= 0).to(dt)[:, None]
    onehot_j = torch.nn.functional.one_hot(slot[jj].clamp(min=0), k).to(dt) * (slot[jj] >= 0).to(dt)[:, None]
    J = (torch.einsum("ehwrd,ek->ehwrkd", res.J_Ti[..., :POSE_DOF], onehot_i)
         + torch.einsum("ehwrd,ek->ehwrkd", res.J_Tj[..., :POSE_DOF], onehot_j)).reshape(len(ii), h, w, 2, k * POSE_DOF)
    H = torch.einsum("ehwr,ehwra,ehwrb->ab", W, J, J)
    g = torch.einsum("ehwr,ehwra,ehwr->a", W, J, r)
    c = (W * r * r).sum()
    # per-pixel structure of the source frames: (N, h, w) summed over each frame's edges
    src = torch.nn.functional.one_hot(ii, N).to(dt)  # (E, N)
    wE = W * res.J_d
    C = torch.einsum("en,ehw->nhw", src, (wE * res.J_d).sum(-1)) + eta.to(dt)
    b = torch.einsum("en,ehw->nhw", src, (wE * r).sum(-1))
    F = torch.einsum("en,ehwa->nhwa", src, torch.einsum("ehwr,ehwra->ehwa", wE, J))
    with warnings.catch_warnings():  # the reduced constant c (a float there) is not needed here
        warnings.filterwarnings("ignore", message="Converting a tensor with requires_grad", category=UserWarning)
        system = eliminate_structure(H, g, c.detach(), F.reshape(N * h * w, -1), b.reshape(-1), C.reshape(-1),
                                     config.min_information)
    Hs = system.H + torch.diag(config.ep + config.lm * torch.diagonal(system.H))
    dx = -torch.linalg.solve(Hs, system.g)
    dd = system.back_substitute(dx).reshape(N, h, w)
    xi = torch.zeros(N, 7, dtype=dt)
    xi = xi.index_put((torch.tensor(free, dtype=torch.long),), torch.cat(
        [dx.reshape(k, POSE_DOF), torch.zeros(k, 1, dtype=dt)], -1)) if k else xi
    new_poses = poses.retract(xi)
    new_depth = (inv_depth + dd).clamp(min=config.min_inv_depth)
    return new_poses, new_depth
