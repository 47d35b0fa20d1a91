"""Train DROID-SLAM's network on synthetic clips (DROID-SLAM section 3.3); checkpoints in the format the
loaders read (``droid.pth``: :func:`fgslam.nets.checkpoint.load_droid`).

Data: ``--pool-seeds`` synthetic sequences (``--preset`` with seeds ``--seed`` onwards: the same motion
through other scene layouts and textures), each rendered at ``--width x --height`` and ``--pool-rate`` Hz
for ``--pool-frames`` frames, with exact poses and depth, once, ahead of training (in ``--workers``
spawned processes when > 0), then held on the training device: sampling a clip is picking frame
indices, so the GPU never waits for rendering. A clip is a random walk of ``--clip-frames``
(7) frames through it where each step's mean induced flow (from the exact depth and poses) lies in
``[--flow-min, --flow-max]`` (8-96 px as in DROID), inside one sequence. Flow is measured in pixels of an image
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

An optimisation step takes ``--batch`` clips at once: the network on all their frames and edges, one
correlation volume, one batched dense BA (one Schur elimination and solve per clip, no loop over
clips); the loss is their mean (``--batch 1`` is the per-clip training, the same numbers). The
geometry and the BA run in ``--ba-dtype`` (auto: float32 on CUDA, float64 on the CPU). A batch whose
BA system or loss is not finite is skipped and counted. ``--time-limit-s`` stops after the first
step past that much training time (a recipe of "N minutes on a GPU"; the step count then depends on
the machine). Log lines give steps/s, clips/s and, on CUDA, the mean GPU utilisation between log
lines (``torch.cuda.utilization``, else ``nvidia-smi``) and the peak memory.

``--eval-clips`` fixed clips (their own seed) are scored before training and at every
``--eval-every`` steps (losses of the last iteration, no gradient), beside the losses of the
starting point itself (``initial_state``: poses and depths before any update, what the network must
beat); JSON lines to stdout, the summary last. CPU by default (threads ``--threads``); ``--device auto`` uses CUDA when present.

Usage (a CPU smoke run, as in docs/benchmarks/learned.md; then a GPU run, and tools/gpu_train_check.py for the whole recipe):
  .venv/bin/python tools/train.py --steps 300 --out runs/train/droid.pth
  python3 tools/train.py --device cuda --batch 16 --pool-seeds 8 --workers 16 --time-limit-s 240 \
      --steps 1000000 --eval-every 200 --out runs/train/droid.pth
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import multiprocessing
import os
import resource
import subprocess
import sys
import threading
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from fgslam.core.config import check_ranges, ranged
from fgslam.core.errors import FGSlamError, OptimizationError
from fgslam.frontends.flow import grid_intrinsics
from fgslam.io.synth import SynthSequence
from fgslam.io.synth.scenarios import load_synth_config
from fgslam.core.lie import Sim3
from fgslam.nets.checkpoint import load_droid, save_checkpoint
from fgslam.nets.config import resolve_device
from fgslam.nets.dba import DenseBAStepConfig, dense_ba_step, induced_coords
from fgslam.nets.droid import CorrVolume, DroidNet, coords_grid

STRIDE = 8


@dataclass
class TrainConfig:
    """Every setting of a training run (command-line flags of the same names)."""

    preset: str = "room-loop"  # synthetic preset the clips come from
    seed: int = ranged(0, ge=0)  # scene of the first pool sequence, clip sampling and initial weights
    pool_seeds: int = ranged(1, ge=1)  # scenes rendered into the pool: seeds seed .. seed + pool_seeds - 1
    width: int = ranged(128, ge=64)  # rendered image width (multiple of 8)
    height: int = ranged(96, ge=64)  # rendered image height (multiple of 8)
    pool_frames: int = ranged(200, ge=8)  # frames rendered per scene for sampling clips
    pool_rate: float = ranged(40.0, gt=0)  # Hz of the rendered pool (dense in time: clips skip frames)
    workers: int = ranged(0, ge=0)  # processes rendering the pool ahead of training (0: this process)
    clip_frames: int = ranged(7, ge=3)  # frames per clip (DROID: 7)
    fixed_poses: int = ranged(2, ge=1)  # first poses held at the ground truth (DROID: 2)
    flow_min: float = ranged(8.0, ge=0)  # px (of a flow_reference_width image): smallest mean flow of a clip step
    flow_max: float = ranged(96.0, gt=0)  # px: largest mean flow of a clip step
    flow_reference_width: int = ranged(512, ge=1)  # image width the flow bounds refer to (DROID's training width)
    max_gap: int = ranged(40, ge=1)  # pool frames a clip step may skip at most
    edge_radius: int = ranged(2, ge=1)  # frame-graph edges between frames at most this far apart in the clip
    iterations: int = ranged(6, ge=1)  # unrolled update iterations per clip
    ba_steps: int = ranged(2, ge=1)  # dense BA steps per iteration (DROID: 2)
    ba_dtype: str = "auto"  # float64, float32 or auto (float32 on CUDA, float64 on the CPU)
    gamma: float = ranged(0.9, gt=0, le=1)  # loss weight gamma^(K-1-k) of iteration k
    pose_weight: float = ranged(10.0, ge=0)  # weight of the pose loss
    flow_weight: float = ranged(0.05, ge=0)  # weight of the flow loss (grid px)
    lr: float = ranged(2.5e-4, gt=0)  # AdamW learning rate (DROID: 2.5e-4)
    weight_decay: float = ranged(1e-5, ge=0)  # AdamW weight decay
    clip_grad: float = ranged(2.5, gt=0)  # gradient norm clipping
    batch: int = ranged(1, ge=1)  # clips per optimisation step (the loss is their mean)
    steps: int = ranged(300, ge=0)  # optimisation steps (``batch`` clips each)
    time_limit_s: float = ranged(0.0, ge=0)  # stop after the first step past this many seconds of training (0: off)
    eval_clips: int = ranged(8, ge=1)  # fixed clips scored before and during training
    eval_every: int = ranged(100, ge=1)  # steps between evaluations
    log_every: int = ranged(10, ge=1)  # steps between training log lines
    threads: int = ranged(2, ge=1)  # torch CPU threads
    device: str = "cpu"  # cpu, cuda or auto
    out: str = "runs/train/droid.pth"  # checkpoint path (written at every evaluation and at the end)


BA_DTYPES = {"float64": torch.float64, "float32": torch.float32}


def ba_dtype(cfg: TrainConfig, device: torch.device) -> torch.dtype:
    """The dtype of the geometry and the dense BA: ``auto`` is float32 on CUDA, float64 on the CPU."""
    if cfg.ba_dtype == "auto":
        return torch.float32 if device.type == "cuda" else torch.float64
    if cfg.ba_dtype not in BA_DTYPES:
        raise FGSlamError(f"train: --ba-dtype must be auto, float32 or float64, got {cfg.ba_dtype!r}")
    return BA_DTYPES[cfg.ba_dtype]


@dataclass
class Frame:
    image: np.ndarray  # (H, W) uint8
    inv_depth: np.ndarray  # (h, w) float64 grid inverse depth (0: no surface)
    T_WC: np.ndarray  # (4, 4)


def _synth_sequence(cfg: TrainConfig, seed: int) -> SynthSequence:
    return SynthSequence(load_synth_config(cfg.preset, overrides=[
        f"frames={cfg.pool_frames}", f"camera.width={cfg.width}", f"camera.height={cfg.height}",
        f"camera.rate_hz={cfg.pool_rate}", f"seed={seed}"]))


def render_frames(cfg: TrainConfig, seed: int, indices: list[int]) -> tuple[np.ndarray, list[Frame]]:
    """Grid intrinsics and the frames ``indices`` of scene ``seed`` (runs in a worker process too)."""
    seq = _synth_sequence(cfg, seed)
    poses = seq.camera_poses(seq.frame_times())
    h, w = cfg.height // STRIDE, cfg.width // STRIDE
    frames = []
    for n in indices:
        view = seq.render_view(poses[n])
        z = view.depth.astype(np.float64)
        inv = np.where(z > 0, 1.0 / np.where(z > 0, z, 1.0), 0.0)
        blocks = inv.reshape(h, STRIDE, w, STRIDE)
        valid = (z.reshape(h, STRIDE, w, STRIDE) > 0).all(axis=(1, 3))
        grey = view.image if view.image.ndim == 2 else view.image.mean(-1)
        frames.append(Frame(np.clip(np.rint(grey), 0, 255).astype(np.uint8),
                            np.where(valid, blocks.mean(axis=(1, 3)), 0.0), poses[n]))
    return grid_intrinsics(seq.K, STRIDE), frames


@dataclass
class PoolTensors:
    """The pool on the training device: every frame's image, grid inverse depth and pose, stacked."""

    images: torch.Tensor  # (P, H, W) uint8
    inv_depth: torch.Tensor  # (P, h, w) BA dtype
    poses: Sim3  # (P,) T_WC, BA dtype
    K: torch.Tensor  # (4,) grid intrinsics, BA dtype


