"""Factor plugins (fgslam/services/plugins.py): loading by dotted path with errors naming the config
key, option validation, the positions file reader's errors, factors on unknown keys, and the two
built-in plugins on synthetic drives fed keyframe by keyframe into a backend by a drifting odometry."""


import gtsam
import numpy as np
import pytest
import yaml

from fgslam.backend.config import BackendConfig
from fgslam.backend.graph import Backend
from fgslam.services.plugins import (
    PlanarMotion,
    PositionPrior,
    attach_plugins,
    build_plugin,
    build_plugins,
    finish_plugins,
    load_plugin_class,
)
from fgslam.core.config import load_config
from fgslam.core.errors import ConfigError, DataError, FormatError, OptimizationError
from fgslam.frontends.base import Frontend
from fgslam.core.geometry import umeyama
from fgslam.io.positions import read_positions
from fgslam.run.config import SlamConfig

from plugin_support import (DriftingOdometry, NoContributor, ate_se3, drive, path_length, plugin_system, run_drive,
                            write_positions)

POSITION_PRIOR = "fgslam.services.plugins:PositionPrior"
PLANAR = "fgslam.services.plugins:PlanarMotion"


def make_backend(solver: str = "lm"):
    return Backend(BackendConfig(solver=solver))


class UnknownKeyPlugin:
    """A user plugin that puts a prior on a keyframe the backend does not hold."""

    def __init__(self, options, key):
        self.key = key
        self.kf = int(options.get("kf", 99))

    def attach(self, backend):
        backend.on_keyframe(self._on_keyframe)
        self.backend = backend

    def _on_keyframe(self, kf_id, timestamp, key):
        factor = gtsam.PriorFactorSimilarity3(gtsam.symbol("x", self.kf), gtsam.Similarity3(),
                                              gtsam.noiseModel.Isotropic.Sigma(7, 1.0))
        self.backend.add_factor(factor, owner=self.key)


class NoAttach:
    def __init__(self, options, key):
        pass


# ----------------------------------------------------------------------------------------- loading errors


@pytest.mark.parametrize("spec, message", [
    ("fgslam.services.plugins.PositionPrior", "expected 'package.module:ClassName'"),
    (42, "expected 'package.module:ClassName'"),
    ("no_such_package.factors:Thing", "module 'no_such_package.factors' does not import: ModuleNotFoundError"),
    ("fgslam.services.plugins:NoSuchClass", "module 'fgslam.services.plugins' has no class 'NoSuchClass'"),
    ("fgslam.backend.plugins:PositionPrior", "moved to 'fgslam.services.plugins'"),
    ("fgslam.services.plugins:FACTORS_KEY", "is not a class"),
    ("test_plugins:NoAttach", "lacks the method attach(backend)"),
])
def test_plugin_class_errors_name_the_config_key(spec, message):
    with pytest.raises(ConfigError) as info:
        build_plugins([{"class": POSITION_PRIOR, "options": {"file": "p.txt"}}, {"class": spec}])
    assert str(info.value).startswith("factors[1].class: ")
    assert message in str(info.value)


def test_plugin_entry_shape_errors():
    with pytest.raises(ConfigError, match=r"factors\[0\]: unknown key 'factors\[0\].option'"):
        build_plugin({"class": PLANAR, "option": {}}, 0)
    with pytest.raises(ConfigError, match=r"factors\[2\].class: missing"):
        build_plugin({"options": {}}, 2)
    with pytest.raises(ConfigError, match=r"factors\[0\].options: expected a mapping"):
        build_plugin({"class": PLANAR, "options": [1, 2]}, 0)
    assert load_plugin_class(PLANAR, "factors[0]") is PlanarMotion


