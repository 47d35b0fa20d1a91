"""Configuration of the synthetic generator and its scene presets (scene + trajectory builders; not
the SLAM run presets of :mod:`fgslam.presets`).

Presets:

- ``room-loop``: hand-held-like smooth loop (a few metres) inside a textured room with furniture
  boxes; the body path and attitude are periodic with period ``loop_duration_s``, so the sequence
  ends exactly where it started (default frame count = one period).
- ``street-loop``: KITTI-like drive around a city block (facades, ground, parked cars, poles) at
  ``camera_height`` with a forward-looking camera at 10 Hz; the road is a smooth Fourier fit of a
  rounded rectangle traversed once per ``loop_duration_s`` (default 1,001 frames, ~600 m).
- ``low-texture``: the ``room-loop`` motion in a room of large uniform surfaces (plain walls and
  ceiling, a floor of tiles with faint grout lines, doors with a darker frame and a handle, a few
  plain cabinets): white walls and corridors with few corners, where sparse patches starve and
  dense methods are meant to keep tracking.
- ``panel-room``: texture-poor indoor RGB-D (issue 23, held-out row 1): walls of near-white panels
  with thin grout lines, a tiled floor, plain ceiling, door frames; lit by a point light at the
  ceiling with Lambertian shading and mild vignetting (``render.point_light``, ``render.vignetting``);
  the camera walks along an elliptic arc close to the walls (0.5-2 m), looking outwards at them, and
  turns ``turn_deg`` of yaw over the default frames (10 Hz), with hand-held wobble.
- ``rotation-sweep``: rotation-dominant hand-held camera (held-out rows 2-3, the distorted global-shutter
  row): the textured room of ``room-loop`` (smaller), a roll / pitch / yaw sweep whose mean angular
  speed is ``rotation_speed_deg_s`` over a small translation, 30 Hz, and raw images with strong radial
  distortion (``camera.distortion``, written to sensor.yaml so that the loaders undistort; depth0 is
  distorted the same way).
- ``orbit``: camera circling a cluster of boxes in a hall, always looking at the cluster centre.
- ``highway``: fast forward drive (``speed`` m/s, 10 Hz: 2-3 m between frames) along a gently
  curved road (one lateral S-bend over ``duration_s``), sparse roadside structure (guard rails,
  lamp poles, sign boards) and distant buildings and hills, so that the optical flow is large near
  the image border and small at the centre. The road does not close: the scene is built to cover
  the configured number of frames plus ``lookahead`` metres.
- ``kitti00-drive``: a KITTI-length drive (issue 24): the camera follows the poses of a KITTI ground-truth
  file (``kitti_drive.poses``, default ``<repo>/../shared/data/kitti_gt/00.txt``: 4,541 frames, 3.7 km
  with the loops of KITTI 00), frame i at row i, played at 10 Hz (KITTI's own stamps, ~9.65 Hz, are not
  used); a street scene is built along that path: ground tiles following the road height, buildings
  with textured facades on both sides wherever they leave every part of the road clear, lamp poles,
  a coarse ground below. The file is read when the scene is built (never at import); a missing file
  is a :class:`~fgslam.errors.DataError`. The scene covers the configured frames plus ``lookahead``
  metres of the path, so a prefix builds (and renders) quickly.

Changing ``frames`` truncates or extends (periodically) the motion, it does not change its speed.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path

import cv2
import numpy as np

from ...config import MAX_COUNT, MAX_FRAMES, MAX_IMAGE_SIDE, MAX_SCALAR, MAX_SEED, MAX_TIME_NS, check_ranges, ranged
from ...errors import ConfigError, DataError
from ..trajectory import read_trajectory
from .imu import ImuConfig
from .render import RenderConfig
from .scene import Scene
from .texture import STYLE_DOOR, STYLE_PANELS, STYLE_PLAIN, STYLE_TILES, PlainTextureConfig, TextureConfig
from .trajectory import (AnalyticTrajectory, Fourier1D, PoseTrackTrajectory, TimeWarp, closed_curve_fourier,
                         euler_zyx_to_R, rounded_rectangle)

PRESET_NAMES = ("room-loop", "street-loop", "orbit", "highway", "low-texture", "panel-room", "rotation-sweep",
                "kitti00-drive")

_ROAD_SAMPLES = 8192  # arc-length samples of the rounded rectangle fitted by the Fourier road
_GROUND_LINE_SAMPLES = 2048  # samples of the road centre line for choosing ground tiles

# street and orbit furniture (metres)
_FAR_GROUND_MARGIN = 40.0      # coarse ground extends this far beyond the outermost buildings
_SETBACK_JITTER = 2.0          # random extra setback of each building
_CAR_SLOT = 8.0                # kerb length per possible parked car
_CAR_SIZE = (4.2, 1.8, 1.5)    # parked car box (length, width, height)
_CAR_YAW = 0.05                # rad, random misalignment of parked cars
_POLE_SIZE = (0.25, 0.25, 5.0)
_POLE_SETBACK = 1.5            # poles stand this much closer to the road than the facades
_ORBIT_FLOOR_MARGIN = 2.5      # the dense floor decal extends this far beyond the orbit radius
_DECAL_OFFSET = 0.002          # height of the dense floor decal above the coarse floor

# panel-room and rotation-sweep camera / lighting defaults
_PANEL_HFOV_DEG = 67.0          # ICL-NUIM-like VGA render (fx ~ 480)
_PANEL_TILE_LINE_DEPTH = 0.3    # floor grout darker than the low-texture preset's faint 0.1
_PANEL_VIGNETTING = 0.1         # corner darkening (0.25 made dense_rgbd drift 10.8 % of the path, 0: 0.12 %)
_PANEL_COLOUR_SATURATION = 0.08  # faint per-surface tints: near-white walls
_PANEL_ALBEDO_JITTER = 0.02     # panels differ by ~2 % in brightness
_LIGHT_BELOW_CEILING = 0.1      # m: the point light hangs this far below the ceiling, at the room centre
_SWEEP_HFOV_DEG = 62.7          # Kinect v1: fx = 525 at 640 px
_SWEEP_RATE_HZ = 1e9 / 33_333_333  # 30 Hz to a whole-nanosecond frame period (SynthConfig.validate)
_SWEEP_EXPOSURE_S = 0.012       # motion blur of a hand-held Kinect indoors (2-3 deg at the fastest rotations)
_SWEEP_BLUR_SAMPLES = 12
_SWEEP_DISTORTION = (-0.30, 0.09, 0.0, 0.0)  # k1, k2, p1, p2: strong barrel, invertible over the VGA image
_SWEEP_SPEED_SAMPLES = 4096     # samples of one period for scaling the sweep to its mean angular speed
_SWEEP_SPEED_ITERATIONS = 50    # fixed-point steps of that scale at most
_SWEEP_SPEED_TOLERANCE = 1e-13  # relative error of the mean angular speed accepted
_SWEEP_MAX_SCALE = 10.0         # largest scale of the base amplitudes (angles beyond it wrap the attitude)
_MIN_TURN_DEG = 1e-3            # panel-room: a smaller turn_deg is treated as this (the ellipse period stays finite)

# kitti00-drive
_KITTI_FRAMES = 4541            # rows of KITTI 00's ground truth: the preset's default frame count
_KITTI_RATE_HZ = 10.0
_KITTI_SIZE = (320, 96)         # KITTI's 1241 x 376 aspect at a size that renders and runs fast on 2 cores
_KITTI_HFOV_DEG = 81.6          # KITTI 00: fx = 718.9 at 1241 px
_KITTI_BASELINE = 0.54          # m, KITTI's stereo baseline
_KITTI_MAX_DISTANCE = 120.0     # m, render.max_distance of the preset (beyond: sky or the coarse ground)
_KITTI_RIDGE = 5.0              # m; regulariser of a ground tile's slopes (a straight road leaves the lateral one free)
# world frame of the drive from KITTI's: KITTI's world is its first camera frame (x right, y down, z forward);
# ours has z up: x = KITTI z (forward at the start), y = -KITTI x, z = -KITTI y (the nominal camera mount)
R_W_KITTI = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])

# texture styles: index into TextureConfig.style_mark_scale
STYLE_WALL, STYLE_GROUND, STYLE_OBJECT = 0, 1, 2


#: lens models of the synthetic raw images (camera.distortion_model; fgslam/io/synth/distortion.py)
DISTORTION_MODELS = ("radtan", "equidistant")


@dataclass
class CameraConfig:
    """Rectified stereo pair (same intrinsics) and its mounting on the body (IMU) frame."""

    width: int = ranged(640, ge=8, le=MAX_IMAGE_SIDE)
    height: int = ranged(480, ge=8, le=MAX_IMAGE_SIDE)
    hfov_deg: float = ranged(90.0, gt=0, lt=170)  # horizontal field of view; fx = fy = (width / 2) / tan(hfov / 2)
    rate_hz: float = ranged(20.0, gt=0, le=MAX_SCALAR)
    baseline: float = ranged(0.11, gt=0, le=MAX_SCALAR)  # metres; cam1 sits at +baseline along the x axis of cam0
    mount_rpy_deg: list[float] = ranged(default_factory=lambda: [0.8, -1.5, 1.2], ge=-180, le=180)  # small rotation
    # (roll, pitch, yaw about the camera x, y, z axes) applied after the nominal forward-looking mount
    t_BS: list[float] = ranged(default_factory=lambda: [0.06, -0.02, 0.03], ge=-MAX_SCALAR, le=MAX_SCALAR)  # cam0 origin in body (m)
    colour: bool = False                # write RGB PNGs (per-surface tints) instead of grey
    depth_scale: float = ranged(1000.0, gt=0, le=MAX_SCALAR)  # depth PNG units per metre (0 = invalid, > 65535 -> 0)
    distortion: list[float] = ranged(default_factory=lambda: [0.0, 0.0, 0.0, 0.0], ge=-1, le=1)  # radial-tangential
    # (k1, k2, p1, p2) of the raw images (OpenCV model, as EuRoC's sensor.yaml): all zero = pinhole images; otherwise
    # every image (and depth0) is rendered through it and sensor.yaml carries it, so that the loaders undistort
    # radtan: camera.distortion is (k1, k2, p1, p2); equidistant: Kannala-Brandt fisheye (k1, k2, k3, k4) on the
    # ray angle (TUM-VI's model, OpenCV cv2.fisheye), fx = fy from hfov_deg as for the pinhole
    distortion_model: str = "radtan"
    exposure_s: float = ranged(0.0, ge=0, le=MAX_SCALAR)  # motion blur: images are the mean of blur_samples renders over
    # this exposure centred on the frame time (0: instantaneous); depth0 is the frame time's
    blur_samples: int = ranged(8, ge=2, le=MAX_COUNT)


@dataclass
class RoomConfig:
    """room-loop scene and motion."""

    size: list[float] = ranged(default_factory=lambda: [8.0, 6.0, 3.0], gt=0, le=MAX_SCALAR)  # room x, y, z extents (m)
    n_boxes: int = ranged(10, ge=0, le=MAX_COUNT)  # furniture boxes
    box_size_range: list[float] = ranged(default_factory=lambda: [0.3, 1.4], gt=0, le=MAX_SCALAR)  # horizontal sizes
    box_height_range: list[float] = ranged(default_factory=lambda: [0.3, 2.0], gt=0, le=MAX_SCALAR)
    path_radii: list[float] = ranged(default_factory=lambda: [1.3, 0.9], gt=0, le=MAX_SCALAR)  # ellipse of the path (m)
    path_clearance: float = ranged(0.9, ge=0, le=MAX_SCALAR)  # minimum gap between the path ellipse and furniture (m)
    height: float = ranged(1.4, gt=0, le=MAX_SCALAR)  # mean body height (m)
    loop_duration_s: float = ranged(20.0, gt=0, le=MAX_SCALAR)
    jitter: float = ranged(1.0, ge=0, le=MAX_SCALAR)  # scale of the hand-held wobble (0: smooth ellipse + turn)
    wall_density: float = ranged(160.0, gt=0, le=MAX_SCALAR)  # texels per metre
    box_density: float = ranged(200.0, gt=0, le=MAX_SCALAR)


@dataclass
class LowTextureConfig(RoomConfig):
    """low-texture scene (the room-loop motion and room fields, plain styles) and its doors."""

    n_boxes: int = ranged(3, ge=0, le=MAX_COUNT)  # plain cabinets
    box_size_range: list[float] = ranged(default_factory=lambda: [0.5, 1.2], gt=0, le=MAX_SCALAR)
    box_height_range: list[float] = ranged(default_factory=lambda: [0.8, 1.8], gt=0, le=MAX_SCALAR)
    wall_density: float = ranged(100.0, gt=0, le=MAX_SCALAR)  # texels per metre (grout lines need ~1 texel)
    box_density: float = ranged(60.0, gt=0, le=MAX_SCALAR)
    n_doors: int = ranged(5, ge=0, le=MAX_COUNT)  # doors on the walls
    door_size: list[float] = ranged(default_factory=lambda: [0.9, 2.05], gt=0, le=MAX_SCALAR)  # width, height (m)
    door_margin: float = ranged(0.4, ge=0, le=MAX_SCALAR)  # minimum distance of a door from a wall corner and from another door (m)
    door_offset: float = ranged(0.003, gt=0, le=MAX_SCALAR)  # the door leaf stands this far in front of its wall (m)


@dataclass
class PanelRoomConfig:
    """panel-room scene and motion: an elliptic arc of the body, looking out at the walls."""

    size: list[float] = ranged(default_factory=lambda: [11.5, 6.5, 2.7], gt=0, le=MAX_SCALAR)  # room x, y, z extents (m)
    path_radii: list[float] = ranged(default_factory=lambda: [4.5, 2.0], gt=0, le=MAX_SCALAR)  # ellipse of the body path (m):
    # 1.25 m from the walls (11 x 6 m: patch lost 73 frames, dense 7.3 % of path; 12 x 7: 2 failures, dense 2.3 %)
    start_angle_deg: float = ranged(-100.0, ge=-360, le=360)  # position on the ellipse at t = 0 (0: on +x)
    turn_deg: float = ranged(184.0, ge=0, le=3600)  # angle along the ellipse (= mean yaw turned) over duration_s
    duration_s: float = ranged(18.8, gt=0, le=MAX_SCALAR)  # seconds of the walk (default frames: duration * rate + 1)
    view_offset_deg: float = ranged(25.0, ge=-180, le=180)  # view direction relative to the outward normal
    # of the ellipse (positive: ahead along the walk)
    height: float = ranged(1.3, gt=0, le=MAX_SCALAR)  # mean body height (m)
    mean_pitch_deg: float = ranged(14.0, ge=-90, le=90)  # nose down: the floor enters the bottom of the view near corners
    jitter: float = ranged(1.0, ge=0, le=MAX_SCALAR)  # scale of the hand-held wobble (_PANEL_WOBBLE)
    wall_density: float = ranged(200.0, gt=0, le=MAX_SCALAR)  # texels per metre (joints of 5 mm need ~1 texel)
    floor_density: float = ranged(100.0, gt=0, le=MAX_SCALAR)
    door_at: list[float] = ranged(default_factory=lambda: [0.6], ge=0, le=1)  # one door (with a darker frame band)
    # on the wall that the mean view direction meets at each of these fractions of the walk (centred there)
    door_size: list[float] = ranged(default_factory=lambda: [0.9, 2.05], gt=0, le=MAX_SCALAR)  # width, height (m)
    door_margin: float = ranged(0.4, ge=0, le=MAX_SCALAR)  # minimum distance from a wall corner (m)
    door_offset: float = ranged(0.003, gt=0, le=MAX_SCALAR)  # the door leaf stands this far in front of its wall (m)


@dataclass
class RotationSweepConfig(RoomConfig):
    """rotation-sweep scene (the room-loop room fields, a smaller room) and its roll / pitch / yaw sweep."""

    size: list[float] = ranged(default_factory=lambda: [5.0, 4.0, 2.7], gt=0, le=MAX_SCALAR)
    n_boxes: int = ranged(8, ge=0, le=MAX_COUNT)
    path_radii: list[float] = ranged(default_factory=lambda: [0.15, 0.15], gt=0, le=MAX_SCALAR)  # boxes keep clear of it
    path_clearance: float = ranged(0.6, ge=0, le=MAX_SCALAR)
    loop_duration_s: float = ranged(10.0, gt=0, le=MAX_SCALAR)  # period of the sweep (default frames: one period + 1)
    rotation_speed_deg_s: float = ranged(69.0, ge=0, le=MAX_SCALAR)  # mean angular speed over one period: the
    # amplitudes of _SWEEP_ROTATION are scaled to it (held-out: ~1,600 deg over 723 frames at 30 Hz)
    translation_radius: float = ranged(0.15, ge=0, le=MAX_SCALAR)  # radius of the slow horizontal circle of the body (m)
    yaw_deg: float = ranged(0.0, ge=-360, le=360)  # mean heading (0: towards +x)
    phase: float = ranged(0.68, ge=0, le=1)  # the sweep starts this fraction into its period (default: its fastest
    # phase, ~3 s at 90-120 deg/s, falls in the first fifth of the default frames, as in the held-out run)


@dataclass
class StreetConfig:
    """street-loop scene and motion."""

    half_size: list[float] = ranged(default_factory=lambda: [100.0, 60.0], gt=0, le=MAX_SCALAR)  # road centre-line box (m)
    corner_radius: float = ranged(20.0, gt=0, le=MAX_SCALAR)
    harmonics: int = ranged(40, ge=1, le=MAX_COUNT)  # Fourier harmonics of the road centre line
    loop_duration_s: float = ranged(100.0, gt=0, le=MAX_SCALAR)
    jitter: float = ranged(1.0, ge=0, le=MAX_SCALAR)  # scale of the body bounce / sway
    camera_height: float = ranged(1.6, gt=0, le=MAX_SCALAR)  # body height above ground (m)
    road_band: float = ranged(11.0, gt=0, le=MAX_SCALAR)  # half-width of the high-resolution ground band (m)
    ground_tile: float = ranged(10.0, gt=0, le=MAX_SCALAR)  # size of the ground texture tiles (m)
    ground_density: float = ranged(24.0, gt=0, le=MAX_SCALAR)
    far_ground_density: float = ranged(2.0, gt=0, le=MAX_SCALAR)
    setback: float = ranged(9.0, gt=0, le=MAX_SCALAR)  # facade distance from the road centre line (m)
    building_width_range: list[float] = ranged(default_factory=lambda: [10.0, 24.0], gt=0, le=MAX_SCALAR)
    building_depth_range: list[float] = ranged(default_factory=lambda: [8.0, 14.0], gt=0, le=MAX_SCALAR)
    building_height_range: list[float] = ranged(default_factory=lambda: [6.0, 24.0], gt=0, le=MAX_SCALAR)
    building_gap_range: list[float] = ranged(default_factory=lambda: [0.0, 5.0], ge=0, le=MAX_SCALAR)
    facade_density: float = ranged(28.0, gt=0, le=MAX_SCALAR)
    side_density: float = ranged(12.0, gt=0, le=MAX_SCALAR)  # building faces perpendicular to the road
    back_density: float = ranged(2.0, gt=0, le=MAX_SCALAR)  # faces that never face the road
    parked_car_prob: float = ranged(0.35, ge=0, le=1)  # probability of a parked car per 8 m of kerb
    kerb_offset: float = ranged(4.8, ge=0, le=MAX_SCALAR)  # parked car centre distance from the centre line (m)
    pole_spacing: float = ranged(25.0, gt=0, le=MAX_SCALAR)  # mean distance between poles (m)
    object_density: float = ranged(48.0, gt=0, le=MAX_SCALAR)


@dataclass
class OrbitConfig:
    """orbit scene and motion."""

    hall_size: list[float] = ranged(default_factory=lambda: [16.0, 16.0, 6.0], gt=0, le=MAX_SCALAR)
    n_boxes: int = ranged(8, ge=0, le=MAX_COUNT)
    cluster_radius: float = ranged(1.0, ge=0, le=MAX_SCALAR)  # box centres within this radius of the origin (m)
    box_size_range: list[float] = ranged(default_factory=lambda: [0.3, 0.9], gt=0, le=MAX_SCALAR)  # box sides (m)
    radius: float = ranged(3.5, gt=0, le=MAX_SCALAR)  # orbit radius (m)
    height: float = ranged(1.5, gt=0, le=MAX_SCALAR)  # mean camera height (m)
    target_height: float = ranged(0.5, ge=0, le=MAX_SCALAR)  # height of the looked-at point (m)
    loop_duration_s: float = ranged(15.0, gt=0, le=MAX_SCALAR)
    jitter: float = ranged(1.0, ge=0, le=MAX_SCALAR)  # scale of the height / pitch oscillation
    wall_density: float = ranged(40.0, gt=0, le=MAX_SCALAR)
    floor_density: float = ranged(100.0, gt=0, le=MAX_SCALAR)
    box_density: float = ranged(200.0, gt=0, le=MAX_SCALAR)


@dataclass
class HighwayConfig:
    """highway scene and motion (x along the road at t = 0, y left, metres)."""

    speed: float = ranged(27.0, gt=0, le=MAX_SCALAR)  # forward speed along x (m/s); the bend adds a little
    duration_s: float = ranged(20.0, gt=0, le=MAX_SCALAR)  # period of the lateral bend (default frame count: one period + 1)
    bend_amplitude: float = ranged(12.0, ge=0, le=MAX_SCALAR)  # lateral offset of the S-bend, y = A (1 - cos(2 pi t / duration)) (m)
    jitter: float = ranged(1.0, ge=0, le=MAX_SCALAR)  # scale of the body bounce / sway
    camera_height: float = ranged(1.6, gt=0, le=MAX_SCALAR)  # body height above the road (m)
    lookahead: float = ranged(300.0, ge=0, le=MAX_SCALAR)  # road and roadside continue this far beyond the last frame (m)
    behind: float = ranged(30.0, ge=0, le=MAX_SCALAR)  # ... and start this far behind the first (m)
    road_band: float = ranged(12.0, gt=0, le=MAX_SCALAR)  # half-width of the high-resolution ground band (m)
    ground_tile: float = ranged(10.0, gt=0, le=MAX_SCALAR)  # size of the ground texture tiles (m)
    ground_density: float = ranged(16.0, gt=0, le=MAX_SCALAR)  # texels per metre of the road band
    far_ground_density: float = ranged(1.0, gt=0, le=MAX_SCALAR)  # texels per metre of the ground beyond the band
    far_ground_margin: float = ranged(600.0, gt=0, le=MAX_SCALAR)  # the coarse ground extends this far around the road (m)
    rail_offset: float = ranged(7.5, gt=0, le=MAX_SCALAR)  # guard rails' distance from the road centre line (m)
    rail_size: list[float] = ranged(default_factory=lambda: [0.3, 0.8], gt=0, le=MAX_SCALAR)  # rail (width, height) (m)
    rail_segment: float = ranged(12.0, gt=0, le=MAX_SCALAR)  # length of a straight rail segment (m)
    rail_gap_prob: float = ranged(0.25, ge=0, le=1)  # probability that a segment is left out
    pole_offset: float = ranged(9.5, gt=0, le=MAX_SCALAR)  # lamp poles' distance from the centre line (m)
    pole_spacing: float = ranged(45.0, gt=0, le=MAX_SCALAR)  # mean distance between poles on each side (m)
    pole_size: list[float] = ranged(default_factory=lambda: [0.3, 0.3, 9.0], gt=0, le=MAX_SCALAR)  # pole box (m)
    sign_spacing: float = ranged(160.0, gt=0, le=MAX_SCALAR)  # mean distance between sign boards on each side (m)
    sign_offset: float = ranged(11.0, gt=0, le=MAX_SCALAR)  # sign boards' distance from the centre line (m)
    sign_size: list[float] = ranged(default_factory=lambda: [4.5, 0.2, 2.5], gt=0, le=MAX_SCALAR)  # board (along x, thick, height) (m)
    sign_height: float = ranged(4.0, ge=0, le=MAX_SCALAR)  # bottom edge of a sign board above the road (m)
    building_distance: list[float] = ranged(default_factory=lambda: [60.0, 220.0], gt=0, le=MAX_SCALAR)  # lateral range of building centres (m)
    building_spacing: float = ranged(100.0, gt=0, le=MAX_SCALAR)  # mean distance between buildings on each side (m)
    building_size_range: list[float] = ranged(default_factory=lambda: [12.0, 40.0], gt=0, le=MAX_SCALAR)  # horizontal sides (m)
    building_height_range: list[float] = ranged(default_factory=lambda: [8.0, 35.0], gt=0, le=MAX_SCALAR)
    hill_distance: list[float] = ranged(default_factory=lambda: [350.0, 700.0], gt=0, le=MAX_SCALAR)  # lateral / ahead range of hill centres (m)
    hill_spacing: float = ranged(250.0, gt=0, le=MAX_SCALAR)  # mean distance between hills on each side (m)
    hill_size_range: list[float] = ranged(default_factory=lambda: [200.0, 500.0], gt=0, le=MAX_SCALAR)  # hill widths (m)
    hill_height_range: list[float] = ranged(default_factory=lambda: [40.0, 140.0], gt=0, le=MAX_SCALAR)
    object_density: float = ranged(48.0, gt=0, le=MAX_SCALAR)  # texels per metre of rails, poles, signs
    building_density: float = ranged(6.0, gt=0, le=MAX_SCALAR)
    hill_density: float = ranged(2.0, gt=0, le=MAX_SCALAR)


@dataclass
class KittiDriveConfig:
    """kitti00-drive scene and motion: the camera path of a KITTI pose file with a street built along it."""

    poses: str = ""  # KITTI pose file (one 3x4 T_K0Ci per line); "": <repository>/../shared/data/kitti_gt/00.txt
    camera_height: float = ranged(1.65, gt=0, le=MAX_SCALAR)  # camera above the road (m; KITTI's mount)
    lookahead: float = ranged(150.0, ge=0, le=MAX_SCALAR)  # the scene covers the path this far beyond the last frame (m)
    grid_cell: float = ranged(0.5, gt=0, le=MAX_SCALAR)  # m; raster of the layout (distance to the road, occupied ground)
    road_band: float = ranged(11.0, gt=0, le=MAX_SCALAR)  # half-width of the textured ground along the road (m)
    ground_tile: float = ranged(8.0, gt=0, le=MAX_SCALAR)  # side of a ground tile (m); each tile is a plane fitted to
    ground_fit_radius: float = ranged(15.0, gt=0, le=MAX_SCALAR)  # the road heights within this distance (m)
    ground_fit_height: float = ranged(1.5, gt=0, le=MAX_SCALAR)  # ... and within this height of the nearest one (m)
    max_ground_slope: float = ranged(0.12, ge=0, le=MAX_SCALAR)  # tile slopes are clipped to this (KITTI 00: <= 0.07)
    ground_overlap: float = ranged(0.05, ge=0, le=MAX_SCALAR)  # tiles are grown by this much (m): no cracks where slopes differ
    ground_density: float = ranged(12.0, gt=0, le=MAX_SCALAR)  # texels per metre
    far_ground_density: float = ranged(1.0, gt=0, le=MAX_SCALAR)
    far_ground_drop: float = ranged(0.5, ge=0, le=MAX_SCALAR)  # the coarse ground lies this far below the lowest road (m)
    far_ground_margin: float = ranged(60.0, ge=0, le=MAX_SCALAR)  # ... and extends this far beyond the scene's path (m)
    setback: float = ranged(9.0, gt=0, le=MAX_SCALAR)  # facade distance from the road centre line (m)
    setback_jitter: float = ranged(2.0, ge=0, le=MAX_SCALAR)  # random extra setback of each building (m)
    clearance: float = ranged(7.5, ge=0, le=MAX_SCALAR)  # no building comes closer than this to any road of the path (m)
    building_width_range: list[float] = ranged(default_factory=lambda: [8.0, 22.0], gt=0, le=MAX_SCALAR)
    building_depth_range: list[float] = ranged(default_factory=lambda: [8.0, 14.0], gt=0, le=MAX_SCALAR)
    building_height_range: list[float] = ranged(default_factory=lambda: [6.0, 20.0], gt=0, le=MAX_SCALAR)
    building_gap_range: list[float] = ranged(default_factory=lambda: [0.0, 4.0], ge=0, le=MAX_SCALAR)
    building_sink: float = ranged(3.0, ge=0, le=MAX_SCALAR)  # buildings reach this far below the road (m): no gaps on slopes
    facade_density: float = ranged(16.0, gt=0, le=MAX_SCALAR)  # ~1 texel per pixel at 9 m for 320 px at 82 deg
    side_density: float = ranged(8.0, gt=0, le=MAX_SCALAR)  # building faces perpendicular to the road
    back_density: float = ranged(2.0, gt=0, le=MAX_SCALAR)  # faces that never face the road
    pole_spacing: float = ranged(25.0, gt=0, le=MAX_SCALAR)  # mean distance between lamp poles on each side (m)
    pole_setback: float = ranged(1.5, ge=0, le=MAX_SCALAR)  # poles stand this much closer to the road than the facades (m)
    object_density: float = ranged(32.0, gt=0, le=MAX_SCALAR)  # texels per metre of the poles


@dataclass
class SynthConfig:
    """Everything the generator needs; ``default_config(preset)`` gives the preset's defaults."""

    preset: str = "room-loop"
    frames: int = ranged(401, ge=1, le=MAX_FRAMES)  # camera frames (default: one loop period + 1)
    seed: int = ranged(0, ge=0, le=MAX_SEED)
    start_time_ns: int = ranged(1_600_000_000_000_000_000, ge=0, le=MAX_TIME_NS)  # timestamp of frame 0
    camera: CameraConfig = field(default_factory=CameraConfig)
    imu: ImuConfig = field(default_factory=ImuConfig)
    texture: TextureConfig = field(default_factory=TextureConfig)
    render: RenderConfig = field(default_factory=RenderConfig)
    room: RoomConfig = field(default_factory=RoomConfig)
    low_texture: LowTextureConfig = field(default_factory=LowTextureConfig)
    street: StreetConfig = field(default_factory=StreetConfig)
    orbit: OrbitConfig = field(default_factory=OrbitConfig)
    highway: HighwayConfig = field(default_factory=HighwayConfig)
    panel_room: PanelRoomConfig = field(default_factory=PanelRoomConfig)
    rotation_sweep: RotationSweepConfig = field(default_factory=RotationSweepConfig)
    kitti_drive: KittiDriveConfig = field(default_factory=KittiDriveConfig)
    stop_frame: int = ranged(0, ge=0, le=MAX_FRAMES)  # stop-and-go: camera frame at which the body comes to rest (any preset)
    stop_frames: int = ranged(0, ge=0, le=MAX_FRAMES)  # stop-and-go: frames the body stays at rest (0: no stop); the motion after it is delayed
    stop_ramp_s: float = ranged(1.0, gt=0, le=MAX_SCALAR)  # stop-and-go: seconds of smooth deceleration before and acceleration after the stop

    def validate(self) -> None:
        if self.preset not in PRESET_NAMES:
            raise ConfigError(f"preset: unknown preset '{self.preset}' (valid: {', '.join(PRESET_NAMES)})")
        check_ranges(self)
        if len(self.texture.plain.albedo) != 3:
            raise ConfigError("texture.plain.albedo: expected 3 albedos (plain, tiles, door), "
                              f"got {len(self.texture.plain.albedo)}")
        if self.camera.distortion_model not in DISTORTION_MODELS:
            raise ConfigError(f"camera.distortion_model: expected one of {', '.join(DISTORTION_MODELS)}, "
                              f"got {self.camera.distortion_model!r}")
        if len(self.camera.distortion) != 4:
            raise ConfigError("camera.distortion: expected 4 radial-tangential coefficients (k1, k2, p1, p2), "
                              f"got {len(self.camera.distortion)}")
        if 1e9 / self.camera.rate_hz != round(1e9 / self.camera.rate_hz) or \
                1e9 / self.imu.rate_hz != round(1e9 / self.imu.rate_hz):
            raise ConfigError("camera.rate_hz / imu.rate_hz: periods must be whole nanoseconds")

    def loop_duration_s(self) -> float:
        return {"room-loop": self.room.loop_duration_s, "low-texture": self.low_texture.loop_duration_s,
                "street-loop": self.street.loop_duration_s,
                "orbit": self.orbit.loop_duration_s, "highway": self.highway.duration_s,
                "panel-room": self.panel_room.duration_s,
                "rotation-sweep": self.rotation_sweep.loop_duration_s,
                "kitti00-drive": (_KITTI_FRAMES - 1) / _KITTI_RATE_HZ}[self.preset]


