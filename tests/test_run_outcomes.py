"""Outcomes of runs on bad inputs (issue 21, items 4 and 5): a run without any pose fails with one
reason line, a rerun never mixes its outputs with a previous run's, ``fgslam batch --address``
fails within seconds, ``compare-colmap`` without a COLMAP registration fails, the messages say what
happened (events by kind, frames skipped by kind, checkpoint folders, YAML errors), ``batch.md``
keeps whole errors, and ``fgslam run --help`` lists the presets."""

from __future__ import annotations

import json
import re
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from fgslam.cli import main
from fgslam.core.errors import ConfigError, DataError

HUGE_SIDE = 10000  # the trial's image size (one black frame: decoding and undistorting it take seconds)
LARGE_SIDE = 5000  # above fgslam.run.results.LARGE_IMAGE_SIDE, below the size limit a dataset refuses at open (if any)
CLI_TIMEOUT_S = 180  # a subprocess that hangs fails the test instead of blocking the suite (slow shared machine)


def _error_line(err: str) -> str:
    """The one ``fgslam: error: ...`` line of a failed command, which must be the last line of stderr."""
    lines = err.strip().splitlines()
    errors = [ln for ln in lines if ln.startswith("fgslam:")]
    assert len(errors) == 1 and lines[-1] == errors[0], err
    assert errors[0].startswith("fgslam: error: "), err
    return errors[0]


def _folder(root: Path, n: int, width: int, height: int, black: bool = False) -> Path:
    """An image folder of ``n`` random-texture (or black) frames with its calibration.yaml."""
    root.mkdir(parents=True)
    rng = np.random.default_rng(0)
    for i in range(n):
        img = np.zeros((height, width), np.uint8) if black else (rng.random((height, width)) * 255).astype(np.uint8)
        cv2.imwrite(str(root / f"{i:04d}.png"), img)
    (root / "calibration.yaml").write_text(
        f"width: {width}\nheight: {height}\nintrinsics: [{0.8 * width}, {0.8 * width}, {width / 2}, {height / 2}]\n")
    return root


@pytest.fixture(scope="module")
def room(tmp_path_factory) -> Path:
    """A small textured room-loop render (stereo, depth, ground truth)."""
    from fgslam.io.synth import SynthSequence, write_sequence
    from fgslam.io.synth.scenarios import load_synth_config

    root = tmp_path_factory.mktemp("room") / "seq"
    write_sequence(SynthSequence(load_synth_config("room-loop", None, [
        "frames=16", "camera.width=96", "camera.height=72"])), root)
    return root


# --------------------------------------------------------------------------------------- no frame got a pose


def _no_pose_case(case: str, tmp_path: Path, room: Path) -> tuple[str, Path]:
    """(preset, dataset) of one of the trial's runs in which no frame gets a pose."""
    if case == "two frames":
        return "patch_mono", _folder(tmp_path / "two", 2, 320, 240)
    if case == "one frame":
        return "patch_mono", _folder(tmp_path / "one", 1, 320, 240)
    if case == "black frames":
        return "patch_mono", _folder(tmp_path / "black", 10, 320, 240, black=True)
    if case == "invalid depth":
        import shutil

        root = tmp_path / "nodepth"
        shutil.copytree(room, root)
        for path in (root / "mav0" / "depth0" / "data").glob("*.png"):
            cv2.imwrite(str(path), np.zeros(cv2.imread(str(path), cv2.IMREAD_UNCHANGED).shape, np.uint16))
        return "patch_rgbd", root
    side = {"10000x10000": HUGE_SIDE, f"{LARGE_SIDE}x{LARGE_SIDE}": LARGE_SIDE}[case]
    return "patch_mono", _folder(tmp_path / "huge", 1, side, side, black=True)


@pytest.mark.parametrize("case", ["one frame", "two frames", "black frames", "invalid depth", "10000x10000",
                                  f"{LARGE_SIDE}x{LARGE_SIDE}"])
