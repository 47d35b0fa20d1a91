"""``fgslam compare-colmap`` on a tiny synthetic clip (pycolmap SfM with few SIFT features), and the
point-cloud metrics on clouds with known distances."""

from __future__ import annotations

import json

import numpy as np
import pytest

from fgslam.cli import main
from fgslam.export.compare import cloud_distances
from fgslam.io.synth.scenarios import load_synth_config
from eval_support import BEAT_FACTOR

FRAMES = 40


def test_cloud_distances_known_offsets():
    rng = np.random.default_rng(0)
    reference = rng.uniform(-1, 1, (400, 3))
    cloud = reference[:200] + np.array([0.0, 0.0, 0.01])  # half the reference, 1 cm off
    d = cloud_distances(cloud, reference)
    assert d["accuracy_mean"] == pytest.approx(0.01, abs=1e-3)  # every cloud point is 1 cm from a reference point
    assert d["completion_mean"] > 0.05  # the missing half of the reference is far from the cloud
    assert d["completion_median"] >= d["accuracy_median"]
    assert np.isnan(cloud_distances(np.zeros((0, 3)), reference)["accuracy_mean"])


@pytest.fixture(scope="module")
def clip(tmp_path_factory):
    from patch_support import render_room

    return render_room(tmp_path_factory, "clip", ["frames=40", "camera.width=320", "camera.height=240"])  # shared, read only


def _surface_distances(X_W: np.ndarray, frames) -> np.ndarray:
    """Distance (m) of each world point to the true surface along its viewing ray: the smallest
    |point depth - rendered depth| over the frames that see it (inf where none does)."""
    best = np.full(len(X_W), np.inf)
    for f in frames:
        T_CW = np.linalg.inv(f.T_WC_gt)
        Y = X_W @ T_CW[:3, :3].T + T_CW[:3, 3]
        fx, fy, cx, cy = f.calibration.K
        H, W = f.depth.shape
        with np.errstate(divide="ignore", invalid="ignore"):
            u, v = np.rint(fx * Y[:, 0] / Y[:, 2] + cx), np.rint(fy * Y[:, 1] / Y[:, 2] + cy)
        seen = (Y[:, 2] > 0) & (u >= 0) & (u < W) & (v >= 0) & (v < H)
        D = f.depth[v[seen].astype(int), u[seen].astype(int)]
        d = np.full(len(X_W), np.inf)
        d[seen] = np.where(D > 0, np.abs(Y[seen, 2] - D), np.inf)
        best = np.minimum(best, d)
    return best


def _aligned_fgslam_cloud(out, groundtruth) -> np.ndarray:
    """fgslam's map points in the ground truth's frame (its trajectory's Sim(3) alignment)."""
    from fgslam.eval.trajectory import EvalConfig, evaluate
    from fgslam.export.map import load_run_map
    from fgslam.io.trajectory import read_trajectory
    from fgslam.io.run_files import TUM_FILE
    from fgslam.run.files import MAP_FILE

    a = evaluate(groundtruth, read_trajectory(out / "fgslam" / TUM_FILE, "tum"), EvalConfig(align="sim3")).alignment
    return a.s * load_run_map(out / "fgslam" / MAP_FILE).map.X_W @ a.R.T + a.t


def test_compare_colmap_on_a_synthetic_clip(clip, tmp_path, capsys):
    out = tmp_path / "cmp"
    assert main(["-q", "compare-colmap", "--data", str(clip), "--frames", str(FRAMES), "--out", str(out),
                 "--features", "2048", "--no-progress", "--json"]) == 0
    r = json.loads(capsys.readouterr().out)
    assert r["dataset"]["frames"] == FRAMES and r["fgslam"]["preset"] == "patch_mono"
    fg, cm = r["fgslam"], r["colmap"]
    assert fg["registered_frames"] == FRAMES and cm["registered_frames"] >= FRAMES // 2
    assert cm["settings"]["max_num_features"] == 2048 and cm["points"] > 100 and fg["points"] > 100
    # both reconstruct the room: Sim(3) ATE a few mm on a path of tens of cm
    assert 0 < fg["ate_m"] < 0.02 and 0 < cm["ate_m"] < 0.02
    assert r["speed_ratio_wall"] == pytest.approx(cm["wall_s"] / fg["wall_s"])
    d = r["clouds"]["fgslam_against_colmap"]
    # two sparse clouds of different features (1,248 and 1,822 points) are as far apart as their spacing
    # (measured medians 0.185 and 0.236 m): bounded by a tenth of the room's smallest extent
    room = min(load_synth_config("room-loop").room.size)
    assert 0 < d["accuracy_median"] < 0.1 * room and 0 < d["completion_median"] < 0.1 * room
    # against the true surfaces (rendered depth): fgslam's points along their viewing rays (measured median
    # 0.20 m at a median depth of 3 m) beat doing nothing, a constant-depth map (measured median 0.80 m),
    # and stay within a tenth of the room's smallest extent
    from fgslam.io.datasets import DatasetConfig, open_dataset

    ds = open_dataset(clip, config=DatasetConfig(load_depth=True, load_imu=False, end=FRAMES))
    frames = list(ds)
    surface = _surface_distances(_aligned_fgslam_cloud(out, ds.groundtruth), frames)
    constant_depth = np.median([np.median(np.abs(f.depth[f.depth > 0] - np.median(f.depth[f.depth > 0])))
                                for f in frames])
    assert np.isfinite(surface).mean() > 0.95
    assert np.median(surface[np.isfinite(surface)]) < min(BEAT_FACTOR * constant_depth, 0.1 * room)
    assert json.loads((out / "compare.json").read_text())["colmap"]["points"] == cm["points"]
    assert (out / "compare.png").stat().st_size > 10_000
    # an existing output is refused
    assert main(["compare-colmap", "--data", str(clip), "--frames", "5", "--out", str(out)]) == 2
    assert "exists and is not empty" in capsys.readouterr().err


def test_refused_compare_leaves_no_output_folder(tmp_path, capsys, noise_images):
    """A compare refused by the run's checks (here: a missing --map to extend) leaves no --out behind; an
    --out that existed before stays, even empty."""
    data = noise_images(tmp_path / "data", 4)
    missing_map = tmp_path / "none.fgmap"
    out = tmp_path / "cmp"
    for existed in (False, True):
        argv = ["compare-colmap", "--data", str(data), "--out", str(out), "-o", f"output.extend_map={missing_map}"]
        assert main(argv) == 2
        assert capsys.readouterr().err == f"fgslam: error: {missing_map}: no such map file\n"
        assert out.is_dir() == existed and (not existed or not any(out.iterdir()))
        out.mkdir(exist_ok=True)
