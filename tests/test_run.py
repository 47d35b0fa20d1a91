"""The SLAM runner (fgslam.run), the frontend registry, the presets and ``fgslam run``.

Most tests drive the runner with a fake frontend that returns the ground truth in a different
world frame (and scale) plus noise, so the expected ATE and counts are known by construction.
"""

from __future__ import annotations

import json
import re
import shutil
import time
from pathlib import Path

import numpy as np
import pytest

from fgslam.backend import Backend, BackendConfig
from fgslam.core.config import load_config
from fgslam.core.errors import ConfigError, DataError, FGSlamError
from fgslam.frontends import make_frontend
from fgslam.frontends.base import FrameStatus, Frontend
from fgslam.io.synth import SynthSequence, write_sequence
from fgslam.io.synth.scenarios import load_synth_config
from fgslam.io.trajectory import read_trajectory
from fgslam.run.presets import configs_dir, resolve_preset
from fgslam.io.run_files import SUMMARY_FILE, TUM_FILE
from fgslam.run.config import SlamConfig, load_slam_config
from fgslam.run.files import KITTI_FILE, KITTI_TIMES_FILE, PLOT_FILE, PLY_FILE
from fgslam.run.prepare import check_sensor, open_slam_dataset
from fgslam.run.runner import NoPoseError, RunError, run_slam
from test_config import ISSUE9_OUT_OF_RANGE, ISSUE21_INFINITE, ISSUE21_TOO_LARGE

N_FRAMES = 16
REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def synth_root(tmp_path_factory) -> Path:
    """A tiny room-loop sequence (stereo, depth, exact ground truth)."""
    root = tmp_path_factory.mktemp("room") / "seq"
    cfg = load_synth_config("room-loop", None, [f"frames={N_FRAMES}", "camera.width=96", "camera.height=72"])
    write_sequence(SynthSequence(cfg), root)
    return root


def _random_sim3(rng: np.random.Generator, scale: float) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    S = np.eye(4)
    S[:3, :3] = scale * Rotation.from_rotvec(rng.normal(size=3)).as_matrix()
    S[:3, 3] = rng.normal(size=3)
    return S


class FakeFrontend(Frontend):
    """Ground truth mapped by a similarity ``S`` into its own world frame, plus position noise.

    No pose for the first ``init_frames`` frames (initialising); frames in ``fail_at`` report a
    motion-model pose; frame ``raise_at`` raises; every ``kf_every``-th frame is a keyframe.
    """

    name = "fake"

    def __init__(self, S: np.ndarray, noise: float, rng, init_frames=2, fail_at=(), raise_at=None,
                 kf_every=4, nan_at=(), points=False):
        self.S, self.noise, self.rng = S, noise, rng
        self.init_frames, self.fail_at, self.raise_at = init_frames, set(fail_at), raise_at
        self.kf_every, self.nan_at, self.points = kf_every, set(nan_at), points
        self.t: list[float] = []
        self.T: list[np.ndarray] = []
        self.src: list[str] = []
        self.kf = 0
        self.finished = False
        self.time_flow = 0.0

    def _map(self, T_WC_gt: np.ndarray) -> np.ndarray:
        s = np.cbrt(np.linalg.det(self.S[:3, :3]))
        T = np.eye(4)
        T[:3, :3] = self.S[:3, :3] / s @ T_WC_gt[:3, :3]
        T[:3, 3] = self.S[:3, :3] @ T_WC_gt[:3, 3] + self.S[:3, 3] + self.noise * self.rng.normal(size=3)
        return T

    def process(self, frame) -> FrameStatus:
        if frame.index == self.raise_at:
            raise RuntimeError("simulated frontend crash")
        self.time_flow += 0.001
        if frame.index < self.init_frames:
            return FrameStatus(frame.index, frame.timestamp, None, "initializing", events=["waiting: parallax"])
        T = self._map(frame.T_WC_gt)
        if frame.index in self.nan_at:
            T[0, 3] = np.nan
        source = "motion_model" if frame.index in self.fail_at else "tracked"
        is_kf = frame.index % self.kf_every == 0
        self.kf += is_kf
        self.t.append(frame.timestamp)
        self.T.append(T)
        self.src.append(source)
        events = ["tracking lost: 3 valid"] if source == "motion_model" else []
        return FrameStatus(frame.index, frame.timestamp, T, source, is_keyframe=is_kf, num_valid=50, events=events)

    def trajectory(self):
        return np.array(self.t), np.array(self.T).reshape(-1, 4, 4), list(self.src)

    def num_keyframes(self) -> int:
        return self.kf

    def finish(self) -> None:
        self.finished = True

    def stage_times(self) -> dict[str, float]:
        return {"flow": self.time_flow, "ba": 2 * self.time_flow}

    def keyframe_points(self):
        if not self.points:
            return None
        X = self.rng.normal(size=(20, 3))
        if self.points == "far":  # and one at a near-zero inverse depth, a million units away
            X = np.vstack([X, [1e6, 0.0, 0.0]])
        return X, np.full((len(X), 3), 200, dtype=np.uint8)


def _config(*overrides: str) -> SlamConfig:
    return load_config(SlamConfig, None, list(overrides))


def _run(synth_root, tmp_path, sensor="mono", frontend_kwargs=None, overrides=(), scale=0.5, noise=0.0):
    config = _config(f"sensor={sensor}", *overrides)
    ds = open_slam_dataset(synth_root, config)
    rng = np.random.default_rng(1)
    S = _random_sim3(rng, scale if sensor == "mono" else 1.0)
    fe = FakeFrontend(S, noise, rng, **(frontend_kwargs or {}))
    summary = run_slam(ds, config, tmp_path / "out", progress=True, frontend=fe, overwrite=True)  # reruns: on purpose
    return summary, fe, ds


# --------------------------------------------------------------------------------------- outputs


def test_summary_max_frame_time(synth_root, tmp_path):
    """``max_frame_s`` is the longest ``process()`` call: one frame that stalls tracking sets it."""
    stall_s, stall_at = 0.3, 6

    class Stalling(FakeFrontend):
        def process(self, frame):
            if frame.index == stall_at:
                time.sleep(stall_s)
            return super().process(frame)

    config = _config("sensor=mono")
    rng = np.random.default_rng(1)
    fe = Stalling(_random_sim3(rng, 0.5), 0.0, rng)
    summary = run_slam(open_slam_dataset(synth_root, config), config, tmp_path / "out", progress=False, frontend=fe)
    assert stall_s <= summary.max_frame_s <= summary.wall_s
    assert json.loads((tmp_path / "out" / SUMMARY_FILE).read_text())["max_frame_s"] == summary.max_frame_s


