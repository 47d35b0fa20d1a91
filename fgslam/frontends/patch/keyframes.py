"""Keyframes of the patch frontend (:class:`Keyframes`): graph frames entering and leaving the backend,
DPVO's redundant-keyframe removal, and retirement (inactive edges, released caches, finalised
keyframes that keep their pose and patches for the global BA and the map export)."""

from __future__ import annotations

import numpy as np

from ..records import KeyframePose, RelativePose
from .graph import GraphFrame
from .state import BackendFrame, PatchState


class Keyframes:
    """Keyframe membership and policy on the shared :class:`~.state.PatchState`: every graph frame is
    a backend keyframe from when it enters the graph until it leaves as redundant or rejected;
    finalised frames stay."""

    def __init__(self, state: PatchState):
        self.state = state

    def enter(self, f: GraphFrame) -> None:
        """Frame ``f`` enters the patch graph and becomes a backend keyframe."""
        self.state.graph.add_frame(f)
        self.ensure(f)

    def ensure(self, f: GraphFrame) -> None:
        """Graph frame ``f`` is a backend keyframe (added with its pose and timestamp if it was not)."""
        backend = self.state.backend
        if not backend.has_keyframe(f.fid):
            backend.add_keyframe(f.fid, f.T_WC, f.timestamp)
            if isinstance(f, BackendFrame):
                f.attach(backend)

    def leave(self, f: GraphFrame) -> None:
        """Frame ``f`` left the patch graph without being finalised (redundant, rejected): it leaves
        the backend too (its pose stays on the frame)."""
        if isinstance(f, BackendFrame):
            f.detach()
        backend = self.state.backend
        if backend.has_keyframe(f.fid):
            backend.remove_keyframe(f.fid)

    def finalise(self, f: GraphFrame) -> None:
        """A keyframe leaves the graph: its pose and patches are kept (global BA, point export)."""
        st = self.state
        f.features = None
        f.features_right = None
        f.depth = None
        f.surface = None
        st.final[f.fid] = f
        st.records[f.fid] = KeyframePose()
        st.finalised += 1

    def remove_redundant(self) -> int | None:
        """DPVO keyframe removal: drop the frame ``keyframe_index`` positions before the newest when
        the mean flow between its two neighbours (``keyframe_flow``: raw, or rotation-compensated:
        :meth:`translation_flow`) is below ``keyframe_threshold``. Returns the
        removed frame's index, or None."""
        st = self.state
        g = st.graph
        n = len(g) - 1
        k = n - st.config.tracking.keyframe_index
        if k < 1 or st.sensor_mode == "mono" and len(g) <= 3:
            return None
        a, b = g.frames[k - 1], g.frames[k + 1]
        if st.config.tracking.keyframe_flow == "translation":
            flow = 0.5 * (self.translation_flow(a, b) + self.translation_flow(b, a))
        else:
            flow = 0.5 * (self.mean_flow(a, b) + self.mean_flow(b, a))
        if flow >= st.config.tracking.keyframe_threshold:
            return None
        victim = g.frames[k]
        st.records[victim.fid] = RelativePose(a.fid, np.linalg.inv(a.T_WC) @ victim.T_WC)
        self.leave(g.remove_frame(victim.fid))
        return int(victim.index)

    def mean_flow(self, a: GraphFrame, b: GraphFrame) -> float:
        """Mean pixel flow of frame a's patches reprojected into frame b (inf when none reprojects)."""
        uv, ok = self.state.reproject_to(a, b.T_WC)
        if not ok.any():
            return float("inf")
        return float(np.linalg.norm(uv[ok] - a.uv[ok], axis=1).mean())

    def translation_flow(self, a: GraphFrame, b: GraphFrame) -> float:
        """Mean rotation-compensated pixel flow of frame a's patches in frame b: each patch reprojected
        at its depth minus reprojected at infinite depth (the flow of the rotation alone), so the
        part of the flow that translation induces (inf when none reprojects)."""
        uv, ok = self.state.reproject_to(a, b.T_WC)
        uv_rot, ok_rot = self.state.reproject_rotation(a, b.T_WC)
        ok = ok & ok_rot
        if not ok.any():
            return float("inf")
        return float(np.linalg.norm(uv[ok] - uv_rot[ok], axis=1).mean())

    def retire(self) -> None:
        """Deactivate old edges, finalise frames no active edge reaches, release old caches."""
        g = self.state.graph
        gcfg = self.state.config.graph
        g.deactivate_old_edges()
        n = len(g) - 1
        for f in g.frames[: max(0, n - gcfg.patch_lifetime)]:
            f.features = None
            f.features_right = None
        for f in g.pop_frames_before(n - gcfg.removal_window - gcfg.patch_lifetime):
            self.finalise(f)
