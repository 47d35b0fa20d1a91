"""The learned presets carry the official schedules (docs/architecture.md section 15), and the two schedule
settings added for them do what they say.

The official values are written out here from the public sources, in their own units:
princeton-vl/DROID-SLAM ``demo.py`` argument defaults, ``droid_slam/droid_frontend.py`` (``iters1``,
``iters2``, the initialisation's two rounds of 8 updates), ``factor_graph.py`` (``update(itrs=2)``,
``t0 = min(ii) + 1``), ``droid.py`` ``terminate`` (``backend(7)``, ``backend(12)``); princeton-vl/DPVO
``config/default.yaml`` over ``dpvo/config.py`` and ``dpvo/dpvo.py`` (12 updates at initialisation on 8
frames, one update per frame, ``fastba.BA(..., 2)``).
"""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from fgslam.run.config import load_slam_config

DROID_GRID = 8  # DROID's distances are 1/8-resolution pixels; fgslam's image pixels
DROID_DEMO = {"filter_thresh": 2.4, "warmup": 8, "keyframe_thresh": 4.0, "frontend_thresh": 16.0,
              "frontend_window": 25, "frontend_radius": 2, "iters1": 4, "iters2": 2, "init_updates": (8, 8),
              "init_radius": 3,
              "ba_itrs": 2, "backend_steps": 7 + 12, "backend_radius": 2, "backend_nms": 3, "backend_thresh": 22.0}
DPVO_RES = 4  # DPVO's flows are 1/4-resolution pixels
DPVO_DEFAULT = {"PATCHES_PER_FRAME": 96, "REMOVAL_WINDOW": 22, "OPTIMIZATION_WINDOW": 10, "PATCH_LIFETIME": 13,
                "KEYFRAME_INDEX": 4, "KEYFRAME_THRESH": 15.0, "MOTION_DAMPING": 0.5, "init_frames": 8,
                "init_updates": 12, "ba_itrs": 2}


def test_dense_learned_preset_follows_the_droid_slam_demo_schedule():
    cfg = load_slam_config("dense_learned_mono")
    d, o = cfg.dense, DROID_DEMO
    assert cfg.frontend == "dense" and d.source.kind == "droid" and cfg.needs_colour()
    assert d.source.droid.iterations == 1  # one operator iteration per update
    assert d.graph.motion_filter_flow == pytest.approx(o["filter_thresh"] * DROID_GRID)
    assert d.graph.init_keyframes == o["warmup"]
    assert (d.ba.init_neighbour_rounds, d.ba.init_rounds) == o["init_updates"]
    assert d.graph.init_radius == o["init_radius"] and d.ba.init_iterations == o["ba_itrs"]
    assert d.ba.rounds == o["iters1"] and d.ba.kept_rounds == o["iters2"] and d.ba.iterations == o["ba_itrs"]
    assert d.graph.remove_threshold == pytest.approx(o["keyframe_thresh"] * DROID_GRID)
    assert d.graph.max_edge_distance == pytest.approx(o["frontend_thresh"] * DROID_GRID)
    assert d.graph.active_keyframes == o["frontend_window"] and d.graph.temporal_radius == o["frontend_radius"]
    assert d.ba.window == o["frontend_window"] - 1  # all but the oldest keyframe of the graph free
    assert d.ba.remeasure >= d.graph.active_keyframes  # every edge re-measured by every update
    assert d.tracking.motion_damping == 0.0  # the new frame starts at the previous pose
    g = d.global_ba
    assert g.final and g.rounds == o["backend_steps"] and g.iterations == o["ba_itrs"]
    assert g.temporal_radius == o["backend_radius"] and g.nms_radius == o["backend_nms"]
    assert g.max_distance == pytest.approx(o["backend_thresh"] * DROID_GRID)