def test_a_run_without_any_pose_fails_with_one_reason_line(case, tmp_path, room, capsys):
    preset, data = _no_pose_case(case, tmp_path, room)
    out = tmp_path / "out"
    assert main(["run", preset, "--data", str(data), "--out", str(out), "--no-progress"]) == 2
    captured = capsys.readouterr()
    line = _error_line(captured.err)
    if case == "10000x10000":  # refused when the dataset opens (over MAX_IMAGE_SIDE), before any output
        assert "10000x10000" in line and "dataset.resize_width" in line, line  # the resize key is named
        assert not out.exists() or not any(out.iterdir())
        return
    assert line.startswith("fgslam: error: no frame got a pose: frontend 'patch' "), line
    assert "never initialised in" in line
    if case == f"{LARGE_SIDE}x{LARGE_SIDE}":
        assert f"{LARGE_SIDE}x{LARGE_SIDE}, too large" in line and "dataset.resize_width" in line
    if case == "invalid depth":
        assert "waiting for depth" in line  # what the frontend reported, by kind
    assert "exports no map" not in captured.out  # no result: no note that blames the frontend
    assert "stopped:" in captured.out  # the console report still comes, with the reason
    summary = json.loads((out / "summary.json").read_text())
    assert summary["frames_with_pose"] == 0 and summary["error"].startswith("no frame got a pose")


def test_batch_records_a_cell_without_any_pose_as_failed(tmp_path):
    from fgslam.run.batch import BatchMatrix, finished_row, run_batch

    data = _folder(tmp_path / "two", 2, 320, 240)
    matrix = BatchMatrix(configs={"mono": "patch_mono"}, datasets={"two": str(data)}, overrides=["output.plot=false"])
    rows, _ = run_batch(matrix, tmp_path / "batch", use_ray=False)
    assert rows[0]["status"] == "failed" and "no frame got a pose" in rows[0]["error"]
    # a summary of an older version (no pose, no error) is not a finished cell: it is run again
    cell = {"config": "mono", "dataset": "two", "out": str(tmp_path / "old")}
    (tmp_path / "old").mkdir()
    (tmp_path / "old" / "summary.json").write_text(json.dumps({"error": None, "frames_with_pose": 0}))
    assert finished_row(cell) is None
    # and a rerun runs the failed cell again over its previous attempt (no refusal of its folder)
    rows, facts = run_batch(matrix, tmp_path / "batch", use_ray=False)
    assert facts["run"] == 1 and "no frame got a pose" in rows[0]["error"] and "previous run" not in rows[0]["error"]


# --------------------------------------------------------------------------------------- reruns into an --out


def test_a_rerun_into_a_previous_out_is_refused_and_overwrite_removes_the_old_outputs(tmp_path, room, capsys,
                                                                                       monkeypatch):
    out = tmp_path / "out"
    args = ["run", "patch_mono", "--data", str(room), "--out", str(out), "--no-progress"]
    assert main(args) == 0
    old = {name for name in ("trajectory_tum.txt", "trajectory_kitti.txt", "trajectory.png", "map.npz", "summary.json")}
    assert old <= {p.name for p in out.iterdir()}
    (out / "notes.txt").write_text("mine")  # not an output: left alone
    capsys.readouterr()
    assert main(args) == 2
    line = _error_line(capsys.readouterr().err)
    assert str(out) in line and "--overwrite" in line and "previous run" in line
    # --overwrite with a run that cannot start (its config is refused, or its dataset does not open):
    # the previous run's outputs stay
    assert main(args + ["--overwrite", "-o", "dataset.resize_width=9000"]) == 2
    assert "dataset.resize_width" in _error_line(capsys.readouterr().err)
    assert main(["run", "patch_mono", "--data", str(tmp_path / "missing"), "--out", str(out), "--overwrite"]) == 2
    assert "missing" in _error_line(capsys.readouterr().err)
    assert old <= {p.name for p in out.iterdir()}
    # ... nor a run refused when its system is built (a frontend that cannot be built), after every other check
    from fgslam.run.system import SlamSystem

    def cannot_build(*args, **kwargs):
        raise ConfigError("cannot build (simulated)")

    with monkeypatch.context() as patch:
        patch.setattr(SlamSystem, "build", cannot_build)
        assert main(args + ["--overwrite"]) == 2
    assert "cannot build (simulated)" in _error_line(capsys.readouterr().err)
    assert old <= {p.name for p in out.iterdir()}
    # --overwrite with a run that gives no pose: none of the previous run's outputs is left beside its summary
    assert main(args + ["--overwrite", "-o", "dataset.end=1"]) == 2
    assert "no frame got a pose" in _error_line(capsys.readouterr().err)
    assert {p.name for p in out.iterdir()} == {"summary.json", "notes.txt"}
    assert json.loads((out / "summary.json").read_text())["frames_with_pose"] == 0
    assert main(["export", str(out), "--ply", str(tmp_path / "x.ply")]) == 2  # no old map to export
    capsys.readouterr()