def default_config(preset: str) -> SynthConfig:
    """Preset defaults: frame count = one loop + 1, resolution, field of view, rate, baseline."""
    if preset not in PRESET_NAMES:
        raise ConfigError(f"unknown preset '{preset}' (valid: {', '.join(PRESET_NAMES)})")
    cfg = SynthConfig(preset=preset)
    if preset in ("street-loop", "highway"):
        cfg.camera = CameraConfig(width=640, height=200, hfov_deg=82.0, rate_hz=10.0, baseline=0.54)
    elif preset == "orbit":
        cfg.camera = CameraConfig(hfov_deg=70.0)
    elif preset == "panel-room":  # VGA RGB-D at 10 Hz, albedo-only textures lit per pixel by the point light
        cfg.camera = CameraConfig(hfov_deg=_PANEL_HFOV_DEG, rate_hz=10.0, colour=True)
        cfg.texture = TextureConfig(ambient=1.0, colour_saturation=_PANEL_COLOUR_SATURATION,
                                    plain=PlainTextureConfig(tile_line_depth=_PANEL_TILE_LINE_DEPTH,
                                                             panel_albedo_jitter=_PANEL_ALBEDO_JITTER))
        cfg.render = RenderConfig(point_light=True, light_position=[0.0, 0.0, cfg.panel_room.size[2] - _LIGHT_BELOW_CEILING],
                                  vignetting=_PANEL_VIGNETTING)
    elif preset == "rotation-sweep":  # Kinect-like VGA at 30 Hz with a strong barrel distortion
        cfg.camera = CameraConfig(hfov_deg=_SWEEP_HFOV_DEG, rate_hz=_SWEEP_RATE_HZ, colour=True,
                                  distortion=list(_SWEEP_DISTORTION), exposure_s=_SWEEP_EXPOSURE_S,
                                  blur_samples=_SWEEP_BLUR_SAMPLES)
    elif preset == "kitti00-drive":  # KITTI's aspect and field of view, small; the pose file sets the mount
        cfg.camera = CameraConfig(width=_KITTI_SIZE[0], height=_KITTI_SIZE[1], hfov_deg=_KITTI_HFOV_DEG,
                                  rate_hz=_KITTI_RATE_HZ, baseline=_KITTI_BASELINE)
        cfg.render = RenderConfig(max_distance=_KITTI_MAX_DISTANCE)
    cfg.frames = int(round(cfg.loop_duration_s() * cfg.camera.rate_hz)) + 1
    return cfg


