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
from ..export.mapfile import MapJoinConfig, MapMergeConfig, StoredMap
from .anchor import mean_rotation, scale_translation
from .localizer import LocalizeConfig, MapLocalizer

logger = logging.getLogger(__name__)


@dataclass
class MapMerge:
    """A recording merged into a stored map: ``S_MR`` (4x4 Sim(3), recording frame -> map frame;
    rigid for metric maps), the first keyframe localised in the map (``merge_kf_id``, at
    ``merge_time``: frames from then on are reported in the map's frame) and the keyframes that
    support it (``verified`` of ``tried``). A recording whose run started new maps after a lost track
    (its sessions, :func:`fgslam.export.mapfile.map_segments`) is placed part by part:
    ``S_MR_by_part`` (P, 4, 4) holds each part's transform, ``parts`` what each part did, and only the
    parts with a transform of their own are placed (:func:`placed_parts`); ``S_MR`` is then the one of
    the part with most consistent keyframes."""

    S_MR: np.ndarray
    merge_kf_id: int
    merge_time: float
    verified: int
    consistent: int
    tried: int
    #: the consistent localisations: (recording keyframe position, stored keyframe position it was
    #: verified against, the recording keyframe's pose in the map's frame 4x4)
    links: list[tuple[int, int, np.ndarray]] = field(default_factory=list)
    S_MR_by_part: np.ndarray | None = None  # None: one part, S_MR
    parts: list[dict[str, Any]] = field(default_factory=list)  # per part: keyframes, localised, consistent, merged, S_MR

    def to_dict(self) -> dict[str, Any]:
        return {"S_MR": self.S_MR.tolist(), "merge_keyframe": self.merge_kf_id, "merge_time": self.merge_time,
                "verified_keyframes": self.verified, "consistent_keyframes": self.consistent,
                "keyframes_tried": self.tried, **({"parts": self.parts} if len(self.parts) > 1 else {})}


Localised = tuple[int, np.ndarray, np.ndarray, int]  # (recording position, T_MC, recording T_WC, stored position)


def merge_recording(stored: StoredMap, recording: StoredMap, config: LocalizeConfig | None = None,
                    metric: bool | None = None) -> MapMerge | None:
    """Localise the keyframes of a ``recording`` (a stored map of the new run, own frame) in
    ``stored`` one after the other (:class:`MapLocalizer`: retrieval + verification, then tracking),
    and estimate the transform between the two frames from the localised keyframes: the rotation
    from their poses (the map-from-recording rotations within ``merge.max_rotation_deg`` of the
    best-supported one, averaged), the scale (unless ``metric``: by default when both maps are metric,
    ``meta["metric"]``; a monocular map on either side has its own scale) and translation from their
    positions (least squares). Each part of a recording whose run started a new map after a lost
    track (``recording.kf_session``: another frame, and monocular another scale) gets a transform of
    its own from its own keyframes; a part with fewer than ``merge.min_keyframes`` consistent is not
    placed. None (no merge) when no part is."""
    config = config or LocalizeConfig()
    if metric is None:
        metric = stored.metric and recording.metric
    mc = config.merge
    if stored.meta["features"] != recording.meta["features"]:
        logger.warning("map merge: the recording's keyframe features were made with other settings than the "
                       "map's (output.map_features): not merged")
        return None
    localizer = MapLocalizer(stored, config)
    localised: list[Localised] = []
    position = {int(kf): i for i, kf in enumerate(stored.kf_ids)}
    for k in range(recording.num_keyframes):
        uv, desc, _ = recording.features(k)
        res = localizer.localize_features(uv, desc)
        if res.T_WC is not None:
            localised.append((k, res.T_WC, recording.T_WC[k], position[res.kf_id]))
    fits: list[tuple[np.ndarray, list[Localised]] | None] = []
    parts = []
    for part in range(recording.sessions):
        own = [loc for loc in localised if recording.kf_session[loc[0]] == part]
        fit = fit_transform(own, mc, metric)
        fits.append(fit)
        parts.append({"keyframes": int(np.sum(recording.kf_session == part)), "localised": len(own),
                      "consistent": 0 if fit is None else len(fit[1]), "merged": fit is not None,
                      **({} if fit is None else {"S_MR": fit[0].tolist()})})
    merged = [part for part, fit in enumerate(fits) if fit is not None]
    several = len(parts) > 1
    if not merged:
        logger.info("map merge: %d of %d recording keyframes localised, fewer than %d consistent%s: not merged",
                    len(localised), recording.num_keyframes, mc.min_keyframes,
                    f" in each of its {len(parts)} parts" if several else "")
        return None
    links = sorted(((k, i, T_MC) for part in merged for k, T_MC, _, i in fits[part][1]), key=lambda link: link[0])
    best = max(merged, key=lambda part: len(fits[part][1]))
    S_MR_by_part = np.stack([np.eye(4) if fit is None else fit[0] for fit in fits])
    first = links[0][0]
    logger.info("map merge: %d of %d recording keyframes localised, %d consistent; merged from keyframe %d "
                "(scale %.4f)%s", len(localised), recording.num_keyframes, len(links), int(recording.kf_ids[first]),
                float(np.cbrt(np.linalg.det(S_MR_by_part[best][:3, :3]))),
                f"; {len(merged)} of the recording's {len(parts)} parts placed by their own keyframes" if several else "")
    return MapMerge(S_MR_by_part[best], int(recording.kf_ids[first]), float(recording.kf_timestamps[first]),
                    len(localised), len(links), recording.num_keyframes, links,
                    S_MR_by_part if several else None, parts if several else [])


