"""The factor-plugin contract (:mod:`fgslam.services.plugins` loads and runs plugins): what a plugin
class offers (:class:`FactorPlugin`) and how it reads its typed options (:func:`parse_options`), so
that a plugin written in a frontend family (e.g. :mod:`fgslam.frontends.pointmap.mix`) needs
nothing of the service."""

from __future__ import annotations

from collections.abc import Mapping
from typing import TYPE_CHECKING, Protocol, TypeVar

from ..core.config import from_dict

if TYPE_CHECKING:
    from ..backend.graph import Backend

T = TypeVar("T")


class FactorPlugin(Protocol):
    """What the runner needs from a plugin class (built as ``Cls(options, key)``): ``attach`` with
    the run's backend; ``check_run(timestamps)``, ``poll(backend)`` and ``finish(backend)`` are
    optional (:mod:`fgslam.services.plugins`)."""

    def attach(self, backend: Backend) -> None: ...


def parse_options(cls: type[T], options: Mapping[str, object], key: str) -> T:
    """A plugin's options (the config's parsed values) as the typed dataclass ``cls`` (ranges
    checked); a ConfigError names the option as ``<key>.options.<name>``."""
    return from_dict(cls, options, source="factor plugin", prefix=f"{key}.options.")
