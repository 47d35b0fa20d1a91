"""Tests of the synthetic sequence generator (fgslam.io.synth) and ``fgslam synth``."""

from __future__ import annotations

import filecmp
import json
from pathlib import Path

import cv2
import numpy as np
import pytest
from geometry_support import transfer_pixels

from fgslam.io.synth import SynthSequence, write_sequence
from fgslam.io.synth.imu import ImuConfig, simulate_imu, specific_force
from fgslam.io.synth.layouts import build_scene, highway_centre_line
from fgslam.io.synth.motions import build_trajectory
from fgslam.io.synth.scenarios import camera_mount, load_synth_config
from fgslam.io.synth.trajectory import AnalyticTrajectory, Fourier1D
from fgslam.io.synth.writer import continuous_quaternions, depth_to_png16, rotation_to_quaternion_wxyz

# cheap textures for tests that do not look at image quality
LOW_RES_TEXTURES = ["room.wall_density=40", "room.box_density=60"]


def _config(preset: str, *overrides: str):
    return load_synth_config(preset, None, list(overrides))


def _so3_log(R: np.ndarray) -> np.ndarray:
    c = np.clip((np.trace(R) - 1) / 2, -1.0, 1.0)
    ang = np.arccos(c)
    w = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    return w * (0.5 if ang < 1e-8 else ang / (2 * np.sin(ang)))


def _so3_exp(w: np.ndarray) -> np.ndarray:
    return cv2.Rodrigues(np.asarray(w, np.float64).reshape(3, 1))[0]


@pytest.fixture(scope="module")
def room_seq() -> SynthSequence:
    return SynthSequence(_config("room-loop", "camera.width=320", "camera.height=240"))


# ------------------------------------------------------------------------------ determinism

def _tree(root: Path) -> list[Path]:
    return sorted(p.relative_to(root) for p in root.rglob("*") if p.is_file())


def test_same_seed_gives_identical_files_and_other_seed_differs(tmp_path):
    args = ["frames=3", "camera.width=48", "camera.height=32", *LOW_RES_TEXTURES]
    roots = {}
    for name, seed in (("a", 5), ("b", 5), ("c", 6)):
        roots[name] = tmp_path / name
        write_sequence(SynthSequence(_config("room-loop", f"seed={seed}", *args)), roots[name])
    files = _tree(roots["a"])
    assert files == _tree(roots["b"]) == _tree(roots["c"])
    assert len(files) >= 9 + 3 * 3
    for rel in files:
        assert filecmp.cmp(roots["a"] / rel, roots["b"] / rel, shallow=False), rel
    img = Path("mav0/cam0/data") / files[[str(f).startswith("mav0/cam0/data/") for f in files].index(True)].name
    assert not filecmp.cmp(roots["a"] / img, roots["c"] / img, shallow=False)
    imu = Path("mav0/imu0/data.csv")
    assert not filecmp.cmp(roots["a"] / imu, roots["c"] / imu, shallow=False)


# ------------------------------------------------------------------------------ photometry

def _backward_warp_error(seq: SynthSequence, img_i, depth_i, T_WCi, img_j, depth_j, T_WCj,
                         edge_px: int = 2) -> tuple[float, float]:
    """Mean |I_j - warp(I_i)| over pixels of j visible in i, and their fraction. Pixel p of j is
    back-projected with its ground-truth depth, moved into camera i and sampled there; occluded
    pixels (depth mismatch in i) and pixels near depth edges of i are excluded."""
    H, W = depth_j.shape
    z = depth_j.astype(np.float64)
    ui, vi, zi = transfer_pixels(depth_j, seq.K, T_WCj, T_WCi)
    valid = (z > 0) & (zi > 0.1) & (ui >= 1) & (ui <= W - 2) & (vi >= 1) & (vi <= H - 2)
    mapx = np.where(valid, ui, -1).astype(np.float32)
    mapy = np.where(valid, vi, -1).astype(np.float32)
    warped = cv2.remap(img_i.astype(np.float32), mapx, mapy, cv2.INTER_LINEAR)
    d_near = cv2.remap(depth_i.astype(np.float32), mapx, mapy, cv2.INTER_NEAREST)
    # depth edges of frame i: local max / min ratio
    k = np.ones((2 * edge_px + 1,) * 2, np.uint8)
    d = np.where(depth_i > 0, depth_i, np.float32(1e6)).astype(np.float32)
    edge = cv2.dilate(d, k) > 1.05 * cv2.erode(d, k)
    edge_w = cv2.remap(edge.astype(np.uint8), mapx, mapy, cv2.INTER_NEAREST).astype(bool)
    visible = valid & (np.abs(d_near - zi) < 0.01 * zi) & ~edge_w
    err = np.abs(warped - img_j.astype(np.float32))[visible]
    return float(err.mean()), float(visible.mean())


