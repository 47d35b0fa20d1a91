"""Frontend families and their registry.

:data:`FAMILIES` is the one list of frontend families. An entry names the family (the value of a
run config's ``frontend:`` key and the name of its config section), its config dataclass, its
builder and its part of a run's peak-memory estimate, each as a lazy ``"module:attr"`` path. Adding a
family is one entry here: the run's ``SlamConfig`` (:mod:`fgslam.run.config`) gets a section named
after each family that has a config class (see :func:`family_config_classes`), presets named
``<family>_*.yaml`` load into it, and the memory estimate (:mod:`fgslam.run.memory`) asks the entry
for the family's parts (:meth:`FrontendFamily.memory_parts`, in the vocabulary :class:`MemoryPart`
and :class:`MemorySizes` defined here).

A builder is called as ``builder(section, calibration, sensor_mode, backend=backend)``: the family's
own config section, the camera calibration, ``mono | stereo | rgbd``, and the run's backend (the
frontend builds no backend and no service: the system, :class:`fgslam.run.system.SlamSystem`, owns them
and connects the loop service through :meth:`~fgslam.frontends.base.Frontend.connect`). The registry
knows nothing of the run (:mod:`fgslam.run` imports this module, never the reverse), and each
family is imported only when its config class or builder is first needed, so importing
:mod:`fgslam.frontends` stays cheap.

Families: ``patch`` (DPVO / DPV-SLAM, issue 4), ``dense`` (DROID-SLAM, issue 12) and ``pointmap``
(MASt3R-SLAM, issue 13) are implemented. A family listed without a builder is planned (no config
section, no builder yet) and raises a
:class:`~fgslam.core.errors.ConfigError` that says so.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Optional

from ..core.config import import_object
from ..core.errors import ConfigError
from .base import FrameStatus, Frontend, PoseSource, SensorMode

if TYPE_CHECKING:
    from ..backend import Backend
    from ..io.calibration import Calibration

# ----------------------------------------------------------------------------------------- memory vocabulary

GIB = 1024**3

#: pyramid overhead of an image pyramid (1 + 1/4 + 1/16 + ...)
PYRAMID_FACTOR = 4 / 3
#: B per output pixel of a frame's grey image and of its float32 depth map
GREY_BYTES, DEPTH_BYTES = 1, 4
#: Share of the frames that become keyframes, for what grows with the keyframes (pointmap keyframes,
#: loop-closure descriptors): at most 8 % measured (pointmap 52 of 723 hand-held frames; patch on
#: KITTI and 7-Scenes 5-30 % but it keeps no per-keyframe image), 25 % for a margin. Assuming every
#: frame a keyframe refused honest long sequences (10,000 frames at 512 px over 16 GiB).
KEYFRAME_SHARE = 0.25


@dataclass
class MemoryPart:
    """One part of a run's peak-memory estimate: bytes and the config keys (with their values) that set them."""

    name: str
    bytes: float
    keys: list[str] = field(default_factory=list)

    @property
    def gib(self) -> float:
        return self.bytes / GIB


@dataclass
class MemorySizes:
    """What a family's memory parts read of a run besides the family's own section."""

    width: int  # output images (after resizing and cropping), pixels
    height: int
    frames: int  # frames of the run
    stereo: bool  # sensor stereo
    rgbd: bool  # sensor rgbd
    loop_mode: str  # loop_closure.mode
    size_keys: list[str]  # the dataset keys (with their values) that set the image size


# ----------------------------------------------------------------------------------------- the registry


@dataclass(frozen=True)
class FrontendFamily:
    """One registry entry: a frontend family, its config section class, its builder and its memory parts."""

    name: str  # frontend: <name> in a run config, and the name of its config section
    title: str  # what it is, for messages ("the DPVO / DPV-SLAM patch family")
    config: Optional[str] = None  # "module:Class" of its section dataclass; None: planned, no section yet
    builder: Optional[str] = None  # "module:callable": builder(section, calibration, sensor_mode, backend=backend)
    memory: Optional[str] = None  # "module:callable": memory(section, sizes) -> list[MemoryPart]; None: no parts

    def __post_init__(self) -> None:
        if self.builder is not None and self.config is None:
            raise ValueError(f"frontend family '{self.name}': a builder needs a config section class")

    @property
    def implemented(self) -> bool:
        return self.builder is not None

    def memory_parts(self, section: Any, sizes: MemorySizes) -> list[MemoryPart]:
        """The family's parts of a run's peak-memory estimate for its config ``section`` (an instance
        of its ``config`` class; ``Any``: a user's family has its own), from its ``memory`` callable;
        none without one or without a section."""
        if self.memory is None or section is None:
            return []
        parts = import_object(self.memory, f"frontend family '{self.name}' memory estimate")
        return parts(section, sizes)


