"""The IMU service's keyframe chain on the backend (the service: :mod:`fgslam.services.imu`).

:class:`ImuChain` holds the keyframes in time order and, from the first linked one on, each linked
keyframe's velocity ``v<kf>`` (``Point3``, world frame, m/s) and bias ``b<kf>``
(``imuBias.ConstantBias``) attached to it on the backend; consecutive keyframes (in time) are linked
by a ``CombinedImuFactor`` through the Sim(3) adapter (:func:`fgslam.factors.imu.imu_factor_on_sim3`)
where the buffer covers their interval, a keyframe without a link to its predecessor starts a new
chain with priors on its velocity and bias, and (``history: window``) the oldest linked keyframes
beyond ``window_keyframes`` lose their velocity and bias into a marginal prior. After a map
correction (:meth:`ImuChain.follow_correction`) the velocities turn and scale with the poses and the
marginal priors are re-anchored (rigid corrections) or dropped.
"""

from __future__ import annotations

import bisect
from typing import TYPE_CHECKING, Callable, Optional

import numpy as np

from ..backend.graph import Backend
from ..backend.keys import bias_key, kf_id_of, pose_key, velocity_key
from ..factors.imu import body_pose, imu_factor_on_sim3
from ..core.lie import gtsam_matrix, gtsam_sim3, sim3_matrix_parts
from ..loop.records import PoseCorrection
from .imu_samples import ImuBuffer, ImuServiceConfig, ImuStats

if TYPE_CHECKING:
    import gtsam

OWNER = "imu"
_MIN_CENTRE_STEP = 1e-9  # map units: neighbouring camera centres closer than this give no local scale of a correction
_RIGID_SCALE_TOL = 1e-9  # a correction whose local scales all lie this close to 1 is rigid (marginal priors re-anchored)
_POSE_DIM, _VELOCITY_DIM, _BIAS_DIM = 7, 3, 6  # tangent dimensions of a marginal prior's keys


