"""The pointmap frontend (fgslam.frontends.pointmap.frontend) end to end on short synthetic room-loop clips
with each built-in source (RGB-D, stereo, monocular two-view): accuracy against the generator's ground
truth, keyframes and edges in the backend, the canonical pointmaps' outputs (PLY points, depth maps), bad
input (NaN / missing depth, no overlap), and the registry / runner path (``frontend: pointmap``)."""

from __future__ import annotations

import json
import logging

import numpy as np
import pytest

from fgslam.backend.keys import pose_key
from fgslam.frontends import make_frontend
from fgslam.frontends.pointmap.config import PointmapConfig
from fgslam.frontends.pointmap.frontend import PointmapFrontend
from fgslam.core.lie import sim3_matrix_parts
from fgslam.backend import Backend, BackendConfig
from eval_support import assert_beats_doing_nothing, frames_groundtruth
from pointmap_support import ate_percent, open_clip, render_clip

FRAMES = 30


@pytest.fixture(scope="module")
def room(tmp_path_factory):
    return render_clip(tmp_path_factory.mktemp("pm_room"), FRAMES)


def _run(frames, mode, config=None):
    fe = PointmapFrontend(config or PointmapConfig(), sensor_mode=mode, backend=Backend(BackendConfig()))
    statuses = [fe.process(f) for f in frames]
    fe.finish()
    return fe, statuses


def _beats_doing_nothing(fe, frames, ate, align):
    """Measured on the 30-frame clip: RGB-D 1.6 mm, stereo 1.6 mm, mono 18.5 mm against 0.119 m standing still."""
    assert_beats_doing_nothing(ate, frames_groundtruth(frames), fe.trajectory()[0], align)


def _keyframe_config(gap=8):
    cfg = PointmapConfig()
    cfg.keyframe.max_gap = gap  # force keyframes on a short clip: edges and the backend's optimisation run
    return cfg


def test_rgbd_room_accuracy_keyframes_and_outputs(room):
    frames = open_clip(room, "rgbd")
    fe, statuses = _run(frames, "rgbd", _keyframe_config())
    assert [s.pose_source for s in statuses] == ["tracked"] * FRAMES
    ate, pct = ate_percent(fe, frames, "se3")
    assert pct <= 0.5, (ate, pct)  # issue 13 target on room-loop RGB-D
    _beats_doing_nothing(fe, frames, ate, "se3")
    # keyframes every 8 tracked frames, chained by edges in one pointmap block of the backend
    kfs = fe.backend.keyframe_ids
    assert len(kfs) == fe.num_keyframes() == 4
    (block,) = fe.backend.blocks("pointmap")
    assert [(e.key_i, e.key_j) for e in block.edges] == [(pose_key(a), pose_key(b)) for a, b in zip(kfs, kfs[1:])]
    for kf in kfs:  # metric source: SE(3) tracking, the keyframe scales stay 1
        assert abs(sim3_matrix_parts(fe.backend.pose_matrix(kf))[2] - 1.0) < 1e-6
    # outputs: canonical depth of keyframe 0 against the rendered depth, points in the world
    depths = fe.keyframe_depths()
    t0, z, c = depths[kfs[0]]
    truth = frames[0].depth
    ok = (z > 0) & (truth > 0)
    assert ok.mean() > 0.9 and c.max() <= 1.0
    assert np.median(np.abs(z[ok] - truth[ok]) / truth[ok]) < 0.005
    X, colour = fe.keyframe_points()
    assert X.shape[1] == 3 and colour.shape == X.shape and np.isfinite(X).all() and len(X) > 1000


def test_stereo_room(room):
    frames = open_clip(room, "stereo")
    fe, statuses = _run(frames, "stereo")
    assert all(s.pose_source == "tracked" for s in statuses)
    ate, pct = ate_percent(fe, frames, "se3")
    assert pct <= 1.0, (ate, pct)
    _beats_doing_nothing(fe, frames, ate, "se3")  # a moving stereo clip (the EuRoC stereo clip is static)


def test_mono_room_two_view(room):
    """Monocular: the map starts from a two-view pair; frames without parallax are tracked by PnP."""
    frames = open_clip(room, "mono")
    cfg = _keyframe_config()
    cfg.features.mode = "two_view"  # the issue-13 source (the per-frame features: tests/test_pointmap_mono_features.py)
    fe, statuses = _run(frames, "mono", cfg)
    sources = [s.pose_source for s in statuses]
    assert "motion_model" not in sources and sources.count("tracked") >= FRAMES - 8
    ate, pct = ate_percent(fe, frames, "sim3")
    assert pct <= 5.0, (ate, pct)  # measured 3.9 % on this 30-frame clip (the full loop: tools/bench_pointmap.py)
    _beats_doing_nothing(fe, frames, ate, "sim3")
    assert not fe.backend.config.gauge.hold_scale  # real per-keyframe scales: no scale priors