def test_outputs_exist_and_parse_back(synth_root, tmp_path):
    summary, fe, ds = _run(synth_root, tmp_path)
    out = tmp_path / "out"
    for name in (TUM_FILE, KITTI_FILE, KITTI_TIMES_FILE, SUMMARY_FILE, PLOT_FILE):
        assert (out / name).is_file(), name
    tum = read_trajectory(out / TUM_FILE, "tum")
    kitti = read_trajectory(out / KITTI_FILE, "kitti", out / KITTI_TIMES_FILE)
    t, T, _ = fe.trajectory()
    assert len(tum) == len(kitti) == N_FRAMES - 2
    np.testing.assert_allclose(tum.timestamps, t, atol=1e-9)
    np.testing.assert_allclose(kitti.timestamps, t, atol=1e-9)
    np.testing.assert_allclose(tum.T_WC, T, atol=1e-9)
    np.testing.assert_allclose(kitti.T_WC, T, atol=1e-9)
    assert fe.finished
    assert (out / PLOT_FILE).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_summary_fields_mono_sim3(synth_root, tmp_path):
    summary, fe, ds = _run(synth_root, tmp_path, frontend_kwargs={"fail_at": (5, 9), "kf_every": 4})
    data = json.loads((tmp_path / "out" / SUMMARY_FILE).read_text())
    assert data == json.loads(json.dumps(summary.to_dict()))
    assert data["frames_total"] == data["frames_read"] == data["frames_processed"] == N_FRAMES
    assert data["frames_with_pose"] == N_FRAMES - 2
    assert data["keyframes"] == len([i for i in range(2, N_FRAMES) if i % 4 == 0])
    assert data["failures"] == {"tracking": 2, "no_pose": 2, "skipped_corrupt": 0, "nonfinite_pose": 0}
    assert data["failure_frames"] == [5, 9]
    assert data["pose_sources"] == {"tracked": N_FRAMES - 4, "motion_model": 2}
    assert data["events"] == {"waiting": 2, "tracking lost": 2}
    assert data["stage_s"] == pytest.approx({"flow": 0.001 * N_FRAMES, "ba": 0.002 * N_FRAMES})
    assert data["stage_ms_per_frame"]["ba"] == pytest.approx(2.0)
    assert data["fps"] > 0 and data["fps_frontend"] >= data["fps"]
    assert 0 < data["max_frame_s"] <= data["wall_s"]  # the longest process() call
    assert data["peak_rss_mb"] > 0 and len(data["load_average"]) == 3 and data["cpu_s"] >= 0
    ev = data["evaluation"]
    assert ev["align"] == "sim3"
    assert ev["scale"] == pytest.approx(2.0, rel=1e-6)  # the fake map is at half scale
    assert ev["ate_rmse_m"] < 1e-6  # noise-free: exact after Sim(3) alignment
    gt_len = ds.groundtruth.subset(np.arange(2, N_FRAMES)).path_length()
    assert ev["gt_path_length_m"] == pytest.approx(gt_len, rel=1e-9)
    assert ev["n_matched"] == N_FRAMES - 2
    assert data["motion"]["path_length"] == pytest.approx(0.5 * gt_len, rel=1e-6)
    assert data["config"]["sensor"] == "mono" and data["config"]["frontend"] == "patch"
    assert data["error"] is None


def test_text_report(synth_root, tmp_path):
    from fgslam.commands.run import format_report

    summary, _, _ = _run(synth_root, tmp_path, frontend_kwargs={"fail_at": (4,)})
    text = format_report(summary.to_dict())
    for part in (f"{N_FRAMES} processed of {N_FRAMES}", f"{N_FRAMES - 2} with a pose", "frames/s",
                 "flow 1.0, ba 2.0 ms/frame", "1 tracking", "2 without pose", "sim3 alignment, scale 2.0000",
                 "% of the", str(tmp_path / "out")):
        assert part in text, part
    with pytest.raises(NoPoseError):
        _run(synth_root, tmp_path, frontend_kwargs={"init_frames": N_FRAMES})
    assert "never initialised" in format_report(json.loads((tmp_path / "out" / SUMMARY_FILE).read_text()))


def test_noise_gives_matching_ate(synth_root, tmp_path):
    summary, fe, ds = _run(synth_root, tmp_path, sensor="stereo", noise=0.01)
    ev = summary.evaluation
    assert ev["align"] == "se3" and ev["scale"] == 1.0
    # 3-D isotropic noise of 1 cm per axis -> RMSE ~ sqrt(3) cm (alignment absorbs a little)
    assert 0.008 < ev["ate_rmse_m"] < 0.025
    assert ev["ate_percent_of_path"] == pytest.approx(100 * ev["ate_rmse_m"] / ev["gt_path_length_m"])


def test_explicit_alignment_overrides_auto(synth_root, tmp_path):
    summary, _, _ = _run(synth_root, tmp_path, overrides=("auto_align=false", "eval.align=se3"))
    assert summary.evaluation["align"] == "se3"
    assert summary.evaluation["ate_rmse_m"] > 0.01  # half-scale map, no scale correction


def test_progress_lines(synth_root, tmp_path, caplog):
    caplog.set_level("INFO", logger="fgslam.run.runner")
    _run(synth_root, tmp_path, overrides=("log_interval_frames=5", "log_interval_s=1000"))
    lines = [r.getMessage() for r in caplog.records if r.name == "fgslam.run.runner" and "frames/s" in r.getMessage()]
    assert len(lines) == N_FRAMES // 5 + 1  # every 5 frames plus the final line
    assert lines[0].startswith(f"frame 5/{N_FRAMES}") and "ETA" in lines[0] and "keyframes" in lines[0]
    assert lines[-1].startswith(f"frame {N_FRAMES}/{N_FRAMES} (100%)")
    caplog.clear()
    config = _config("log_interval_frames=5")
    fe = FakeFrontend(np.eye(4), 0.0, np.random.default_rng(0))
    run_slam(open_slam_dataset(synth_root, config), config, tmp_path / "quiet", progress=False, frontend=fe)
    assert not [r for r in caplog.records if "frames/s" in r.getMessage()]


def test_nonfinite_pose_dropped_and_counted(synth_root, tmp_path):
    summary, _, _ = _run(synth_root, tmp_path, frontend_kwargs={"nan_at": (7,)})
    assert summary.failures["nonfinite_pose"] == 2  # the live pose and the final one
    assert summary.frames_with_pose == N_FRAMES - 3
    assert len(read_trajectory(tmp_path / "out" / TUM_FILE, "tum")) == N_FRAMES - 3


