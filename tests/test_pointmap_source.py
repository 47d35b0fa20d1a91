"""Tests of fgslam.frontends.pointmap.source and .descriptors: the built-in pointmap sources (RGB-D,
stereo SGBM, monocular two-view) on synthetic renders against the generator's ground truth, the MASt3R
slot's errors, and bad input (no overlap, pure rotation, missing depth)."""

from __future__ import annotations

import logging

import numpy as np
import pytest

from fgslam.core.errors import ConfigError, DataError
from fgslam.frontends.pointmap.descriptors import DescriptorConfig, dense_descriptors
from fgslam.frontends.pointmap.source import (
    Mast3rPointmapSource,
    PointmapSourceConfig,
    make_pointmap_source,
    unproject_depth,
)
from pointmap_support import render, room_sequence, rotation_angle_deg

I, J = 40, 46


@pytest.fixture(scope="module")
def room():
    seq = room_sequence()
    return seq, render(seq, I, stereo=True), render(seq, J, stereo=True)


def _relative(vi, vj):
    return np.linalg.inv(vi.T_WC) @ vj.T_WC


def test_rgbd_source_pointmaps_and_pose(room):
    seq, vi, vj = room
    depth_i = vi.depth.copy()
    depth_i[:10, :10] = 0.0  # a hole: no reading there
    src = make_pointmap_source(PointmapSourceConfig(kind="rgbd"), seq.K)
    src.add_frame(I, vi.image, depth=depth_i)
    src.add_frame(J, vj.image, depth=vj.depth)
    pair = src.predict(I, J)
    T_true = _relative(vi, vj)
    assert rotation_angle_deg(pair.T_CiCj[:3, :3].T @ T_true[:3, :3]) < 0.3
    assert np.linalg.norm(pair.T_CiCj[:3, 3] - T_true[:3, 3]) < 0.02  # m, over a 0.10 m motion
    np.testing.assert_allclose(pair.X_i_in_i[..., 2], depth_i, rtol=1e-6)
    assert (pair.C_i[:10, :10] == 0).all() and (pair.C_i[10:, 10:] == 1).all()
    # X_j^i: j's points in i's frame through the estimated pose; vs the true transform
    X_true = unproject_depth(vj.depth, seq.K).reshape(-1, 3) @ T_true[:3, :3].T + T_true[:3, 3]
    err = np.linalg.norm(pair.X_j_in_i.reshape(-1, 3) - X_true, axis=-1)
    assert np.median(err) < 0.02
    # a given pose is used as is
    exact = src.predict(I, J, T_CiCj=T_true)
    np.testing.assert_allclose(exact.X_j_in_i.reshape(-1, 3), X_true, atol=1e-4)
    assert pair.D_i.shape == (240, 320, 16) and np.allclose(np.linalg.norm(pair.D_i, axis=-1)[pair.Q_i > 0.5], 1, atol=1e-4)


def test_stereo_source_depth_from_sgbm(room):
    seq, vi, vj = room
    src = make_pointmap_source(PointmapSourceConfig(kind="stereo"), seq.K, baseline=seq.cfg.camera.baseline)
    src.add_frame(I, vi.image, right=vi.right)
    src.add_frame(J, vj.image, right=vj.right)
    pair = src.predict(I, J)
    ok = pair.C_i > 0
    assert ok.mean() > 0.6
    rel = np.abs(pair.X_i_in_i[..., 2][ok] - vi.depth[ok]) / vi.depth[ok]
    assert np.median(rel) < 0.04  # disparities of ~6 px (0.11 m baseline, f = 160 px, 3 m): 0.15 px is 2.5 %
    T_true = _relative(vi, vj)
    assert rotation_angle_deg(pair.T_CiCj[:3, :3].T @ T_true[:3, :3]) < 0.5
    assert np.linalg.norm(pair.T_CiCj[:3, 3] - T_true[:3, 3]) < 0.03
    with pytest.raises(DataError, match="right image"):
        src.add_frame(99, vi.image)
    with pytest.raises(ConfigError, match="stereo rig"):
        make_pointmap_source(PointmapSourceConfig(kind="stereo"), seq.K)


