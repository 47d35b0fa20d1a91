"""COLMAP export and import (fgslam.export.colmap) on a synthetic map with exact geometry."""

from __future__ import annotations

import numpy as np
import pytest

from fgslam.core.errors import DataError
from fgslam.export.colmap import (
    ColmapExportConfig,
    build_reconstruction,
    read_colmap_model,
    reprojection_errors,
    write_model,
)
from fgslam.export.map import RunMap, load_run_map, save_run_map
from fgslam.core.mapdata import MapExport

K = np.array([300.0, 310.0, 159.5, 119.5])
W, H = 320, 240


def _look_at(centre: np.ndarray, target: np.ndarray) -> np.ndarray:
    z = target - centre
    z /= np.linalg.norm(z)
    x = np.cross([0.0, -1.0, 0.0], z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    T = np.eye(4)
    T[:3, :3] = np.stack([x, y, z], 1)
    T[:3, 3] = centre
    return T


def synthetic_run_map(seed: int = 0, noise_px: float = 0.5, outliers: int = 20, keyframes: int = 8,
                      points: int = 300) -> RunMap:
    """Keyframes on an arc looking at a cloud of points; every point observed in every keyframe it
    projects into, with Gaussian pixel noise, plus ``outliers`` observations 30-60 px off."""
    rng = np.random.default_rng(seed)
    X_W = rng.uniform([-2, -1, 4], [2, 1, 7], size=(points, 3))
    T_WC = np.stack([_look_at(np.array([np.sin(a) * 2.0, 0.1 * k, -np.cos(a) * 2.0 + 1.0]), np.array([0.0, 0.0, 5.5]))
                     for k, a in enumerate(np.linspace(-0.4, 0.4, keyframes))])
    kf_ids = np.arange(keyframes) * 3 + 5
    tp, tk, tuv = [], [], []
    for i, T in enumerate(T_WC):
        X_C = (X_W - T[:3, 3]) @ T[:3, :3]
        uv = np.stack([K[0] * X_C[:, 0] / X_C[:, 2] + K[2], K[1] * X_C[:, 1] / X_C[:, 2] + K[3]], 1)
        inside = (X_C[:, 2] > 0) & (uv[:, 0] >= 0) & (uv[:, 0] <= W - 1) & (uv[:, 1] >= 0) & (uv[:, 1] <= H - 1)
        idx = np.flatnonzero(inside)
        tp.append(idx), tk.append(np.full(idx.size, kf_ids[i])), tuv.append(uv[idx] + rng.normal(0, noise_px, (idx.size, 2)))
    tp, tk, tuv = np.concatenate(tp), np.concatenate(tk), np.concatenate(tuv)
    bad = rng.choice(tp.size, outliers, replace=False)
    tuv[bad] += rng.uniform(30, 60, (outliers, 2)) * rng.choice([-1, 1], (outliers, 2))
    m = MapExport(kf_ids, kf_ids * 0.1, T_WC, X_W, rng.integers(0, 255, (points, 3)), tp, tk, tuv)
    n = int(kf_ids.max()) + 3
    return RunMap(m, K, W, H, np.arange(n) * 0.1, np.arange(n), [f"/data/{i:06d}.png" for i in range(n)], "mono")


@pytest.mark.parametrize("fmt", ["bin", "txt"])
def test_round_trip_same_counts_and_small_reprojection_error(tmp_path, fmt):
    run_map = synthetic_run_map()
    names = {int(k): f"{int(i):06d}.png" for k, i in zip(run_map.map.kf_ids, run_map.keyframe_frame_indices())}
    rec, stats = build_reconstruction(run_map, names)
    assert stats.images == 8
    assert stats.dropped_observations >= 20  # every outlier (30-60 px off) is left out
    write_model(rec, tmp_path / "model", fmt)
    written = {p.name for p in (tmp_path / "model").iterdir()}
    assert {f"{n}.{fmt}" for n in ("cameras", "images", "points3D")} <= written
    model = read_colmap_model(tmp_path / "model")
    assert len(model.names) == 8 and model.X_W.shape[0] == stats.points == rec.num_points3D()
    assert stats.points > 250
    errors = reprojection_errors(model.reconstruction)
    assert errors.size == stats.observations
    assert np.median(errors) < 2.0
    assert np.max(errors) <= ColmapExportConfig().max_reprojection_px + 1e-6
    # poses and points come back as written (COLMAP stores camera-from-world)
    order = np.argsort(model.names)
    np.testing.assert_allclose(model.T_WC[order], run_map.map.T_WC, atol=1e-9)
    cam = model.intrinsics[1]
    assert cam[0] == "PINHOLE" and cam[1:3] == (W, H)
    np.testing.assert_allclose(cam[3], [K[0], K[1], K[2] + 0.5, K[3] + 0.5])


def test_pixel_convention_is_shifted_by_half_a_pixel(tmp_path):
    """Noise-free observations reproject with zero error only when both the principal point and
    the keypoints are shifted to COLMAP's pixel-centre convention."""
    run_map = synthetic_run_map(noise_px=0.0, outliers=0)
    rec, _ = build_reconstruction(run_map, {int(k): f"{int(k)}.png" for k in run_map.map.kf_ids})
    errors = reprojection_errors(rec)
    assert errors.max() < 1e-6


def test_trajectory_from_names_and_map_file_round_trip(tmp_path):
    run_map = synthetic_run_map()
    save_run_map(tmp_path / "map.npz", run_map)
    back = load_run_map(tmp_path / "map.npz")
    np.testing.assert_array_equal(back.map.track_uv, run_map.map.track_uv)
    assert back.frame_paths == run_map.frame_paths and back.width == W and back.sensor == "mono"
    names = {int(k): f"{int(i):06d}.png" for k, i in zip(back.map.kf_ids, back.keyframe_frame_indices())}
    rec, _ = build_reconstruction(back, names)
    write_model(rec, tmp_path / "m")
    traj = read_colmap_model(tmp_path / "m").trajectory({f"{i:06d}.png": 0.1 * i for i in range(100)})
    np.testing.assert_allclose(traj.timestamps, back.map.kf_timestamps)


def test_missing_model_files_are_named(tmp_path):
    rec, _ = build_reconstruction(synthetic_run_map(), {k: f"{k}.png" for k in synthetic_run_map().map.kf_ids.tolist()})
    write_model(rec, tmp_path / "m")
    (tmp_path / "m" / "points3D.bin").unlink()
    with pytest.raises(DataError, match=r"missing points3D\.bin"):
        read_colmap_model(tmp_path / "m")
    with pytest.raises(DataError, match="no such COLMAP model folder"):
        read_colmap_model(tmp_path / "nowhere")


def test_map_file_errors(tmp_path):
    with pytest.raises(DataError, match="no saved map"):
        load_run_map(tmp_path / "map.npz")
    np.savez(tmp_path / "bad.npz", X_W=np.zeros((1, 3)))
    with pytest.raises(DataError, match="not a fgslam map"):
        load_run_map(tmp_path / "bad.npz")
