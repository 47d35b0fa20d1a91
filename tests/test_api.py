"""The public Python API (``import fgslam``): the same bytes as ``fgslam run`` on the shared clips in every
sensor mode, its errors, and what it reports per frame."""

import subprocess
import sys

import numpy as np
import pytest

import fgslam
from fgslam.cli import main as cli_main
from fgslam.core.errors import ConfigError, DataError
from fgslam.io.trajectory import write_trajectory

SEVEN_SCENES = "7scenes_redkitchen_0-599"
KITTI = "kitti00_0-199"
EUROC = "euroc_v101_micro"

# (clip, preset, frames): one per sensor mode; enough frames that every run initialises and makes keyframes
MODES = {
    "rgbd": (SEVEN_SCENES, "handheld_rgbd", 40),
    "mono": (KITTI, "driving_mono", 40),
    "stereo": (EUROC, "patch_euroc_stereo", 30),
    "inertial": (EUROC, "patch_euroc_stereo_inertial", 30),
}


def api_run(data, preset, frames):
    """The clip through the API, frame by frame (its IMU samples through add_imu); the final trajectory."""
    overrides = {"dataset.end": frames}
    dataset = fgslam.open_dataset(data, preset, overrides=overrides)
    results = []
    with fgslam.Slam.from_preset(preset, dataset.camera, overrides=overrides, imu_noise=dataset.imu_noise,
                                 has_imu=dataset.has_imu) as slam:
        for frame in dataset:
            if frame.imu is not None:
                for t, gyro, accel in zip(frame.imu.timestamps, frame.imu.gyro, frame.imu.accel):
                    slam.add_imu(t, accel, gyro)
            results.append(slam.track(frame.image, frame.timestamp, depth=frame.depth, right=frame.image_right))
    return slam, slam.finish(), results


@pytest.mark.parametrize("mode", sorted(MODES))
def test_the_api_gives_the_bytes_of_fgslam_run(mode, shared_data, tmp_path, capsys):
    clip, preset, frames = MODES[mode]
    data = shared_data / clip
    assert cli_main(["run", preset, "--data", str(data), "--out", str(tmp_path / "cli"), "--no-progress",
                     "-o", f"dataset.end={frames}"]) == 0
    slam, trajectory, results = api_run(data, preset, frames)
    write_trajectory(tmp_path / "api_tum.txt", trajectory, "tum")
    cli_bytes = (tmp_path / "cli" / "trajectory_tum.txt").read_bytes()
    assert (tmp_path / "api_tum.txt").read_bytes() == cli_bytes
    # and the run did something: poses for most frames, keyframes, a trajectory that moved (not a stationary copy)
    assert len(trajectory) >= frames // 2 and len(slam.keyframes()) >= 2
    assert [r.index for r in results] == list(range(frames))
    assert all(r.status in ("initializing", "tracked", "motion_model", "relocalized", "imu") for r in results)
    assert all((r.T_WC is None) == (r.reason is not None and r.status == "initializing") for r in results
               if r.status in ("initializing", "tracked"))
    positions = trajectory.T_WC[:, :3, 3]
    assert np.linalg.norm(positions - positions[0], axis=1).max() > 0


def test_track_checks_its_input_and_the_camera(shared_data):
    camera = fgslam.Camera(fx=585.0, fy=585.0, cx=320.0, cy=240.0, width=640, height=480)
    slam = fgslam.Slam.from_preset("handheld_mono", camera, overrides={"loop_closure.mode": "off"})
    grey = np.zeros((480, 640), np.uint8)
    with pytest.raises(DataError, match=r"image size 320x240 does not match the calibration \(640x480\)"):
        slam.track(np.zeros((240, 320), np.uint8), 0.0)
    with pytest.raises(DataError, match="uint8"):
        slam.track(grey.astype(np.float32), 0.0)
    first = slam.track(np.zeros((480, 640, 3), np.uint8), 0.0)  # colour (BGR) is taken too
    assert first.T_WC is None and first.status == "initializing" and first.reason.startswith("initialising")
    with pytest.raises(DataError, match="not after the previous frame"):
        slam.track(grey, 0.0)
    with pytest.raises(ConfigError, match="no IMU service"):
        slam.add_imu(0.5, [0.0, 0.0, 9.81], [0.0, 0.0, 0.0])
    slam.abort()
    with pytest.raises(ConfigError, match="finished"):
        slam.track(grey, 1.0)
    with pytest.raises(ConfigError, match="aborted"):
        slam.finish()
    assert len(slam.trajectory()) == 0  # the per-frame estimates: none while initialising
    with pytest.raises(ConfigError, match="stereo camera"):
        fgslam.Slam.from_preset("handheld_stereo", camera)
    with pytest.raises(ConfigError, match="no_such_preset"):
        fgslam.Slam.from_preset("no_such_preset", camera)
    with pytest.raises(ConfigError, match="patch.no_such_key"):
        fgslam.Slam.from_preset("handheld_mono", camera, overrides={"patch.no_such_key": 1})
    with pytest.raises(DataError, match="principal point"):
        fgslam.Slam.from_preset("handheld_mono", fgslam.Camera(500.0, 500.0, 900.0, 240.0, 640, 480))


