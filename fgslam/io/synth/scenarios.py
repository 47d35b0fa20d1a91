"""Configuration of the synthetic generator and its scene presets (not the SLAM run presets of
:mod:`fgslam.run.presets`): the config dataclasses, each preset's defaults and the loader.

The presets' sensor sections (camera, texture, render) are a data table, ``data/presets.yaml``
(:mod:`.tables`); their scenes are built by :mod:`.layouts`, their body motions by :mod:`.motions`.

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
  is a :class:`~fgslam.core.errors.DataError`. The scene covers the configured frames plus ``lookahead``
  metres of the path, so a prefix builds (and renders) quickly.

Changing ``frames`` truncates or extends (periodically) the motion, it does not change its speed.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ...core.config import (MAX_COUNT, MAX_FRAMES, MAX_IMAGE_SIDE, MAX_SCALAR, MAX_SEED, MAX_TIME_NS, check_ranges,
                       from_dict, merge_overrides, ranged, read_yaml, to_dict)
from ...core.errors import ConfigError
from .imu import ImuConfig
from .render import RenderConfig
from .tables import PRESETS_FILE, preset_sections
from .texture import TextureConfig
from .trajectory import euler_zyx_to_R

PRESET_NAMES = ("room-loop", "street-loop", "orbit", "highway", "low-texture", "panel-room", "rotation-sweep",
                "kitti00-drive")

_LIGHT_BELOW_CEILING = 0.1      # m: panel-room's point light hangs this far below the ceiling, at the room centre
_KITTI_FRAMES = 4541            # rows of KITTI 00's ground truth: kitti00-drive's default frame count
_KITTI_RATE_HZ = 10.0           # kitti00-drive's frame rate (its camera.rate_hz in data/presets.yaml)


#: lens models of the synthetic raw images (camera.distortion_model; fgslam/io/synth/distortion.py)
DISTORTION_MODELS = ("radtan", "equidistant")


@dataclass
class CameraConfig:
    """Rectified stereo pair (same intrinsics) and its mounting on the body (IMU) frame."""

    width: int = ranged(640, ge=8, le=MAX_IMAGE_SIDE)  # image width (px)
    height: int = ranged(480, ge=8, le=MAX_IMAGE_SIDE)  # image height (px)
    hfov_deg: float = ranged(90.0, gt=0, lt=170)  # horizontal field of view; fx = fy = (width / 2) / tan(hfov / 2)
    rate_hz: float = ranged(20.0, gt=0, le=MAX_SCALAR)  # camera frame rate (Hz)
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
    box_height_range: list[float] = ranged(default_factory=lambda: [0.3, 2.0], gt=0, le=MAX_SCALAR)  # box heights (m, min and max)
    path_radii: list[float] = ranged(default_factory=lambda: [1.3, 0.9], gt=0, le=MAX_SCALAR)  # ellipse of the path (m)
    path_clearance: float = ranged(0.9, ge=0, le=MAX_SCALAR)  # minimum gap between the path ellipse and furniture (m)
    height: float = ranged(1.4, gt=0, le=MAX_SCALAR)  # mean body height (m)
    loop_duration_s: float = ranged(20.0, gt=0, le=MAX_SCALAR)  # period of the motion (s): the sequence repeats after it
    jitter: float = ranged(1.0, ge=0, le=MAX_SCALAR)  # scale of the hand-held wobble (0: smooth ellipse + turn)
    wall_density: float = ranged(160.0, gt=0, le=MAX_SCALAR)  # texels per metre
    box_density: float = ranged(200.0, gt=0, le=MAX_SCALAR)  # texels per metre of the boxes


@dataclass
class LowTextureConfig(RoomConfig):
    """low-texture scene (the room-loop motion and room fields, plain styles) and its doors."""

    n_boxes: int = ranged(3, ge=0, le=MAX_COUNT)  # plain cabinets
    box_size_range: list[float] = ranged(default_factory=lambda: [0.5, 1.2], gt=0, le=MAX_SCALAR)
    box_height_range: list[float] = ranged(default_factory=lambda: [0.8, 1.8], gt=0, le=MAX_SCALAR)  # box heights (m, min and max)
    wall_density: float = ranged(100.0, gt=0, le=MAX_SCALAR)  # texels per metre (grout lines need ~1 texel)
    box_density: float = ranged(60.0, gt=0, le=MAX_SCALAR)  # texels per metre of the boxes
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
    jitter: float = ranged(1.0, ge=0, le=MAX_SCALAR)  # scale of the hand-held wobble (panel_room of data/motions.yaml)
    wall_density: float = ranged(200.0, gt=0, le=MAX_SCALAR)  # texels per metre (joints of 5 mm need ~1 texel)
    floor_density: float = ranged(100.0, gt=0, le=MAX_SCALAR)  # texels per metre of the floor
    door_at: list[float] = ranged(default_factory=lambda: [0.6], ge=0, le=1)  # one door (with a darker frame band)
    # on the wall that the mean view direction meets at each of these fractions of the walk (centred there)
    door_size: list[float] = ranged(default_factory=lambda: [0.9, 2.05], gt=0, le=MAX_SCALAR)  # width, height (m)
    door_margin: float = ranged(0.4, ge=0, le=MAX_SCALAR)  # minimum distance from a wall corner (m)
    door_offset: float = ranged(0.003, gt=0, le=MAX_SCALAR)  # the door leaf stands this far in front of its wall (m)


@dataclass
class RotationSweepConfig(RoomConfig):
    """rotation-sweep scene (the room-loop room fields, a smaller room) and its roll / pitch / yaw sweep."""

    size: list[float] = ranged(default_factory=lambda: [5.0, 4.0, 2.7], gt=0, le=MAX_SCALAR)
    n_boxes: int = ranged(8, ge=0, le=MAX_COUNT)  # boxes standing in the hall
    path_radii: list[float] = ranged(default_factory=lambda: [0.15, 0.15], gt=0, le=MAX_SCALAR)  # boxes keep clear of it
    path_clearance: float = ranged(0.6, ge=0, le=MAX_SCALAR)
    loop_duration_s: float = ranged(10.0, gt=0, le=MAX_SCALAR)  # period of the sweep (default frames: one period + 1)
    rotation_speed_deg_s: float = ranged(69.0, ge=0, le=MAX_SCALAR)  # mean angular speed over one period: the
    # amplitudes of sweep_rotation (data/motions.yaml) are scaled to it (held-out: ~1,600 deg over 723 frames at 30 Hz)
    translation_radius: float = ranged(0.15, ge=0, le=MAX_SCALAR)  # radius of the slow horizontal circle of the body (m)
    yaw_deg: float = ranged(0.0, ge=-360, le=360)  # mean heading (0: towards +x)
    phase: float = ranged(0.68, ge=0, le=1)  # the sweep starts this fraction into its period (default: its fastest
    # phase, ~3 s at 90-120 deg/s, falls in the first fifth of the default frames, as in the held-out run)


@dataclass
class StreetConfig:
    """street-loop scene and motion."""

    half_size: list[float] = ranged(default_factory=lambda: [100.0, 60.0], gt=0, le=MAX_SCALAR)  # road centre-line box (m)
    corner_radius: float = ranged(20.0, gt=0, le=MAX_SCALAR)  # radius of the road corners (m)
    harmonics: int = ranged(40, ge=1, le=MAX_COUNT)  # Fourier harmonics of the road centre line
    loop_duration_s: float = ranged(100.0, gt=0, le=MAX_SCALAR)  # period of the motion (s): the sequence repeats after it
    jitter: float = ranged(1.0, ge=0, le=MAX_SCALAR)  # scale of the body bounce / sway
    camera_height: float = ranged(1.6, gt=0, le=MAX_SCALAR)  # body height above ground (m)
    road_band: float = ranged(11.0, gt=0, le=MAX_SCALAR)  # half-width of the high-resolution ground band (m)
    ground_tile: float = ranged(10.0, gt=0, le=MAX_SCALAR)  # size of the ground texture tiles (m)
    ground_density: float = ranged(24.0, gt=0, le=MAX_SCALAR)  # texels per metre of the road band
    far_ground_density: float = ranged(2.0, gt=0, le=MAX_SCALAR)  # texels per metre of the ground beyond the road band
    setback: float = ranged(9.0, gt=0, le=MAX_SCALAR)  # facade distance from the road centre line (m)
    building_width_range: list[float] = ranged(default_factory=lambda: [10.0, 24.0], gt=0, le=MAX_SCALAR)  # building widths along the road (m, min and max)
    building_depth_range: list[float] = ranged(default_factory=lambda: [8.0, 14.0], gt=0, le=MAX_SCALAR)  # building depths away from the road (m, min and max)
    building_height_range: list[float] = ranged(default_factory=lambda: [6.0, 24.0], gt=0, le=MAX_SCALAR)  # building heights (m, min and max)
    building_gap_range: list[float] = ranged(default_factory=lambda: [0.0, 5.0], ge=0, le=MAX_SCALAR)  # gaps between neighbouring buildings (m, min and max)
    facade_density: float = ranged(28.0, gt=0, le=MAX_SCALAR)  # texels per metre of the facades facing the road
    side_density: float = ranged(12.0, gt=0, le=MAX_SCALAR)  # building faces perpendicular to the road
    back_density: float = ranged(2.0, gt=0, le=MAX_SCALAR)  # faces that never face the road
    parked_car_prob: float = ranged(0.35, ge=0, le=1)  # probability of a parked car per 8 m of kerb
    kerb_offset: float = ranged(4.8, ge=0, le=MAX_SCALAR)  # parked car centre distance from the centre line (m)
    pole_spacing: float = ranged(25.0, gt=0, le=MAX_SCALAR)  # mean distance between poles (m)
    object_density: float = ranged(48.0, gt=0, le=MAX_SCALAR)  # texels per metre of the street objects (cars, poles)


@dataclass
class OrbitConfig:
    """orbit scene and motion."""

    hall_size: list[float] = ranged(default_factory=lambda: [16.0, 16.0, 6.0], gt=0, le=MAX_SCALAR)  # hall length, width and height (m)
    n_boxes: int = ranged(8, ge=0, le=MAX_COUNT)  # boxes standing in the hall
    cluster_radius: float = ranged(1.0, ge=0, le=MAX_SCALAR)  # box centres within this radius of the origin (m)
    box_size_range: list[float] = ranged(default_factory=lambda: [0.3, 0.9], gt=0, le=MAX_SCALAR)  # box sides (m)
    radius: float = ranged(3.5, gt=0, le=MAX_SCALAR)  # orbit radius (m)
    height: float = ranged(1.5, gt=0, le=MAX_SCALAR)  # mean camera height (m)
    target_height: float = ranged(0.5, ge=0, le=MAX_SCALAR)  # height of the looked-at point (m)
    loop_duration_s: float = ranged(15.0, gt=0, le=MAX_SCALAR)  # period of the motion (s): the sequence repeats after it
    jitter: float = ranged(1.0, ge=0, le=MAX_SCALAR)  # scale of the height / pitch oscillation
    wall_density: float = ranged(40.0, gt=0, le=MAX_SCALAR)  # texels per metre of the walls
    floor_density: float = ranged(100.0, gt=0, le=MAX_SCALAR)  # texels per metre of the floor
    box_density: float = ranged(200.0, gt=0, le=MAX_SCALAR)  # texels per metre of the boxes


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
    building_height_range: list[float] = ranged(default_factory=lambda: [8.0, 35.0], gt=0, le=MAX_SCALAR)  # building heights (m, min and max)
    hill_distance: list[float] = ranged(default_factory=lambda: [350.0, 700.0], gt=0, le=MAX_SCALAR)  # lateral / ahead range of hill centres (m)
    hill_spacing: float = ranged(250.0, gt=0, le=MAX_SCALAR)  # mean distance between hills on each side (m)
    hill_size_range: list[float] = ranged(default_factory=lambda: [200.0, 500.0], gt=0, le=MAX_SCALAR)  # hill widths (m)
    hill_height_range: list[float] = ranged(default_factory=lambda: [40.0, 140.0], gt=0, le=MAX_SCALAR)  # hill heights (m, min and max)
    object_density: float = ranged(48.0, gt=0, le=MAX_SCALAR)  # texels per metre of rails, poles, signs
    building_density: float = ranged(6.0, gt=0, le=MAX_SCALAR)  # texels per metre of the buildings
    hill_density: float = ranged(2.0, gt=0, le=MAX_SCALAR)  # texels per metre of the hills


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
    far_ground_density: float = ranged(1.0, gt=0, le=MAX_SCALAR)  # texels per metre of the ground beyond the road band
    far_ground_drop: float = ranged(0.5, ge=0, le=MAX_SCALAR)  # the coarse ground lies this far below the lowest road (m)
    far_ground_margin: float = ranged(60.0, ge=0, le=MAX_SCALAR)  # ... and extends this far beyond the scene's path (m)
    setback: float = ranged(9.0, gt=0, le=MAX_SCALAR)  # facade distance from the road centre line (m)
    setback_jitter: float = ranged(2.0, ge=0, le=MAX_SCALAR)  # random extra setback of each building (m)
    clearance: float = ranged(7.5, ge=0, le=MAX_SCALAR)  # no building comes closer than this to any road of the path (m)
    building_width_range: list[float] = ranged(default_factory=lambda: [8.0, 22.0], gt=0, le=MAX_SCALAR)  # building widths along the road (m, min and max)
    building_depth_range: list[float] = ranged(default_factory=lambda: [8.0, 14.0], gt=0, le=MAX_SCALAR)  # building depths away from the road (m, min and max)
    building_height_range: list[float] = ranged(default_factory=lambda: [6.0, 20.0], gt=0, le=MAX_SCALAR)  # building heights (m, min and max)
    building_gap_range: list[float] = ranged(default_factory=lambda: [0.0, 4.0], ge=0, le=MAX_SCALAR)  # gaps between neighbouring buildings (m, min and max)
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

    preset: str = "room-loop"  # scene and motion: room-loop, street-loop, orbit, highway, low-texture, panel-room, rotation-sweep, kitti00-drive
    frames: int = ranged(401, ge=1, le=MAX_FRAMES)  # camera frames (default: one loop period + 1)
    seed: int = ranged(0, ge=0, le=MAX_SEED)  # random seed of the scene (textures, placements) and of the IMU noise
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


#: the SynthConfig sections that data/presets.yaml may set per preset
_PRESET_SECTIONS: dict[str, type] = {"camera": CameraConfig, "texture": TextureConfig, "render": RenderConfig}


def default_config(preset: str) -> SynthConfig:
    """Preset defaults: frame count = one loop + 1; resolution, field of view, rate, baseline and the
    other sensor settings of ``data/presets.yaml`` (each section listed there replaces the default one)."""
    if preset not in PRESET_NAMES:
        raise ConfigError(f"unknown preset '{preset}' (valid: {', '.join(PRESET_NAMES)})")
    cfg = SynthConfig(preset=preset)
    source = f"{PRESETS_FILE} (preset {preset})"
    for name, values in preset_sections().get(preset, {}).items():
        if name not in _PRESET_SECTIONS:
            raise ConfigError(f"{source}: section '{name}' is not one of {', '.join(_PRESET_SECTIONS)}")
        setattr(cfg, name, from_dict(_PRESET_SECTIONS[name], values, source, prefix=f"{name}."))
    if preset == "panel-room":  # the point light hangs at the room centre, just below the ceiling
        cfg.render.light_position = [0.0, 0.0, cfg.panel_room.size[2] - _LIGHT_BELOW_CEILING]
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


def load_synth_config(preset: str | None = None, path: str | Path | None = None,
                      overrides: Sequence[str] = ()) -> SynthConfig:
    """Preset defaults, then the YAML file ``path`` (keys as in :class:`SynthConfig`; its ``preset``
    is used when ``preset`` is None), then ``section.key=value`` overrides."""
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