def test_ply_written_when_requested(synth_root, tmp_path):
    summary, _, _ = _run(synth_root, tmp_path, overrides=("output.write_ply=true",), frontend_kwargs={"points": True})
    data = (tmp_path / "out" / PLY_FILE).read_bytes()
    header, body = data.split(b"end_header\n", 1)
    assert b"element vertex 20" in header
    assert len(body) == 20 * (3 * 4 + 3)
    assert summary.outputs["ply"].endswith(PLY_FILE)


@pytest.mark.parametrize("factor, vertices", [(None, 20), ("0", 21)])
def test_the_runs_ply_leaves_out_far_points_unless_told_not_to(synth_root, tmp_path, factor, vertices):
    """points.ply drops a point a million units away by default (output.ply.max_point_range_factor, the
    export's rule); 0 keeps every point."""
    overrides = ("output.write_ply=true",) + (() if factor is None else (f"output.ply.max_point_range_factor={factor}",))
    _run(synth_root, tmp_path, overrides=overrides, frontend_kwargs={"points": "far"})
    header = (tmp_path / "out" / PLY_FILE).read_bytes().split(b"end_header\n", 1)[0]
    assert f"element vertex {vertices}\n".encode() in header


def test_never_initialised_writes_summary_without_trajectory_and_fails(synth_root, tmp_path):
    """No frame got a pose: the summary is written with the reason as its error, and the run fails."""
    with pytest.raises(NoPoseError) as info:
        _run(synth_root, tmp_path, frontend_kwargs={"init_frames": N_FRAMES + 1})
    out = tmp_path / "out"
    assert not (out / TUM_FILE).exists()
    data = json.loads((out / SUMMARY_FILE).read_text())
    assert data["frames_with_pose"] == 0 and data["failures"]["no_pose"] == N_FRAMES
    assert data["evaluation"] is None and data["motion"]["path_length"] == 0.0
    assert data["error"].startswith(f"no frame got a pose: frontend 'patch' (mono) never initialised in {N_FRAMES} "
                                    f"frames processed of {N_FRAMES} (events: waiting x{N_FRAMES})")
    assert str(info.value).startswith(data["error"])
    assert not any("exports no map" in n for n in data["notes"])  # no result: no note blaming the frontend


# --------------------------------------------------------------------------------------- errors


def test_frontend_raising_mid_run_leaves_partial_outputs(synth_root, tmp_path):
    with pytest.raises(RunError) as info:
        _run(synth_root, tmp_path, frontend_kwargs={"raise_at": 10})
    msg = str(info.value)
    assert "frame 10" in msg and "simulated frontend crash" in msg and "partial outputs" in msg
    assert isinstance(info.value.__cause__, RuntimeError)
    out = tmp_path / "out"
    traj = read_trajectory(out / TUM_FILE, "tum")
    assert len(traj) == 8  # frames 2..9
    data = json.loads((out / SUMMARY_FILE).read_text())
    assert "simulated frontend crash" in data["error"]
    assert data["frames_processed"] == 10 and data["frames_read"] == 11
    assert data["evaluation"]["n_matched"] == 8


def test_corrupt_frames_skipped_and_counted(synth_root, tmp_path):
    root = tmp_path / "seq"
    shutil.copytree(synth_root, root)
    images = sorted((root / "mav0" / "cam0" / "data").glob("*.png"))
    images[6].write_bytes(b"not a png")
    summary, _, ds = _run(root, tmp_path, frontend_kwargs={"fail_at": (3,)})
    assert summary.failures["skipped_corrupt"] == 1
    assert summary.skipped_frames[0]["index"] == 6
    assert summary.frames_read == summary.frames_processed == N_FRAMES - 1
    assert summary.frames_with_pose == N_FRAMES - 3


def test_dataset_failing_mid_run_leaves_partial_outputs(synth_root, tmp_path):
    root = tmp_path / "seq"
    shutil.copytree(synth_root, root)
    images = sorted((root / "mav0" / "cam0" / "data").glob("*.png"))
    for i in (8, 9):  # 2 of 16 corrupt: more than max_skipped_fraction = 0.1 allows
        images[i].write_bytes(b"")
    with pytest.raises(DataError, match=r"2 of the first 10 frames \(of 16\) skipped: 2 unreadable; more than allowed"):
        _run(root, tmp_path)
    data = json.loads((tmp_path / "out" / SUMMARY_FILE).read_text())
    assert "while reading the dataset" in data["error"]
    assert data["frames_processed"] == 8 and data["failures"]["skipped_corrupt"] == 2
    assert len(read_trajectory(tmp_path / "out" / TUM_FILE, "tum")) == 6


def test_sensor_validation(synth_root, tmp_path):
    # mono run: right images and depth are not even loaded
    ds = open_slam_dataset(synth_root, _config("sensor=mono"))
    assert not ds.has_stereo and not ds.has_depth
    with pytest.raises(ConfigError, match="sensor 'stereo' needs right camera images"):
        check_sensor(ds, "stereo")
    with pytest.raises(ConfigError, match="sensor 'rgbd' needs depth maps.*load_depth is false"):
        open_slam_dataset(synth_root, _config("sensor=rgbd", "dataset.load_depth=false"))
    assert open_slam_dataset(synth_root, _config("sensor=rgbd")).has_depth
    assert open_slam_dataset(synth_root, _config("sensor=stereo")).has_stereo


def test_sensor_validation_on_real_mono_dataset(shared_data, tmp_path):
    config = _config("sensor=rgbd", "dataset.end=3")
    with pytest.raises(ConfigError, match="sensor 'rgbd' needs depth maps.*has no depth maps"):
        open_slam_dataset(shared_data / "kitti00_0-199", config)
    with pytest.raises(ConfigError, match="stereo"):
        open_slam_dataset(shared_data / "7scenes_redkitchen_0-599", _config("sensor=stereo", "dataset.end=3"))
    with pytest.raises(ConfigError, match="needs depth"):  # run_slam checks too
        run_slam(open_slam_dataset(shared_data / "kitti00_0-199", _config("dataset.end=3")), config, tmp_path)


def test_bad_config_values():
    with pytest.raises(ConfigError, match="sensor"):
        _config("sensor=lidar")
    with pytest.raises(ConfigError, match="frontend"):
        _config("frontend=orbslam")
    with pytest.raises(ConfigError, match="threads"):
        _config("threads=-1")
    with pytest.raises(ConfigError, match="patch.ba.nonsense"):
        _config("patch.ba.nonsense=1")


# --------------------------------------------------------------------------------------- registry


def test_planned_frontends_say_not_implemented(synth_root, monkeypatch):
    """A family listed in the registry without a builder (planned) is refused with an error naming it;
    every family shipped today is implemented."""
    import fgslam.frontends as frontends

    assert all(f.implemented for f in frontends.FAMILIES)
    monkeypatch.setattr(frontends, "FAMILIES", frontends.FAMILIES + (frontends.FrontendFamily("sketch", "a sketched family"),))
    calib = open_slam_dataset(synth_root, _config()).calibration
    with pytest.raises(ConfigError, match="frontend 'sketch'.*not implemented yet.*issue"):
        make_frontend("sketch", None, calib, "mono", backend=Backend(BackendConfig()))


