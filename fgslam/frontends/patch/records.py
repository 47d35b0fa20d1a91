"""Pose records of the patch frontend: the shared :mod:`fgslam.frontends.records` (re-exported here)."""

from ..records import AbsolutePose, InterpolatedPose, KeyframePose, PoseRecord, RelativePose, resolve_pose

__all__ = ["AbsolutePose", "InterpolatedPose", "KeyframePose", "PoseRecord", "RelativePose", "resolve_pose"]
