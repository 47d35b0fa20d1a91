"""Frontend families and their registry.

``make_frontend(name, config, calibration, sensor_mode)`` builds the frontend a
:class:`fgslam.slam.SlamConfig` names (``config.frontend``). Each family is imported only when it
is built, so importing :mod:`fgslam.frontends` stays cheap and a family's heavy dependencies are
loaded only by the runs that use it.

Families: ``patch`` (DPVO / DPV-SLAM, issue 4) is implemented; ``dense`` (DROID-SLAM) and
``pointmap`` (MASt3R-SLAM) are planned and raise a :class:`~fgslam.errors.ConfigError` that says so.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Callable

from ..errors import ConfigError
from .base import FrameStatus, Frontend, PoseSource, SensorMode

if TYPE_CHECKING:  # pragma: no cover - typing only
    from ..backend import Backend
    from ..io.calibration import Calibration
    from ..slam import SlamConfig

#: Every family name a config may give, implemented or not.
FRONTEND_NAMES: tuple[str, ...] = ("patch", "dense", "pointmap")

# Families that are designed (docs/design.md section 1) but have no implementation yet.
_PLANNED: dict[str, str] = {
    "dense": "the dense DROID-SLAM family",
    "pointmap": "the MASt3R-SLAM pointmap family",
}


def _build_patch(config: SlamConfig, calibration: Calibration, sensor_mode: SensorMode,
                 backend: Backend | None = None) -> Frontend:
    from .patch.frontend import PatchFrontend

    return PatchFrontend(config.patch, calibration, sensor_mode, map_config=config.map,
                         loop_config=config.loop_closure, backend=backend)


_BUILDERS: dict[str, Callable[..., Frontend]] = {
    "patch": _build_patch,
}


def available_frontends() -> tuple[str, ...]:
    """Names :func:`make_frontend` can build."""
    return tuple(_BUILDERS)


def make_frontend(name: str, config: SlamConfig, calibration: Calibration, sensor_mode: SensorMode,
                  backend: Backend | None = None) -> Frontend:
    """Build frontend family ``name`` from the run's ``config`` (its section ``config.<name>``,
    ``config.map`` and ``config.loop_closure``) for images described by ``calibration`` in ``sensor_mode`` (mono|stereo|rgbd),
    feeding ``backend`` (the run's :class:`fgslam.backend.Backend`; None: the frontend builds its own
    from ``config.map``).

    Raises:
        ConfigError: ``name`` is planned but not implemented yet (``dense``, ``pointmap``) or unknown.
    """
    builder = _BUILDERS.get(name)
    if builder is not None:
        return builder(config, calibration, sensor_mode, backend=backend)
    if name in _PLANNED:
        raise ConfigError(
            f"frontend '{name}' ({_PLANNED[name]}) is not implemented yet: it has no issue of its own so far "
            f"(the patch frontend of issue 4 is the one available); set frontend: patch"
        )
    raise ConfigError(f"unknown frontend '{name}' (known: {', '.join(FRONTEND_NAMES)}; implemented: "
                      f"{', '.join(available_frontends())})")


__all__ = ["FRONTEND_NAMES", "FrameStatus", "Frontend", "PoseSource", "SensorMode", "available_frontends",
           "make_frontend"]
