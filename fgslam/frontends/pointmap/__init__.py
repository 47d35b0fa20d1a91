"""Pointmap frontend (MASt3R-SLAM family, issue 13): two-view pointmap sources (:mod:`.source`), dense
descriptors (:mod:`.descriptors`), iterative projective matching (:mod:`.matching`), tracking and fusion
(:mod:`.tracking`), keyframes and edge measurement (:mod:`.keyframes`), the frontend (:mod:`.frontend`,
config :mod:`.config`; its collaborators :mod:`.tracker`, :mod:`.relocalization`, :mod:`.mapping`,
:mod:`.edges`, :mod:`.cache`, :mod:`.contributor`, :mod:`.export`, :mod:`.camera`) and the mixed-family contributor (:mod:`.mix`); the pose-only ray blocks it emits
to the backend live in :mod:`fgslam.factors.pointmap_block`."""
