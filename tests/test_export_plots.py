"""Plots of ``fgslam run`` / ``fgslam eval``: trajectory top view plus error over time when there is
ground truth (fgslam/io/plot.py)."""

from __future__ import annotations

import json

import numpy as np

from fgslam.cli import main
from fgslam.io.plot import COLOURS, ERROR_FIGURE_SIZE_IN, FIGURE_DPI, FIGURE_SIZE_IN, plot_trajectories, pose_errors
from fgslam.io.trajectory import Trajectory, write_trajectory


def _png_size(path) -> tuple[int, int]:
    import cv2

    image = cv2.imread(str(path))
    return image.shape[1], image.shape[0]


def _colour_pixels(path, colour: str, half: str) -> int:
    """Pixels of one half (``left`` / ``right``) of a PNG within a small distance of a matplotlib colour."""
    import cv2
    from matplotlib.colors import to_rgb

    image = cv2.imread(str(path))[..., ::-1].astype(np.float64)  # RGB
    w = image.shape[1] // 2
    image = image[:, :w] if half == "left" else image[:, w:]
    return int((np.linalg.norm(image - 255 * np.array(to_rgb(colour)), axis=-1) < 20).sum())


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
    # content: the top view draws the estimate (first colour), the other trajectory (second colour) and
    # the ground truth (grey); the error panel (right half) draws the estimate's error only
    est_c, other_c = COLOURS[:2]
    counts = {(name, half): _colour_pixels(tmp_path / "two.png", c, half)
              for name, c in (("est", est_c), ("other", other_c), ("gt", "0.4")) for half in ("left", "right")}
    # (measured, pixels within 20 of the colour: estimate 1,664 left / 4,732 right, other 2,157 / 0, grey 883 / 304;
    # grey also matches anti-aliased text, so the ground truth is told apart by the halves)
    assert counts["est", "left"] > 500 and counts["est", "right"] > 500
    assert counts["other", "left"] > 500 and counts["other", "right"] == 0
    assert counts["gt", "left"] > 2 * counts["gt", "right"]
    # the single-panel plot has no other trajectory
    assert _colour_pixels(tmp_path / "one.png", other_c, "left") == _colour_pixels(tmp_path / "one.png", other_c, "right") == 0
    assert _colour_pixels(tmp_path / "one.png", est_c, "left") > 500


def test_eval_plot_has_the_error_panel(tmp_path, capsys):
    gt, est = _circle(40, 0.0), _circle(40, 0.01, 3)
    write_trajectory(tmp_path / "gt.txt", gt, "tum")
    write_trajectory(tmp_path / "est.txt", est, "tum")
    assert main(["eval", str(tmp_path / "gt.txt"), str(tmp_path / "est.txt"), "--format", "tum",
                 "--plot", str(tmp_path / "p.png"), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["plot"] == str(tmp_path / "p.png")
    assert _png_size(tmp_path / "p.png") == tuple(int(v * FIGURE_DPI) for v in ERROR_FIGURE_SIZE_IN)
