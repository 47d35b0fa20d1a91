"""Train DROID-SLAM's network on synthetic clips (DROID-SLAM section 3.3); checkpoints in the format the
loaders read (``droid.pth``: :func:`fgslam.nets.checkpoint.load_droid`).

Data: one synthetic sequence (``--preset``, rendered at ``--width x --height`` and ``--pool-rate`` Hz
for ``--pool-frames`` frames, with exact poses and depth). A clip is a random walk of ``--clip-frames``
(7) frames through it where each step's mean induced flow (from the exact depth and poses) lies in
``[--flow-min, --flow-max]`` (8-96 px as in DROID). Flow is measured in pixels of an image
``--flow-reference-width`` (512, DROID's training width) wide: at 128 px a 96 px flow of a 512-px
image is 24 px, which keeps the same fraction of the view.

Per clip: features and context of the 7 frames; a frame graph of the edges between frames at most
``--edge-radius`` apart; the first two poses fixed to the ground truth (the gauge, with the scale);
the other poses start at the second pose and every inverse-depth map at the first frame's median.
``--iterations`` unrolled update iterations, each: correlation lookup at the current reprojection,
the update operator (revision, confidence, damping), ``--ba-steps`` steps of the differentiable
dense BA (:mod:`fgslam.nets.dba`: the dense frontend's residual, Schur elimination and retraction),
the new reprojection (inputs detached at the start of each iteration, as in DROID). Losses per
iteration k, weighted ``gamma^(K-1-k)`` (gamma = 0.9): pose loss, the mean over the graph's edges of
the relative-pose error (translation norm + chordal rotation distance) against the ground truth; flow
loss, the mean distance between the reprojection with the estimated poses and depths and the one
with the exact ones (grid px, where the exact depth exists).

``--eval-clips`` fixed clips (their own seed) are scored before training and at every
``--eval-every`` steps (losses of the last iteration, no gradient), beside the losses of the
starting point itself (``initial_state``: poses and depths before any update, what the network must
beat); JSON lines to stdout, the summary last. CPU by default (threads ``--threads``); ``--device auto`` uses CUDA when present.

Usage (the CPU smoke run of the README):
  .venv/bin/python tools/train.py --steps 300 --out runs/train/droid.pth
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import resource
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from fgslam.config import check_ranges, ranged
from fgslam.errors import FGSlamError
from fgslam.frontends.flow import grid_intrinsics
from fgslam.io.synth import SynthSequence
from fgslam.io.synth.scenarios import load_synth_config
from fgslam.lie import Sim3
from fgslam.nets.checkpoint import load_droid, save_checkpoint
from fgslam.nets.config import resolve_device
from fgslam.nets.dba import DenseBAStepConfig, dense_ba_step, induced_coords
from fgslam.nets.droid import CorrVolume, DroidNet, coords_grid

STRIDE = 8


@dataclass
class TrainConfig:
    """Every setting of a training run (command-line flags of the same names)."""

    preset: str = "room-loop"  # synthetic preset the clips come from
    seed: int = ranged(0, ge=0)  # scene, clip sampling and initial weights
    width: int = ranged(128, ge=64)  # rendered image width (multiple of 8)
    height: int = ranged(96, ge=64)  # rendered image height (multiple of 8)
    pool_frames: int = ranged(200, ge=8)  # frames rendered for sampling clips
    pool_rate: float = ranged(40.0, gt=0)  # Hz of the rendered pool (dense in time: clips skip frames)
    clip_frames: int = ranged(7, ge=3)  # frames per clip (DROID: 7)
    fixed_poses: int = ranged(2, ge=1)  # first poses held at the ground truth (DROID: 2)
    flow_min: float = ranged(8.0, ge=0)  # px (of a flow_reference_width image): smallest mean flow of a clip step
    flow_max: float = ranged(96.0, gt=0)  # px: largest mean flow of a clip step
    flow_reference_width: int = ranged(512, ge=1)  # image width the flow bounds refer to (DROID's training width)
    max_gap: int = ranged(40, ge=1)  # pool frames a clip step may skip at most
    edge_radius: int = ranged(2, ge=1)  # frame-graph edges between frames at most this far apart in the clip
    iterations: int = ranged(6, ge=1)  # unrolled update iterations per clip
    ba_steps: int = ranged(2, ge=1)  # dense BA steps per iteration (DROID: 2)
    gamma: float = ranged(0.9, gt=0, le=1)  # loss weight gamma^(K-1-k) of iteration k
    pose_weight: float = ranged(10.0, ge=0)  # weight of the pose loss
    flow_weight: float = ranged(0.05, ge=0)  # weight of the flow loss (grid px)
    lr: float = ranged(2.5e-4, gt=0)  # AdamW learning rate (DROID: 2.5e-4)
    weight_decay: float = ranged(1e-5, ge=0)  # AdamW weight decay
    clip_grad: float = ranged(2.5, gt=0)  # gradient norm clipping
    steps: int = ranged(300, ge=0)  # optimisation steps (one clip each)
    eval_clips: int = ranged(8, ge=1)  # fixed clips scored before and during training
    eval_every: int = ranged(100, ge=1)  # steps between evaluations
    log_every: int = ranged(10, ge=1)  # steps between training log lines
    threads: int = ranged(2, ge=1)  # torch CPU threads
    device: str = "cpu"  # cpu, cuda or auto
    out: str = "runs/train/droid.pth"  # checkpoint path (written at every evaluation and at the end)


@dataclass
class Frame:
    image: np.ndarray  # (H, W) uint8
    inv_depth: np.ndarray  # (h, w) float64 grid inverse depth (0: no surface)
    T_WC: np.ndarray  # (4, 4)


class ClipPool:
    """Rendered frames of one synthetic sequence and the flow between them (module docstring)."""

    def __init__(self, cfg: TrainConfig):
        self.cfg = cfg
        synth = load_synth_config(cfg.preset, overrides=[f"frames={cfg.pool_frames}", f"camera.width={cfg.width}",
                                                         f"camera.height={cfg.height}", f"camera.rate_hz={cfg.pool_rate}",
                                                         f"seed={cfg.seed}"])
        seq = SynthSequence(synth)
        self.K = torch.tensor(grid_intrinsics(seq.K, STRIDE), dtype=torch.float64)
        times = seq.frame_times()
        poses = seq.camera_poses(times)
        h, w = cfg.height // STRIDE, cfg.width // STRIDE
        self.frames = []
        for T in poses:
            view = seq.render_view(T)
            z = view.depth.astype(np.float64)
            inv = np.where(z > 0, 1.0 / np.where(z > 0, z, 1.0), 0.0)
            blocks = inv.reshape(h, STRIDE, w, STRIDE)
            valid = (z.reshape(h, STRIDE, w, STRIDE) > 0).all(axis=(1, 3))
            grey = view.image if view.image.ndim == 2 else view.image.mean(-1)
            self.frames.append(Frame(np.clip(np.rint(grey), 0, 255).astype(np.uint8),
                                     np.where(valid, blocks.mean(axis=(1, 3)), 0.0), T))
        self.flow = self._flow_table()

    def _flow_table(self) -> np.ndarray:
        """``(P, max_gap + 1)`` mean flow (reference px) from frame a to a + g (NaN: no overlap)."""
        cfg, P = self.cfg, len(self.frames)
        table = np.full((P, cfg.max_gap + 1), np.nan)
        depth = torch.tensor(np.stack([f.inv_depth for f in self.frames]))
        poses = Sim3.from_matrix(torch.tensor(np.stack([f.T_WC for f in self.frames])))
        h, w = depth.shape[1:]
        grid = coords_grid(h, w, dtype=torch.float64)
        scale = STRIDE * cfg.flow_reference_width / cfg.width
        for gap in range(1, cfg.max_gap + 1):
            ii = torch.arange(0, P - gap)
            if not len(ii):
                break
            uv, valid = induced_coords(poses, depth, self.K, ii, ii + gap)
            valid = valid & (depth[ii] > 0)
            dist = torch.linalg.vector_norm(uv - grid, dim=-1)
            n = valid.sum((1, 2))
            mean = torch.where(n > 0.5 * h * w, (dist * valid).sum((1, 2)) / n.clamp(min=1), torch.nan)
            table[: P - gap, gap] = (mean * scale).numpy()
        return table

    def sample(self, rng: np.random.Generator) -> list[int]:
        cfg = self.cfg
        for _ in range(1000):
            path = [int(rng.integers(0, len(self.frames)))]
            while len(path) < cfg.clip_frames:
                row = self.flow[path[-1]]
                ok = np.nonzero((row >= cfg.flow_min) & (row <= cfg.flow_max))[0]
                if not len(ok):
                    break
                path.append(path[-1] + int(rng.choice(ok)))
            if len(path) == cfg.clip_frames:
                return path
        raise FGSlamError(f"train: no clip of {cfg.clip_frames} frames with mean flow in [{cfg.flow_min}, "
                          f"{cfg.flow_max}] px in the pool (more --pool-frames, a larger --max-gap or another range)")


def edges(n: int, radius: int) -> tuple[torch.Tensor, torch.Tensor]:
    pairs = [(i, j) for i in range(n) for j in range(n) if i != j and abs(i - j) <= radius]
    return torch.tensor([p[0] for p in pairs]), torch.tensor([p[1] for p in pairs])


def relative_pose_error(est: Sim3, gt: Sim3, ii, jj) -> torch.Tensor:
    """Mean over edges of ``|t_rel - t_rel_gt| + |R_rel - R_rel_gt|_F`` of ``T_i^-1 T_j``."""
    rel_e = est[ii].inverse() @ est[jj]
    rel_g = gt[ii].inverse() @ gt[jj]
    return (torch.linalg.vector_norm(rel_e.t - rel_g.t, dim=-1)
            + torch.linalg.matrix_norm(rel_e.R - rel_g.R)).mean()


def unroll(net: DroidNet, pool: ClipPool, clip: list[int], cfg: TrainConfig, device) -> list[tuple[torch.Tensor, torch.Tensor]]:
    """The clip's (pose loss, flow loss) after each unrolled iteration (module docstring)."""
    frames = [pool.frames[n] for n in clip]
    N = len(frames)
    images = torch.tensor(np.stack([f.image for f in frames]), dtype=torch.float32, device=device)[:, None].expand(N, 3, -1, -1)
    gt_depth = torch.tensor(np.stack([f.inv_depth for f in frames]))
    gt_poses = Sim3.from_matrix(torch.tensor(np.stack([f.T_WC for f in frames])))
    ii, jj = edges(N, cfg.edge_radius)
    K = pool.K
    fixed = list(range(cfg.fixed_poses))
    init = torch.tensor([min(n, cfg.fixed_poses - 1) for n in range(N)])
    poses = gt_poses[init]
    depth = torch.full_like(gt_depth, float(gt_depth[0][gt_depth[0] > 0].median()))
    coords_gt, valid_gt = induced_coords(gt_poses, gt_depth, K, ii, jj)
    valid_gt = valid_gt & (gt_depth[ii] > 0)
    fmaps, hidden, inp = net.extract(images)
    hidden, inp = hidden[ii], inp[ii]
    corr_fn = CorrVolume(fmaps[ii], fmaps[jj])
    h, w = gt_depth.shape[1:]
    coords0 = coords_grid(h, w, device=device)[None].expand(len(ii), h, w, 2)
    coords1, valid = induced_coords(poses, depth, K, ii, jj)
    target = coords1.float().to(device)
    ba = DenseBAStepConfig()
    losses = []
    for _ in range(cfg.iterations):
        poses = Sim3(poses.R.detach(), poses.t.detach(), poses.s.detach())
        depth = depth.detach()
        c1 = torch.where(valid[..., None], coords1.detach(), coords0.double().cpu()).float().to(device)
        corr = corr_fn(c1)
        hidden, delta, weight, (eta, _mask, _frames) = net.update(hidden, inp, corr, net.motion(coords0, c1, target.detach()), ii.to(device))
        target = c1 + delta
        for _ in range(cfg.ba_steps):
            poses, depth = dense_ba_step(poses, depth, K, ii, jj, target.double().cpu(), weight.double().cpu(),
                                         eta.double().cpu(), fixed, ba)
        coords1, valid = induced_coords(poses, depth, K, ii, jj, ba)
        both = valid & valid_gt
        flow = (torch.linalg.vector_norm(coords1 - coords_gt, dim=-1) * both).sum() / both.sum().clamp(min=1)
        losses.append((relative_pose_error(poses, gt_poses, ii, jj), flow))
    return losses