@pytest.mark.parametrize("step", [1, 4])
def test_ground_truth_warp_reproduces_next_frame(room_seq, step):
    i, j = 60, 60 + step
    Ti, Tj = room_seq.camera_poses(room_seq.frame_times()[[i, j]])
    ri, rj = room_seq.render_view(Ti), room_seq.render_view(Tj)
    err, frac = _backward_warp_error(room_seq, ri.image, ri.depth, Ti, rj.image, rj.depth, Tj)
    assert frac > 0.5
    assert err < 4.0, err  # grey levels of 255 (texture resampling differences only)
    # control: a 3 cm error in the pose must be visible
    T_bad = Tj.copy()
    T_bad[:3, 3] += T_bad[:3, 0] * 0.03
    err_bad, _ = _backward_warp_error(room_seq, ri.image, ri.depth, Ti, rj.image, rj.depth, T_bad)
    assert err_bad > 2.0 * err


def test_stereo_disparity_is_fx_b_over_z(room_seq):
    fr = room_seq.frame(30)
    fx = room_seq.K[0]
    b = room_seq.cfg.camera.baseline
    H, W = fr.depth0.shape
    u, v = np.meshgrid(np.arange(W, dtype=np.float32), np.arange(H, dtype=np.float32))
    z = fr.depth0
    valid = z > 0
    disparity = np.where(valid, fx * b / np.where(valid, z, 1), 0).astype(np.float32)
    right_depth = room_seq.render_view(fr.T_WC0 @ room_seq.T_S0S1).depth
    ur = u - disparity
    inside = valid & (ur >= 1) & (ur <= W - 2)
    # right-view depth at the predicted pixel equals the left depth (same z for a baseline along x)
    zr = cv2.remap(right_depth, ur, v, cv2.INTER_NEAREST)
    same = inside & (np.abs(zr - z) < 0.01 * z)
    assert same.sum() > 0.8 * inside.sum()
    warped = cv2.remap(fr.image1, ur, v, cv2.INTER_LINEAR)
    err = np.abs(warped - fr.image0)[same].mean()
    wrong = cv2.remap(fr.image1, u - 1.3 * disparity, v, cv2.INTER_LINEAR)
    err_wrong = np.abs(wrong - fr.image0)[same].mean()
    assert err < 4.0 and err_wrong > 2 * err, (err, err_wrong)


def test_lucas_kanade_tracks_follow_ground_truth_flow(room_seq):
    i, j = 100, 102
    Ti, Tj = room_seq.camera_poses(room_seq.frame_times()[[i, j]])
    ri, rj = room_seq.render_view(Ti), room_seq.render_view(Tj)
    img_i = np.clip(np.rint(ri.image), 0, 255).astype(np.uint8)
    img_j = np.clip(np.rint(rj.image), 0, 255).astype(np.uint8)
    pts = cv2.goodFeaturesToTrack(img_i, maxCorners=300, qualityLevel=0.01, minDistance=7)[:, 0]
    tracked, status, _ = cv2.calcOpticalFlowPyrLK(img_i, img_j, pts, None, winSize=(21, 21), maxLevel=3)
    # ground-truth flow of the corners from depth and poses
    fx, fy, cx, cy = room_seq.K
    z = ri.depth[pts[:, 1].round().astype(int), pts[:, 0].round().astype(int)].astype(np.float64)
    X_i = np.stack([(pts[:, 0] - cx) / fx * z, (pts[:, 1] - cy) / fy * z, z], -1)
    T_CjCi = np.linalg.inv(Tj) @ Ti
    X_j = X_i @ T_CjCi[:3, :3].T + T_CjCi[:3, 3]
    uv_j = np.stack([fx * X_j[:, 0] / X_j[:, 2] + cx, fy * X_j[:, 1] / X_j[:, 2] + cy], -1)
    err = np.linalg.norm(tracked - uv_j, axis=1)[status[:, 0] == 1]
    assert len(err) > 0.8 * len(pts)
    assert np.median(err) < 0.5 and np.mean(err < 1.5) > 0.8, (np.median(err), np.mean(err < 1.5))
    assert np.median(np.linalg.norm(uv_j - pts, axis=1)) > 2.0  # the motion is not trivial