class ImuChain:
    """Velocity and bias keys, IMU links, chain-start priors and marginal priors of the keyframes on a
    backend (module docstring).

    Args:
        config: the ``imu`` section.
        backend: the run's backend (the keys and factors live there; ``owner`` :data:`OWNER`).
        T_CB: body-to-camera transform (``gtsam.Pose3``).
        buffer: the IMU samples (the links' preintegration).
        stats: the service's counters (links, unlinked intervals, marginalisations).
        on_relinked: called at the end of every :meth:`relink` that ran (the service bounds its buffer).
    """

    def __init__(self, config: ImuServiceConfig, backend: Backend, T_CB: gtsam.Pose3, buffer: ImuBuffer,
                 stats: ImuStats, on_relinked: Callable[[], None]) -> None:
        self.config = config
        self.backend = backend
        self.T_CB = T_CB
        self.buffer = buffer
        self.stats = stats
        self._on_relinked = on_relinked
        self.params: Optional[gtsam.PreintegrationCombinedParams] = None  # at the gravity of the initialisation
        # keyframes in time order: (timestamp, kf_id)
        self.kfs: list[tuple[float, int]] = []
        self.linked: set[int] = set()  # keyframes with velocity and bias keys
        self.links: dict[tuple[int, int], int] = {}  # (kf_a, kf_b) -> factor handle
        self._starts: dict[int, list[int]] = {}  # chain-start prior handles per keyframe
        self._marginal_lin: dict[int, gtsam.Values] = {}  # marginal prior handle -> its linearisation point

    # ------------------------------------------------------------------ keyframes
    def insert(self, timestamp: float, kf_id: int) -> None:
        """A new keyframe of the backend, in time order."""
        bisect.insort(self.kfs, (float(timestamp), int(kf_id)))

    def remove(self, kf_id: int) -> None:
        """A keyframe the backend removed (its keys and factors went with it)."""
        self.kfs = [(t, k) for t, k in self.kfs if k != kf_id]
        self.linked.discard(kf_id)
        self._starts.pop(kf_id, None)
        for pair in [p for p in self.links if kf_id in p]:
            del self.links[pair]  # the backend removed the factor with the keyframe

    def linked_in_order(self) -> list[int]:
        """The linked keyframes in time order."""
        return [k for _, k in self.kfs if k in self.linked]

    def window_keys(self, free_kf_ids: list[int]) -> list[int]:
        """Velocity and bias keys of the linked keyframes (``free_window_states``)."""
        return [key for kf in self.linked for key in (velocity_key(kf), bias_key(kf))]

    def state(self, kf_id: int) -> tuple[gtsam.Pose3, np.ndarray, gtsam.imuBias.ConstantBias]:
        """(T_WB Pose3, velocity, bias) of a linked keyframe."""
        b = self.backend
        values = b.values_of([pose_key(kf_id), velocity_key(kf_id), bias_key(kf_id)])
        return (body_pose(values.atSimilarity3(pose_key(kf_id)), self.T_CB), np.asarray(values.atPoint3(velocity_key(kf_id))),
                values.atConstantBias(bias_key(kf_id)))

    def velocity(self, kf_id: int) -> Optional[np.ndarray]:
        return np.asarray(self.backend.values_of([velocity_key(kf_id)]).atPoint3(velocity_key(kf_id))) \
            if kf_id in self.linked else None

    def bias(self, kf_id: int) -> Optional[gtsam.imuBias.ConstantBias]:
        return self.backend.values_of([bias_key(kf_id)]).atConstantBias(bias_key(kf_id)) if kf_id in self.linked else None

    # ------------------------------------------------------------------ links
    def seed(self, velocities: dict[int, np.ndarray], bias: gtsam.imuBias.ConstantBias,
             velocity_sigma: float) -> tuple[float, int]:
        """The initialisation's keys: the oldest keyframe of ``velocities`` gets its velocity, ``bias``
        and chain-start priors, the later ones of ``velocities`` their solved velocities and ``bias``;
        returns the oldest's ``(timestamp, kf_id)``."""
        ordered = [(t, k) for t, k in self.kfs if k in velocities]
        t0, kf0 = ordered[0]
        self.backend.add_variable(velocity_key(kf0), np.asarray(velocities[kf0], dtype=np.float64), attach_to=kf0)
        self.backend.add_variable(bias_key(kf0), bias, attach_to=kf0)
        self.linked.add(kf0)
        self._starts[kf0] = self.start_priors(kf0, velocities[kf0], bias, velocity_sigma)
        # the other keyframes of the initialisation take their solved velocities
        i0 = self.kfs.index((t0, kf0))
        for i in range(i0 + 1, len(self.kfs)):
            t_b, kf_b = self.kfs[i]
            if kf_b in velocities:
                self.backend.add_variable(velocity_key(kf_b), np.asarray(velocities[kf_b], dtype=np.float64), attach_to=kf_b)
                self.backend.add_variable(bias_key(kf_b), bias, attach_to=kf_b)
                self.linked.add(kf_b)
        return t0, kf0

    def relink(self) -> None:
        """Velocity/bias keys for every keyframe from the first linked one on, links between consecutive
        ones (in time) where the IMU covers the interval, chain-start priors where not; then the window
        and ``on_relinked``."""
        kfs = self.kfs
        if not self.linked:
            return
        first = next(i for i, (_, k) in enumerate(kfs) if k in self.linked)
        for i in range(first, len(kfs)):
            t_b, kf_b = kfs[i]
            if i == first:
                continue
            t_a, kf_a = kfs[i - 1]
            link_ok = (t_b - t_a <= self.config.max_interval_s and t_b > t_a and self.buffer.covered(t_a, t_b))
            if kf_b not in self.linked:
                self._add_state(kf_b, kf_a if link_ok else None, t_a, t_b)
            if (kf_a, kf_b) in self.links:
                continue
            # a link from another predecessor (the keyframe between was removed) is replaced
            for pair in [p for p in self.links if p[1] == kf_b]:
                self.backend.remove_factor(self.links.pop(pair))
            if link_ok:
                bias = self.state(kf_a)[2]
                pim = self.buffer.preintegrate(self.params, t_a, t_b, bias)
                keys = (pose_key(kf_a), velocity_key(kf_a), pose_key(kf_b), velocity_key(kf_b), bias_key(kf_a), bias_key(kf_b))
                self.links[(kf_a, kf_b)] = self.backend.add_factor(imu_factor_on_sim3(keys, pim, self.T_CB), OWNER)
                self.stats.links += 1
                for handle in self._starts.pop(kf_b, []):  # linked now: no chain-start priors
                    self.backend.remove_factor(handle)
            elif kf_b not in self._starts:
                self.stats.unlinked += 1
                T_WB, v, bias = self.state(kf_b)
                self._starts[kf_b] = self.start_priors(kf_b, v, bias, self.config.init.restart_velocity_sigma)
        if self.config.history == "window":
            self._marginalise_old()
        self._on_relinked()

    def _add_state(self, kf_b: int, kf_a: Optional[int], t_a: float, t_b: float) -> None:
        """Velocity and bias keys of a new keyframe: predicted from its predecessor when the IMU covers
        the interval, else the predecessor's bias and its visual velocity."""
        import gtsam  # deferred: gtsam

        if kf_a is not None and kf_a in self.linked:
            T_WB_a, v_a, bias = self.state(kf_a)
            pim = self.buffer.preintegrate(self.params, t_a, t_b, bias)
            v_b = np.asarray(pim.predict(gtsam.NavState(T_WB_a, v_a), bias).velocity())
        else:
            prev = [k for _, k in self.kfs if k in self.linked]
            bias = self.state(prev[-1])[2] if prev else gtsam.imuBias.ConstantBias()
            v_b = np.zeros(3)
            if kf_a is not None and t_b > t_a:
                c_a = body_pose(self.backend.pose(kf_a), self.T_CB).translation()
                c_b = body_pose(self.backend.pose(kf_b), self.T_CB).translation()
                v_b = (np.asarray(c_b) - np.asarray(c_a)) / (t_b - t_a)
        self.backend.add_variable(velocity_key(kf_b), np.asarray(v_b, dtype=np.float64), attach_to=kf_b)
        self.backend.add_variable(bias_key(kf_b), bias, attach_to=kf_b)
        self.linked.add(kf_b)

    def start_priors(self, kf_id: int, v: np.ndarray, bias: gtsam.imuBias.ConstantBias,
                     velocity_sigma: float) -> list[int]:
        """Priors on a chain start's velocity (``velocity_sigma``) and bias; their handles."""
        import gtsam  # deferred: gtsam

        ic = self.config.init
        bias_sigmas = np.array([ic.bias_accel_sigma] * 3 + [ic.bias_gyro_sigma] * 3)
        return [
            self.backend.add_factor(gtsam.PriorFactorPoint3(velocity_key(kf_id), np.asarray(v, dtype=np.float64),
                                                            gtsam.noiseModel.Isotropic.Sigma(3, velocity_sigma)), OWNER),
            self.backend.add_factor(gtsam.PriorFactorConstantBias(bias_key(kf_id), bias,
                                                                  gtsam.noiseModel.Diagonal.Sigmas(bias_sigmas)), OWNER),
        ]

    def _marginalise_old(self) -> None:
        """history: window: the oldest linked keyframes beyond ``window_keyframes`` lose their velocity
        and bias into a linear prior on what their factors reach (their pose held)."""
        linked = [k for _, k in self.kfs if k in self.linked]
        while len(linked) > self.config.window_keyframes:
            kf = linked.pop(0)
            handles = self.backend.marginalize_variables([velocity_key(kf), bias_key(kf)], condition_on=[pose_key(kf)],
                                                         owner=OWNER)
            alive = set(self.backend.factor_handles(OWNER))
            self._marginal_lin = {h: lin for h, lin in self._marginal_lin.items() if h in alive}
            for h in handles:  # the estimate is the linearisation point right after the marginalisation
                self._marginal_lin[h] = self.backend.values_of(list(self.backend.factor(h).keys()))
            self.linked.discard(kf)
            self._starts.pop(kf, None)
            for pair in [p for p in self.links if kf in p]:
                del self.links[pair]
            self.stats.marginalised += 1

    def start_velocities(self, window: list[tuple[float, int]], poses: list[gtsam.Similarity3]) -> np.ndarray:
        """(n, 3) start of the window's velocities: the linked keyframes' own, else the body centres'
        central differences (m/s, map frame)."""
        p = np.array([np.asarray(body_pose(S, self.T_CB).translation()) for S in poses])
        t = np.array([tk for tk, _ in window])
        v = np.gradient(p, t, axis=0)
        for i, (_, kf) in enumerate(window):
            if kf in self.linked:
                v[i] = self.velocity(kf)
        return v

    def rebuild_links(self) -> None:
        """Every IMU link and chain-start prior again at the current gravity and biases (marginal priors
        dropped: linearised at the old state); the oldest linked keyframe gets start priors."""
        for handle in list(self.links.values()) + [h for hs in self._starts.values() for h in hs]:
            self.backend.remove_factor(handle)
        self.links.clear()
        self._starts.clear()
        self._drop_marginals()
        linked = [k for _, k in self.kfs if k in self.linked]
        if not linked:
            return
        first = linked[0]
        T_WB, v, bias = self.state(first)
        self._starts[first] = self.start_priors(first, v, bias, self.config.init.velocity_sigma)
        self.relink()

    def _drop_marginals(self) -> None:
        import gtsam  # deferred: gtsam

        for handle in self.backend.factor_handles(OWNER):  # marginal priors linearised at the old state
            if isinstance(self.backend.factor(handle), gtsam.LinearContainerFactor):
                self.backend.remove_factor(handle)
        self._marginal_lin.clear()

    # ------------------------------------------------------------------ map corrections
    def follow_correction(self, correction: PoseCorrection) -> None:
        """After a map correction (the keyframe poses already moved): each linked keyframe's velocity
        turns with its update's rotation and scales with the local scale of the correction
        (``v <- s_loc R_U v``; ``s_loc`` the ratio of its neighbouring keyframes' centre distances after
        and before: 1 for a rigid correction, the factor of a uniform rescale); biases are kept;
        chain-start priors move with their velocity; the marginal priors are re-anchored at the
        corrected linearisation point (rigid corrections: velocity columns turned) or dropped."""
        if not self.linked:
            return
        linked = [k for _, k in self.kfs if k in self.linked]
        c_new, c_old = {}, {}
        for kf in linked:
            U, _ = correction.update_for(kf)
            T = self.backend.pose_matrix(kf)
            c_new[kf] = T[:3, 3].copy()
            c_old[kf] = (np.linalg.inv(U) @ np.append(T[:3, 3], 1.0))[:3]
        rotations, local_scales = {}, {}
        for i, kf in enumerate(linked):
            U, _ = correction.update_for(kf)
            R, _, _ = sim3_matrix_parts(U, project=True)
            a, b = linked[max(i - 1, 0)], linked[min(i + 1, len(linked) - 1)]
            d_old = float(np.linalg.norm(c_old[b] - c_old[a]))
            s_loc = float(np.linalg.norm(c_new[b] - c_new[a])) / d_old if a != b and d_old > _MIN_CENTRE_STEP \
                else sim3_matrix_parts(U)[2]
            rotations[kf], local_scales[kf] = R, s_loc
            v = self.velocity(kf)
            self.backend.set_value(velocity_key(kf), s_loc * (R @ v))
        import gtsam  # deferred: gtsam

        for kf, handles in list(self._starts.items()):
            if kf not in rotations:
                continue
            new_handles = []
            for handle in handles:
                f = self.backend.factor(handle)
                self.backend.remove_factor(handle)
                if isinstance(f, gtsam.PriorFactorPoint3):
                    f = gtsam.PriorFactorPoint3(velocity_key(kf), local_scales[kf] * (rotations[kf] @ np.asarray(f.prior())),
                                                f.noiseModel())
                new_handles.append(self.backend.add_factor(f, OWNER))
            self._starts[kf] = new_handles
        if all(abs(s - 1.0) <= _RIGID_SCALE_TOL for s in local_scales.values()) and not correction.fold_scale:
            self._reanchor_marginals(correction, rotations)
        else:
            self._drop_marginals()

    def _reanchor_marginals(self, correction: PoseCorrection, rotations: dict[int, np.ndarray]) -> None:
        """Rigid correction: each marginal prior at the corrected linearisation point (poses ``U T``:
        their right-perturbation columns unchanged; velocities ``R v``: columns ``A_v R^T``; biases
        unchanged); a prior it cannot rebuild (more than 3 keys, unknown linearisation point) is dropped."""
        import gtsam  # deferred: gtsam

        for handle in [h for h in self.backend.factor_handles(OWNER)
                       if isinstance(self.backend.factor(h), gtsam.LinearContainerFactor)]:
            f = self.backend.factor(handle)
            lin = self._marginal_lin.pop(handle, None)
            self.backend.remove_factor(handle)
            keys = [int(k) for k in f.keys()]
            if lin is None or len(keys) > 3:
                continue
            try:
                jf = gtsam.JacobianFactor(f.factor())
            except RuntimeError:
                continue
            A, b = jf.jacobian()
            A = np.asarray(A)
            new_lin = gtsam.Values()
            blocks, col = [], 0
            for key in keys:
                kf = kf_id_of(key)
                U, _ = correction.update_for(kf)
                R = rotations.get(kf, sim3_matrix_parts(U, project=True)[0])
                if key == pose_key(kf):
                    T_new, _ = correction.apply_pose(kf, gtsam_matrix(lin.atSimilarity3(key)))
                    new_lin.insert(key, gtsam_sim3(T_new))
                    dim = _POSE_DIM
                    blocks.append(A[:, col:col + dim])
                elif key == velocity_key(kf):
                    new_lin.insert(key, R @ np.asarray(lin.atPoint3(key)))
                    dim = _VELOCITY_DIM
                    blocks.append(A[:, col:col + dim] @ R.T)
                else:
                    new_lin.insert(key, lin.atConstantBias(key))
                    dim = _BIAS_DIM
                    blocks.append(A[:, col:col + dim])
                col += dim
            unit = gtsam.noiseModel.Diagonal.Sigmas(np.ones(A.shape[0]))
            args = [x for key, block in zip(keys, blocks) for x in (key, block)]
            new = gtsam.LinearContainerFactor(gtsam.JacobianFactor(*args, np.asarray(b, dtype=np.float64), unit), new_lin)
            h = self.backend.add_factor(new, OWNER)
            self._marginal_lin[h] = new_lin
