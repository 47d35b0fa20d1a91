"""Dense frontend (DROID-SLAM family): frame graph of keyframes with 1/8-resolution inverse-depth maps,
measured by dense flow revisions (:mod:`.source`) and optimised as Schur-eliminated dense blocks
(:mod:`fgslam.factors.dense`) through the backend. Only the measurement sources exist so far."""