def test_textures_have_trackable_corners(room_seq):
    img = np.clip(room_seq.frame(0).image0, 0, 255).astype(np.uint8)
    corners = cv2.goodFeaturesToTrack(img, maxCorners=500, qualityLevel=0.01, minDistance=5)
    assert corners is not None and len(corners) > 150
    orb = cv2.ORB_create(nfeatures=500)
    assert len(orb.detect(img, None)) > 150


# ------------------------------------------------------------------------------ IMU

def test_trajectory_derivatives_match_finite_differences():
    for preset in ("room-loop", "street-loop", "orbit", "highway"):
        cfg = _config(preset)
        traj = build_trajectory(cfg)
        t = np.linspace(0.3, cfg.loop_duration_s() - 0.3, 7)
        h = 1e-5
        s, sp, sm = traj.sample(t), traj.sample(t + h), traj.sample(t - h)
        np.testing.assert_allclose((sp.p_WB - sm.p_WB) / (2 * h), s.v_WB, atol=1e-5)
        np.testing.assert_allclose((sp.v_WB - sm.v_WB) / (2 * h), s.a_WB, atol=1e-4)
        for k in range(len(t)):
            w_fd = _so3_log(sm.R_WB[k].T @ sp.R_WB[k]) / (2 * h)
            np.testing.assert_allclose(w_fd, s.w_B[k], atol=1e-5)


@pytest.mark.parametrize("preset", ["room-loop", "street-loop"])
def test_integrating_noise_free_imu_reproduces_ground_truth(preset):
    cfg = _config(preset)
    traj = build_trajectory(cfg)
    dt = 1.0 / cfg.imu.rate_hz
    t = 5.0 + np.arange(int(round(1.0 / dt)) + 1) * dt  # 1 s
    st = traj.sample(t)
    imu = simulate_imu(st, ImuConfig(), np.random.default_rng(0))
    g_W = np.array([0.0, 0.0, -cfg.imu.gravity])
    R, v, p = st.R_WB[0].copy(), st.v_WB[0].copy(), st.p_WB[0].copy()
    for k in range(len(t) - 1):
        w = 0.5 * (imu.gyro_true[k] + imu.gyro_true[k + 1])
        R_next = R @ _so3_exp(w * dt)
        a0 = R @ imu.accel_true[k] + g_W
        a1 = R_next @ imu.accel_true[k + 1] + g_W
        p = p + v * dt + (a0 / 3 + a1 / 6) * dt * dt
        v = v + 0.5 * (a0 + a1) * dt
        R = R_next
    assert np.linalg.norm(p - st.p_WB[-1]) < 2e-3
    assert np.linalg.norm(v - st.v_WB[-1]) < 2e-3
    assert np.linalg.norm(_so3_log(R.T @ st.R_WB[-1])) < 1e-4
    # noisy samples: white noise of the configured density around true + bias
    resid = imu.gyro - imu.gyro_true - imu.bias_gyro
    assert np.isclose(resid.std(), ImuConfig().gyroscope_noise_density / np.sqrt(dt), rtol=0.15)


