"""Tests of the synthetic reproductions of issue 23's held-out failure classes: ``panel-room``
(texture-poor RGB-D room, point-light shading, vignetting) and ``rotation-sweep`` (rotation-dominant
hand-held camera, motion blur, radial distortion written to sensor.yaml and undone by the loader)."""

from __future__ import annotations

import filecmp
import hashlib
from pathlib import Path

import numpy as np
import pytest

from fgslam.io.synth import SynthSequence, write_sequence
from fgslam.io.synth.distortion import distort_normalized, undistort_normalized
from fgslam.io.synth.render import Renderer, RenderConfig
from fgslam.io.synth.motions import sweep_mean_angular_speed, sweep_rotation_scale
from fgslam.io.synth.scenarios import load_synth_config
from fgslam.io.synth.texture import (STYLE_DOOR, STYLE_PANELS, STYLE_TILES, PlainTextureConfig,
                                     make_plain_texture)

TINY = ["camera.width=64", "camera.height=48", "frames=3"]
CHEAP = {"panel-room": ["panel_room.wall_density=100", "panel_room.floor_density=50"],  # smaller texture atlases
         "rotation-sweep": ["rotation_sweep.wall_density=40", "rotation_sweep.box_density=60"]}


def _seq(preset: str, *overrides: str) -> SynthSequence:
    return SynthSequence(load_synth_config(preset, None, list(overrides)))


def _files(root: Path) -> list[Path]:
    return sorted(p.relative_to(root) for p in root.rglob("*") if p.is_file())


def _rotation_angles_deg(T: np.ndarray) -> np.ndarray:
    """Geodesic angle (deg) between consecutive rotations of poses (N, 4, 4)."""
    R = T[:, :3, :3]
    c = (np.einsum("nij,nij->n", R[:-1], R[1:]) - 1.0) / 2.0
    return np.degrees(np.arccos(np.clip(c, -1.0, 1.0)))


# ------------------------------------------------------------------------------ determinism

@pytest.mark.parametrize("preset", ["panel-room", "rotation-sweep"])
def test_new_presets_render_deterministically(tmp_path, preset):
    roots = [tmp_path / "a", tmp_path / "b"]
    for root in roots:
        write_sequence(_seq(preset, *TINY, *CHEAP[preset]), root)
    files = _files(roots[0])
    assert files == _files(roots[1]) and len(files) >= 3 * 3 + 6
    for rel in files:
        assert filecmp.cmp(roots[0] / rel, roots[1] / rel, shallow=False), rel


# Hashes of the 64x48, 4-frame grey and colour renders (every file but synth_config.yaml, which
# gains the new keys) of the presets before panel-room / rotation-sweep existed (commit 34b7e9b):
# the new options default off and leave them byte-identical.
_GOLDEN = {("room-loop", False): "fe34474921c5b002", ("low-texture", False): "673a739942ee201e",
           ("low-texture", True): "b1dba32eb47352d4"}


@pytest.mark.parametrize("preset,colour", sorted(_GOLDEN))
def test_existing_presets_are_byte_identical(tmp_path, preset, colour):
    extra = ["camera.colour=true"] if colour else []
    write_sequence(_seq(preset, "camera.width=64", "camera.height=48", "frames=4", *extra), tmp_path)
    h = hashlib.sha256()
    for rel in _files(tmp_path):
        if rel.name != "synth_config.yaml":
            h.update(str(rel).encode())
            h.update((tmp_path / rel).read_bytes())
    assert h.hexdigest()[:16] == _GOLDEN[(preset, colour)]


# ------------------------------------------------------------------------------ panel-room

@pytest.fixture(scope="module")
def panel() -> SynthSequence:
    return _seq("panel-room", "camera.width=80", "camera.height=60")


def test_panel_room_defaults_match_the_held_out_class(panel):
    cfg = panel.cfg
    assert cfg.frames == 189 and cfg.camera.rate_hz == 10.0
    assert cfg.render.point_light and 0 < cfg.render.vignetting < 1 and cfg.texture.ambient == 1.0
    T = panel.camera_poses(panel.frame_times())
    yaw = np.unwrap(np.arctan2(T[:, 1, 2], T[:, 0, 2]))  # heading of the optical axis
    assert abs(np.degrees(yaw[-1] - yaw[0]) - cfg.panel_room.turn_deg) < 15.0
    assert _rotation_angles_deg(T).sum() > cfg.panel_room.turn_deg  # plus hand-held wobble


def test_panel_room_camera_stays_within_two_metres_of_the_walls(panel):
    pc = panel.cfg.panel_room
    T = panel.camera_poses(panel.frame_times())
    p = T[:, :3, 3]
    half = np.array(pc.size[:2]) / 2
    nearest_wall = np.min(half - np.abs(p[:, :2]), axis=1)
    assert nearest_wall.min() > 0.5 and np.percentile(nearest_wall, 95) < 2.0, (nearest_wall.min(), nearest_wall.max())
    medians = [float(np.median(panel.render_view(T[i]).depth)) for i in range(0, len(T), 6)]
    assert all(d > 0.5 for d in medians)
    assert 0.5 < np.median(medians) < 2.0, medians


