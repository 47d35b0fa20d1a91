"""``fgslam batch MATRIX.yaml``: runs a matrix of configs x datasets and collects one table.

A matrix file (every key optional but ``configs`` and ``datasets``; an unknown key is an error
naming it)::

    configs:                       # name -> preset / YAML file (+ overrides), or just the preset
      mono: patch_mono
      light: {preset: patch_mono, overrides: [patch.graph.patches_per_frame=48]}
    datasets:                      # name -> folder (+ format, overrides), or just the folder
      room: data/room              # relative paths: from the matrix file's folder
      kitti: {path: ../shared/data/kitti00_0-199, format: kitti, overrides: [dataset.end=100]}
    overrides: [output.plot=false] # for every cell (before the config's and the dataset's own)
    cpus: 1                        # CPUs of each cell: its Ray resource request and its `threads`
    out: runs/batch                # default: <matrix folder>/<matrix name>

Each cell (config, dataset) is one ``fgslam run`` into ``OUT/<config>/<dataset>/``. With Ray
(an optional extra) each cell is one Ray task with ``cpus`` CPUs on a local Ray instance
(``workers`` cells at a time) or on the cluster at ``address``; Ray schedules them (no scheduler
of fgslam's own). Without Ray the cells run one after another in this process (said in the log).
A failing cell (a run that gave no frame a pose included) records its whole error in the table
and never stops the batch; a cell whose folder already holds a successful ``summary.json`` is not
run again (its summary is read back), so running a batch again completes what failed or is
missing: a failed cell is run again over its previous attempt's outputs (``overwrite``).
SIGTERM or Ctrl-C stop the batch; the tables of the cells finished by then are written.

Outputs in ``OUT``: ``batch.json`` (every cell's row), ``batch.csv`` and ``batch.md`` (a Markdown
table of ATE and frames/s per cell).
"""

from __future__ import annotations

import csv
import importlib.util
import io
import json
import logging
import os
import signal
import socket
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Optional, TypedDict

from ..core.config import MAX_MEMORY_MIB, MAX_SCALAR, MAX_THREADS, from_dict, ranged, read_yaml
from ..core.errors import ConfigError, DataError, Interrupted
from ..io.run_files import SUMMARY_FILE
from .signals import StopOnSignal

logger = logging.getLogger(__name__)

BATCH_JSON = "batch.json"
BATCH_CSV = "batch.csv"
BATCH_MD = "batch.md"
COLUMNS = ("config", "dataset", "status", "ate_m", "align", "ate_percent", "fps", "frames", "frames_with_pose",
           "keyframes", "wall_s", "cpu_s", "skipped", "error", "out")


@dataclass
class ConfigEntry:
    """One row of the matrix: a preset name or YAML file and its overrides."""

    preset: str = "patch_mono"  # preset name or YAML path (relative: from the matrix file)
    overrides: list[str] = field(default_factory=list)  # -o key=value of this config


@dataclass
class DatasetEntry:
    """One column of the matrix: a dataset folder, its loader and overrides."""

    path: str = ""  # dataset folder (relative: from the matrix file)
    format: str = "auto"  # loader (auto-detected by default)
    overrides: list[str] = field(default_factory=list)  # -o key=value for runs on this dataset

    def validate(self) -> None:
        if not self.path:
            raise ConfigError("path: a dataset needs a path")


@dataclass
class BatchMatrix:
    """The matrix file (see the module docstring)."""

    configs: dict[str, Any] = field(default_factory=dict)  # name -> ConfigEntry mapping, or a preset name
    datasets: dict[str, Any] = field(default_factory=dict)  # name -> DatasetEntry mapping, or a folder
    overrides: list[str] = field(default_factory=list)  # for every cell
    cpus: int = ranged(1, ge=1, le=MAX_THREADS)  # CPUs per cell (Ray resources; the run's `threads`)
    out: str = ""  # output folder (default: beside the matrix file, named after it)

    def validate(self) -> None:
        self.configs = {k: _entry(ConfigEntry, "preset", v, f"configs.{k}.") for k, v in self.configs.items()}
        self.datasets = {k: _entry(DatasetEntry, "path", v, f"datasets.{k}.") for k, v in self.datasets.items()}
        for name in list(self.configs) + list(self.datasets):
            if not name or "/" in name or name.startswith("."):
                raise ConfigError(f"cell names become folder names: {name!r} is not a valid one")


def _entry(cls, main_key: str, value: Any, prefix: str):
    """A matrix entry from a mapping (unknown keys named) or the shorthand of its main key."""
    if isinstance(value, (str, Path)):
        return cls(**{main_key: str(value)})
    if isinstance(value, cls):
        return value
    return from_dict(cls, value, source="matrix", prefix=prefix)