#: Every family a config may name, implemented or planned (docs/architecture.md section 1).
FAMILIES: tuple[FrontendFamily, ...] = (
    FrontendFamily("patch", "the DPVO / DPV-SLAM patch family",
                   config="fgslam.frontends.patch.config:PatchConfig",
                   builder="fgslam.frontends.patch.frontend:PatchFrontend",
                   memory="fgslam.frontends.patch.config:memory_parts"),
    FrontendFamily("dense", "the dense DROID-SLAM family",
                   config="fgslam.frontends.dense.config:DenseConfig",
                   builder="fgslam.frontends.dense.frontend:DenseFrontend",
                   memory="fgslam.frontends.dense.config:memory_parts"),
    FrontendFamily("pointmap", "the MASt3R-SLAM pointmap family",
                   config="fgslam.frontends.pointmap.config:PointmapConfig",
                   builder="fgslam.frontends.pointmap.frontend:PointmapFrontend",
                   memory="fgslam.frontends.pointmap.config:memory_parts"),
)

#: Every family name a config may give, implemented or not.
FRONTEND_NAMES: tuple[str, ...] = tuple(f.name for f in FAMILIES)


def available_frontends() -> tuple[str, ...]:
    """Names :func:`make_frontend` can build."""
    return tuple(f.name for f in FAMILIES if f.implemented)


def frontend_family(name: str) -> FrontendFamily:
    """The registry entry of family ``name``; ConfigError naming the known ones otherwise."""
    for family in FAMILIES:
        if family.name == name:
            return family
    raise ConfigError(f"unknown frontend '{name}' (known: {', '.join(FRONTEND_NAMES)}; implemented: "
                      f"{', '.join(available_frontends())})")


def family_config_classes() -> dict[str, type]:
    """Family name -> its config section dataclass, for every family that has one (imports them)."""
    return {f.name: import_object(f.config, f"frontend family '{f.name}' config") for f in FAMILIES
            if f.config is not None}


def make_frontend(name: str, config: Any, calibration: Optional["Calibration"], sensor_mode: SensorMode,
                  backend: "Backend") -> Frontend:
    """Build frontend family ``name`` on the run's ``backend`` for images described by ``calibration``
    in ``sensor_mode`` (mono | stereo | rgbd).

    ``config`` is the family's own section (an instance of its config class, or None for its
    defaults) or a root config holding the family sections, such as :class:`fgslam.run.config.SlamConfig`:
    any object with ``family_section(name)`` (``Any``: each family has its own section class).

    Raises:
        ConfigError: ``name`` is planned but not implemented yet (a registry entry without a builder) or unknown.
    """
    family = frontend_family(name)
    if not family.implemented:
        raise ConfigError(
            f"frontend '{name}' ({family.title}) is not implemented yet: its registry entry has no builder "
            f"(an issue of its own will add it); implemented: {', '.join(available_frontends())}"
        )
    section_class = import_object(family.config, f"frontend family '{name}' config")
    section = config
    if config is not None and not isinstance(config, section_class):
        if not hasattr(config, "family_section"):
            raise TypeError(f"make_frontend('{name}', ...): config must be a {section_class.__name__}, None, or a "
                            f"root config with family_section(), got {type(config).__name__}")
        section = config.family_section(name)
    builder = import_object(family.builder, f"frontend family '{name}' builder")
    return builder(section, calibration, sensor_mode, backend=backend)


__all__ = ["DEPTH_BYTES", "FAMILIES", "FRONTEND_NAMES", "GIB", "GREY_BYTES", "KEYFRAME_SHARE", "PYRAMID_FACTOR",
           "FrameStatus", "Frontend", "FrontendFamily", "MemoryPart", "MemorySizes", "PoseSource", "SensorMode",
           "available_frontends", "family_config_classes", "frontend_family", "make_frontend"]
