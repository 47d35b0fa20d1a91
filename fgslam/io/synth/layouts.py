"""Scene layouts of the synthetic generator's presets (:mod:`.scenarios`): the textured rooms,
streets, hall and roads of :func:`build_scene`, with random furniture drawn from the layout stream.

The kitti00-drive street follows the poses of a KITTI ground-truth file (:func:`.motions.kitti_camera_poses`):
ground tiles along the road height, buildings wherever they leave every road of the path clear, lamp
poles and a coarse ground below (the module docstring of :mod:`.scenarios`).
"""

from __future__ import annotations

import cv2
import numpy as np

from .motions import kitti_camera_poses
from .scenarios import (HighwayConfig, KittiDriveConfig, LowTextureConfig, OrbitConfig, PanelRoomConfig, RoomConfig,
                        StreetConfig, SynthConfig)
from .scene import Scene
from .texture import STYLE_DOOR, STYLE_GROUND, STYLE_OBJECT, STYLE_PANELS, STYLE_PLAIN, STYLE_TILES, STYLE_WALL
from .trajectory import rounded_rectangle

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
_KITTI_RIDGE = 5.0              # m; regulariser of a ground tile's slopes (a straight road leaves the lateral one free)


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


def _add_doors(scene: Scene, cfg: LowTextureConfig, density: float, rng: np.random.Generator) -> None:
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

