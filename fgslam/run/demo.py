"""The demo: render a synthetic ``room-loop`` sequence, run the default SLAM configuration (patch
frontend, monocular) on it, evaluate against the exact ground truth and report.

Configuration: :class:`DemoConfig`, preset ``fgslam/configs/demo.yaml``, with two sections: ``scene``
(:class:`DemoSceneConfig`: what is rendered) and ``slam`` (a :class:`fgslam.run.config.SlamConfig`: what
is run). ``-o scene.frames=200`` / ``-o slam.patch.ba.iterations=3`` override.

Outputs under the demo folder: ``sequence/`` (the rendered EuRoC-layout sequence, reused when a
later demo asks for the same scene) and ``run/`` (trajectories, ``summary.json``, ``trajectory.png``).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal, Sequence

import yaml

from ..core.config import MAX_FRAMES, MAX_IMAGE_SIDE, MAX_SCALAR, MAX_SEED, load_config, ranged, to_dict
from ..io.synth import SynthSequence, write_sequence
from ..io.synth.scenarios import load_synth_config
from .config import SlamConfig
from .prepare import prepare_run
from .presets import configs_dir
from .runner import run_prepared

PRESET_NAME = "demo"  # fgslam/configs/demo.yaml


@dataclass
class DemoSceneConfig:
    """The synthetic sequence the demo renders (one loop at 10 Hz: the demo must stay short)."""

    preset: Literal["room-loop", "street-loop", "orbit", "highway", "low-texture"] = "room-loop"  # synthetic scene and motion
    frames: int = ranged(201, ge=2, le=MAX_FRAMES)  # rendered frames (room-loop: one loop lasts 20 s: 201 frames at 10 Hz, 401 at 20 Hz)
    rate_hz: float = ranged(10.0, gt=0, le=MAX_SCALAR)  # camera frame rate (the motion's speed is fixed: a lower rate, larger steps)
    width: int = ranged(640, ge=32, le=MAX_IMAGE_SIDE)  # image width (px)
    height: int = ranged(480, ge=32, le=MAX_IMAGE_SIDE)  # image height (px)
    seed: int = ranged(0, ge=0, le=MAX_SEED)  # scene layout / texture seed


@dataclass
class DemoConfig:
    """``fgslam/configs/demo.yaml``: the scene rendered and the SLAM configuration run on it."""

    scene: DemoSceneConfig = field(default_factory=DemoSceneConfig)
    slam: SlamConfig = field(default_factory=SlamConfig)


def load_demo_config(path: str | Path | None = None, overrides: Sequence[str] = ()) -> DemoConfig:
    """DemoConfig from a YAML file (None: the preset ``fgslam/configs/demo.yaml`` when it exists, else the defaults)."""
    if path is None:
        default = configs_dir() / f"{PRESET_NAME}.yaml"
        path = default if default.is_file() else None
    return load_config(DemoConfig, path, overrides)


def render_scene(scene: DemoSceneConfig, root: str | Path) -> dict:
    """Render ``scene`` under ``root`` unless the same scene is already there; returns facts about it."""
    root = Path(root)
    cfg = load_synth_config(scene.preset, None, [
        f"frames={scene.frames}", f"seed={scene.seed}", f"camera.width={scene.width}",
        f"camera.height={scene.height}", f"camera.rate_hz={scene.rate_hz}"])
    recorded = root / "synth_config.yaml"
    t0 = time.perf_counter()
    complete = (root / "mav0" / "cam0" / "data.csv").is_file()
    if complete and recorded.is_file() and yaml.safe_load(recorded.read_text()) == to_dict(cfg):
        return {"path": str(root), "reused": True, "render_s": 0.0}
    if recorded.is_file():
        recorded.unlink()  # written last by write_sequence: an interrupted render is never reused
    write_sequence(SynthSequence(cfg), root)
    return {"path": str(root), "reused": False, "render_s": time.perf_counter() - t0}


def run_demo(config: DemoConfig, out_dir: str | Path, progress: bool = True) -> dict:
    """Render (or reuse) the scene under ``out_dir/sequence``, run SLAM into ``out_dir/run``.

    Returns ``{"scene", "sequence", "total_s", "summary"}`` (the run's summary.json content)."""
    out = Path(out_dir)
    t0 = time.perf_counter()
    rendered = render_scene(config.scene, out / "sequence")
    run = prepare_run(out / "sequence", config.slam, out / "run", fmt="euroc", overwrite=True)  # the demo's own run folder
    summary = run_prepared(run, progress=progress).to_dict()
    return {"scene": to_dict(config.scene), "sequence": rendered, "total_s": time.perf_counter() - t0,
            "summary": summary}


def format_demo_report(scene: DemoSceneConfig, rendered: dict, s: dict, total_s: float) -> str:
    """The demo's short report."""
    how = "reused" if rendered["reused"] else f"rendered in {rendered['render_s']:.1f} s"
    lines = [
        f"fgslam demo: {scene.preset}, {scene.frames} frames {scene.width}x{scene.height} ({how})",
        f"  SLAM:      {s['frontend']} frontend, {s['sensor']}",
        f"  frames:    {s['frames_processed']} processed, {s['frames_with_pose']} with a pose, "
        f"{s['keyframes']} keyframes, "
        f"{s['failures']['tracking']} tracking failures",
        f"  speed:     {s['fps']:.1f} frames/s ({s['wall_s']:.1f} s wall, {s['cpu_s']:.1f} s CPU)",
    ]
    ev = s["evaluation"]
    if ev is not None:
        pct = ev["ate_percent_of_path"]
        lines.append(f"  accuracy:  ATE {ev['ate_rmse_m']:.3f} m RMSE = {pct:.2f}% of the "
                     f"{ev['gt_path_length_m']:.2f} m path "
                     f"({ev['align']} alignment)")
    else:
        lines.append("  accuracy:  not evaluated (" + "; ".join(s["notes"] or ["no estimate"]) + ")")
    files = ", ".join(sorted(Path(p).name for p in s["outputs"].values()))
    lines.append(f"  outputs:   {s['out_dir']}: {files}")
    lines.append(f"  total:     {total_s:.1f} s")
    return "\n".join(lines)
