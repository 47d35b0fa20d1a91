"""Mixing families (fgslam.frontends.pointmap.mix): pointmap edges between the patch frontend's keyframes
in the same backend, selected by a ``factors`` entry; without the primary's keyframe images it logs and
adds nothing."""

from __future__ import annotations

import logging

import pytest

from fgslam.backend.keys import pose_key
from fgslam.core.errors import ConfigError
from fgslam.frontends.pointmap.mix import PointmapMix
from eval_support import assert_beats_doing_nothing
from pointmap_support import render_clip

FRAMES = 16
MIX = {"class": "fgslam.frontends.pointmap.mix:PointmapMix",
       "options": {"lag": 3, "pointmap": {"query_stride": 4}}}  # a quarter of the default's matches: a fast test


@pytest.fixture(scope="module")
def room(tmp_path_factory):
    return render_clip(tmp_path_factory.mktemp("pm_mix"), FRAMES)


def _run(room, out, loop_mode, factors):
    from fgslam.run.config import load_slam_config
    from fgslam.run.prepare import open_slam_dataset
    from fgslam.run.runner import run_slam

    config = load_slam_config("patch_rgbd", ["output.plot=false", f"loop_closure.mode={loop_mode}",
                                             "loop_closure.run_in_thread=false"])
    config.factors = factors
    return run_slam(open_slam_dataset(room, config), config, out, progress=False)


def _groundtruth(room):
    from fgslam.io.datasets import DatasetConfig, open_dataset

    return open_dataset(room, config=DatasetConfig(load_imu=False)).groundtruth


def test_pointmap_edges_join_the_patch_graph(room, tmp_path, monkeypatch):
    made = []
    original = PointmapMix.attach

    def attach(self, backend):  # keep the plugin to look at it after the run
        made.append(self)
        original(self, backend)

    monkeypatch.setattr(PointmapMix, "attach", attach)
    summary = _run(room, tmp_path / "mix", "classical", [MIX])
    (mix,) = made
    assert mix.counts["edges"] >= 3 and mix.counts["no_image"] == 0
    assert mix.primary is not None and mix.primary.name == "patch"
    blocks = mix.backend.blocks("pointmap")
    assert len(blocks) >= 1
    for block in blocks:  # every edge joins two keyframes the patch frontend still holds
        (edge,) = block.edges
        assert all(mix.backend.has_key(k) for k in (edge.key_i, edge.key_j))
        assert edge.key_i in {pose_key(k) for k in mix.backend.keyframe_ids}
    assert summary.ate_rmse < 0.01
    # as well as the patch family alone on the same clip (measured: ATE 0.0020 m mixed, 0.0043 m alone),
    # both far better than doing nothing (0.072 m)
    alone = _run(room, tmp_path / "alone", "classical", [])
    assert alone.ate_rmse < 0.01 and summary.ate_rmse <= alone.ate_rmse, (summary.ate_rmse, alone.ate_rmse)
    gt = _groundtruth(room)
    assert_beats_doing_nothing(summary.ate_rmse, gt, gt.timestamps, "se3")


def test_without_keyframe_images_it_logs_and_adds_nothing(room, tmp_path, caplog, monkeypatch):
    made = []
    original = PointmapMix.attach
    monkeypatch.setattr(PointmapMix, "attach", lambda self, b: (made.append(self), original(self, b)))
    with caplog.at_level(logging.WARNING, logger="fgslam.frontends.pointmap.mix"):
        _run(room, tmp_path / "nolc", "off", [MIX])
    assert made[0].counts["edges"] == 0 and made[0].counts["no_image"] > 0
    assert "keeps no image" in caplog.text


def test_options_are_checked():
    with pytest.raises(ConfigError, match=r"factors\[0\].options.lag"):
        PointmapMix({"lag": -1}, "factors[0]")
    with pytest.raises(ConfigError, match=r"factors\[0\].options.pointmap.query_stride"):
        PointmapMix({"pointmap": {"query_stride": 0}}, "factors[0]")
