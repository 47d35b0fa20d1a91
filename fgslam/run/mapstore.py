"""``--save-map`` and ``--map`` of a run: a step of its own that the runner calls once the run's
results are in (:func:`store_map`).

``--save-map``: the stored map of :mod:`fgslam.export.mapfile` (keyframes, structure, features,
retrieval database, calibration, config and the run's alignment to its ground truth), written
atomically. ``--map``: the recording is merged into that stored map when its keyframes localise in it
(:func:`fgslam.localize.merge.merge_recording`) and the sessions are optimised together
(:func:`fgslam.localize.merge.join_sessions`; ``output.map_join``): ``merge.json``,
``merged_trajectory_tum.txt`` (the recording's frames from the merge on, in the map's frame) and
``joint_trajectory_tum.txt`` (every session's frames, in the map's frame, after the joint
optimisation), and ``--save-map`` saves the joined map. A failure is
recorded among the run's output errors, never raised: the other outputs are written regardless."""

from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np

from ..core.config import to_dict
from ..export.mapfile import build_stored_map, load_stored_map, save_stored_map
from ..frontends.base import Frontend
from ..io.trajectory import Trajectory, write_trajectory
from ..localize.localizer import LocalizeConfig
from ..localize.merge import combine_maps, join_sessions, merge_recording, placed_parts
from .files import JOINT_TUM_FILE, MERGE_FILE, MERGED_TUM_FILE
from .outputs import OutputWriter
from .prepare import PreparedRun
from .results import RunResults, RunState

logger = logging.getLogger(__name__)


def store_map(writer: OutputWriter, run: PreparedRun, frontend: Frontend, state: RunState, results: RunResults) -> None:
    """Save the run's stored map (``output.save_map``) and, with ``output.extend_map``, merge the
    recording into that map first (module docstring); the run has a final trajectory
    (``results.traj``)."""
    config, dataset, traj, notes = run.config, run.dataset, results.traj, results.notes
    out, result = writer.out, results.eval_result
    save_path = Path(config.output.save_map) if config.output.save_map else None
    try:
        exported = frontend.map_export()
    except Exception as exc:  # noqa: BLE001 - recorded; the other outputs are still written
        writer.fail("stored_map", f"map_export() failed: {type(exc).__name__}: {exc}")
        return
    if exported is None or exported.num_keyframes == 0:
        notes.append(f"frontend '{frontend.name}' exports no keyframes: no stored map written or extended")
        return
    alignment = None if result is None else {"align": result.align, "matrix": result.alignment.matrix().tolist()}
    try:
        recording = build_stored_map(
            exported, dataset, sensor=config.sensor, family=frontend.name, config=to_dict(config),
            features=config.output.map_features, verification=config.loop_closure.verification,
            groundtruth_alignment=alignment, frame_indices=np.array(sorted(state.frame_paths), dtype=np.int64),
            trajectory=(traj.timestamps, traj.T_WC), map_starts=np.asarray(state.map_starts))
    except Exception as exc:  # noqa: BLE001 - recorded; the other outputs are still written
        writer.fail("stored_map", f"building the stored map failed: {type(exc).__name__}: {exc}")
        logger.error("could not build the stored map: %s: %s", type(exc).__name__, exc)
        return
    to_save = recording
    if config.output.extend_map:
        try:
            stored = load_stored_map(config.output.extend_map)
            merge = merge_recording(stored, recording, LocalizeConfig(merge=config.output.map_merge))  # Sim(3) unless both metric
        except Exception as exc:  # noqa: BLE001 - recorded; the other outputs are still written
            writer.fail("merge", f"--map {config.output.extend_map}: {type(exc).__name__}: {exc}")
            logger.error("could not merge the recording into %s: %s", config.output.extend_map, exc)
            return
        joint = None
        if merge is not None and config.output.map_join.enabled:
            try:
                joint = join_sessions(stored, recording, merge, config.output.map_join)
            except Exception as exc:  # noqa: BLE001 - a logged recovery: the merge by its transforms is written
                why = f"the joint optimisation failed ({type(exc).__name__}: {exc}): merged by the transform of each part alone"
                notes.append(f"--map {config.output.extend_map}: {why}")
                logger.warning("%s", why)
        info = {"map": config.output.extend_map, "merged": merge is not None,
                **({} if merge is None else merge.to_dict()),
                **({} if joint is None else {"joint": joint.to_dict()})}
        if merge is None:
            notes.append(f"--map {config.output.extend_map}: no keyframe of the recording localised in it "
                         "consistently: not merged (the recording stays its own map)")
        else:  # the recording's frames in the map's frame: with their keyframes, moved by the join or the merge
            if joint is None:
                placed, _, S_MR_by_part = placed_parts(recording, merge)
                to_save = combine_maps(stored, placed, S_MR_by_part)
            else:
                to_save = joint.joined
            t_all, T_all = to_save.frame_poses()
            ours = np.arange(len(t_all)) >= len(stored.frame_timestamps)  # the recording's frames come last
            keep = ours & (t_all >= merge.merge_time)
            path = out / MERGED_TUM_FILE
            writer.write("merged_trajectory", [path],
                         lambda: write_trajectory(path, Trajectory(t_all[keep], T_all[keep]), "tum"))
            if joint is not None:
                by_time = np.argsort(t_all, kind="stable")  # sessions of one clock (a dataset's parts) follow each other
                joint_path = out / JOINT_TUM_FILE
                writer.write("joint_trajectory", [joint_path],
                             lambda: write_trajectory(joint_path, Trajectory(t_all[by_time], T_all[by_time]), "tum"))
        merge_path = out / MERGE_FILE
        writer.write("merge", [merge_path],
                     lambda: merge_path.write_text(json.dumps(info, indent=2) + "\n", encoding="utf-8"))
    if save_path is not None:  # written atomically: a failure leaves an earlier file at that path as it was
        try:
            save_stored_map(save_path, to_save)
            writer.record("stored_map", str(save_path))
        except Exception as exc:  # noqa: BLE001 - recorded; the other outputs are still written
            writer.fail("stored_map", f"{save_path}: {type(exc).__name__}: {exc}")
            logger.error("could not write the stored map %s: %s", save_path, exc)
