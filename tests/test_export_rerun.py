"""``fgslam run --rerun out.rrd``: the log holds a camera pose per posed frame, images, keyframe points
and loop edges (read back with rerun's own RRD reader). Skipped without the optional rerun SDK."""

from __future__ import annotations

import json
from types import SimpleNamespace

import numpy as np
import pytest

from fgslam.cli import main

FRAMES = 30


def _rows(path) -> dict[str, int]:
    """Rows per entity path of an RRD file."""
    import rerun.chunk as chunk

    rows: dict[str, int] = {}
    for c in chunk.RrdReader(str(path)).store().stream():
        key = str(c.entity_path)
        rows[key] = rows.get(key, 0) + int(c.num_rows)
    return rows


def test_run_writes_a_rerun_log(tmp_path):
    pytest.importorskip("rerun", reason="rerun is an optional extra (pip install 'fgslam[rerun]')")
    from fgslam.io.synth import SynthSequence, write_sequence
    from fgslam.io.synth.scenarios import load_synth_config

    root = tmp_path / "room"
    write_sequence(SynthSequence(load_synth_config("room-loop", overrides=[
        f"frames={FRAMES}", "camera.width=320", "camera.height=240"])), root)
    rrd = tmp_path / "run.rrd"
    assert main(["-q", "run", "patch_stereo", "--data", str(root), "--out", str(tmp_path / "out"), "--no-progress",
                 "--rerun", str(rrd), "-o", "output.rerun.map_every=10", "-o", "output.rerun.image_every=5"]) == 0
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    rows = _rows(rrd)  # stereo: every frame has a live pose (monocular frames wait for initialisation)
    assert rows["/world/camera"] == summary["frames_with_pose"] > 0
    assert rows["/world/camera/image"] == 1 + FRAMES // 5  # the static pinhole + every 5th frame
    assert rows["/world/points"] >= 1 and rows["/world/trajectory"] >= 1


def test_loop_edges_between_keyframe_centres(tmp_path):
    pytest.importorskip("rerun", reason="rerun is an optional extra (pip install 'fgslam[rerun]')")
    from fgslam.backend import Backend, BackendConfig
    from fgslam.export.rerun import RerunView, loop_segments
    from fgslam.loop.records import LoopRecord
    from fgslam.services.loops import LoopService

    backend = Backend(BackendConfig())
    for k in range(4):
        T = np.eye(4)
        T[:3, 3] = (k, 0.0, 0.0)
        backend.add_keyframe(k, T, float(k))
    classical = [LoopRecord(3, 0, np.eye(4), 50, "accepted"), LoopRecord(2, 0, np.eye(4), 9, "rejected")]
    service = SimpleNamespace(verified_loops=lambda: classical, proximity=object(),
                              proximity_loops=[(2, 1, "accepted"), (3, 9, "accepted")])
    pairs = LoopService.accepted_pairs(service)  # the service's own method on a stand-in
    assert pairs == [(3, 0), (2, 1), (3, 9)]
    calibration = SimpleNamespace(K=np.array([100.0, 100.0, 50.0, 40.0]), width=100, height=80)
    view = RerunView(str(tmp_path / "l.rrd"), calibration)
    segments = loop_segments(pairs, backend)  # keyframe 9 is not in the backend: skipped
    np.testing.assert_allclose(np.array(segments), [[[3, 0, 0], [0, 0, 0]], [[2, 0, 0], [1, 0, 0]]])
    view.close(None, segments)
    assert _rows(tmp_path / "l.rrd")["/world/loops"] == 1


def test_rerun_target_errors(tmp_path, capsys, monkeypatch):
    import fgslam.export.rerun as rerun_mod

    monkeypatch.setattr(rerun_mod, "rerun_available", lambda: False)
    assert main(["run", "patch_mono", "--data", str(tmp_path), "--out", str(tmp_path / "o"), "--rerun", "x.rrd"]) == 2
    assert "pip install 'fgslam[rerun]'" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()
    monkeypatch.setattr(rerun_mod, "rerun_available", lambda: True)
    assert main(["run", "patch_mono", "--data", str(tmp_path), "--out", str(tmp_path / "o"), "--rerun", "x.txt"]) == 2
    assert "give a .rrd file" in capsys.readouterr().err