def placed_parts(recording: StoredMap, merge: MapMerge) -> tuple[StoredMap, MapMerge, np.ndarray]:
    """The part of ``recording`` that ``merge`` places in the map, the merge with its keyframe positions
    in it, and the transform of each of its parts ((P', 4, 4) for :func:`combine_maps`). A part without
    a transform of its own (too few consistent localisations) is left out of the map (its keyframes,
    points and frames): it stays in the run's own outputs. One part: the recording as it is."""
    if merge.S_MR_by_part is None:
        return recording, merge, merge.S_MR[None]
    placed = np.array([part["merged"] for part in merge.parts] or [True] * len(merge.S_MR_by_part), bool)
    if placed.all():
        return recording, merge, merge.S_MR_by_part
    keep = placed[recording.kf_session]
    kept = _keyframes_of(recording, keep)
    new_position = np.cumsum(keep) - 1
    links = [(int(new_position[k]), i, T_MC) for k, i, T_MC in merge.links]  # all of placed parts
    parts = [part for part in merge.parts if part["merged"]]
    return kept, replace(merge, links=links, S_MR_by_part=merge.S_MR_by_part[placed], parts=parts), \
        merge.S_MR_by_part[placed]


def _keyframes_of(stored: StoredMap, keep: np.ndarray) -> StoredMap:
    """``stored`` with the keyframes ``keep`` (K,) bool: their features, database vectors, points (with
    the keyframe they move with, :func:`_point_owners`), tracks and frames; sessions renumbered."""
    kf = np.flatnonzero(keep)
    points = np.flatnonzero(keep[_point_owners(stored)]) if len(stored.points_X_W) else np.zeros(0, np.int64)
    point_index = np.full(len(stored.points_X_W), -1, np.int64)
    point_index[points] = np.arange(len(points))
    kept_ids = np.isin(stored.track_kf, stored.kf_ids[kf])
    tracks = np.flatnonzero(kept_ids & (point_index[stored.track_point] >= 0)) if len(stored.track_point) else \
        np.zeros(0, np.int64)
    frames = np.flatnonzero(keep[stored.frame_kf]) if len(stored.frame_kf) else np.zeros(0, np.int64)
    kf_position = np.cumsum(keep) - 1

    def rows(ptr: np.ndarray) -> np.ndarray:  # the CSR rows of the kept keyframes
        return np.concatenate([np.arange(ptr[k], ptr[k + 1]) for k in kf]).astype(np.int64) if len(kf) else \
            np.zeros(0, np.int64)

    def offsets(ptr: np.ndarray) -> np.ndarray:
        return np.concatenate([[0], np.cumsum(np.diff(ptr)[kf])]).astype(ptr.dtype)

    feat, bow = rows(stored.feat_ptr), rows(stored.bow_ptr)
    return StoredMap(
        dict(stored.meta), stored.kf_ids[kf], stored.kf_timestamps[kf], stored.kf_frame_index[kf], stored.T_WC[kf],
        offsets(stored.feat_ptr), stored.feat_uv[feat], stored.feat_desc[feat], stored.feat_X_C[feat],
        offsets(stored.bow_ptr), stored.bow_words[bow], stored.bow_weights[bow],
        stored.points_X_W[points], stored.points_colour[points], point_index[stored.track_point[tracks]],
        stored.track_kf[tracks], stored.track_uv[tracks],
        np.unique(stored.kf_session[kf], return_inverse=True)[1].astype(np.int64),
        stored.frame_timestamps[frames], kf_position[stored.frame_kf[frames]], stored.frame_T_KC[frames])