class ClipPool:
    """Rendered frames of ``pool_seeds`` synthetic sequences and the flow between them (module docstring).

    The frames are rendered once, ahead of training (in ``workers`` processes when > 0); a clip is a
    list of frame indices into them, and :meth:`tensors` holds them on the training device.
    """

    def __init__(self, cfg: TrainConfig):
        self.cfg = cfg
        seeds = range(cfg.seed, cfg.seed + cfg.pool_seeds)
        jobs = [(seed, chunk.tolist()) for seed in seeds
                for chunk in np.array_split(np.arange(cfg.pool_frames), max(1, -(-cfg.workers // cfg.pool_seeds)))]
        if cfg.workers > 0:
            # spawn: the parent may hold CUDA and torch threads, which fork must not copy
            with ProcessPoolExecutor(max_workers=cfg.workers, mp_context=multiprocessing.get_context("spawn")) as ex:
                parts = list(ex.map(render_frames, [cfg] * len(jobs), *zip(*jobs)))
        else:
            parts = [render_frames(cfg, seed, idx) for seed, idx in jobs]
        self.K = torch.tensor(parts[0][0], dtype=torch.float64)
        self.frames = [f for _, frames in parts for f in frames]
        self.scene = np.repeat(np.arange(cfg.pool_seeds), cfg.pool_frames)  # scene of each frame
        self.flow = self._flow_table()
        self._tensors: dict = {}

    def _flow_table(self) -> np.ndarray:
        """``(P, max_gap + 1)`` mean flow (reference px) from frame a to a + g (NaN: no overlap or
        another scene)."""
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
            same = torch.tensor(self.scene[: P - gap] == self.scene[gap:])
            table[: P - gap, gap] = torch.where(same, mean, torch.nan).numpy() * scale
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

    def tensors(self, device: torch.device, dtype: torch.dtype) -> PoolTensors:
        """The pool on ``device`` (built once per device and dtype)."""
        key = (str(device), dtype)
        if key not in self._tensors:
            self._tensors[key] = PoolTensors(
                torch.tensor(np.stack([f.image for f in self.frames]), device=device),
                torch.tensor(np.stack([f.inv_depth for f in self.frames]), dtype=dtype, device=device),
                Sim3.from_matrix(torch.tensor(np.stack([f.T_WC for f in self.frames]))).to(device=device, dtype=dtype),
                self.K.to(device=device, dtype=dtype))
        return self._tensors[key]


def edges(n: int, radius: int) -> tuple[torch.Tensor, torch.Tensor]:
    pairs = [(i, j) for i in range(n) for j in range(n) if i != j and abs(i - j) <= radius]
    return torch.tensor([p[0] for p in pairs]), torch.tensor([p[1] for p in pairs])


def relative_pose_error(est: Sim3, gt: Sim3, ii, jj) -> torch.Tensor:
    """Per clip ``(B,)``: mean over edges of ``|t_rel - t_rel_gt| + |R_rel - R_rel_gt|_F`` of ``T_i^-1 T_j``."""
    rel_e = est[:, ii].inverse() @ est[:, jj]
    rel_g = gt[:, ii].inverse() @ gt[:, jj]
    return (torch.linalg.vector_norm(rel_e.t - rel_g.t, dim=-1)
            + torch.linalg.matrix_norm(rel_e.R - rel_g.R)).mean(-1)


def _as_batch(clips) -> list[list[int]]:
    """A clip (list of frame indices) or a list of clips -> a list of clips."""
    return [list(clips)] if np.ndim(clips) == 1 else [list(c) for c in clips]


@dataclass
class ClipBatch:
    """``B`` clips on the device: ground truth, the starting point and the frame graph (module docstring)."""

    index: torch.Tensor  # (B, N) pool frames
    gt_depth: torch.Tensor  # (B, N, h, w)
    gt_poses: Sim3  # (B, N)
    poses: Sim3  # (B, N) the starting poses
    depth: torch.Tensor  # (B, N, h, w) the starting inverse depths
    ii: torch.Tensor  # (E,) edges of one clip (on the device)
    jj: torch.Tensor
    coords_gt: torch.Tensor  # (B, E, h, w, 2) exact reprojections
    valid_gt: torch.Tensor  # (B, E, h, w)


def clip_batch(pool: ClipPool, clips, cfg: TrainConfig, device, dtype) -> ClipBatch:
    data = pool.tensors(device, dtype)
    index = torch.tensor(_as_batch(clips), device=device)
    N = index.shape[1]
    gt_depth = data.inv_depth[index]
    gt_poses = data.poses[index]
    ii, jj = (e.to(device) for e in edges(N, cfg.edge_radius))
    poses = gt_poses[:, torch.tensor([min(n, cfg.fixed_poses - 1) for n in range(N)], device=device)]
    first = gt_depth[:, 0].flatten(1)
    median = torch.where(first > 0, first, torch.nan).nanmedian(1).values  # the first frame's median (lower)
    depth = median[:, None, None, None].expand_as(gt_depth).clone()
    coords_gt, valid_gt = induced_coords(gt_poses, gt_depth, data.K, ii, jj)
    return ClipBatch(index, gt_depth, gt_poses, poses, depth, ii, jj, coords_gt, valid_gt & (gt_depth[:, ii] > 0))


def flow_error(coords: torch.Tensor, valid: torch.Tensor, clip: ClipBatch) -> torch.Tensor:
    """Per clip ``(B,)``: mean distance to the exact reprojection where both are valid (grid px)."""
    both = valid & clip.valid_gt
    dist = torch.linalg.vector_norm(coords - clip.coords_gt, dim=-1) * both
    return dist.sum((1, 2, 3)) / both.sum((1, 2, 3)).clamp(min=1)


def unroll(net: DroidNet, pool: ClipPool, clips, cfg: TrainConfig, device,
           dtype: torch.dtype | None = None) -> list[tuple[torch.Tensor, torch.Tensor]]:
    """The (pose loss, flow loss) after each unrolled iteration (module docstring), means over the
    clips: ``clips`` is one clip or a list of ``B`` clips of equal length, run as one batch (the
    network on ``B N`` frames and ``B E`` edges, one batched dense BA); ``dtype`` of the geometry and
    BA (default: :func:`ba_dtype`)."""
    device = torch.device(device)
    dt = dtype or ba_dtype(cfg, device)
    clip = clip_batch(pool, clips, cfg, device, dt)
    K = pool.tensors(device, dt).K
    B, N = clip.index.shape
    ii, jj = clip.ii, clip.jj
    E = len(ii)
    h, w = clip.gt_depth.shape[-2:]
    offset = (torch.arange(B, device=device) * N)[:, None]
    ii_all, jj_all = (offset + ii).reshape(-1), (offset + jj).reshape(-1)  # (B E,) into B N frames
    H, W = pool.frames[0].image.shape
    images = pool.tensors(device, dt).images[clip.index.reshape(-1)].float()[:, None].expand(B * N, 3, H, W)
    fixed = list(range(cfg.fixed_poses))
    poses, depth = clip.poses, clip.depth
    fmaps, hidden, inp = net.extract(images)
    hidden, inp = hidden[ii_all], inp[ii_all]
    corr_fn = CorrVolume(fmaps[ii_all], fmaps[jj_all])
    coords0 = coords_grid(h, w, device=device)[None].expand(B * E, h, w, 2)
    coords1, valid = induced_coords(poses, depth, K, ii, jj)
    target = coords1.float().reshape(B * E, h, w, 2)
    ba = DenseBAStepConfig()
    losses = []
    for _ in range(cfg.iterations):
        poses = Sim3(poses.R.detach(), poses.t.detach(), poses.s.detach())
        depth = depth.detach()
        c1 = torch.where(valid[..., None], coords1.detach(), coords0.reshape(B, E, h, w, 2).to(dt)).float()
        c1 = c1.reshape(B * E, h, w, 2)
        corr = corr_fn(c1)
        hidden, delta, weight, (eta, _mask, frames) = net.update(hidden, inp, corr, net.motion(coords0, c1, target.detach()),
                                                                 ii_all)
        if frames.numel() != B * N:
            raise FGSlamError(f"train: every clip frame must be the source of an edge (--edge-radius {cfg.edge_radius})")
        target = c1 + delta
        for _ in range(cfg.ba_steps):
            poses, depth = dense_ba_step(poses, depth, K, ii, jj, target.to(dt).reshape(B, E, h, w, 2),
                                         weight.to(dt).reshape(B, E, h, w, 2), eta.to(dt).reshape(B, N, h, w), fixed, ba)
        coords1, valid = induced_coords(poses, depth, K, ii, jj, ba)
        losses.append((relative_pose_error(poses, clip.gt_poses, ii, jj).mean(), flow_error(coords1, valid, clip).mean()))
    return losses


def initial_losses(pool: ClipPool, clips, cfg: TrainConfig) -> tuple[float, float]:
    """Pose and flow loss of the starting point itself (no update), means over the clips: what the
    network must beat (float64 on the CPU)."""
    clip = clip_batch(pool, clips, cfg, torch.device("cpu"), torch.float64)
    coords, valid = induced_coords(clip.poses, clip.depth, pool.K, clip.ii, clip.jj)
    return (float(relative_pose_error(clip.poses, clip.gt_poses, clip.ii, clip.jj).mean()),
            float(flow_error(coords, valid, clip).mean()))


def total_loss(losses, cfg: TrainConfig) -> torch.Tensor:
    K = len(losses)
    return sum(cfg.gamma ** (K - 1 - k) * (cfg.pose_weight * p + cfg.flow_weight * f) for k, (p, f) in enumerate(losses))


def evaluate(net, pool, clips, cfg, device) -> dict:
    """Losses of the last iteration on ``clips`` (in batches of ``cfg.batch``), no gradient."""
    net.eval()
    pose, flow = [], []
    with torch.no_grad():
        for lo in range(0, len(clips), cfg.batch):
            part = clips[lo:lo + cfg.batch]
            p, f = unroll(net, pool, part, cfg, device)[-1]
            pose.append(float(p) * len(part))
            flow.append(float(f) * len(part))
    net.train()
    return {"pose_loss": float(np.sum(pose) / len(clips)), "flow_loss": float(np.sum(flow) / len(clips))}


def cpu_seconds() -> float:
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


class GpuMonitor:
    """Mean GPU utilisation (%) between reads, sampled every ``period`` s in a thread (only for the
    log: it never touches training), from ``torch.cuda.utilization`` (needs pynvml) or ``nvidia-smi``;
    plus the peak memory torch allocated. On the CPU, or with neither source, utilisation is None."""

    def __init__(self, device: torch.device, period: float = 0.5):
        self.device, self.period = device, period
        self.samples: list[float] = []
        self.source = None
        self._stop = threading.Event()
        if device.type != "cuda":
            return
        for source in (self._torch, self._smi):
            if source() is not None:
                self.source = source
                break
        if self.source is not None:
            threading.Thread(target=self._run, daemon=True).start()

    def _torch(self) -> float | None:
        try:
            return float(torch.cuda.utilization(self.device))
        except Exception:  # pynvml missing or no NVML: the next source
            return None

    def _smi(self) -> float | None:
        index = self.device.index if self.device.index is not None else torch.cuda.current_device()
        try:
            out = subprocess.run(["nvidia-smi", "--query-gpu=utilization.gpu", "--format=csv,noheader,nounits",
                                  f"--id={index}"], capture_output=True, text=True, timeout=5)
            return float(out.stdout.strip().splitlines()[0])
        except Exception:  # no nvidia-smi: no utilisation figure
            return None

    def _run(self) -> None:
        while not self._stop.wait(self.period):
            value = self.source()
            if value is not None:
                self.samples.append(value)

    def read(self) -> dict:
        """``gpu_util_percent`` (mean since the last read), ``gpu_util_source``, ``gpu_max_mem_mib``."""
        if self.device.type != "cuda":
            return {}
        samples, self.samples = self.samples, []
        return {"gpu_util_percent": float(np.mean(samples)) if samples else None,
                "gpu_util_source": None if self.source is None else self.source.__name__.strip("_"),
                "gpu_max_mem_mib": torch.cuda.max_memory_allocated(self.device) / 2 ** 20}

    def stop(self) -> None:
        self._stop.set()


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def train(cfg: TrainConfig, log=print, pool: ClipPool | None = None) -> dict:
    """Run the training of ``cfg`` (``pool``: frames already rendered for the same settings)."""
    check_ranges(cfg, "train.")
    if cfg.width % STRIDE or cfg.height % STRIDE:
        raise FGSlamError(f"train: --width and --height must be multiples of {STRIDE}")
    torch.set_num_threads(cfg.threads)
    torch.manual_seed(cfg.seed)
    device = resolve_device(cfg.device)
    dtype = ba_dtype(cfg, device)
    if device.type == "cuda":
        torch.backends.cudnn.benchmark = True  # fixed input sizes: pick the fastest convolutions once
    t0, c0 = time.perf_counter(), cpu_seconds()
    pool = pool or ClipPool(cfg)
    pool.tensors(device, dtype)
    pool_s = time.perf_counter() - t0
    log(json.dumps({"pool": {"frames": len(pool.frames), "scenes": cfg.pool_seeds, "workers": cfg.workers,
                             "wall_s": pool_s, "device": str(device), "ba_dtype": str(dtype).replace("torch.", "")}}))
    rng = np.random.default_rng(cfg.seed)
    eval_rng = np.random.default_rng(cfg.seed + 1_000_003)
    eval_clips = [pool.sample(eval_rng) for _ in range(cfg.eval_clips)]
    net = DroidNet().to(device)
    opt = torch.optim.AdamW(net.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
    start = initial_losses(pool, eval_clips, cfg)
    log(json.dumps({"eval_initial_state": {"pose_loss": start[0], "flow_loss": start[1]}}))
    history = [{"step": 0, **evaluate(net, pool, eval_clips, cfg, device)}]
    log(json.dumps({"eval": history[-1]}))
    monitor = GpuMonitor(device)
    monitor.read()
    recent = []
    _sync(device)
    t_train = t_mark = time.perf_counter()
    step_mark = 0
    train_s = 0.0  # training time without the evaluations
    step = skipped = 0
    try:
        while step < cfg.steps:
            step += 1
            try:
                losses = unroll(net, pool, [pool.sample(rng) for _ in range(cfg.batch)], cfg, device, dtype)
                loss = total_loss(losses, cfg)
                ok = bool(torch.isfinite(loss))
            except OptimizationError:  # a non-finite BA system (diverged depths): no update from this batch
                ok = False
            if ok:
                opt.zero_grad()
                loss.backward()
                torch.nn.utils.clip_grad_norm_(net.parameters(), cfg.clip_grad)
                opt.step()
                recent.append(torch.stack([losses[-1][0].detach(), losses[-1][1].detach(), loss.detach()]).float())
            else:
                skipped += 1
                log(json.dumps({"step": step, "skipped": "non-finite loss or BA system"}))
            out_of_time = cfg.time_limit_s > 0 and time.perf_counter() - t_train >= cfg.time_limit_s
            if step % cfg.log_every == 0 or out_of_time:
                p, f, total = torch.stack(recent).mean(0).tolist() if recent else [float("nan")] * 3
                now = time.perf_counter()
                train_s += now - t_mark
                rate = (step - step_mark) / (now - t_mark)
                log(json.dumps({"step": step, "pose_loss": p, "flow_loss": f, "loss": total, "s_per_step": 1.0 / rate,
                                "steps_per_s": rate, "clips_per_s": rate * cfg.batch, "s_per_clip": 1.0 / (rate * cfg.batch),
                                "window_steps": step - step_mark, "window_s": now - t_mark, **monitor.read()}))
                recent, t_mark, step_mark = [], now, step
            if step % cfg.eval_every == 0 or step == cfg.steps or out_of_time:
                _sync(device)
                train_s += time.perf_counter() - t_mark  # steps since the last log line count, not in a log line
                step_mark, recent = step, []
                history.append({"step": step, **evaluate(net, pool, eval_clips, cfg, device)})
                log(json.dumps({"eval": history[-1]}))
                save_checkpoint(net, cfg.out)
                t_mark = time.perf_counter()
            if out_of_time:
                break
    finally:
        monitor.stop()
    if step == 0:
        save_checkpoint(net, cfg.out)
    load_droid(cfg.out)  # the file is what the dense source loads
    throughput = {"steps": step, "clips": step * cfg.batch, "skipped_steps": skipped, "train_s": train_s,
                  "steps_per_s": step / train_s if train_s else None,
                  "clips_per_s": step * cfg.batch / train_s if train_s else None}
    return {"config": dataclasses.asdict(cfg), "eval": history,
            "initial_state": {"pose_loss": start[0], "flow_loss": start[1]}, "checkpoint": str(Path(cfg.out).resolve()),
            "throughput": throughput, "pool_wall_s": pool_s,
            "gpu_max_mem_mib": torch.cuda.max_memory_allocated(device) / 2 ** 20 if device.type == "cuda" else None,
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
