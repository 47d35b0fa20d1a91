"""The ``kitti00-drive`` synthetic preset (issue 24 item 3): KITTI 00's camera path through a street
scene, and the pose-track trajectory and render distance limit it is built on."""

from __future__ import annotations

import numpy as np
import pytest

from fgslam.core.errors import ConfigError, DataError
from fgslam.io.synth import SynthSequence, write_sequence
from fgslam.io.synth.render import RenderConfig, Renderer
from fgslam.io.synth.scenarios import load_synth_config
from fgslam.io.synth.scene import Scene
from fgslam.io.synth.texture import TextureConfig, build_atlas
from fgslam.io.synth.trajectory import PoseTrackTrajectory, _so3_exp, _so3_log

PREFIX = 30
CAMERA_HEIGHT = 1.65  # the preset's kitti_drive.camera_height
# KITTI's world (x right, y down, z forward) in the generator's (z up), written out independently
R_W_K = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


def _kitti_rows(path, n: int) -> np.ndarray:
    rows = np.loadtxt(path)[:n]
    T = np.tile(np.eye(4), (len(rows), 1, 1))
    T[:, :3, :] = rows.reshape(-1, 3, 4)
    return T


@pytest.fixture(scope="module")
def drive_prefix(shared_data, tmp_path_factory):
    poses = shared_data / "kitti_gt" / "00.txt"
    if not poses.is_file():
        pytest.skip(f"KITTI ground truth {poses} not found")
    cfg = load_synth_config("kitti00-drive", None, [f"frames={PREFIX}", f"kitti_drive.poses={poses}"])
    seq = SynthSequence(cfg)
    root = tmp_path_factory.mktemp("kitti00_drive")
    summary = write_sequence(seq, root)
    return seq, root, summary, poses


