"""``fgslam export`` of a real patch-frontend run on a small synthetic room clip: map.npz written by the
runner, COLMAP model (tracks from the patches) read back by pycolmap, PLY, and the bad-input errors."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from fgslam.cli import main
from fgslam.export.colmap import read_colmap_model, reprojection_errors
from fgslam.export.map import load_run_map
from fgslam.export.ply import read_ply

FRAMES = 40


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory) -> Path:
    from fgslam.io.synth import SynthSequence, write_sequence
    from fgslam.io.synth.scenarios import load_synth_config

    root = tmp_path_factory.mktemp("room")
    write_sequence(SynthSequence(load_synth_config("room-loop", overrides=[
        f"frames={FRAMES}", "camera.width=320", "camera.height=240", "camera.colour=true"])), root)
    out = tmp_path_factory.mktemp("run") / "run"
    assert main(["-q", "run", "patch_mono", "--data", str(root), "--out", str(out), "--no-progress",
                 "-o", "output.plot=false"]) == 0
    return out


def test_run_saves_the_map_with_patch_tracks(run_dir):
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["outputs"]["map"] == str(run_dir / "map.npz")
    rm = load_run_map(run_dir / "map.npz")
    m = rm.map
    assert m.num_keyframes == summary["keyframes"] and m.num_points > 100
    assert (rm.width, rm.height) == (320, 240) and rm.frame_indices.tolist() == list(range(FRAMES))
    assert all(p.endswith(".png") for p in rm.frame_paths)
    # tracks: every point has its source keyframe and most have more observations (patch edges)
    counts = np.bincount(m.track_point, minlength=m.num_points)
    assert counts.min() >= 1 and np.median(counts) >= 2
    # keyframe poses are rigid
    R = m.T_WC[:, :3, :3]
    np.testing.assert_allclose(R @ R.transpose(0, 2, 1), np.broadcast_to(np.eye(3), R.shape), atol=1e-9)


@pytest.mark.parametrize("fmt", ["bin", "txt"])
def test_export_colmap_reads_back(run_dir, tmp_path, capsys, fmt):
    out = tmp_path / "colmap"
    assert main(["export", str(run_dir), "--colmap", str(out), "--colmap-format", fmt, "--json"]) == 0
    result = json.loads(capsys.readouterr().out)
    model = read_colmap_model(out)  # DIR/sparse/0 found from DIR
    rm = load_run_map(run_dir / "map.npz")
    assert len(model.names) == result["images"] == rm.map.num_keyframes
    assert model.X_W.shape[0] == result["points"] > 100
    assert result["images_written"] == rm.map.num_keyframes
    assert sorted(p.name for p in (out / "images").iterdir()) == sorted(model.names)
    errors = reprojection_errors(model.reconstruction)
    assert errors.size == result["observations"] and np.median(errors) < 2.0


def test_export_all_frames_and_ply(run_dir, tmp_path, capsys):
    out = tmp_path / "all"
    assert main(["export", str(run_dir), "--colmap", str(out), "--all-frames", "--no-images", "--json"]) == 0
    model = read_colmap_model(out / "sparse" / "0")
    summary = json.loads((run_dir / "summary.json").read_text())
    assert len(model.names) == summary["frames_with_pose"]
    assert not (out / "images").exists()
    capsys.readouterr()
    assert main(["export", str(run_dir), "--ply", str(tmp_path / "map.ply")]) == 0
    X, colour = read_ply(tmp_path / "map.ply")
    np.testing.assert_allclose(X, load_run_map(run_dir / "map.npz").map.X_W.astype(np.float32))


def test_existing_output_refused_unless_overwrite(run_dir, tmp_path, capsys):
    (tmp_path / "taken").mkdir()
    assert main(["export", str(run_dir), "--colmap", str(tmp_path / "taken"), "--no-images"]) == 2
    assert "exists (use --overwrite" in capsys.readouterr().err
    assert main(["export", str(run_dir), "--colmap", str(tmp_path / "taken"), "--no-images", "--overwrite"]) == 0
    (tmp_path / "p.ply").write_text("x")
    assert main(["export", str(run_dir), "--ply", str(tmp_path / "p.ply")]) == 2
    assert "exists" in capsys.readouterr().err


def test_run_folder_without_map(run_dir, tmp_path, capsys):
    bare = tmp_path / "bare"
    bare.mkdir()
    (bare / "summary.json").write_text((run_dir / "summary.json").read_text())
    assert main(["export", str(bare), "--ply", str(tmp_path / "x.ply")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("fgslam: error: ") and "has no map (map.npz)" in err and err.count("\n") == 1
    assert main(["export", str(tmp_path), "--ply", str(tmp_path / "x.ply")]) == 2
    assert "not a run folder" in capsys.readouterr().err