def test_a_distorted_camera_is_undistorted_as_a_loader_does():
    # the camera's lens model goes through the loaders' undistortion: the system's camera has no distortion
    camera = fgslam.Camera(500.0, 500.0, 320.0, 240.0, 640, 480, distortion=(-0.2, 0.05, 0.0, 0.0))
    slam = fgslam.Slam.from_preset("handheld_mono", camera)
    assert slam.calibration.distortion_model == "none" and slam.calibration.size == (640, 480)
    assert not np.allclose(slam.calibration.K, [500.0, 500.0, 320.0, 240.0])  # the undistorted camera's own
    stereo = fgslam.Camera(500.0, 500.0, 320.0, 240.0, 640, 480, baseline=0.1)
    calib = stereo.calibration()
    assert calib.right is not None and calib.baseline == pytest.approx(0.1)
    slam.abort()


def test_importing_fgslam_is_light_and_lists_its_public_names():
    code = ("import sys, fgslam; assert 'torch' not in sys.modules and 'cv2' not in sys.modules; "
            "print(sorted(fgslam.__all__))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    names = eval(out.stdout)  # noqa: S307 - our own printed list
    assert {"Slam", "Camera", "TrackResult", "open_dataset", "LiveFrames"} <= set(names)
    for name in names:
        assert getattr(fgslam, name).__doc__, name
    with pytest.raises(AttributeError, match="no attribute 'Nope'"):
        fgslam.Nope  # noqa: B018


def test_localising_with_the_api_gives_the_bytes_of_fgslam_localize(shared_data, tmp_path, capsys):
    data = shared_data / SEVEN_SCENES
    map_path = tmp_path / "kitchen.map"
    assert cli_main(["run", "handheld_rgbd", "--data", str(data), "--out", str(tmp_path / "run"), "--no-progress",
                     "-o", "dataset.end=60", "--save-map", str(map_path)]) == 0
    assert cli_main(["localize", str(map_path), "--data", str(data), "--out", str(tmp_path / "loc"),  # the API's
                     "--start", "0", "--end", "60", "--stride", "5", "-o", "odometry.enabled=false"]) == 0  # localiser alone
    localizer = fgslam.Slam.localize_in(map_path)
    dataset = fgslam.open_dataset(data, "handheld_rgbd", overrides={"dataset.end": 60, "dataset.stride": 5})
    results = [localizer.track(frame.image, frame.timestamp) for frame in dataset]
    found = [r for r in results if r.T_WC is not None]
    assert len(found) >= len(results) // 2 and len(localizer.keyframes()) >= 2
    assert all(r.keyframe_id is not None and r.position_std is not None for r in found)
    trajectory = fgslam.Trajectory(np.array([r.t for r in found]), np.stack([r.T_WC for r in found]))
    write_trajectory(tmp_path / "api_tum.txt", trajectory, "tum")
    cli_file = next((tmp_path / "loc").glob("*tum*.txt"))
    assert (tmp_path / "api_tum.txt").read_bytes() == cli_file.read_bytes()


def test_the_kept_frames_of_a_stored_map_are_the_keyframes_and_the_newest(monkeypatch):
    from fgslam.io.calibration import Calibration
    from fgslam.io.frame import Frame
    from fgslam.run.session import KEPT_RECENT_FRAMES, _KeptFrames

    calib = Calibration(8, 8, [8.0, 8.0, 4.0, 4.0])
    keyframe_times = {0.0, 5.0, 13.0}
    kept = _KeptFrames(calib, lambda: keyframe_times)
    image = np.zeros((8, 8), np.uint8)
    n = 3 * KEPT_RECENT_FRAMES
    for i in range(n):
        image[:] = i % 256  # one buffer, reused by the caller: the kept frames hold copies
        kept.add(Frame(i, i, float(i), image, calib))
    times = kept.timestamps
    newest = np.arange(n - KEPT_RECENT_FRAMES, n, dtype=float)
    assert np.array_equal(times, np.concatenate([sorted(keyframe_times), newest]))
    assert [int(kept[k].image[0, 0]) for k in kept.indices()] == [int(t) % 256 for t in times]


def test_the_frame_where_a_lost_run_starts_a_new_map_says_so(shared_data):
    """Frames 20-23 black (image and depth): the run loses its track and, after
    ``max_motion_model_frames`` (2 here) failures, starts a new map; that frame's result says so
    (``new_map``), and no other frame's does."""
    preset, frames = "handheld_rgbd", 40
    overrides = {"dataset.end": frames, "patch.tracking.max_motion_model_frames": 2}
    dataset = fgslam.open_dataset(shared_data / SEVEN_SCENES, preset, overrides={"dataset.end": frames})
    results = []
    with fgslam.Slam.from_preset(preset, dataset.camera, overrides=overrides) as slam:
        for frame in dataset:
            black = 20 <= frame.index < 24
            results.append(slam.track(np.zeros_like(frame.image) if black else frame.image, frame.timestamp,
                                      depth=np.zeros_like(frame.depth) if black else frame.depth))
    restarts = [r.index for r in results if r.new_map]
    assert len(restarts) == 1 and 20 <= restarts[0] < 24
    assert restarts == [r.index for r in results if "re-initialising" in r.events]
