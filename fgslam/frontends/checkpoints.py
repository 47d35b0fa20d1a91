"""The one check of a learned measurement source's checkpoint (patch: DPVO, dense: DROID-SLAM,
pointmap: MASt3R). fgslam ships no weights and downloads nothing; a learned source whose
checkpoint (or package) is missing fails at construction with an error that names the config key
and the built-in alternative, never a silent fallback (docs/architecture.md section 7).

:func:`checkpoint_path` returns the checked path (DROID and DPVO run from it, :mod:`fgslam.nets`);
:func:`require_checkpoint` is for a slot whose network is not part of this build (MASt3R)."""

from __future__ import annotations

import importlib.util
from dataclasses import dataclass
from pathlib import Path
from typing import NoReturn, Optional

from ..core.errors import ConfigError, DataError


@dataclass(frozen=True)
class LearnedSlot:
    """What the errors of one learned source name."""

    network: str  # "DPVO"
    weights: str  # the checkpoint file users look for: "dpvo.pth"
    selected: str  # the setting that chose it: "patch.source=learned"
    key: str  # the checkpoint's config key: "patch.checkpoint"
    builtin: str  # the built-in alternative: "patch.source=lk"
    package: Optional[str] = None  # a Python package the network also needs ("mast3r")


def checkpoint_path(slot: LearnedSlot, checkpoint: str | None) -> Path:
    """The configured checkpoint of ``slot``, checked: no checkpoint configured is a ConfigError, a
    missing file or an absent package a DataError, each naming the key and the built-in alternative."""
    if checkpoint is None:
        raise ConfigError(f"{slot.selected} needs {slot.key}, the path of the {slot.network} weights "
                          f"({slot.weights}); the built-in alternative is {slot.builtin}")
    path = Path(checkpoint).expanduser()
    if path.is_dir():
        raise DataError(f"{slot.network} checkpoint {path} ({slot.key}) is a folder; a file is expected "
                        f"({slot.weights}), or use {slot.builtin}")
    if not path.is_file():
        raise DataError(f"{slot.network} checkpoint {path} not found ({slot.key}); fgslam downloads nothing: get "
                        f"{slot.weights} from the {slot.network} project, or use {slot.builtin}")
    if slot.package is not None and importlib.util.find_spec(slot.package) is None:
        raise DataError(f"{slot.selected} needs the {slot.package} package (not installed; fgslam does not install "
                        f"it); or use {slot.builtin}")
    return path


def load_learned(slot: LearnedSlot, checkpoint: str | None, build):
    """``build(path)`` for the checked checkpoint of ``slot`` (:func:`checkpoint_path`); a file the
    loader rejects (:class:`fgslam.nets.checkpoint.CheckpointError`) is re-raised naming the config key
    and the built-in alternative."""
    from ..nets.checkpoint import CheckpointError  # deferred: torch (fgslam.nets; pointmap's source loads none)

    path = checkpoint_path(slot, checkpoint)
    try:
        return build(path)
    except CheckpointError as exc:
        raise CheckpointError(f"{exc} ({slot.key}); use {slot.weights} from the {slot.network} project, or "
                              f"{slot.builtin}") from None


def require_checkpoint(slot: LearnedSlot, checkpoint: str | None) -> NoReturn:
    """Raise the error that says why the learned source ``slot`` cannot run: the errors of
    :func:`checkpoint_path`, or, with checkpoint and package present, that the network's adapter is
    not part of this build (DataError)."""
    path = checkpoint_path(slot, checkpoint)
    raise DataError(f"{slot.network} checkpoint {path} found, but the learned {slot.network} network is not part "
                    f"of this fgslam build yet; use the built-in source with {slot.builtin}")
