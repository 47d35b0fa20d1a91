"""Patch frontend (DPVO / DPV-SLAM family): patch graph, Lucas-Kanade or learned measurements,
local bundle adjustment over Sim(3) keyframe poses. See :mod:`.frontend`."""

from .config import BAConfig, PatchGraphConfig, LKConfig, PatchConfig, PatchTrackingConfig
from .frontend import PatchFrontend
from .measurement import MeasurementSource
from .source import make_source

__all__ = ["BAConfig", "PatchGraphConfig", "LKConfig", "PatchConfig", "PatchFrontend", "PatchTrackingConfig",
           "MeasurementSource", "make_source"]
