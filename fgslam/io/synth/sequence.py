"""In-memory synthetic stereo + depth + IMU sequence with exact ground truth.

Frames: body B = IMU frame, cam0 = left camera S0, cam1 = right camera S1 (rectified, same K,
``T_S0S1 = [I | (baseline, 0, 0)]``), ``T_BS`` = sensor-to-body (EuRoC convention). Camera poses
are ``T_WC = T_WB @ T_BS``. Times are seconds from frame 0 (``t = i / camera.rate_hz``); the files
written by :mod:`.writer` add ``start_time_ns``.

Random streams (all from ``np.random.SeedSequence(seed)``): scene layout, textures, IMU noise, so a
given seed gives identical bytes.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from functools import cached_property

import numpy as np

from .distortion import DistortedCamera
from .imu import ImuData, simulate_imu
from .layouts import build_scene
from .motions import build_trajectory
from .scenarios import SynthConfig, camera_mount
from .render import Renderer, RenderOutput
from .texture import build_atlas
from .trajectory import BodyState

logger = logging.getLogger(__name__)

__all__ = ["StereoFrame", "SynthSequence"]

@dataclass(frozen=True)
class StereoFrame:
    """One rendered frame: ``t`` seconds, ``T_WB`` (4, 4), ``T_WC0`` (4, 4), images (float32 [0, 255]),
    ``depth0`` float32 z-depth of cam0 (0 = no surface)."""

    index: int
    t: float
    T_WB: np.ndarray
    T_WC0: np.ndarray
    image0: np.ndarray
    image1: np.ndarray
    depth0: np.ndarray


class SynthSequence:
    """Scene, textures, trajectory, renderers and IMU of one configured synthetic sequence."""

    def __init__(self, cfg: SynthConfig):
        cfg.validate()
        self.cfg = cfg
        layout_seed, texture_seed, imu_seed = np.random.SeedSequence(cfg.seed).spawn(3)
        self.scene = build_scene(cfg, np.random.default_rng(layout_seed)).arrays()
        self.atlas = build_atlas(self.scene, cfg.texture, np.random.default_rng(texture_seed))
        self._imu_rng_seed = imu_seed
        self.trajectory = build_trajectory(cfg)
        cam = cfg.camera
        f = 0.5 * cam.width / np.tan(0.5 * np.deg2rad(cam.hfov_deg))
        self.K = (float(f), float(f), 0.5 * cam.width, 0.5 * cam.height)
        # raw images with lens distortion (camera.distortion not all zero): a pinhole canvas resampled
        self.distorted = DistortedCamera(self.K, cam.width, cam.height, cam.distortion, cam.distortion_model) \
            if any(cam.distortion) else None
        if self.distorted is None:
            self.renderer = Renderer(self.scene, self.atlas, self.K, cam.width, cam.height, cfg.render)
        else:
            self.renderer = Renderer(self.scene, self.atlas, self.distorted.canvas_K, *self.distorted.canvas_size,
                                     cfg.render)
        logger.info("synthetic %s: %d quads, %.1f M texels", cfg.preset, len(self.scene),
                    self.atlas.texels.size / 1e6)

    # ------------------------------------------------------------------ calibration
    @cached_property
    def T_BS0(self) -> np.ndarray:
        """(4, 4) cam0-to-body transform."""
        return camera_mount(self.cfg.camera)

    @cached_property
    def T_S0S1(self) -> np.ndarray:
        """(4, 4) cam1-to-cam0 transform (pure translation by the baseline along x)."""
        T = np.eye(4)
        T[0, 3] = self.cfg.camera.baseline
        return T

    @cached_property
    def T_BS1(self) -> np.ndarray:
        return self.T_BS0 @ self.T_S0S1

    # ------------------------------------------------------------------ timing and states
    @property
    def n_frames(self) -> int:
        return self.cfg.frames

    def frame_times(self) -> np.ndarray:
        """(N,) seconds of the camera frames (from 0)."""
        return np.arange(self.cfg.frames) * (1.0 / self.cfg.camera.rate_hz)

    def imu_times(self) -> np.ndarray:
        """(M,) seconds of the IMU samples, covering [0, last frame time]."""
        t_end = (self.cfg.frames - 1) / self.cfg.camera.rate_hz
        n = int(np.floor(t_end * self.cfg.imu.rate_hz + 1e-9)) + 1
        return np.arange(n) * (1.0 / self.cfg.imu.rate_hz)

    def states(self, t: np.ndarray) -> BodyState:
        return self.trajectory.sample(np.asarray(t, np.float64))

    def camera_poses(self, t: np.ndarray) -> np.ndarray:
        """(N, 4, 4) ``T_WC0`` at times ``t``."""
        return self.states(t).T_WB() @ self.T_BS0

    @cached_property
    def imu(self) -> ImuData:
        """Noisy IMU over :meth:`imu_times` (deterministic for the seed)."""
        return simulate_imu(self.states(self.imu_times()), self.cfg.imu,
                            np.random.default_rng(self._imu_rng_seed))

    # ------------------------------------------------------------------ rendering
    def render_view(self, T_WC: np.ndarray) -> RenderOutput:
        """Raw view of camera pose ``T_WC``: intrinsics ``K``, distorted by ``camera.distortion``."""
        out = self.renderer.render(T_WC, colour=self.cfg.camera.colour)
        return out if self.distorted is None else self.distorted.resample(out)

    def frame(self, index: int) -> StereoFrame:
        t = float(index) / self.cfg.camera.rate_hz
        T_WB = self.states(np.array([t])).T_WB()[0]
        T_WC0 = T_WB @ self.T_BS0
        left = self.render_view(T_WC0)
        right = self.render_view(T_WC0 @ self.T_S0S1)
        image0, image1 = left.image, right.image
        cam = self.cfg.camera
        if cam.exposure_s > 0:  # motion blur: mean over the exposure (depth stays the frame time's)
            dt = cam.exposure_s * (np.arange(cam.blur_samples) / (cam.blur_samples - 1) - 0.5)
            image0, image1 = np.zeros_like(image0), np.zeros_like(image1)
            for T in self.camera_poses(t + dt):
                image0 += self.render_view(T).image
                image1 += self.render_view(T @ self.T_S0S1).image
            image0 /= cam.blur_samples
            image1 /= cam.blur_samples
        return StereoFrame(index=index, t=t, T_WB=T_WB, T_WC0=T_WC0, image0=image0,
                           image1=image1, depth0=left.depth)
