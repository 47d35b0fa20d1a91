"""Dense frontend (DROID-SLAM family): frame graph of keyframes with 1/8-resolution inverse-depth maps,
measured by dense flow revisions (:mod:`.source`) and optimised as Schur-eliminated dense blocks
(:mod:`fgslam.factors.dense`) through the backend (:mod:`.frontend` with its shared state :mod:`.state` and
its collaborators :mod:`.tracking`, :mod:`.keyframes`, :mod:`.ba`, :mod:`.lifecycle`, :mod:`.contributor`,
:mod:`.export`, :mod:`.weights`; :mod:`.graph`, :mod:`.config`)."""

from .config import DenseConfig
from .frontend import DenseFrontend

__all__ = ["DenseConfig", "DenseFrontend"]
