"""CLI subcommands: one module per command with ``HELP``, ``add_arguments`` and ``run``."""

from __future__ import annotations

import argparse

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