# --------------------------------------------------------------------------------------- batch --address


class _Server:
    """A TCP server on a loopback port that is not Ray: silent, or answering like an HTTP/1.1 server."""

    def __init__(self, reply: bytes) -> None:
        self.sock = socket.socket()
        self.sock.bind(("127.0.0.1", 0))
        self.sock.listen()
        self.port = self.sock.getsockname()[1]
        self.reply, self.conns = reply, []
        threading.Thread(target=self._serve, daemon=True).start()

    def _serve(self) -> None:
        while True:
            try:
                conn, _ = self.sock.accept()
            except OSError:
                return
            self.conns.append(conn)
            if self.reply:
                conn.sendall(self.reply)

    def close(self) -> None:
        for c in self.conns:
            c.close()
        self.sock.close()


def _closed_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.mark.parametrize("kind", ["silent", "http", "closed", "unresolvable", "bad port"])
def test_batch_address_that_is_not_ray_fails_within_seconds(kind, tmp_path):
    """``fgslam batch --address`` in a subprocess (a hang fails the test, never blocks it): one error
    line, status 2, no traceback; the address check itself takes at most its timeout."""
    pytest.importorskip("ray", reason="Ray is an optional extra (pip install 'fgslam[batch]')")
    from fgslam.run.batch import BatchOptions, check_address

    server = _Server(b"HTTP/1.1 400 Bad Request\r\n\r\n" if kind == "http" else b"") if kind in ("silent", "http") else None
    address = {"silent": f"127.0.0.1:{server.port if server else 0}", "http": f"127.0.0.1:{server.port if server else 0}",
               "closed": f"127.0.0.1:{_closed_port()}", "unresolvable": "no-such-host.invalid:6379",
               "bad port": "127.0.0.1:99999"}[kind]
    expected = {"silent": "does not answer as a Ray cluster", "http": "is not a Ray cluster",
                "closed": "cannot be reached", "unresolvable": "cannot be reached", "bad port": "expected host:port"}[kind]
    matrix = tmp_path / "m.yaml"
    matrix.write_text(f"configs: {{mono: patch_mono}}\ndatasets: {{d: {tmp_path / 'nothing'}}}\n")
    try:
        timeout_s = BatchOptions().connect_timeout_s
        t0 = time.perf_counter()
        with pytest.raises((DataError, ConfigError), match=re.escape(expected)):
            check_address(address, timeout_s)
        assert time.perf_counter() - t0 < timeout_s + 2
        proc = subprocess.run([sys.executable, "-m", "fgslam", "batch", str(matrix), "--address", address],
                              capture_output=True, text=True, timeout=CLI_TIMEOUT_S)
    finally:
        if server is not None:
            server.close()
    assert proc.returncode == 2, proc.stderr[-2000:]
    line = _error_line(proc.stderr)
    assert expected in line and address in line and "Traceback" not in proc.stderr
    assert not (tmp_path / "m").exists()  # nothing ran


