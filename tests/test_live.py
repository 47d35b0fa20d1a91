"""Live input: the feed that drops the oldest frame when the consumer is behind (fgslam.io.live), the
capture of ``camera:SPEC``, and ``fgslam run --live`` on a video replayed through the capture path, at
its rate and faster than the system keeps up with."""

import json
import signal
import subprocess
import sys
import threading
import time

import numpy as np
import pytest

from fgslam.cli import main as cli_main
from fgslam.core.errors import ConfigError
from fgslam.io.calibration import Calibration
from fgslam.io.frame import Frame
from fgslam.io.live import LiveConfig, LiveFrames

from conftest import CLIP_FRAMES, CLIP_RATE_HZ


def frames(n, rate_hz):
    calib = Calibration(8, 8, [8.0, 8.0, 4.0, 4.0])
    for i in range(n):
        yield Frame(i, i, i / rate_hz, np.zeros((8, 8), np.uint8), calib)


def test_a_slow_consumer_gets_the_newest_frames_and_the_drops_are_counted():
    live = LiveFrames(frames(40, 200.0), LiveConfig(queue=1))  # 200 Hz, paced
    got = []
    for frame in live:
        got.append(frame.index)
        time.sleep(0.02)  # 50 Hz: behind
    assert got == sorted(got) and got[0] == 0 and got[-1] == 39  # in order, and the last frame always comes
    assert live.dropped > 0 and live.dropped + len(got) == 40 and live.delivered == len(got)
    assert set(live.arrival_s) == set(got)


def test_a_paced_replay_takes_the_clip_duration_over_its_speed_and_drops_nothing_when_kept_up_with():
    for speed in (1.0, 2.0):
        live = LiveFrames(frames(11, 50.0), LiveConfig(speed=speed))  # 0.2 s of clip
        t0 = time.perf_counter()
        got = [f.index for f in live]
        elapsed = time.perf_counter() - t0
        assert got == list(range(11)) and live.dropped == 0
        assert elapsed >= 0.2 / speed * 0.95  # never faster than the clip's times (the upper side: a loaded machine)


def test_an_error_of_the_source_reaches_the_consumer_and_close_stops_the_reader():
    def broken():
        yield from frames(3, 100.0)
        raise ValueError("decoder broke")

    live = LiveFrames(broken(), LiveConfig(queue=8, paced=False))
    with pytest.raises(ValueError, match="decoder broke"):
        for _ in live:
            time.sleep(0.01)
    endless = LiveFrames(frames(10**6, 1000.0), LiveConfig(paced=False))
    for frame in endless:
        if frame.index >= 2:
            break
    endless.close()
    assert not endless._thread.is_alive()


def live_summary(out):
    return json.loads((out / "summary.json").read_text())


@pytest.mark.parametrize("data", ["file", "capture"])
def test_a_video_replayed_at_its_rate_is_tracked_live(video_clip, tmp_path, capsys, data):
    # the file loader and the camera:SPEC capture path replay the clip at its own 10 Hz
    spec = str(video_clip) if data == "file" else f"camera:{video_clip}"
    args = ["run", "driving_mono", "--data", spec, "--out", str(tmp_path), "--no-progress", "--live",
            "-o", f"dataset.calibration_file={video_clip.with_suffix('.yaml')}"]
    t0 = time.perf_counter()
    assert cli_main(args) == 0
    elapsed = time.perf_counter() - t0
    s = live_summary(tmp_path)
    live = s["live"]
    assert live["delivered"] + live["dropped"] == CLIP_FRAMES == s["frames_processed"] + live["dropped"]
    assert elapsed >= (CLIP_FRAMES - 1) / CLIP_RATE_HZ * 0.95  # paced: not faster than the clip
    assert 0 < live["latency_ms_p50"] <= live["latency_ms_p99"] <= live["latency_ms_max"]
    assert s["frames_with_pose"] >= live["delivered"] // 2
    assert "live:" in capsys.readouterr().out


def test_a_replay_faster_than_the_system_drops_the_oldest_frames(video_clip, tmp_path, capsys):
    args = ["run", "driving_mono", "--data", str(video_clip), "--out", str(tmp_path), "--no-progress",
            "--live", "--live-speed", "4"]
    assert cli_main(args) == 0
    s = live_summary(tmp_path)
    assert s["live"]["dropped"] > 0 and s["live"]["delivered"] + s["live"]["dropped"] == CLIP_FRAMES
    assert s["live"]["speed"] == 4


def test_live_option_and_capture_errors_are_one_line(video_clip, tmp_path, capsys):
    assert cli_main(["run", "driving_mono", "--data", str(video_clip), "--out", str(tmp_path / "a"),
                     "--live-speed", "0"]) != 0
    assert "live.speed" in capsys.readouterr().err
    assert cli_main(["run", "driving_mono", "--data", f"camera:{video_clip}", "--out", str(tmp_path / "b")]) != 0
    assert "dataset.calibration_file" in capsys.readouterr().err
    with pytest.raises(ConfigError):
        from fgslam.io.datasets import open_dataset

        open_dataset(f"camera:{video_clip}")


def test_ctrl_c_ends_a_live_run_with_its_outputs(video_clip, tmp_path):
    out = tmp_path / "out"
    proc = subprocess.Popen([sys.executable, "-m", "fgslam", "run", "driving_mono", "--data", str(video_clip),
                             "--out", str(out), "--no-progress", "--live", "--live-speed", "0.5"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    lines = []
    reader = threading.Thread(target=lambda: lines.extend(proc.stderr), daemon=True)
    reader.start()
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline and proc.poll() is None and not any("initialised" in x for x in lines):
        time.sleep(0.2)  # the map started: the run is in its frame loop (the clip lasts 8 s at half speed)
    proc.send_signal(signal.SIGINT)
    proc.wait(timeout=60)
    reader.join(timeout=10)
    err = "".join(lines)
    assert proc.returncode == 130, err
    s = live_summary(out)
    assert s["interrupted"] == "SIGINT" and 0 < s["live"]["delivered"] < CLIP_FRAMES
    assert (out / "trajectory_tum.txt").is_file() and "Traceback" not in err
