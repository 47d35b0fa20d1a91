"""The CLI's console logging lasts as long as the command: :func:`fgslam.cli.main` called in-process
(tests, notebooks, batch workers) leaves the root logger as it found it, so no later log line goes to
a stream the caller has closed since ("--- Logging error --- ValueError: I/O operation on closed
file" after a captured test)."""

from __future__ import annotations

import io
import logging
import sys

from fgslam import cli


def test_main_restores_the_root_logger(tmp_path, monkeypatch):
    root = logging.getLogger()
    before = root.handlers[:], root.level
    stream = io.StringIO()
    monkeypatch.setattr(sys, "stderr", stream)
    assert cli.main(["eval", str(tmp_path / "missing_gt.txt"), str(tmp_path / "missing_est.txt"),
                     "--format", "tum"]) == 2
    assert "fgslam: error:" in stream.getvalue()
    assert (root.handlers, root.level) == before
    stream.close()
    logging.getLogger("fgslam").warning("after the command")  # no handler writes to the closed stream


def test_log_lines_of_the_command_reach_its_stderr(tmp_path, monkeypatch):
    stream = io.StringIO()
    monkeypatch.setattr(sys, "stderr", stream)
    seen = []

    def fake_run(args):
        logging.getLogger("fgslam.test").info("inside the command")
        seen.append(True)
        return 0

    parser = cli.build_parser
    monkeypatch.setattr(cli, "build_parser", lambda command=None: _with_run(parser(command), fake_run))
    assert cli.main(["info", str(tmp_path)]) == 0 and seen
    assert "inside the command" in stream.getvalue()


def _with_run(parser, run):
    parser.set_defaults(_run=run)
    for action in parser._subparsers._group_actions:  # the sub-commands' own defaults win otherwise
        for sub in action.choices.values():
            sub.set_defaults(_run=run)
    return parser
