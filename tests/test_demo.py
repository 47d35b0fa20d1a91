"""``fgslam demo``: config loading, and a smoke run with a reduced frame count and resolution."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from fgslam.run.demo import DemoConfig, DemoSceneConfig, format_demo_report, load_demo_config, render_scene
from fgslam.core.errors import ConfigError
from fgslam.io.run_files import SUMMARY_FILE, TUM_FILE

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture
def cli_main():
    """``fgslam.cli.main``."""
    from fgslam import cli

    return cli.main


def test_demo_config_file_loads():
    config = load_demo_config(REPO / "fgslam" / "configs" / "demo.yaml")
    assert isinstance(config, DemoConfig)
    assert config.scene.preset == "room-loop"
    assert config.slam.frontend == "patch" and config.slam.sensor == "mono"
    # the default (no path) is the package's fgslam/configs/demo.yaml
    assert load_demo_config(None) == config


def test_demo_config_overrides_and_errors(tmp_path):
    config = load_demo_config(None, ["scene.frames=30", "slam.sensor=stereo", "slam.patch.ba.iterations=4"])
    scene, slam = config.scene, config.slam
    assert scene.frames == 30 and slam.sensor == "stereo" and slam.patch.ba.iterations == 4
    with pytest.raises(ConfigError, match="unknown key 'render'"):
        load_demo_config(None, ["render.x=1"])
    with pytest.raises(ConfigError, match="key .scene.frames.: must be >= 2"):
        load_demo_config(None, ["scene.frames=1"])
    with pytest.raises(ConfigError, match="slam.*sensor"):
        load_demo_config(None, ["slam.sensor=sonar"])
    bad = tmp_path / "demo.yaml"
    bad.write_text("scene:\n  width: 8\n")
    with pytest.raises(ConfigError, match="key .scene.width.: must be >= 32"):
        load_demo_config(bad)
    assert DemoSceneConfig().frames >= 2


def test_demo_smoke(tmp_path, cli_main, capsys):
    """A reduced demo end to end with the real default frontend (patch, mono)."""
    out = tmp_path / "demo"
    argv = ["demo", "--out", str(out), "--frames", "30", "-o", "scene.width=160", "-o", "scene.height=120", "--json"]
    assert cli_main(argv) == 0
    result = json.loads(capsys.readouterr().out)
    assert result["sequence"]["reused"] is False
    summary = result["summary"]
    assert summary == json.loads((out / "run" / SUMMARY_FILE).read_text())
    assert summary["frames_processed"] == 30
    assert summary["frontend"] == "patch" and summary["sensor"] == "mono"
    assert summary["frames_with_pose"] > 0, summary["notes"]
    assert (out / "run" / TUM_FILE).is_file()
    assert summary["evaluation"]["align"] == "sim3"
    report = format_demo_report(DemoSceneConfig(**result["scene"]), result["sequence"], summary, result["total_s"])
    for text in ("room-loop, 30 frames 160x120", "keyframes", "frames/s", "ATE", "% of the", "trajectory.png"):
        assert text in report


def test_render_scene_reuses_identical_sequence(tmp_path):
    scene = DemoSceneConfig(frames=3, width=48, height=32)
    first = render_scene(scene, tmp_path / "seq")
    assert first["reused"] is False and (tmp_path / "seq" / "mav0" / "cam0" / "data.csv").is_file()
    assert render_scene(scene, tmp_path / "seq")["reused"] is True
    assert render_scene(DemoSceneConfig(frames=4, width=48, height=32), tmp_path / "seq")["reused"] is False