def test_drive_prefix_follows_kitti_rows_and_renders_a_street(drive_prefix):
    seq, root, summary, poses = drive_prefix
    T_WK = np.eye(4)
    T_WK[:3, :3] = R_W_K
    T_WK[2, 3] = CAMERA_HEIGHT
    expected = T_WK @ _kitti_rows(poses, PREFIX)  # frame i = KITTI row i, played at 10 Hz
    road_all = (T_WK @ _kitti_rows(poses, 200))[:, :3, 3] - [0.0, 0.0, CAMERA_HEIGHT]
    T_WC = seq.camera_poses(seq.frame_times())
    assert seq.cfg.camera.rate_hz == 10.0 and seq.n_frames == PREFIX
    np.testing.assert_allclose(T_WC, expected, atol=1e-9)
    # between the rows the path stays on the segment's neighbourhood (no overshoot of the spline)
    mid = seq.camera_poses(seq.frame_times()[:-1] + 0.05)[:, :3, 3]
    seg = np.linalg.norm(np.diff(expected[:, :3, 3], axis=0), axis=1)
    off = np.linalg.norm(mid - 0.5 * (expected[1:, :3, 3] + expected[:-1, :3, 3]), axis=1)
    assert np.all(off <= 0.05 * seg + 1e-9)
    # images: a street (textured surfaces over most of the view, some sky), on both cameras
    for i in (0, PREFIX // 2, PREFIX - 1):
        fr = seq.frame(i)
        np.testing.assert_allclose(fr.T_WC0, expected[i], atol=1e-9)
        for img in (fr.image0, fr.image1):
            assert img.shape == (96, 320)
            assert img.std() > 20.0
            sky = img == seq.cfg.render.sky_grey
            assert 0.01 < sky.mean() < 0.5
        assert (fr.depth0 > 0).mean() > 0.5
        # nothing stands on the road: the central image column below the horizon sees the ground, which
        # follows the height of the road (KITTI 00 climbs 3 % here) under the nearest KITTI position
        v = np.arange(seq.K[3] + 10, 96).astype(int)
        z = fr.depth0[v, 160]
        assert np.all(z > 0)
        X_C = np.stack([np.zeros_like(z), z * (v - seq.K[3]) / seq.K[1], z, np.ones_like(z)], -1)
        X_W = (expected[i] @ X_C.T).T[:, :3]
        road = road_all[np.argmin(np.linalg.norm(X_W[:, None, :2] - road_all[None, :, :2], axis=2), axis=1)]
        dz = X_W[:, 2] - road[:, 2]
        assert np.all(dz < 0.5)  # nothing higher than the road stands in the lane
        assert np.mean(np.abs(dz) < 0.2) > 0.9  # the tiles follow the road (a few pixels see through the cracks
        # between tiles of different slopes to the coarse ground below)
    # the written sequence: every image and the ground truth at the IMU rate
    for cam in ("cam0", "cam1", "depth0"):
        assert len(list((root / "mav0" / cam / "data").glob("*.png"))) == PREFIX
    assert summary.frames == PREFIX and summary.path_length_m == pytest.approx(seg.sum(), rel=0.01)


def test_drive_pose_file_is_read_when_built_not_when_configured(tmp_path):
    missing = tmp_path / "nope.txt"
    cfg = load_synth_config("kitti00-drive", None, [f"kitti_drive.poses={missing}", "frames=5"])  # no read yet
    assert cfg.frames == 5 and cfg.camera.width == 320
    with pytest.raises(DataError, match="not found"):
        SynthSequence(cfg)
    short = tmp_path / "short.txt"
    rows = np.tile(np.eye(4)[:3].ravel(), (4, 1))
    rows[:, 11] = np.arange(4)  # 1 m forward per row
    np.savetxt(short, rows)
    with pytest.raises(ConfigError, match="4 poses"):
        SynthSequence(load_synth_config("kitti00-drive", None, [f"kitti_drive.poses={short}", "frames=10"]))
    bad = tmp_path / "bad.txt"
    bad.write_text("1 2 3\n4 5 6\n")
    with pytest.raises(DataError, match="12 numbers for the kitti format"):
        SynthSequence(load_synth_config("kitti00-drive", None, [f"kitti_drive.poses={bad}", "frames=2"]))


def _track(n: int = 12, dt: float = 0.1) -> PoseTrackTrajectory:
    t = np.arange(n) * dt
    T = np.tile(np.eye(4), (n, 1, 1))
    T[:, :3, 3] = np.stack([8.0 * t, 2.0 * np.sin(t), 0.3 * t ** 2], -1)
    T[:, :3, :3] = _so3_exp(np.stack([0.2 * t, -0.1 * t ** 2, 0.5 * t], -1))
    return PoseTrackTrajectory(T_WB_knots=T, dt=dt)


def test_pose_track_meets_knots_and_its_derivatives_match_finite_differences():
    tr = _track()
    knots = tr.sample(np.arange(12) * 0.1)
    np.testing.assert_allclose(knots.T_WB(), tr.T_WB_knots, atol=1e-12)
    t = np.array([0.03, 0.27, 0.55, 0.91])
    h = 1e-6
    s0, sp, sm = tr.sample(t), tr.sample(t + h), tr.sample(t - h)
    np.testing.assert_allclose(s0.v_WB, (sp.p_WB - sm.p_WB) / (2 * h), rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(s0.a_WB, (sp.v_WB - sm.v_WB) / (2 * h), rtol=1e-4, atol=1e-4)
    w_fd = _so3_log(np.einsum("nji,njk->nik", sm.R_WB, sp.R_WB)) / (2 * h)  # body rate: R^T dR
    np.testing.assert_allclose(s0.w_B, w_fd, rtol=1e-5, atol=1e-6)
    # velocity is continuous across a knot (C1 spline)
    np.testing.assert_allclose(tr.sample(np.array([0.3 - 1e-9])).v_WB, tr.sample(np.array([0.3 + 1e-9])).v_WB,
                               atol=1e-5)
    # outside the track: clamped to the ends, at rest
    out = tr.sample(np.array([-1.0, 5.0]))
    np.testing.assert_allclose(out.p_WB, tr.T_WB_knots[[0, -1], :3, 3], atol=1e-12)
    assert np.all(out.v_WB == 0) and np.all(out.w_B == 0)


def test_render_max_distance_drops_far_quads():
    scene = Scene()
    for x in (5.0, 40.0):  # two walls facing the camera (at the origin, looking along +x)
        scene.add_quad((x, 50.0, -50.0), (0, -1, 0), (0, 0, 1), 100.0, 100.0, density=2.0)
    arrays = scene.arrays()
    atlas = build_atlas(arrays, TextureConfig(), np.random.default_rng(0))
    T_WC = np.eye(4)
    T_WC[:3, :3] = R_W_K  # camera z along world x
    K = (20.0, 20.0, 16.0, 12.0)
    near_only = Renderer(arrays, atlas, K, 32, 24, RenderConfig()).render(T_WC)
    np.testing.assert_allclose(near_only.depth, 5.0, rtol=1e-5)  # the near wall hides the far one
    far_cut = Renderer(arrays, atlas, K, 32, 24, RenderConfig(max_distance=4.0)).render(T_WC)
    assert np.all(far_cut.quad_id == -1)
    kept = Renderer(arrays, atlas, K, 32, 24, RenderConfig(max_distance=6.0)).render(T_WC)
    np.testing.assert_array_equal(kept.quad_id, near_only.quad_id)