def test_mono_source_triangulates_up_to_scale(room):
    seq, vi, vj = room
    src = make_pointmap_source(PointmapSourceConfig(kind="mono"), seq.K)
    src.add_frame(I, vi.image)
    src.add_frame(J, vj.image)
    pair = src.predict(I, J)
    T_true = _relative(vi, vj)
    t, t_true = pair.T_CiCj[:3, 3], T_true[:3, 3]
    cos = t @ t_true / np.linalg.norm(t) / np.linalg.norm(t_true)
    assert np.degrees(np.arccos(min(cos, 1.0))) < 10.0
    assert rotation_angle_deg(pair.T_CiCj[:3, :3].T @ T_true[:3, :3]) < 1.0
    good = pair.C_i > 0.5
    assert good.sum() > 1000
    np.testing.assert_allclose(np.median(pair.X_i_in_i[..., 2][good]), 1.0, rtol=1e-6)  # the pair's scale
    scale = np.median(vi.depth[good] / pair.X_i_in_i[..., 2][good])
    rel = np.abs(scale * pair.X_i_in_i[..., 2][good] - vi.depth[good]) / vi.depth[good]
    assert np.median(rel) < 0.05
    # X_j^j and X_j^i are linked by the pair's pose
    ok = pair.C_j > 0
    back = pair.X_j_in_j.reshape(-1, 3) @ pair.T_CiCj[:3, :3].T + pair.T_CiCj[:3, 3]
    np.testing.assert_allclose(back[ok.reshape(-1)], pair.X_j_in_i.reshape(-1, 3)[ok.reshape(-1)], atol=1e-4)


def test_no_overlap_and_pure_rotation_give_zero_confidence(room, caplog):
    seq, vi, vj = room
    rng = np.random.default_rng(0)
    noise = rng.integers(0, 256, size=vi.image.shape, dtype=np.uint8)
    for kind in ("rgbd", "mono"):
        src = make_pointmap_source(PointmapSourceConfig(kind=kind), seq.K)
        src.add_frame(0, vi.image, depth=vi.depth)
        src.add_frame(1, noise, depth=vi.depth)
        with caplog.at_level(logging.WARNING):
            pair = src.predict(0, 1)
        assert (pair.C_j == 0).all() and pair.T_CiCj is None
        assert "pointmap source" in caplog.text
    # pure rotation: the same centre, turned by 3 degrees; no triangulation angle
    c, s = np.cos(np.radians(3)), np.sin(np.radians(3))
    T_rot = vi.T_WC.copy()
    T_rot[:3, :3] = vi.T_WC[:3, :3] @ np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])
    turned = np.clip(np.rint(seq.render_view(T_rot).image), 0, 255).astype(np.uint8)
    src = make_pointmap_source(PointmapSourceConfig(kind="mono"), seq.K)
    src.add_frame(0, vi.image)
    src.add_frame(1, turned)
    caplog.clear()
    with caplog.at_level(logging.WARNING):
        pair = src.predict(0, 1)
    assert (pair.C_i > 0.5).sum() < 0.01 * pair.C_i.size
    assert np.isfinite(pair.X_i_in_i).all() and np.isfinite(pair.X_j_in_i).all()


def test_bad_input_errors(room):
    seq, vi, _ = room
    src = make_pointmap_source(PointmapSourceConfig(kind="rgbd"), seq.K)
    with pytest.raises(DataError, match="no depth"):
        src.add_frame(0, vi.image)
    with pytest.raises(DataError, match="not added"):
        src.predict(0, 1)
    with pytest.raises(ConfigError, match="unknown source"):
        make_pointmap_source(PointmapSourceConfig(kind="lidar"), seq.K)  # type: ignore[arg-type]


def test_mast3r_slot_errors(tmp_path):
    with pytest.raises(ConfigError, match="pointmap.source.checkpoint"):
        make_pointmap_source(PointmapSourceConfig(kind="mast3r"), (100.0, 100.0, 50.0, 50.0))
    with pytest.raises(DataError, match="not found"):
        Mast3rPointmapSource(str(tmp_path / "missing.pth"))
    ckpt = tmp_path / "mast3r.pth"
    ckpt.write_bytes(b"\0")
    with pytest.raises(DataError, match="mast3r"):
        Mast3rPointmapSource(str(ckpt))


@pytest.mark.parametrize("kind", ["patch", "gradient"])
def test_descriptors_unit_norm_shift_equivariant_and_confident_on_texture(room, kind):
    _, vi, _ = room
    cfg = DescriptorConfig(kind=kind)
    D, Q = dense_descriptors(vi.image, cfg)
    assert D.shape == (240, 320, 16) and D.dtype == np.float32
    ok = Q > 0.5
    np.testing.assert_allclose(np.linalg.norm(D[ok], axis=-1), 1.0, atol=1e-4)
    # a shifted image gives the shifted descriptors (away from the border)
    D2, _ = dense_descriptors(np.roll(vi.image, (3, 5), axis=(0, 1)), cfg)
    np.testing.assert_allclose(D2[20:-20, 20:-20], D[17:-23, 15:-25], atol=1e-5)
    # a flat image has no descriptor confidence
    _, Qf = dense_descriptors(np.full((32, 32), 128, np.uint8), cfg)
    assert (Qf == 0).all()
