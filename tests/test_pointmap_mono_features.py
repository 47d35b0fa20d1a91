"""The monocular pointmap source that measures the pose of every frame (issue 28,
fgslam.frontends.pointmap.features): corners tracked by KLT, PnP against the keyframe's canonical pointmap,
keyframes triangulated with the measured pose. On a synthetic room-loop clip: every frame measured and
accurate (beating standing still and the motion model alone), and a true pose jump with a wrong prediction
either reported as lost or recovered, never silently confirmed."""

from __future__ import annotations

import numpy as np
import pytest

from fgslam.backend import Backend, BackendConfig
from fgslam.eval.trajectory import EvalConfig, evaluate
from fgslam.frontends.pointmap.config import PointmapConfig
from fgslam.frontends.pointmap.features import carry_pointmap
from fgslam.frontends.pointmap.frontend import PointmapFrontend
from fgslam.io.trajectory import Trajectory
from eval_support import assert_beats_doing_nothing, frames_groundtruth
from pointmap_support import ate_percent, open_clip, render_clip

FRAMES = 48
JUMP_FROM, JUMP_TO = 24, 44  # frames 0..JUMP_FROM-1, then the camera is at frame JUMP_TO's pose


@pytest.fixture(scope="module")
def room(tmp_path_factory):
    return render_clip(tmp_path_factory.mktemp("pm_features_room"), FRAMES)


def _run(frames, config=None):
    fe = PointmapFrontend(config or PointmapConfig(), sensor_mode="mono", backend=Backend(BackendConfig()))
    statuses = [fe.process(f) for f in frames]
    fe.finish()
    return fe, statuses


MOTION_MODEL_FRACTION_7SCENES = 0.7  # the 7-Scenes slice's bound: its ATE over the motion model's (docstring)


def motion_model_ate(frames, stamps) -> float:
    """Sim(3) ATE of the motion model alone: constant velocity from the ground truth of the first two frames."""
    gt = frames_groundtruth(frames)
    P0, P1 = gt.T_WC[0, :3, 3], gt.T_WC[1, :3, 3]
    dt = gt.timestamps[1] - gt.timestamps[0]
    T = np.repeat(gt.T_WC[:1], len(stamps), axis=0).copy()
    T[:, :3, 3] = P0 + (np.asarray(stamps)[:, None] - gt.timestamps[0]) / dt * (P1 - P0)
    return float(evaluate(gt, Trajectory(np.asarray(stamps), T), EvalConfig(align="sim3")).ate.rmse)


def test_every_frame_is_measured_and_accurate(room):
    """After the two-view start every frame is posed by the corners' PnP (or becomes a keyframe); no frame
    keeps the prediction. Measured on this clip: 0.42 % of the path (2.9 mm) against 0.18 m standing still and
    0.052 m for the motion model alone (two-view source: 3.9 % on 30 frames)."""
    frames = open_clip(room, "mono")
    fe, statuses = _run(frames)
    sources = [s.pose_source for s in statuses]
    assert "motion_model" not in sources and "relocalized" not in sources
    started = sources.index("tracked")
    assert started <= 6 and sources[started:] == ["tracked"] * (FRAMES - started)
    counts = fe.state.counts
    assert counts["feature_tracked"] + counts["keyframes"] >= FRAMES - started
    assert counts["keyframes"] >= 2 and len(fe.graph.edges) == counts["keyframes"] - 1
    ate, pct = ate_percent(fe, frames, "sim3")
    assert pct <= 1.5, (ate, pct)
    t = fe.trajectory()[0]
    assert_beats_doing_nothing(ate, frames_groundtruth(frames), t, "sim3")
    assert ate < 0.5 * motion_model_ate(frames, t)