def test_accelerometer_at_rest_reads_plus_gravity_up():
    T = 10.0
    const = lambda c: Fourier1D(period=T, c0=c)  # noqa: E731
    for yaw, pitch, roll in ((0.0, 0.0, 0.0), (0.7, 0.3, -0.2)):
        traj = AnalyticTrajectory(const(1.0), const(2.0), const(1.5), const(yaw), const(pitch), const(roll))
        st = traj.sample(np.linspace(0, 1, 5))
        f = specific_force(st, 9.81)
        np.testing.assert_allclose(np.einsum("nij,nj->ni", st.R_WB, f), [[0, 0, 9.81]] * 5, atol=1e-12)
        np.testing.assert_allclose(st.w_B, 0.0, atol=1e-15)
    np.testing.assert_allclose(specific_force(traj.sample(np.zeros(1)), 9.81)[0] @ [0, 0, 1],
                               9.81 * np.cos(0.3) * np.cos(-0.2), atol=1e-12)


# ------------------------------------------------------------------------------ loops, scenes

@pytest.mark.parametrize("preset", ["room-loop", "street-loop", "orbit"])
def test_loops_end_where_they_start(preset):
    cfg = _config(preset)
    traj = build_trajectory(cfg)
    t_end = (cfg.frames - 1) / cfg.camera.rate_hz
    st = traj.sample(np.array([0.0, t_end]))
    np.testing.assert_allclose(st.p_WB[1], st.p_WB[0], atol=1e-9)
    np.testing.assert_allclose(st.R_WB[1], st.R_WB[0], atol=1e-9)
    np.testing.assert_allclose(st.v_WB[1], st.v_WB[0], atol=1e-9)
    path = traj.sample(np.arange(cfg.frames) / cfg.camera.rate_hz).p_WB
    length = np.linalg.norm(np.diff(path, axis=0), axis=1).sum()
    if preset == "street-loop":
        assert cfg.frames >= 1000 and cfg.camera.rate_hz == 10.0
        assert 400.0 < length < 1000.0
    elif preset == "room-loop":
        assert 2.0 < length < 20.0


def test_street_camera_height_and_clearance_from_buildings():
    cfg = _config("street-loop")
    T_BS0 = camera_mount(cfg.camera)
    T_WC = build_trajectory(cfg).sample(np.arange(0, cfg.frames, 3) / cfg.camera.rate_hz).T_WB() @ T_BS0
    c = T_WC[:, :3, 3]
    assert np.all(np.abs(c[:, 2] - cfg.street.camera_height) < 0.05)
    # forward (camera z) is horizontal-ish
    assert np.all(np.abs(T_WC[:, 2, 2]) < 0.1)
    sc = build_scene(cfg, np.random.default_rng(0)).arrays()
    upright = np.abs(sc.normals[:, 2]) < 0.5  # facades, poles, car sides
    o, a, b, sz = sc.origins[upright], sc.axes_u[upright], sc.axes_v[upright], sc.sizes[upright]
    rel = c[:, None, :] - o[None]
    s = np.clip(np.einsum("pqi,qi->pq", rel, a), 0, sz[:, 0])
    t = np.clip(np.einsum("pqi,qi->pq", rel, b), 0, sz[:, 1])
    closest = o[None] + s[..., None] * a[None] + t[..., None] * b[None]
    assert np.linalg.norm(c[:, None] - closest, axis=-1).min() > 1.5


# cheap highway: few texels, short lookahead (tests that do not look at image quality)
LOW_RES_HIGHWAY = ["highway.ground_density=2", "highway.far_ground_density=0.2", "highway.object_density=4",
                   "highway.building_density=1", "highway.hill_density=0.2", "highway.lookahead=120"]


