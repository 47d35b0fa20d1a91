"""Pointmap frontend (MASt3R-SLAM family, issue 13): two-view pointmap sources (:mod:`.source`), dense
descriptors (:mod:`.descriptors`), iterative projective matching (:mod:`.matching`), tracking and fusion
(:mod:`.tracking`), keyframes and edge measurement (:mod:`.keyframes`), the monocular feature tracks
(:mod:`.features`), the frontend (:mod:`.frontend`, config :mod:`.config`; its shared state
:mod:`.state` and the collaborators that take it: :mod:`.cache`, :mod:`.tracker`, :mod:`.relocalization`,
:mod:`.edges`, :mod:`.mapping`, :mod:`.pair_tracking`, :mod:`.feature_tracking`, :mod:`.contributor`;
:mod:`.export`, :mod:`.camera`) and the mixed-family contributor (:mod:`.mix`); the pose-only ray blocks
it emits to the backend live in :mod:`fgslam.factors.pointmap_block`."""