class _FakeGrpc(_Server):
    """Answers the HTTP/2 preface with a SETTINGS frame (as Ray's gRPC ports do), then nothing: passes
    the address check, and Ray's own connection attempts then hang."""

    def __init__(self) -> None:
        super().__init__(bytes((0, 0, 0, 4, 0, 0, 0, 0, 0)))


def test_joining_a_cluster_that_never_answers_is_bounded_and_sigterm_stops_it(tmp_path):
    pytest.importorskip("ray", reason="Ray is an optional extra (pip install 'fgslam[batch]')")
    matrix = tmp_path / "m.yaml"
    matrix.write_text(f"configs: {{mono: patch_mono}}\ndatasets: {{d: {tmp_path / 'nothing'}}}\n")
    server = _FakeGrpc()
    try:
        # a SIGTERM while ray.init hangs: the batch stops at once, one line, exit 143
        proc = subprocess.Popen([sys.executable, "-m", "fgslam", "batch", str(matrix), "--address",
                                 f"127.0.0.1:{server.port}"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                                preexec_fn=lambda: signal.signal(signal.SIGTERM, signal.SIG_DFL))
        watchdog = threading.Timer(CLI_TIMEOUT_S, proc.kill)
        watchdog.start()
        try:
            lines = []
            for line in proc.stderr:  # past the address check, joining the cluster
                lines.append(line)
                if "joining the Ray cluster at" in line:
                    break
            time.sleep(1)
            t0 = time.perf_counter()
            proc.send_signal(signal.SIGTERM)
            _, rest = proc.communicate()
            stop_s = time.perf_counter() - t0
        finally:
            watchdog.cancel()
        err = "".join(lines) + rest
        assert proc.returncode == 143, err[-2000:]
        assert stop_s < 30, stop_s
        assert "fgslam: interrupted by SIGTERM" in err and "Traceback" not in err
    finally:
        server.close()


def test_joining_a_cluster_that_never_answers_fails_after_the_init_timeout(tmp_path):
    """Past the address check, ray.init is bounded (BatchOptions.init_timeout_s): one error line, and the
    process ends (in a subprocess: the abandoned ray.init thread must not keep it alive)."""
    pytest.importorskip("ray", reason="Ray is an optional extra (pip install 'fgslam[batch]')")
    init_timeout_s = 3.0
    server = _FakeGrpc()
    code = (
        "import sys, time\n"
        "from fgslam.run.batch import BatchMatrix, BatchOptions, run_batch\n"
        "from fgslam.core.errors import FGSlamError\n"
        "import fgslam.run.runner, ray  # imported before the clock starts: slow on a loaded machine\n"
        f"m = BatchMatrix(configs={{'mono': 'patch_mono'}}, datasets={{'d': {str(tmp_path / 'nothing')!r}}})\n"
        "t0 = time.perf_counter()\n"
        "try:\n"
        f"    run_batch(m, __import__('pathlib').Path({str(tmp_path / 'out')!r}), BatchOptions(init_timeout_s={init_timeout_s}),\n"
        f"              address='127.0.0.1:{server.port}')\n"
        "except FGSlamError as exc:\n"
        "    print(f'{time.perf_counter() - t0:.1f} {exc}')\n"
        "    sys.exit(2)\n")
    try:
        proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=CLI_TIMEOUT_S)
    finally:
        server.close()
    assert proc.returncode == 2, proc.stderr[-2000:]
    seconds, message = proc.stdout.strip().split(" ", 1)
    assert f"did not finish within {init_timeout_s:g} s" in message and "init_timeout_s" in message
    assert float(seconds) < init_timeout_s + 5


# --------------------------------------------------------------------------------------- compare-colmap