def test_highway_speed_rate_and_gentle_road():
    cfg = _config("highway")
    assert cfg.camera.rate_hz == 10.0 and cfg.frames == 201
    traj = build_trajectory(cfg)
    st = traj.sample(np.arange(cfg.frames) / cfg.camera.rate_hz)
    speed = np.linalg.norm(st.v_WB, axis=1)
    assert np.all((speed >= 25.0) & (speed <= 30.0))
    step = np.linalg.norm(np.diff(st.p_WB, axis=0), axis=1)
    assert np.all((step >= 2.0) & (step <= 3.0))                 # 2-3 m between frames
    length = step.sum()
    assert np.linalg.norm(st.p_WB[-1] - st.p_WB[0]) > 0.95 * length  # straight-ish, open road
    # gently curved: horizontal curvature |v x a| / |v|^3 corresponds to a radius above 300 m, not straight
    v, a = st.v_WB[:, :2], st.a_WB[:, :2]
    curvature = np.abs(v[:, 0] * a[:, 1] - v[:, 1] * a[:, 0]) / np.linalg.norm(v, axis=1) ** 3
    assert 1 / 2000.0 < curvature.max() < 1 / 300.0
    # the camera rides at the configured height, looking along the road
    T_WC = st.T_WB() @ camera_mount(cfg.camera)
    assert np.all(np.abs(T_WC[:, 2, 3] - cfg.highway.camera_height) < 0.05)
    forward = T_WC[:-1, :3, 2]
    assert np.all(np.einsum("ni,ni->n", forward, np.diff(st.p_WB, axis=0)) > 0.99 * step)
    # faster speed, same rate: longer steps (the speed is what the config says)
    fast = build_trajectory(_config("highway", "highway.speed=30")).sample(np.array([0.0, 0.1])).p_WB
    assert np.linalg.norm(fast[1] - fast[0]) == pytest.approx(3.0, rel=0.02)


def test_highway_scene_sparse_roadside_far_structure_and_deterministic():
    cfg = _config("highway", *LOW_RES_HIGHWAY)
    sc = build_scene(cfg, np.random.default_rng(3)).arrays()
    again = build_scene(cfg, np.random.default_rng(3)).arrays()
    other = build_scene(cfg, np.random.default_rng(4)).arrays()
    np.testing.assert_array_equal(sc.origins, again.origins)
    assert len(other) != len(sc) or not np.array_equal(other.origins, sc.origins)
    upright = np.abs(sc.normals[:, 2]) < 0.5
    centre = sc.origins + 0.5 * (sc.axes_u * sc.sizes[:, :1] + sc.axes_v * sc.sizes[:, 1:])
    y_road, _ = highway_centre_line(cfg.highway, centre[:, 0])
    lateral = np.abs(centre[:, 1] - y_road)
    # nothing upright stands on the carriageway; roadside objects within 15 m, far ones beyond 50 m
    assert lateral[upright].min() > cfg.highway.rail_offset - 0.5
    near = upright & (lateral < 15.0)
    assert near.sum() > 50
    assert (upright & (lateral > 50.0)).sum() > 10 and (upright & (lateral > 300.0)).sum() > 4
    # the road covers the frames' path and the lookahead
    x_last = cfg.highway.speed * (cfg.frames - 1) / cfg.camera.rate_hz
    ground = sc.normals[:, 2] > 0.9
    assert sc.origins[ground, 0].min() <= -cfg.highway.behind + 1e-6
    assert (sc.origins[ground, 0] + sc.sizes[ground, 0]).max() >= x_last + cfg.highway.lookahead - 1e-6


def test_highway_flow_is_large_at_the_border_and_small_at_the_centre():
    seq = SynthSequence(_config("highway", "frames=3", "camera.width=160", "camera.height=50", *LOW_RES_HIGHWAY))
    fr0 = seq.frame(0)
    T_C1C0 = np.linalg.inv(seq.camera_poses(np.array([0.1]))[0]) @ fr0.T_WC0
    fx, fy, cx, cy = seq.K
    H, W = fr0.depth0.shape
    u, v = np.meshgrid(np.arange(W, dtype=np.float64), np.arange(H, dtype=np.float64))
    z = fr0.depth0.astype(np.float64)
    ok = z > 0
    X = np.stack([(u - cx) / fx * z, (v - cy) / fy * z, z], -1)[ok]
    X1 = X @ T_C1C0[:3, :3].T + T_C1C0[:3, 3]
    flow = np.full(z.shape, np.nan)
    with np.errstate(divide="ignore", invalid="ignore"):
        flow[ok] = np.hypot(fx * X1[:, 0] / X1[:, 2] + cx - u[ok], fy * X1[:, 1] / X1[:, 2] + cy - v[ok])
    r = np.hypot((u - cx) / W, (v - cy) / H)
    centre, border = ok & (r < 0.1), ok & (r > 0.4)
    assert np.nanmedian(flow[centre]) < 2.0 and np.nanmedian(flow[border]) > 8.0
    # ground truth written like the other presets: stereo and depth
    assert fr0.image1.shape == fr0.image0.shape and ok.mean() > 0.5


