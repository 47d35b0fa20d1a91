"""The five recommended presets, one per sensor class (issue 23, item 5): ``handheld_rgbd``,
``handheld_mono``, ``handheld_stereo``, ``driving_mono``, ``driving_stereo``. Each loads into the run
config through its sensor-class prefix, validates, has the sensor mode its name says, is listed by
``fgslam run --help`` and in the README's first table, and a short real run of each on data of its
class beats doing nothing (a stationary estimate) clearly."""

import json
import re

import numpy as np
import pytest

from fgslam.cli import main
from fgslam.core.config import check_ranges
from fgslam.core.errors import ConfigError
from fgslam.run.presets import SENSOR_CLASSES, config_class_for, configs_dir, load_preset_file, run_presets
from fgslam.run.config import SlamConfig, load_slam_config

#: preset -> the sensor mode its name says
SENSOR_PRESETS = {
    "handheld_rgbd": "rgbd",
    "handheld_mono": "mono",
    "handheld_stereo": "stereo",
    "driving_mono": "mono",
    "driving_stereo": "stereo",
}

#: a short run must reach at most this share of the stationary estimate's ATE ("clearly better than
#: doing nothing"; measured: 0.004-0.08, the hand-held 2-s clips the largest)
MAX_SHARE_OF_STATIONARY = 0.2


@pytest.mark.parametrize("name", SENSOR_PRESETS)
def test_sensor_class_preset_loads_validates_and_has_its_sensor_mode(name):
    path = configs_dir() / f"{name}.yaml"
    assert path.is_file()
    assert config_class_for(path) is SlamConfig  # the sensor-class prefix selects the run config
    config = load_preset_file(name)
    assert isinstance(config, SlamConfig)
    check_ranges(config, source=name)
    config.validate()
    assert config.sensor == SENSOR_PRESETS[name]
    assert load_slam_config(name) == config  # `fgslam run NAME` loads the same
    assert path.read_text().splitlines()[0].startswith("# description: RECOMMENDED for ")


def test_every_sensor_class_preset_is_one_of_the_five():
    """No sixth preset of a sensor class slips in untested, and each class prefix is used."""
    shipped = sorted(n for n in run_presets() if n.split("_", 1)[0] in SENSOR_CLASSES)
    assert shipped == sorted(SENSOR_PRESETS)


def test_run_help_lists_the_sensor_class_presets_first_with_their_description(capsys):
    with pytest.raises(SystemExit):
        main(["run", "--help"])
    help_text = capsys.readouterr().out
    presets = run_presets()
    listed = re.findall(r"^  (\S+) +\S", help_text.split("presets (CONFIG)", 1)[1], re.M)
    assert listed[: len(SENSOR_PRESETS)] == sorted(SENSOR_PRESETS)  # the recommended ones first
    for name in SENSOR_PRESETS:
        assert re.search(rf"^  {name} +{re.escape(presets[name])}$", help_text, re.M), name


def test_a_bad_key_in_a_sensor_class_preset_names_the_key(tmp_path):
    with pytest.raises(ConfigError, match=r"patch\.graph\.no_such_key"):
        load_slam_config("driving_mono", ["patch.graph.no_such_key=1"])
    copy = tmp_path / "handheld_mine.yaml"  # a user's copy keeps the prefix: still the run config
    copy.write_text((configs_dir() / "handheld_rgbd.yaml").read_text() + "patch_typo: 1\n")
    with pytest.raises(ConfigError, match="patch_typo"):
        load_preset_file(copy)


def test_readme_first_table_recommends_each_sensor_class_preset(repo_root):
    """The README's first table (right after the two copy-paste commands, before the overview) has
    one line per preset."""
    text = (repo_root / "README.md").read_text()
    first_table = re.search(r"(?m)^\|.*\n\|[-| ]+\|\n((?:\|.*\n)+)", text)
    assert first_table is not None
    rows = first_table.group(1).splitlines()
    for name in SENSOR_PRESETS:
        assert sum(f"`{name}`" in row for row in rows) == 1, name
    fences = [m.start() for m in re.finditer("```", text)]
    assert fences[3] < first_table.start() < text.index("\n---\n")  # right after the two commands


# ----------------------------------------------------------------------------- short real runs


def _stationary_ate(dataset) -> float:
    """ATE of doing nothing (one pose for every frame): after the best SE(3) or Sim(3) alignment the
    constant estimate sits at the mean ground-truth position, so its ATE is the RMS distance of the
    ground-truth positions from their mean."""
    p = dataset.groundtruth.T_WC[:, :3, 3]
    return float(np.sqrt(np.mean(np.sum((p - p.mean(axis=0)) ** 2, axis=1))))


