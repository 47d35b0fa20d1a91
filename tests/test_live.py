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
from fgslam.io.frame import Frame, ImuSamples
from fgslam.io.live import LiveConfig, LiveFrames, ReadAhead

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
    assert got == sorted(got) and got[-1] == 39  # in order, and the last frame always comes
    assert live.dropped > 0 and live.dropped + len(got) == 40 and live.delivered == len(got)
    assert set(live.arrival_s) == set(got)


def test_a_paced_replay_takes_the_clip_duration_over_its_speed_and_drops_nothing_when_kept_up_with():
    for speed in (1.0, 2.0):
        live = LiveFrames(frames(11, 50.0), LiveConfig(speed=speed, queue=11))  # 0.2 s of clip; room for all
        t0 = time.perf_counter()
        got = [f.index for f in live]
        elapsed = time.perf_counter() - t0
        assert got == list(range(11)) and live.dropped == 0
        assert elapsed >= 0.2 / speed * 0.95  # never faster than the clip's times (the upper side: a loaded machine)


def test_a_dropped_frame_hands_its_imu_samples_to_the_next_one():
    calib = Calibration(8, 8, [8.0, 8.0, 4.0, 4.0])
    rate_hz, per_frame = 100.0, 10  # IMU at 1 kHz: ten samples a frame

    def with_imu():
        for i in range(30):
            t = i / rate_hz
            stamps = t - np.arange(per_frame)[::-1] / (rate_hz * per_frame)
            yield Frame(i, i, t, np.zeros((8, 8), np.uint8), calib,
                        imu=ImuSamples(stamps, np.zeros((per_frame, 3)), np.ones((per_frame, 3))))

    live = LiveFrames(with_imu(), LiveConfig(queue=1))
    delivered = []
    for frame in live:
        delivered.append(frame)
        time.sleep(0.03)  # three frames' time: behind
    assert live.dropped > 0
    stamps = np.concatenate([f.imu.timestamps for f in delivered])
    # every sample from the first delivered frame's block on arrives once, in order: no gap where frames were dropped
    everything = np.concatenate([f.imu.timestamps for f in with_imu()])
    assert np.array_equal(stamps, everything[everything >= stamps[0]])


def test_live_options_out_of_range_are_refused():
    for bad, key in ((LiveConfig(queue=0), "live.queue"), (LiveConfig(speed=0.0), "live.speed")):
        with pytest.raises(ConfigError, match=key):
            LiveFrames(frames(1, 1.0), bad)


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
    endless._thread.join(30)  # close() waited a while; a loaded machine may need longer
    assert not endless._thread.is_alive()


def test_read_ahead_gives_every_frame_in_order_and_reads_while_the_consumer_works():
    n = 12
    read = [threading.Event() for _ in range(n)]

    def source():
        for frame in frames(n, 100.0):
            read[frame.index].set()
            yield frame

    got, lead = [], []
    for frame in ReadAhead(source()):
        k = frame.index
        got.append(k)
        lead.append(sum(e.is_set() for e in read) - 1 - k)
        if k + 1 < n:  # while the consumer holds frame k, frame k + 1 is read (iterated directly, it never is)
            assert read[k + 1].wait(30)
    assert got == list(range(n))  # none dropped, in order
    assert max(lead) <= 2  # one frame waits, and the reader holds one more until there is room


def test_read_ahead_counts_the_cpu_of_its_own_thread_only():
    """``cpu_s``: the reader thread's CPU (decoding), not the consumer's; a run reports it as ``read_cpu_s``."""
    import time

    def busy(seconds):
        end = time.thread_time() + seconds
        while time.thread_time() < end:
            pass

    def source():
        for frame in frames(4, 100.0):
            busy(0.05)  # "decoding": CPU in the reader thread
            yield frame

    reader = ReadAhead(source())
    for _ in reader:
        busy(0.1)  # the consumer's work, in its own thread
    assert 0.2 <= reader.cpu_s < 0.35


def test_read_ahead_raises_the_source_error_after_the_frames_before_it_and_stops_on_close():
    def broken():
        yield from frames(3, 100.0)
        raise ValueError("decoder broke")

    got = []
    with pytest.raises(ValueError, match="decoder broke"):
        for frame in ReadAhead(broken()):
            got.append(frame.index)
    assert got == [0, 1, 2]
    endless = ReadAhead(frames(10**6, 1000.0))
    for frame in endless:
        if frame.index >= 2:
            break
    endless.close()
    endless._thread.join(30)
    assert not endless._thread.is_alive()
    with pytest.raises(ValueError, match="ahead"):
        ReadAhead(frames(1, 1.0), ahead=0)


def live_summary(out):
    return json.loads((out / "summary.json").read_text())


