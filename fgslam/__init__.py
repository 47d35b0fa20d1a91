"""fgslam: modular factor-graph visual SLAM on GTSAM.

The public Python API (``__all__``; every other module is private and may move)::

    import fgslam

    camera = fgslam.Camera(fx=525.0, fy=525.0, cx=319.5, cy=239.5, width=640, height=480)
    with fgslam.Slam.from_preset("handheld_rgbd", camera) as slam:
        for image, depth, t in my_frames():
            result = slam.track(image, t, depth=depth)   # result.T_WC: camera-to-world, metres
    trajectory = slam.finish()                            # timestamps (N,), T_WC (N, 4, 4)

- :class:`Slam`: a run driven frame by frame (``track``, ``add_imu``, ``trajectory``, ``keyframes``,
  ``map_points``, ``save_map``, ``finish``; ``localize_in`` a stored map), the object ``fgslam run`` uses;
- :class:`Camera`: intrinsics, size, distortion, stereo partner and IMU extrinsics;
- :class:`TrackResult`: what ``track`` says of a frame; :class:`Keyframes`; :class:`Trajectory`;
- :func:`open_dataset`: the frames of any sequence ``fgslam run --data`` reads, for a script's own loop;
- :class:`LiveFrames` (:class:`LiveConfig`): a live source (a camera, a stream, a file replayed at its rate) that drops the
  oldest frame when the system is behind.

Importing the package has no side effects and imports no heavy dependency: the names load on first use.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

__version__ = "0.1.0"

#: public name -> the module that defines it (loaded on first use: ``import fgslam`` stays light)
_PUBLIC = {
    "Slam": "fgslam.run.session",
    "TrackResult": "fgslam.core.tracking",
    "Keyframes": "fgslam.core.tracking",
    "Localizer": "fgslam.localize.localizer",
    "open_dataset": "fgslam.run.session",
    "Camera": "fgslam.io.camera",
    "Trajectory": "fgslam.io.trajectory",
    "LiveFrames": "fgslam.io.live",
    "LiveConfig": "fgslam.io.live",
}

__all__ = ["Camera", "Keyframes", "LiveConfig", "LiveFrames", "Localizer", "Slam", "TrackResult", "Trajectory", "open_dataset"]

if TYPE_CHECKING:  # the type checker sees the names; at run time they load on first use
    from .io.camera import Camera
    from .io.live import LiveConfig, LiveFrames
    from .io.trajectory import Trajectory
    from .core.tracking import Keyframes, TrackResult
    from .localize.localizer import Localizer
    from .run.session import Slam, open_dataset


def __getattr__(name: str) -> Any:
    module = _PUBLIC.get(name)
    if module is None:
        raise AttributeError(f"module 'fgslam' has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_PUBLIC))
