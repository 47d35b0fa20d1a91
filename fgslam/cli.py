"""The ``fgslam`` command line: a thin dispatcher over ``fgslam.commands.<name>`` modules.

Each command module exposes ``HELP``, ``add_arguments(parser)`` and ``run(args) -> int`` and keeps
heavy imports (torch, gtsam, OpenCV) inside ``run`` so that ``fgslam --help`` stays fast.
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

#: Subcommands in the order ``fgslam --help`` lists them.
COMMANDS: tuple[str, ...] = ("run", "localize", "demo", "synth", "info", "eval", "pgo", "export", "compare-colmap", "batch")

_LOG_FORMAT = "%(asctime)s %(levelname).1s %(name)s: %(message)s"


def build_parser() -> argparse.ArgumentParser:
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
    for name in COMMANDS:
        module = importlib.import_module(f".commands.{name.replace('-', '_')}", __package__)
        cmd = sub.add_parser(name, help=module.HELP, description=module.HELP)
        module.add_arguments(cmd)
        cmd.set_defaults(_run=module.run)
    return parser


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
    parser = build_parser()
    args = parser.parse_args(argv)
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
