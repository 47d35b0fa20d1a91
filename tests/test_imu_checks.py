"""The IMU stream's plausibility checks (fgslam/services/imu_checks.py): synthetic room-loop streams (the
generator's noise and bias walk) with each usual mistake are named; the correct stream passes; a run
with a wrong stream stops with a DataError before any work."""

import logging

import numpy as np
import pytest

from fgslam.core.errors import DataError
from fgslam.io.frame import ImuSamples
from fgslam.services.imu_checks import DEG_PER_RAD, ImuCheckConfig, check_imu_stream, find_imu_problems

GRAVITY = 9.81


@pytest.fixture(scope="module")
def R_CB():
    """The room loop's body-to-camera rotation (its forward-looking camera mount)."""
    from fgslam.io.synth.scenarios import camera_mount, load_synth_config

    return camera_mount(load_synth_config("room-loop").camera)[:3, :3].T


@pytest.fixture(scope="module")
def stream():
    """20 s of the room loop's hand-held motion: IMU samples at 200 Hz and frame times at 20 Hz (s)."""
    from fgslam.io.synth.imu import simulate_imu
    from fgslam.io.synth.motions import build_trajectory
    from fgslam.io.synth.scenarios import load_synth_config

    cfg = load_synth_config("room-loop", overrides=["frames=401"])
    t = np.arange(0.0, 20.0 + 1e-9, 1.0 / cfg.imu.rate_hz)
    imu = simulate_imu(build_trajectory(cfg).sample(t), cfg.imu, np.random.default_rng(0))
    frames = np.arange(0.0, 20.0 + 1e-9, 1.0 / cfg.camera.rate_hz)
    return ImuSamples(t, imu.gyro, imu.accel), frames


def _checks(imu, frames, R_CB=None, **kw):
    return find_imu_problems(imu.timestamps, imu.gyro, imu.accel, frames, ImuCheckConfig(**kw), GRAVITY, R_CB)


def test_the_correct_stream_passes(stream, R_CB):
    imu, frames = stream
    assert np.percentile(np.linalg.norm(imu.gyro, axis=1), 99) > 0.3  # it moves: the gyro check sees rotation
    assert _checks(imu, frames, R_CB) == []


@pytest.mark.parametrize("axes", ["flip_z", "swap_xz", "swap_yz"])
def test_wrong_accelerometer_axes_are_a_warning(stream, R_CB, axes):
    """Axes that move gravity away from the image's up direction (the magnitudes stay right)."""
    imu, frames = stream
    a = imu.accel
    wrong = {"flip_z": a * [1, 1, -1], "swap_xz": a[:, [2, 1, 0]], "swap_yz": a[:, [0, 2, 1]]}[axes]
    found = _checks(ImuSamples(imu.timestamps, imu.gyro, wrong), frames, R_CB)
    assert [(f.check, f.mistake) for f in found] == [("axes", False)], found


def test_accelerometer_in_g_is_named(stream):
    imu, frames = stream
    found = _checks(ImuSamples(imu.timestamps, imu.gyro, imu.accel / GRAVITY), frames)
    assert [(f.check, f.mistake) for f in found] == [("accel_units", True)]
    assert "likely in g" in found[0].message


def test_accelerometer_with_another_wrong_scale_is_a_warning(stream):
    imu, frames = stream
    found = _checks(ImuSamples(imu.timestamps, imu.gyro, imu.accel * 3.0), frames)
    assert [(f.check, f.mistake) for f in found] == [("accel_units", False)]


def test_gyroscope_in_deg_per_s_is_named(stream):
    imu, frames = stream
    found = _checks(ImuSamples(imu.timestamps, imu.gyro * DEG_PER_RAD, imu.accel), frames)
    assert [(f.check, f.mistake) for f in found] == [("gyro_units", True)]
    assert "deg/s" in found[0].message


def test_swapped_columns_are_named(stream):
    imu, frames = stream
    found = _checks(ImuSamples(imu.timestamps, imu.accel, imu.gyro), frames)
    assert [(f.check, f.mistake) for f in found] == [("axes", True)]
    assert "swapped" in found[0].message


def test_imu_timestamps_in_microseconds_are_named(stream):
    imu, frames = stream
    t = imu.timestamps / 1000.0  # microseconds read as nanoseconds: a span 1000x too short
    found = _checks(ImuSamples(t, imu.gyro, imu.accel), frames)
    assert ("clock", True) in [(f.check, f.mistake) for f in found]
    assert "microseconds" in next(f.message for f in found if f.check == "clock")


def test_imu_rate_below_the_frame_rate_is_a_warning(stream):
    imu, frames = stream
    keep = slice(None, None, 20)  # 10 Hz IMU beside 20 Hz frames
    found = _checks(ImuSamples(imu.timestamps[keep], imu.gyro[keep], imu.accel[keep]), frames)
    assert [f.check for f in found if not f.mistake] == ["rate", "rate"]  # samples per frame, plausible rate
    assert not any(f.mistake for f in found)