def test_unknown_frontend_name(synth_root):
    calib = open_slam_dataset(synth_root, _config()).calibration
    with pytest.raises(ConfigError, match="unknown frontend 'orb'"):
        make_frontend("orb", _config(), calib, "mono", backend=Backend(BackendConfig()))


def test_registry_import_is_lazy():
    import subprocess
    import sys

    code = "import sys, fgslam.frontends; print('fgslam.frontends.patch.frontend' in sys.modules, 'torch' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.split()
    assert out == ["False", "False"]


# --------------------------------------------------------------------------------------- presets


def _preset_files() -> list[Path]:
    return sorted((REPO / "fgslam" / "configs").glob("patch_*.yaml"))


def test_presets_exist():
    names = {p.stem for p in _preset_files()}
    for needed in ("patch_mono", "patch_stereo", "patch_rgbd", "patch_kitti_mono", "patch_7scenes_mono",
                   "patch_7scenes_rgbd", "patch_euroc_mono", "patch_euroc_stereo"):
        assert needed in names


@pytest.mark.parametrize("path", _preset_files(), ids=lambda p: p.stem)
def test_preset_loads(path):
    config = load_config(SlamConfig, path)
    assert config.frontend == "patch"
    expected = "stereo" if "stereo" in path.stem else "rgbd" if "rgbd" in path.stem else "mono"
    assert config.sensor == expected
    assert load_slam_config(path.stem) == config  # by preset name


def test_preset_resolution(tmp_path):
    assert resolve_preset("patch_kitti_mono") == REPO / "fgslam" / "configs" / "patch_kitti_mono.yaml"
    assert resolve_preset("patch_kitti_mono.yaml") == REPO / "fgslam" / "configs" / "patch_kitti_mono.yaml"
    own = tmp_path / "mine.yaml"
    own.write_text("sensor: stereo\n")
    assert load_slam_config(own).sensor == "stereo"
    with pytest.raises(ConfigError, match="no preset of that name.*patch_kitti_mono"):
        resolve_preset("patch_nonexistent")
    assert configs_dir() == REPO / "fgslam" / "configs"


def test_overrides_on_preset():
    config = load_slam_config("patch_kitti_mono", ["dataset.end=20", "patch.ba.iterations=3"])
    assert config.dataset.end == 20 and config.patch.ba.iterations == 3


# --------------------------------------------------------------------------------------- CLI


@pytest.fixture
def cli_main():
    """``fgslam.cli.main``."""
    from fgslam import cli

    return cli.main


def test_cli_run_errors_are_clear(synth_root, tmp_path, capsys, cli_main):
    main = cli_main
    rc = main(["run", "patch_nonexistent", "--data", str(synth_root), "--out", str(tmp_path / "o")])
    assert rc == 2 and "no preset of that name" in capsys.readouterr().err
    rc = main(["run", "patch_mono", "--data", str(synth_root), "--out", str(tmp_path / "o"), "-o", "frontend=orb"])
    assert rc == 2 and "key 'frontend': must be one of" in capsys.readouterr().err
    rc = main(["run", "patch_mono", "--data", str(tmp_path / "missing"), "--out", str(tmp_path / "o")])
    assert rc == 2 and "no such file" in capsys.readouterr().err


@pytest.fixture(scope="module")
def small_root(tmp_path_factory) -> Path:
    """A short room-loop sequence large enough for the real patch frontend."""
    return _render_seq(tmp_path_factory, "small", ["frames=20", "camera.width=128", "camera.height=96"])


def test_cli_run_with_patch_frontend(small_root, tmp_path, capsys, cli_main):
    """``fgslam run`` end to end with the real patch frontend (RGB-D: metric, SE(3) evaluation)."""
    out = tmp_path / "run"
    rc = cli_main(["run", "patch_rgbd", "--data", str(small_root), "--out", str(out), "--json",
                   "-o", "log_interval_frames=5"])
    assert rc == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary == json.loads((out / SUMMARY_FILE).read_text())
    assert summary["frames_processed"] == 20 and summary["frames_with_pose"] == 20
    assert summary["sensor"] == "rgbd" and summary["error"] is None
    assert 1 <= summary["keyframes"] <= 20
    assert set(summary["stage_ms_per_frame"]) >= {"flow", "ba"}
    traj = read_trajectory(out / TUM_FILE, "tum")
    assert len(traj) == 20
    ev = summary["evaluation"]
    assert ev["align"] == "se3" and ev["n_matched"] == 20
    assert ev["ate_rmse_m"] < 0.05  # 0.29 m of hand-held motion; a broken frontend is far off
    assert (out / PLOT_FILE).is_file()


def test_cli_run_selects_frames_with_start_end_and_stride_as_localize_does(synth_root, tmp_path, capsys, cli_main,
                                                                           monkeypatch):
    """``fgslam run --start/--end/--stride``: the dataset.start/end/stride keys (over an -o of the same key),
    defined once for run and localize (same help); a live capture still refuses --start."""
    import fgslam.run.runner as runner
    from fgslam.cli import build_parser

    prepared = []
    monkeypatch.setattr(runner, "run_prepared", lambda run, **kwargs: prepared.append(run))
    base = ["run", "patch_mono", "--data", str(synth_root), "--no-progress"]
    assert cli_main(base + ["--out", str(tmp_path / "a"), "--start", "2", "--end", "14", "--stride", "3",
                            "-o", "dataset.end=5"]) == 0
    ds = prepared[0].dataset
    assert (ds.config.start, ds.config.end, ds.config.stride) == (2, 14, 3)
    assert len(ds) == 4 and ds.timestamps[0] == ds.raw_timestamps[2]
    assert cli_main(base + ["--out", str(tmp_path / "b"), "-o", "dataset.end=5"]) == 0
    assert len(prepared[1].dataset) == 5  # without the options: the config's selection
    helps = {}
    for command in ("run", "localize"):
        sub = next(a for a in build_parser()._actions if a.dest == "command").choices[command]
        helps[command] = {a.dest: (a.help, a.metavar, a.default) for a in sub._actions if a.dest in ("start", "end", "stride")}
    assert helps["run"] == helps["localize"] and len(helps["run"]) == 3
    assert cli_main(["run", "patch_mono", "--data", "camera:0", "--out", str(tmp_path / "c"), "--start", "3"]) == 2
    assert "dataset.start and dataset.stride do not apply to a live capture" in capsys.readouterr().err


