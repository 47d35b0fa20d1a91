"""``fgslam export`` of a real patch-frontend run on a small synthetic room clip: map.npz written by the
runner, COLMAP model (tracks from the patches) read back by pycolmap, PLY, and the bad-input errors."""

from __future__ import annotations

import errno
import json
import os
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from fgslam.cli import main
from fgslam.core.mapdata import MapExport
from fgslam.export import inplace
from fgslam.export.colmap import read_colmap_model, reprojection_errors
from fgslam.export.map import RunMap, load_run_map, save_run_map
from fgslam.export.mapfile import check_map_file
from fgslam.export.ply import read_ply
from fgslam.core.errors import DataError

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
    from fgslam.core.mapdata import points_near_cameras
    from fgslam.export.ply import PlyExportConfig

    capsys.readouterr()
    m = load_run_map(run_dir / "map.npz").map
    assert main(["export", str(run_dir), "--ply", str(tmp_path / "map.ply")]) == 0
    X, colour = read_ply(tmp_path / "map.ply")  # without the far points (PlyExportConfig.max_point_range_factor)
    near, _ = points_near_cameras(m.X_W, m.T_WC[:, :3, 3], PlyExportConfig().max_point_range_factor)
    np.testing.assert_allclose(X, m.X_W[near].astype(np.float32))
    assert main(["export", str(run_dir), "--ply", str(tmp_path / "all.ply"), "--max-point-range", "0"]) == 0
    np.testing.assert_allclose(read_ply(tmp_path / "all.ply")[0], m.X_W.astype(np.float32))


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


# ------------------------------------------------------------------ bad inputs on a synthetic run folder


FAR_M = 1e6  # a point at near-zero inverse depth: this far from the cameras (a few metres apart)


def _error_line(err: str) -> str:
    """The one ``fgslam: error: ...`` line of a failed command (no traceback)."""
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("fgslam: error: "), err
    return lines[0]


def _synthetic_run(root: Path, dataset: Path, far_point: bool = False) -> Path:
    """A run folder (summary.json, map.npz) of the exact synthetic map of tests/test_colmap_export.py whose
    dataset was at ``dataset``; with ``far_point`` one more point ``FAR_M`` in front of the cameras."""
    from test_colmap_export import synthetic_run_map

    run_map = synthetic_run_map()
    if far_point:
        m = run_map.map
        m = MapExport(m.kf_ids, m.kf_timestamps, m.T_WC, np.vstack([m.X_W, [0.0, 0.0, FAR_M]]),
                      np.vstack([m.colour, [255, 0, 0]]), m.track_point, m.track_kf, m.track_uv)
        run_map = RunMap(m, run_map.intrinsics, run_map.width, run_map.height, run_map.frame_timestamps,
                         run_map.frame_indices, run_map.frame_paths, run_map.sensor)
    root.mkdir(parents=True)
    save_run_map(root / "map.npz", run_map)
    (root / "summary.json").write_text(json.dumps({
        "frames_with_pose": int(run_map.frame_indices.size), "error": None, "notes": [], "output_errors": {},
        "dataset": {"path": str(dataset), "format": "folder"}, "config": {"output": {"write_map": True}}}))
    return root