def test_compare_colmap_without_a_registered_frame_fails_without_a_ratio(tmp_path, room, capsys, monkeypatch):
    import fgslam.export.colmap as colmap
    from fgslam.export.colmap import SfmResult

    monkeypatch.setattr(colmap, "run_colmap_sfm", lambda *a, **k: SfmResult(None, 0, {"total": 30.0}, 40.0))
    out = tmp_path / "cmp"
    assert main(["-q", "compare-colmap", "--data", str(room), "--frames", "16", "--out", str(out), "--no-progress"]) == 2
    captured = capsys.readouterr()
    assert "COLMAP registered no frame of 16" in captured.out and "x wall" not in captured.out
    assert "COLMAP registered no frame" in _error_line(captured.err)
    report = json.loads((out / "compare.json").read_text())
    assert report["speed_ratio_wall"] is None and report["speed_ratio_cpu"] is None
    assert report["colmap"]["error"] == "COLMAP registered no frame of 16"


# --------------------------------------------------------------------------------------- messages


def test_events_are_counted_by_kind_without_ids():
    from fgslam.run.session import event_kind

    kinds = [event_kind(f"keyframe {i} removed") for i in range(376)]
    assert set(kinds) == {"keyframe removed"}
    assert event_kind("keyframe removed: 12") == "keyframe removed"
    assert event_kind("waiting for parallax (1.2 px)") == "waiting for parallax"
    assert event_kind("tracking lost: 3 valid") == "tracking lost"
    assert event_kind("initialisation reference reset (tracks lost)") == "initialisation reference reset (tracks lost)"


def test_summary_events_have_one_key_per_kind(room, tmp_path):
    from fgslam.frontends.base import FrameStatus, Frontend
    from fgslam.run.config import load_slam_config
    from fgslam.run.prepare import open_slam_dataset
    from fgslam.run.runner import run_slam

    class Removing(Frontend):
        name = "removing"

        def __init__(self):
            self.t, self.T = [], []

        def process(self, frame):
            self.t.append(frame.timestamp)
            self.T.append(np.eye(4))
            return FrameStatus(frame.index, frame.timestamp, np.eye(4), "tracked",
                               events=[f"keyframe {frame.index} removed", f"keyframe {frame.index}"])

        def trajectory(self):
            return np.array(self.t), np.array(self.T), ["tracked"] * len(self.t)

        def num_keyframes(self):
            return 0

    config = load_slam_config(None, ["output.plot=false"])
    summary = run_slam(open_slam_dataset(room, config), config, tmp_path / "out", progress=False, frontend=Removing())
    assert summary.events == {"keyframe removed": 16, "keyframe": 16}


def test_an_all_corrupt_folder_counts_what_it_read(tmp_path):
    from fgslam.io.datasets import open_dataset

    root = _folder(tmp_path / "f", 10, 64, 48)
    for path in root.glob("*.png"):
        path.write_bytes(b"not an image")
    ds = open_dataset(root)
    with pytest.raises(DataError) as info:
        list(ds)
    msg = str(info.value)
    assert "2 of the first 2 frames (of 10) skipped: 2 unreadable; more than allowed" in msg
    assert "at most 1 of 10" in msg


def test_frames_of_the_wrong_size_are_not_called_unreadable(tmp_path):
    from fgslam.io.datasets import open_dataset

    root = _folder(tmp_path / "f", 10, 64, 48)
    for i in (3, 4):
        cv2.imwrite(str(root / f"{i:04d}.png"), np.full((40, 64), 128, np.uint8))
    ds = open_dataset(root)
    with pytest.raises(DataError) as info:
        list(ds)
    msg = str(info.value)
    assert "2 of the first 5 frames (of 10) skipped: 2 of the wrong size;" in msg and "unreadable" not in msg
    assert "frame 4 is 64x40, expected 64x48" in msg
    assert "frame 3 is 64x40, expected 64x48" in ds.skipped_frames[0][1]