# nominal forward-looking mount: camera z = body x (forward), camera x = -body y, camera y = -body z
R_B_CAM_NOMINAL = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


def camera_mount(cam: CameraConfig) -> np.ndarray:
    """(4, 4) ``T_BS`` of cam0: the nominal forward-looking mount times the small rotation
    ``Rz(yaw) Ry(pitch) Rx(roll)`` of ``cam.mount_rpy_deg`` (camera axes), origin at ``cam.t_BS``."""
    roll, pitch, yaw = np.deg2rad(cam.mount_rpy_deg)
    R_pert = euler_zyx_to_R(np.array(yaw), np.array(pitch), np.array(roll))
    T = np.eye(4)
    T[:3, :3] = R_B_CAM_NOMINAL @ R_pert
    T[:3, 3] = cam.t_BS
    return T


def kitti_poses_path(kc: KittiDriveConfig) -> Path:
    """The pose file of ``kc.poses`` ("": the repository's ``../shared/data/kitti_gt/00.txt``)."""
    if kc.poses:
        return Path(kc.poses).expanduser()
    return Path(__file__).resolve().parents[4] / "shared" / "data" / "kitti_gt" / "00.txt"


def load_kitti_poses(path: Path) -> np.ndarray:
    """(N, 4, 4) ``T_K0Ci`` of a KITTI pose file (12 numbers per line: the 3x4 camera-to-world matrix),
    read by :func:`fgslam.io.trajectory.read_trajectory` (its format errors name the file and line)."""
    if not path.is_file():
        raise DataError(f"kitti_drive.poses: KITTI pose file {path} not found (the kitti00-drive preset follows "
                        "a KITTI ground-truth path: set kitti_drive.poses=FILE, e.g. kitti_gt/00.txt of the shared data)")
    T = read_trajectory(path, "kitti").T_WC
    if len(T) < 2:
        raise DataError(f"{path}: expected at least 2 KITTI poses, got {len(T)}")
    return T


