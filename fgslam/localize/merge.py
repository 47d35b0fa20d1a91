"""Extending a stored map with a recording (``fgslam run ... --map MAP``, :mod:`fgslam.run.mapstore`):
the recording's keyframes localised in the map (:class:`fgslam.localize.localizer.MapLocalizer`), the
transform between the two frames estimated from them (:func:`merge_recording`), and the merged map
(:func:`combine_maps`) with the recording's poses in the map's frame
(:func:`fgslam.localize.anchor.rigid_in_map`)."""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..export.mapfile import StoredMap
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
    for k in range(recording.num_keyframes):
        uv, desc, _ = recording.features(k)
        res = localizer.localize_features(uv, desc)
        if res.T_WC is not None:
            pairs.append((k, res.T_WC, recording.T_WC[k]))
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
    return MapMerge(S, int(recording.kf_ids[first]), float(recording.kf_timestamps[first]), len(pairs),
                    len(consistent), recording.num_keyframes)


def combine_maps(stored: StoredMap, recording: StoredMap, S_MR: np.ndarray) -> StoredMap:
    """The merged map: ``stored`` and the ``recording``'s keyframes, structure and database moved
    into the map's frame by ``S_MR`` (Sim(3) poses ``S_MR T_WC``: camera points keep the
    recording's units), the recording's keyframe ids after the stored ones."""
    offset = int(stored.kf_ids.max()) + 1 if stored.num_keyframes else 0
    meta = dict(stored.meta)
    meta["recordings"] = int(stored.meta.get("recordings", 1)) + 1
    X_new = recording.points_X_W @ S_MR[:3, :3].T + S_MR[:3, 3]
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
        np.concatenate([stored.track_uv, recording.track_uv]))