def test_orbit_looks_at_the_cluster():
    seq = SynthSequence(_config("orbit", "camera.width=64", "camera.height=48", "orbit.wall_density=10",
                                "orbit.floor_density=20", "orbit.box_density=30"))
    for i in (0, seq.n_frames // 3):
        depth = seq.render_view(seq.camera_poses(seq.frame_times()[[i]])[0]).depth
        assert (depth > 0).all()
        assert depth[20:28, 28:36].mean() < seq.cfg.orbit.radius + 0.5


# ------------------------------------------------------------------------------ files

def test_depth_png_encoding():
    d = np.array([[0.0, 1.25, 65.535, 70.0, -1.0]], np.float32)
    np.testing.assert_array_equal(depth_to_png16(d, 1000.0), [[0, 1250, 65535, 0, 0]])


def test_quaternion_conversion_round_trip():
    rng = np.random.default_rng(1)
    R = np.stack([_so3_exp(w) for w in rng.normal(size=(50, 3)) * 2])
    q = rotation_to_quaternion_wxyz(R)
    w, x, y, z = q.T
    R_back = np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
        np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
        np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1)], 1)
    np.testing.assert_allclose(R_back, R, atol=1e-12)
    qc = continuous_quaternions(q)
    assert np.all(np.einsum("ni,ni->n", qc[1:], qc[:-1]) >= 0)
    np.testing.assert_allclose(np.abs(np.einsum("ni,ni->n", qc, q)), 1.0, atol=1e-12)


def test_cli_writes_the_highway_preset(tmp_path, capsys):
    from fgslam.cli import main
    from fgslam.io.datasets import EurocDataset
    from fgslam.io.datasets.common import DatasetConfig

    out = tmp_path / "hw"
    rc = main(["synth", "--preset", "highway", "--out", str(out), "--frames", "3", "--width", "64", "--height", "24",
               "--json", *sum((["-o", o] for o in LOW_RES_HIGHWAY), [])])
    assert rc == 0
    assert json.loads(capsys.readouterr().out)["preset"] == "highway"
    ds = EurocDataset(out, DatasetConfig(crop_multiple=1, rectify_stereo=False))
    assert len(ds) == 3 and ds.has_stereo and ds.has_depth and ds.has_imu
    np.testing.assert_allclose(np.diff(ds.timestamps), 0.1, atol=1e-6)  # float64 s at 1.6e9 s
    step = np.linalg.norm(np.diff(ds.groundtruth.t_WC, axis=0), axis=1)
    assert np.all((step > 2.6) & (step < 2.8))  # 27 m/s at 10 Hz


def test_cli_output_round_trips_through_euroc_loader(tmp_path):
    from fgslam.cli import main

    out = tmp_path / "seq"
    rc = main(["synth", "--preset", "room-loop", "--out", str(out), "--frames", "4", "--width", "64",
               "--height", "48", "--seed", "3", "--json", *sum((["-o", o] for o in LOW_RES_TEXTURES), [])])
    assert rc == 0
    cfg = _config("room-loop", "frames=4", "camera.width=64", "camera.height=48", "seed=3", *LOW_RES_TEXTURES)
    seq = SynthSequence(cfg)
    datasets = pytest.importorskip("fgslam.io.datasets")
    from fgslam.io.datasets.common import DatasetConfig

    ds = datasets.EurocDataset(out, DatasetConfig(crop_multiple=1, rectify_stereo=False))
    assert len(ds) == 4 and ds.has_stereo and ds.has_depth and ds.has_imu
    gt = ds.groundtruth
    T_WC_true = seq.camera_poses(seq.frame_times())
    np.testing.assert_allclose(gt.T_WC, T_WC_true, atol=1e-8)
    np.testing.assert_allclose(ds.timestamps - ds.timestamps[0], seq.frame_times(), atol=1e-6)  # float64 s
    for i, frame in enumerate(ds):
        fr = seq.frame(i)
        np.testing.assert_array_equal(frame.image, np.clip(np.rint(fr.image0), 0, 255).astype(np.uint8))
        np.testing.assert_array_equal(frame.image_right, np.clip(np.rint(fr.image1), 0, 255).astype(np.uint8))
        np.testing.assert_allclose(frame.depth, fr.depth0, atol=0.5 / cfg.camera.depth_scale + 1e-6)
    calib = frame.calibration
    np.testing.assert_allclose(calib.K, seq.K, atol=1e-9)
    np.testing.assert_allclose(calib.T_BC, seq.T_BS0, atol=1e-9)
    np.testing.assert_allclose(calib.T_CLCR, seq.T_S0S1, atol=1e-9)
    imu = ds.imu
    np.testing.assert_allclose(imu.gyro, seq.imu.gyro, atol=1e-9)
    np.testing.assert_allclose(imu.accel, seq.imu.accel, atol=1e-9)


