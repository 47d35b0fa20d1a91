"""Trajectory plots written as PNG with matplotlib's Agg backend (no pyplot global state).

A plot shows the camera positions ``t_WC`` projected on one plane of the world frame: ``"xz"``
(top view of camera-convention worlds such as KITTI's, y pointing down), ``"xy"`` (top view of
z-up worlds such as EuRoC's and TUM's) or ``"yz"``. Axes are equal-scaled, in metres.
"""

from __future__ import annotations

import logging
from pathlib import Path

from ..errors import DataError
from .trajectory import Trajectory

logger = logging.getLogger(__name__)

PLANES = {"xy": (0, 1), "xz": (0, 2), "yz": (1, 2)}
FIGURE_SIZE_IN = (7.0, 6.0)  # inches
FIGURE_DPI = 120


def plot_trajectories(
    path_png: str | Path,
    gt: Trajectory | None,
    est: Trajectory,
    title: str = "",
    plane: str = "xz",
) -> Path:
    """Draw ``est`` (and ``gt`` when given) seen on ``plane`` and save a PNG at ``path_png``.

    Both trajectories are drawn as given: align the estimate first (``fgslam.eval``) to overlay
    it on the ground truth. Start points are marked with a circle. Returns the written path.

    Raises:
        DataError: unknown plane, or the file cannot be written.
    """
    if plane not in PLANES:
        raise DataError(f"plot: unknown plane {plane!r} (expected one of {', '.join(PLANES)})")
    # Heavy imports stay local: importing fgslam.io must not load matplotlib.
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    a, b = PLANES[plane]
    fig = Figure(figsize=FIGURE_SIZE_IN, dpi=FIGURE_DPI)
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(1, 1, 1)
    if gt is not None:
        ax.plot(gt.t_WC[:, a], gt.t_WC[:, b], color="0.4", linestyle="--", linewidth=1.2, label="ground truth")
        ax.plot(gt.t_WC[0, a], gt.t_WC[0, b], "o", color="0.4")
    ax.plot(est.t_WC[:, a], est.t_WC[:, b], color="tab:blue", linewidth=1.2, label="estimate")
    ax.plot(est.t_WC[0, a], est.t_WC[0, b], "o", color="tab:blue")
    ax.set_xlabel(f"{plane[0]} [m]")
    ax.set_ylabel(f"{plane[1]} [m]")
    ax.set_aspect("equal", adjustable="datalim")
    ax.grid(True, linewidth=0.5, alpha=0.5)
    ax.legend(loc="best")
    if title:
        ax.set_title(title)
    fig.tight_layout()
    path = Path(path_png)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fig.savefig(path, format="png")
    except OSError as exc:
        raise DataError(f"{path}: cannot write plot: {exc}") from exc
    logger.debug("wrote trajectory plot %s", path)
    return path
