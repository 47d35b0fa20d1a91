"""The persistent GTSAM backend that every frontend feeds (docs/design.md section 1).

Modules: :mod:`.keys` (gtsam keys of keyframe poses and other variables), :mod:`.blocks` (the
contract of a frontend's measurement blocks), :mod:`.solver` (the one Levenberg-Marquardt loop).
Importing this package imports no gtsam or torch (each module imports them where used).
"""