def test_run_error_is_fgslam_error():
    assert issubclass(RunError, FGSlamError)
    assert issubclass(DataError, FGSlamError)


# --------------------------------------------------------------------------------------- stopping (SIGTERM, SIGINT)


class SignallingFrontend(FakeFrontend):
    """A FakeFrontend that sends ``signum`` to its own process while processing frame ``signal_at``
    and records the SIGTERM handler in force during the run."""

    def __init__(self, *args, signal_at=None, signum=None, **kwargs):
        super().__init__(*args, **kwargs)
        self.signal_at, self.signum = signal_at, signum
        self.handler_during_run = None

    def process(self, frame):
        import os
        import signal

        self.handler_during_run = signal.getsignal(signal.SIGTERM)
        if frame.index == self.signal_at:
            os.kill(os.getpid(), self.signum)
        return super().process(frame)


def test_sigterm_mid_run_writes_partial_outputs_and_restores_the_handler(synth_root, tmp_path):
    import signal

    from fgslam.core.errors import Interrupted

    config = _config("sensor=stereo")
    fe = SignallingFrontend(np.eye(4), 0.0, np.random.default_rng(0), signal_at=7, signum=signal.SIGTERM)
    before = signal.getsignal(signal.SIGTERM)
    reported = []
    with pytest.raises(Interrupted) as info:
        run_slam(open_slam_dataset(synth_root, config), config, tmp_path / "out", frontend=fe, on_summary=reported.append)
    assert info.value.exit_code == 143 and info.value.signum == signal.SIGTERM
    assert "SIGTERM" in str(info.value) and "frame 7" in str(info.value) and "(7 of 16 frames processed" in str(info.value)
    assert signal.getsignal(signal.SIGTERM) is before  # restored
    assert fe.handler_during_run is not before  # installed for the run only
    data = json.loads((tmp_path / "out" / SUMMARY_FILE).read_text())
    assert data["interrupted"] == "SIGTERM" and data["error"].startswith("interrupted by SIGTERM at frame 7")
    assert data["frames_processed"] == 7 and not fe.finished
    assert len(read_trajectory(tmp_path / "out" / TUM_FILE, "tum")) == 5  # frames 2..6
    assert (tmp_path / "out" / PLOT_FILE).is_file()
    assert len(reported) == 1 and reported[0].interrupted == "SIGTERM"


def test_sigint_mid_run_keeps_exit_code_130(synth_root, tmp_path):
    import signal

    from fgslam.core.errors import Interrupted

    config = _config()
    fe = SignallingFrontend(np.eye(4), 0.0, np.random.default_rng(0), signal_at=9, signum=signal.SIGINT)
    with pytest.raises(Interrupted) as info:
        run_slam(open_slam_dataset(synth_root, config), config, tmp_path / "out", frontend=fe)
    assert info.value.exit_code == 130 and isinstance(info.value, KeyboardInterrupt)
    data = json.loads((tmp_path / "out" / SUMMARY_FILE).read_text())
    assert data["interrupted"] == "SIGINT" and data["frames_processed"] == 9
    assert len(read_trajectory(tmp_path / "out" / TUM_FILE, "tum")) == 7


class InitialisingFrontend(SignallingFrontend):
    """A monocular-like frontend: no pose for the first ``init_frames`` frames when they are processed,
    then, once it initialises, poses for them too in its trajectory (as the patch frontend poses the
    frames its initialisation buffered)."""

    def process(self, frame):
        status = super().process(frame)
        if frame.index < self.init_frames:
            self.t.append(frame.timestamp)
            self.T.append(self._map(frame.T_WC_gt))
            self.src.append("tracked")
        return status

    def trajectory(self):
        order = np.argsort(self.t)
        return np.array(self.t)[order], np.array(self.T).reshape(-1, 4, 4)[order], [self.src[k] for k in order]


@pytest.mark.parametrize("stop", ["SIGINT", "frontend error"])
def test_a_stopped_mono_run_keeps_the_frames_posed_at_initialisation(stop, synth_root, tmp_path):
    """An interrupted or failed monocular run: the frames posed once the map initialised (after they were
    processed) are in the partial trajectory, and summary.json counts them as posed."""
    import signal

    from fgslam.core.errors import Interrupted

    config = _config("sensor=mono")
    stop_at = 7
    kwargs = {"signal_at": stop_at, "signum": signal.SIGINT} if stop == "SIGINT" else {"raise_at": stop_at}
    fe = InitialisingFrontend(np.eye(4), 0.0, np.random.default_rng(0), **kwargs)
    with pytest.raises(Interrupted if stop == "SIGINT" else RunError):
        run_slam(open_slam_dataset(synth_root, config), config, tmp_path / "out", frontend=fe, progress=False)
    data = json.loads((tmp_path / "out" / SUMMARY_FILE).read_text())
    traj = read_trajectory(tmp_path / "out" / TUM_FILE, "tum")
    ds = open_slam_dataset(synth_root, config)
    np.testing.assert_allclose(traj.timestamps, ds.timestamps[:stop_at], atol=1e-6)  # frames 0..6, 0 and 1 included
    assert data["frames_processed"] == data["frames_with_pose"] == len(traj) == stop_at
    assert data["failures"]["no_pose"] == 0
    assert data["evaluation"]["n_matched"] == stop_at


class ReroundingFrontend(InitialisingFrontend):
    """An InitialisingFrontend whose trajectory hands the frames posed at initialisation back with their
    timestamps a little off (``shift`` s: a frontend's own rounding of the time it was given)."""

    shift = 3e-7

    def trajectory(self):
        t, T, src = super().trajectory()
        return t + np.where(np.arange(len(t)) < self.init_frames, self.shift, 0.0), T, src


def test_a_stopped_run_matches_the_frames_posed_later_by_nearby_timestamps(synth_root, tmp_path):
    """The frames posed at initialisation are matched by timestamp within a fraction of a microsecond,
    on epoch-time stamps: taken once each (none missed as unequal, no other frame taken twice)."""
    config = _config("sensor=mono")
    stop_at = 7
    fe = ReroundingFrontend(np.eye(4), 0.0, np.random.default_rng(0), raise_at=stop_at)
    ds = open_slam_dataset(synth_root, config)
    assert ds.timestamps[0] > 1e6  # epoch-like times: a tolerance relative to the stamp would span minutes
    with pytest.raises(RunError):
        run_slam(ds, config, tmp_path / "out", frontend=fe, progress=False)
    traj = read_trajectory(tmp_path / "out" / TUM_FILE, "tum")
    np.testing.assert_allclose(traj.timestamps, ds.timestamps[:stop_at], rtol=0, atol=1e-6)
    assert json.loads((tmp_path / "out" / SUMMARY_FILE).read_text())["frames_with_pose"] == len(traj) == stop_at