@pytest.mark.parametrize("rolled", [False, True])
def test_a_true_jump_with_a_wrong_prediction_is_lost_or_recovered(room, rolled):
    """The camera jumps from frame JUMP_FROM-1 to frame JUMP_TO's pose (0.3 m away in a 1.8 m clip; the stamps run on,
    so the motion model predicts the old path); ``rolled``: also turned 180 degrees about its optical axis (the
    image rotated, the principal point at the centre), which no KLT track survives. Each jumped frame must be
    reported lost (``motion_model`` with a ``tracking lost`` event) or posed near its true pose: never tracked
    at the prediction. Measured: the plain jump is recovered by the corners (KLT over the pyramid), the
    rolled one is reported lost."""
    frames = open_clip(room, "mono")
    dt = frames[1].timestamp - frames[0].timestamp
    jumped = frames[JUMP_TO:JUMP_TO + 3]
    for k, f in enumerate(jumped):
        f.timestamp = frames[JUMP_FROM - 1].timestamp + (k + 1) * dt
        if rolled:
            f.image = np.ascontiguousarray(f.image[::-1, ::-1])
            f.T_WC_gt = f.T_WC_gt @ np.diag([-1.0, -1.0, 1.0, 1.0])
    clip = frames[:JUMP_FROM] + jumped
    fe, statuses = _run(clip)
    before = [s.pose_source for s in statuses[:JUMP_FROM]]
    assert before[-10:] == ["tracked"] * 10
    # the estimate's frame: Sim(3) of the frames before the jump onto their ground truth
    res = evaluate(frames_groundtruth(clip[:JUMP_FROM]),
                   Trajectory(np.array([s.timestamp for s in statuses[:JUMP_FROM] if s.T_WC is not None]),
                              np.stack([s.T_WC for s in statuses[:JUMP_FROM] if s.T_WC is not None])),
                   EvalConfig(align="sim3"))
    S = np.asarray(res.alignment.matrix())  # estimate -> ground truth
    jump = np.linalg.norm(jumped[0].T_WC_gt[:3, 3] - clip[JUMP_FROM - 1].T_WC_gt[:3, 3])
    assert jump > 0.25
    for f, s in zip(jumped, statuses[JUMP_FROM:]):
        if s.pose_source == "motion_model":
            assert any("tracking lost" in e for e in s.events)
            continue
        assert s.pose_source in ("tracked", "relocalized"), s
        p = S[:3, :3] @ s.T_WC[:3, 3] + S[:3, 3]
        assert np.linalg.norm(p - f.T_WC_gt[:3, 3]) < 0.25 * jump, (s.pose_source, s.events)


def test_carried_pointmap_is_the_keyframe_seen_from_the_frame():
    """A plane's points moved into a frame: every pixel hit holds the nearest point, in the frame's units."""
    K = (100.0, 100.0, 32.0, 24.0)
    H, W = 48, 64
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    z = np.full((H, W), 2.0)
    X = np.stack(((u - K[2]) / K[0] * z, (v - K[3]) / K[1] * z, z), -1).astype(np.float32)
    C = np.ones((H, W), np.float32)
    T = np.eye(4)
    T[:3, :3] *= 2.0  # a Sim(3) of scale 2: the frame's units are half the keyframe's
    T[0, 3] = 0.1
    X_f, C_f = carry_pointmap(X, C, T, K)
    hit = C_f > 0
    assert hit.mean() > 0.8
    assert np.allclose(X_f[hit][:, 2], 1.0, atol=1e-5)  # depth 2 in k, scale 2: depth 1 in f
    back = X_f[hit].astype(np.float64) @ T[:3, :3].T + T[:3, 3]
    assert np.allclose(back[:, 2], 2.0, atol=1e-5)


def test_7scenes_mono_slice_is_measured_every_frame(shared_data):
    """7-Scenes kitchen frames 0-149 (5 s, 0.9 m of hand-held motion), monocular at 320x240 (the preset's
    width): every frame after the two-view start posed by the corners, none by the motion model, and the
    Sim(3) ATE clearly below standing still and the motion model alone. Measured with the calibration's
    focal length changed by -1, 0, +1 and +2 parts per million (tools/bench_stability.py's perturbation):
    0.046-0.050 m against 0.28 m standing still and 0.082 m for the motion model alone. (With corner fusion,
    off by default since it made long runs chaotic: 0.036-0.043 m, so its former bound of half the motion
    model, 0.041 m, held by luck on one machine; the two-view source of issue 13: 0.049 m over frames 0-199.)
    The bounds sit 20 % (0.06 m) and 13 % (0.7 x 0.082 m) above the largest of those four runs."""
    from fgslam.io.datasets import DatasetConfig, open_dataset

    frames = list(open_dataset(shared_data / "7scenes_redkitchen_0-599",
                               config=DatasetConfig(load_imu=False, load_depth=False, crop_multiple=1, end=150)))
    fe, statuses = _run(frames)
    sources = [s.pose_source for s in statuses]
    started = sources.index("tracked")
    assert sources[started:] == ["tracked"] * (len(frames) - started)
    t, T, _ = fe.trajectory()
    assert len(t) == len(frames)
    gt = frames_groundtruth(frames)
    ate = float(evaluate(gt, Trajectory(t, T), EvalConfig(align="sim3")).ate.rmse)
    assert ate < 0.06
    assert_beats_doing_nothing(ate, gt, t, "sim3")
    assert ate < MOTION_MODEL_FRACTION_7SCENES * motion_model_ate(frames, t)
