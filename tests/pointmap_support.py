"""Shared helpers of the pointmap-family tests (importable because pytest puts tests/ on the path):
synthetic room-loop renders at 320x240 and the generator's ground-truth correspondences."""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from fgslam.frontends.pointmap.source import unproject_depth
from fgslam.io.synth import SynthSequence
from fgslam.io.synth.scenarios import load_synth_config


def room_sequence() -> SynthSequence:
    return SynthSequence(load_synth_config("room-loop", None, ["camera.width=320", "camera.height=240",
                                                               "room.wall_density=80", "room.box_density=100"]))


@dataclass
class View:
    index: int
    T_WC: np.ndarray
    image: np.ndarray  # uint8 grey
    depth: np.ndarray  # float32 metres
    right: np.ndarray | None = None


def render(seq: SynthSequence, index: int, stereo: bool = False) -> View:
    T = seq.camera_poses(seq.frame_times()[[index]])[0]
    out = seq.render_view(T)
    right = None
    if stereo:
        right = np.clip(np.rint(seq.render_view(T @ seq.T_S0S1).image), 0, 255).astype(np.uint8)
    return View(index, T, np.clip(np.rint(out.image), 0, 255).astype(np.uint8), out.depth.astype(np.float32), right)


def true_correspondences(K, vi: View, vj: View):
    """For every pixel of j (row-major): its true pixel in i ``(N, 2)``, visible ``(N,)`` (inside i and the
    surface there within 1 % of the point's depth) and clearly occluded ``(N,)`` (inside i, behind a
    surface at least 20 % nearer)."""
    fx, fy, cx, cy = K
    T = np.linalg.inv(vi.T_WC) @ vj.T_WC
    H, W = vj.depth.shape
    Xj = unproject_depth(vj.depth, K).reshape(-1, 3).astype(np.float64)
    Xi = Xj @ T[:3, :3].T + T[:3, 3]
    uv = np.stack((fx * Xi[:, 0] / Xi[:, 2] + cx, fy * Xi[:, 1] / Xi[:, 2] + cy), -1)
    zi = cv2.remap(vi.depth, uv[:, 0].astype(np.float32).reshape(H, W), uv[:, 1].astype(np.float32).reshape(H, W),
                   cv2.INTER_LINEAR).reshape(-1)
    inside = (uv[:, 0] >= 0) & (uv[:, 0] <= W - 1) & (uv[:, 1] >= 0) & (uv[:, 1] <= H - 1) & (vj.depth.reshape(-1) > 0)
    visible = inside & (np.abs(zi - Xi[:, 2]) < 0.01 * Xi[:, 2])
    occluded = inside & (zi < 0.8 * Xi[:, 2])
    return uv, visible, occluded


def rotation_angle_deg(R: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1.0, 1.0))))


def render_clip(root, frames: int, preset: str = "room-loop", extra: tuple[str, ...] = ()):
    """Write a synthetic clip (320x240, ``frames`` frames) into ``root`` (a fresh folder) and return it."""
    from fgslam.io.synth import write_sequence

    write_sequence(SynthSequence(load_synth_config(preset, None, [f"frames={frames}", "camera.width=320",
                                                                  "camera.height=240", *extra])), root)
    return root


def open_clip(root, mode: str):
    """The frames of a written clip for sensor ``mode`` (right images for stereo, depth for RGB-D)."""
    from fgslam.io.datasets import DatasetConfig, open_dataset

    ds = open_dataset(root, config=DatasetConfig(load_right=mode == "stereo", load_depth=mode == "rgbd", load_imu=False))
    return list(ds)


def ate_percent(frontend, frames, align: str) -> tuple[float, float]:
    """(ATE RMSE, ATE as % of the ground-truth path) of a frontend's trajectory over ``frames``."""
    from fgslam.eval.trajectory import EvalConfig, evaluate
    from fgslam.io.trajectory import Trajectory

    t, T, _ = frontend.trajectory()
    gt = {f.timestamp: f.T_WC_gt for f in frames}
    G = np.stack([gt[x] for x in t])
    res = evaluate(Trajectory(t, G), Trajectory(t, T), EvalConfig(align=align))
    path = float(np.linalg.norm(np.diff(G[:, :3, 3], axis=0), axis=1).sum())
    return float(res.ate.rmse), 100.0 * float(res.ate.rmse) / path