def fit_transform(pairs: list[Localised], mc: MapMergeConfig, metric: bool) -> tuple[np.ndarray, list[Localised]] | None:
    """The map-from-recording transform (4x4) of localised keyframes ``pairs`` (:func:`merge_recording`)
    and the consistent ones among them, or None with fewer than ``mc.min_keyframes`` consistent."""
    if len(pairs) < mc.min_keyframes:
        return None
    R_rec = [T_R[:3, :3] / np.cbrt(np.linalg.det(T_R[:3, :3])) for _, _, T_R, _ in pairs]
    R_MR = np.stack([T_M[:3, :3] @ R.T for (_, T_M, _, _), R in zip(pairs, R_rec)])
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
        return None
    S = np.eye(4)
    S[:3, :3] = scale * R
    S[:3, 3] = t
    return S, [pairs[i] for i in consistent]


def combine_maps(stored: StoredMap, recording: StoredMap, S_MR: np.ndarray) -> StoredMap:
    """The merged map: ``stored`` and the ``recording``'s keyframes, structure and database moved
    into the map's frame by ``S_MR`` (Sim(3) poses ``S_MR T_WC``: camera points keep the
    recording's units; (P, 4, 4): a transform per part of the recording, ``recording.kf_session``, its
    points moved with their keyframe's, :func:`placed_parts`), the recording's keyframe ids after the
    stored ones."""
    offset = int(stored.kf_ids.max()) + 1 if stored.num_keyframes else 0
    meta = dict(stored.meta)
    meta["recordings"] = int(stored.meta.get("recordings", 1)) + 1
    S_MR_by_part = np.asarray(S_MR, np.float64).reshape(-1, 4, 4)
    if len(S_MR_by_part) == 1:
        S_MR_kf = S_MR_by_part
        X_new = recording.points_X_W @ S_MR_by_part[0, :3, :3].T + S_MR_by_part[0, :3, 3]
    else:
        S_MR_kf = S_MR_by_part[recording.kf_session]
        S_MR_point = S_MR_kf[_point_owners(recording)]
        X_new = np.einsum("nij,nj->ni", S_MR_point[:, :3, :3], recording.points_X_W) + S_MR_point[:, :3, 3]
    K1 = stored.num_keyframes
    return StoredMap(
        meta,
        np.concatenate([stored.kf_ids, recording.kf_ids + offset]),
        np.concatenate([stored.kf_timestamps, recording.kf_timestamps]),
        np.concatenate([stored.kf_frame_index, recording.kf_frame_index]),
        np.concatenate([stored.T_WC, S_MR_kf @ recording.T_WC]),
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
    recording_moved_max: float  # ... of a recording keyframe against the merge's transforms

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
    """The recording joined to ``stored`` in one graph: its parts that the merge placed
    (:func:`placed_parts`) moved by their transforms (:func:`combine_maps`), then
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
    recording, merge, S_MR_by_part = placed_parts(recording, merge)
    joined = combine_maps(stored, recording, S_MR_by_part)
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
