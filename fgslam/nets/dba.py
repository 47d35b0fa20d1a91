"""The dense bundle-adjustment layer inside the training graph (DROID-SLAM section 3.3): differentiable
Gauss-Newton steps on keyframe poses and 1/8-resolution inverse depths, built from the frontends' own
pieces, so training and the dense frontend minimise the same cost:

- residuals and Jacobians: :func:`fgslam.factors.reprojection.reproject_inv_depth` (the residual of the
  dense block :mod:`fgslam.factors.dense`, DROID eq. 4), batched torch, differentiable by autograd;
- per-pixel Schur elimination of the inverse depths with DROID's damping ``eta`` on the depth block
  (eq. 5): :func:`fgslam.factors.schur.eliminate_structure` and :meth:`SchurSystem.back_substitute`;
- pose updates: :meth:`fgslam.core.lie.Sim3.retract` (right perturbation, tangent ``[w, u, lambda]``).

What differs from the frontend is only the assembly of ``J^T W J`` (``schur_reduce`` accumulates
into preallocated buffers with ``out=``, which autograd cannot follow; here one-hot slot matrices
and ``einsum``) and the solver (a damped Gauss-Newton step, DROID's ``H + (ep + lm diag H)``, instead
of the backend's GTSAM LM loop). Poses ``fixed`` (the first two in training: the gauge, including the
monocular scale) do not move; every pose's scale is held (6 free dof), as the monocular frontends do.

Batched over clips: with a leading batch dimension (``poses (B, N)``, ``inv_depth (B, N, h, w)``,
``target``/``weight (B, E, h, w, 2)``, ``eta (B, N, h, w)``) every clip is one system of the same frame
graph ``(ii, jj)``, solved at once (one batched Schur elimination and solve, no loop over clips). The
step runs in the dtype and on the device of ``inv_depth`` (float32 on a GPU in training; the tests
check it against float64).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import torch

from ..core.config import MAX_LAMBDA, MAX_SCALAR, ranged
from ..factors.reprojection import ReprojectionConfig, reproject, reproject_inv_depth
from ..factors.schur import eliminate_structure
from ..core.lie import Sim3

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


def _batched(poses: Sim3, inv_depth: torch.Tensor) -> tuple[Sim3, torch.Tensor, bool]:
    """``(B, N)`` poses and ``(B, N, h, w)`` depths (a single clip gets ``B = 1``) and whether it had none."""
    if inv_depth.dim() == 3:
        return Sim3(poses.R[None], poses.t[None], poses.s[None]), inv_depth[None], True
    return poses, inv_depth, False


def _edge_poses(poses: Sim3, idx: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Poses ``(B, N)`` of the edges' frames ``idx`` ``(E,)``, broadcast over ``(B, E, h, w)`` pixels."""
    idx = idx.to(poses.R.device)
    return (poses.R[:, idx, None, None], poses.t[:, idx, None, None],
            poses.s.expand(poses.R.shape[:-2])[:, idx, None, None])