class BrokenTrajectoryFrontend(FakeFrontend):
    """A FakeFrontend whose final ``trajectory()`` raises; counts the calls."""

    calls = 0

    def trajectory(self):
        self.calls += 1
        raise RuntimeError("simulated trajectory failure")


def test_a_failing_final_trajectory_is_asked_once_and_the_live_estimates_are_written(synth_root, tmp_path):
    """A run that ends but whose frontend cannot give its final trajectory: the live estimates are written,
    and the frontend is not asked again (for the frames without a live pose) for what just failed."""
    config = _config("sensor=mono")
    fe = BrokenTrajectoryFrontend(np.eye(4), 0.0, np.random.default_rng(0), init_frames=2)
    with pytest.raises(RunError, match=r"in trajectory\(\): RuntimeError: simulated trajectory failure"):
        run_slam(open_slam_dataset(synth_root, config), config, tmp_path / "out", frontend=fe, progress=False)
    assert fe.calls == 1
    data = json.loads((tmp_path / "out" / SUMMARY_FILE).read_text())
    assert data["frames_with_pose"] == N_FRAMES - 2 == len(read_trajectory(tmp_path / "out" / TUM_FILE, "tum"))
    assert any("live per-frame estimates" in note for note in data["notes"])
    assert not any("could not be taken from the frontend" in note for note in data["notes"])


def test_importing_fgslam_installs_no_signal_handler():
    import subprocess
    import sys

    code = ("import signal; before = signal.getsignal(signal.SIGTERM); import fgslam.run.runner, fgslam.cli; "
            "print(signal.getsignal(signal.SIGTERM) is before)")
    assert subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.strip() == "True"


@pytest.fixture(scope="module")
def long_root(tmp_path_factory) -> Path:
    """A room-loop sequence long enough that a run is still going when the test signals it."""
    return _render_seq(tmp_path_factory, "long", ["frames=120", "camera.width=96", "camera.height=72"])


def _render_seq(tmp_path_factory, name: str, overrides: list[str]) -> Path:
    """A room-loop sequence (``load_synth_config`` overrides) in ``<fresh temp folder>/seq``."""
    root = tmp_path_factory.mktemp(name) / "seq"
    write_sequence(SynthSequence(load_synth_config("room-loop", None, overrides)), root)
    return root


def _signalled_run(cmd: list[str], signals: list[int], at_line: str = "frame 4/120"):
    """Run ``cmd`` in a subprocess and send it ``signals`` (``SECOND_SIGINT_AFTER_S`` apart) once its
    stderr shows ``at_line``; returns (exit status, stdout, stderr lines)."""
    import signal
    import subprocess
    import threading

    # default dispositions in the child, as from a terminal (a background job of a non-interactive shell ignores SIGINT)
    defaults = lambda: [signal.signal(s, signal.SIG_DFL) for s in (signal.SIGINT, signal.SIGTERM)]  # noqa: E731
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, preexec_fn=defaults)
    watchdog = threading.Timer(300, proc.kill)  # a hung run fails the test instead of blocking it
    watchdog.start()
    try:
        stderr_lines = []
        for line in proc.stderr:
            stderr_lines.append(line)
            if at_line in line:
                for k, sig in enumerate(signals):
                    if k:
                        time.sleep(SECOND_SIGINT_AFTER_S)
                    proc.send_signal(sig)
                break
        stdout, rest = proc.communicate()
    finally:
        watchdog.cancel()
    return proc.returncode, stdout, stderr_lines + rest.splitlines(keepends=True)


@pytest.mark.parametrize("signame, rc", [("SIGTERM", 143), ("SIGINT", 130)])
def test_cli_run_killed_mid_run(long_root, tmp_path, signame, rc):
    """``fgslam run`` in a subprocess gets the signal after a few frames: partial trajectory,
    summary.json naming the signal, the console report, one clean error line, exit 128 + signal."""
    import signal
    import sys

    out = tmp_path / "out"
    cmd = [sys.executable, "-m", "fgslam", "run", "patch_rgbd", "--data", str(long_root), "--out", str(out),
           "-o", "log_interval_frames=1"]
    returncode, stdout, stderr_lines = _signalled_run(cmd, [getattr(signal, signame)])
    assert returncode == rc, "".join(stderr_lines[-5:])
    errors = [ln for ln in stderr_lines if ln.startswith("fgslam:")]
    assert len(errors) == 1 and re.match(rf"fgslam: interrupted by {signame} (at frame|after frame|while reading the dataset)", errors[0])
    assert "Traceback" not in "".join(stderr_lines)
    data = json.loads((out / SUMMARY_FILE).read_text())
    assert data["interrupted"] == signame and 4 <= data["frames_processed"] < 120
    traj = read_trajectory(out / TUM_FILE, "tum")
    assert 4 <= len(traj) == data["frames_with_pose"] < 120
    assert f"interrupted by {signame}" in stdout and "outputs:" in stdout  # the console report still comes


SLOW_PLOT_S = 3.0  # the plot takes this long in the next test: the second Ctrl-C surely lands while it is written
SECOND_SIGINT_AFTER_S = 0.3  # the trial's two Ctrl-C


def test_cli_run_two_ctrl_c_lose_nothing(long_root, tmp_path):
    """Two SIGINTs 0.3 s apart: the second, while the outputs are written, is logged and ignored;
    summary.json, the plot and the console report are all there; exit 130 with one line."""
    import signal
    import sys

    out = tmp_path / "out"
    slow_plot = (  # the child's plot takes SLOW_PLOT_S: the writing of the outputs is under way at the second signal
        "import sys, time\n"
        "import fgslam.io.plot as plot\n"
        "draw = plot.plot_trajectories\n"
        f"plot.plot_trajectories = lambda *a, **k: (time.sleep({SLOW_PLOT_S}), draw(*a, **k))[1]\n"
        "from fgslam.cli import main\n"
        "sys.exit(main(sys.argv[1:]))\n")
    cmd = [sys.executable, "-c", slow_plot, "run", "patch_rgbd", "--data", str(long_root), "--out", str(out),
           "-o", "log_interval_frames=1"]
    returncode, stdout, stderr_lines = _signalled_run(cmd, [signal.SIGINT, signal.SIGINT])
    err = "".join(stderr_lines)
    assert (out / SUMMARY_FILE).is_file() and (out / PLOT_FILE).is_file() and (out / TUM_FILE).is_file(), err[-3000:]
    data = json.loads((out / SUMMARY_FILE).read_text())
    assert data["interrupted"] == "SIGINT" and 4 <= data["frames_processed"] < 120
    assert "interrupted by SIGINT" in stdout and "outputs:" in stdout  # the console report
    assert returncode == 130, err[-3000:]
    assert "Traceback" not in err
    assert "stopping: writing outputs, please wait" in err
    errors = [ln for ln in err.splitlines() if ln.startswith("fgslam:")]
    assert len(errors) == 1 and errors[0].startswith("fgslam: interrupted by SIGINT"), errors


