"""Optional rerun log of a run (``fgslam run ... --rerun out.rrd``, or ``--rerun live`` to stream to a
running viewer): frames, camera poses, the trajectory, keyframe points and loop edges.

rerun is an optional extra (``pip install 'fgslam[rerun]'``); without it ``--rerun`` is a clear
error before the run starts. :class:`RerunView` is a peer service of the run's system
(:class:`fgslam.run.system.SlamSystem`): after every frame the system hands it the frame and its status,
and it logs the camera (pinhole + pose) on the ``frame`` timeline (and the frame's time on
``time``), the frame's image every ``image_every`` frames (JPEG); every ``map_every`` frames (and at
the end) the system hands it the map: the frontend's keyframe points and the accepted loop edges
(classical and proximity loops) as segments between keyframe centres, which the view logs with the
trajectory so far and the keyframe centres (each keyframe's pose when it was made a keyframe).
With each logged image go the map points (as last logged) projected into it from the frame's pose
(``world/camera/image/map_points``: the map as the current camera sees it), and every frame's
number of valid measurements goes on ``stats/num_valid``. Entities: ``world/camera`` (+ ``/image``,
``/image/map_points``), ``world/trajectory``, ``world/keyframes``, ``world/points``,
``world/loops``, ``stats/num_valid``. A default blueprint (:func:`default_blueprint`: 3-D world |
current image over the measurement count) is sent with the recording.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from ..core.config import MAX_FRAMES, MAX_SCALAR, ranged
from ..core.errors import ConfigError, DataError

if TYPE_CHECKING:
    import rerun.blueprint as rrb

    from ..backend.graph import Backend
    from ..frontends.base import FrameStatus
    from ..io.calibration import Calibration
    from ..io.frame import Frame

logger = logging.getLogger(__name__)

LIVE = "live"  # --rerun live: stream to a running viewer (rerun's default address)


@dataclass
class RerunConfig:
    """What a rerun log of a run holds (``output.rerun``)."""

    image_every: int = ranged(5, ge=1, le=MAX_FRAMES)  # log every n-th frame's image
    map_every: int = ranged(50, ge=1, le=MAX_FRAMES)  # log the trajectory, keyframe points and loops every n frames
    jpeg_quality: int = ranged(80, ge=1, le=100)  # images are logged JPEG-encoded at this quality
    point_radius: float = ranged(0.01, gt=0, le=MAX_SCALAR)  # keyframe points' radius (map units)
    keyframe_radius: float = ranged(0.03, gt=0, le=MAX_SCALAR)  # keyframe centres' radius (map units)
    image_point_radius: float = ranged(2.0, gt=0, le=MAX_SCALAR)  # projected map points' radius (pixels)
    min_depth: float = ranged(0.01, gt=0, le=MAX_SCALAR)  # map points nearer than this (map units) are not projected


def rerun_available() -> bool:
    try:
        import rerun  # noqa: F401  # deferred: rerun (optional extra), only probed
    except ImportError:
        return False
    return True


def check_rerun_target(target: str) -> None:
    """Before the run: rerun installed, and a ``.rrd`` file whose folder exists (or ``live``)."""
    if not rerun_available():
        raise ConfigError("--rerun needs the rerun SDK, an optional extra: pip install 'fgslam[rerun]'")
    if target == LIVE:
        return
    path = Path(target)
    if path.suffix != ".rrd":
        raise ConfigError(f"--rerun {target}: give a .rrd file (or 'live' for a running viewer)")
    if not path.parent.is_dir():
        raise DataError(f"--rerun {target}: folder {path.parent} does not exist")


def default_blueprint() -> rrb.Blueprint:
    """The layout sent with a recording: the 3-D world (cameras, trajectory, keyframes, points, loops)
    beside the current image with its projected map points over the measurement count."""
    import rerun.blueprint as rrb  # deferred: rerun (optional extra)

    return rrb.Blueprint(rrb.Horizontal(
        rrb.Spatial3DView(origin="world", name="map"),
        rrb.Vertical(rrb.Spatial2DView(origin="world/camera/image", name="current image"),
                     rrb.TimeSeriesView(origin="stats", name="measurements")),
        column_shares=[2, 1]))


class RerunView:
    """A run's rerun log (see the module docstring); ``target`` is a ``.rrd`` file or ``live``."""

    def __init__(self, target: str, calibration: Calibration, config: RerunConfig | None = None) -> None:
        import rerun as rr  # deferred: rerun (optional extra)

        self._rr = rr
        self.config = config or RerunConfig()
        self.target = target
        self.rec = rr.RecordingStream("fgslam")
        if target == LIVE:
            self.rec.connect_grpc()
        else:
            self.rec.save(target)
        K = np.asarray(calibration.K, dtype=np.float64)
        self._K = K
        self._size = (int(calibration.width), int(calibration.height))
        self._positions: list[np.ndarray] = []
        self._keyframes: dict[int, np.ndarray] = {}  # frame index -> centre when made a keyframe
        self._map_points: np.ndarray | None = None  # (N, 3) X_W as last logged
        self._frames = 0
        self.rec.send_blueprint(default_blueprint())
        self.rec.log("world", rr.ViewCoordinates.RDF, static=True)  # camera convention: x right, y down, z forward
        self.rec.log("world/camera/image", rr.Pinhole(focal_length=[K[0], K[1]], principal_point=[K[2], K[3]],
                                                      resolution=list(self._size)), static=True)

    def map_due(self) -> bool:
        """Whether the map is logged with the frame just logged (every ``map_every`` frames)."""
        return self._frames % self.config.map_every == 0

    def close(self, points: tuple[np.ndarray, np.ndarray] | None, segments: list[np.ndarray]) -> None:
        """Log the final map and close the log (a ``.rrd`` file gets its footer); a failure is logged."""
        try:
            self.log_map(points, segments)
            self.rec.flush()
            if self.target != LIVE:
                self.rec.disconnect()
        except Exception as exc:  # noqa: BLE001 - a viewer problem never stops the run
            logger.warning("rerun logging failed at the end: %s: %s", type(exc).__name__, exc)

    # ------------------------------------------------------------------ logging
    def log_frame(self, frame: Frame, status: FrameStatus) -> None:
        """Log one frame: its camera pose (when it has one) and every ``image_every``-th image."""
        rr, rec, cfg = self._rr, self.rec, self.config
        rec.set_time("frame", sequence=int(frame.index))
        rec.set_time("time", duration=float(frame.timestamp))
        self._frames += 1
        rec.log("stats/num_valid", rr.Scalars(float(status.num_valid)))
        T = None
        if status.T_WC is not None:
            T = np.asarray(status.T_WC, dtype=np.float64)
            rec.log("world/camera", rr.Transform3D(translation=T[:3, 3], mat3x3=T[:3, :3]))
            self._positions.append(T[:3, 3].copy())
            if status.is_keyframe:
                self._keyframes[int(frame.index)] = T[:3, 3].copy()
        if self._frames % cfg.image_every == 1 or cfg.image_every == 1:
            if T is not None and self._map_points is not None:
                rec.log("world/camera/image/map_points", rr.Points2D(self.project(T, self._map_points),
                                                                      radii=cfg.image_point_radius))
            import cv2  # deferred: cv2

            image = frame.image if getattr(frame, "rgb", None) is None else cv2.cvtColor(frame.rgb, cv2.COLOR_RGB2BGR)
            ok, buf = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, cfg.jpeg_quality])
            if ok:
                rec.log("world/camera/image", rr.EncodedImage(contents=buf.tobytes(), media_type="image/jpeg"))

    def log_map(self, points: tuple[np.ndarray, np.ndarray] | None, segments: list[np.ndarray]) -> None:
        """Log the trajectory so far, the map points ``(X_W, colour)`` and loop ``segments``."""
        rr, rec, cfg = self._rr, self.rec, self.config
        if len(self._positions) >= 2:
            rec.log("world/trajectory", rr.LineStrips3D([np.stack(self._positions)]))
        if self._keyframes:
            rec.log("world/keyframes", rr.Points3D(np.stack(list(self._keyframes.values())),
                                                   radii=cfg.keyframe_radius, colors=[64, 160, 255]))
        if points is not None and len(points[0]):
            self._map_points = np.asarray(points[0], dtype=np.float64)
            rec.log("world/points", rr.Points3D(np.asarray(points[0], dtype=np.float32),
                                                colors=np.asarray(points[1], dtype=np.uint8), radii=cfg.point_radius))
        if segments:
            rec.log("world/loops", rr.LineStrips3D(segments, colors=[255, 64, 64]))


    def project(self, T_WC: np.ndarray, X_W: np.ndarray) -> np.ndarray:
        """Pixels ``(M, 2)`` of the points ``X_W`` in front of the camera ``T_WC`` that fall in the image."""
        R, t = T_WC[:3, :3], T_WC[:3, 3]
        X_C = (X_W - t) @ R  # R^T (X_W - t), row-wise
        z = X_C[:, 2]
        front = z > self.config.min_depth
        fx, fy, cx, cy = self._K
        uv = np.stack([fx * X_C[front, 0] / z[front] + cx, fy * X_C[front, 1] / z[front] + cy], axis=1)
        w, h = self._size
        inside = (uv[:, 0] >= -0.5) & (uv[:, 0] < w - 0.5) & (uv[:, 1] >= -0.5) & (uv[:, 1] < h - 0.5)
        return uv[inside]


def loop_segments(pairs: list[tuple[int, int]], backend: Backend) -> list[np.ndarray]:
    """Loop edges ``(query id, candidate id)`` as (2, 3) segments between the keyframe centres of
    ``backend`` (pairs with a keyframe no longer in the backend are skipped)."""
    return [np.stack([backend.pose_matrix(q)[:3, 3], backend.pose_matrix(c)[:3, 3]]) for q, c in pairs
            if backend.has_keyframe(q) and backend.has_keyframe(c)]
