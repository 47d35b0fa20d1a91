"""Pointmap frontend (MASt3R-SLAM family): two-view pointmap sources (:mod:`.source`), dense
descriptors (:mod:`.descriptors`) and iterative projective matching (:mod:`.matching`); the pose-only
ray blocks it emits to the backend live in :mod:`fgslam.factors.pointmap_block`. Tracking, fusion,
keyframing and the frontend itself do not exist yet (issue 13)."""