def test_patch_learned_preset_follows_the_dpvo_defaults():
    cfg = load_slam_config("patch_learned_mono")
    p, o = cfg.patch, DPVO_DEFAULT
    assert cfg.frontend == "patch" and p.source == "dpvo" and cfg.needs_colour()
    assert cfg.loop_closure.mode == "off"
    assert p.dpvo.iterations == 1 and p.ba.rounds == 1 and p.ba.iterations == o["ba_itrs"]
    assert p.ba.remeasure == "window"  # the update runs on every edge of the patch graph
    assert p.ba.init_rounds == o["init_updates"] and p.ba.init_iterations == o["ba_itrs"]
    assert p.tracking.init_min_frames == p.tracking.init_max_frames == o["init_frames"]
    assert p.graph.patches_per_frame == o["PATCHES_PER_FRAME"] and p.graph.patch_size == 3
    assert p.graph.patch_stride == DPVO_RES
    # DPVO counts windows in frames including the newest, fgslam in frames before it
    assert p.graph.patch_lifetime == o["PATCH_LIFETIME"] - 1
    assert p.graph.removal_window == o["REMOVAL_WINDOW"] - 1
    assert p.graph.optimization_window == o["OPTIMIZATION_WINDOW"]
    assert p.tracking.keyframe_index == o["KEYFRAME_INDEX"] - 1
    assert p.tracking.keyframe_threshold == pytest.approx(o["KEYFRAME_THRESH"] * DPVO_RES)
    assert p.tracking.motion_damping == o["MOTION_DAMPING"]
    assert p.tracking.motion_filter_flow == 0.0  # every frame enters once initialised


def test_built_in_presets_keep_their_measured_schedules():
    dense, patch = load_slam_config("dense_mono").dense, load_slam_config("patch_mono").patch
    assert dense.source.kind == "flow" and dense.ba.kept_rounds == 0 and dense.ba.rounds == 1
    assert dense.ba.init_neighbour_rounds == 0 and dense.ba.init_rounds == 5
    assert dense.graph.motion_filter_flow == 12.0 and dense.graph.active_keyframes == 12
    assert patch.source == "lk" and patch.ba.remeasure == "new" and patch.ba.rounds == 2
    assert patch.graph.patch_lifetime == 5 and patch.tracking.keyframe_threshold == 20.0
    assert not load_slam_config("dense_mono").needs_colour() and not load_slam_config("patch_mono").needs_colour()


# ---------------------------------------------------------------- the two settings added for them
def _local_ba(remeasure: str, num_edges: int, created: np.ndarray):
    """A LocalBA whose measurer and optimiser only record what they are given."""
    from fgslam.frontends.patch.config import PatchConfig
    from fgslam.frontends.patch.window import LocalBA

    cfg = PatchConfig()
    cfg.ba.remeasure = remeasure
    cfg.tracking.min_valid_edges = 1
    measured = []
    graph = SimpleNamespace(num_edges=num_edges, created=created, confidence=np.ones(num_edges),
                            robust=np.ones(num_edges), right=np.zeros(num_edges, bool), src=created.copy(),
                            tgt=created.copy(), _select=lambda keep: None)
    state = SimpleNamespace(graph=graph, config=cfg, times={"bookkeeping": 0.0})
    ba = LocalBA.__new__(LocalBA)
    ba.state = state
    ba.measurer = SimpleNamespace(measure=lambda idx, huber: measured.append(np.asarray(idx).copy()))

    def optimize(iterations, init):
        ba.last_residual = np.where(np.arange(num_edges) % 2 == 0, 10.0, 0.0)  # even edges: bad residuals
    ba.optimize = optimize
    return ba, measured


def test_patch_remeasure_window_measures_every_active_edge_every_round():
    created = np.array([1, 1, 1, 1, 2, 2, 2, 2])  # edges 4..7 are the new frame's
    new = np.arange(4, 8)
    ba, measured = _local_ba("new", 8, created)
    ba.rounds(new, rounds=2, iterations=1, init=False, new_fid=2, premeasured=np.array([5]))
    assert [m.tolist() for m in measured] == [[4, 6, 7], [4, 6]]  # new edges, then its bad ones
    ba, measured = _local_ba("window", 8, created)
    ba.rounds(new, rounds=3, iterations=1, init=False, new_fid=2, premeasured=np.array([5]))
    assert [m.tolist() for m in measured] == [[0, 1, 2, 3, 4, 6, 7], list(range(8)), list(range(8))]