def _columns(path, entity: str, column: str) -> list:
    """Every logged value of ``column`` of ``entity`` in an RRD file, in log order (rerun's chunk API)."""
    import rerun.chunk as chunk

    out = []
    for c in chunk.RrdReader(str(path)).store().stream():
        if str(c.entity_path) == entity:
            batch = c.to_record_batch()
            if column in batch.schema.names:
                out += batch.column(column).to_pylist()
    return out


def test_live_view_logs_poses_keyframes_points_and_the_current_image(tmp_path, monkeypatch):
    """``--rerun live``: the stream a viewer receives (rerun's in-memory sink in place of the gRPC
    connection) holds a camera pose per posed frame, the keyframe centres, the map points, the images
    with the map points projected into them and the measurement counts."""
    rr = pytest.importorskip("rerun", reason="rerun is an optional extra (pip install 'fgslam[rerun]')")
    from fgslam.export.rerun import RerunView, default_blueprint
    from fgslam.io.synth import SynthSequence, write_sequence
    from fgslam.io.synth.scenarios import load_synth_config

    sinks = []
    monkeypatch.setattr(rr.RecordingStream, "connect_grpc", lambda self, *a, **k: sinks.append(self.memory_recording()))
    root = tmp_path / "room"
    write_sequence(SynthSequence(load_synth_config("room-loop", overrides=[
        f"frames={FRAMES}", "camera.width=320", "camera.height=240"])), root)
    assert main(["-q", "run", "patch_stereo", "--data", str(root), "--out", str(tmp_path / "out"), "--no-progress",
                 "--rerun", "live", "-o", "output.rerun.map_every=10", "-o", "output.rerun.image_every=5"]) == 0
    assert len(sinks) == 1
    rrd = tmp_path / "live.rrd"
    rrd.write_bytes(sinks[0].drain_as_bytes())
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    rows = _rows(rrd)
    assert rows["/world/camera"] == summary["frames_with_pose"] == FRAMES
    assert rows["/stats/num_valid"] == FRAMES
    counts = _columns(rrd, "/stats/num_valid", "Scalars:scalars")
    assert min(v[0] for v in counts) > 0
    # the keyframe centres: one Points3D per map log (every 10 frames and at the end), growing
    keyframes = _columns(rrd, "/world/keyframes", "Points3D:positions")
    assert len(keyframes) == FRAMES // 10 + 1 and 2 <= len(keyframes[0]) <= len(keyframes[-1]) <= FRAMES
    poses = _columns(rrd, "/world/camera", "Transform3D:translation")
    assert any(np.allclose(keyframes[-1][-1], p) for p in poses)  # a keyframe centre is a logged camera pose
    assert len(_columns(rrd, "/world/points", "Points3D:positions")[-1]) > 50
    # each image after the first map log carries the map points projected from its pose, inside the image
    projected = _columns(rrd, "/world/camera/image/map_points", "Points2D:positions")
    assert len(projected) == (FRAMES - 10) // 5 and all(len(p) > 20 for p in projected)
    uv = np.concatenate([np.asarray(p) for p in projected])
    assert uv.min() >= -0.5 and uv[:, 0].max() < 320 and uv[:, 1].max() < 240
    # projection: a point on the optical axis lands on the principal point; points behind are dropped
    view = RerunView(str(tmp_path / "p.rrd"), type("C", (), {"K": np.array([100.0, 90.0, 50.0, 40.0]),
                                                           "width": 100, "height": 80})())
    T = np.eye(4)
    T[:3, 3] = (1.0, 2.0, 3.0)
    np.testing.assert_allclose(view.project(T, np.array([[1.0, 2.0, 5.0], [1.0, 2.0, 1.0], [1.5, 2.0, 5.0]])),
                               [[50.0, 40.0], [75.0, 40.0]])
    assert type(default_blueprint()).__name__ == "Blueprint"