MAX_WAIT_S = 3600.0  # upper bound of the waits below (an hour)


@dataclass
class BatchOptions:
    """How ``fgslam batch`` runs its cells (an --address that is not Ray fails after
    ``connect_timeout_s`` too: it does not answer the HTTP/2 preface)."""
    init_timeout_s: float = ranged(60.0, gt=0, le=MAX_WAIT_S)  # joining the cluster at --address fails after this
    poll_s: float = ranged(1.0, gt=0, le=MAX_WAIT_S)  # the wait for a finished cell wakes this often (signals handled then)

    workers: int = ranged(2, ge=1, le=MAX_THREADS)  # local Ray: CPUs given to the instance = workers x cpus
    connect_timeout_s: float = ranged(5.0, gt=0, le=MAX_SCALAR)  # an unreachable --address fails after this long
    object_store_mb: int = ranged(128, ge=80, le=MAX_MEMORY_MIB)  # local Ray's object store (cells return small dicts)


#: The HTTP/2 client connection preface and an empty SETTINGS frame (RFC 9113 sections 3.4, 6.5): the
#: Ray head's GCS and Ray Client ports speak gRPC, i.e. HTTP/2, and answer with a SETTINGS frame.
HTTP2_PREFACE = b"PRI * HTTP/2.0\r\n\r\nSM\r\n\r\n" + bytes((0, 0, 0, 4, 0, 0, 0, 0, 0))
HTTP2_FRAME_HEADER = 9  # bytes of an HTTP/2 frame header: length (3), type (1), flags (1), stream (4)
HTTP2_SETTINGS = 4  # the SETTINGS frame type
MAX_PORT = 65535


def load_matrix(path: str | Path) -> tuple[BatchMatrix, Path]:
    """The matrix at ``path`` with relative paths resolved against its folder; and its output folder."""
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"{path}: no such matrix file")
    matrix = from_dict(BatchMatrix, read_yaml(path), source=str(path))
    for key in ("configs", "datasets"):
        if not getattr(matrix, key):
            raise ConfigError(f"{path}: {key}: the matrix needs at least one entry")
    base = path.parent.resolve()
    for entry in matrix.datasets.values():
        entry.path = str((base / entry.path).resolve()) if not Path(entry.path).is_absolute() else entry.path
    for entry in matrix.configs.values():
        candidate = base / entry.preset
        if entry.preset.endswith((".yaml", ".yml")) and not Path(entry.preset).is_absolute():
            entry.preset = str(candidate.resolve())
    out = Path(matrix.out) if matrix.out else base / path.stem
    if not out.is_absolute():
        out = (base / out).resolve()
    return matrix, out


class Cell(TypedDict):
    """One cell of the matrix, as a plain dict (what a Ray task receives)."""

    config: str  # the config's name in the matrix
    dataset: str  # the dataset's name in the matrix
    preset: str  # preset name or YAML path
    data: str  # dataset folder
    format: str  # dataset loader
    overrides: list[str]  # the cell's -o key=value: threads, the matrix's, the config's, the dataset's
    out: str  # the cell's output folder


def cells_of(matrix: BatchMatrix, out: Path) -> list[Cell]:
    """One plain dict per cell (what a Ray task receives)."""
    cells = []
    for cname, c in matrix.configs.items():
        for dname, d in matrix.datasets.items():
            cells.append({
                "config": cname, "dataset": dname, "preset": c.preset, "data": d.path, "format": d.format,
                "overrides": [f"threads={matrix.cpus}", *matrix.overrides, *c.overrides, *d.overrides],
                "out": str(out / cname / dname),
            })
    return cells


def check_cells(cells: list[Cell]) -> None:
    """Load every cell's config before anything runs: a bad key fails the batch at once, naming the
    cell (a missing dataset folder does not: that cell fails and the others run)."""
    from .config import load_slam_config  # deferred: the run package pulls torch (fgslam --help stays fast)

    for cell in cells:
        try:
            load_slam_config(cell["preset"], cell["overrides"])
        except ConfigError as exc:
            raise ConfigError(f"cell {cell['config']} x {cell['dataset']}: {exc}") from exc


def finished_row(cell: Cell) -> Optional[dict[str, Any]]:
    """The row of a cell whose folder holds a successful summary (None: run it)."""
    path = Path(cell["out"]) / SUMMARY_FILE
    try:
        summary = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    if summary.get("error") or summary.get("output_errors") or not summary.get("frames_with_pose"):
        return None  # failed, or no frame got a pose (summaries of older versions did not call that an error)
    return _row(cell, summary, skipped=True)


