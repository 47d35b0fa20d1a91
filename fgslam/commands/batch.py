"""``fgslam batch MATRIX.yaml``: a matrix of configs x datasets, one run per cell (on Ray when it is
installed: a local instance, or ``--address`` of a cluster), one table of ATE and frames/s
(``batch.json``, ``batch.csv``, ``batch.md``; see :mod:`fgslam.run.batch`).

Exit status: 0 when every cell gave a result, :data:`EXIT_CELLS_FAILED` (1) when some cell failed (the
tables, with every cell that worked and each failed cell's error, are written all the same), 2 when the
batch itself was refused (a bad matrix, an unreachable Ray cluster), 130/143 when interrupted."""

from __future__ import annotations

import argparse
import json
import logging
import sys
from dataclasses import replace
from pathlib import Path
from typing import Any

from tqdm import tqdm

from ..run.batch import BATCH_MD, BatchOptions, load_matrix, markdown_table, run_batch
from ..core.config import check_ranges


logger = logging.getLogger("fgslam.run.batch")

#: exit status of a batch that ran but in which some cell failed (scripts and CI can tell; the tables are written)
EXIT_CELLS_FAILED = 1


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.epilog = (f"exit status: 0 every cell gave a result, {EXIT_CELLS_FAILED} some cell failed (the tables are "
                     "written all the same), 2 the batch was refused")
    parser.add_argument("matrix", metavar="MATRIX.yaml", help="matrix file (configs, datasets, overrides, cpus, out)")
    parser.add_argument("--out", default=None, metavar="DIR", help="output folder (default: the matrix's `out`, "
                        "else beside the matrix file, named after it)")
    parser.add_argument("--address", default=None, metavar="HOST:PORT",
                        help="join the Ray cluster at this address (default: start a local Ray)")
    parser.add_argument("--workers", type=int, default=None, metavar="N",
                        help="local Ray: cells at a time (default 2)")
    engine = parser.add_mutually_exclusive_group()
    engine.add_argument("--sequential", action="store_true", help="run the cells one after another in this process")
    engine.add_argument("--ray", action="store_true", help="require Ray (error when it is not installed)")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar or lines")
    parser.add_argument("--json", action="store_true", help="print the table as one JSON object")


def run(args: argparse.Namespace) -> int:
    matrix, out = load_matrix(args.matrix)
    if args.out:
        out = Path(args.out)
    options = BatchOptions()
    if args.workers is not None:
        options = replace(options, workers=args.workers)
        check_ranges(options, source="--workers")
    use_ray = False if args.sequential else True if (args.ray or args.address) else None
    bar = None
    if not args.no_progress and sys.stderr.isatty():
        n = len(matrix.configs) * len(matrix.datasets)
        bar = tqdm(total=n, desc="cells", unit="cell", file=sys.stderr)

    def on_row(row: dict[str, Any], done: int, total: int) -> None:
        if bar is not None:
            bar.update(1)
            bar.set_postfix_str(f"{row['config']} x {row['dataset']}: {row['status']}")
        elif not args.no_progress:
            logger.info("cell %d/%d %s x %s: %s", done, total, row["config"], row["dataset"], row["status"])

    try:
        rows, facts = run_batch(matrix, out, options, address=args.address, use_ray=use_ray, on_row=on_row)
    finally:
        if bar is not None:
            bar.close()
    failed = sum(r["status"] != "ok" for r in rows)
    if args.json:
        print(json.dumps({"facts": facts, "cells": rows}, default=str))
    else:
        print(markdown_table(rows))
        print(f"\n{len(rows)} cells ({facts['skipped']} finished before, {failed} failed) on {facts['engine']} "
              f"in {facts['wall_s']:.1f} s; tables in {out}/batch.md, batch.csv, batch.json")
    if failed:
        logger.error("%d of %d cells failed (errors in %s); exit status %d", failed, len(rows), out / BATCH_MD,
                     EXIT_CELLS_FAILED)
        return EXIT_CELLS_FAILED
    return 0