@pytest.mark.parametrize("entry, message", [
    ({"class": POSITION_PRIOR, "options": {}}, "factors[0].options.file: missing"),
    ({"class": POSITION_PRIOR, "options": {"file": "p.txt", "sigma": 0}}, "key 'factors[0].options.sigma': must be > 0"),
    ({"class": POSITION_PRIOR, "options": {"file": "p.txt", "sigma": [1.0, 2.0]}}, "factors[0].options.sigma: expected one sigma or a list of three"),
    ({"class": POSITION_PRIOR, "options": {"file": "p.txt", "sigma": [1.0, -2.0, 1.0]}}, "key 'factors[0].options.sigma': must be > 0"),
    ({"class": POSITION_PRIOR, "options": {"file": "p.txt", "max_dt": -1}}, "key 'factors[0].options.max_dt': must be > 0"),
    ({"class": POSITION_PRIOR, "options": {"file": "p.txt", "sigmaa": 1}}, "unknown key 'factors[0].options.sigmaa'"),
    ({"class": PLANAR, "options": {"up_axis": [0, 0, 0]}}, "factors[0].options.up_axis: up axis must be a non-zero"),
    ({"class": PLANAR, "options": {"tilt_sigma": "small"}}, "key 'factors[0].options.tilt_sigma': expected a number"),
])
def test_plugin_options_errors_name_the_option(entry, message):
    with pytest.raises(ConfigError) as info:
        build_plugins([entry])
    assert message in str(info.value)


def test_slam_config_factors_section_loads_and_reports_the_key(tmp_path):
    good = tmp_path / "patch_gps.yaml"
    good.write_text(yaml.safe_dump({"factors": [{"class": POSITION_PRIOR, "options": {"file": "gps.txt", "sigma": 2.0}},
                                                {"class": PLANAR, "options": {"height_sigma": 0.1}}]}))
    config = load_config(SlamConfig, good)
    assert [f["class"] for f in config.factors] == [POSITION_PRIOR, PLANAR]
    plugins = build_plugins(config.factors)
    assert plugins[0].options.sigma == 2.0 and plugins[1].options.height_sigma == 0.1
    assert [p.key for p in plugins] == ["factors[0]", "factors[1]"]
    bad = tmp_path / "patch_bad.yaml"
    bad.write_text(yaml.safe_dump({"factors": [{"class": PLANAR}, {"class": "fgslam.nothing:X"}]}))
    with pytest.raises(ConfigError) as info:
        load_config(SlamConfig, bad)
    assert str(bad) in str(info.value) and "factors[1].class: module 'fgslam.nothing' does not import" in str(info.value)
    with pytest.raises(ConfigError, match=r"factors\[0\].options.height_sigma"):
        load_config(SlamConfig, good, ["factors=[{class: " + PLANAR + ", options: {height_sigma: 0}}]"])


def test_shipped_plugin_examples_load():
    from fgslam.run.presets import load_preset_file, resolve_preset

    for name in ("patch_mono_gps", "patch_mono_planar"):
        config = load_preset_file(resolve_preset(name))
        assert config.factors and all(isinstance(p, (PositionPrior, PlanarMotion)) for p in build_plugins(config.factors))


def test_factors_need_a_frontend_that_feeds_a_backend():
    class NoBackend(Frontend):
        name = "toy"

        def process(self, frame):
            return frame

        def trajectory(self):
            return np.zeros(0), np.zeros((0, 4, 4)), []

        def num_keyframes(self) -> int:
            return 0

    from fgslam.run.config import SlamConfig
    from fgslam.run.system import SlamSystem

    config = SlamConfig()
    assert SlamSystem.build(config, None, frontend=NoBackend()).plugins is None
    config.factors = [{"class": PLANAR}]
    with pytest.raises(ConfigError, match="factors: frontend 'toy' feeds no backend"):
        SlamSystem.build(config, None, frontend=NoBackend())


