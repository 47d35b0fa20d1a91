"""A fourth frontend built only from the protocol runs end to end through the system, with loop
closure and a plugin factor (docs/architecture.md, "Adding a fourth frontend", which this test keeps honest)."""

from __future__ import annotations

import importlib
import re
from pathlib import Path

import numpy as np
import pytest

from eval_support import assert_beats_doing_nothing
from fgslam.backend import Backend
from fgslam.frontends.base import BackendFrontend, Frontend, LoopPort
from fgslam.loop.records import LoopClosureConfig
from fgslam.contracts.contributor import Contributor
from fgslam.run.config import SlamConfig
from fgslam.run.prepare import open_slam_dataset
from fgslam.run.runner import run_slam
from plugin_support import write_positions
from toy_frontend import ToyConfig, ToyFrontend

DESIGN = Path(__file__).resolve().parents[1] / "docs" / "architecture.md"
SECTION = "Adding a fourth frontend"
SHAPE = "### The shape of a run"  # the diagram of docs/architecture.md section 2
RATE_HZ = 4.0
EXTRA_FRAMES = 19  # frames past the first return to the start
POSITION_SIGMA_M = 0.3  # coarse positions: their noise and the prior's sigma (m)


@pytest.fixture(scope="module")
def room(room_loop_clip):
    """The synthetic room loop, past its return to the start (rendered once per session, conftest.py)."""
    return room_loop_clip(RATE_HZ, EXTRA_FRAMES)[0]


def _run(root: Path, out: Path, loops: bool, positions: Path | None):
    config = SlamConfig(sensor="rgbd")
    config.output.plot = False
    if loops:
        config.loop_closure = LoopClosureConfig(mode="classical", run_in_thread=False)
    if positions is not None:  # the shipped plugin, as a user's factors section names it
        config.factors = [{"class": "fgslam.services.plugins:PositionPrior",
                           "options": {"file": str(positions), "sigma": POSITION_SIGMA_M, "max_dt": 0.2, "min_spread": 0.5,
                                       "min_lateral_spread": 0.2, "align_scale": False}}]
    config.validate()
    dataset = open_slam_dataset(root, config)
    frontend = ToyFrontend(ToyConfig(), dataset.calibration, "rgbd", backend=Backend(config.map))
    summary = run_slam(dataset, config, out, progress=False, frontend=frontend)
    return summary, frontend, dataset


def test_a_fourth_frontend_runs_with_loop_closure_and_a_plugin(room, tmp_path):
    alone, _, dataset = _run(room, tmp_path / "alone", loops=False, positions=None)
    gt = dataset.groundtruth
    positions = write_positions(tmp_path / "positions.txt", gt.timestamps, gt.T_WC, 1.0, POSITION_SIGMA_M,
                                np.random.default_rng(0))
    both, frontend, _ = _run(room, tmp_path / "both", loops=True, positions=positions)
    assert alone.frames_with_pose == both.frames_with_pose == len(dataset)
    # the loop service found the return to the start and its corrections reached the toy
    assert both.loop["accepted_loops"] >= 1 and both.loop["corrections_applied"] >= 1
    assert both.loop["keyframes_added"] >= len(dataset) - 1
    # the plugin's priors are factors of the same graph
    assert len(frontend.backend.factor_handles("factors[0]")) >= 5
    ate_alone, ate_both = alone.ate_rmse, both.ate_rmse
    assert ate_both <= 0.5 * ate_alone, (ate_both, ate_alone)  # the drift is taken out (measured 0.045 vs 0.106 m)
    t_est = np.array(gt.timestamps)
    assert_beats_doing_nothing(ate_both, gt, t_est, "se3")


def test_the_toy_is_built_only_from_the_protocol():
    """What the design's section names is what the toy implements and the system calls."""
    text = DESIGN.read_text()
    start = text.index(SECTION)
    end = text.find("\n## ", start)
    section = text[start:end if end >= 0 else len(text)]
    named = set(re.findall(r"`(?:\w+\.)?(_?[a-z]\w*)\(", section))
    assert {"process", "connect", "finish", "finish_map", "trajectory", "num_keyframes", "_measure_frame",
            "_recover", "keyframe_image", "keyframe_pose", "apply_correction", "long_range_edges"} <= named
    for name in named:  # each is a method of the protocol, the port, the contract, or the toy's hook or config
        assert any(hasattr(cls, name) for cls in (Frontend, BackendFrontend, LoopPort, Contributor, ToyFrontend,
                                                  ToyConfig)), name
    frontend = ToyFrontend(backend=Backend())
    assert isinstance(frontend, Contributor)
    assert not any(hasattr(frontend, attr) for attr in ("closer", "imu_service", "plugins")), "services stay out"


def _resolves(dotted: str) -> bool:
    """Whether ``dotted`` names an importable module or an attribute of one."""
    parts = dotted.split(".")
    for cut in range(len(parts), 0, -1):
        try:
            obj = importlib.import_module(".".join(parts[:cut]))
        except ImportError:
            continue
        for name in parts[cut:]:
            if not hasattr(obj, name):
                return False
            obj = getattr(obj, name)
        return True
    return False


def test_the_design_diagram_names_what_the_code_has():
    """Every fgslam name in the diagram of the run's shape exists, and the diagram names the plug-in
    points this test's toy uses: the family registry, the frontend base class, the contributor
    contract, the factor-plugin contract and the system that owns them."""
    text = DESIGN.read_text()
    start = text.index("```text", text.index(SHAPE))
    block = text[start:text.index("```\n", start + len("```text"))]
    names = set(re.findall(r"\bfgslam(?:\.\w+)+", block))
    assert {"fgslam.frontends.FrontendFamily", "fgslam.frontends.base.BackendFrontend",
            "fgslam.contracts.contributor.Contributor", "fgslam.contracts.plugins.FactorPlugin",
            "fgslam.run.system.SlamSystem", "fgslam.backend.graph.Backend"} <= names
    assert [name for name in sorted(names) if not _resolves(name)] == []
    assert issubclass(ToyFrontend, BackendFrontend)  # the toy plugs in where the diagram says


def test_diagram_resolver_rejects_a_wrong_name():
    assert _resolves("fgslam.run.system.SlamSystem")
    assert not _resolves("fgslam.run.system.NoSuchSystem")
    assert not _resolves("fgslam.nosuchpackage.Thing")