def test_colour_output_and_room_clearance_over_the_loop(tmp_path):
    seq = SynthSequence(_config("room-loop", "camera.width=48", "camera.height=36", "camera.colour=true",
                                "frames=2", *LOW_RES_TEXTURES))
    fr = seq.frame(0)
    assert fr.image0.shape == (36, 48, 3) and fr.image1.shape == (36, 48, 3)
    assert np.abs(fr.image0[..., 0] - fr.image0[..., 2]).max() > 5.0
    write_sequence(seq, tmp_path)
    png = next((tmp_path / "mav0" / "cam0" / "data").glob("*.png"))
    assert cv2.imread(str(png), cv2.IMREAD_UNCHANGED).shape == (36, 48, 3)
    # the whole hand-held loop stays inside the room, clear of the furniture
    full = _config("room-loop", "camera.width=48", "camera.height=36", *LOW_RES_TEXTURES)
    seq = SynthSequence(full)
    for T_WC in seq.camera_poses(seq.frame_times()[::10]):
        depth = seq.render_view(T_WC).depth
        assert (depth > 0.3).all() and depth.max() < np.linalg.norm(full.room.size)


# ------------------------------------------------------------------------------ stop-and-go

@pytest.mark.parametrize("preset", ["room-loop", "street-loop", "orbit"])
def test_stop_and_go_holds_still_then_moves_on(preset):
    """``stop_frame``/``stop_frames``: constant pose, zero velocity and angular rate during the stop,
    the IMU reads gravity only; derivatives stay consistent through the ramps (chain rule of the
    time warp); afterwards the motion resumes where it stopped, delayed by the stop plus one ramp."""
    cfg = _config(preset, "stop_frame=60", "stop_frames=20", "stop_ramp_s=1.0")
    plain = build_trajectory(_config(preset))
    traj = build_trajectory(cfg)
    rate = cfg.camera.rate_hz
    t0, dur, ramp = 60 / rate, 20 / rate, 1.0
    rest = traj.sample(t0 + np.linspace(0.0, dur, 9))
    np.testing.assert_allclose(rest.p_WB, np.repeat(rest.p_WB[:1], 9, 0), atol=1e-12)
    np.testing.assert_allclose(rest.R_WB, np.repeat(rest.R_WB[:1], 9, 0), atol=1e-12)
    np.testing.assert_allclose(rest.v_WB, 0.0, atol=1e-12)
    np.testing.assert_allclose(rest.a_WB, 0.0, atol=1e-12)
    np.testing.assert_allclose(rest.w_B, 0.0, atol=1e-12)
    imu = simulate_imu(rest, ImuConfig(), np.random.default_rng(0))
    np.testing.assert_allclose(imu.gyro_true, 0.0, atol=1e-12)
    np.testing.assert_allclose(np.einsum("nij,nj->ni", rest.R_WB, imu.accel_true), [[0, 0, cfg.imu.gravity]] * 9,
                               atol=1e-9)
    # the frames of the sequence during the stop have one pose; before the stop nothing changed
    seq_t = np.arange(cfg.frames) / rate
    T = traj.sample(seq_t).T_WB()
    still = (seq_t >= t0) & (seq_t <= t0 + dur)
    assert still.sum() == 21
    np.testing.assert_allclose(T[still], np.repeat(T[still][:1], still.sum(), 0), atol=1e-12)
    early = seq_t <= t0 - ramp
    np.testing.assert_allclose(T[early], plain.sample(seq_t[early]).T_WB(), atol=1e-12)
    moving_before = np.linalg.norm(plain.sample(np.array([t0])).v_WB)
    assert moving_before > 0.1  # a real stop: the body was moving there
    late = np.array([t0 + dur + ramp, t0 + dur + ramp + 2.0])
    np.testing.assert_allclose(traj.sample(late).T_WB(), plain.sample(late - dur - ramp).T_WB(), atol=1e-9)
    # derivatives through the ramps and the stop, against central differences
    t = np.concatenate([t0 - ramp + np.array([0.1, 0.5, 0.9]) * ramp, [t0 + 0.5 * dur],
                        t0 + dur + np.array([0.1, 0.5, 0.9]) * ramp])
    h = 1e-5
    s, sp, sm = traj.sample(t), traj.sample(t + h), traj.sample(t - h)
    np.testing.assert_allclose((sp.p_WB - sm.p_WB) / (2 * h), s.v_WB, atol=1e-5)
    np.testing.assert_allclose((sp.v_WB - sm.v_WB) / (2 * h), s.a_WB, atol=1e-4)
    for k in range(len(t)):
        np.testing.assert_allclose(_so3_log(sm.R_WB[k].T @ sp.R_WB[k]) / (2 * h), s.w_B[k], atol=1e-5)


