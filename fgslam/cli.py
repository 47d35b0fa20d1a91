"""The ``fgslam`` command line: a thin dispatcher over ``fgslam.commands.<name>`` modules.

Each command module exposes ``add_arguments(parser)`` and ``run(args) -> int`` (its one-line help is
in :data:`COMMANDS`) and keeps heavy imports (torch, gtsam, OpenCV) inside ``run``; only the command
given is imported, so that ``fgslam --help`` and a refused command answer at once.
"""

from __future__ import annotations

import argparse
import contextlib
import importlib
import logging
import sys
from collections.abc import Sequence

from . import __version__
from .core.errors import FGSlamError

#: Subcommands in the order ``fgslam --help`` lists them, with their one-line help.
COMMANDS: dict[str, str] = {
    "run": "run SLAM on a dataset (trajectory in TUM/KITTI formats, summary.json, trajectory.png)",
    "localize": "localise a sequence in a stored map (pose per frame in the map's frame, or 'not localised')",
    "demo": "render a synthetic room sequence, run SLAM on it and report accuracy and speed (< 2 min)",
    "synth": "generate a synthetic EuRoC-layout sequence (stereo, depth, IMU, exact ground truth)",
    "info": "describe a dataset folder, video or ROS bag: format, frames, resolution, rate, stereo/depth/IMU/ground truth",
    "eval": "evaluate an estimated trajectory against ground truth (ATE, RPE, KITTI t_rel/r_rel)",
    "pgo": "optimise a g2o pose graph (SE2 / SE3:QUAT) and report initial/final cost, iterations and time",
    "export": "export a run's map as a COLMAP model (binary or text, with images) or a PLY point cloud, or its trajectory as a ROS bag",
    "compare-colmap": "run pycolmap's SfM and fgslam (monocular) on the same frames and compare time, ATE and point clouds",
    "batch": "run a matrix of configs x datasets (on Ray when installed) and collect one summary table",
}

_LOG_FORMAT = "%(asctime)s %(levelname).1s %(name)s: %(message)s"


def build_parser(command: str | None = None) -> argparse.ArgumentParser:
    """The ``fgslam`` parser. ``command``: only that subcommand's options are built (only its module is
    imported, so that a command, or its refusal, does not wait for the others' imports; "": none); every
    command is listed with its help. None: every command's options (the CLI reference)."""
    parser = argparse.ArgumentParser(
        prog="fgslam",
        description="Modular factor-graph visual SLAM on GTSAM (dense, patch and pointmap frontends).",
    )
    parser.add_argument("--version", action="version", version=f"fgslam {__version__}")
    verbosity = parser.add_mutually_exclusive_group()
    verbosity.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    verbosity.add_argument("-q", "--quiet", action="store_true", help="warnings and errors only")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True
    for name, text in COMMANDS.items():
        cmd = sub.add_parser(name, help=text, description=text)
        if command is None or name == command:
            module = importlib.import_module(f".commands.{name.replace('-', '_')}", __package__)
            module.add_arguments(cmd)
            cmd.set_defaults(_run=module.run)
    return parser


def command_of(argv: Sequence[str]) -> str:
    """The subcommand ``argv`` names: its first word that is not an option ("" when that is no command;
    the global options take no value)."""
    word = next((a for a in argv if not a.startswith("-")), "")
    return word if word in COMMANDS else ""


@contextlib.contextmanager
def _console_logging(verbose: bool, quiet: bool):
    """The command's log lines on the current ``sys.stderr`` while it runs; the root logger's earlier
    handlers and level come back afterwards (so that a caller of :func:`main`, e.g. a test with
    captured output, is not left with a handler on a stream that it closes later)."""
    root = logging.getLogger()
    saved = root.handlers[:], root.level
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(logging.Formatter(_LOG_FORMAT, datefmt="%H:%M:%S"))
    root.handlers = [handler]
    root.setLevel(logging.DEBUG if verbose else logging.WARNING if quiet else logging.INFO)
    try:
        yield
    finally:
        handler.flush()
        root.handlers, level = saved
        root.setLevel(level)


def main(argv: Sequence[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    args = build_parser(command_of(argv)).parse_args(argv)
    with _console_logging(args.verbose, args.quiet):
        try:
            return int(args._run(args) or 0)
        except FGSlamError as exc:
            print(f"fgslam: error: {exc}", file=sys.stderr)
            return 2
        except KeyboardInterrupt as exc:  # Ctrl-C, or fgslam.core.errors.Interrupted (SIGINT/SIGTERM during a run)
            print(f"fgslam: {str(exc) or 'interrupted'}", file=sys.stderr)
            return getattr(exc, "exit_code", 130)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
