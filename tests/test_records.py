"""Typed pose records shared by the frontend families (fgslam.frontends.records): resolution through
references and re-expression under a pose correction."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from fgslam.frontends.records import sim3_interp as _interp
from fgslam.frontends.records import (AbsolutePose, InterpolatedPose, KeyframePose, RelativePose,
                                            resolve_pose)
from fgslam.loop.records import PoseCorrection


def _sim3(yaw: float, t, s: float = 1.0) -> np.ndarray:
    c, si = np.cos(yaw), np.sin(yaw)
    T = np.eye(4)
    T[:3, :3] = s * np.array([[c, 0, si], [0, 1, 0], [-si, 0, c]])
    T[:3, 3] = t
    return T


KF = {0: _sim3(0.1, [0, 0, 0], 1.0), 4: _sim3(0.3, [1.0, 0.2, 2.0], 1.5)}


def _records():
    return {0: KeyframePose(), 4: KeyframePose(), 1: RelativePose(0, _sim3(0.05, [0.1, 0, 0.3])),
            2: InterpolatedPose(1, 4, 0.25), 3: AbsolutePose(_sim3(-0.2, [5.0, 1.0, 0.0], 2.0)), 5: None,
            6: RelativePose(5, np.eye(4))}


def test_resolution_follows_references():
    records = _records()
    cache: dict = {}
    T = {fid: resolve_pose(fid, records, KF.__getitem__, cache) for fid in range(7)}
    np.testing.assert_array_equal(T[0], KF[0])
    np.testing.assert_allclose(T[1], KF[0] @ records[1].T_ref_frame, atol=1e-15)
    np.testing.assert_allclose(T[2], _interp(T[1], KF[4], 0.25), atol=1e-12)
    np.testing.assert_array_equal(T[3], records[3].T_WC)
    assert T[5] is None and T[6] is None  # no pose, and a frame relative to it
    assert resolve_pose(99, records, KF.__getitem__, cache) is None  # unknown frame
    assert set(cache) >= set(range(7))


def test_a_reference_cycle_gives_no_pose_not_an_endless_recursion(caplog):
    """A record that refers (directly or through others) back to itself resolves to None with a warning;
    the frames around it still resolve."""
    records = _records()
    records[6] = RelativePose(6, np.eye(4))
    records[7], records[8] = RelativePose(8, np.eye(4)), InterpolatedPose(0, 7, 0.5)
    records[9] = RelativePose(7, np.eye(4))
    cache = {}
    with caplog.at_level("WARNING", logger="fgslam.frontends.records"):
        assert resolve_pose(6, records, KF.__getitem__, cache) is None
        assert resolve_pose(9, records, KF.__getitem__, cache) is None
    assert "refers back to itself" in caplog.text
    np.testing.assert_allclose(resolve_pose(1, records, KF.__getitem__, cache), KF[0] @ records[1].T_ref_frame)
    # a lookup that raises leaves no frame marked as in progress: the next one in the same cache resolves
    cache, calls = {}, []

    def failing_once(kf):
        calls.append(kf)
        if len(calls) == 1:
            raise RuntimeError("keyframe pose not ready")
        return KF[kf]

    with pytest.raises(RuntimeError):
        resolve_pose(1, records, failing_once, cache)
    np.testing.assert_allclose(resolve_pose(1, records, failing_once, cache), KF[0] @ records[1].T_ref_frame)


def test_records_are_immutable():
    with pytest.raises(dataclasses.FrozenInstanceError):
        _records()[1].ref = 4


@pytest.mark.parametrize("fold", [True, False])
def test_correction_reexpresses_the_records(fold):
    """After a correction, every frame's pose is the corrected one: keyframes ``U_k T`` (scale folded:
    pose keeps its scale), relative records follow their reference with the translation in the folded
    units, absolute records get their own update, interpolated ones follow their ends."""
    U = {0: _sim3(0.2, [1.0, 0, 0], 1.3), 4: _sim3(-0.1, [0, 2.0, 0.5], 0.8)}
    corr = PoseCorrection(U, {0: 1.3, 4: 0.8}, {}, [], fold, 1, 0.0)
    records = _records()
    new = {fid: (rec.corrected(fid, corr) if rec is not None else None) for fid, rec in records.items()}
    assert new[0] is records[0] and new[2] is records[2]  # keyframes and interpolations are unchanged records
    assert (new[1] is records[1]) == (not fold)
    kf_new = {k: corr.apply_pose(k, T)[0] for k, T in KF.items()}
    T_old = resolve_pose(1, records, KF.__getitem__, {})
    T_new = resolve_pose(1, new, kf_new.__getitem__, {})
    if fold:  # the relative pose is rescaled with its reference's fold factor
        np.testing.assert_allclose(new[1].T_ref_frame[:3, 3], 1.3 * records[1].T_ref_frame[:3, 3], atol=1e-15)
        np.testing.assert_allclose(new[1].T_ref_frame[:3, :3], records[1].T_ref_frame[:3, :3], atol=0)
    else:  # rigid world update: the frame moves with its keyframe
        np.testing.assert_allclose(T_new, U[0] @ T_old, atol=1e-12)
    np.testing.assert_allclose(new[3].T_WC, corr.apply_pose(3, records[3].T_WC)[0], atol=0)
    assert not np.allclose(new[3].T_WC, records[3].T_WC)


def test_per_frame_motion_composes_back_to_the_whole_motion():
    """``steps`` applications of the per-frame motion take T_prev to T_new; one step is the motion itself."""
    import gtsam as _gtsam

    from fgslam.frontends.records import per_frame_motion
    from fgslam.core.lie import gtsam_matrix

    T_prev = gtsam_matrix(_gtsam.Similarity3(_gtsam.Rot3.Expmap([0.1, -0.2, 0.05]), [0.3, 0.1, -0.2], 1.3))
    T_new = gtsam_matrix(_gtsam.Similarity3(_gtsam.Rot3.Expmap([0.3, -0.1, 0.15]), [0.6, 0.2, 0.1], 1.1))
    V = per_frame_motion(T_prev, T_new, 3)
    np.testing.assert_allclose(T_prev @ V @ V @ V, T_new, atol=1e-9)
    np.testing.assert_allclose(per_frame_motion(T_prev, T_new, 1), np.linalg.inv(T_prev) @ T_new, atol=1e-12)
