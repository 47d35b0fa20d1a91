"""Extending a stored map with a recording (``fgslam run ... --map MAP``, :mod:`fgslam.run.mapstore`):
the recording's keyframes localised in the map (:class:`fgslam.localize.localizer.MapLocalizer`), the
transform between the two frames estimated from them (:func:`merge_recording`), the merged map
(:func:`combine_maps`) with the recording's poses in the map's frame, and the joint optimisation of
the sessions (:func:`join_sessions`): one Sim(3) pose graph of every session's keyframes, whose loops
are the recording's localisations in the map, so that both sessions are corrected."""

from __future__ import annotations

import logging
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from ..core.mapdata import rigid_poses
from ..export.mapfile import MapJoinConfig, StoredMap
from .anchor import mean_rotation, scale_translation
from .localizer import LocalizeConfig, MapLocalizer

logger = logging.getLogger(__name__)


@dataclass
class MapMerge:
    """A recording merged into a stored map: ``S_MR`` (4x4 Sim(3), recording frame -> map frame;
    rigid for metric maps), the first keyframe localised in the map (``merge_kf_id``, at
    ``merge_time``: frames from then on are reported in the map's frame) and the keyframes that
    support it (``verified`` of ``tried``)."""

    S_MR: np.ndarray
    merge_kf_id: int
    merge_time: float
    verified: int
    consistent: int
    tried: int
    #: the consistent localisations: (recording keyframe position, stored keyframe position it was
    #: verified against, the recording keyframe's pose in the map's frame 4x4)
    links: list[tuple[int, int, np.ndarray]] = field(default_factory=list)

    def to_dict(self) -> dict[str, Any]:
        return {"S_MR": self.S_MR.tolist(), "merge_keyframe": self.merge_kf_id, "merge_time": self.merge_time,
                "verified_keyframes": self.verified, "consistent_keyframes": self.consistent,
                "keyframes_tried": self.tried}


def merge_recording(stored: StoredMap, recording: StoredMap, config: LocalizeConfig | None = None,
                    metric: bool | None = None) -> MapMerge | None:
    """Localise the keyframes of a ``recording`` (a stored map of the new run, own frame) in
    ``stored`` one after the other (:class:`MapLocalizer`: retrieval + verification, then tracking),
    and estimate the transform between the two frames from the localised keyframes: the rotation
    from their poses (the map-from-recording rotations within ``merge.max_rotation_deg`` of the
    best-supported one, averaged), the scale (unless ``metric``: by default when both maps are metric,
    ``meta["metric"]``; a monocular map on either side has its own scale) and translation from their
    positions (least squares). None (no merge) with fewer than ``merge.min_keyframes`` consistent."""
    config = config or LocalizeConfig()
    if metric is None:
        metric = stored.metric and recording.metric
    mc = config.merge
    if stored.meta["features"] != recording.meta["features"]:
        logger.warning("map merge: the recording's keyframe features were made with other settings than the "
                       "map's (output.map_features): not merged")
        return None
    localizer = MapLocalizer(stored, config)
    pairs: list[tuple[int, np.ndarray, np.ndarray]] = []
    verified_on: list[int] = []
    position = {int(kf): i for i, kf in enumerate(stored.kf_ids)}
    for k in range(recording.num_keyframes):
        uv, desc, _ = recording.features(k)
        res = localizer.localize_features(uv, desc)
        if res.T_WC is not None:
            pairs.append((k, res.T_WC, recording.T_WC[k]))
            verified_on.append(position[res.kf_id])
    if len(pairs) < mc.min_keyframes:
        logger.info("map merge: %d of %d recording keyframes localised in the map (< %d): not merged",
                    len(pairs), recording.num_keyframes, mc.min_keyframes)
        return None
    R_rec = [T_R[:3, :3] / np.cbrt(np.linalg.det(T_R[:3, :3])) for _, _, T_R in pairs]
    R_MR = np.stack([T_M[:3, :3] @ R.T for (_, T_M, _), R in zip(pairs, R_rec)])
    cos_max = np.cos(np.deg2rad(mc.max_rotation_deg))
    agree = (np.einsum("aij,bij->ab", R_MR, R_MR) - 1.0) / 2.0 >= cos_max   # cos of the angle between each two
    best = int(agree.sum(axis=1).argmax())
    inl = np.flatnonzero(agree[best])
    R = mean_rotation(R_MR[inl])
    p_M = np.stack([pairs[i][1][:3, 3] for i in inl])
    p_R = np.stack([pairs[i][2][:3, 3] for i in inl])
    scale, t = scale_translation(R, p_R, p_M, with_scale=not metric)
    resid = np.linalg.norm(p_M - (scale * p_R @ R.T + t), axis=1)
    extent = max(float(np.linalg.norm(p_M.max(axis=0) - p_M.min(axis=0))), float(np.finfo(float).eps))
    consistent = inl[resid <= mc.max_position_error * extent] if len(inl) > 2 else inl
    if len(consistent) < mc.min_keyframes or scale <= 0:
        logger.info("map merge: %d consistent keyframes (< %d): not merged", len(consistent), mc.min_keyframes)
        return None
    S = np.eye(4)
    S[:3, :3] = scale * R
    S[:3, 3] = t
    first = pairs[int(consistent.min())][0]
    logger.info("map merge: %d of %d recording keyframes localised, %d consistent; merged from keyframe %d "
                "(scale %.4f)", len(pairs), recording.num_keyframes, len(consistent),
                int(recording.kf_ids[first]), scale)
    links = [(pairs[i][0], verified_on[i], pairs[i][1]) for i in consistent]
    return MapMerge(S, int(recording.kf_ids[first]), float(recording.kf_timestamps[first]), len(pairs),
                    len(consistent), recording.num_keyframes, links)