def _row(cell: Cell, summary: Optional[dict[str, Any]], skipped: bool = False, error: str = "") -> dict[str, Any]:
    row = {k: None for k in COLUMNS}
    row.update(config=cell["config"], dataset=cell["dataset"], out=cell["out"], skipped=skipped, error=error or None)
    if summary is not None:
        ev = summary.get("evaluation") or {}
        row.update(ate_m=ev.get("ate_rmse_m"), align=ev.get("align"), ate_percent=ev.get("ate_percent_of_path"),
                   fps=summary.get("fps"), frames=summary.get("frames_processed"),
                   frames_with_pose=summary.get("frames_with_pose"), keyframes=summary.get("keyframes"),
                   wall_s=summary.get("wall_s"), cpu_s=summary.get("cpu_s"))
        row["error"] = row["error"] or summary.get("error")
    row["status"] = "failed" if row["error"] else "ok"
    return row


def run_cell(cell: Cell) -> dict[str, Any]:
    """Run one cell (in a Ray worker or in this process); never raises: a failure is the row's error."""
    from .config import load_slam_config  # deferred: the run package pulls torch (fgslam --help stays fast)
    from .prepare import prepare_run  # deferred: as above
    from .runner import run_prepared  # deferred: as above

    summary = None
    started_ns = time.time_ns()
    try:
        config = load_slam_config(cell["preset"], cell["overrides"])
        # the batch owns its cell folders: a cell not finished before is run again over its last attempt
        run = prepare_run(cell["data"], config, cell["out"], fmt=cell["format"], overwrite=True)
        result = run_prepared(run, progress=False)
        summary = result.to_dict()
        return _row(cell, json.loads(json.dumps(summary, default=str)))
    except Exception as exc:  # noqa: BLE001 - a failing cell is recorded, the batch goes on
        path = Path(cell["out"]) / SUMMARY_FILE
        try:  # the summary this attempt wrote (partial outputs), never an earlier attempt's
            fresh = path.is_file() and path.stat().st_mtime_ns >= started_ns
            summary = json.loads(path.read_text()) if fresh else None
        except (OSError, ValueError):
            summary = None
        return _row(cell, summary, error=f"{type(exc).__name__}: {exc}")


# ----------------------------------------------------------------------------------------- running


def ray_available() -> bool:
    """Whether Ray is installed (found without importing it: importing Ray takes seconds)."""
    return importlib.util.find_spec("ray") is not None


def check_address(address: str, timeout_s: float) -> None:
    """Fail within about ``timeout_s`` when the Ray address ``host:port`` (or ``ray://host:port``) does
    not accept connections or does not speak Ray's protocol (gRPC over HTTP/2: its answer to the
    HTTP/2 preface is a SETTINGS frame); Ray's own connection attempts retry for minutes. DataError
    (ConfigError for an address that is not host:port), one line naming the address."""
    if address in ("auto", "local"):
        return
    target = address.split("://", 1)[-1]
    host, _, port = target.rpartition(":")
    if not host or not port.isdigit() or not 0 < int(port) <= MAX_PORT:
        raise ConfigError(f"--address {address!r}: expected host:port (or ray://host:port, or auto) with a port "
                          f"from 1 to {MAX_PORT}")
    not_ray = ("give the Ray head's address (its GCS port, default 6379) or leave out --address for a local Ray")
    try:
        conn = socket.create_connection((host.strip("[]"), int(port)), timeout=timeout_s)
    except OSError as exc:
        why = "timed out" if isinstance(exc, (TimeoutError, socket.timeout)) else (exc.strerror or str(exc))
        raise DataError(f"Ray cluster at {address} cannot be reached ({why} after at most {timeout_s:g} s); "
                        "start it (`ray start --head`) or leave out --address for a local Ray") from exc
    answer = b""
    try:
        with conn:
            conn.settimeout(timeout_s)
            conn.sendall(HTTP2_PREFACE)
            while len(answer) < HTTP2_FRAME_HEADER:
                chunk = conn.recv(HTTP2_FRAME_HEADER - len(answer))
                if not chunk:
                    break
                answer += chunk
    except OSError as exc:
        timed_out = isinstance(exc, (TimeoutError, socket.timeout))
        why = f"no answer within {timeout_s:g} s" if timed_out else (exc.strerror or str(exc))
        raise DataError(f"{address} accepts connections but does not answer as a Ray cluster ({why}); "
                        f"{not_ray}") from exc
    if len(answer) < HTTP2_FRAME_HEADER or answer[3] != HTTP2_SETTINGS:
        raise DataError(f"{address} accepts connections but is not a Ray cluster (its answer is not gRPC/HTTP/2); "
                        f"{not_ray}")


