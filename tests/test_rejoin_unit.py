"""The rejoin's rules (frontends/rejoin.py) with a stand-in loop port: the attempts' cadence, two agreeing
relocalisations needed, only the new map moved, the reference after a map that was not rejoined, the
attempts' limit, monocular maps and failing attempts. Each family's runs: tests/test_patch_rejoin.py and
tests/test_maps.py (a loaded map)."""

from __future__ import annotations

from types import SimpleNamespace

import cv2
import numpy as np

from fgslam.frontends.patch.config import PatchTrackingConfig
from fgslam.frontends.dense.config import DenseTrackingConfig
from fgslam.frontends.rejoin import MapRejoin, RejoinSettings

K = np.array([500.0, 500.0, 320.0, 240.0])
FRAME = SimpleNamespace(index=0, image=np.zeros((4, 4), np.uint8))
EYE = lambda fid: np.eye(4)  # noqa: E731  (every frame of the new map at the origin)


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


def _rejoin(port, every=2, frames=20, metric=True, keyframes=None):
    settings = RejoinSettings(frames=frames, every=every, max_translation=0.05, max_rotation_deg=2.0)
    keyframes = {} if keyframes is None else keyframes
    return MapRejoin(settings, port, metric=metric, keyframe_poses=lambda: dict(keyframes)), keyframes


def test_the_settings_are_each_familys_tracking_keys():
    for cfg in (PatchTrackingConfig(rejoin_frames=7, rejoin_every=3, rejoin_max_translation=0.1),
                DenseTrackingConfig(rejoin_frames=7, rejoin_every=3, rejoin_max_translation=0.1)):
        assert RejoinSettings.of(cfg) == RejoinSettings(7, 3, 0.1, 2.0)


def test_two_agreeing_relocalisations_move_the_new_map_only():
    U = _shift(1.0)  # the new map's world -> the old map's
    port = Port([(2, U @ _shift(0.0)), (2, U @ _shift(0.2) @ _shift(0.001))])
    rejoin, keyframes = _rejoin(port, keyframes={3: _shift(0.5)})  # the old map's keyframe: never moved
    rejoin.begin(10)
    events = []
    for fid, x in ((10, 0.0), (11, 0.1), (12, 0.2)):
        keyframes[fid] = _shift(x)
        events.append(rejoin.step(fid, FRAME, K, keyframes.get))
    assert port.calls == [10, 10]  # frames 10 and 12 (every 2nd), among the keyframes before the restart
    assert events[:2] == [None, None] and events[2].startswith("map rejoined")
    (correction, moved), = port.moves
    assert sorted(moved) == [10, 11, 12]
    for k in (10, 11, 12):
        np.testing.assert_allclose(moved[k][:3, 3], [1.0 + 0.1 * (k - 10) + 0.001, 0, 0], atol=1e-12)
    np.testing.assert_allclose(correction.apply_pose(3, _shift(0.5))[0], _shift(0.5))  # older: held
    assert rejoin.start is None and rejoin.rejoined == 1 and not rejoin.waiting


def test_disagreeing_relocalisations_wait_and_a_second_restart_keeps_the_reference():
    port = Port([(2, _shift(1.0)), (2, _shift(3.0)), (2, _shift(5.0))])
    rejoin, _ = _rejoin(port, every=1)
    rejoin.begin(10)
    assert rejoin.step(10, FRAME, K, EYE) is None
    assert rejoin.step(12, FRAME, K, EYE) is None and not port.moves  # 2 m apart: waits for another
    rejoin.begin(20)  # a second restart: the map of frame 10 stays out of the reference
    rejoin.step(20, FRAME, K, EYE)
    assert port.calls == [10, 10, 10] and rejoin.reference_end == 10


def test_the_attempts_end_after_rejoin_frames():
    port = Port([None] * 3)
    rejoin, _ = _rejoin(port, every=1, frames=3)
    rejoin.begin(10)
    for fid in range(10, 15):
        assert rejoin.step(fid, FRAME, K, EYE) is None
    assert port.calls == [10, 10, 10] and not rejoin.waiting and rejoin.reference_end == 10


def test_monocular_maps_and_failing_attempts_end_quietly():
    port = Port([])
    rejoin, _ = _rejoin(port, every=1, metric=False)
    rejoin.begin(10)
    assert not rejoin.waiting and rejoin.step(10, FRAME, K, EYE) is None and port.calls == []
    port2 = Port([cv2.error("bad image")])
    rejoin2, _ = _rejoin(port2, every=1)
    rejoin2.begin(10)
    assert rejoin2.step(10, FRAME, K, EYE) is None
    assert rejoin2.start is None and rejoin2.reference_end == 10  # given up, the run goes on



def test_a_waiting_map_that_restarts_relocalised_stays_out_of_the_reference():
    """A map waiting to rejoin (begun at 10) loses its track and the restart relocalises: the new map is in
    the reference frame, the waiting one is not, so later relocalisations land only before it."""
    port = Port([(2, np.eye(4))])
    rejoin, _ = _rejoin(port, every=1)
    assert rejoin.reference_before is None  # nothing restarted yet: every keyframe
    rejoin.restarted(10, relocalised=False)
    assert rejoin.waiting and rejoin.reference_before == 10
    rejoin.restarted(20, relocalised=True)
    assert not rejoin.waiting and rejoin.reference_end == 10 and rejoin.reference_before == 10
    rejoin.restarted(30, relocalised=False)
    rejoin.step(30, FRAME, K, EYE)
    assert port.calls == [10]
