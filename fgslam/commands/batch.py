"""``fgslam batch MATRIX.yaml``: placeholder (being written)."""

from __future__ import annotations

import argparse

HELP = "run a matrix of configs x datasets (Ray when installed) and collect one summary table"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("matrix", metavar="MATRIX.yaml")


def run(args: argparse.Namespace) -> int:
    raise NotImplementedError
