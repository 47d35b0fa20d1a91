"""The run's system: one object that owns the backend and the services and runs the per-frame skeleton.

:class:`SlamSystem` is built from a run config (:meth:`SlamSystem.build`; the runner
:func:`fgslam.run.runner.run_prepared` does it) or around a frontend built by hand (:meth:`SlamSystem.around`,
tests and tools). It owns, as peers:

- the :class:`~fgslam.backend.Backend` (every keyframe pose, every factor, every optimisation);
- the frontend (:class:`~fgslam.frontends.base.Frontend`), which only measures: it is built with the
  backend and connected to the loop service through its narrow loop port; the system calls it only
  through the members the ``Frontend`` contract declares;
- the loop-closure service (:class:`~fgslam.services.loops.LoopService`, inert when
  ``loop_closure.mode`` is off), the IMU service (:class:`~fgslam.services.imu.ImuService`), the factor
  plugins (:class:`~fgslam.services.plugins.FactorPlugins`) and the live view
  (:class:`~fgslam.export.rerun.RerunView`), each optional.

Per frame (:meth:`SlamSystem.step`): the frame's IMU samples to the IMU service; when the frontend
has a map, the loop service's safe point (corrections and a finished global BA applied) and the
frontend's :meth:`~fgslam.frontends.base.Frontend.corrections_applied`; the frontend's ``process``
(its own numerical guard reports a failed frame as a tracking failure); then the IMU service's and the
plugins' safe points, and the view. At the end (:meth:`SlamSystem.finish`): a running global BA is
applied, the frontend hands over its last keyframes, the loop service applies its last correction, the
frontend runs its final optimisation, then the IMU, plugins and view finish. Every step happens at a
fixed point of the frame sequence, so a run gives the same bytes however fast the background work is.
"""

from __future__ import annotations

import logging
from typing import Iterable, Optional

import numpy as np

from ..backend import Backend
from ..contracts.contributor import Contributor
from ..core.errors import ConfigError, OptimizationError
from ..export.rerun import RerunView, loop_segments
from ..frontends import make_frontend
from ..frontends.base import FrameStatus, Frontend
from ..io.calibration import Calibration
from ..io.frame import Frame
from ..loop.records import LoopClosureConfig
from ..services.corrections import ObservedContributor
from ..services.imu import ImuService, make_imu_service
from ..services.loops import LoopService, MapLink
from ..services.plugins import FactorPlugins
from .config import SlamConfig

logger = logging.getLogger(__name__)

# numerical trouble in a service's safe point (gtsam/numpy): logged, the visual run goes on
_NUMERICAL_ERRORS = (OptimizationError, RuntimeError, np.linalg.LinAlgError)