#: What the child process of :func:`_probe_ray_init` runs: join the cluster at ``argv[1]`` and leave.
_PROBE_RAY_INIT = ("import sys, ray; ray.init(address=sys.argv[1], include_dashboard=False, log_to_driver=False, "
                   "configure_logging=False); ray.shutdown()")


def _probe_ray_init(address: str, timeout_s: float) -> None:
    """Join the cluster at ``address`` once in a child process, killed after ``timeout_s``: Ray's own
    attempts retry for minutes inside its C++ client (no signal handled, no thread can stop them), so
    only a process of its own bounds them. DataError, one line naming the address, on failure."""
    logger.info("joining the Ray cluster at %s (at most %g s)", address, timeout_s)
    try:
        proc = subprocess.run([sys.executable, "-c", _PROBE_RAY_INIT, address], capture_output=True, text=True,
                              timeout=timeout_s, stdin=subprocess.DEVNULL)
    except subprocess.TimeoutExpired as exc:
        raise DataError(f"Ray cluster at {address}: joining it did not finish within {timeout_s:g} s "
                        "(BatchOptions.init_timeout_s); check that the address is the Ray head's") from exc
    if proc.returncode != 0:
        last = (proc.stderr.strip().splitlines() or [f"exit status {proc.returncode}"])[-1]
        raise DataError(f"Ray cluster at {address}: joining it failed: {last}")


def _init_ray(kwargs: dict[str, object], address: str | None, timeout_s: float) -> None:
    """``ray.init(**kwargs)``; a cluster at ``address`` is first joined once by a child process
    bounded by ``timeout_s`` (:func:`_probe_ray_init`). The batch's SIGTERM handler is kept (ray.init
    installs its own, a ``sys.exit``)."""
    import ray  # deferred: ray (optional, seconds to import)

    if address:
        _probe_ray_init(address, timeout_s)
    handler = signal.getsignal(signal.SIGTERM)
    try:
        ray.init(**kwargs)
    except Exception as exc:  # noqa: BLE001 - any error of Ray's: one line naming the address
        first = (str(exc).strip().splitlines() or [""])[0]
        raise DataError(f"Ray at {address or 'a local instance'}: ray.init failed: {type(exc).__name__}: {first}") \
            from exc
    finally:
        signal.signal(signal.SIGTERM, handler)


def run_batch(matrix: BatchMatrix, out: Path, options: BatchOptions | None = None, address: str | None = None,
              use_ray: bool | None = None, on_row: Callable[[dict[str, Any], int, int], None] | None = None,
              ) -> tuple[list[dict[str, Any]], dict[str, Any]]:
    """Run every cell not finished yet; returns the rows (matrix order) and run facts (engine, times).

    ``use_ray``: None = Ray when installed; False = one after another in this process; True = Ray
    (ConfigError when it is not installed)."""
    options = options or BatchOptions()
    matrix.validate()
    have_ray = ray_available()
    if use_ray and not have_ray:
        raise ConfigError("Ray is not installed: install the extra (pip install 'fgslam[batch]') or run without --ray")
    if address and not have_ray:
        raise ConfigError(f"--address {address}: Ray is not installed (pip install 'fgslam[batch]')")
    if address and use_ray is not False:
        check_address(address, options.connect_timeout_s)  # first: a wrong address fails within seconds
    cells = cells_of(matrix, out)
    check_cells(cells)
    out.mkdir(parents=True, exist_ok=True)
    rows: dict[int, dict[str, Any]] = {}
    todo = []
    for i, cell in enumerate(cells):
        row = finished_row(cell)
        if row is not None:
            rows[i] = row
        else:
            todo.append(i)
    if rows:
        logger.info("%d of %d cells finished before: not run again", len(rows), len(cells))
    engine = "ray" if (use_ray if use_ray is not None else have_ray) else "sequential"
    if engine == "sequential" and use_ray is None:
        logger.warning("Ray is not installed: running the %d cells one after another (pip install 'fgslam[batch]' "
                       "for parallel cells)", len(todo))
    t0 = time.perf_counter()
    done = len(rows)

    def record(i: int, row: dict[str, Any]) -> None:
        nonlocal done
        rows[i] = row
        done += 1
        if row["status"] != "ok":
            logger.warning("cell %s x %s failed: %s", row["config"], row["dataset"], row["error"])
        if on_row is not None:
            on_row(row, done, len(cells))

    facts: dict[str, Any] = {"engine": engine, "cells": len(cells), "run": len(todo), "skipped": len(cells) - len(todo),
                             "load_average_start": [round(v, 2) for v in os.getloadavg()]}
    try:
        with StopOnSignal((signal.SIGTERM,)):  # SIGTERM (and Ctrl-C) stop the batch; the finished rows are kept
            if engine == "ray" and todo:
                facts.update(_run_ray(cells, todo, matrix.cpus, options, address, record))
            else:
                for i in todo:
                    record(i, run_cell(cells[i]))
    except KeyboardInterrupt as exc:
        signum = getattr(exc, "signum", signal.SIGINT)
        name = signal.Signals(signum).name
        facts.update(wall_s=time.perf_counter() - t0, interrupted=name)
        write_tables(out, [rows[i] for i in sorted(rows)], facts)
        raise Interrupted(f"interrupted by {name}: {done} of {len(cells)} cells done (rows in {out / BATCH_JSON})",
                          signum) from exc
    facts["wall_s"] = time.perf_counter() - t0
    ordered = [rows[i] for i in range(len(cells))]
    write_tables(out, ordered, facts)
    return ordered, facts