def combine_maps(stored: StoredMap, recording: StoredMap, S_MR: np.ndarray) -> StoredMap:
    """The merged map: ``stored`` and the ``recording``'s keyframes, structure and database moved
    into the map's frame by ``S_MR`` (Sim(3) poses ``S_MR T_WC``: camera points keep the
    recording's units), the recording's keyframe ids after the stored ones."""
    offset = int(stored.kf_ids.max()) + 1 if stored.num_keyframes else 0
    meta = dict(stored.meta)
    meta["recordings"] = int(stored.meta.get("recordings", 1)) + 1
    X_new = recording.points_X_W @ S_MR[:3, :3].T + S_MR[:3, 3]
    K1 = stored.num_keyframes
    return StoredMap(
        meta,
        np.concatenate([stored.kf_ids, recording.kf_ids + offset]),
        np.concatenate([stored.kf_timestamps, recording.kf_timestamps]),
        np.concatenate([stored.kf_frame_index, recording.kf_frame_index]),
        np.concatenate([stored.T_WC, S_MR[None] @ recording.T_WC]),
        np.concatenate([stored.feat_ptr, recording.feat_ptr[1:] + stored.feat_ptr[-1]]),
        np.concatenate([stored.feat_uv, recording.feat_uv]),
        np.concatenate([stored.feat_desc, recording.feat_desc]),
        np.concatenate([stored.feat_X_C, recording.feat_X_C]),
        np.concatenate([stored.bow_ptr, recording.bow_ptr[1:] + stored.bow_ptr[-1]]),
        np.concatenate([stored.bow_words, recording.bow_words]),
        np.concatenate([stored.bow_weights, recording.bow_weights]),
        np.concatenate([stored.points_X_W, X_new]),
        np.concatenate([stored.points_colour, recording.points_colour]),
        np.concatenate([stored.track_point, recording.track_point + len(stored.points_X_W)]),
        np.concatenate([stored.track_kf, recording.track_kf + offset]),
        np.concatenate([stored.track_uv, recording.track_uv]),
        np.concatenate([stored.kf_session, recording.kf_session + stored.sessions]),
        np.concatenate([stored.frame_timestamps, recording.frame_timestamps]),
        np.concatenate([stored.frame_kf, recording.frame_kf + K1]),
        np.concatenate([stored.frame_T_KC, recording.frame_T_KC]))


@dataclass
class JointResult:
    """:func:`join_sessions`: the joined map and what the joint pose graph did."""

    joined: StoredMap
    loops: int
    accepted: int
    stored_moved_max: float  # largest position change of a stored keyframe (map units)
    recording_moved_max: float  # ... of a recording keyframe against the one-transform merge

    def to_dict(self) -> dict[str, Any]:
        return {"loops": self.loops, "accepted_loops": self.accepted, "sessions": self.joined.sessions,
                "stored_keyframes_moved_max": self.stored_moved_max,
                "recording_keyframes_moved_max": self.recording_moved_max}


def _similarity(T: np.ndarray, scale: np.ndarray) -> np.ndarray:
    """Poses ``T`` (N, 4, 4) with their rotation blocks scaled by ``scale`` (N,): Sim(3) of that scale."""
    S = rigid_poses(T)
    S[:, :3, :3] *= scale[:, None, None]
    return S