def test_plugins_poll_after_each_frame_and_corrections_reach_the_frontend(tmp_path):
    """The run's system: the alignment happens at a poll after a frame (not inside add_keyframe), and the
    uniform correction reaches the contributor (its scale folded into its measurements)."""
    t, T_true, _, _ = drive("street-loop", seconds=40.0, keyframe_dt=0.3)
    gps = write_positions(tmp_path / "gps.txt", t, T_true, 1.0, 1.0, np.random.default_rng(0))
    odometry = DriftingOdometry(make_backend(), t, T_true, np.random.default_rng(1), first_pose=np.eye(4),
                                initial_scale=0.3)
    seen = []
    odometry.apply_correction = lambda c, f=odometry.apply_correction: (seen.append(c), f(c))
    system = plugin_system(odometry, [{"class": POSITION_PRIOR, "options": {"file": str(gps), "max_dt": 0.2,
                                                                             "correct_every": 0}}], timestamps=t)
    plugin = system.plugins.plugins[0]
    for k in range(len(t)):
        system.step(k)
        if plugin.aligned:
            break
    assert plugin.aligned and len(seen) == 2  # the alignment, then a pose-graph correction
    uniform = seen[0]
    assert len({round(s, 12) for s in uniform.scale.values()}) == 1 and 2.5 < uniform.scale[0] < 4.0
    assert uniform.fold_scale and odometry.log_scale == pytest.approx(np.log(0.3 * uniform.scale[k] * seen[1].scale[k]))
    assert len(odometry.backend.factor_handles("factors[0]")) == len(plugin._matched)


# ----------------------------------------------------------------------------------------- positions file


def test_read_positions(tmp_path):
    path = tmp_path / "p.txt"
    path.write_text("# t x y z\n\n0.0 1 2 3\n1.0, 4, 5, 6\n2.5 7 8 9\n")
    track = read_positions(path)
    assert len(track) == 3 and track.lines == (3, 4, 5)
    np.testing.assert_allclose(track.p[1], [4, 5, 6])
    np.testing.assert_allclose(track.interpolate(0.5), [2.5, 3.5, 4.5])
    np.testing.assert_allclose(track.interpolate(-1.0), [1, 2, 3])


@pytest.mark.parametrize("text, error, message", [
    ("0 0 0 0\n1 1 1 1\n0.5 2 2 2\n", DataError, ":3: time 0.5 is not after the previous one (1.0 on line 2)"),
    ("0 0 0 0\n1 1 1 1\n1 2 2 2\n", DataError, ":3: time 1.0 is not after the previous one"),
    ("0 0 0 0\n1 nan 1 1\n", FormatError, ":2: non-finite value"),
    ("0 0 0 0\n1 1 1\n", FormatError, ":2: expected 4 numbers 't x y z', got 3"),
    ("0 0 0 0\n1 1 one 1\n", FormatError, ":2: not a number"),
    ("# only a comment\n", FormatError, "no positions found"),
])
def test_positions_file_errors_name_file_and_line(tmp_path, text, error, message):
    path = tmp_path / "gps.txt"
    path.write_text(text)
    with pytest.raises(error) as info:
        read_positions(path)
    assert str(info.value).startswith(str(path)) and message in str(info.value)


def test_position_prior_refuses_a_file_that_does_not_overlap_the_run(tmp_path):
    path = tmp_path / "gps.txt"
    path.write_text("# header\n100 0 0 0\n101 1 0 0\n102 2 0 0\n")
    plugin = build_plugin({"class": POSITION_PRIOR, "options": {"file": str(path)}}, 0)
    with pytest.raises(DataError) as info:
        attach_plugins([plugin], make_backend(), timestamps=np.arange(0.0, 10.0, 0.1))
    assert f"{path}:2-4: position times 100.000000 (line 2) to 102.000000 (line 4) do not overlap" in str(info.value)
    # the same file with a time offset onto the run's clock is accepted
    shifted = build_plugin({"class": POSITION_PRIOR, "options": {"file": str(path), "time_offset": -95.0}}, 0)
    attach_plugins([shifted], make_backend(), timestamps=np.arange(0.0, 10.0, 0.1))
    missing = build_plugin({"class": POSITION_PRIOR, "options": {"file": str(tmp_path / "none.txt")}}, 0)
    with pytest.raises(DataError, match="none.txt: positions file not found"):
        attach_plugins([missing], make_backend())


# ----------------------------------------------------------------------------------------- unknown keys


def test_a_plugin_factor_on_an_unknown_key_is_an_optimization_error_naming_it():
    backend = make_backend()
    plugins = build_plugins([{"class": "test_plugins:UnknownKeyPlugin", "options": {"kf": 12}}])
    attach_plugins(plugins, backend)
    with pytest.raises(OptimizationError, match=r"\bx12\b"):
        backend.add_keyframe(0, np.eye(4), 0.0)


