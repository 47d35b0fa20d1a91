"""CLI subcommands: one module per command with ``add_arguments`` and ``run`` (its help line:
:data:`fgslam.cli.COMMANDS`)."""

from __future__ import annotations

import argparse

#: the options of :func:`add_selection_arguments`, each the ``dataset.`` key of the same name
SELECTION_KEYS = ("start", "end", "stride")

#: ``--format`` of the commands that open a dataset (fgslam.io.datasets' loaders; auto: detect)
FORMAT_CHOICES = ("auto", "tum", "euroc", "tumvi", "kitti", "tartanair", "7scenes", "folder", "video", "rosbag", "camera")


def add_config_arguments(parser: argparse.ArgumentParser, config_name: str, example: str) -> None:
    """The options every configurable command shares: ``--config YAML``, ``-o KEY=VALUE`` and ``--json``.

    Parsed into ``args.config`` (path or None), ``args.overrides`` (list of strings) and ``args.json``.
    """
    parser.add_argument("--config", metavar="YAML", default=None, help=f"{config_name} YAML file (e.g. {example})")
    parser.add_argument(
        "-o",
        "--override",
        dest="overrides",
        metavar="KEY=VALUE",
        action="append",
        default=[],
        help=f"override a {config_name} field, e.g. -o section.key=value (repeatable)",
    )
    parser.add_argument("--json", action="store_true", help="print one JSON object instead of text")


def add_selection_arguments(parser: argparse.ArgumentParser) -> None:
    """The frames a command reads of its sequence: ``--start``, ``--end`` and ``--stride`` (raw frame
    indices, as ``dataset.start``, ``dataset.end`` and ``dataset.stride`` count them); parsed into
    ``args.start``, ``args.end`` and ``args.stride``, None when not given (:func:`selection_overrides`)."""
    parser.add_argument("--start", type=int, default=None, metavar="N", help="first raw frame index (default 0)")
    parser.add_argument("--end", type=int, default=None, metavar="N", help="one past the last raw frame index")
    parser.add_argument("--stride", type=int, default=None, metavar="N", help="every N-th frame (default 1)")


def selection_overrides(args: argparse.Namespace) -> list[str]:
    """The ``dataset.start/end/stride=N`` overrides of the selection options given (none when none was)."""
    return [f"dataset.{key}={getattr(args, key)}" for key in SELECTION_KEYS if getattr(args, key) is not None]
