"""tools/bench_long_drive.py without running SLAM: the per-frame timing of its dataset wrapper and
the window statistics of its report (no timing checks)."""

import time

import numpy as np
import pytest
from tool_support import load_tool

MIB = 1024 ** 2


@pytest.fixture(scope="module")
def bench():
    return load_tool("bench_long_drive")


class _FakeDataset:
    root = "fake"

    def __init__(self, n: int) -> None:
        self.n = n
        self.reads = 0

    def __len__(self) -> int:
        return self.n

    def __iter__(self):
        for i in range(self.n):
            time.sleep(0.02)  # reading is not the step's time
            self.reads += 1
            yield i


def test_timed_dataset_times_the_consumer_step_not_the_read(bench):
    ds = bench.TimedDataset(_FakeDataset(4))
    assert len(ds) == 4 and ds.root == "fake"  # the wrapped dataset's attributes
    seen = []
    for i in ds:
        seen.append(i)
        time.sleep(0.05 if i == 2 else 0.0)  # the run's step on frame 2 is slow
    assert seen == [0, 1, 2, 3] and len(ds.wall_s) == len(ds.rss) == len(ds.cpu_s) == 4
    assert ds.wall_s[2] >= 0.05 and max(ds.wall_s[:2] + ds.wall_s[3:]) < 0.02
    assert all(r > 0 for r in ds.rss)


def _record(n: int, rss_mib, cpu_ms) -> dict:
    return {"family": "patch", "mode": "mono", "loops": "on", "preset": "driving_mono", "overrides": [],
            "error": None, "summary": {"evaluation": {"ate_rmse_m": 1.5}, "loop": {"accepted_loops": 3}},
            "wall_s": list(np.full(n, 0.1)), "cpu_s": list(np.asarray(cpu_ms) / 1000.0),
            "rss": list(np.asarray(rss_mib) * MIB), "ru_maxrss_mib": 900.0,
            "loadavg_before": [1.0, 1.0, 1.0], "loadavg_after": [1.0, 1.0, 1.0]}


def test_window_stats_first_and_last_windows_and_targets(bench):
    n = 2000
    flat = bench.window_stats(_record(n, np.full(n, 700.0), np.full(n, 50.0)), 500)
    assert flat["fps_cpu_first"] == pytest.approx(20.0) and flat["fps_cpu_last"] == pytest.approx(20.0)
    assert flat["rss_ratio"] == 1.0 and flat["rss_target_met"] and flat["fps_target_met"]
    assert flat["ate_rmse_m"] == 1.5 and flat["accepted_loops"] == 3
    assert flat["rss_slope_mib_per_1000_frames"] == pytest.approx(0.0, abs=1e-9)
    # memory growing linearly to twice its frame-500 value and the last frames 30 % slower: both missed
    rss = np.concatenate([np.full(500, 700.0), np.linspace(700.0, 1400.0, n - 500)])
    cpu = np.concatenate([np.full(n - 500, 50.0), np.full(500, 50.0 / 0.7)])
    grown = bench.window_stats(_record(n, rss, cpu), 500)
    assert grown["rss_ratio"] == pytest.approx(2.0) and not grown["rss_target_met"]
    assert grown["fps_cpu_ratio"] == pytest.approx(0.7) and not grown["fps_target_met"]
    assert grown["rss_slope_mib_per_1000_frames"] == pytest.approx(700.0 / 1.5, rel=1e-3)