def test_check_raises_a_clear_error_or_warns(stream, caplog):
    imu, frames = stream
    bad = ImuSamples(imu.timestamps, imu.gyro, imu.accel / GRAVITY)
    with pytest.raises(DataError, match="likely in g.*on_mistake=warn"):
        check_imu_stream(bad, frames, ImuCheckConfig(), GRAVITY, where="clip")
    caplog.set_level(logging.WARNING, logger="fgslam.services.imu_checks")
    messages = check_imu_stream(bad, frames, ImuCheckConfig(on_mistake="warn"), GRAVITY)
    assert len(messages) == 1 and "likely in g" in caplog.text
    assert check_imu_stream(bad, frames, ImuCheckConfig(enabled=False), GRAVITY) == []


def test_a_run_with_a_wrong_stream_stops_before_any_work(tmp_path):
    """Through the runner: a tiny synthetic clip whose IMU is rewritten in g stops with the named cause."""
    pytest.importorskip("gtsam")
    from fgslam.io.synth import SynthSequence, write_sequence
    from fgslam.io.synth.scenarios import load_synth_config
    from fgslam.run.config import load_slam_config
    from fgslam.run.prepare import open_slam_dataset
    from fgslam.run.runner import run_slam

    root = tmp_path / "clip"
    write_sequence(SynthSequence(load_synth_config("room-loop", overrides=["frames=12", "camera.width=64",
                                                                            "camera.height=48"])), root)
    csv = root / "mav0" / "imu0" / "data.csv"
    lines = csv.read_text().splitlines()
    rows = [line.split(",") for line in lines[1:]]
    csv.write_text("\n".join([lines[0]] + [",".join(r[:4] + [repr(float(v) / GRAVITY) for v in r[4:]]) for r in rows]) + "\n")
    cfg = load_slam_config("patch_stereo_inertial", [])
    ds = open_slam_dataset(root, cfg)
    with pytest.raises(DataError, match="accelerometer is likely in g"):
        run_slam(ds, cfg, tmp_path / "out", progress=False)
    assert not (tmp_path / "out" / "summary.json").exists()


def test_inertial_state_in_the_summary_and_the_console_report():
    """summary.json ``inertial`` from the service's mapping, and its console line (not initialised, and
    initialised with a monocular scale and an input warning)."""
    from fgslam.commands.run import inertial_text
    from fgslam.run.results import inertial_summary

    assert inertial_summary(None) is None
    idle = inertial_summary({"initialized": False, "init_time": None, "scale": None, "gravity_W": None}, 100.0)
    assert idle["initialized"] is False and idle["init_after_s"] is None and idle["bias_gyro_norm"] is None
    assert inertial_text(idle) == "not initialised"
    state = {"initialized": True, "init_time": 102.5, "scale": 0.84, "gravity_W": [0.0, 6.0, 8.0],
             "bias_gyro": [0.003, 0.0, 0.004], "bias_accel": [0.0, 0.03, 0.04], "links": 7,
             "input_warnings": ["IMU rate 10.0 Hz ..."]}
    out = inertial_summary(state, 100.0)
    assert out["init_after_s"] == pytest.approx(2.5) and out["gravity_norm"] == pytest.approx(10.0)
    assert out["bias_gyro_norm"] == pytest.approx(0.005) and out["bias_accel_norm"] == pytest.approx(0.05)
    assert out["scale"] == 0.84 and out["links"] == 7
    assert inertial_text(out) == ("initialised 2.50 s after the first frame, scale 0.8400, |g| 10.000 m/s^2, "
                                  "bias |gyro| 0.0050 rad/s, |accel| 0.0500 m/s^2; input: IMU rate 10.0 Hz ...")


def test_imu_timestamps_1000x_too_large_say_which_unit(stream):
    imu, frames = stream
    epoch = 1000.0  # absolute times: a stream 1000x too large no longer overlaps the frames
    t = (imu.timestamps + epoch) * 1000.0  # the frames span 1e-3 of the IMU's time
    found = _checks(ImuSamples(t, imu.gyro, imu.accel), frames + epoch)
    message = next(f.message for f in found if f.check == "clock")
    assert "frames' timestamps likely in microseconds" in message and "x 1000" not in message


def test_a_rate_range_upside_down_is_a_config_error():
    from fgslam.core.errors import ConfigError
    from fgslam.run.config import load_slam_config

    with pytest.raises(ConfigError, match=r"min_rate_hz \(500\) must be <= max_rate_hz \(100\)"):
        load_slam_config("patch_euroc_stereo", ["imu.checks.min_rate_hz=500", "imu.checks.max_rate_hz=100"])