def initial_losses(pool: ClipPool, clip: list[int], cfg: TrainConfig) -> tuple[float, float]:
    """Pose and flow loss of the starting point itself (no update): what the network must beat."""
    frames = [pool.frames[n] for n in clip]
    N = len(frames)
    gt_depth = torch.tensor(np.stack([f.inv_depth for f in frames]))
    gt_poses = Sim3.from_matrix(torch.tensor(np.stack([f.T_WC for f in frames])))
    ii, jj = edges(N, cfg.edge_radius)
    poses = gt_poses[torch.tensor([min(n, cfg.fixed_poses - 1) for n in range(N)])]
    depth = torch.full_like(gt_depth, float(gt_depth[0][gt_depth[0] > 0].median()))
    coords_gt, valid_gt = induced_coords(gt_poses, gt_depth, pool.K, ii, jj)
    coords, valid = induced_coords(poses, depth, pool.K, ii, jj)
    both = valid & valid_gt & (gt_depth[ii] > 0)
    flow = (torch.linalg.vector_norm(coords - coords_gt, dim=-1) * both).sum() / both.sum().clamp(min=1)
    return float(relative_pose_error(poses, gt_poses, ii, jj)), float(flow)


def total_loss(losses, cfg: TrainConfig) -> torch.Tensor:
    K = len(losses)
    return sum(cfg.gamma ** (K - 1 - k) * (cfg.pose_weight * p + cfg.flow_weight * f) for k, (p, f) in enumerate(losses))


