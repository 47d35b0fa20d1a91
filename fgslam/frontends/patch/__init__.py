"""Patch frontend (DPVO / DPV-SLAM family): patch graph, Lucas-Kanade or learned measurements,
local bundle adjustment over Sim(3) keyframe poses. See :mod:`.frontend`.

The configs are imported here; the frontend, its measurement sources and ``make_source`` (which
pull torch and OpenCV) when first asked for (``from fgslam.frontends.patch import PatchFrontend``),
so that a run's config loads without them."""

from .config import BAConfig, PatchGraphConfig, LKConfig, PatchConfig, PatchTrackingConfig

#: name -> module of this package that defines it, imported on first access (:func:`__getattr__`)
_DEFERRED = {"PatchFrontend": "frontend", "MeasurementSource": "measurement", "make_source": "source"}

__all__ = ["BAConfig", "PatchGraphConfig", "LKConfig", "PatchConfig", "PatchFrontend", "PatchTrackingConfig",
           "MeasurementSource", "make_source"]


def __getattr__(name: str):
    """The deferred names of :data:`_DEFERRED` (PEP 562): imported from their module when first asked for."""
    if name not in _DEFERRED:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    from importlib import import_module

    value = getattr(import_module(f".{_DEFERRED[name]}", __name__), name)
    globals()[name] = value
    return value