@pytest.fixture(scope="module")
def room_rgbd(tmp_path_factory):
    from fgslam.io.datasets import DatasetConfig, open_dataset
    from patch_support import render_room

    root = render_room(tmp_path_factory, "kept_rounds_room", ["frames=10", "camera.width=160", "camera.height=128"])
    return list(open_dataset(root, config=DatasetConfig(load_depth=True, load_imu=False)))


def test_dense_kept_rounds_run_only_when_the_keyframe_stays(room_rgbd):
    """With ``kept_rounds`` the local BA runs again (that many rounds) after each keyframe decision that
    keeps the second newest keyframe, never after one that removes it; with 0 never."""
    from fgslam.backend import Backend, BackendConfig
    from fgslam.frontends.dense.config import DenseConfig
    from fgslam.frontends.dense.frontend import DenseFrontend

    def run(kept_rounds):
        cfg = DenseConfig()
        cfg.ba.kept_rounds = kept_rounds
        cfg.graph.motion_filter_flow = 2.0  # small images: many keyframes
        cfg.graph.remove_threshold = 4.0  # ... some of them removed
        fe = DenseFrontend(cfg, sensor_mode="rgbd", backend=Backend(BackendConfig()))
        calls, local = [], fe.ba.local

        def recording(fid, rounds=None):
            calls.append((fid, rounds))
            return local(fid, rounds)
        fe.ba.local = recording
        statuses = [fe.process(f) for f in room_rgbd]
        fe.finish()
        return calls, statuses

    calls, statuses = run(2)
    first = [fid for fid, rounds in calls if rounds is None]
    again = [fid for fid, rounds in calls if rounds == 2]
    removed = {n for n, s in enumerate(statuses) if any("keyframe removed" in e for e in s.events)}
    assert first and removed and again  # the clip exercises both outcomes
    assert sorted(again) == sorted(f for f in first if f not in removed)
    calls, _ = run(0)
    assert calls and all(rounds is None for _, rounds in calls)


def test_dense_initialisation_starts_on_the_neighbourhood_edges(room_rgbd):
    """With ``init_neighbour_rounds`` the monocular initialisation first measures only the edges between
    keyframes at most ``init_radius`` apart (both ways, each pair once), then every pair within reach."""
    from fgslam.backend import Backend, BackendConfig
    from fgslam.frontends.dense.config import DenseConfig
    from fgslam.frontends.dense.frontend import DenseFrontend

    cfg = DenseConfig()
    cfg.graph.init_keyframes, cfg.graph.init_radius, cfg.graph.motion_filter_flow = 6, 1, 2.0
    cfg.ba.init_neighbour_rounds, cfg.ba.init_rounds = 2, 1
    fe = DenseFrontend(cfg, sensor_mode="mono", backend=Backend(BackendConfig()))
    calls, measure = [], fe.ba.measure

    def recording(edges, *args):
        calls.append((fe.state.initialized, list(edges)))
        return measure(edges, *args)
    fe.ba.measure = recording
    for frame in room_rgbd:
        fe.process(frame)
        if fe.state.initialized:
            break
    assert fe.state.initialized
    init = [edges for done, edges in calls if not done]
    assert len(init) == 3
    pos = {f: k for k, f in enumerate(fe.state.graph.order())}
    n = cfg.graph.init_keyframes
    neighbourhood = sorted((f, g) for f in pos for g in pos if 0 < abs(pos[f] - pos[g]) <= 1 and pos[f] < n and pos[g] < n)
    assert sorted(init[0]) == sorted(init[1]) == neighbourhood
    assert set(init[2]) > set(neighbourhood)  # then the wider edge set (temporal radius 2, nearest keyframes)