def induced_coords(poses: Sim3, inv_depth: torch.Tensor, K: torch.Tensor, ii: torch.Tensor, jj: torch.Tensor,
                   config: DenseBAStepConfig | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Each grid pixel of ``i`` reprojected into ``j`` for edges ``(ii, jj)``: ``(E, h, w, 2)`` and validity
    (``(B, E, h, w, 2)`` for a batch of clips)."""
    config = config or DenseBAStepConfig()
    poses, inv_depth, single = _batched(poses, inv_depth)
    B, N, h, w = inv_depth.shape
    ii_d = ii.to(inv_depth.device)
    uv = _grid(h, w, inv_depth).expand(B, len(ii), h, w, 2)
    uv, valid = reproject(uv, inv_depth[:, ii_d], _edge_poses(poses, ii), _edge_poses(poses, jj), K.to(inv_depth),
                          config=config.reprojection)
    return (uv[0], valid[0]) if single else (uv, valid)


def _linearize(poses, inv_depth, K, ii, jj, target, config):
    B, N, h, w = inv_depth.shape
    uv = _grid(h, w, inv_depth).expand(B, len(ii), h, w, 2)
    return reproject_inv_depth(uv, inv_depth[:, ii.to(inv_depth.device)], _edge_poses(poses, ii),
                               _edge_poses(poses, jj), K.to(inv_depth), target, config=config.reprojection)


def dense_cost(poses: Sim3, inv_depth: torch.Tensor, K: torch.Tensor, ii, jj, target, weight,
               config: DenseBAStepConfig | None = None) -> torch.Tensor:
    """``0.5 sum w r^2`` (the dense block's cost, GTSAM convention; per clip ``(B,)`` for a batch)."""
    config = config or DenseBAStepConfig()
    poses, inv_depth, single = _batched(poses, inv_depth)
    res = _linearize(poses, inv_depth, K, ii, jj, target.reshape(-1, *target.shape[-4:]), config)
    w = torch.where(res.valid[..., None], weight.reshape(res.residual.shape), torch.zeros_like(res.residual))
    cost = 0.5 * (w * res.residual ** 2).sum((1, 2, 3, 4))
    return cost[0] if single else cost


def dense_ba_step(poses: Sim3, inv_depth: torch.Tensor, K: torch.Tensor, ii: torch.Tensor, jj: torch.Tensor,
                  target: torch.Tensor, weight: torch.Tensor, eta: torch.Tensor, fixed: Sequence[int],
                  config: DenseBAStepConfig | None = None) -> tuple[Sim3, torch.Tensor]:
    """One damped Gauss-Newton step (module docstring).

    ``poses`` ``(N,)`` Sim(3) ``T_WC``; ``inv_depth`` ``(N, h, w)``; ``K`` ``(4,)`` grid intrinsics;
    ``target``, ``weight`` ``(E, h, w, 2)`` (``p*_ij`` and ``w_ij``); ``eta`` ``(N, h, w)`` depth damping;
    ``fixed`` pose indices held (in every clip). With a leading batch dimension ``B`` on ``poses``,
    ``inv_depth``, ``target``, ``weight`` and ``eta``, ``B`` clips of the same graph are solved at once.
    The step runs in ``inv_depth``'s dtype and device. Returns the new poses and inverse depths
    (differentiable in every input).
    """
    config = config or DenseBAStepConfig()
    poses, inv_depth, single = _batched(poses, inv_depth)
    B, N, h, w = inv_depth.shape
    E = len(ii)
    dt, dev = inv_depth.dtype, inv_depth.device
    target, weight = target.reshape(B, E, h, w, 2), weight.reshape(B, E, h, w, 2)
    eta = eta.reshape(B, N, h, w)
    ii, jj = ii.to(dev), jj.to(dev)
    # the free poses' slots 0..k-1 (-1: fixed), built on the device: no host round trip inside the step
    fixed_set = set(int(f) for f in fixed if 0 <= int(f) < N)
    k = N - len(fixed_set)
    free = torch.ones(N, dtype=torch.bool, device=dev)
    for f in fixed_set:
        free[f] = False
    slot = torch.where(free, torch.cumsum(free.long(), 0) - 1, -1)
    slots = torch.arange(k, device=dev)
    res = _linearize(poses, inv_depth, K, ii, jj, target, config)
    W = torch.where(res.valid[..., None], weight.to(dt), torch.zeros((), dtype=dt, device=dev))  # (B, E, h, w, 2)
    r = res.residual
    # pose Jacobians scattered into the free slots: (B, E, h, w, 2, k * 6); a fixed pose's row is zero
    onehot_i = (slot[ii, None] == slots).to(dt)
    onehot_j = (slot[jj, None] == slots).to(dt)
    J = (torch.einsum("behwrd,ek->behwrkd", res.J_Ti[..., :POSE_DOF], onehot_i)
         + torch.einsum("behwrd,ek->behwrkd", res.J_Tj[..., :POSE_DOF], onehot_j)).reshape(B, E, h, w, 2, k * POSE_DOF)
    WJ = (W[..., None] * J).reshape(B, -1, k * POSE_DOF)
    H = WJ.transpose(1, 2) @ J.reshape(B, -1, k * POSE_DOF)
    g = (WJ.transpose(1, 2) @ r.reshape(B, -1, 1))[..., 0]
    c = (W * r * r).sum((1, 2, 3, 4))
    # per-pixel structure of the source frames: (B, N, h, w) summed over each frame's edges
    src = (ii[:, None] == torch.arange(N, device=dev)).to(dt)  # (E, N)
    wE = W * res.J_d
    C = torch.einsum("en,behw->bnhw", src, (wE * res.J_d).sum(-1)) + eta.to(dt)
    b = torch.einsum("en,behw->bnhw", src, (wE * r).sum(-1))
    F = torch.einsum("en,behwa->bnhwa", src, torch.einsum("behwr,behwra->behwa", wE, J))
    system = eliminate_structure(H, g, c.detach(), F.reshape(B, N * h * w, -1), b.reshape(B, -1), C.reshape(B, -1),
                                 config.min_information)
    diag = torch.diagonal(system.H, dim1=-2, dim2=-1)
    Hs = system.H + torch.diag_embed(config.ep + config.lm * diag)
    # Hs is positive definite for ep > 0 (a Schur complement plus ep I); solve_ex skips linalg.solve's
    # singularity check, a device sync per step (eliminate_structure's finiteness check stays)
    dx = -torch.linalg.solve_ex(Hs, system.g[..., None])[0][..., 0]  # (B, 6 k)
    dd = system.back_substitute(dx).reshape(B, N, h, w)
    # pose tangents [w, u, lambda] of every frame: the free slots' steps, zero on the fixed poses and the scale
    place = (slot[:, None] == slots).to(dt)  # (N, k)
    xi = torch.cat([torch.einsum("nk,bkd->bnd", place, dx.reshape(B, k, POSE_DOF)),
                    torch.zeros(B, N, 1, dtype=dt, device=dev)], -1)
    new_poses = poses.retract(xi)
    new_depth = (inv_depth + dd).clamp(min=config.min_inv_depth)
    if single:
        return new_poses[0], new_depth[0]
    return new_poses, new_depth