def kitti_camera_poses(cfg: SynthConfig) -> np.ndarray:
    """(N, 4, 4) ``T_WC`` of every row of the preset's pose file in the generator's world (z up, the
    road under the first camera at z = 0): ``T_WC = T_WK T_K0Ci`` with ``T_WK = [R_W_KITTI | (0, 0,
    camera_height)]``; a ConfigError when ``frames`` exceeds the rows."""
    kc = cfg.kitti_drive
    T_KC = load_kitti_poses(kitti_poses_path(kc))
    if cfg.frames > len(T_KC):
        raise ConfigError(f"frames: {cfg.frames} frames asked but {kitti_poses_path(kc)} has {len(T_KC)} poses")
    T_WK = np.eye(4)
    T_WK[:3, :3] = R_W_KITTI
    T_WK[2, 3] = kc.camera_height
    return T_WK @ T_KC


# ----------------------------------------------------------------------------------- scenes

def _room_box(scene: Scene, size, density: float, style: int, center=(0.0, 0.0),
              floor_style: int = STYLE_GROUND) -> None:
    """Inward-facing room (walls, floor, ceiling) of ``size = (x, y, z)``, floor at z = 0."""
    sx, sy, sz = size
    x0, x1 = center[0] - sx / 2, center[0] + sx / 2
    y0, y1 = center[1] - sy / 2, center[1] + sy / 2
    ez = (0.0, 0.0, 1.0)
    scene.add_quad((x1, y0, 0), (-1, 0, 0), ez, sx, sz, density=density, style=style)  # y0, faces +y
    scene.add_quad((x0, y1, 0), (1, 0, 0), ez, sx, sz, density=density, style=style)   # y1, faces -y
    scene.add_quad((x1, y1, 0), (0, -1, 0), ez, sy, sz, density=density, style=style)  # x1, faces -x
    scene.add_quad((x0, y0, 0), (0, 1, 0), ez, sy, sz, density=density, style=style)   # x0, faces +x
    scene.add_quad((x0, y0, 0), (1, 0, 0), (0, 1, 0), sx, sy, density=density, style=floor_style)
    scene.add_quad((x0, y1, sz), (1, 0, 0), (0, -1, 0), sx, sy, density=density, style=style)


def _build_room(cfg: RoomConfig, rng: np.random.Generator, wall_style: int = STYLE_WALL,
                floor_style: int = STYLE_GROUND, box_style: int = STYLE_OBJECT) -> Scene:
    scene = Scene()
    _room_box(scene, cfg.size, cfg.wall_density, wall_style, floor_style=floor_style)
    sx, sy, _ = cfg.size
    rx, ry = cfg.path_radii
    placed = 0
    for _ in range(1000 * max(cfg.n_boxes, 1)):
        if placed == cfg.n_boxes:
            break
        w, d = rng.uniform(*cfg.box_size_range, size=2)
        h = rng.uniform(*cfg.box_height_range)
        r_box = 0.5 * np.hypot(w, d)
        x = rng.uniform(-sx / 2 + r_box, sx / 2 - r_box)
        y = rng.uniform(-sy / 2 + r_box, sy / 2 - r_box)
        m = cfg.path_clearance + r_box
        if (x / (rx + m)) ** 2 + (y / (ry + m)) ** 2 < 1.0:
            continue
        scene.add_box((x, y, h / 2), (w, d, h), rng.uniform(0, np.pi), density=cfg.box_density,
                      style=box_style, faces=("+x", "-x", "+y", "-y", "+z"))
        placed += 1
    return scene


def _build_low_texture(cfg: LowTextureConfig, rng: np.random.Generator) -> Scene:
    """The room of :func:`_build_room` in plain styles, plus ``n_doors`` doors (:func:`_add_doors`)."""
    scene = _build_room(cfg, rng, wall_style=STYLE_PLAIN, floor_style=STYLE_TILES, box_style=STYLE_PLAIN)
    _add_doors(scene, cfg, cfg.wall_density, rng)
    return scene


