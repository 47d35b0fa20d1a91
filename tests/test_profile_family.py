"""tools/profile_family.py on a tiny synthetic RGB-D clip: the per-stage profile's keys, that the stages
add up to the profiled time (and that to the process CPU time around the run), that the measurement,
linearisation and elimination stages are seen, and the stage rules on names of each family."""

from __future__ import annotations

import json

import pytest
from patch_support import render_room
from tool_support import load_tool

FRAMES = 16


@pytest.fixture(scope="module")
def tool():
    return load_tool("profile_family")


@pytest.fixture(scope="module")
def clip(tmp_path_factory):
    return render_room(tmp_path_factory, "profile_room", [f"frames={FRAMES}", "camera.width=160", "camera.height=120"])


def test_dense_profile_stages_add_up(tool, clip, capsys):
    assert tool.main(["dense_rgbd", "--data", str(clip), "--end", str(FRAMES), "--top", "5"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["family"] == "dense" and out["frames"] == FRAMES and out["timer"] == "cpu"
    stages = out["stage_ms_per_frame"]
    assert set(stages) == set(tool.STAGES)
    assert all(v >= 0 for v in stages.values())
    total = sum(stages.values())
    assert total == pytest.approx(out["total_ms_per_frame"], rel=1e-3, abs=0.01)
    # the profiler's clock is the process CPU clock: the stages cover what the process spent around the run
    assert out["profiled_s"] <= 1.05 * out["process_cpu_s"] + 0.05
    assert out["profiled_s"] >= 0.5 * out["process_cpu_s"]
    # the dense family measures flow, linearises and eliminates on every frame
    for stage in ("flow_or_matching", "linearisation", "elimination", "solve", "bookkeeping"):
        assert stages[stage] > 0, stage
    python = out["stage_python_ms_per_frame"]
    assert all(python[k] <= stages[k] + 1e-6 for k in stages)
    assert out["python_overhead_ms_per_frame"] == pytest.approx(sum(python.values()), rel=1e-3, abs=0.01)
    assert {"flow", "tracking", "ba"} <= set(out["run_stage_wall_ms_per_frame"])
    assert len(out["top_functions"]) == 5 and out["run"]["ate_m"] is not None


def test_stage_rules_name_each_family(tool):
    assert tool.stage_of("/x/fgslam/frontends/flow.py", "_revise_edge") == "flow_or_matching"
    assert tool.stage_of("/x/fgslam/frontends/patch/lk.py", "measure_batch") == "flow_or_matching"
    assert tool.stage_of("/x/fgslam/frontends/pointmap/matching.py", "anything") == "flow_or_matching"
    assert tool.stage_of("/x/fgslam/factors/dense.py", "linearize") == "linearisation"
    assert tool.stage_of("/x/fgslam/factors/schur.py", "schur_reduce") == "elimination"
    assert tool.stage_of("~", "<method 'optimize' of 'gtsam.gtsam.GaussianFactorGraph' objects>") == "elimination"
    assert tool.stage_of("/x/fgslam/backend/solver.py", "levenberg_marquardt") == "solve"
    assert tool.stage_of("/x/fgslam/factors/dense.py", "evaluate") is None  # inherits: linearize or a trial's cost
    assert tool.stage_of("~", "<built-in method torch.stack>") is None
    assert tool.stage_of("/x/fgslam/frontends/patch/patches.py", "select_patches") == "flow_or_matching"
    assert tool.stage_of("/x/fgslam/frontends/patch/window.py", "optimize") == "solve"