# ----------------------------------------------------------------------------------------- PositionPrior


def test_position_samples_go_to_the_nearest_keyframe_within_max_dt(tmp_path):
    """Samples at 1 Hz, keyframes every 0.3 s with gaps: each sample is matched once, to the keyframe
    nearest in time, its position interpolated there; samples farther than max_dt from every keyframe
    are dropped; when the backend drops a keyframe, its sample goes to the nearest remaining one."""
    path = tmp_path / "gps.txt"
    path.write_text("".join(f"{t:.1f} {10 * t:.3f} 0 0\n" for t in range(7)))
    plugin = build_plugin({"class": POSITION_PRIOR, "options": {"file": str(path), "max_dt": 0.15,
                                                                  "min_samples": 50}}, 0)
    backend = make_backend()
    attach_plugins([plugin], backend, timestamps=np.arange(0, 7.0, 0.3))
    times = [0.0, 0.3, 0.6, 0.9, 1.2, 1.5, 2.4, 2.7, 3.0, 3.3, 5.1, 5.9, 6.2]  # nothing near 2.0 and 4.0
    for k, t in enumerate(times):
        T = np.eye(4)
        T[0, 3] = 10 * t
        backend.add_keyframe(k, T, t)

    def matched():
        return {times[k]: p for k, (dt, p, j) in plugin._matched.items()}

    plugin.poll(backend)
    assert sorted(matched()) == [0.0, 0.9, 3.0, 5.1, 5.9]
    np.testing.assert_allclose(matched()[0.9], [9.0, 0, 0])  # interpolated at the keyframe's time
    backend.remove_keyframe(3)  # 0.9 s: sample 1 s would go to 1.2 s, 0.2 s away: dropped
    backend.remove_keyframe(8)  # 3.0 s: sample 3 s would go to 3.3 s: dropped
    plugin.poll(backend)  # the safe point re-matches
    assert sorted(matched()) == [0.0, 5.1, 5.9]
    plugin.options.max_dt = 0.25
    backend.remove_keyframe(11)  # 5.9 s: sample 6 s goes to 6.2 s
    finish_plugins([plugin], backend)
    assert sorted(matched()) == [0.0, 5.1, 6.2]
    np.testing.assert_allclose(matched()[6.2], [60.0, 0, 0])  # past the last sample: the last one
    assert not plugin.aligned  # min_samples not reached: no alignment, no factors
    assert backend.factor_handles("factors[0]") == []


def run_position_drive(tmp_path, preset, use_plugin, seed=0, scale_drift=0.02, contributor=True, solver="lm", **options):
    """Monocular-like odometry (own frame, 0.3 map units per metre, log-scale random walk) along a
    synthetic drive, with or without 1 Hz positions of 1 m noise. Returns (estimate, truth, plugin)."""
    t, T_true, _, _ = drive(preset, keyframe_dt=0.3)
    gps = write_positions(tmp_path / f"gps_{preset}.txt", t, T_true, 1.0, 1.0, np.random.default_rng(seed))
    odometry = DriftingOdometry(make_backend(solver), t, T_true, np.random.default_rng(seed + 1), scale_drift=scale_drift,
                                first_pose=np.eye(4), initial_scale=0.3)
    factors = [{"class": POSITION_PRIOR, "options": {"file": str(gps), "sigma": 1.0, "max_dt": 0.2, **options}}]
    system = plugin_system(odometry if contributor else NoContributor(odometry), factors if use_plugin else [],
                           timestamps=t)
    est = run_drive(system, len(t))
    return est, T_true, (system.plugins.plugins[0] if use_plugin else None)


@pytest.mark.parametrize("preset, contributor, solver", [("street-loop", True, "lm"), ("highway", True, "lm"),
                                                         ("street-loop", False, "lm"), ("street-loop", True, "isam2")])
