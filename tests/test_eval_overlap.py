"""fgslam.eval.overlap: the share of a frame's view that a map keyframe saw, by ground truth."""

import numpy as np
import pytest

from fgslam.eval.overlap import grid_pixels, seen_share, view_overlap, view_samples

K = np.array([100.0, 100.0, 32.0, 24.0])  # 64 x 48 pixels
W, H = 64, 48


def plane(z: float) -> np.ndarray:
    return np.full((H, W), z, dtype=np.float32)


def pose(t=(0.0, 0.0, 0.0), yaw_deg: float = 0.0) -> np.ndarray:
    a = np.radians(yaw_deg)
    T = np.eye(4)
    T[:3, :3] = [[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]]
    T[:3, 3] = t
    return T


def test_grid_pixels_are_cell_centres_inside_the_image():
    u, v = grid_pixels(W, H, (4, 3))
    assert sorted(set(u.tolist())) == [8, 24, 40, 56] and sorted(set(v.tolist())) == [8, 24, 40]
    assert len(u) == 12


def test_a_view_is_all_seen_by_itself_and_half_by_a_camera_moved_half_its_width():
    view = view_samples(plane(2.0), K, pose())
    assert len(view.X_C) == 32 * 24
    assert seen_share(view, plane(2.0), K, pose()) == 1.0
    # the image spans x in [-0.64, 0.64] m at 2 m; moved by 0.64 m the keyframe sees the half with x >= 0
    assert seen_share(view, plane(2.0), K, pose((0.64, 0.0, 0.0))) == 0.5
    assert seen_share(view, plane(2.0), K, pose((2.0, 0.0, 0.0))) == 0.0


def test_points_behind_the_camera_occluded_or_in_holes_are_not_seen():
    view = view_samples(plane(2.0), K, pose())
    assert seen_share(view, plane(2.0), K, pose(yaw_deg=180.0)) == 0.0  # looking away
    assert seen_share(view, plane(1.0), K, pose()) == 0.0  # a nearer surface hides the points
    assert seen_share(view, plane(2.1), K, pose()) == 1.0  # within the 10 % of the keyframe's depth
    assert seen_share(view, plane(2.2), K, pose()) == 1.0  # 0.2 m off, within 10 % of 2.2 m: relative
    assert seen_share(view, plane(1.8), K, pose()) == 0.0  # 0.2 m off, beyond 10 % of 1.8 m
    assert seen_share(view, plane(2.0), K, pose(), depth_tolerance=0.01) == 1.0
    assert seen_share(view, plane(2.1), K, pose(), depth_tolerance=0.01) == 0.0
    holes = plane(2.0)
    holes[:, : W // 2] = 0.0
    holes[1, -1] = np.nan  # a grid pixel (cell centres: rows 1, 3, 5, ...): one point fewer seen
    assert seen_share(view, holes, K, pose()) == 0.5 - 1 / (32 * 24)


def test_the_keyframe_pose_is_camera_to_world():
    """The keyframe 0.64 m to the right sees the frame's right half, at its own left: the half of its depth
    image on the right holds nothing of it (the inverse convention would look at the other half)."""
    view = view_samples(plane(2.0), K, pose())
    right_empty = plane(2.0)
    right_empty[:, W // 2:] = 0.0
    assert seen_share(view, right_empty, K, pose((0.64, 0.0, 0.0))) == 0.5
    left_empty = plane(2.0)
    left_empty[:, : W // 2] = 0.0
    assert seen_share(view, left_empty, K, pose((0.64, 0.0, 0.0))) == 0.0


def test_pixels_without_depth_leave_the_view_and_an_empty_view_is_unseen():
    d = plane(2.0)
    d[: H // 2] = 0.0
    d[H // 2 + 1, 1] = np.nan  # a grid pixel (cell centres: 1, 3, 5, ...)
    view = view_samples(d, K, pose())
    assert len(view.X_C) == 32 * 12 - 1
    assert seen_share(view, plane(2.0), K, pose()) == 1.0
    empty = view_samples(np.zeros((H, W), np.float32), K, pose())
    assert seen_share(empty, plane(2.0), K, pose()) == 0.0


def test_the_overlap_is_the_keyframe_that_saw_most():
    view = view_samples(plane(2.0), K, pose((5.0, 0.0, 0.0)))
    keys = np.stack([pose((7.0, 0.0, 0.0)), pose((5.64, 0.0, 0.0)), pose((5.0, 0.0, 0.0), yaw_deg=180.0)])
    assert view_overlap(view, [plane(2.0)] * 3, K, keys) == 0.5
    assert view_overlap(view, [], K, np.zeros((0, 4, 4))) == 0.0
    with pytest.raises(ValueError):
        view_overlap(view, [plane(2.0)] * 2, K, keys)
