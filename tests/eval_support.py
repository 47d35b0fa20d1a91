"""The do-nothing baseline of the trajectory tests (importable because pytest puts tests/ on the path).

A trajectory test passes only if its estimate beats doing nothing: the ATE of a *stationary* estimate
(every pose at the first ground-truth pose, the estimate of a frontend that never moves) is computed in
the test over the same stamps and with the same alignment, and the estimate's ATE must be clearly
below it (:data:`BEAT_FACTOR`), on top of any absolute bound the test has."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from fgslam.eval.trajectory import EvalConfig, evaluate
from fgslam.io.run_files import TUM_FILE
from fgslam.io.trajectory import Trajectory

BEAT_FACTOR = 0.5  # the estimate's ATE must be below this fraction of the stationary estimate's


def frames_groundtruth(frames) -> Trajectory:
    """The ground truth of a list of dataset frames (their timestamps and ``T_WC_gt``)."""
    return Trajectory(np.array([f.timestamp for f in frames]), np.stack([f.T_WC_gt for f in frames]))


def stationary(groundtruth: Trajectory, stamps) -> Trajectory:
    """The do-nothing estimate: at every stamp, the ground-truth pose nearest the first stamp."""
    stamps = np.asarray(stamps, dtype=np.float64)
    first = int(np.argmin(np.abs(groundtruth.timestamps - stamps[0])))
    return Trajectory(stamps, np.repeat(groundtruth.T_WC[first][None], len(stamps), axis=0))


def do_nothing_ate(groundtruth: Trajectory, stamps, align: str, **eval_options) -> float:
    """ATE RMSE (m) of the stationary estimate at ``stamps``, evaluated like the estimate
    (``align``, other :class:`EvalConfig` fields in ``eval_options``). A stationary estimate has no
    spread to fix a Sim(3) scale: the best similarity of one point is a translation, so ``sim3`` is
    evaluated as ``se3`` (same value)."""
    align = "se3" if align == "sim3" else align
    res = evaluate(groundtruth, stationary(groundtruth, stamps), EvalConfig(align=align, **eval_options))
    return float(res.ate.rmse)


def assert_beats_doing_nothing(ate: float, groundtruth: Trajectory, stamps, align: str, **eval_options) -> float:
    """Assert ``ate`` < BEAT_FACTOR x the do-nothing ATE over the same stamps; returns the do-nothing ATE."""
    still = do_nothing_ate(groundtruth, stamps, align, **eval_options)
    assert ate < BEAT_FACTOR * still, f"ATE {ate:.4f} m does not beat doing nothing ({still:.4f} m) by 1/{BEAT_FACTOR:g}"
    return still


# what a summary may differ in between two runs of the same input: times, machine state, the folder
RUN_ONLY = {"fps", "fps_frontend", "stage_ms_per_frame", "peak_rss_mb", "load_average", "out_dir", "outputs"}


def timeless(value):
    """A run's summary without what measures the run rather than the estimate (times, load, memory)."""
    if isinstance(value, dict):
        return {k: timeless(v) for k, v in value.items() if not (k.endswith("_s") or k in RUN_ONLY)}
    if isinstance(value, list):
        return [timeless(v) for v in value]
    return value


def run_preset(root, preset: str, out, overrides=()):
    """``(dataset, summary, est)`` of ``fgslam``'s run of ``preset`` (with ``overrides``) on the dataset
    at ``root`` into ``out``; ``est`` is the written TUM trajectory as an (N, 8) array."""
    from fgslam.run.config import load_slam_config
    from fgslam.run.prepare import open_slam_dataset
    from fgslam.run.runner import run_slam

    cfg = load_slam_config(preset, list(overrides))
    ds = open_slam_dataset(root, cfg)
    summary = run_slam(ds, cfg, out, progress=False)
    return ds, summary, np.loadtxt(Path(out) / TUM_FILE)


def evaluate_tum_rows(groundtruth: Trajectory, est, align: str):
    """:func:`fgslam.eval.trajectory.evaluate` of a TUM trajectory given as an (N, 8) array against ``groundtruth``."""
    return evaluate(groundtruth, Trajectory.from_position_quaternion(est[:, 0], est[:, 1:4], est[:, 4:8]),
                    EvalConfig(align=align))
