"""Readers of the synthetic generator's data tables, shipped with the package in
``fgslam/io/synth/data/``: the presets' sensor sections (``presets.yaml``, used by
:func:`~fgslam.io.synth.scenarios.default_config`) and the harmonic tables of the preset motions
(``motions.yaml``, used by :mod:`.motions`).

The files are read on first use (never at import) through :mod:`importlib.resources`, so an installed
fgslam finds them as well as a checkout, and kept for the process; the returned tables are shared:
read them, never change them. A malformed table is a :class:`~fgslam.core.errors.ConfigError` naming the
file and the key.
"""

from __future__ import annotations

import functools
from importlib import resources
from pathlib import Path
from typing import Any

from ...core.config import read_yaml
from ...core.errors import ConfigError

DATA_FOLDER = "data"
PRESETS_FILE = "presets.yaml"
MOTIONS_FILE = "motions.yaml"

#: one term of a motion: {harmonic k (1, 2, ...): amplitude (m or rad)}
Harmonics = dict[int, float]
#: one motion: {term name (``x_cos``, ``yaw_sin``, ...): its harmonics}
MotionTable = dict[str, Harmonics]


def data_path(name: str) -> Path:
    """Path of the data file ``name`` of this package's ``data`` folder."""
    return Path(str(resources.files(__package__).joinpath(DATA_FOLDER, name)))


@functools.cache
def preset_sections() -> dict[str, dict[str, dict[str, Any]]]:
    """``{preset: {section: {field: parsed YAML value}}}`` of ``presets.yaml`` (shared: read only)."""
    path = data_path(PRESETS_FILE)
    out: dict[str, dict[str, dict[str, Any]]] = {}
    for preset, sections in read_yaml(path).items():
        if not isinstance(sections, dict) or not all(isinstance(v, dict) for v in sections.values()):
            raise ConfigError(f"{path}: key '{preset}': expected a mapping of sections to mappings of fields")
        out[str(preset)] = sections
    return out


@functools.cache
def motion_tables() -> dict[str, MotionTable]:
    """``{motion: {term: {harmonic: amplitude}}}`` of ``motions.yaml`` (shared: read only)."""
    path = data_path(MOTIONS_FILE)
    out: dict[str, MotionTable] = {}
    for motion, terms in read_yaml(path).items():
        if not isinstance(terms, dict):
            raise ConfigError(f"{path}: key '{motion}': expected a mapping of terms to harmonics")
        table: MotionTable = {}
        for term, harmonics in terms.items():
            if not isinstance(harmonics, dict) or not all(
                    isinstance(k, int) and not isinstance(k, bool) and k >= 1 and isinstance(a, float)
                    for k, a in harmonics.items()):
                raise ConfigError(f"{path}: key '{motion}.{term}': expected {{harmonic (integer >= 1): "
                                  f"amplitude (a number with a decimal point)}} (got {harmonics!r})")
            table[str(term)] = dict(harmonics)
        out[str(motion)] = table
    return out