def _add_doors(scene: Scene, cfg, density: float, rng: np.random.Generator) -> None:
    """``cfg.n_doors`` doors (``door_size``, ``door_margin``, ``door_offset`` of ``cfg``): quads just in
    front of the walls (the first four quads of :func:`_room_box`: origin corner, u along the wall)."""
    walls = scene.arrays()
    door_w, door_h = cfg.door_size
    taken: list[list[tuple[float, float]]] = [[] for _ in range(4)]  # door intervals along each wall
    placed = 0
    for _ in range(1000 * max(cfg.n_doors, 1)):
        if placed == cfg.n_doors:
            break
        wall = int(rng.integers(0, 4))  # the first four quads of _room_box are the walls
        length = walls.sizes[wall, 0]
        if length < door_w + 2 * cfg.door_margin:
            continue
        s0 = rng.uniform(cfg.door_margin, length - cfg.door_margin - door_w)
        if any(s0 < b + cfg.door_margin and a < s0 + door_w + cfg.door_margin for a, b in taken[wall]):
            continue
        taken[wall].append((s0, s0 + door_w))
        origin = walls.origins[wall] + s0 * walls.axes_u[wall] + cfg.door_offset * walls.normals[wall]
        scene.add_quad(origin, walls.axes_u[wall], walls.axes_v[wall], door_w, door_h,
                       density=density, style=STYLE_DOOR)
        placed += 1


def _build_panel_room(cfg: PanelRoomConfig) -> Scene:
    """Walls of near-white panels (joints every ``texture.plain.panel_size_m``), a tiled floor, a plain
    ceiling and a door at each ``door_at`` fraction of the walk, where the mean view direction (the
    ellipse angle plus ``view_offset_deg``, without wobble) meets a wall; no furniture, no randomness."""
    scene = Scene()
    _room_box(scene, cfg.size, cfg.wall_density, STYLE_PANELS, floor_style=STYLE_TILES)
    # floor and ceiling (quads 4 and 5 of _room_box) at their own density; a plain ceiling
    scene.densities[4] = cfg.floor_density
    scene.densities[5] = cfg.floor_density
    scene.styles[5] = STYLE_PLAIN
    walls = scene.arrays()
    rx, ry = cfg.path_radii
    door_w, door_h = cfg.door_size
    for frac in cfg.door_at:
        phi = np.deg2rad(cfg.start_angle_deg + frac * cfg.turn_deg)
        p = np.array([rx * np.cos(phi), ry * np.sin(phi), 0.0])
        view = phi + np.deg2rad(cfg.view_offset_deg)
        d = np.array([np.cos(view), np.sin(view), 0.0])
        best = None  # (ray parameter, wall) of the nearest wall the view ray meets from inside
        for wall in range(4):
            den = float(walls.normals[wall] @ d)
            if den >= 0:  # inward-facing walls: the ray must run against the normal
                continue
            lam = float(walls.normals[wall] @ (walls.origins[wall] - p)) / den
            if best is None or lam < best[0]:
                best = (lam, wall)
        if best is None:
            continue
        wall = best[1]
        length = walls.sizes[wall, 0]
        s_hit = float((p + best[0] * d - walls.origins[wall]) @ walls.axes_u[wall])
        s0 = float(np.clip(s_hit - door_w / 2, cfg.door_margin, max(cfg.door_margin, length - cfg.door_margin - door_w)))
        origin = walls.origins[wall] + s0 * walls.axes_u[wall] + cfg.door_offset * walls.normals[wall]
        scene.add_quad(origin, walls.axes_u[wall], walls.axes_v[wall], door_w, door_h,
                       density=cfg.wall_density, style=STYLE_DOOR)
    return scene


def _build_street(cfg: StreetConfig, rng: np.random.Generator) -> Scene:
    scene = Scene()
    hx, hy = cfg.half_size
    r = cfg.corner_radius
    margin = cfg.setback + max(cfg.building_depth_range) + _FAR_GROUND_MARGIN
    scene.add_quad((-hx - margin, -hy - margin, -0.05), (1, 0, 0), (0, 1, 0), 2 * (hx + margin),
                   2 * (hy + margin), density=cfg.far_ground_density, style=STYLE_GROUND)
    # high-resolution ground tiles where the distance to the road centre line < road_band
    tile = cfg.ground_tile
    xs = np.arange(-hx - cfg.road_band - tile, hx + cfg.road_band + tile, tile)
    ys = np.arange(-hy - cfg.road_band - tile, hy + cfg.road_band + tile, tile)
    line = rounded_rectangle(hx, hy, r, _GROUND_LINE_SAMPLES)
    for x0 in xs:
        for y0 in ys:
            c = np.array([x0 + tile / 2, y0 + tile / 2])
            if np.min(np.linalg.norm(line - c, axis=1)) < cfg.road_band + tile / 2:
                scene.add_quad((x0, y0, 0.0), (1, 0, 0), (0, 1, 0), tile, tile,
                               density=cfg.ground_density, style=STYLE_GROUND)
    sides = [((0.0, -hy), (1.0, 0.0), 2 * (hx - r)), ((hx, 0.0), (0.0, 1.0), 2 * (hy - r)),
             ((0.0, hy), (-1.0, 0.0), 2 * (hx - r)), ((-hx, 0.0), (0.0, -1.0), 2 * (hy - r))]
    for c, tdir, length in sides:
        c, tdir = np.array(c), np.array(tdir)
        left = np.array([-tdir[1], tdir[0]])  # towards the block centre
        yaw = float(np.arctan2(tdir[1], tdir[0]))
        for sign, front in ((1.0, "-y"), (-1.0, "+y")):
            s = -length / 2 + rng.uniform(*cfg.building_gap_range)
            while True:
                w = rng.uniform(*cfg.building_width_range)
                if s + w > length / 2:
                    break
                d = rng.uniform(*cfg.building_depth_range)
                h = rng.uniform(*cfg.building_height_range)
                off = cfg.setback + rng.uniform(0.0, _SETBACK_JITTER) + d / 2
                center = c + tdir * (s + w / 2) + sign * left * off
                back = "+y" if front == "-y" else "-y"
                scene.add_box((center[0], center[1], h / 2), (w, d, h), yaw, density=cfg.facade_density,
                              style=STYLE_WALL, faces=("+x", "-x", "+y", "-y"),
                              face_density={back: cfg.back_density, "+x": cfg.side_density,
                                          "-x": cfg.side_density})
                s += w + rng.uniform(*cfg.building_gap_range)
            # parked cars along the kerb and poles on the pavement
            for s_car in np.arange(-length / 2 + _CAR_SLOT / 2, length / 2 - _CAR_SLOT / 2, _CAR_SLOT):
                if rng.random() < cfg.parked_car_prob:
                    center = c + tdir * (s_car + rng.uniform(-1, 1)) + sign * left * cfg.kerb_offset
                    scene.add_box((center[0], center[1], _CAR_SIZE[2] / 2), _CAR_SIZE,
                                  yaw + rng.uniform(-_CAR_YAW, _CAR_YAW), density=cfg.object_density,
                                  style=STYLE_OBJECT, faces=("+x", "-x", "+y", "-y", "+z"))
            s = -length / 2 + rng.uniform(0, cfg.pole_spacing)
            while s < length / 2:
                center = c + tdir * s + sign * left * (cfg.setback - _POLE_SETBACK)
                scene.add_box((center[0], center[1], _POLE_SIZE[2] / 2), _POLE_SIZE, yaw,
                              density=cfg.object_density, style=STYLE_OBJECT,
                              faces=("+x", "-x", "+y", "-y"))
                s += rng.uniform(0.5, 1.5) * cfg.pole_spacing
    # one building facing each outer corner (its front face at the setback from the curved road)
    for sx_, sy_ in ((1, -1), (1, 1), (-1, 1), (-1, -1)):
        centre = np.array([sx_ * (hx - r), sy_ * (hy - r)])
        phi = float(np.arctan2(sy_, sx_))
        d = rng.uniform(*cfg.building_depth_range)
        h = rng.uniform(*cfg.building_height_range)
        pos = centre + (r + cfg.setback + d / 2) * np.array([np.cos(phi), np.sin(phi)])
        scene.add_box((pos[0], pos[1], h / 2), (max(cfg.building_width_range), d, h), phi + 0.5 * np.pi,
                      density=cfg.facade_density, style=STYLE_WALL, faces=("+x", "-x", "+y", "-y"),
                      face_density={"-y": cfg.back_density, "+x": cfg.side_density,
                                    "-x": cfg.side_density})
    return scene


def _build_orbit(cfg: OrbitConfig, rng: np.random.Generator) -> Scene:
    scene = Scene()
    _room_box(scene, cfg.hall_size, cfg.wall_density, STYLE_WALL)
    # replace the floor density: a dense floor quad just above the coarse one near the cluster
    half = cfg.radius + _ORBIT_FLOOR_MARGIN
    scene.add_quad((-half, -half, _DECAL_OFFSET), (1, 0, 0), (0, 1, 0), 2 * half, 2 * half,
                   density=cfg.floor_density, style=STYLE_GROUND)
    stacks: list[tuple[float, float, float, float]] = []  # x, y, footprint radius, top height
    for _ in range(cfg.n_boxes):
        w, d = rng.uniform(*cfg.box_size_range, size=2)
        h = rng.uniform(*cfg.box_size_range)
        rad = rng.uniform(0, cfg.cluster_radius)
        ang = rng.uniform(0, 2 * np.pi)
        x, y = rad * np.cos(ang), rad * np.sin(ang)
        base = 0.0
        for (px, py, pr, top) in stacks:  # stack on a box whose footprint contains the centre
            if np.hypot(x - px, y - py) < 0.5 * pr:
                base = max(base, top)
        scene.add_box((x, y, base + h / 2), (w, d, h), rng.uniform(0, np.pi), density=cfg.box_density,
                      style=STYLE_OBJECT, faces=("+x", "-x", "+y", "-y", "+z"))
        stacks.append((x, y, 0.5 * min(w, d), base + h))
    return scene