# --------------------------------------------------------------------------------------- outputs are never lost


def _cli_run(cli_main, data, out, *extra, preset="patch_mono"):
    return cli_main(["run", preset, "--data", str(data), "--out", str(out), *extra])


def _one_error_line(err: str) -> str:
    """The single ``fgslam: ...`` line of a failed command's stderr (log lines may precede it), which must be the last."""
    lines = err.splitlines()
    errors = [ln for ln in lines if ln.startswith("fgslam:")]
    assert len(errors) == 1 and lines[-1] == errors[0], err
    assert errors[0].startswith("fgslam: error: "), err
    return errors[0]


def test_failing_plot_leaves_every_other_output(synth_root, tmp_path, monkeypatch):
    import fgslam.io.plot
    from fgslam.run.runner import OutputError

    def broken_plot(*args, **kwargs):
        raise RuntimeError("matplotlib backend exploded")

    monkeypatch.setattr(fgslam.io.plot, "plot_trajectories", broken_plot)
    reported = []
    config = _config("output.write_ply=true")
    fe = FakeFrontend(np.eye(4), 0.0, np.random.default_rng(0), points=True)
    with pytest.raises(OutputError, match=r"plot.*matplotlib backend exploded"):
        run_slam(open_slam_dataset(synth_root, config), config, tmp_path / "out", frontend=fe, on_summary=reported.append)
    out = tmp_path / "out"
    for name in (TUM_FILE, KITTI_FILE, KITTI_TIMES_FILE, PLY_FILE, SUMMARY_FILE):
        assert (out / name).is_file(), name
    assert not (out / PLOT_FILE).exists()
    data = json.loads((out / SUMMARY_FILE).read_text())
    assert "matplotlib backend exploded" in data["output_errors"]["plot"] and "plot" not in data["outputs"]
    assert data["error"] is None and data["evaluation"]["n_matched"] == N_FRAMES - 2
    assert reported and reported[0].output_errors == data["output_errors"]


def _full_disk(path: Path) -> None:
    """Make writes to ``path`` fail with ENOSPC: a symlink to /dev/full."""
    if not Path("/dev/full").exists():
        pytest.skip("no /dev/full on this system")
    path.symlink_to("/dev/full")


def test_full_disk_on_one_trajectory_leaves_the_others(synth_root, tmp_path):
    from fgslam.run.runner import OutputError

    out = tmp_path / "out"
    out.mkdir()
    _full_disk(out / TUM_FILE)
    config = _config()
    fe = FakeFrontend(np.eye(4), 0.0, np.random.default_rng(0))
    with pytest.raises(OutputError, match=r"tum.*No space left on device"):
        run_slam(open_slam_dataset(synth_root, config), config, out, frontend=fe)
    assert not (out / TUM_FILE).exists() and not (out / TUM_FILE).is_symlink()  # no truncated file left
    assert len(read_trajectory(out / KITTI_FILE, "kitti", out / KITTI_TIMES_FILE)) == N_FRAMES - 2
    assert (out / PLOT_FILE).is_file()
    data = json.loads((out / SUMMARY_FILE).read_text())
    assert "No space left on device" in data["output_errors"]["tum"] and "tum" not in data["outputs"]


def test_full_disk_on_the_summary_still_reports_on_the_console(synth_root, tmp_path, capsys, cli_main):
    out = tmp_path / "out"
    out.mkdir()
    _full_disk(out / (SUMMARY_FILE + ".tmp"))  # the summary is written to a temporary file, then renamed
    rc = _cli_run(cli_main, synth_root, out, "-o", "dataset.end=4", preset="patch_rgbd")
    captured = capsys.readouterr()
    assert rc == 2
    err = _one_error_line(captured.err)
    assert "summary" in err and "No space left on device" in err
    assert "not written: summary" in captured.out and "4 processed of 4" in captured.out  # the report still comes
    assert not (out / SUMMARY_FILE).exists() and not (out / (SUMMARY_FILE + ".tmp")).exists()
    assert len(read_trajectory(out / TUM_FILE, "tum")) == 4 and (out / PLOT_FILE).is_file()


def test_output_folder_checked_before_any_work(synth_root, tmp_path, capsys, cli_main, monkeypatch):
    import fgslam.run.prepare

    def no_work(*args, **kwargs):
        raise AssertionError("the dataset was opened before the output folder was checked")

    monkeypatch.setattr(fgslam.run.prepare, "open_slam_dataset", no_work)
    blocker = tmp_path / "a_file"
    blocker.write_text("not a folder")
    for out in (blocker / "out", blocker):  # under a regular file; a regular file
        rc = _cli_run(cli_main, synth_root, out)
        err = capsys.readouterr().err
        assert rc == 2 and "cannot create the output folder" in _one_error_line(err) and str(out) in err

    def unwritable(*args, **kwargs):
        raise PermissionError(13, "Permission denied")

    monkeypatch.setattr(fgslam.run.prepare.tempfile, "mkstemp", unwritable)
    rc = _cli_run(cli_main, synth_root, tmp_path / "ro")
    err = capsys.readouterr().err
    assert rc == 2 and "not writable: Permission denied" in _one_error_line(err)


def test_output_folder_inside_the_dataset_is_refused(synth_root, tmp_path, capsys, cli_main):
    data = tmp_path / "seq"
    shutil.copytree(synth_root, data)
    before = sorted(p.relative_to(data) for p in data.rglob("*"))
    for out, why in ((data, "is the dataset folder"), (data / "mav0" / "results", "is inside the dataset folder"),
                     (tmp_path / "seq" / ".." / "seq" / "out", "is inside the dataset folder")):
        rc = _cli_run(cli_main, data, out)
        err = capsys.readouterr().err
        assert rc == 2 and why in _one_error_line(err), err
    assert sorted(p.relative_to(data) for p in data.rglob("*")) == before  # nothing written into the data
    with pytest.raises(ConfigError, match="inside the dataset folder"):  # the library checks too
        config = _config()
        run_slam(open_slam_dataset(data, config), config, data / "out", frontend=FakeFrontend(np.eye(4), 0.0, None))


# --------------------------------------------------------------------------------------- config ranges on the command line


@pytest.mark.parametrize("override, key", ISSUE9_OUT_OF_RANGE)
def test_cli_rejects_out_of_range_values_before_any_work(override, key, synth_root, tmp_path, capsys, cli_main):
    out = tmp_path / "out"
    rc = _cli_run(cli_main, synth_root, out, "-o", override)
    err = capsys.readouterr().err
    assert rc == 2
    err = _one_error_line(err)
    assert f"key '{key}': must be" in err
    assert not out.exists()  # refused before the output folder was even made