def test_truncated_map_is_the_stored_maps_one_line_error(tmp_path, capsys):
    """A truncated map.npz: the error of a truncated stored map (fgslam localize's check), no BadZipFile."""
    run = _synthetic_run(tmp_path / "run", tmp_path / "data")
    data = (run / "map.npz").read_bytes()
    (run / "map.npz").write_bytes(data[: len(data) // 2])
    with pytest.raises(DataError) as info:
        check_map_file(run / "map.npz")  # the one check, as `fgslam localize` and `fgslam run --map` make it
    for target in (["--colmap", str(tmp_path / "colmap"), "--no-images"], ["--ply", str(tmp_path / "map.ply")]):
        assert main(["export", str(run), *target]) == 2
        line = _error_line(capsys.readouterr().err)
        assert line == f"fgslam: error: {info.value}" and "truncated or damaged map file" in line
    assert not (tmp_path / "colmap").exists() and not (tmp_path / "map.ply").exists()


def test_failed_colmap_export_leaves_nothing_and_the_advised_retry_works(tmp_path, capsys):
    """The dataset moved: the export with images fails and leaves no sparse/0 behind, so the retry with
    --no-images that its error advises is not refused as an existing output; a failed --overwrite keeps
    the model written before."""
    run = _synthetic_run(tmp_path / "run", tmp_path / "moved_away")
    out = tmp_path / "colmap"
    assert main(["export", str(run), "--colmap", str(out)]) == 2
    line = _error_line(capsys.readouterr().err)
    assert "not there any more; export with --no-images" in line
    assert not out.exists() and sorted(p.name for p in tmp_path.iterdir()) == ["run"]  # no temporary folder left
    assert main(["export", str(run), "--colmap", str(out), "--no-images"]) == 0
    assert len(read_colmap_model(out).names) == 8 and not (out / "images").exists()
    before = {p.name: p.read_bytes() for p in (out / "sparse" / "0").iterdir()}
    assert main(["export", str(run), "--colmap", str(out), "--overwrite"]) == 2
    assert "not there any more" in _error_line(capsys.readouterr().err)
    assert {p.name: p.read_bytes() for p in (out / "sparse" / "0").iterdir()} == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["colmap", "run"]


def test_export_of_a_run_without_pose_gives_the_runs_reason(tmp_path, capsys, noise_images):
    """A run that never initialised has no map because it has no pose: the export says so with the reason
    of its summary.json, and does not advise output.write_map=true (which it had)."""
    data = noise_images(tmp_path / "two", 2)
    run = tmp_path / "run"
    assert main(["-q", "run", "patch_mono", "--data", str(data), "--out", str(run), "--no-progress"]) == 2
    capsys.readouterr()
    summary = json.loads((run / "summary.json").read_text())
    assert summary["frames_with_pose"] == 0 and summary["error"].startswith("no frame got a pose")
    assert main(["export", str(run), "--ply", str(tmp_path / "x.ply")]) == 2
    line = _error_line(capsys.readouterr().err)
    assert line == f"fgslam: error: {run}: the run produced no pose, so it has no map (map.npz): {summary['error']}"
    assert "write_map" not in line
    # a run with poses whose map was switched off: then (only) the advice
    bare = _synthetic_run(tmp_path / "bare", data)
    (bare / "map.npz").unlink()
    summary = json.loads((bare / "summary.json").read_text())
    summary["config"]["output"]["write_map"] = False
    (bare / "summary.json").write_text(json.dumps(summary))
    assert main(["export", str(bare), "--ply", str(tmp_path / "x.ply")]) == 2
    assert "output.write_map=false; rerun the sequence with true" in _error_line(capsys.readouterr().err)


def test_ply_leaves_out_far_points_unless_the_limit_is_raised_or_off(tmp_path, capsys):
    run = _synthetic_run(tmp_path / "run", tmp_path / "data", far_point=True)
    n = load_run_map(run / "map.npz").map.num_points
    ply = tmp_path / "map.ply"
    assert main(["export", str(run), "--ply", str(ply), "--json"]) == 0  # the default limit: on
    result = json.loads(capsys.readouterr().out)
    X, _ = read_ply(ply)
    assert X.shape[0] == result["points"] == n - 1 and result["points_left_out"] == 1
    assert np.abs(X).max() < 10 and 0 < result["range_limit"] < FAR_M
    for factor in ("0", "1e6"):  # off, and raised past the far point (1e6 x a median distance of metres)
        assert main(["export", str(run), "--ply", str(ply), "--overwrite", "--max-point-range", factor]) == 0
        X, colour = read_ply(ply)
        assert X.shape[0] == n and X[-1, 2] == FAR_M and colour[-1].tolist() == [255, 0, 0]
    capsys.readouterr()
    assert main(["export", str(run), "--ply", str(ply), "--overwrite", "--max-point-range", "-1"]) == 2
    assert "--max-point-range: key 'max_point_range_factor': must be >= 0" in _error_line(capsys.readouterr().err)


# ------------------------------------------------------------------ replacing an output (fgslam.export.inplace)


def _tree(folder: Path) -> dict[str, bytes]:
    """Every file under ``folder`` (relative path -> bytes)."""
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def _replace_failing(monkeypatch, failing: Callable[[Path, Path], bool], error: BaseException) -> None:
    """``os.replace`` of fgslam.export.inplace raising ``error`` for the renames ``failing(src, dst)`` picks."""
    real = os.replace

    def replace(src, dst):
        if failing(Path(src), Path(dst)):
            raise error
        real(src, dst)

    monkeypatch.setattr(inplace.os, "replace", replace)


@pytest.mark.parametrize("error", [OSError(errno.EXDEV, "Invalid cross-device link"), KeyboardInterrupt()])
def test_a_failed_swap_keeps_the_previous_output(tmp_path, capsys, monkeypatch, error):
    """The new output's rename into place fails (an error, Ctrl-C): the previous COLMAP export, moved aside
    first, is back in place, the previous PLY untouched (a file is replaced in one rename), nothing else left."""
    run = _synthetic_run(tmp_path / "run", tmp_path / "data")
    out, ply = tmp_path / "colmap", tmp_path / "map.ply"
    assert main(["export", str(run), "--colmap", str(out), "--no-images", "--colmap-format", "txt"]) == 0
    assert main(["export", str(run), "--ply", str(ply)]) == 0
    before, ply_before = _tree(out), ply.read_bytes()
    assert before and ply_before
    capsys.readouterr()
    _replace_failing(monkeypatch, lambda src, dst: ".tmp" in src.name, error)
    for target in (["--colmap", str(out), "--no-images"], ["--ply", str(ply), "--max-point-range", "0"]):
        if isinstance(error, OSError):
            assert main(["export", str(run), *target, "--overwrite"]) == 2
            line = _error_line(capsys.readouterr().err)
            assert "cannot move the new output into place" in line and "Invalid cross-device link" in line
        else:
            assert main(["export", str(run), *target, "--overwrite"]) == 130  # the CLI's Ctrl-C status
            assert capsys.readouterr().err == "fgslam: interrupted\n"
    assert _tree(out) == before and ply.read_bytes() == ply_before  # the text model kept, not the binary one
    assert sorted(p.name for p in tmp_path.iterdir()) == ["colmap", "map.ply", "run"]


def test_moving_the_previous_output_aside_fails_in_one_line(tmp_path, capsys, monkeypatch):
    """An OSError of the export's own file operations is a one-line error, and the previous output stays."""
    run = _synthetic_run(tmp_path / "run", tmp_path / "data")
    out = tmp_path / "colmap"
    assert main(["export", str(run), "--colmap", str(out), "--no-images"]) == 0
    before = _tree(out)
    capsys.readouterr()
    _replace_failing(monkeypatch, lambda src, dst: src == out, PermissionError(errno.EACCES, "Permission denied", str(out)))
    assert main(["export", str(run), "--colmap", str(out), "--no-images", "--overwrite"]) == 2
    line = _error_line(capsys.readouterr().err)
    assert f"{out}: cannot move the previous output aside: Permission denied ({out})" in line
    assert _tree(out) == before and sorted(p.name for p in tmp_path.iterdir()) == ["colmap", "run"]


def test_an_output_created_meanwhile_is_not_replaced(tmp_path, capsys, monkeypatch):
    """Without --overwrite, an output that appears at the path while the export writes (another export to
    the same path) is refused at the swap, not deleted; the new output is not left behind."""
    import fgslam.export.run_export as run_export

    run = _synthetic_run(tmp_path / "run", tmp_path / "data")
    out, ply = tmp_path / "colmap", tmp_path / "map.ply"
    real_model, real_ply = run_export.write_model, run_export.write_ply

    def model_and_another(*args, **kwargs):
        real_model(*args, **kwargs)
        (out / "sparse").mkdir(parents=True)
        (out / "sparse" / "theirs.txt").write_text("the other export")

    def ply_and_another(*args, **kwargs):
        real_ply(*args, **kwargs)
        ply.write_text("the other export")

    monkeypatch.setattr(run_export, "write_model", model_and_another)
    monkeypatch.setattr(run_export, "write_ply", ply_and_another)
    for target in (["--colmap", str(out), "--no-images"], ["--ply", str(ply)]):
        assert main(["export", str(run), *target]) == 2
        assert "exists (use --overwrite" in _error_line(capsys.readouterr().err)
    assert _tree(out) == {"sparse/theirs.txt": b"the other export"} and ply.read_text() == "the other export"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["colmap", "map.ply", "run"]


def test_overwrite_never_deletes_another_folder(tmp_path, capsys):
    """--overwrite replaces a PLY file or a previous COLMAP export (or an empty folder): a folder given to
    --ply, a --colmap folder that is not an export, or a file there, are refused and kept."""
    run = _synthetic_run(tmp_path / "run", tmp_path / "data")
    results = tmp_path / "results"
    results.mkdir()
    (results / "keep.txt").write_text("mine")
    for overwrite in ([], ["--overwrite"]):
        assert main(["export", str(run), "--ply", str(results), *overwrite]) == 2
        assert f"{results}: is a folder (--ply takes a file name" in _error_line(capsys.readouterr().err)
        assert main(["export", str(run), "--colmap", str(results), "--no-images", *overwrite]) == 2
        assert f"{results}: not a previous COLMAP export (no sparse/ in it" in _error_line(capsys.readouterr().err)
    (tmp_path / "file").write_text("mine too")
    assert main(["export", str(run), "--colmap", str(tmp_path / "file"), "--no-images", "--overwrite"]) == 2
    assert "exists and is not a folder" in _error_line(capsys.readouterr().err)
    assert _tree(results) == {"keep.txt": b"mine"} and (tmp_path / "file").read_text() == "mine too"
    empty = tmp_path / "empty"
    empty.mkdir()
    assert main(["export", str(run), "--colmap", str(empty), "--no-images"]) == 2  # refused without --overwrite
    assert "exists (use --overwrite" in _error_line(capsys.readouterr().err)
    assert main(["export", str(run), "--colmap", str(empty), "--no-images", "--overwrite"]) == 0
    assert len(read_colmap_model(empty).names) == 8


def test_missing_parent_folder_is_refused_for_colmap_as_for_ply(tmp_path, capsys):
    run = _synthetic_run(tmp_path / "run", tmp_path / "data")
    for flag, name in (("--colmap", "colmap"), ("--ply", "map.ply")):
        target = tmp_path / "missing" / name
        assert main(["export", str(run), flag, str(target), "--no-images"]) == 2
        assert _error_line(capsys.readouterr().err) == f"fgslam: error: {target}: folder {target.parent} does not exist"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run"]


def _dead_pid() -> int:
    """The id of a process that has ended (and been reaped)."""
    child = subprocess.Popen([sys.executable, "-c", "pass"])
    child.wait()
    return child.pid


def test_stale_siblings_of_ended_exports_are_swept(tmp_path, capsys):
    """The temporary output of an export killed outright (its process gone) is removed by the next export
    of that path, and a previous output it had moved aside is put back; the siblings of a running process,
    of another path, or of another name pattern are left alone."""
    run = _synthetic_run(tmp_path / "run", tmp_path / "data")
    dead, alive = _dead_pid(), os.getppid()
    out = tmp_path / "colmap"
    stale = tmp_path / f".colmap.tmp{dead}"
    (stale / "images").mkdir(parents=True)
    (stale / "images" / "000000.png").write_bytes(b"partial")
    (tmp_path / f".colmap.old{dead}" / "sparse").mkdir(parents=True)  # the previous export, moved aside
    (tmp_path / f".colmap.old{dead}" / "sparse" / "earlier.txt").write_text("earlier")
    kept = [tmp_path / f".colmap.tmp{alive}", tmp_path / f".colmap2.tmp{dead}", tmp_path / ".colmap.tmpx",
            tmp_path / f"colmap.tmp{dead}"]
    for path in kept:
        path.mkdir()
    assert main(["-q", "export", str(run), "--colmap", str(out), "--no-images"]) == 2  # the put-back export exists
    put_back, error = capsys.readouterr().err.splitlines()  # -q: the warning and the error, no traceback
    assert put_back.endswith(f"{out}: put back the previous output that an interrupted write had moved aside")
    assert "exists (use --overwrite" in _error_line(error)
    assert _tree(out) == {"sparse/earlier.txt": b"earlier"}
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(["colmap", "run", *(p.name for p in kept)])
    ply = tmp_path / "map.ply"
    (tmp_path / f".map.ply.tmp{dead}").write_bytes(b"partial")
    assert main(["export", str(run), "--ply", str(ply)]) == 0
    assert not (tmp_path / f".map.ply.tmp{dead}").exists() and ply.is_file()
