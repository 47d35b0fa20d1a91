"""``fgslam compare-colmap`` on a tiny synthetic clip (pycolmap SfM with few SIFT features), and the
point-cloud metrics on clouds with known distances."""

from __future__ import annotations

import json

import numpy as np
import pytest

from fgslam.cli import main
from fgslam.export.compare import cloud_distances

FRAMES = 40


def test_cloud_distances_known_offsets():
    rng = np.random.default_rng(0)
    reference = rng.uniform(-1, 1, (400, 3))
    cloud = reference[:200] + np.array([0.0, 0.0, 0.01])  # half the reference, 1 cm off
    d = cloud_distances(cloud, reference)
    assert d["accuracy_mean"] == pytest.approx(0.01, abs=1e-3)  # every cloud point is 1 cm from a reference point
    assert d["completion_mean"] > 0.05  # the missing half of the reference is far from the cloud
    assert d["completion_median"] >= d["accuracy_median"]
    assert np.isnan(cloud_distances(np.zeros((0, 3)), reference)["accuracy_mean"])


@pytest.fixture(scope="module")
def clip(tmp_path_factory):
    from fgslam.io.synth import SynthSequence, write_sequence
    from fgslam.io.synth.presets import load_synth_config

    root = tmp_path_factory.mktemp("clip")
    write_sequence(SynthSequence(load_synth_config("room-loop", overrides=[
        "frames=40", "camera.width=320", "camera.height=240"])), root)
    return root


def test_compare_colmap_on_a_synthetic_clip(clip, tmp_path, capsys):
    out = tmp_path / "cmp"
    assert main(["-q", "compare-colmap", "--data", str(clip), "--frames", str(FRAMES), "--out", str(out),
                 "--features", "2048", "--no-progress", "--json"]) == 0
    r = json.loads(capsys.readouterr().out)
    assert r["dataset"]["frames"] == FRAMES and r["fgslam"]["preset"] == "patch_mono"
    fg, cm = r["fgslam"], r["colmap"]
    assert fg["registered_frames"] == FRAMES and cm["registered_frames"] >= FRAMES // 2
    assert cm["settings"]["max_num_features"] == 2048 and cm["points"] > 100 and fg["points"] > 100
    # both reconstruct the room: Sim(3) ATE a few mm on a path of tens of cm
    assert 0 < fg["ate_m"] < 0.02 and 0 < cm["ate_m"] < 0.02
    assert r["speed_ratio_wall"] == pytest.approx(cm["wall_s"] / fg["wall_s"])
    d = r["clouds"]["fgslam_against_colmap"]
    assert 0 < d["accuracy_median"] < 1.0 and 0 < d["completion_median"] < 1.0
    assert json.loads((out / "compare.json").read_text())["colmap"]["points"] == cm["points"]
    assert (out / "compare.png").stat().st_size > 10_000
    # an existing output is refused
    assert main(["compare-colmap", "--data", str(clip), "--frames", "5", "--out", str(out)]) == 2
    assert "exists and is not empty" in capsys.readouterr().err
