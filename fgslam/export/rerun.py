"""Optional rerun log of a run (``fgslam run ... --rerun out.rrd``, or ``--rerun live`` to stream to a
running viewer): frames, camera poses, the trajectory, keyframe points and loop edges.

rerun is an optional extra (``pip install 'fgslam[rerun]'``); without it ``--rerun`` is a clear
error before the run starts. The logger wraps the run's frontend (any :class:`Frontend`): after every
``process(frame)`` it logs the camera (pinhole + pose) on the ``frame`` timeline (and the frame's
time on ``time``), the frame's image every ``image_every`` frames (JPEG), and every ``map_every``
frames (and after ``finish``) the trajectory so far, the frontend's keyframe points and the
accepted loop edges (from the shared loop service: classical and proximity loops) as segments
between keyframe centres. Entities: ``world/camera`` (+ ``/image``), ``world/trajectory``,
``world/points``, ``world/loops``.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..config import MAX_FRAMES, MAX_SCALAR, ranged
from ..errors import ConfigError, DataError

logger = logging.getLogger(__name__)

LIVE = "live"  # --rerun live: stream to a running viewer (rerun's default address)


@dataclass
class RerunConfig:
    """What a rerun log of a run holds (``output.rerun``)."""

    image_every: int = ranged(5, ge=1, le=MAX_FRAMES)  # log every n-th frame's image
    map_every: int = ranged(50, ge=1, le=MAX_FRAMES)  # log the trajectory, keyframe points and loops every n frames
    jpeg_quality: int = ranged(80, ge=1, le=100)  # images are logged JPEG-encoded at this quality
    point_radius: float = ranged(0.01, gt=0, le=MAX_SCALAR)  # keyframe points' radius (map units)


def rerun_available() -> bool:
    try:
        import rerun  # noqa: F401
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


class FrontendWithRerun:
    """The run's frontend, logging to rerun after each frame and at the end (see the module docstring).
    Everything else is the frontend's own."""

    def __init__(self, frontend: Any, target: str, calibration: Any, config: RerunConfig | None = None) -> None:
        import rerun as rr

        self._frontend = frontend
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
        self._frames = 0
        self.rec.log("world", rr.ViewCoordinates.RDF, static=True)  # camera convention: x right, y down, z forward
        self.rec.log("world/camera/image", rr.Pinhole(focal_length=[K[0], K[1]], principal_point=[K[2], K[3]],
                                                      resolution=list(self._size)), static=True)

    def __getattr__(self, name: str) -> Any:
        return getattr(self._frontend, name)

    def process(self, frame: Any) -> Any:
        status = self._frontend.process(frame)
        try:
            self._log_frame(frame, status)
        except Exception as exc:  # noqa: BLE001 - a viewer problem never stops the run
            logger.warning("rerun logging failed at frame %d: %s: %s", frame.index, type(exc).__name__, exc)
        return status

    def finish(self) -> Any:
        out = self._frontend.finish()
        try:
            self._log_map()
            self.rec.flush()
            if self.target != LIVE:
                self.rec.disconnect()  # closes the .rrd file (with its footer)
        except Exception as exc:  # noqa: BLE001
            logger.warning("rerun logging failed at the end: %s: %s", type(exc).__name__, exc)
        return out

    # ------------------------------------------------------------------ logging
    def _log_frame(self, frame: Any, status: Any) -> None:
        rr, rec, cfg = self._rr, self.rec, self.config
        rec.set_time("frame", sequence=int(frame.index))
        rec.set_time("time", duration=float(frame.timestamp))
        self._frames += 1
        if status.T_WC is not None:
            T = np.asarray(status.T_WC, dtype=np.float64)
            rec.log("world/camera", rr.Transform3D(translation=T[:3, 3], mat3x3=T[:3, :3]))
            self._positions.append(T[:3, 3].copy())
        if self._frames % cfg.image_every == 1 or cfg.image_every == 1:
            import cv2

            image = frame.image if getattr(frame, "rgb", None) is None else cv2.cvtColor(frame.rgb, cv2.COLOR_RGB2BGR)
            ok, buf = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, cfg.jpeg_quality])
            if ok:
                rec.log("world/camera/image", rr.EncodedImage(contents=buf.tobytes(), media_type="image/jpeg"))
        if self._frames % cfg.map_every == 0:
            self._log_map()

    def _log_map(self) -> None:
        rr, rec, cfg = self._rr, self.rec, self.config
        if len(self._positions) >= 2:
            rec.log("world/trajectory", rr.LineStrips3D([np.stack(self._positions)]))
        points = self._frontend.keyframe_points()
        if points is not None and len(points[0]):
            rec.log("world/points", rr.Points3D(np.asarray(points[0], dtype=np.float32),
                                                colors=np.asarray(points[1], dtype=np.uint8), radii=cfg.point_radius))
        segments = self.loop_segments()
        if segments:
            rec.log("world/loops", rr.LineStrips3D(segments, colors=[255, 64, 64]))

    def loop_segments(self) -> list[np.ndarray]:
        """Accepted loop edges as (2, 3) segments between keyframe centres (classical and proximity
        loops of the shared loop service; keyframes no longer in the backend are skipped)."""
        service = getattr(self._frontend, "loops", None)
        backend = getattr(self._frontend, "backend", None)
        if service is None or backend is None:
            return []
        pairs = []
        closer = getattr(service, "closer", None)
        if closer is not None:
            pairs += [(r.query_id, r.candidate_id) for r in closer.loops if r.status == "accepted"]
        pairs += [(q, c) for q, c, status in getattr(service, "proximity_loops", []) if status == "accepted"]
        segments = []
        for q, c in pairs:
            if backend.has_keyframe(q) and backend.has_keyframe(c):
                segments.append(np.stack([backend.pose_matrix(q)[:3, 3], backend.pose_matrix(c)[:3, 3]]))
        return segments


def with_rerun(frontend: Any, target: str | None, calibration: Any, config: RerunConfig | None = None) -> Any:
    """The frontend wrapped by :class:`FrontendWithRerun` when ``target`` is given, else itself."""
    if not target:
        return frontend
    check_rerun_target(target)
    return FrontendWithRerun(frontend, target, calibration, config)