def _run(preset: str, data, out, overrides=()):
    """Run ``preset`` on ``data`` (no plot, no map); (summary dict, ATE, stationary ATE)."""
    from fgslam.io.run_files import SUMMARY_FILE
    from fgslam.run.prepare import open_slam_dataset
    from fgslam.run.runner import run_slam

    config = load_slam_config(preset, ["output.plot=false", "output.write_map=false", *overrides])
    dataset = open_slam_dataset(data, config)
    run_slam(dataset, config, out, progress=False)
    summary = json.loads((out / SUMMARY_FILE).read_text())
    assert summary["frames_with_pose"] == summary["frames_processed"] == len(dataset), summary["failures"]
    assert summary["failures"]["tracking"] == 0, summary["failure_frames"]
    ate, stationary = summary["evaluation"]["ate"]["rmse"], _stationary_ate(dataset)
    print(f"{preset}: {len(dataset)} frames, ATE {ate:.4f} m, stationary {stationary:.4f} m, {summary['cpu_s']:.1f} CPU s")
    return summary, ate, stationary


@pytest.mark.parametrize("preset, data, frames", [
    ("handheld_rgbd", "7scenes_redkitchen_0-599", 60),  # 2 s of hand-held motion at 30 Hz
    ("handheld_mono", "7scenes_redkitchen_0-599", 60),
    ("driving_mono", "kitti00_0-199", 40),  # 4 s of driving at 10 Hz (30 m)
])
def test_sensor_class_preset_beats_a_stationary_estimate_on_real_data(shared_data, tmp_path, preset, data, frames):
    summary, ate, stationary = _run(preset, shared_data / data, tmp_path / "run", [f"dataset.end={frames}"])
    assert summary["sensor"] == SENSOR_PRESETS[preset]
    assert ate < MAX_SHARE_OF_STATIONARY * stationary, (ate, stationary)


def test_handheld_stereo_beats_a_stationary_estimate_on_the_room_loop(room_loop_clip, tmp_path):
    """The shared EuRoC clip is static (no motion to beat); the session's synthetic room loop is a
    hand-held-like stereo clip (320x240)."""
    root, _ = room_loop_clip(4.0, 19)  # rendered once per session (conftest.py)
    summary, ate, stationary = _run("handheld_stereo", root, tmp_path / "run", ["dataset.end=40"])  # 10 s, 40 %
    assert ate < MAX_SHARE_OF_STATIONARY * stationary, (ate, stationary)


@pytest.fixture(scope="module")
def street_stereo(tmp_path_factory):
    """A short synthetic street-loop drive (stereo, 0.54 m baseline, 10 Hz, 640x200): there is no
    real stereo driving data in ../shared/data."""
    from fgslam.io.synth import SynthSequence, write_sequence
    from fgslam.io.synth.scenarios import load_synth_config

    cfg = load_synth_config("street-loop")
    cfg.frames = STREET_FRAMES
    root = tmp_path_factory.mktemp("street_stereo")
    write_sequence(SynthSequence(cfg), root)
    return root


STREET_FRAMES = 30  # 3 s of driving (about 18 m)


def test_driving_stereo_beats_a_stationary_estimate_on_a_synthetic_street(street_stereo, tmp_path):
    summary, ate, stationary = _run("driving_stereo", street_stereo, tmp_path / "run")
    assert ate < MAX_SHARE_OF_STATIONARY * stationary, (ate, stationary)


def test_driving_stereo_starts_on_a_wide_baseline_where_the_default_start_measures_nothing(street_stereo, tmp_path):
    """With the first frame's patches at the default 1 m (``patch.ba.stereo_init_inv_depth=1``) the
    right-image search on a 0.54 m baseline starts 200 px off and no patch is measured; the preset
    starts in the far field (20 m) and poses the first frame."""
    from fgslam.core.errors import FGSlamError

    with pytest.raises(FGSlamError, match=r"never initialised.*waiting for depth"):
        _run("driving_stereo", street_stereo, tmp_path / "default", ["patch.ba.stereo_init_inv_depth=1.0",
                                                                     "dataset.end=3"])
    summary, _, _ = _run("driving_stereo", street_stereo, tmp_path / "preset", ["dataset.end=3"])
    assert summary["events"].get("initialised") == 1
