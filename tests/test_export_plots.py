"""Plots of ``fgslam run`` / ``fgslam eval``: trajectory top view plus error over time when there is
ground truth (fgslam/io/plot.py)."""

from __future__ import annotations

import json

import numpy as np

from fgslam.cli import main
from fgslam.io.plot import ERROR_FIGURE_SIZE_IN, FIGURE_DPI, FIGURE_SIZE_IN, plot_trajectories, pose_errors
from fgslam.io.trajectory import Trajectory, write_trajectory


def _png_size(path) -> tuple[int, int]:
    import cv2

    image = cv2.imread(str(path))
    return image.shape[1], image.shape[0]


def _circle(n: int, noise: float, seed: int = 0) -> Trajectory:
    rng = np.random.default_rng(seed)
    a = np.linspace(0, 2 * np.pi, n)
    T = np.tile(np.eye(4), (n, 1, 1))
    T[:, 0, 3], T[:, 2, 3] = np.cos(a), np.sin(a)
    T[:, :3, 3] += rng.normal(0, noise, (n, 3))
    return Trajectory(np.arange(n) * 0.1, T)


def test_error_panel_and_other_trajectories(tmp_path):
    gt, est, other = _circle(50, 0.0), _circle(50, 0.02, 1), _circle(50, 0.05, 2)
    t, e = pose_errors(gt, est)
    np.testing.assert_allclose(e, np.linalg.norm(gt.t_WC - est.t_WC, axis=1))
    plot_trajectories(tmp_path / "one.png", gt, est)
    plot_trajectories(tmp_path / "two.png", gt, est, others={"other": other}, errors={"est": (t, e)})
    assert _png_size(tmp_path / "one.png") == tuple(int(v * FIGURE_DPI) for v in FIGURE_SIZE_IN)
    assert _png_size(tmp_path / "two.png") == tuple(int(v * FIGURE_DPI) for v in ERROR_FIGURE_SIZE_IN)


def test_eval_plot_has_the_error_panel(tmp_path, capsys):
    gt, est = _circle(40, 0.0), _circle(40, 0.01, 3)
    write_trajectory(tmp_path / "gt.txt", gt, "tum")
    write_trajectory(tmp_path / "est.txt", est, "tum")
    assert main(["eval", str(tmp_path / "gt.txt"), str(tmp_path / "est.txt"), "--format", "tum",
                 "--plot", str(tmp_path / "p.png"), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["plot"] == str(tmp_path / "p.png")
    assert _png_size(tmp_path / "p.png") == tuple(int(v * FIGURE_DPI) for v in ERROR_FIGURE_SIZE_IN)