def join_sessions(stored: StoredMap, recording: StoredMap, merge: MapMerge,
                  config: MapJoinConfig | None = None) -> JointResult:
    """The recording joined to ``stored`` in one graph: :func:`combine_maps` by ``merge.S_MR``, then
    one Sim(3) pose graph (:func:`fgslam.loop.pose_graph.optimize_sim3_pose_graph`) of every keyframe of
    every session, smooth along each session, weakly linked across session boundaries
    (``session_link_sigma_multiple``), with the recording's localisations in the map as loops
    (``merge.links``: the pose of the recording keyframe relative to the stored keyframe it was verified
    against, the scale being the recording's, which a localisation does not measure). When both sides
    are metric every keyframe keeps its scale (SE(3)); with a monocular side the graph is Sim(3).
    Keyframes, points (with the keyframe of their first track; a point without tracks with the nearest
    keyframe) and frames (with their anchor keyframe) move with the correction."""
    from ..core.lie import Sim3  # deferred: torch
    from ..loop.pose_graph import optimize_sim3_pose_graph  # deferred: torch, gtsam

    import torch  # deferred: torch

    config = config or MapJoinConfig()
    pose_graph = _in_map_units(config, stored)
    joined = combine_maps(stored, recording, merge.S_MR)
    K1, K = stored.num_keyframes, joined.num_keyframes
    T_old = joined.T_WC
    scale = np.cbrt(np.linalg.det(T_old[:, :3, :3]))
    rec = np.array([K1 + k for k, _, _ in merge.links], np.int64)
    ref = np.array([i for _, i, _ in merge.links], np.int64)
    T_loc = _similarity(np.stack([T for _, _, T in merge.links]), scale[rec]) if merge.links else np.zeros((0, 4, 4))
    Z = np.linalg.inv(T_old[ref]) @ T_loc if len(rec) else np.zeros((0, 4, 4))
    boundary = np.diff(joined.kf_session) != 0
    smooth_scale = np.where(boundary, config.session_link_sigma_multiple, 1.0)
    result = optimize_sim3_pose_graph(
        Sim3.from_matrix(torch.from_numpy(T_old)), ref, rec, Sim3.from_matrix(torch.from_numpy(Z)),
        pose_graph, hold_scale=stored.metric and recording.metric, smooth_scale=smooth_scale)
    T_new = result.T_WC.matrix().numpy()
    correction = T_new @ np.linalg.inv(T_old)  # X_W' = C_k X_W for what keyframe k carries
    C = correction[_point_owners(joined)]
    joined.points_X_W = np.einsum("nij,nj->ni", C[:, :3, :3], joined.points_X_W) + C[:, :3, 3]
    joined.T_WC = T_new
    moved = np.linalg.norm(T_new[:, :3, 3] - T_old[:, :3, 3], axis=1)
    logger.info("joint optimisation of %d sessions: %d keyframes, %d of %d loops accepted; stored keyframes moved "
                "up to %.4g, recording keyframes up to %.4g", joined.sessions, K, int(result.accepted.sum()),
                len(rec), float(moved[:K1].max(initial=0.0)), float(moved[K1:].max(initial=0.0)))
    return JointResult(joined, len(rec), int(result.accepted.sum()), float(moved[:K1].max(initial=0.0)),
                       float(moved[K1:].max(initial=0.0)))


def _in_map_units(config: MapJoinConfig, stored: StoredMap):
    """``config.pose_graph`` with its translation sigmas scaled by the stored map's median feature depth
    over ``config.reference_depth`` (unchanged for a map without 3-D features)."""
    kf_scale = np.cbrt(np.linalg.det(stored.T_WC[:, :3, :3]))  # camera units -> map units per keyframe
    z = stored.feat_X_C[:, 2] * np.repeat(kf_scale, np.diff(stored.feat_ptr))
    z = z[np.isfinite(z) & (z > 0)]
    if z.size == 0:
        return config.pose_graph
    units = float(np.median(z)) / config.reference_depth
    pg = config.pose_graph

    def scaled(sigmas: tuple[float, ...]) -> tuple[float, ...]:
        return (*sigmas[:3], *(units * np.asarray(sigmas[3:6])).tolist(), *sigmas[6:])

    return replace(pg, loop_sigmas=scaled(pg.loop_sigmas), smooth_sigmas=scaled(pg.smooth_sigmas))


def _point_owners(stored: StoredMap) -> np.ndarray:
    """(M,) the keyframe position each point moves with: the keyframe of its first track, else (a
    family that exports points without tracks) the keyframe whose camera is nearest."""
    from scipy.spatial import cKDTree  # deferred: scipy

    K, M = stored.num_keyframes, len(stored.points_X_W)
    owner = np.full(M, -1, np.int64)
    if len(stored.track_point):
        position = np.full(int(stored.kf_ids.max()) + 1, -1, np.int64)
        position[stored.kf_ids] = np.arange(K)
        points, first = np.unique(stored.track_point, return_index=True)
        owner[points] = position[stored.track_kf[first]]
    lone = np.flatnonzero(owner < 0)
    if lone.size and K:
        owner[lone] = cKDTree(stored.T_WC[:, :3, 3]).query(stored.points_X_W[lone])[1]
    return owner
