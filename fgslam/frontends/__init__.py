"""Frontend families and their registry.

:data:`FAMILIES` is the one list of frontend families. An entry names the family (the value of a
run config's ``frontend:`` key and the name of its config section), its config dataclass and its
builder, both as lazy ``"module:attr"`` paths. Adding a family is one entry here: the runner's
``SlamConfig`` gets a section named after each family that has a config class (see
:func:`family_config_classes`), and presets named ``<family>_*.yaml`` load into it.

A builder is called as ``builder(section, calibration, sensor_mode, backend=backend)``: the family's
own config section, the camera calibration, ``mono | stereo | rgbd``, and the run's backend (the
frontend builds no backend and no service: the system, :class:`fgslam.system.SlamSystem`, owns them
and connects the loop service through :meth:`~fgslam.frontends.base.Frontend.connect`). The registry
knows nothing of the system (:mod:`fgslam.system` imports this module, never the reverse), and each
family is imported only when its config class or builder is first needed, so importing
:mod:`fgslam.frontends` stays cheap.

Families: ``patch`` (DPVO / DPV-SLAM, issue 4), ``dense`` (DROID-SLAM, issue 12) and ``pointmap``
(MASt3R-SLAM, issue 13) are implemented. A family listed without a builder is planned (no config
section, no builder yet) and raises a
:class:`~fgslam.errors.ConfigError` that says so.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Optional

from ..config import import_object
from ..errors import ConfigError
from .base import FrameStatus, Frontend, PoseSource, SensorMode


@dataclass(frozen=True)
class FrontendFamily:
    """One registry entry: a frontend family, its config section class and its builder."""

    name: str  # frontend: <name> in a run config, and the name of its config section
    title: str  # what it is, for messages ("the DPVO / DPV-SLAM patch family")
    config: Optional[str] = None  # "module:Class" of its section dataclass; None: planned, no section yet
    builder: Optional[str] = None  # "module:callable": builder(section, calibration, sensor_mode, backend=backend)

    def __post_init__(self) -> None:
        if self.builder is not None and self.config is None:
            raise ValueError(f"frontend family '{self.name}': a builder needs a config section class")

    @property
    def implemented(self) -> bool:
        return self.builder is not None


#: Every family a config may name, implemented or planned (docs/design.md section 1).
FAMILIES: tuple[FrontendFamily, ...] = (
    FrontendFamily("patch", "the DPVO / DPV-SLAM patch family",
                   config="fgslam.frontends.patch.config:PatchConfig",
                   builder="fgslam.frontends.patch.frontend:PatchFrontend"),
    FrontendFamily("dense", "the dense DROID-SLAM family",
                   config="fgslam.frontends.dense.config:DenseConfig",
                   builder="fgslam.frontends.dense.frontend:DenseFrontend"),
    FrontendFamily("pointmap", "the MASt3R-SLAM pointmap family",
                   config="fgslam.frontends.pointmap.config:PointmapConfig",
                   builder="fgslam.frontends.pointmap.frontend:PointmapFrontend"),
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


def make_frontend(name: str, config: Any, calibration: Any, sensor_mode: SensorMode, backend: Any) -> Frontend:
    """Build frontend family ``name`` on the run's ``backend`` for images described by ``calibration``
    in ``sensor_mode`` (mono | stereo | rgbd).

    ``config`` is the family's own section (an instance of its config class, or None for its
    defaults) or a root config holding the family sections, such as :class:`fgslam.runconfig.SlamConfig`:
    any object with ``family_section(name)``.

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


__all__ = ["FAMILIES", "FRONTEND_NAMES", "FrameStatus", "Frontend", "FrontendFamily", "PoseSource", "SensorMode",
           "available_frontends", "family_config_classes", "frontend_family", "make_frontend"]
