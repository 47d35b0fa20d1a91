"""Synthetic sequences with exact ground truth: textured ray-cast scenes, stereo, depth and IMU,
written in the EuRoC layout (see :mod:`.writer`)."""

from .scenarios import PRESET_NAMES, SynthConfig, default_config
from .sequence import StereoFrame, SynthSequence
from .writer import WriteSummary, write_sequence, write_tumvi_sequence

__all__ = ["PRESET_NAMES", "SynthConfig", "default_config", "SynthSequence", "StereoFrame",
           "WriteSummary", "write_sequence", "write_tumvi_sequence"]