def highway_centre_line(hc: HighwayConfig, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Lateral position y (m) and heading (rad) of the highway's centre line at ``x`` (m): the body
    path of the ``highway`` trajectory, ``y = A (1 - cos(2 pi x / (speed * duration)))``."""
    x = np.asarray(x, np.float64)
    k = 2.0 * np.pi / (hc.speed * hc.duration_s)
    y = hc.bend_amplitude * (1.0 - np.cos(k * x))
    heading = np.arctan(hc.bend_amplitude * k * np.sin(k * x))
    return y, heading


def _highway_extent(cfg: SynthConfig) -> tuple[float, float]:
    """x range (m) the highway scene covers: the frames' path plus ``behind`` / ``lookahead``."""
    hc = cfg.highway
    x_last = hc.speed * (cfg.frames - 1) / cfg.camera.rate_hz
    return -hc.behind, x_last + hc.lookahead


def _spaced(rng: np.random.Generator, x0: float, x1: float, spacing: float) -> list[float]:
    """Positions from ``x0`` to ``x1`` at random gaps of 0.5-1.5 x ``spacing``."""
    out, x = [], x0 + rng.uniform(0.0, spacing)
    while x < x1:
        out.append(x)
        x += rng.uniform(0.5, 1.5) * spacing
    return out


def _build_highway(cfg: SynthConfig, rng: np.random.Generator) -> Scene:
    hc = cfg.highway
    scene = Scene()
    x_start, x_end = _highway_extent(cfg)
    m = hc.far_ground_margin
    y_lo, y_hi = -m, 2.0 * hc.bend_amplitude + m
    scene.add_quad((x_start - m, y_lo, -0.05), (1, 0, 0), (0, 1, 0), x_end - x_start + 2 * m, y_hi - y_lo,
                   density=hc.far_ground_density, style=STYLE_GROUND)
    # high-resolution ground tiles within road_band of the centre line
    tile = hc.ground_tile
    for x0 in np.arange(x_start, x_end, tile):
        yc, _ = highway_centre_line(hc, np.linspace(x0, x0 + tile, 5))
        lo = np.floor((yc.min() - hc.road_band) / tile) * tile
        for y0 in np.arange(lo, yc.max() + hc.road_band, tile):
            scene.add_quad((x0, y0, 0.0), (1, 0, 0), (0, 1, 0), tile, tile, density=hc.ground_density,
                           style=STYLE_GROUND)

    def roadside(x: float, offset: float, sign: float) -> tuple[np.ndarray, float]:
        y, heading = highway_centre_line(hc, np.array(x))
        normal = np.array([-np.sin(heading), np.cos(heading)])  # left of the direction of travel
        return np.array([x, float(y)]) + sign * offset * normal, float(heading)

    rail_w, rail_h = hc.rail_size
    pole = hc.pole_size
    sign_w, sign_t, sign_h = hc.sign_size
    for side in (1.0, -1.0):
        for x0 in np.arange(x_start, x_end, hc.rail_segment):  # guard rail segments, some left out
            if rng.random() < hc.rail_gap_prob:
                continue
            c, yaw = roadside(x0 + hc.rail_segment / 2, hc.rail_offset, side)
            scene.add_box((c[0], c[1], rail_h / 2), (hc.rail_segment / np.cos(yaw), rail_w, rail_h), yaw,
                          density=hc.object_density, style=STYLE_OBJECT, faces=("+x", "-x", "+y", "-y", "+z"))
        for x in _spaced(rng, x_start, x_end, hc.pole_spacing):  # lamp poles
            c, yaw = roadside(x, hc.pole_offset, side)
            scene.add_box((c[0], c[1], pole[2] / 2), pole, yaw, density=hc.object_density,
                          style=STYLE_OBJECT, faces=("+x", "-x", "+y", "-y"))
        for x in _spaced(rng, x_start, x_end, hc.sign_spacing):  # sign boards facing the traffic, on a post
            c, yaw = roadside(x, hc.sign_offset, side)
            scene.add_box((c[0], c[1], hc.sign_height + sign_h / 2), (sign_t, sign_w, sign_h), yaw,
                          density=hc.object_density, style=STYLE_OBJECT, faces=("+x", "-x", "+y", "-y", "+z"))
            scene.add_box((c[0], c[1], hc.sign_height / 2), (pole[0], pole[1], hc.sign_height), yaw,
                          density=hc.object_density, style=STYLE_OBJECT, faces=("+x", "-x", "+y", "-y"))
        for x in _spaced(rng, x_start, x_end, hc.building_spacing):  # distant buildings
            c, yaw = roadside(x, rng.uniform(*hc.building_distance), side)
            w, d = rng.uniform(*hc.building_size_range, size=2)
            h = rng.uniform(*hc.building_height_range)
            scene.add_box((c[0], c[1], h / 2), (w, d, h), yaw + rng.uniform(-0.5, 0.5), density=hc.building_density,
                          style=STYLE_WALL, faces=("+x", "-x", "+y", "-y"))
        for x in _spaced(rng, x_start, x_end + hc.hill_distance[1], hc.hill_spacing):  # hills on the sides
            c, yaw = roadside(x, rng.uniform(*hc.hill_distance), side)
            w, h = rng.uniform(*hc.hill_size_range), rng.uniform(*hc.hill_height_range)
            scene.add_box((c[0], c[1], h / 2), (w, 0.5 * w, h), yaw + rng.uniform(-0.3, 0.3),
                          density=hc.hill_density, style=STYLE_WALL, faces=("+x", "-x", "+y", "-y"))
    # hills across the road beyond its end: far structure at the centre of the image
    y_end, _ = highway_centre_line(hc, np.array(x_end))
    y = float(y_end) - hc.hill_distance[1]
    while y < float(y_end) + hc.hill_distance[1]:
        w, h = rng.uniform(*hc.hill_size_range), rng.uniform(*hc.hill_height_range)
        x = x_end + rng.uniform(*hc.hill_distance)
        scene.add_box((x, y + w / 2, h / 2), (0.5 * w, w, h), rng.uniform(-0.3, 0.3), density=hc.hill_density,
                      style=STYLE_WALL, faces=("+x", "-x", "+y", "-y"))
        y += w
    return scene


def _kitti_scene_path(cfg: SynthConfig, T_WC: np.ndarray) -> np.ndarray:
    """(M, 3) road centre points (camera positions lowered by ``camera_height``) of the configured frames
    and of the rows up to ``lookahead`` metres of path beyond the last one."""
    kc = cfg.kitti_drive
    p = T_WC[:, :3, 3] - np.array([0.0, 0.0, kc.camera_height])
    seg = np.linalg.norm(np.diff(p, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    last = cfg.frames - 1
    end = int(np.searchsorted(s, s[last] + kc.lookahead, side="right"))
    return p[:max(end, last + 1)]


def _ground_plane(road: np.ndarray, centre: np.ndarray, kc: KittiDriveConfig) -> tuple[float, float, float]:
    """Height and slopes ``(z, dz/dx, dz/dy)`` at ``centre`` of the plane fitted (least squares, slopes
    regularised by :data:`_KITTI_RIDGE`, then clipped to ``max_ground_slope``) to the road points within
    ``ground_fit_radius`` whose height is within ``ground_fit_height`` of the nearest road point's (a
    nearby road at another level does not tilt the tile); that nearest height and no slope when no
    other point is that close."""
    d = np.linalg.norm(road[:, :2] - centre, axis=1)
    z_nearest = road[np.argmin(d), 2]
    near = (d < kc.ground_fit_radius) & (np.abs(road[:, 2] - z_nearest) < kc.ground_fit_height)
    if near.sum() < 2:
        return float(z_nearest), 0.0, 0.0
    dx = road[near, :2] - centre
    ridge = _KITTI_RIDGE * np.sqrt(len(dx))  # a slope of 1 costs as much as every point _KITTI_RIDGE m off
    A = np.concatenate([np.column_stack([np.ones(len(dx)), dx]), np.diag([0.0, ridge, ridge])[1:]])
    b = np.concatenate([road[near, 2], [0.0, 0.0]])
    g = np.clip(np.linalg.lstsq(A, b, rcond=None)[0][1:], -kc.max_ground_slope, kc.max_ground_slope)
    z = float(np.mean(road[near, 2] - dx @ g))  # the plane through the points' mean with the slopes kept
    return z, float(g[0]), float(g[1])


def _build_kitti_drive(cfg: SynthConfig, rng: np.random.Generator) -> Scene:
    """Street along the KITTI path (module docstring): a raster of the distance to the road centre line
    (every row's path, so that no building stands on a road driven later) and of the ground already
    built on decides where buildings and poles go."""
    kc = cfg.kitti_drive
    T_WC = kitti_camera_poses(cfg)
    road_all = T_WC[:, :3, 3] - np.array([0.0, 0.0, kc.camera_height])
    road = _kitti_scene_path(cfg, T_WC)
    scene = Scene()
    reach = kc.setback + kc.setback_jitter + max(kc.building_depth_range) + kc.far_ground_margin
    lo = road[:, :2].min(axis=0) - reach
    hi = road[:, :2].max(axis=0) + reach
    cell = kc.grid_cell
    shape = tuple(int(np.ceil(v)) + 1 for v in (hi - lo)[::-1] / cell)  # rows (y), columns (x)

    def to_px(xy: np.ndarray) -> np.ndarray:
        return np.round((np.asarray(xy) - lo) / cell).astype(np.int64)

    canvas = np.full(shape, 255, np.uint8)
    inside = np.all((road_all[:, :2] >= lo) & (road_all[:, :2] <= hi), axis=1)
    for run in np.split(np.arange(len(road_all)), np.flatnonzero(np.diff(inside.astype(np.int8)) != 0) + 1):
        if inside[run[0]] and len(run) > 1:
            cv2.polylines(canvas, [to_px(road_all[run, :2]).astype(np.int32)], False, 0, 1)
        elif inside[run[0]]:
            canvas[tuple(to_px(road_all[run[0], :2])[::-1])] = 0
    dist_road = cv2.distanceTransform(canvas, cv2.DIST_L2, cv2.DIST_MASK_PRECISE) * cell  # metres
    taken = np.zeros(shape, bool)

    def lookup(raster: np.ndarray, xy: np.ndarray) -> np.ndarray:
        px = to_px(xy)
        px[:, 0] = px[:, 0].clip(0, shape[1] - 1)
        px[:, 1] = px[:, 1].clip(0, shape[0] - 1)
        return raster[px[:, 1], px[:, 0]]

    # coarse ground below everything, then tiles along the road following its height
    z_floor = float(road[:, 2].min()) - kc.far_ground_drop
    scene.add_quad((lo[0], lo[1], z_floor), (1, 0, 0), (0, 1, 0), hi[0] - lo[0], hi[1] - lo[1],
                   density=kc.far_ground_density, style=STYLE_GROUND)
    tile = kc.ground_tile
    road_scene = np.zeros(shape, np.uint8) + 255
    cv2.polylines(road_scene, [to_px(road[:, :2]).astype(np.int32)], False, 0, 1)
    dist_scene = cv2.distanceTransform(road_scene, cv2.DIST_L2, cv2.DIST_MASK_PRECISE) * cell
    x0s = np.arange(np.floor(lo[0] / tile) * tile, hi[0], tile)
    y0s = np.arange(np.floor(lo[1] / tile) * tile, hi[1], tile)
    grown = tile + 2 * kc.ground_overlap
    for y0 in y0s:
        for x0 in x0s:
            c = np.array([x0 + tile / 2, y0 + tile / 2])
            if lookup(dist_scene, c[None])[0] > kc.road_band + tile * np.sqrt(0.5):
                continue
            z, gx, gy = _ground_plane(road, c, kc)
            o = np.array([x0 - kc.ground_overlap, y0 - kc.ground_overlap])
            z0 = z + gx * (o[0] - c[0]) + gy * (o[1] - c[1])
            scene.add_quad((o[0], o[1], z0), (1.0, 0.0, gx), (0.0, 1.0, gy), grown * np.hypot(1.0, gx),
                           grown * np.hypot(1.0, gy), density=kc.ground_density, style=STYLE_GROUND)

    # buildings and poles along both sides, kept clear of every road and of each other
    seg = np.linalg.norm(np.diff(road[:, :2], axis=0), axis=1)
    s_road = np.concatenate([[0.0], np.cumsum(seg)])

    def at(s: float) -> tuple[np.ndarray, float, float]:
        """Road point (x, y), height and heading at arc length s."""
        i = int(np.clip(np.searchsorted(s_road, s) - 1, 0, len(road) - 2))
        f = (s - s_road[i]) / max(seg[i], 1e-9)
        p = (1 - f) * road[i] + f * road[i + 1]
        d = road[i + 1, :2] - road[i, :2]
        return p[:2], float(p[2]), float(np.arctan2(d[1], d[0]))

    def footprint(centre: np.ndarray, yaw: float, w: float, d: float) -> np.ndarray:
        """(K, 2) raster sample points of a w x d rectangle."""
        u = np.arange(-w / 2, w / 2 + cell, cell).clip(-w / 2, w / 2)
        v = np.arange(-d / 2, d / 2 + cell, cell).clip(-d / 2, d / 2)
        uu, vv = np.meshgrid(u, v)
        c, s_ = np.cos(yaw), np.sin(yaw)
        return centre + np.stack([c * uu - s_ * vv, s_ * uu + c * vv], -1).reshape(-1, 2)

    def claim(pts: np.ndarray, min_road: float) -> bool:
        if (lookup(dist_road, pts) < min_road).any() or lookup(taken, pts).any():
            return False
        px = to_px(pts)
        ok = (px[:, 0] >= 0) & (px[:, 0] < shape[1]) & (px[:, 1] >= 0) & (px[:, 1] < shape[0])
        taken[px[ok, 1], px[ok, 0]] = True
        return True

    length = float(s_road[-1])
    for side, front in ((1.0, "-y"), (-1.0, "+y")):  # left of the direction of travel, then right
        back = "+y" if front == "-y" else "-y"
        s = rng.uniform(*kc.building_gap_range)
        while s < length:
            w = rng.uniform(*kc.building_width_range)
            d = rng.uniform(*kc.building_depth_range)
            h = rng.uniform(*kc.building_height_range)
            off = kc.setback + rng.uniform(0.0, kc.setback_jitter) + d / 2
            xy, z, yaw = at(s + w / 2)
            centre = xy + side * off * np.array([-np.sin(yaw), np.cos(yaw)])
            if claim(footprint(centre, yaw, w, d), kc.clearance):
                base = z - kc.building_sink
                scene.add_box((centre[0], centre[1], base + (h + kc.building_sink) / 2), (w, d, h + kc.building_sink),
                              yaw, density=kc.facade_density, style=STYLE_WALL, faces=("+x", "-x", "+y", "-y"),
                              face_density={back: kc.back_density, "+x": kc.side_density, "-x": kc.side_density})
            s += w + rng.uniform(*kc.building_gap_range)
        s = rng.uniform(0.0, kc.pole_spacing)
        while s < length:
            xy, z, yaw = at(s)
            off = kc.setback - kc.pole_setback
            centre = xy + side * off * np.array([-np.sin(yaw), np.cos(yaw)])
            if claim(footprint(centre, yaw, _POLE_SIZE[0], _POLE_SIZE[1]), off - kc.pole_setback):
                scene.add_box((centre[0], centre[1], z - kc.building_sink + (_POLE_SIZE[2] + kc.building_sink) / 2),
                              (_POLE_SIZE[0], _POLE_SIZE[1], _POLE_SIZE[2] + kc.building_sink), yaw,
                              density=kc.object_density, style=STYLE_OBJECT, faces=("+x", "-x", "+y", "-y"))
            s += rng.uniform(0.5, 1.5) * kc.pole_spacing
    return scene


def build_scene(cfg: SynthConfig, rng: np.random.Generator) -> Scene:
    """Scene of the preset ``cfg.preset`` (random layout drawn from ``rng``)."""
    builders = {"room-loop": lambda: _build_room(cfg.room, rng),
                "low-texture": lambda: _build_low_texture(cfg.low_texture, rng),
                "street-loop": lambda: _build_street(cfg.street, rng),
                "orbit": lambda: _build_orbit(cfg.orbit, rng),
                "highway": lambda: _build_highway(cfg, rng),
                "panel-room": lambda: _build_panel_room(cfg.panel_room),
                "rotation-sweep": lambda: _build_room(cfg.rotation_sweep, rng),
                "kitti00-drive": lambda: _build_kitti_drive(cfg, rng)}
    return builders[cfg.preset]()


# ------------------------------------------------------------------------------ trajectories

# Wobble of the motions, as {harmonic k of the loop frequency: amplitude} (m or rad), scaled by the
# preset's ``jitter``: hand-held sway for the room, body bounce / sway for the car, height and
# pitch oscillation for the orbit. These shape the motion only; any values give exact derivatives.
_ROOM_WOBBLE = {
    "x_cos": {3: 0.05}, "x_sin": {2: 0.12, 5: 0.02},
    "y_cos": {2: 0.08, 4: 0.03}, "y_sin": {3: 0.06},
    "z_sin": {3: 0.12, 6: 0.02},
    "yaw_cos": {3: 0.1}, "yaw_sin": {2: 0.3, 5: 0.06},
    "pitch_sin": {2: 0.12, 7: 0.03},
    "roll_cos": {6: 0.02}, "roll_sin": {3: 0.06},
}
_ROOM_YAW_OFFSET = 0.5 * np.pi + 0.6  # rad: view direction relative to the radial direction at t=0
_ROOM_MEAN_PITCH = 0.1                # rad, slightly looking down (positive pitch = nose down)
_STREET_WOBBLE = {"z_sin": {37: 0.01, 54: 0.006}, "pitch_sin": {18: 0.006, 44: 0.004},
                  "roll_cos": {7: 0.004, 33: 0.006}}
_HIGHWAY_WOBBLE = {"z_sin": {23: 0.01, 31: 0.005}, "pitch_sin": {9: 0.004, 27: 0.003},
                   "roll_cos": {5: 0.003, 17: 0.004}}
# panel-room: hand-held wobble at 0.3-1.5 Hz ({harmonic of the walk's full-ellipse period: amplitude})
_PANEL_WOBBLE = {"radial": {14: 0.04, 33: 0.015}, "tangential": {19: 0.05, 41: 0.01}, "z_sin": {11: 0.04, 29: 0.015},
                 "yaw_sin": {12: 0.05, 27: 0.02}, "pitch_sin": {16: 0.04, 37: 0.015}, "roll_sin": {13: 0.03, 31: 0.01}}
# rotation-sweep: roll / pitch / yaw as {harmonic of the period: amplitude (rad)} before scaling to
# rotation_speed_deg_s; incommensurate harmonics give slow and fast phases (the fastest in the first fifth)
_SWEEP_ROTATION = {"yaw_sin": {2: 0.35, 5: 0.12, 9: 0.04}, "yaw_cos": {3: 0.1},
                   "pitch_sin": {3: 0.2, 7: 0.05}, "pitch_cos": {4: 0.08},
                   "roll_sin": {4: 0.15, 11: 0.03}, "roll_cos": {2: 0.1}}
_SWEEP_HEIGHT_WOBBLE = {3: 0.04, 7: 0.01}  # z (m)
_SWEEP_MEAN_PITCH = 0.15  # rad, nose down
_ORBIT_WOBBLE = {"xy_radial": {3: 0.1}, "z_sin": {2: 0.3}, "yaw_sin": {3: 0.05}, "pitch_sin": {2: 0.06}}


def _coeffs(terms: dict[int, float], scale: float = 1.0, base: dict[int, float] | None = None
            ) -> tuple[float, ...]:
    """Coefficient tuple (harmonics 1..K) from {k: amplitude} (times ``scale``) plus ``base``."""
    merged = {k: scale * a for k, a in terms.items()}
    for k, a in (base or {}).items():
        merged[k] = merged.get(k, 0.0) + a
    out = [0.0] * max(merged, default=0)
    for k, a in merged.items():
        out[k - 1] = a
    return tuple(out)


def build_trajectory(cfg: SynthConfig) -> AnalyticTrajectory:
    """Body trajectory of the preset (deterministic; period = the preset's loop duration), with the
    stop of ``stop_frame`` / ``stop_frames`` / ``stop_ramp_s`` as a time warp when ``stop_frames > 0``."""
    trajectory = _preset_trajectory(cfg)
    if cfg.stop_frames == 0:
        return trajectory
    rate = cfg.camera.rate_hz
    return replace(trajectory, warp=TimeWarp(start=cfg.stop_frame / rate, duration=cfg.stop_frames / rate,
                                             ramp=cfg.stop_ramp_s))


def _preset_trajectory(cfg: SynthConfig) -> AnalyticTrajectory | PoseTrackTrajectory:
    if cfg.preset == "kitti00-drive":  # the body carries cam0 at camera_mount: T_WB = T_WC T_BS0^-1
        T_WB = kitti_camera_poses(cfg) @ np.linalg.inv(camera_mount(cfg.camera))
        return PoseTrackTrajectory(T_WB_knots=T_WB, dt=1.0 / cfg.camera.rate_hz)
    T = cfg.loop_duration_s()
    turn = 2 * np.pi / T  # one full turn of yaw per loop
    if cfg.preset in ("room-loop", "low-texture"):
        rc, w = (cfg.room if cfg.preset == "room-loop" else cfg.low_texture), _ROOM_WOBBLE
        j = rc.jitter
        rx, ry = rc.path_radii
        return AnalyticTrajectory(
            x=Fourier1D(T, cos_coeffs=_coeffs(w["x_cos"], j, {1: rx}), sin_coeffs=_coeffs(w["x_sin"], j)),
            y=Fourier1D(T, cos_coeffs=_coeffs(w["y_cos"], j), sin_coeffs=_coeffs(w["y_sin"], j, {1: ry})),
            z=Fourier1D(T, c0=rc.height, sin_coeffs=_coeffs(w["z_sin"], j)),
            yaw=Fourier1D(T, c0=_ROOM_YAW_OFFSET, rate=turn, cos_coeffs=_coeffs(w["yaw_cos"], j),
                          sin_coeffs=_coeffs(w["yaw_sin"], j)),
            pitch=Fourier1D(T, c0=_ROOM_MEAN_PITCH, sin_coeffs=_coeffs(w["pitch_sin"], j)),
            roll=Fourier1D(T, cos_coeffs=_coeffs(w["roll_cos"], j), sin_coeffs=_coeffs(w["roll_sin"], j)),
        )
    if cfg.preset == "panel-room":
        return _panel_room_trajectory(cfg.panel_room)
    if cfg.preset == "rotation-sweep":
        rs = cfg.rotation_sweep
        scale = sweep_rotation_scale(rs)
        return _sweep_trajectory(rs, scale)
    if cfg.preset == "street-loop":
        sc, w = cfg.street, _STREET_WOBBLE
        j = sc.jitter
        pts = rounded_rectangle(sc.half_size[0], sc.half_size[1], sc.corner_radius, _ROAD_SAMPLES)
        fx, fy = closed_curve_fourier(pts, sc.harmonics, T)
        return AnalyticTrajectory(
            x=fx, y=fy,
            z=Fourier1D(T, c0=sc.camera_height - cfg.camera.t_BS[2], sin_coeffs=_coeffs(w["z_sin"], j)),
            yaw=None, pitch=Fourier1D(T, sin_coeffs=_coeffs(w["pitch_sin"], j)),
            roll=Fourier1D(T, cos_coeffs=_coeffs(w["roll_cos"], j)),
        )
    if cfg.preset == "highway":
        hc, w = cfg.highway, _HIGHWAY_WOBBLE
        j = hc.jitter
        # y(t) = A (1 - cos(2 pi t / T)) with x = speed t: the centre line of highway_centre_line
        return AnalyticTrajectory(
            x=Fourier1D(T, rate=hc.speed),
            y=Fourier1D(T, c0=hc.bend_amplitude, cos_coeffs=(-hc.bend_amplitude,)),
            z=Fourier1D(T, c0=hc.camera_height - cfg.camera.t_BS[2], sin_coeffs=_coeffs(w["z_sin"], j)),
            yaw=None, pitch=Fourier1D(T, sin_coeffs=_coeffs(w["pitch_sin"], j)),
            roll=Fourier1D(T, cos_coeffs=_coeffs(w["roll_cos"], j)),
        )
    oc, w = cfg.orbit, _ORBIT_WOBBLE
    j = oc.jitter
    pitch = float(np.arctan2(oc.height - oc.target_height, oc.radius))
    return AnalyticTrajectory(
        x=Fourier1D(T, cos_coeffs=_coeffs(w["xy_radial"], j, {1: oc.radius})),
        y=Fourier1D(T, sin_coeffs=_coeffs(w["xy_radial"], j, {1: oc.radius})),
        z=Fourier1D(T, c0=oc.height, sin_coeffs=_coeffs(w["z_sin"], j)),
        yaw=Fourier1D(T, c0=np.pi, rate=turn, sin_coeffs=_coeffs(w["yaw_sin"], j)),
        pitch=Fourier1D(T, c0=pitch, sin_coeffs=_coeffs(w["pitch_sin"], j)),
        roll=Fourier1D(T),
    )


def _panel_room_trajectory(pc: PanelRoomConfig) -> AnalyticTrajectory:
    """Body on the ellipse ``(rx cos phi, ry sin phi)`` with ``phi = phi0 + turn * t / duration`` (one
    full-ellipse period ``T = duration * 360 / turn``), radial / tangential / height / attitude wobble,
    yaw = the outward normal of the ellipse plus ``view_offset_deg``. The outward normal direction of
    ``(rx cos, ry sin)`` is not a Fourier series in phi, so the yaw follows the angle phi itself
    (exact for a circle; within a few degrees of the normal for the default ellipse)."""
    w = _PANEL_WOBBLE
    j = pc.jitter
    turn = np.deg2rad(max(pc.turn_deg, _MIN_TURN_DEG))
    T = pc.duration_s * 2.0 * np.pi / turn
    phi0 = np.deg2rad(pc.start_angle_deg)
    rx, ry = pc.path_radii
    c, s = np.cos(phi0), np.sin(phi0)
    # r(phi) (cos phi, sin phi)-like wobble: radial terms along (cos phi, sin phi) are approximated by x / y terms
    # of the same harmonics (the wobble is small; its shape is what matters)
    return AnalyticTrajectory(
        x=Fourier1D(T, cos_coeffs=_coeffs(w["radial"], j, {1: rx * c}), sin_coeffs=_coeffs(w["tangential"], j, {1: -rx * s})),
        y=Fourier1D(T, cos_coeffs=_coeffs(w["tangential"], j, {1: ry * s}), sin_coeffs=_coeffs(w["radial"], j, {1: ry * c})),
        z=Fourier1D(T, c0=pc.height, sin_coeffs=_coeffs(w["z_sin"], j)),
        yaw=Fourier1D(T, c0=phi0 + np.deg2rad(pc.view_offset_deg), rate=2.0 * np.pi / T,
                      sin_coeffs=_coeffs(w["yaw_sin"], j)),
        pitch=Fourier1D(T, c0=np.deg2rad(pc.mean_pitch_deg), sin_coeffs=_coeffs(w["pitch_sin"], j)),
        roll=Fourier1D(T, sin_coeffs=_coeffs(w["roll_sin"], j)),
    )


def _shifted(terms: dict[int, float], other: dict[int, float], shift: float, cos_part: bool) -> dict[int, float]:
    """Coefficients of ``sum_k a_k cos(k w (t + s)) + b_k sin(k w (t + s))`` in cos (``cos_part``) or sin
    terms of ``k w t``, with ``s = shift * period`` (``terms``: the a_k when cos_part else the b_k)."""
    a_terms, b_terms = (terms, other) if cos_part else (other, terms)
    out = {}
    for k in set(a_terms) | set(b_terms):
        a, b, phi = a_terms.get(k, 0.0), b_terms.get(k, 0.0), 2.0 * np.pi * k * shift
        out[k] = a * np.cos(phi) + b * np.sin(phi) if cos_part else b * np.cos(phi) - a * np.sin(phi)
    return out


def _sweep_trajectory(rs: RotationSweepConfig, scale: float) -> AnalyticTrajectory:
    """Roll / pitch / yaw sweep of :data:`_SWEEP_ROTATION` times ``scale`` about a fixed heading, started
    ``phase`` into its period, body on a horizontal circle of ``translation_radius`` (once per period)
    with a height wobble."""
    T = rs.loop_duration_s
    w = _SWEEP_ROTATION
    r = rs.translation_radius

    def series(name: str, c0: float = 0.0) -> Fourier1D:
        cos_t, sin_t = w.get(f"{name}_cos", {}), w.get(f"{name}_sin", {})
        return Fourier1D(T, c0=c0, cos_coeffs=_coeffs(_shifted(cos_t, sin_t, rs.phase, True), scale),
                         sin_coeffs=_coeffs(_shifted(sin_t, cos_t, rs.phase, False), scale))

    return AnalyticTrajectory(
        x=Fourier1D(T, cos_coeffs=(r,)), y=Fourier1D(T, sin_coeffs=(r,)),
        z=Fourier1D(T, c0=rs.height, sin_coeffs=_coeffs(_SWEEP_HEIGHT_WOBBLE, rs.jitter)),
        yaw=series("yaw", np.deg2rad(rs.yaw_deg)), pitch=series("pitch", _SWEEP_MEAN_PITCH), roll=series("roll"),
    )


def sweep_mean_angular_speed(rs: RotationSweepConfig, scale: float) -> float:
    """Mean of |w_B| (deg/s) over one period of the sweep with amplitudes times ``scale``."""
    t = np.arange(_SWEEP_SPEED_SAMPLES) * (rs.loop_duration_s / _SWEEP_SPEED_SAMPLES)
    w_B = _sweep_trajectory(rs, scale).sample(t).w_B
    return float(np.rad2deg(np.linalg.norm(w_B, axis=1).mean()))


def sweep_rotation_scale(rs: RotationSweepConfig) -> float:
    """Amplitude scale of :data:`_SWEEP_ROTATION` whose mean angular speed is ``rotation_speed_deg_s``:
    the mean speed is nearly proportional to the scale, so ``scale *= target / speed(scale)`` converges
    in a few steps (to a relative ``_SWEEP_SPEED_TOLERANCE``)."""
    target = rs.rotation_speed_deg_s
    if target == 0:
        return 0.0
    scale = 1.0
    for _ in range(_SWEEP_SPEED_ITERATIONS):
        speed = sweep_mean_angular_speed(rs, scale)
        if abs(speed - target) <= _SWEEP_SPEED_TOLERANCE * target:
            return scale
        scale *= target / speed
        if scale > _SWEEP_MAX_SCALE:
            raise ConfigError(f"rotation_sweep.rotation_speed_deg_s: {target} deg/s needs the sweep's angles scaled "
                              f"by more than {_SWEEP_MAX_SCALE:g}")
    raise ConfigError(f"rotation_sweep.rotation_speed_deg_s: no sweep of {target} deg/s mean angular speed found")


def load_synth_config(preset: str | None = None, path=None, overrides=()) -> SynthConfig:
    """Preset defaults, then the YAML file ``path`` (keys as in :class:`SynthConfig`; its ``preset``
    is used when ``preset`` is None), then ``section.key=value`` overrides."""
    from ...config import from_dict, merge_overrides, read_yaml, to_dict

    file_data = read_yaml(path) if path is not None else {}
    name = preset or file_data.get("preset") or SynthConfig.preset
    if not isinstance(name, str):
        raise ConfigError(f"{path}: key 'preset': expected a string (got {name!r})")
    data = _deep_merge(to_dict(default_config(name)), file_data)
    data["preset"] = name
    source = str(path) if path is not None else f"<preset {name}>"
    if overrides:
        data = merge_overrides(data, overrides)
        source = f"{source} with overrides {list(overrides)}"
    return from_dict(SynthConfig, data, source)


def _deep_merge(base: dict, update: dict) -> dict:
    out = dict(base)
    for key, value in update.items():
        if isinstance(value, dict) and isinstance(out.get(key), dict):
            out[key] = _deep_merge(out[key], value)
        else:
            out[key] = value
    return out