@pytest.mark.parametrize("override, key", ISSUE21_INFINITE + ISSUE21_TOO_LARGE)
def test_cli_refuses_infinite_and_huge_values_at_once(override, key, synth_root, tmp_path, capsys, cli_main):
    """Issue 21: .inf ran to a garbage trajectory with exit 0; resize_width=100000 grew to 24 GB,
    patches_per_frame=100000000 to 6.7 GB, pointmap.image_width=100000 posted no frame: each is now
    one error line naming the key, exit 2, before the output folder is made."""
    out = tmp_path / "out"
    preset = "pointmap_mono" if key.startswith("pointmap.") else "dense_mono" if key.startswith("dense.") else "patch_mono"
    start = time.perf_counter()
    rc = _cli_run(cli_main, synth_root, out, "-o", override, preset=preset)
    err = capsys.readouterr().err
    assert rc == 2
    assert f"key '{key}': must be" in _one_error_line(err)
    assert time.perf_counter() - start < 10 and not out.exists()


def test_cli_refuses_a_run_whose_memory_estimate_exceeds_the_limit(synth_root, tmp_path, capsys, cli_main, monkeypatch):
    """Sizes each inside its range whose product is not (4096 patches x 200 frames x 199 edges each):
    refused from the estimate (fgslam/run/memory.py) before any frame, naming the keys and the GiB."""
    from fgslam.frontends.patch.frontend import PatchFrontend

    processed = []
    monkeypatch.setattr(PatchFrontend, "process", lambda self, frame: processed.append(frame.index))
    out = tmp_path / "out"
    rc = _cli_run(cli_main, synth_root, out, "-o", "patch.graph.patches_per_frame=4096",
                  "-o", "patch.graph.removal_window=200", "-o", "patch.graph.patch_lifetime=199")
    err = _one_error_line(capsys.readouterr().err)
    assert rc == 2 and processed == [] and not (out / SUMMARY_FILE).exists()
    assert re.search(r"estimated peak memory [\d.]+ GiB exceeds max_memory_gib=16 \(largest part: patch graph edges", err)
    assert "patch.graph.patches_per_frame=4096" in err
    # the limit is a config field: the same sizes fit a larger one
    sizes = ("patch.graph.patches_per_frame=4096", "patch.graph.removal_window=200", "patch.graph.patch_lifetime=199")
    with pytest.raises(ConfigError, match="exceeds max_memory_gib=16"):
        open_slam_dataset(synth_root, _config(*sizes))
    assert len(open_slam_dataset(synth_root, _config(*sizes, "max_memory_gib=1024"))) == N_FRAMES


def test_a_refused_run_leaves_no_output_folder_behind(synth_root, tmp_path, capsys, cli_main, monkeypatch):
    """Missing data, an empty selection, a memory refusal, a frontend that cannot be built: the output folder
    the refused run created is gone; a folder that existed stays, with its files. The parents it created stay
    too: parallel runs (a batch's cells of one config) share them, and removing one could pull it from under
    a run that is creating its own folder there."""
    from fgslam.run.system import SlamSystem

    new = tmp_path / "new" / "deeper" / "out"
    parent = new.parent
    refusals = {
        "missing data": ((tmp_path / "nope",), "no such file or folder"),
        "empty selection": ((synth_root, "--start", "100"), "empty selection"),
        "memory": ((synth_root, "-o", "patch.graph.patches_per_frame=4096", "-o", "patch.graph.removal_window=200",
                    "-o", "patch.graph.patch_lifetime=199"), "exceeds max_memory_gib"),
    }
    for why, ((data, *extra), message) in refusals.items():
        assert _cli_run(cli_main, data, new, *extra) == 2, why
        assert message in _one_error_line(capsys.readouterr().err), why
        assert not new.exists() and parent.is_dir() and not any(parent.iterdir()), why
    kept = tmp_path / "kept"
    kept.mkdir()
    assert _cli_run(cli_main, tmp_path / "nope", kept) == 2
    assert kept.is_dir()  # the user's (empty) folder stays
    (kept / "notes.txt").write_text("mine")
    assert _cli_run(cli_main, synth_root, kept, "--start", "100") == 2
    assert [p.name for p in kept.iterdir()] == ["notes.txt"]
    capsys.readouterr()

    def cannot_build(*args, **kwargs):
        raise ConfigError("frontend 'patch' is not available (simulated)")

    monkeypatch.setattr(SlamSystem, "build", cannot_build)
    assert _cli_run(cli_main, synth_root, new) == 2
    assert "not available (simulated)" in _one_error_line(capsys.readouterr().err)
    assert not new.exists() and parent.is_dir()


def test_cli_rejects_a_border_larger_than_the_image(synth_root, tmp_path, capsys, cli_main, monkeypatch):
    from fgslam.frontends.patch.frontend import PatchFrontend

    processed = []
    monkeypatch.setattr(PatchFrontend, "process", lambda self, frame: processed.append(frame.index))
    rc = _cli_run(cli_main, synth_root, tmp_path / "out", "-o", "patch.graph.border=5000")
    err = capsys.readouterr().err
    assert rc == 2
    err = _one_error_line(err)
    assert "patch.graph.border=5000" in err and "96x72" in err
    assert processed == [] and not (tmp_path / "out" / SUMMARY_FILE).exists()
    # a border that leaves room is accepted (the largest one: 2 * 35 < 72)
    calib = open_slam_dataset(synth_root, _config()).calibration
    PatchFrontend(_config("patch.graph.border=35").patch, calib, backend=Backend(BackendConfig()))
    with pytest.raises(ConfigError, match=r"patch.graph.border=36 .*96x72"):
        PatchFrontend(_config("patch.graph.border=36").patch, calib, backend=Backend(BackendConfig()))


def test_resized_images_keep_a_minimum_size(synth_root, tmp_path, capsys, cli_main):
    rc = _cli_run(cli_main, synth_root, tmp_path / "out", "-o", "dataset.resize_scale=0.25")
    err = capsys.readouterr().err
    assert rc == 2
    err = _one_error_line(err)
    assert "dataset.resize_scale=0.25 gives 24x18 images from 96x72;" in err and "dataset.min_image_side=32" in err
    config = _config("dataset.resize_scale=0.25", "dataset.min_image_side=16")  # the minimum is a config field
    assert open_slam_dataset(synth_root, config).calibration.width == 24
    with pytest.raises(ConfigError, match="dataset.resize_width=40, dataset.resize_height=24 gives 40x24"):
        open_slam_dataset(synth_root, _config("dataset.resize_width=40", "dataset.resize_height=24"))
