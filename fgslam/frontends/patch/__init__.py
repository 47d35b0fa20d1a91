"""Patch frontend (DPVO / DPV-SLAM family): patch graph, Lucas-Kanade or learned measurements,
local bundle adjustment over Sim(3) keyframe poses. See :mod:`.frontend`."""

from .config import BAConfig, GraphConfig, LKConfig, PatchConfig, TrackingConfig
from .frontend import PatchFrontend
from .measurement import MeasurementSource
from .source import make_source

__all__ = ["BAConfig", "GraphConfig", "LKConfig", "PatchConfig", "PatchFrontend", "TrackingConfig",
           "MeasurementSource", "make_source"]