class SlamSystem:
    """The backend, the frontend and the services of one run (module docstring).

    Args:
        frontend: the run's frontend, built with ``backend`` (a frontend without one, as in tests of
            the runner, gets no IMU or plugins).
        backend: the run's backend (None: the frontend's :attr:`~fgslam.frontends.base.Frontend.backend`).
        loops: the loop-closure service (None: none; the frontend keeps its no-op loop port).
        imu: the IMU service (None: off).
        plugins: the factor plugins (None: none).
        view: the live view / rerun log (None: off).
    """

    def __init__(self, frontend: Frontend, backend: Optional[Backend] = None, loops: Optional[LoopService] = None,
                 imu: Optional[ImuService] = None, plugins: Optional[FactorPlugins] = None,
                 view: Optional[RerunView] = None) -> None:
        self.frontend = frontend
        self.backend = backend if backend is not None else frontend.backend
        self.loops = loops
        self.imu = imu
        self.plugins = plugins
        self.view = view
        self.imu_input_warnings: list[str] = []  # the IMU stream's checks before the run (services/imu_checks.py)
        frontend.connect(loops=loops, motion_prior=None if imu is None else imu.predict)

    # ------------------------------------------------------------------ building
    @classmethod
    def build(cls, config: SlamConfig, calibration: Optional[Calibration], *, frontend: Optional[Frontend] = None,
              timestamps: Optional[np.ndarray] = None, has_imu: bool = False, imu_noise: Optional[dict] = None,
              where: str = "the dataset", rerun: Optional[str] = None) -> "SlamSystem":
        """The system of a run config (:class:`fgslam.run.config.SlamConfig`): a backend from ``map``, the
        ``frontend`` family built on it (or the given frontend), and the services the config turns on
        (``rerun``: the live view's target, checked before, :func:`fgslam.run.prepare.prepare_run`).

        Raises:
            ConfigError: the frontend is unknown, or a service needs a backend the given frontend lacks.
            DataError: ``imu.enabled`` but the data has no IMU (``has_imu``) or no ``T_BC``.
        """
        if frontend is None:
            backend = Backend(config.map)
            frontend = make_frontend(config.frontend, config, calibration, config.sensor, backend=backend)
        else:
            backend = frontend.backend
        needs_backend = [key for key, on in (("imu.enabled", config.imu.enabled), ("factors", bool(config.factors)))
                         if on]
        if backend is None and needs_backend:
            raise ConfigError(f"{', '.join(needs_backend)}: frontend '{frontend.name}' "
                              "feeds no backend, so these services cannot apply")
        imu = None
        contributor = frontend.contributor
        if config.imu.enabled:
            imu = make_imu_service(config.imu, backend, calibration, has_imu, config.sensor,
                                   contributor=contributor, dataset_noise=imu_noise, where=where)
            if imu is not None:  # map corrections of loops and plugins move the IMU states too
                contributor = ObservedContributor(contributor, imu.adapt_correction, (imu.on_correction,))
        link = cls._loaded_map_link(config, frontend) if backend is not None else None
        loops = cls._loop_service(frontend, config.loop_closure, contributor, link) if backend is not None else None
        plugins = None
        if config.factors:
            plugins = FactorPlugins(config.factors, backend, timestamps, contributor=contributor)
        view = None
        if rerun:
            view = RerunView(rerun, calibration, config.output.rerun)
        return cls(frontend, backend, loops=loops, imu=imu, plugins=plugins, view=view)

    @classmethod
    def around(cls, frontend: Frontend, loop_config: Optional[LoopClosureConfig] = None) -> "SlamSystem":
        """The system of a frontend built by hand on its backend, with loop closure from ``loop_config``
        (None: off) and no other service (tests, tools)."""
        return cls(frontend, loops=cls._loop_service(frontend, loop_config))

    @staticmethod
    def _loaded_map_link(config: SlamConfig, frontend: Frontend) -> Optional[MapLink]:
        """The loaded map a metric run of a family that uses it relocalises in (``--map``,
        ``output.map_relocalize``; :class:`fgslam.localize.live.LoadedMapLink`), or None. Its camera was
        checked before the run."""
        out = config.output
        if not (out.extend_map and out.map_relocalize and frontend.metric_scale and frontend.relocalizes_in_loaded_map):
            return None
        from ..export.mapfile import load_stored_map  # deferred: the map's libraries
        from ..localize.live import LoadedMapLink  # deferred: as above
        from ..localize.localizer import LocalizeConfig  # deferred: as above

        stored = load_stored_map(out.extend_map)
        if not stored.metric:  # a monocular map has a scale of its own: no rigid tie to this run's frame
            logger.info("--map %s is monocular: the run does not relocalise in it while it goes on", out.extend_map)
            return None
        return LoadedMapLink(stored, LocalizeConfig(merge=out.map_merge))

    @staticmethod
    def _loop_service(frontend: Frontend, loop_config: Optional[LoopClosureConfig],
                      contributor: Optional[Contributor] = None, link: Optional[MapLink] = None
                      ) -> Optional[LoopService]:
        """The loop-closure service with ``frontend`` as its contributor (or ``contributor``, the
        frontend's seen through the IMU's correction hooks) (None: ``loop_config`` None or off,
        unless the frontend hands global optimisations to the service's worker, or ``link``, a loaded
        map to relocalise in, is given: then a service with loop closure off, inert but for them)."""
        if loop_config is None or loop_config.mode == "off":
            if not frontend.background_global_ba and link is None:
                return None
            loop_config = loop_config if loop_config is not None else LoopClosureConfig(mode="off")
        return LoopService(contributor if contributor is not None else frontend.contributor, loop_config,
                           metric=bool(frontend.metric_scale), proximity=frontend.proximity_gates, link=link)

    # ------------------------------------------------------------------ the run
    def step(self, frame: Frame) -> FrameStatus:
        """One frame through the skeleton (module docstring); returns the frontend's status."""
        if self.imu is not None:
            self.imu.feed(frame.imu, frame.timestamp)
        if self.loops is not None and self.frontend.map_started:
            self.loops.poll()  # the safe point: no optimisation running
            self.frontend.corrections_applied()
        status = self.frontend.process(frame)
        if self.imu is not None:
            try:
                self.imu.poll()
            except _NUMERICAL_ERRORS as exc:  # numerical trouble: vision goes on
                logger.warning("IMU: initialisation step after frame %s failed (%s); retrying later", frame.index, exc)
        if self.plugins is not None:
            self.plugins.poll()
        if self.view is not None:
            self._view_frame(frame, status)
        return status

    def finish(self) -> None:
        """After the last frame (module docstring)."""
        if self.loops is not None:
            self.loops.wait()  # a running global BA is applied before the last keyframes go to the closer
        self.frontend.finish()
        if self.loops is not None:
            self.loops.finish()
        self.frontend.finish_map()
        if self.imu is not None:
            logger.info("IMU: %s", self.imu.summary())
        if self.plugins is not None:
            self.plugins.finish()
        if self.view is not None:
            self.view.close(self.frontend.keyframe_points(), self._loop_segments())

    def abort(self) -> None:
        """Stop background work at once without applying it (a stopped or failed run)."""
        if self.loops is not None:
            self.loops.cancel()
        self.frontend.abort()

    # ------------------------------------------------------------------ reports
    def stage_times(self) -> dict[str, float]:
        """Seconds per stage: the frontend's plus the loop service's share in the tracking thread."""
        out = dict(self.frontend.stage_times())
        if self.loops is not None:
            for stage, seconds in self.loops.stage_times().items():
                out[stage] = out.get(stage, 0.0) + seconds
        return out

    def loop_summary(self) -> Optional[dict]:
        """Loop-closure counts for ``summary.json`` (None: loop closure off)."""
        if self.loops is None:
            return None
        out = self.loops.summary(self.frontend.frame_indices())
        if out is not None:
            self.frontend.add_loop_counts(out)
        return out

    def inertial_state(self) -> Optional[dict]:
        """The IMU service's state as a mapping for ``summary.json`` ``inertial``
        (:func:`fgslam.run.results.inertial_summary`), None without IMU service: its ``summary()`` plus the
        newest linked keyframe's bias and the input checks' warnings."""
        if self.imu is None:
            return None
        state = dict(self.imu.summary())
        state["input_warnings"] = list(self.imu_input_warnings)
        if self.backend is not None:
            for kf in sorted(self.backend.keyframe_ids, key=self.backend.timestamp, reverse=True):
                bias = self.imu.bias(kf)
                if bias is not None:
                    state["bias_gyro"] = [float(x) for x in bias.gyroscope()]
                    state["bias_accel"] = [float(x) for x in bias.accelerometer()]
                    break
        return state

    # ------------------------------------------------------------------ view
    def _loop_segments(self) -> list:
        if self.loops is None or self.backend is None:
            return []
        return loop_segments(self.loops.accepted_pairs(), self.backend)

    def _view_frame(self, frame: Frame, status: FrameStatus) -> None:
        try:
            self.view.log_frame(frame, status)
            if self.view.map_due():
                self.view.log_map(self.frontend.keyframe_points(), self._loop_segments())
        except Exception as exc:  # noqa: BLE001 - a viewer problem never stops the run
            logger.warning("rerun logging failed at frame %d: %s: %s", frame.index, type(exc).__name__, exc)


def run_frames(system: SlamSystem, frames: Iterable[Frame]) -> list[FrameStatus]:
    """Every frame through ``system`` then :meth:`SlamSystem.finish` (tests, tools); the statuses."""
    statuses = [system.step(frame) for frame in frames]
    system.finish()
    return statuses
