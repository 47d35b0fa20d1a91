"""``fgslam batch``: a 2 x 2 matrix on a tiny synthetic clip (one cell failing), sequentially and on a
local Ray instance; reruns skip finished cells; bad matrices and unreachable Ray addresses."""

from __future__ import annotations

import json
import socket
import time
from pathlib import Path

import pytest

from fgslam.run.batch import BatchMatrix, BatchOptions, load_matrix, run_batch
from fgslam.cli import main
from fgslam.core.errors import ConfigError, DataError

LIGHT = ["output.plot=false"]


@pytest.fixture(scope="module")
def clip(tmp_path_factory) -> Path:
    from patch_support import render_room

    return render_room(tmp_path_factory, "clip", ["frames=40", "camera.width=320", "camera.height=240"])  # shared, read only


def _matrix(tmp_path: Path, clip: Path, extra: str = "") -> Path:
    path = tmp_path / "matrix.yaml"
    path.write_text(
        "configs:\n"
        "  mono: patch_mono\n"
        "  lighter: {preset: patch_mono, overrides: [patch.graph.patches_per_frame=64]}\n"
        "datasets:\n"
        f"  room: {clip}\n"
        "  missing: {path: no_such_folder}\n"
        f"overrides: [{', '.join(LIGHT)}]\n" + extra)
    return path


def _check_rows(rows):
    by = {(r["config"], r["dataset"]): r for r in rows}
    assert len(rows) == 4
    for c in ("mono", "lighter"):
        ok, bad = by[(c, "room")], by[(c, "missing")]
        assert ok["status"] == "ok" and ok["ate_m"] is not None and ok["fps"] > 0 and ok["frames"] == 40
        assert bad["status"] == "failed" and "no_such_folder" in bad["error"]


def test_sequential_batch_records_the_failing_cell_and_reruns_skip_finished(tmp_path, clip, capsys):
    path = _matrix(tmp_path, clip)
    # 2 of 4 cells fail: exit status 1 (documented: fgslam batch --help), every table and the cells that worked written
    assert main(["-q", "batch", str(path), "--sequential", "--json"]) == 1
    captured = capsys.readouterr()
    assert "2 of 4 cells failed" in captured.err
    result = json.loads(captured.out)
    _check_rows(result["cells"])
    assert result["facts"]["engine"] == "sequential" and result["facts"]["run"] == 4
    out = tmp_path / "matrix"
    assert (out / "mono" / "room" / "summary.json").is_file()
    md = (out / "batch.md").read_text()
    assert md.startswith("| config | room | missing |") and "failed: " in md and "frames/s" in md
    assert (out / "batch.csv").read_text().splitlines()[0].startswith("config,dataset,status,ate_m")
    # a rerun runs only the failed cells
    stamp = (out / "mono" / "room" / "summary.json").stat().st_mtime_ns
    rows, facts = run_batch(*load_matrix(path), use_ray=False)
    assert facts["skipped"] == 2 and facts["run"] == 2
    assert (out / "mono" / "room" / "summary.json").stat().st_mtime_ns == stamp
    assert [r["skipped"] for r in rows if r["dataset"] == "room"] == [True, True]
    _check_rows(rows)


def test_ray_local_batch(tmp_path, clip):
    pytest.importorskip("ray", reason="Ray is an optional extra (pip install 'fgslam[batch]')")
    matrix, out = load_matrix(_matrix(tmp_path, clip))
    del matrix.configs["lighter"]  # one ok and one failing cell: Ray's start and worker imports dominate
    rows, facts = run_batch(matrix, out, BatchOptions(workers=2), use_ray=True)
    assert facts["engine"] == "ray" and facts["ray_cpus"] == 2
    assert [r["status"] for r in rows] == ["ok", "failed"] and rows[0]["ate_m"] is not None
    assert "no_such_folder" in rows[1]["error"]
    assert json.loads((out / "batch.json").read_text())["cells"] == json.loads(json.dumps(rows, default=str))


def test_unreachable_address_fails_within_seconds(tmp_path, clip, capsys):
    pytest.importorskip("ray", reason="Ray is an optional extra (pip install 'fgslam[batch]')")
    with socket.socket() as s:  # a loopback port nobody listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    t0 = time.perf_counter()
    assert main(["batch", str(_matrix(tmp_path, clip)), "--address", f"127.0.0.1:{port}"]) == 2
    assert time.perf_counter() - t0 < 10
    err = capsys.readouterr().err
    assert f"Ray cluster at 127.0.0.1:{port} cannot be reached" in err and err.count("\n") == 1


def test_unknown_matrix_keys_are_named(tmp_path, clip):
    with pytest.raises(ConfigError, match="unknown key 'config'"):
        load_matrix(_matrix(tmp_path, clip, "config: {}\n"))
    (tmp_path / "m2.yaml").write_text("configs: {a: {preset: patch_mono, overides: []}}\ndatasets: {d: x}\n")
    with pytest.raises(ConfigError, match=r"unknown key 'configs\.a\.overides'"):
        load_matrix(tmp_path / "m2.yaml")
    (tmp_path / "m3.yaml").write_text("configs: {a: patch_mono}\ndatasets: {}\n")
    with pytest.raises(ConfigError, match="datasets: the matrix needs at least one entry"):
        load_matrix(tmp_path / "m3.yaml")
    # a bad override fails the batch before any cell runs, naming the cell
    matrix, out = load_matrix(_matrix(tmp_path, clip))
    matrix.configs["mono"].overrides.append("patch.graph.no_such_key=1")
    with pytest.raises(ConfigError, match="cell mono x room: .*no_such_key"):
        run_batch(matrix, out, use_ray=False)
    assert not out.exists()


def test_without_ray_runs_sequentially_and_says_so(tmp_path, clip, monkeypatch, caplog):
    import fgslam.run.batch as batch

    monkeypatch.setattr(batch, "ray_available", lambda: False)
    matrix = BatchMatrix(configs={"mono": "patch_mono"}, datasets={"room": str(clip)}, overrides=list(LIGHT))
    matrix.validate()
    rows, facts = run_batch(matrix, tmp_path / "out")
    assert facts["engine"] == "sequential" and rows[0]["status"] == "ok"
    assert "Ray is not installed: running the 1 cells one after another" in caplog.text
    with pytest.raises(ConfigError, match="Ray is not installed"):
        run_batch(matrix, tmp_path / "out2", use_ray=True)
    with pytest.raises(ConfigError, match="Ray is not installed"):
        run_batch(matrix, tmp_path / "out3", address="127.0.0.1:1")
    with pytest.raises(DataError):
        batch.check_address("127.0.0.1:1", 1.0)


def test_a_failing_cell_never_reports_an_earlier_attempts_figures(tmp_path):
    """A cell whose dataset does not open this time: its row has the error and none of the figures of
    the summary.json an earlier attempt left in the cell's folder."""
    from fgslam.run.batch import run_cell

    out = tmp_path / "cell"
    out.mkdir()
    (out / "summary.json").write_text(json.dumps({"fps": 99.0, "frames_processed": 40,
                                                  "evaluation": {"ate_rmse_m": 0.01}}))
    row = run_cell({"config": "mono", "dataset": "gone", "preset": "patch_mono", "overrides": LIGHT,
                    "data": str(tmp_path / "no_such_folder"), "format": "auto", "out": str(out)})
    assert row["status"] == "failed" and "no_such_folder" in row["error"]
    assert row["fps"] is None and row["ate_m"] is None and row["frames"] is None
