"""The rejoin's rules (frontends/patch/rejoin.py) with a stand-in state and loop port: the attempts'
cadence, stationary frames skipped, two agreeing relocalisations needed, only the new map moved, the
reference after a map that was not rejoined, monocular maps and failing attempts."""

from __future__ import annotations

from types import SimpleNamespace

import cv2
import numpy as np
import torch

from fgslam.frontends.patch.config import PatchTrackingConfig
from fgslam.frontends.patch.rejoin import MapRejoin


def _shift(x: float) -> np.ndarray:
    T = np.eye(4)
    T[0, 3] = x
    return T


class Port:
    """Relocalises every image as the next of ``answers`` (kf id, T_WC; None: not found); records the calls."""

    relocalizes = True

    def __init__(self, answers):
        self.answers, self.calls, self.moves = list(answers), [], []

    def relocalize(self, image, K, before=None):
        self.calls.append(before)
        answer = self.answers.pop(0)
        if isinstance(answer, Exception):
            raise answer
        return answer

    def move_map(self, correction, T_WC_by_id):
        self.moves.append((correction, T_WC_by_id))
        return True


def _state(sensor="rgbd", every=2, frames=20):
    graph = SimpleNamespace(frames=[])
    poses = {}
    st = SimpleNamespace(config=SimpleNamespace(tracking=PatchTrackingConfig(rejoin_every=every, rejoin_frames=frames)),
                         initialized=True, graph=graph, final={}, sensor_mode=sensor, K=torch.ones(4),
                         pose_of=lambda fid: poses.get(fid))
    return st, poses


def _track(st, poses, fid, T):
    """Frame ``fid`` entered the graph at ``T``."""
    poses[fid] = T
    st.graph.frames.append(SimpleNamespace(fid=fid, T_WC=T))


def test_two_agreeing_relocalisations_move_the_new_map_only():
    st, poses = _state()
    st.final[3] = SimpleNamespace(fid=3, T_WC=_shift(0.5))  # the old map's keyframe: never moved
    U = _shift(1.0)  # the new map's world -> the old map's
    port = Port([(2, U @ _shift(0.0)), (2, U @ _shift(0.2) @ _shift(0.001))])
    rejoin = MapRejoin(st, port)
    rejoin.begin(10)
    frame = SimpleNamespace(index=0, image=np.zeros((4, 4), np.uint8))
    events = []
    for fid, x in ((10, 0.0), (11, 0.1), (12, 0.2)):
        _track(st, poses, fid, _shift(x))
        events.append(rejoin.step(fid, frame))
    assert port.calls == [10, 10]  # frames 10 and 12 (every 2nd), among the keyframes before the restart
    assert events[:2] == [None, None] and events[2].startswith("map rejoined")
    (correction, moved), = port.moves
    assert sorted(moved) == [10, 11, 12]
    for k in (10, 11, 12):
        np.testing.assert_allclose(moved[k][:3, 3], [1.0 + 0.1 * (k - 10) + 0.001, 0, 0], atol=1e-12)
    np.testing.assert_allclose(correction.apply_pose(3, _shift(0.5))[0], _shift(0.5))  # older: held
    assert rejoin.start is None and rejoin.rejoined == 1


def test_stationary_frames_disagreeing_relocalisations_and_a_second_restart():
    st, poses = _state(every=1)
    port = Port([(2, _shift(1.0)), (2, _shift(3.0)), (2, _shift(5.0))])
    rejoin = MapRejoin(st, port)
    rejoin.begin(10)
    frame = SimpleNamespace(index=0, image=np.zeros((4, 4), np.uint8))
    _track(st, poses, 10, np.eye(4))
    assert rejoin.step(10, frame) is None
    poses[11] = np.eye(4)  # stationary: not in the graph
    assert rejoin.step(11, frame) is None and port.calls == [10]
    _track(st, poses, 12, np.eye(4))
    assert rejoin.step(12, frame) is None and not port.moves  # 2 m apart: waits for another
    rejoin.begin(20)  # a second restart: the map of frame 10 stays out of the reference
    _track(st, poses, 20, np.eye(4))
    rejoin.step(20, frame)
    assert port.calls == [10, 10, 10] and rejoin.reference_end == 10


def test_monocular_maps_and_failing_attempts_end_quietly():
    st, poses = _state(sensor="mono", every=1)
    port = Port([])
    rejoin = MapRejoin(st, port)
    rejoin.begin(10)
    _track(st, poses, 10, np.eye(4))
    assert rejoin.step(10, SimpleNamespace(index=0, image=None)) is None and port.calls == []
    st2, poses2 = _state(every=1)
    port2 = Port([cv2.error("bad image")])
    rejoin2 = MapRejoin(st2, port2)
    rejoin2.begin(10)
    _track(st2, poses2, 10, np.eye(4))
    assert rejoin2.step(10, SimpleNamespace(index=0, image=None)) is None
    assert rejoin2.start is None and rejoin2.reference_end == 10  # given up, the run goes on
