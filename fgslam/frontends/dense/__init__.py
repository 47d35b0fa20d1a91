"""Dense frontend (DROID-SLAM family): frame graph of keyframes with 1/8-resolution inverse-depth maps,
measured by dense flow revisions (:mod:`.source`) and optimised as Schur-eliminated dense blocks
(:mod:`fgslam.factors.dense`) through the backend (:mod:`.frontend` with its shared state :mod:`.state` and
its collaborators :mod:`.tracking`, :mod:`.keyframes`, :mod:`.ba`, :mod:`.lifecycle`, :mod:`.contributor`,
:mod:`.export`, :mod:`.weights`; :mod:`.graph`, :mod:`.config`).

The config is imported here; the frontend (which pulls torch and OpenCV) when first asked for
(``from fgslam.frontends.dense import DenseFrontend``), so that a run's config loads without them."""

from .config import DenseConfig

__all__ = ["DenseConfig", "DenseFrontend"]


def __getattr__(name: str):
    """``DenseFrontend`` (PEP 562): imported from :mod:`.frontend` when first asked for."""
    if name != "DenseFrontend":
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    from .frontend import DenseFrontend

    globals()[name] = DenseFrontend
    return DenseFrontend