def test_bad_input_is_logged_never_raised(room, caplog):
    """NaN depth, a frame without any valid depth, a noise image (no overlap): failures, then tracking again."""
    frames = open_clip(room, "rgbd")[:10]
    frames[4].depth = np.full_like(frames[4].depth, np.nan)
    frames[5].depth = np.zeros_like(frames[5].depth)
    rng = np.random.default_rng(0)
    frames[6].image = rng.integers(0, 255, frames[6].image.shape, dtype=np.uint8)
    half = frames[7].depth.copy()
    half[:, ::2] = np.nan
    frames[7].depth = half
    with caplog.at_level(logging.INFO, logger="fgslam.frontends.pointmap"):
        fe, statuses = _run(frames, "rgbd")
    sources = [s.pose_source for s in statuses]
    assert sources[4] == sources[5] == "motion_model"
    assert sources[8:] == ["tracked", "tracked"]  # tracking again right after the bad frames
    assert fe.num_failures >= 2 and "tracking lost" in caplog.text
    t, T, _ = fe.trajectory()
    assert len(t) == 10 and np.isfinite(T).all()


def test_mono_without_overlap_never_initialises_and_never_raises(room):
    frames = open_clip(room, "mono")[:4]
    rng = np.random.default_rng(1)
    for f in frames[1:]:
        f.image = rng.integers(0, 255, f.image.shape, dtype=np.uint8)
    fe, statuses = _run(frames, "mono")
    assert [s.pose_source for s in statuses] == ["initializing"] * 4
    assert fe.trajectory()[0].size == 0 and fe.keyframe_points() is None and fe.keyframe_depths() is None


def test_frontend_pointmap_from_any_preset(room, tmp_path):
    """``frontend: pointmap`` on a patch preset: the source follows the sensor (auto); the run writes its
    outputs and the PLY of the canonical pointmaps."""
    from fgslam.run.config import load_slam_config
    from fgslam.run.prepare import open_slam_dataset
    from fgslam.run.runner import run_slam

    config = load_slam_config("patch_rgbd", ["frontend=pointmap", "output.write_ply=true", "output.plot=false",
                                             "dataset.end=12"])
    assert config.pointmap.source.kind == "auto"
    result = run_slam(open_slam_dataset(room, config), config, tmp_path / "run", progress=False)
    summary = json.loads((tmp_path / "run" / "summary.json").read_text())
    assert summary["frontend"] == "pointmap" and summary["frames_processed"] == 12
    assert result.ate_rmse < 0.01
    assert (tmp_path / "run" / "points.ply").stat().st_size > 1000
    fe = make_frontend("pointmap", config, open_clip(room, "rgbd")[0].calibration, "rgbd", backend=Backend(BackendConfig()))
    assert isinstance(fe, PointmapFrontend) and fe.state.kind == "rgbd" and fe.state.fixed_scale


def test_sensor_and_source_mismatch_is_a_config_error():
    from fgslam.core.errors import ConfigError

    cfg = PointmapConfig()
    cfg.source.kind = "rgbd"
    with pytest.raises(ConfigError, match="needs sensor: rgbd"):
        PointmapFrontend(cfg, sensor_mode="mono", backend=Backend(BackendConfig()))
    cfg.keyframe.new_fraction = 0.01
    with pytest.raises(ConfigError, match="new_fraction"):
        PointmapFrontend(cfg, sensor_mode="rgbd", backend=Backend(BackendConfig()))


def test_a_failure_after_a_keyframe_is_made_keeps_its_pose_and_the_run_going(room, monkeypatch):
    """Numerical trouble in the window optimisation after a new keyframe fails that frame (counted) but the
    frame keeps the keyframe's pose and the frames after it track (the failure once wrote the frame's pose
    relative to itself, and every later pose lookup recursed without end)."""
    from fgslam.core.errors import OptimizationError

    frames = open_clip(room, "rgbd")
    fe = PointmapFrontend(_keyframe_config(), sensor_mode="rgbd", backend=Backend(BackendConfig()))
    optimize = fe.graph.optimize
    failed = []

    def failing_optimize():
        if not failed:
            failed.append(fe.state.kf.fid)
            raise OptimizationError("injected")
        return optimize()

    handed = []
    add_keyframe = fe.state.loops.add_keyframe

    def recording_add_keyframe(kf_id, *args):
        handed.append(kf_id)
        return add_keyframe(kf_id, *args)

    monkeypatch.setattr(fe.graph, "optimize", failing_optimize)
    monkeypatch.setattr(fe.state.loops, "add_keyframe", recording_add_keyframe)
    statuses = [fe.process(f) for f in frames]
    fe.finish()
    assert failed and fe.num_failures == 1
    assert [i for i, s in enumerate(statuses) if s.pose_source != "tracked"] == [failed[0]]
    assert statuses[failed[0]].T_WC is not None and np.isfinite(statuses[failed[0]].T_WC).all()
    assert statuses[failed[0]].is_keyframe and failed[0] in handed  # still a keyframe, and the loop port's
    ate, pct = ate_percent(fe, frames, "se3")
    assert pct <= 0.5, (ate, pct)
