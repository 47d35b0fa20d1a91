"""Trajectory plots written as PNG with matplotlib's Agg backend (no pyplot global state).

A plot shows the camera positions ``t_WC`` projected on one plane of the world frame: ``"xz"``
(top view of camera-convention worlds such as KITTI's, y pointing down), ``"xy"`` (top view of
z-up worlds such as EuRoC's and TUM's) or ``"yz"``. Axes are equal-scaled, in metres.

Destination folders: the plot's own folder is created when missing (with a log line); a deeper
missing path is an error naming the first missing folder (a typo in a path never leaves a tree
of new folders behind). :func:`check_plot_path` checks this before any work is done.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from ..core.errors import DataError
from .trajectory import Trajectory

logger = logging.getLogger(__name__)

PLANES = {"xy": (0, 1), "xz": (0, 2), "yz": (1, 2)}
FIGURE_SIZE_IN = (7.0, 6.0)  # inches
FIGURE_DPI = 120


def pose_errors(matched_gt: Trajectory, aligned_est: Trajectory) -> tuple[np.ndarray, np.ndarray]:
    """``(timestamps, translation errors)`` of associated, aligned trajectories (the ATE's terms)."""
    return aligned_est.timestamps, np.linalg.norm(matched_gt.t_WC - aligned_est.t_WC, axis=1)


def check_plot_path(path_png: str | Path) -> Path:
    """Check that a plot can go to ``path_png`` (see the module docstring); creates nothing.

    Raises:
        DataError: ``path_png`` is a folder, its folder is a file, or a folder above its own
            folder is missing (names the first missing one).
    """
    path = Path(path_png)
    if path.is_dir():
        raise DataError(f"{path}: is a folder; give the plot's file name (e.g. {path / 'trajectory.png'})")
    folder = path.parent
    if folder.exists() and not folder.is_dir():
        raise DataError(f"{path}: cannot write the plot: {folder} is not a folder")
    if not folder.exists() and not folder.parent.is_dir():
        missing = folder
        while not missing.parent.exists():
            missing = missing.parent
        raise DataError(
            f"{path}: cannot write the plot: folder {missing} does not exist (only the plot's own folder "
            f"is created; create the folders above it first)"
        )
    return path


ERROR_FIGURE_SIZE_IN = (12.0, 5.5)  # inches, with the error-over-time panel
COLOURS = ("tab:blue", "tab:orange", "tab:green", "tab:red", "tab:purple")


def plot_trajectories(
    path_png: str | Path,
    gt: Trajectory | None,
    est: Trajectory,
    title: str = "",
    plane: str = "xz",
    others: dict[str, Trajectory] | None = None,
    errors: dict[str, Trajectory | tuple] | None = None,
    label: str = "estimate",
) -> Path:
    """Draw ``est`` (and ``gt`` when given, and ``others`` by label) seen on ``plane`` and save a
    PNG at ``path_png``.

    Every trajectory is drawn as given: align the estimates first (``fgslam.eval.trajectory``) to overlay
    them on the ground truth. Start points are marked with a circle. With ``errors`` (label ->
    ``(timestamps, errors in metres)``) a second panel shows the translation error over time (the
    ATE's per-pose errors). Returns the written path.

    Raises:
        DataError: unknown plane, a destination :func:`check_plot_path` refuses, or the file
            cannot be written.
    """
    if plane not in PLANES:
        raise DataError(f"plot: unknown plane {plane!r} (expected one of {', '.join(PLANES)})")
    path = check_plot_path(path_png)
    # Heavy imports stay local: importing fgslam.io must not load matplotlib.
    from matplotlib.backends.backend_agg import FigureCanvasAgg  # deferred: matplotlib
    from matplotlib.figure import Figure  # deferred: matplotlib

    a, b = PLANES[plane]
    fig = Figure(figsize=ERROR_FIGURE_SIZE_IN if errors else FIGURE_SIZE_IN, dpi=FIGURE_DPI)
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(1, 2 if errors else 1, 1)
    if gt is not None:
        ax.plot(gt.t_WC[:, a], gt.t_WC[:, b], color="0.4", linestyle="--", linewidth=1.2, label="ground truth")
        ax.plot(gt.t_WC[0, a], gt.t_WC[0, b], "o", color="0.4")
    for (name, traj), colour in zip({label: est, **(others or {})}.items(), COLOURS):
        ax.plot(traj.t_WC[:, a], traj.t_WC[:, b], color=colour, linewidth=1.2, label=name)
        ax.plot(traj.t_WC[0, a], traj.t_WC[0, b], "o", color=colour)
    ax.set_xlabel(f"{plane[0]} [m]")
    ax.set_ylabel(f"{plane[1]} [m]")
    ax.set_aspect("equal", adjustable="datalim")
    ax.grid(True, linewidth=0.5, alpha=0.5)
    ax.legend(loc="best")
    if title:
        ax.set_title(title)
    if errors:
        ax2 = fig.add_subplot(1, 2, 2)
        for (name, (t, e)), colour in zip(errors.items(), COLOURS):
            t = np.asarray(t, dtype=np.float64)
            ax2.plot(t - t[0] if t.size else t, e, color=colour, linewidth=1.0, label=name)
        ax2.set_xlabel("time [s]")
        ax2.set_ylabel("translation error after alignment [m]")
        ax2.grid(True, linewidth=0.5, alpha=0.5)
        ax2.legend(loc="best")
        ax2.set_title("error over time")
    fig.tight_layout()
    try:
        if not path.parent.exists():
            path.parent.mkdir()
            logger.info("created folder %s for the plot", path.parent)
        fig.savefig(path, format="png")
    except OSError as exc:
        raise DataError(f"{path}: cannot write plot: {exc}") from exc
    logger.debug("wrote trajectory plot %s", path)
    return path