def _run_ray(cells: list[Cell], todo: list[int], cpus: int, options: BatchOptions, address: Optional[str],
             record: Callable[[int, dict[str, Any]], None]) -> dict[str, Any]:
    import ray  # deferred: ray (optional, seconds to import)

    started_here = not ray.is_initialized()
    if started_here:
        kwargs: dict[str, object] = {"include_dashboard": False, "log_to_driver": False, "configure_logging": False}
        if address:
            kwargs["address"] = address
        else:
            kwargs.update(num_cpus=options.workers * cpus, object_store_memory=options.object_store_mb * 1024 * 1024)
        t0 = time.perf_counter()
        _init_ray(kwargs, address, options.init_timeout_s)
        startup_s = time.perf_counter() - t0
    else:
        startup_s = 0.0
    try:
        task = ray.remote(num_cpus=cpus, max_retries=0)(run_cell)
        pending = {task.remote(cells[i]): i for i in todo}
        while pending:  # with a timeout: a signal (SIGTERM, Ctrl-C) is handled while cells run
            ready, _ = ray.wait(list(pending), num_returns=1, timeout=options.poll_s)
            for ref in ready:
                i = pending.pop(ref)
                try:
                    row = ray.get(ref)
                except Exception as exc:  # noqa: BLE001 - a worker that died (crash, out of memory): the cell's error
                    row = _row(cells[i], None, error=f"Ray task failed: {type(exc).__name__}: {str(exc).splitlines()[0]}")
                record(i, row)
        resources = ray.cluster_resources()
    finally:
        if started_here:
            ray.shutdown()
    return {"ray_startup_s": startup_s, "ray_cpus": resources.get("CPU"), "address": address or "local"}


# ----------------------------------------------------------------------------------------- tables


def _fmt(value: object, digits: int = 3) -> str:
    if value is None:
        return "-"
    if isinstance(value, float):
        return f"{value:.{digits}f}"
    return str(value)


def _markdown_text(text: str) -> str:
    """``text`` whole, on one line, as the content of a Markdown table cell (``|`` escaped)."""
    return " ".join(text.split()).replace("|", "\\|")


def markdown_table(rows: list[dict[str, Any]]) -> str:
    """ATE and frames/s per cell: one row per config, one column per dataset."""
    configs = list(dict.fromkeys(r["config"] for r in rows))
    datasets = list(dict.fromkeys(r["dataset"] for r in rows))
    by = {(r["config"], r["dataset"]): r for r in rows}
    lines = ["| config | " + " | ".join(datasets) + " |", "|---|" + "---|" * len(datasets)]
    for c in configs:
        cells = []
        for d in datasets:
            r = by.get((c, d))
            if r is None:
                cells.append("-")
            elif r["status"] != "ok":
                cells.append(f"failed: {_markdown_text(str(r['error']))}")
            else:
                ate = "-" if r["ate_m"] is None else f"ATE {r['ate_m']:.3f} m ({r['align']})"
                cells.append(f"{ate}, {r['fps']:.1f} frames/s")
        lines.append(f"| {c} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def write_tables(out: Path, rows: list[dict[str, Any]], facts: dict[str, Any]) -> None:
    (out / BATCH_JSON).write_text(json.dumps({"facts": facts, "cells": rows}, indent=2, default=str) + "\n")
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=list(COLUMNS))
    writer.writeheader()
    for r in rows:
        writer.writerow({k: r.get(k) for k in COLUMNS})
    (out / BATCH_CSV).write_text(buf.getvalue())
    (out / BATCH_MD).write_text(markdown_table(rows) + "\n")