def test_panel_room_views_are_panels_with_a_floor_corner_and_a_door(panel):
    T = panel.camera_poses(panel.frame_times())
    share = {STYLE_PANELS: [], STYLE_TILES: [], STYLE_DOOR: []}
    for i in range(0, len(T), 6):
        styles = panel.scene.styles[np.maximum(panel.render_view(T[i]).quad_id, 0)]
        for style in share:
            share[style].append(float((styles == style).mean()))
    assert np.median(share[STYLE_PANELS]) > 0.7  # panels fill most of the view
    floor = np.array(share[STYLE_TILES])  # the floor enters some views, in a corner
    assert np.median(floor) < 0.15 and floor.max() < 0.4 and (floor > 0.05).any() and (floor < 0.01).any()
    door = np.array(share[STYLE_DOOR]) > 0
    assert door.any() and not door[: len(door) // 3].any()  # a door frame later in the walk


def test_panel_style_has_thin_joints_at_the_panel_spacing():
    cfg = PlainTextureConfig()
    density = 200.0
    tex = make_plain_texture((1.8, 2.4), density, STYLE_PANELS, cfg, np.random.default_rng(0))
    pw, ph = cfg.panel_size_m
    col = np.median(tex, axis=0)  # joints along u (vertical lines) darken whole columns
    joints = np.flatnonzero(col < cfg.panel_albedo * (1 - 0.5 * cfg.panel_line_depth))
    assert len(joints) > 0
    s = (joints + 0.5) / density
    assert np.all(np.abs(s - pw * np.round(s / pw)) <= cfg.panel_line_width_m)  # only at panel borders
    assert len(joints) <= 3 * (int(1.8 / pw) + 1) * max(1, round(cfg.panel_line_width_m * density))
    assert abs(np.median(tex) - cfg.panel_albedo) < 3 * cfg.noise


def test_vignetting_and_point_light_are_multiplicative_shading(panel):
    T = panel.camera_poses(panel.frame_times()[[5]])[0]
    base = RenderConfig(**{**vars(panel.cfg.render), "vignetting": 0.0})
    flat = Renderer(panel.scene, panel.atlas, panel.K, 80, 60, base).render(T)
    vig = Renderer(panel.scene, panel.atlas, panel.K, 80, 60, panel.cfg.render).render(T)
    ratio = vig.image / np.maximum(flat.image, 1e-6)
    v = panel.cfg.render.vignetting
    assert abs(ratio[30, 40] - 1.0) < 0.01
    assert abs(ratio[0, 0] - (1 - v)) < 0.01
    unlit = Renderer(panel.scene, panel.atlas, panel.K, 80, 60, RenderConfig(**{**vars(base), "point_light": False}))
    lit_ratio = flat.image / np.maximum(unlit.render(T).image, 1e-6)
    assert lit_ratio.std() > 0.01  # shading varies over the view (the light is local)
    assert lit_ratio.min() >= panel.cfg.render.light_ambient - 1e-3


# ------------------------------------------------------------------------------ rotation-sweep

def test_rotation_sweep_summed_rotation_rate_is_the_configured_one():
    for speed in (69.0, 40.0):
        seq = _seq("rotation-sweep", "camera.width=64", "camera.height=48",
                   f"rotation_sweep.rotation_speed_deg_s={speed}", *CHEAP["rotation-sweep"])
        t = seq.frame_times()
        T = seq.camera_poses(t)
        rate = _rotation_angles_deg(T).sum() / (t[-1] - t[0])
        assert abs(rate - speed) < 0.02 * speed, (rate, speed)
        rs = seq.cfg.rotation_sweep
        assert abs(sweep_mean_angular_speed(rs, sweep_rotation_scale(rs)) - speed) < 1e-3 * speed
    path = np.linalg.norm(np.diff(T[:, :3, 3], axis=0), axis=1).sum()
    assert path < 2.0  # rotation-dominant: ~1 m over the default 10 s
    w = np.degrees(np.linalg.norm(seq.states(t).w_B, axis=1))
    fifths = [c.mean() for c in np.array_split(w, 5)]
    assert fifths[0] == max(fifths)  # the fastest rotations come first (as in the held-out run)


@pytest.fixture(scope="module")
def sweep_dir(tmp_path_factory):
    root = tmp_path_factory.mktemp("sweep")
    seq = _seq("rotation-sweep", "camera.width=160", "camera.height=120", "frames=3", "camera.exposure_s=0",
               *CHEAP["rotation-sweep"])
    write_sequence(seq, root)
    return root, seq


def test_rotation_sweep_calibration_carries_the_distortion(sweep_dir):
    from fgslam.io.calibration import read_yaml_file

    root, seq = sweep_dir
    for sensor in ("cam0", "cam1", "depth0"):
        data = read_yaml_file(root / "mav0" / sensor / "sensor.yaml")
        assert data["distortion_model"] == "radial-tangential"
        np.testing.assert_allclose(data["distortion_coefficients"], seq.cfg.camera.distortion)
    assert seq.cfg.camera.distortion[0] == pytest.approx(-0.30)


def test_distortion_round_trips_and_bends_straight_lines():
    coeffs = (-0.30, 0.09, 0.001, -0.0005)
    rng = np.random.default_rng(0)
    x, y = rng.uniform(-0.8, 0.8, 500), rng.uniform(-0.6, 0.6, 500)
    xd, yd = distort_normalized(x, y, coeffs)
    xu, yu = undistort_normalized(xd, yd, coeffs)
    np.testing.assert_allclose(xu, x, atol=1e-10)
    np.testing.assert_allclose(yu, y, atol=1e-10)
    # a straight line of the scene bends in the raw image (barrel: towards the centre)
    xs = np.linspace(-0.8, 0.8, 9)
    _, yl = distort_normalized(xs, np.full_like(xs, 0.5), coeffs)
    assert yl[0] < yl[4] and yl[-1] < yl[4]


def test_loader_undistorts_to_the_pinhole_view(sweep_dir):
    """The loader's undistorted depth and image match a pinhole render of the same pose with the
    loader's output intrinsics, and undistorting raw projections gives the pinhole projections."""
    from fgslam.io.datasets.common import DatasetConfig
    from fgslam.io.datasets.euroc import EurocDataset

    root, seq = sweep_dir
    ds = EurocDataset(root, DatasetConfig(crop_multiple=1, rectify_stereo=False))
    frame = ds[1]
    out = frame.calibration
    assert out.distortion_model == "none"
    np.testing.assert_allclose(ds.raw_calibration.distortion, seq.cfg.camera.distortion)
    T_WC = seq.camera_poses(seq.frame_times()[[1]])[0]
    np.testing.assert_allclose(ds.groundtruth.T_WC[1], T_WC, atol=1e-4)  # interpolated between 200 Hz samples
    pin = Renderer(seq.scene, seq.atlas, out.K, out.width, out.height, seq.cfg.render).render(T_WC, colour=True)
    valid = (frame.depth > 0) & (pin.depth > 0)
    assert valid.mean() > 0.95
    rel = np.abs(frame.depth[valid] - pin.depth[valid]) / pin.depth[valid]
    assert np.mean(rel < 0.01) > 0.95, np.mean(rel < 0.01)
    grey_loaded = frame.image.astype(np.float64)
    grey_loaded = grey_loaded.mean(axis=-1) if grey_loaded.ndim == 3 else grey_loaded
    assert np.median(np.abs(grey_loaded - pin.image.mean(axis=-1))) < 6.0
    # projections: a world point's raw (distorted) pixel maps to its pinhole pixel of the output camera
    rng = np.random.default_rng(1)
    fx, fy, cx, cy = seq.K
    X_C = np.stack([rng.uniform(-0.5, 0.5, 50), rng.uniform(-0.4, 0.4, 50), np.ones(50)], axis=1)
    xd, yd = distort_normalized(X_C[:, 0], X_C[:, 1], seq.cfg.camera.distortion)
    raw_uv = np.stack([fx * xd + cx, fy * yd + cy], axis=1)
    ofx, ofy, ocx, ocy = out.K
    np.testing.assert_allclose(ds._undistorter.points(raw_uv),
                               np.stack([ofx * X_C[:, 0] + ocx, ofy * X_C[:, 1] + ocy], axis=1), atol=0.05)


def test_motion_blur_averages_the_exposure():
    sharp = _seq("rotation-sweep", "camera.width=64", "camera.height=48", "frames=2", "camera.exposure_s=0",
                 *CHEAP["rotation-sweep"])
    blurred = _seq("rotation-sweep", "camera.width=64", "camera.height=48", "frames=2", *CHEAP["rotation-sweep"])
    f_s, f_b = sharp.frame(1), blurred.frame(1)
    np.testing.assert_array_equal(f_s.depth0, f_b.depth0)  # depth of the frame time
    assert not np.array_equal(f_s.image0, f_b.image0)
    grad = lambda im: np.abs(np.diff(im.mean(axis=-1), axis=1)).mean()  # noqa: E731
    assert grad(f_b.image0) < grad(f_s.image0)


def test_synth_help_names_every_preset():
    """``fgslam synth --help`` lists the presets by hand (its parser must not import the scenarios, which
    pull in OpenCV): it must name every one of them."""
    import argparse

    from fgslam.commands import synth as synth_command
    from fgslam.io.synth.scenarios import PRESET_NAMES

    parser = argparse.ArgumentParser()
    synth_command.add_arguments(parser)
    text = " ".join(parser.format_help().split())
    for name in PRESET_NAMES:
        assert name in text, name