def test_stop_and_go_noise_free_imu_integrates_through_the_stop():
    """Integrating the noise-free IMU across deceleration, rest and acceleration reproduces the pose."""
    cfg = _config("street-loop", "stop_frame=100", "stop_frames=20", "stop_ramp_s=1.5")
    traj = build_trajectory(cfg)
    dt = 1.0 / cfg.imu.rate_hz
    t = 8.0 + np.arange(int(round(6.0 / dt)) + 1) * dt  # 8 s to 14 s: ramp, 2 s at rest, ramp
    st = traj.sample(t)
    imu = simulate_imu(st, ImuConfig(), np.random.default_rng(0))
    g_W = np.array([0.0, 0.0, -cfg.imu.gravity])
    R, v, p = st.R_WB[0].copy(), st.v_WB[0].copy(), st.p_WB[0].copy()
    for k in range(len(t) - 1):
        R_next = R @ _so3_exp(0.5 * (imu.gyro_true[k] + imu.gyro_true[k + 1]) * dt)
        a0, a1 = R @ imu.accel_true[k] + g_W, R_next @ imu.accel_true[k + 1] + g_W
        p = p + v * dt + (a0 / 3 + a1 / 6) * dt * dt
        v = v + 0.5 * (a0 + a1) * dt
        R = R_next
    assert np.linalg.norm(st.p_WB[-1] - st.p_WB[0]) > 5.0  # it did move
    assert np.linalg.norm(p - st.p_WB[-1]) < 5e-3
    assert np.linalg.norm(v - st.v_WB[-1]) < 2e-3
    assert np.linalg.norm(_so3_log(R.T @ st.R_WB[-1])) < 1e-4


def test_text_marks_identical_where_opencv_draws_text_on_8bit_images_only(monkeypatch):
    """OpenCV 5 refuses text on float images: the 8-bit-mask path draws the very same pixels."""
    from fgslam.io.synth import texture

    direct = np.full((64, 128), 0.5)
    texture._put_text(direct, "AB12xy", (5, 40), 1.3, 1.0, 2)
    real = cv2.putText

    def eight_bit_only(img, *args):
        if img.dtype != np.uint8:
            raise cv2.error("text on 8-bit images only")
        return real(img, *args)

    monkeypatch.setattr(cv2, "putText", eight_bit_only)
    masked = np.full((64, 128), 0.5)
    texture._put_text(masked, "AB12xy", (5, 40), 1.3, 1.0, 2)
    assert (direct != 0.5).sum() > 100
    np.testing.assert_array_equal(masked, direct)
