"""``patch.tracking.keyframe_flow``: the redundant-keyframe test on the flow between the candidate's
neighbours either raw (DPVO) or rotation-compensated (``translation``: each patch reprojected at its
depth minus at infinite depth). Under pure rotation the raw flow keeps every frame as a keyframe, so
the window spans little translation; the compensated flow removes those frames and keeps the
frames that translation separates (issue 23, the rotation-dominant hand-held class)."""

from __future__ import annotations

import numpy as np
import pytest

from fgslam.backend import Backend, BackendConfig
from fgslam.frontends.patch import PatchConfig, PatchFrontend
from fgslam.frontends.patch.graph import GraphFrame
from fgslam.io.calibration import Calibration

K = 16


def _rot_y(deg: float) -> np.ndarray:
    a = np.radians(deg)
    return np.array([[np.cos(a), 0.0, np.sin(a)], [0.0, 1.0, 0.0], [-np.sin(a), 0.0, np.cos(a)]])


def _frontend(mode: str, step_deg: float, step_m: float) -> PatchFrontend:
    """Five graph frames, each ``step_deg`` of yaw and ``step_m`` sideways from the previous one,
    patches at 5 m (inverse depth 0.2)."""
    cfg = PatchConfig()
    cfg.graph.patches_per_frame = K
    cfg.tracking.keyframe_flow = mode
    cfg.tracking.keyframe_threshold = 10.0
    cfg.validate()
    fe = PatchFrontend(cfg, Calibration(width=320, height=240, K=np.array([200.0, 200.0, 160.0, 120.0])),
                       backend=Backend(BackendConfig()))
    fe.state.sensor_mode = "mono"
    rng = np.random.default_rng(0)
    for fid in range(5):
        T_WC = np.eye(4)
        T_WC[:3, :3] = _rot_y(step_deg * fid)
        T_WC[0, 3] = step_m * fid
        fe.keyframes.enter(GraphFrame(fid=fid, index=fid, timestamp=0.1 * fid, T_WC=T_WC,
                                      uv=rng.uniform([80, 60], [240, 180], (K, 2)), inv_depth=np.full(K, 0.2),
                                      sensor_inv_depth=np.full(K, np.nan), colour=np.zeros((K, 3), np.uint8)))
    return fe


def test_pure_rotation_has_no_translation_flow():
    fe = _frontend("translation", 5.0, 0.0)
    a, b = fe.graph.frames[0], fe.graph.frames[2]
    assert fe.keyframes.mean_flow(a, b) > 30.0  # 10 deg of yaw at f = 200: about 35 px
    assert fe.keyframes.translation_flow(a, b) == pytest.approx(0.0, abs=1e-6)


def test_pure_translation_flow_is_the_raw_flow():
    fe = _frontend("translation", 0.0, 0.3)
    a, b = fe.graph.frames[0], fe.graph.frames[2]
    assert fe.keyframes.translation_flow(a, b) == pytest.approx(fe.keyframes.mean_flow(a, b), rel=1e-9)


@pytest.mark.parametrize("mode, step_deg, step_m, removed", [
    ("raw", 5.0, 0.0, False),           # rotation: raw flow 35 px keeps the frame (DPVO)
    ("translation", 5.0, 0.0, True),    # rotation: no translation flow, the frame is redundant
    ("raw", 0.0, 0.3, False),           # translation 0.6 m at 5 m: 24 px either way
    ("translation", 0.0, 0.3, False),
    ("translation", 5.0, 0.3, False),   # rotation and translation: the translation keeps it
])
def test_keyframe_removal_decision(mode, step_deg, step_m, removed):
    fe = _frontend(mode, step_deg, step_m)
    victim = fe.graph.frames[1].index
    out = fe.keyframes.remove_redundant()
    assert (out == victim) if removed else (out is None)
    assert len(fe.graph) == (4 if removed else 5)


def test_keyframe_flow_is_validated():
    cfg = PatchConfig()
    cfg.tracking.keyframe_flow = "rotation"
    with pytest.raises(Exception, match="keyframe_flow"):
        cfg.validate()
