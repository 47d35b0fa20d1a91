"""The differentiable dense BA layer of training (fgslam.nets.dba): the dense block's residual and cost,
convergence of its Gauss-Newton steps, fixed gauge poses, and gradients against finite differences."""

from __future__ import annotations

import gtsam
import pytest
import torch

from fgslam.backend.keys import pose_key
from fgslam.factors.dense import DenseBlock, DenseEdge, DenseKeyframe
from fgslam.core.lie import Sim3
from fgslam.nets.dba import DenseBAStepConfig, dense_ba_step, dense_cost, induced_coords
from nets_support import one_thread  # noqa: F401 (autouse fixture)

N, h, w = 4, 6, 8
K = torch.tensor([9.0, 9.0, 3.5, 2.5], dtype=torch.float64)




def scene(seed=0):
    g = torch.Generator().manual_seed(seed)
    xi = torch.zeros(N, 7, dtype=torch.float64)
    xi[:, 3] = 0.08 * torch.arange(N, dtype=torch.float64)
    xi[:, :3] = 0.03 * torch.randn(N, 3, generator=g, dtype=torch.float64)
    poses = Sim3.exp(xi)
    depth = 0.3 + 0.3 * torch.rand(N, h, w, generator=g, dtype=torch.float64)
    ii = torch.tensor([i for i in range(N) for j in range(N) if i != j and abs(i - j) <= 2])
    jj = torch.tensor([j for i in range(N) for j in range(N) if i != j and abs(i - j) <= 2])
    return poses, depth, ii, jj, g


def perturb(poses, depth, g, scale=0.01):
    xi = scale * torch.randn(N, 7, generator=g, dtype=torch.float64)
    xi[:2] = 0.0
    xi[:, 6] = 0.0
    return poses.retract(xi), depth * (1 + 0.1 * torch.randn(N, h, w, generator=g, dtype=torch.float64))


def test_cost_is_the_dense_blocks_cost():
    poses, depth, ii, jj, g = scene()
    target, _ = induced_coords(poses, depth, K, ii, jj)
    target = target + 0.3 * torch.randn(target.shape, generator=g, dtype=torch.float64)
    weight = torch.rand(target.shape, generator=g, dtype=torch.float64)
    est_poses, est_depth = perturb(poses, depth, g)
    ours = float(dense_cost(est_poses, est_depth, K, ii, jj, target, weight))
    keys = [pose_key(n) for n in range(N)]
    block = DenseBlock([DenseKeyframe(keys[n], est_depth[n]) for n in range(N)],
                       [DenseEdge(keys[int(i)], keys[int(j)], target[e], weight[e]) for e, (i, j) in enumerate(zip(ii, jj))],
                       K)
    values = gtsam.Values()
    for n in range(N):
        values.insert(keys[n], est_poses[n].to_gtsam())
    assert ours == pytest.approx(block.cost(values), rel=1e-10)


def test_steps_converge_to_the_truth_and_keep_the_gauge_poses():
    poses, depth, ii, jj, g = scene(1)
    target, _ = induced_coords(poses, depth, K, ii, jj)
    weight = torch.ones_like(target)
    est_poses, est_depth = perturb(poses, depth, g)
    eta = torch.full((N, h, w), 1e-3, dtype=torch.float64)
    config = DenseBAStepConfig(lm=1e-4, ep=1e-6)
    costs = [float(dense_cost(est_poses, est_depth, K, ii, jj, target, weight))]
    for _ in range(8):
        est_poses, est_depth = dense_ba_step(est_poses, est_depth, K, ii, jj, target, weight, eta, fixed=(0, 1),
                                             config=config)
        costs.append(float(dense_cost(est_poses, est_depth, K, ii, jj, target, weight)))
    assert costs[-1] < 1e-6 * costs[0], costs
    torch.testing.assert_close(est_poses.t[:2], poses.t[:2], rtol=0, atol=1e-14)  # fixed
    torch.testing.assert_close(est_poses.t, poses.t, rtol=0, atol=1e-5)
    torch.testing.assert_close(est_depth, depth, rtol=1e-4, atol=0)
    torch.testing.assert_close(est_poses.s, poses.s)  # scale held