def test_position_prior_pins_scale_and_drift_of_a_monocular_drive(tmp_path, preset, contributor, solver):
    """Issue 11 target: SE(3)-aligned ATE with no scale alignment <= 1 % of the path, with corrections
    folded by the contributor or (no contributor) applied to the Sim(3) poses with their scales, with
    either of the backend's solvers (map.solver lm / isam2). The
    same odometry without the plugin stays in its own scale (0.3 units per metre, drifting): far off."""
    est, T_true, plugin = run_position_drive(tmp_path, preset, use_plugin=True, contributor=contributor, solver=solver)
    scales = np.cbrt(np.linalg.det(est[:, :3, :3]))
    if contributor:  # folded: every keyframe keeps scale 1
        np.testing.assert_allclose(scales, 1.0, atol=0.05)
    else:  # the map's 0.3 units per metre are in the keyframe scales
        assert np.all(scales > 2.5)
    length = path_length(T_true)
    ate = ate_se3(est, T_true)
    assert plugin.aligned and plugin.corrections >= 2
    assert ate <= 0.01 * length, f"ATE {ate:.2f} m over {length:.0f} m"
    # the map is in the positions' frame: even without any alignment the error is small
    raw = float(np.sqrt(np.mean(np.sum((est[:, :3, 3] - T_true[:, :3, 3]) ** 2, axis=1))))
    assert raw <= 0.01 * length
    est_free, _, _ = run_position_drive(tmp_path, preset, use_plugin=False)
    assert ate_se3(est_free, T_true) > 0.05 * length


# ----------------------------------------------------------------------------------------- PlanarMotion


def planar_errors(est: np.ndarray, T_true: np.ndarray, up_C: np.ndarray) -> tuple[float, float]:
    """RMS error of the camera height above the ground and of the tilt of its up axis (rad), after
    the best rigid alignment of the estimate onto the truth (a map's tilt is a gauge without gravity)."""
    a = umeyama(est[:, :3, 3], T_true[:, :3, 3], with_scale=False)
    height = est[:, :3, 3] @ a.R.T[:, 2] + a.t[2] - T_true[:, 2, 3]
    R = a.R @ (est[:, :3, :3] / np.cbrt(np.linalg.det(est[:, :3, :3]))[:, None, None])
    tilt = np.linalg.norm(R @ up_C - T_true[:, :3, :3] @ up_C, axis=1)
    return float(np.sqrt(np.mean(height ** 2))), float(np.sqrt(np.mean(tilt ** 2)))


def test_planar_motion_brings_height_and_tilt_errors_to_noise_level():
    """A ground vehicle (street-loop, 334 keyframes, 606 m) with noisy odometry (3 mrad and 2 % per
    keyframe, no scale drift): without the constraint the height and tilt wander (random walk);
    with it they stay at the level of the odometry's noise per keyframe and the vehicle's own
    bounce and wobble (true height 8 mm rms about its mean, tilt 7 mrad)."""
    t, T_true, up_C, height_true = drive("street-loop", keyframe_dt=0.3)
    step_noise = 0.02 * float(np.median(np.linalg.norm(np.diff(T_true[:, :3, 3], axis=0), axis=1)))
    wobble = float(np.sqrt(np.mean(np.sum((T_true[:, :3, :3] @ up_C - np.array([0, 0, 1.0])) ** 2, axis=1))))
    results = {}
    for use in (False, True):
        odometry = DriftingOdometry(make_backend(), t, T_true, np.random.default_rng(1), rot_sigma=0.003,
                                    trans_sigma=0.02)
        factors = [{"class": PLANAR, "options": {"up_axis": up_C.tolist(), "height_sigma": 0.05, "tilt_sigma": 0.01}}]
        est = run_drive(plugin_system(odometry, factors if use else []), len(t))
        results[use] = planar_errors(est, T_true, up_C)
    (h_free, tilt_free), (h_planar, tilt_planar) = results[False], results[True]
    assert h_free > 10 * step_noise and tilt_free > 2 * wobble  # the odometry alone drifts
    assert h_planar <= step_noise, (h_planar, step_noise)
    assert tilt_planar <= wobble, (tilt_planar, wobble)
    assert h_planar < 0.1 * h_free and tilt_planar < 0.5 * tilt_free


# ----------------------------------------------------------------------------------------- through run_slam