def evaluate(net, pool, clips, cfg, device) -> dict:
    net.eval()
    pose, flow = [], []
    with torch.no_grad():
        for clip in clips:
            p, f = unroll(net, pool, clip, cfg, device)[-1]
            pose.append(float(p))
            flow.append(float(f))
    net.train()
    return {"pose_loss": float(np.mean(pose)), "flow_loss": float(np.mean(flow))}


def cpu_seconds() -> float:
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def train(cfg: TrainConfig, log=print, pool: ClipPool | None = None) -> dict:
    """Run the training of ``cfg`` (``pool``: frames already rendered for the same settings)."""
    check_ranges(cfg, "train.")
    if cfg.width % STRIDE or cfg.height % STRIDE:
        raise FGSlamError(f"train: --width and --height must be multiples of {STRIDE}")
    torch.set_num_threads(cfg.threads)
    torch.manual_seed(cfg.seed)
    device = resolve_device(cfg.device)
    t0, c0 = time.perf_counter(), cpu_seconds()
    pool = pool or ClipPool(cfg)
    rng = np.random.default_rng(cfg.seed)
    eval_rng = np.random.default_rng(cfg.seed + 1_000_003)
    eval_clips = [pool.sample(eval_rng) for _ in range(cfg.eval_clips)]
    net = DroidNet().to(device)
    opt = torch.optim.AdamW(net.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
    start = np.mean([initial_losses(pool, clip, cfg) for clip in eval_clips], axis=0)
    log(json.dumps({"eval_initial_state": {"pose_loss": float(start[0]), "flow_loss": float(start[1])}}))
    history = [{"step": 0, **evaluate(net, pool, eval_clips, cfg, device)}]
    log(json.dumps({"eval": history[-1]}))
    recent = []
    for step in range(1, cfg.steps + 1):
        losses = unroll(net, pool, pool.sample(rng), cfg, device)
        loss = total_loss(losses, cfg)
        opt.zero_grad()
        loss.backward()
        torch.nn.utils.clip_grad_norm_(net.parameters(), cfg.clip_grad)
        opt.step()
        recent.append((float(losses[-1][0]), float(losses[-1][1]), float(loss)))
        if step % cfg.log_every == 0:
            p, f, total = np.mean(recent, axis=0)
            log(json.dumps({"step": step, "pose_loss": p, "flow_loss": f, "loss": total,
                            "s_per_step": (time.perf_counter() - t0) / step}))
            recent = []
        if step % cfg.eval_every == 0 or step == cfg.steps:
            history.append({"step": step, **evaluate(net, pool, eval_clips, cfg, device)})
            log(json.dumps({"eval": history[-1]}))
            save_checkpoint(net, cfg.out)
    if cfg.steps == 0:
        save_checkpoint(net, cfg.out)
    load_droid(cfg.out)  # the file is what the dense source loads
    return {"config": dataclasses.asdict(cfg), "eval": history,
            "initial_state": {"pose_loss": float(start[0]), "flow_loss": float(start[1])}, "checkpoint": str(Path(cfg.out).resolve()),
            "wall_s": time.perf_counter() - t0, "cpu_s": cpu_seconds() - c0, "load": os.getloadavg()[0]}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    for f in dataclasses.fields(TrainConfig):
        flag = "--" + f.name.replace("_", "-")
        ap.add_argument(flag, type=type(f.default), default=f.default)
    args = ap.parse_args(argv)
    cfg = TrainConfig(**{f.name: getattr(args, f.name) for f in dataclasses.fields(TrainConfig)})
    try:
        summary = train(cfg)
    except FGSlamError as exc:
        print(f"train: error: {exc}", file=sys.stderr)
        return 2
    print(json.dumps({"summary": summary}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
