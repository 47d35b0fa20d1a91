"""The patch frontend runs through the run's backend: one Backend per run handed to the frontend,
graph frames are backend keyframes, the local BA is the backend's window optimisation with the
backend's own settings, and ``-o map.solver=isam2`` runs end to end."""

from __future__ import annotations

import numpy as np
import pytest

import fgslam.backend.optimizer as backend_optimizer
import fgslam.backend.window as backend_window
from fgslam.backend import Backend, BackendConfig, pose_key
from fgslam.core.config import load_config
from fgslam.frontends.patch import PatchFrontend
from fgslam.frontends.records import RelativePose
from fgslam.run.config import SlamConfig
from fgslam.run.prepare import open_slam_dataset
from fgslam.run.runner import run_slam
from patch_support import light_patch_config, open_frames, render_room

FRAMES = 40


@pytest.fixture(scope="module")
def room(tmp_path_factory):
    return render_room(tmp_path_factory, "room", [f"frames={FRAMES}", "camera.width=320", "camera.height=240"])


def test_graph_frames_are_backend_keyframes_and_poses_live_in_the_backend(room):
    ds, frames = open_frames(room, "mono")
    backend = Backend(BackendConfig())
    fe = PatchFrontend(light_patch_config(), sensor_mode="mono", backend=backend)
    assert fe.backend is backend
    events = []
    with_block = 0
    for frame in frames:
        events += fe.process(frame).events
        # the patch contributor's block: the last window's, over graph frames only (dropped with a
        # keyframe that leaves the backend)
        blocks = backend.blocks("patch")
        assert len(blocks) <= 1
        if blocks:
            with_block += 1
            assert set(blocks[0].keys) <= {pose_key(f.fid) for f in fe.graph.frames}
    assert with_block > FRAMES // 2
    assert any("removed" in e for e in events)  # a redundant keyframe left the graph (and the backend)
    graph_fids = [f.fid for f in fe.graph.frames]
    final_fids = sorted(fe._final)
    assert final_fids  # some keyframes were finalised: they stay in the backend
    assert backend.keyframe_ids == sorted(graph_fids + final_fids)
    removed = [fid for fid, rec in fe._records.items() if isinstance(rec, RelativePose)
               and fid not in fe._final and not any(fid == f.fid for f in fe.graph.frames)]
    assert removed and not any(backend.has_keyframe(fid) for fid in removed)
    for f in fe.graph.frames + list(fe._final.values()):
        np.testing.assert_array_equal(f.T_WC, backend.pose_matrix(f.fid))
        assert backend.timestamp(f.fid) == f.timestamp
    # a pose assigned on the frame is the backend's pose
    f = fe.graph.frames[-1]
    T = f.T_WC.copy()
    T[:3, 3] += 0.25
    f.T_WC = T
    np.testing.assert_allclose(backend.pose_matrix(f.fid), T, atol=1e-12)


def test_local_ba_uses_the_backends_settings(room, monkeypatch):
    """No override of map.solver, the gauge sigmas or the damping: the window's LM runs with
    map.window.lambda_factor and the frontend's own iteration count."""
    ds, frames = open_frames(room, "mono")
    seen = []
    real = backend_optimizer.levenberg_marquardt

    def spy(problem, settings, propose=None, ordering_cache=None, initial_cost=None):
        seen.append((settings, propose))
        return real(problem, settings, propose=propose, ordering_cache=ordering_cache, initial_cost=initial_cost)

    monkeypatch.setattr(backend_optimizer, "levenberg_marquardt", spy)
    config = BackendConfig()
    config.window.lambda_factor = 7.0
    config.lambda_factor = 3.0
    patch = light_patch_config()
    fe = PatchFrontend(patch, sensor_mode="mono", backend=Backend(config))
    for f in frames[:20]:
        fe.process(f)
    assert seen
    assert {s.lambda_factor for s, _ in seen} == {7.0}
    assert {s.max_iterations for s, _ in seen} <= {patch.ba.iterations, patch.ba.init_iterations}
    assert all(p is None for _, p in seen)  # map.solver lm


def test_map_solver_isam2_runs_the_patch_frontend_end_to_end(room, tmp_path, monkeypatch):
    """``-o map.solver=isam2`` through the runner: the one Backend it builds runs every window step
    through iSAM2, and the run is as accurate as test_patch_frontend's monocular bound."""
    built = []
    steps = []
    real_init = Backend.__init__
    real_call = backend_window.Isam2Stepper.__call__

    def init_spy(self, config=None):
        built.append(self)
        real_init(self, config)

    def call_spy(self, gfg):
        steps.append(1)
        return real_call(self, gfg)

    monkeypatch.setattr(Backend, "__init__", init_spy)
    monkeypatch.setattr(backend_window.Isam2Stepper, "__call__", call_spy)
    config = load_config(SlamConfig, None, ["sensor=mono", "map.solver=isam2", "output.plot=false"])
    config.patch = light_patch_config()
    ds = open_slam_dataset(room, config)
    summary = run_slam(ds, config, tmp_path / "out", progress=False)
    assert len(built) == 1 and built[0].config.solver_kind == "isam2"
    assert steps  # the window steps came from iSAM2
    assert summary.error is None and summary.failures["tracking"] == 0
    ev = summary.evaluation
    assert ev["ate_rmse_m"] <= 0.01 * ev["gt_path_length_m"] + 0.001  # test_patch_frontend's mono bound
