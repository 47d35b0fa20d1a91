"""Tests of the synthetic ``low-texture`` preset (issue 12 item 8): large uniform surfaces, faint
tile lines and doors, with the room-loop motion and the same ground truth (mono, stereo, depth)."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
from geometry_support import transfer_pixels

from fgslam.io.synth import SynthSequence
from fgslam.io.synth.scenarios import load_synth_config
from fgslam.io.synth.texture import STYLE_DOOR, STYLE_PLAIN, STYLE_TILES, PlainTextureConfig, make_plain_texture

SIZE = ["camera.width=320", "camera.height=240"]
FRAMES = (0, 100, 200, 300)


def _seq(preset: str, *overrides: str) -> SynthSequence:
    return SynthSequence(load_synth_config(preset, None, [*SIZE, *overrides]))


@pytest.fixture(scope="module")
def low() -> SynthSequence:
    return _seq("low-texture")


def _grey(image: np.ndarray) -> np.ndarray:
    return np.clip(np.rint(image), 0, 255).astype(np.uint8)


def _corner_stats(seq: SynthSequence) -> tuple[float, int]:
    """Median over FRAMES of the 90th percentile of the Shi-Tomasi response (smallest eigenvalue of
    the structure tensor) and the mean number of FAST corners at an absolute threshold."""
    p90, fast = [], []
    detector = cv2.FastFeatureDetector_create(threshold=20)
    for T_WC in seq.camera_poses(seq.frame_times()[list(FRAMES)]):
        img = _grey(seq.render_view(T_WC).image)
        p90.append(np.percentile(cv2.cornerMinEigenVal(img.astype(np.float32), 5, 3), 90))
        fast.append(len(detector.detect(img)))
    return float(np.median(p90)), int(np.mean(fast))


def test_texture_is_far_lower_than_room_loop(low):
    room = _seq("room-loop", "room.wall_density=80", "room.box_density=100")
    p90_low, fast_low = _corner_stats(low)
    p90_room, fast_room = _corner_stats(room)
    assert p90_room > 1.0 and fast_room > 100  # the reference really is textured
    assert p90_low < 0.02 * p90_room, (p90_low, p90_room)
    assert fast_low < 0.1 * fast_room, (fast_low, fast_room)


def test_same_motion_as_room_loop_and_loop_closes(low):
    room_cfg = load_synth_config("room-loop", None, SIZE)
    assert low.cfg.frames == room_cfg.frames
    t = low.frame_times()
    np.testing.assert_allclose(low.camera_poses(t), SynthSequence(room_cfg).camera_poses(t), atol=1e-12)
    T0, T1 = low.camera_poses(t[[0, -1]])
    np.testing.assert_allclose(T0, T1, atol=1e-9)


def test_scene_has_plain_surfaces_tiled_floor_and_doors_on_the_walls(low):
    sc, cfg = low.scene, low.cfg.low_texture
    styles = sc.styles
    assert set(np.unique(styles)) == {STYLE_PLAIN, STYLE_TILES, STYLE_DOOR}
    assert (styles == STYLE_TILES).sum() == 1 and sc.normals[styles == STYLE_TILES][0] @ [0, 0, 1] > 0.99
    doors = np.flatnonzero(styles == STYLE_DOOR)
    assert len(doors) == cfg.n_doors
    np.testing.assert_allclose(sc.sizes[doors], [cfg.door_size] * len(doors))
    walls = range(4)
    for q in doors:
        w = next(w for w in walls if np.allclose(sc.normals[w], sc.normals[q]))
        rel = sc.corners()[q] - sc.origins[w]
        np.testing.assert_allclose(rel @ sc.normals[w], cfg.door_offset, atol=1e-12)  # just in front
        s = rel @ sc.axes_u[w]
        assert s.min() >= cfg.door_margin - 1e-9 and s.max() <= sc.sizes[w, 0] - cfg.door_margin + 1e-9
        assert np.allclose(rel[:, 2].min(), 0.0)  # standing on the floor
    # doors on the same wall do not overlap
    for a in doors:
        for b in doors:
            if a < b and np.allclose(sc.normals[a], sc.normals[b]) and np.allclose(sc.origins[a] @ sc.normals[a],
                                                                                   sc.origins[b] @ sc.normals[b]):
                sa, sb = sc.origins[a] @ sc.axes_u[a], sc.origins[b] @ sc.axes_u[b]
                assert abs(sa - sb) >= cfg.door_size[0] + cfg.door_margin - 1e-9
    # doors are seen: the view of some frames holds door pixels
    door_pixels = [np.isin(low.render_view(T).quad_id, doors).mean()
                   for T in low.camera_poses(low.frame_times()[list(FRAMES)])]
    assert max(door_pixels) > 0.05


def test_plain_textures_uniform_faint_tile_lines_door_frame_and_handle():
    cfg = PlainTextureConfig()
    rng = np.random.default_rng(0)
    density = 200.0
    plain = make_plain_texture((2.0, 1.5), density, STYLE_PLAIN, cfg, rng)
    assert abs(plain.mean() - cfg.albedo[0]) < 0.01 and plain.std() < 2 * cfg.noise * cfg.albedo[0]
    fine = 1000.0  # texels per metre: the 8 mm grout line covers whole texels
    tiles = make_plain_texture((0.2, 1.9), fine, STYLE_TILES, PlainTextureConfig(noise=0.0), rng)
    col = tiles[:, 100]  # a column inside the first tile: grout rows every tile_size_m
    grout_rows = np.flatnonzero(col < cfg.albedo[1] * (1 - 0.5 * cfg.tile_line_depth))
    spacing = np.diff(grout_rows[np.r_[True, np.diff(grout_rows) > 1]]) / fine
    assert len(spacing) == 3  # lines at 0 (cut by the edge), 0.6, 1.2 and 1.8 m
    np.testing.assert_allclose(spacing, cfg.tile_size_m, atol=5.0 / fine)
    assert col.min() == pytest.approx(cfg.albedo[1] * (1 - cfg.tile_line_depth), abs=1e-6)  # faint: 10 %
    door = make_plain_texture((0.9, 2.05), density, STYLE_DOOR, PlainTextureConfig(noise=0.0), rng)
    assert door[0, 90] == pytest.approx(cfg.albedo[2] * (1 - cfg.door_frame_depth), abs=1e-6)  # frame band
    assert door[100, 90] == pytest.approx(cfg.albedo[2], abs=1e-6)  # leaf
    hu, hv = 0.9 - cfg.handle_position_m[0], cfg.handle_position_m[1]
    assert door[int(hv * density), int(hu * density)] == pytest.approx(cfg.handle_albedo, abs=1e-6)


def test_ground_truth_depth_and_poses_are_consistent(low):
    """Pixels of frame i moved into frame j with the ground-truth depth and poses land on the depth j
    renders (geometry, not texture: uniform surfaces would hide a wrong pose photometrically), and
    a 3 cm pose error is seen; the stereo pair matches at the door and box edges."""
    i, j = 150, 154
    Ti, Tj = low.camera_poses(low.frame_times()[[i, j]])
    ri, rj = low.render_view(Ti), low.render_view(Tj)
    fx = low.K[0]
    H, W = ri.depth.shape

    def transfer(T_WCj):
        uj, vj, z_in_j = transfer_pixels(ri.depth, low.K, Ti, T_WCj)
        ok = (ri.depth > 0) & (uj >= 0) & (uj <= W - 1) & (vj >= 0) & (vj <= H - 1)
        zj = cv2.remap(rj.depth, uj.astype(np.float32), vj.astype(np.float32), cv2.INTER_LINEAR)
        rel = np.abs(zj - z_in_j) / z_in_j
        return rel[ok], ok

    rel, ok = transfer(Tj)
    assert ok.mean() > 0.7 and np.mean(rel < 0.01) > 0.95, (ok.mean(), np.mean(rel < 0.01))
    T_bad = Tj.copy()
    T_bad[:3, 3] += T_bad[:3, 2] * 0.03  # 3 cm along the optical axis
    rel_bad, _ = transfer(T_bad)
    assert np.median(rel_bad) > 5 * np.median(rel)
    # stereo: disparity fx b / z moves the left image onto the right one
    fr = low.frame(i)
    d = np.where(fr.depth0 > 0, fx * low.cfg.camera.baseline / np.maximum(fr.depth0, 1e-6), 0).astype(np.float32)
    u, v = np.meshgrid(np.arange(W, dtype=np.float32), np.arange(H, dtype=np.float32))
    inside = (u - d >= 1) & (fr.depth0 > 0)
    warped = cv2.remap(fr.image1, u - d, v, cv2.INTER_LINEAR)
    grad = cv2.morphologyEx(fr.image0, cv2.MORPH_GRADIENT, np.ones((3, 3), np.uint8)) > 20  # edges only
    err = np.abs(warped - fr.image0)[inside & grad].mean()
    wrong = cv2.remap(fr.image1, u - 1.5 * d - 2, v, cv2.INTER_LINEAR)
    err_wrong = np.abs(wrong - fr.image0)[inside & grad].mean()
    assert (inside & grad).sum() > 200 and err < 0.5 * err_wrong, (err, err_wrong)


def test_cli_writes_low_texture_with_depth_for_mono_and_rgbd(tmp_path, capsys):
    from fgslam.cli import main
    from fgslam.io.datasets import EurocDataset
    from fgslam.io.datasets.common import DatasetConfig

    out = tmp_path / "lt"
    rc = main(["synth", "--preset", "low-texture", "--out", str(out), "--frames", "3", "--width", "64",
               "--height", "48", "--json"])
    assert rc == 0
    assert json.loads(capsys.readouterr().out)["preset"] == "low-texture"
    ds = EurocDataset(out, DatasetConfig(crop_multiple=1, rectify_stereo=False))
    assert len(ds) == 3 and ds.has_depth and ds.has_stereo and ds.groundtruth is not None
    frame = next(iter(ds))
    assert (frame.depth > 0).all()


def test_plain_albedo_list_checked():
    from fgslam.core.errors import ConfigError

    with pytest.raises(ConfigError, match="texture.plain.albedo"):
        load_synth_config("low-texture", None, ["texture.plain.albedo=[0.5, 0.5]"]).validate()