def test_run_with_position_prior_preset_on_a_synthetic_street_drive(tmp_path):
    """The runner's wiring: the patch_mono_gps preset's factors section (file in tmp_path) on a written
    synthetic street clip (20 s, 120 m; tiny images: the frontend uses only its ground truth), a
    frontend feeding a backend with monocular-like drifting odometry, 1 Hz positions with 1 m noise on
    the dataset's clock. The summary's SE(3) ATE (no scale) is <= 1 % of the path; a file whose times
    miss the run is refused before the first frame, naming the file."""
    from fgslam.io.synth import SynthSequence
    from fgslam.io.synth.scenarios import load_synth_config
    from fgslam.io.synth.writer import write_sequence
    from fgslam.run.presets import load_preset_file
    from fgslam.run.prepare import open_slam_dataset
    from fgslam.run.runner import run_slam

    from plugin_support import OdometryFrontend

    cfg = load_synth_config("street-loop", None, ["frames=201", "camera.width=32", "camera.height=32"])
    write_sequence(SynthSequence(cfg), tmp_path / "street")
    base = load_preset_file("patch_mono_gps")
    config = load_preset_file("patch_mono_gps", ["dataset.crop_multiple=1", "output.plot=false"])
    dataset = open_slam_dataset(tmp_path / "street", config)
    gt = dataset.groundtruth
    gps = write_positions(tmp_path / "gps.txt", gt.timestamps, gt.T_WC, 1.0, 1.0, np.random.default_rng(0))
    config.factors = [dict(base.factors[0], options=dict(base.factors[0]["options"], file=str(gps), max_dt=0.05))]

    def frontend():
        # every frame a keyframe (0.1 s): the drift rate of the 0.3 s keyframes above, 0.02 * sqrt(1 / 3)
        return OdometryFrontend(Backend(), gt.timestamps, gt.T_WC, np.random.default_rng(1), scale_drift=0.0115,
                                first_pose=np.eye(4), initial_scale=0.3)

    summary = run_slam(dataset, config, tmp_path / "out", progress=False, frontend=frontend())
    ev = summary.evaluation
    assert ev["align"] == "se3" and summary.frames_with_pose == 201
    assert ev["ate_percent_of_path"] <= 1.0, ev["ate_percent_of_path"]
    assert ev["scale"] == 1.0

    late = tmp_path / "late.txt"
    late.write_text("".join(f"{gt.timestamps[-1] + 10 + i:.3f} 0 0 0\n" for i in range(5)))
    config.factors = [{"class": POSITION_PRIOR, "options": {"file": str(late)}}]
    with pytest.raises(DataError, match=r"late.txt:1-5: position times .* do not overlap the run's frames"):
        run_slam(dataset, config, tmp_path / "out2", progress=False, frontend=frontend())


def test_position_prior_and_planar_motion_together(tmp_path):
    """Both plugins on one backend: the alignment and the pose-graph corrections of the positions move
    the whole map, and the planar factors' plane (held in a reference keyframe's coordinates) moves
    with it, so the two agree: ATE <= 1 % of the path without scale, heights at the odometry's noise."""
    t, T_true, up_C, _ = drive("street-loop", keyframe_dt=0.3)
    gps = write_positions(tmp_path / "gps.txt", t, T_true, 1.0, 1.0, np.random.default_rng(0))
    odometry = DriftingOdometry(make_backend(), t, T_true, np.random.default_rng(1), scale_drift=0.02,
                                first_pose=np.eye(4), initial_scale=0.3)
    factors = [{"class": POSITION_PRIOR, "options": {"file": str(gps), "max_dt": 0.2}},
               {"class": PLANAR, "options": {"up_axis": up_C.tolist(), "height_sigma": 0.05, "tilt_sigma": 0.01}}]
    system = plugin_system(odometry, factors, timestamps=t)
    est = run_drive(system, len(t))
    position, planar = system.plugins.plugins
    assert position.aligned and planar.rebuilds >= 1
    assert ate_se3(est, T_true) <= 0.01 * path_length(T_true)
    height, tilt = planar_errors(est, T_true, up_C)
    step_noise = 0.02 * float(np.median(np.linalg.norm(np.diff(T_true[:, :3, 3], axis=0), axis=1)))
    assert height <= 2 * step_noise, height
