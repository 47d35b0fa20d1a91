"""Outputs written whole or not at all: a temporary sibling moved into place (:func:`written_in_place`).

An output ``DIR/NAME`` (a file or a folder) is written into ``DIR/.NAME.tmp<PID>`` and renamed over
``NAME`` once complete. A file replaces an existing one in one atomic rename; a folder cannot be renamed
over a folder that holds anything, so the existing one is first renamed aside to ``DIR/.NAME.old<PID>``,
the new one renamed into place, and the old copy removed last (put back when the second rename fails).
Whatever happens (an error, Ctrl-C, a failed rename) the previous output stays or the new one is in place:
never neither.

A process killed outright (SIGKILL, a power cut) leaves its siblings behind; the next write of the same
output removes those of processes no longer running (:func:`sweep_stale`), and puts a previous output
moved aside back when nothing took its place.
"""

from __future__ import annotations

import contextlib
import logging
import os
import re
import shutil
from collections.abc import Callable, Iterator
from pathlib import Path

from ..core.errors import ConfigError, DataError

logger = logging.getLogger(__name__)

#: the new output being written: ``.NAME.tmp<PID>``
TMP_TAG = "tmp"
#: the previous output, moved aside while the new one is renamed into place: ``.NAME.old<PID>``
OLD_TAG = "old"


def sibling(path: Path, tag: str, pid: int | None = None) -> Path:
    """The hidden sibling ``.NAME.<tag><PID>`` of ``path`` (this process's by default)."""
    return path.with_name(f".{path.name}.{tag}{os.getpid() if pid is None else pid}")


def _os_error(what: str, exc: OSError) -> DataError:
    """A one-line error for an OSError of a file operation (``what`` names it)."""
    where = f" ({exc.filename})" if exc.filename else ""
    return DataError(f"{what}: {exc.strerror or exc}{where}")


def _exists(path: Path) -> bool:
    return path.exists() or path.is_symlink()


def remove(path: Path) -> None:
    """Remove a file, a link (not what it points to) or a folder with what it holds; nothing if absent."""
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path)
    elif _exists(path):
        path.unlink()


def _running(pid: int) -> bool:
    """Whether a process ``pid`` runs (this process's own siblings are left overs of an earlier write:
    not running). Where that cannot be told (Windows, whose ``os.kill`` would end the process), True:
    the sibling is kept."""
    if pid == os.getpid():
        return False
    if os.name == "nt":
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except OSError:  # another user's process (PermissionError), or a pid out of range: kept
        return True
    return True


def sweep_stale(path: Path) -> None:
    """Remove the siblings of ``path`` (:func:`sibling`: exactly ``.NAME.tmp<PID>``, ``.NAME.old<PID>``)
    left by writes whose process no longer runs; a previous output moved aside (``old``) is put back when
    ``path`` is missing (the write was killed between its two renames). Best effort: a sibling that cannot
    be removed is named in a warning and kept."""
    pattern = re.compile(rf"\.{re.escape(path.name)}\.({TMP_TAG}|{OLD_TAG})(\d+)")
    try:
        names = [p.name for p in path.parent.iterdir()]
    except OSError:  # no parent folder, or not readable: checked by the caller
        return
    matches = [m for m in map(pattern.fullmatch, names) if m is not None and not _running(int(m.group(2)))]
    for match in sorted(matches, key=lambda m: m.group(1) != OLD_TAG):  # an old copy is put back first
        name = match.group(0)
        stale = path.parent / name
        try:
            if match.group(1) == OLD_TAG and not _exists(path):
                os.replace(stale, path)
                logger.warning("%s: put back the previous output that an interrupted write had moved aside", path)
                continue
            remove(stale)
            logger.info("removed %s, left by an interrupted write of %s", stale, path)
        except OSError as exc:
            logger.warning("cannot remove %s, left by an interrupted write: %s", stale, exc.strerror or exc)


def refuse_existing(path: Path, overwrite: bool) -> None:
    """The default check of an output: an existing ``path`` is refused unless ``overwrite``."""
    if _exists(path) and not overwrite:
        raise ConfigError(f"{path}: exists (use --overwrite to replace it)")


def check_target(path: Path, overwrite: bool, check: Callable[[Path, bool], None] = refuse_existing) -> None:
    """Before any work: the siblings of earlier interrupted writes swept (:func:`sweep_stale`), the folder
    of ``path`` there (DataError) and ``check(path, overwrite)`` (raises when ``path`` may not be written)."""
    sweep_stale(path)
    if not path.parent.is_dir():
        raise DataError(f"{path}: folder {path.parent} does not exist")
    check(path, overwrite)


@contextlib.contextmanager
def written_in_place(path: Path, *, overwrite: bool, folder: bool = False, same_name: bool = False,
                     check: Callable[[Path, bool], None] = refuse_existing) -> Iterator[Path]:
    """A fresh temporary sibling of ``path`` (an empty folder when ``folder``) to write an output into,
    moved into place when the block succeeds (module docstring), removed with whatever it holds when the
    block fails or is interrupted. ``check(path, overwrite)`` runs before the block (:func:`check_target`)
    and again just before the swap: an output that appeared meanwhile is not replaced unless ``overwrite``.
    ``same_name``: the path given to the block has ``path``'s own name, inside the temporary folder (for a
    writer that reads the kind of output from its name, e.g. a ``.bag`` suffix), and what the block
    writes there is moved into place.

    Raises:
        DataError: the folder of ``path`` is missing, or creating, renaming or removing failed (one line).
        ConfigError (or what ``check`` raises): ``path`` may not be replaced.
    """
    check_target(path, overwrite, check)
    tmp = sibling(path, TMP_TAG)
    try:
        remove(tmp)
        if folder or same_name:
            tmp.mkdir()
    except OSError as exc:
        raise _os_error(f"{tmp}: cannot create the temporary output", exc) from exc
    written = tmp / path.name if same_name else tmp
    try:
        yield written
        check(path, overwrite)
        _swap(written, path)
    finally:
        try:
            remove(tmp)
        except OSError as exc:  # the error that got here is the one to report
            logger.warning("cannot remove the temporary output %s: %s", tmp, exc.strerror or exc)


def _swap(tmp: Path, path: Path) -> None:
    """Rename ``tmp`` to ``path``: a file in one atomic rename, a folder after the existing ``path`` is
    renamed aside (put back when the second rename fails; removed once the new one is in place)."""
    if not tmp.is_dir() or not _exists(path):
        try:
            os.replace(tmp, path)
        except OSError as exc:
            raise _os_error(f"{path}: cannot move the new output into place", exc) from exc
        return
    old = sibling(path, OLD_TAG)
    try:
        remove(old)
        os.replace(path, old)
    except OSError as exc:
        raise _os_error(f"{path}: cannot move the previous output aside", exc) from exc
    try:
        os.replace(tmp, path)
    except BaseException as exc:  # an error or Ctrl-C: the previous output goes back
        try:
            os.replace(old, path)
        except OSError as back:
            raise DataError(f"{path}: cannot move the new output into place, and the previous one is in {old}: "
                            f"{back.strerror or back}") from exc
        if isinstance(exc, OSError):
            raise _os_error(f"{path}: cannot move the new output into place (the previous one is kept)", exc) from exc
        raise
    try:
        remove(old)
    except OSError as exc:  # the new output is in place: the old copy is removed by the next write's sweep
        logger.warning("cannot remove the previous output %s: %s", old, exc.strerror or exc)