def test_gradients_through_the_step_match_finite_differences():
    poses, depth, ii, jj, g = scene(2)
    target0, _ = induced_coords(poses, depth, K, ii, jj)
    est_poses, est_depth = perturb(poses, depth, g)
    weight0 = 0.2 + 0.8 * torch.rand(target0.shape, generator=g, dtype=torch.float64)
    eta = torch.full((N, h, w), 1e-2, dtype=torch.float64)
    probe = torch.randn(N, 3, generator=g, dtype=torch.float64)

    def loss(weight, target, eta):
        p, d = dense_ba_step(est_poses, est_depth, K, ii, jj, target, weight, eta, fixed=(0, 1))
        return (p.t * probe).sum() + d.mean()

    # a few entries of each input, central differences
    for arg in range(3):
        inputs = [weight0.clone().requires_grad_(arg == 0), target0.clone().requires_grad_(arg == 1),
                  eta.clone().requires_grad_(arg == 2)]
        (grad,) = torch.autograd.grad(loss(*inputs), inputs[arg])
        assert torch.isfinite(grad).all()
        flat = inputs[arg].detach().reshape(-1)
        for idx in torch.randperm(flat.numel(), generator=g)[:4].tolist() + [int(grad.abs().reshape(-1).argmax())]:
            eps = 1e-6
            plus, minus = [x.detach().clone() for x in inputs], [x.detach().clone() for x in inputs]
            plus[arg].reshape(-1)[idx] += eps
            minus[arg].reshape(-1)[idx] -= eps
            fd = (loss(*plus) - loss(*minus)) / (2 * eps)
            assert float(grad.reshape(-1)[idx]) == pytest.approx(float(fd), rel=1e-4, abs=1e-8), (arg, idx)


def test_a_batch_of_clips_is_each_clip_solved_alone_and_float32_follows_float64():
    clips = []
    for seed in (3, 4):
        poses, depth, ii, jj, g = scene(seed)
        target, _ = induced_coords(poses, depth, K, ii, jj)
        target = target + 0.2 * torch.randn(target.shape, generator=g, dtype=torch.float64)
        weight = 0.2 + 0.8 * torch.rand(target.shape, generator=g, dtype=torch.float64)
        eta = torch.full((N, h, w), 1e-2, dtype=torch.float64)
        clips.append((*perturb(poses, depth, g), target, weight, eta))
    alone = [dense_ba_step(p, d, K, ii, jj, t, wt, e, fixed=(0, 1)) for p, d, t, wt, e in clips]
    stack = [torch.stack(x) for x in zip(*[(p.R, p.t, p.s, d, t, wt, e) for p, d, t, wt, e in clips])]
    batch = Sim3(*stack[:3])
    p_b, d_b = dense_ba_step(batch, stack[3], K, ii, jj, *stack[4:], fixed=(0, 1))
    assert p_b.shape == (2, N) and d_b.shape == (2, N, h, w)
    for b, (p, d) in enumerate(alone):
        torch.testing.assert_close(p_b.t[b], p.t, rtol=0, atol=1e-12)
        torch.testing.assert_close(p_b.R[b], p.R, rtol=0, atol=1e-12)
        torch.testing.assert_close(d_b[b], d, rtol=1e-12, atol=0)
    assert (dense_cost(batch, stack[3], K, ii, jj, stack[4], stack[5]).tolist()
            == pytest.approx([float(dense_cost(p, d, K, ii, jj, t, wt)) for p, d, t, wt, _ in clips], rel=1e-12))
    # the same step in float32 (training on a GPU): the step itself agrees to float32 precision
    p32, d32 = dense_ba_step(batch.to(torch.float32), stack[3].float(), K.float(), ii, jj,
                             *[x.float() for x in stack[4:]], fixed=(0, 1))
    assert p32.dtype == torch.float32 and d32.dtype == torch.float32
    step64 = (p_b.t - batch.t).abs().max()
    assert step64 > 1e-3  # the step moves the poses: the comparison below is not of two no-ops
    torch.testing.assert_close(p32.t.double(), p_b.t, rtol=0, atol=1e-4 * float(step64))
    torch.testing.assert_close((d32.double() - stack[3]), (d_b - stack[3]), rtol=0,
                               atol=1e-4 * float((d_b - stack[3]).abs().max()))