def test_a_checkpoint_that_is_a_folder_is_named_a_folder(tmp_path):
    from fgslam.frontends.checkpoints import LearnedSlot, checkpoint_path

    slot = LearnedSlot("DPVO", "dpvo.pth", "patch.source=dpvo", "patch.checkpoint", "patch.source=lk")
    with pytest.raises(DataError, match=r"is a folder; a file is expected \(dpvo\.pth\)") as info:
        checkpoint_path(slot, str(tmp_path))
    assert "not found" not in str(info.value)
    pytest.importorskip("torch")
    from fgslam.nets.checkpoint import read_state_dict

    with pytest.raises(DataError, match="is a folder; a file"):
        read_state_dict(tmp_path)


def test_the_mast3r_checkpoint_message_reads_well():
    from fgslam.frontends.checkpoints import LearnedSlot, checkpoint_path

    slot = LearnedSlot("MASt3R", "a MASt3R checkpoint", "pointmap.source.kind=mast3r", "pointmap.source.checkpoint",
                       "pointmap.source.kind=rgbd, stereo or mono", package="mast3r")
    with pytest.raises(ConfigError) as info:
        checkpoint_path(slot, None)
    msg = str(info.value)
    assert "weights a MASt3R" not in msg
    assert "needs pointmap.source.checkpoint, the path of the MASt3R weights (a MASt3R checkpoint)" in msg


def test_yaml_syntax_errors_name_the_file_or_the_override(tmp_path):
    from fgslam.io.calibration import read_yaml_file
    from fgslam.run.config import load_slam_config

    bad = tmp_path / "bad.yaml"
    bad.write_text("frontend: patch\nsensor: [mono\n")
    with pytest.raises(ConfigError) as info:
        load_slam_config(bad)
    assert str(info.value).startswith(f"{bad}:3:") and "<unicode string>" not in str(info.value)
    with pytest.raises(ConfigError) as info:
        load_slam_config(None, ["dataset.end=[1, 2"])
    assert str(info.value).startswith("-o override 'dataset.end=[1, 2' (value):1:")
    assert "<unicode string>" not in str(info.value)
    calib = tmp_path / "calibration.yaml"
    calib.write_text("%YAML:1.0\nwidth: 64\nheight: : 48\n")
    with pytest.raises(DataError) as info:
        read_yaml_file(calib)
    assert str(info.value).startswith(f"{calib}:3:") and "<unicode string>" not in str(info.value)


# --------------------------------------------------------------------------------------- batch.md


def test_batch_md_shows_the_whole_error_with_pipes_escaped():
    from fgslam.run.batch import markdown_table

    error = "DataError: /very/long/path/to/some/dataset/folder/that/does/not/exist | more: no such folder\nsecond"
    rows = [{"config": "mono", "dataset": "d", "status": "failed", "error": error}]
    table = markdown_table(rows)
    cell = table.splitlines()[-1]
    assert "/very/long/path/to/some/dataset/folder/that/does/not/exist \\| more: no such folder second" in cell
    assert len(re.findall(r"(?<!\\)\|", cell)) == 3  # the row's own separators only


# --------------------------------------------------------------------------------------- newcomers


def test_run_help_lists_every_preset_with_what_data_it_is_for(capsys):
    from fgslam.run.presets import configs_dir, run_presets

    presets = run_presets()
    assert "patch_kitti_mono" in presets and "dense_mono" in presets and "pointmap_rgbd" in presets
    assert "pgo" not in presets and "demo" not in presets
    for name, text in presets.items():
        assert text, f"{name}: no '# description:' line"
        assert (configs_dir() / f"{name}.yaml").read_text().splitlines()[0] == f"# description: {text}"
    with pytest.raises(SystemExit):
        main(["run", "--help"])
    help_text = capsys.readouterr().out
    for name, text in presets.items():
        assert re.search(rf"^  {name} +{re.escape(text)}$", help_text, re.M), name


def test_the_data_page_names_the_calibration_file_of_folders_and_videos(repo_root):
    page = (repo_root / "docs" / "data.md").read_text()
    assert "`DIR/calibration.yaml`" in page and "`<video stem>.yaml` or `calibration.yaml` next to it" in page
    assert "-o dataset.calibration_file=PATH" in page