@pytest.mark.parametrize("data", ["file", "capture"])
def test_a_video_replayed_at_its_rate_is_tracked_live(video_clip, tmp_path, capsys, data):
    # the file loader and the camera:SPEC capture path replay the clip at its own 10 Hz
    spec = str(video_clip) if data == "file" else f"camera:{video_clip}"
    # room for every frame (the drops: the next test), so that the run gets poses however slow the machine
    args = ["run", "driving_mono", "--data", spec, "--out", str(tmp_path), "--no-progress", "--live",
            "--live-queue", str(CLIP_FRAMES), "-o", f"dataset.calibration_file={video_clip.with_suffix('.yaml')}"]
    t0 = time.perf_counter()
    assert cli_main(args) == 0
    elapsed = time.perf_counter() - t0
    s = live_summary(tmp_path)
    live = s["live"]
    assert live["delivered"] == CLIP_FRAMES == s["frames_processed"] and live["dropped"] == 0
    assert elapsed >= (CLIP_FRAMES - 1) / CLIP_RATE_HZ * 0.95  # paced: not faster than the clip
    assert 0 < live["latency_ms_p50"] <= live["latency_ms_p99"] <= live["latency_ms_max"]
    assert s["frames_with_pose"] > 0 and s["motion"]["path_length"] > 0
    assert "live:" in capsys.readouterr().out


def test_a_replay_faster_than_the_system_drops_the_oldest_frames(video_clip, tmp_path, capsys):
    # at 1000 times its rate the clip arrives as fast as it decodes: faster than any machine tracks; with so
    # few frames left the run may get no pose (then it exits 2, as any run without a result): the drops count
    args = ["run", "driving_mono", "--data", str(video_clip), "--out", str(tmp_path), "--no-progress",
            "--live", "--live-speed", "1000"]
    assert cli_main(args) in (0, 2)
    s = live_summary(tmp_path)
    assert s["live"]["dropped"] > 0 and s["live"]["delivered"] + s["live"]["dropped"] == CLIP_FRAMES
    assert s["live"]["speed"] == 1000


def test_live_option_and_capture_errors_are_one_line(video_clip, tmp_path, capsys):
    assert cli_main(["run", "driving_mono", "--data", str(video_clip), "--out", str(tmp_path / "a"),
                     "--live-speed", "0"]) != 0
    assert "live.speed" in capsys.readouterr().err
    assert cli_main(["run", "driving_mono", "--data", f"camera:{video_clip}", "--out", str(tmp_path / "b")]) != 0
    assert "dataset.calibration_file" in capsys.readouterr().err
    calibration = f"dataset.calibration_file={video_clip.with_suffix('.yaml')}"
    assert cli_main(["run", "driving_mono", "--data", f"camera:{video_clip}", "--out", str(tmp_path / "c"),
                     "-o", calibration, "-o", "dataset.stride=2"]) != 0
    assert "dataset.stride" in capsys.readouterr().err
    assert cli_main(["run", "driving_mono", "--data", f"camera:{video_clip}", "--out", str(tmp_path / "d"),
                     "-o", calibration, "--save-map", str(tmp_path / "m.map")]) != 0
    assert "record it to a video file" in capsys.readouterr().err
    assert cli_main(["run", "driving_mono", "--data", "camera:no_such_stream", "--out", str(tmp_path / "e"),
                     "-o", calibration]) != 0
    assert "cannot open this capture" in capsys.readouterr().err
    from fgslam.io.datasets import open_dataset

    with pytest.raises(ConfigError, match="calibration_file"):
        open_dataset(f"camera:{video_clip}")


def test_ctrl_c_ends_a_live_run_with_its_outputs(video_clip, tmp_path):
    out = tmp_path / "out"
    proc = subprocess.Popen([sys.executable, "-m", "fgslam", "run", "driving_mono", "--data", str(video_clip),
                             "--out", str(out), "--no-progress", "--live", "--live-speed", "0.25"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    lines = []
    reader = threading.Thread(target=lambda: lines.extend(proc.stderr), daemon=True)
    reader.start()
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline and proc.poll() is None and not any("initialised" in x for x in lines):
        time.sleep(0.2)  # the map started: the run is in its frame loop (the clip lasts 16 s at a quarter speed)
    assert proc.poll() is None, "".join(lines)
    proc.send_signal(signal.SIGINT)
    proc.wait(timeout=60)
    reader.join(timeout=10)
    err = "".join(lines)
    assert proc.returncode == 130, err
    s = live_summary(out)
    assert s["interrupted"] == "SIGINT" and 0 < s["live"]["delivered"] < CLIP_FRAMES
    assert (out / "trajectory_tum.txt").is_file() and "Traceback" not in err
