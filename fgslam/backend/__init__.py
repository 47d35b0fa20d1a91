"""The persistent GTSAM backend that every frontend feeds (docs/architecture.md section 8).

Modules: :mod:`.keys` (gtsam keys of keyframe poses and other variables), :mod:`.solver` (the one
Levenberg-Marquardt loop), :mod:`.config` (``BackendConfig``, the ``map`` section), :mod:`.graph`
(``Backend``: the :mod:`.store` with its :mod:`.gauge` and :mod:`.optimizer`, whose problem of one
optimisation is :mod:`.window`'s), :mod:`.pose_graph` (Sim(3) pose graphs, loop closure's included), :mod:`.global_ba`
(the patch map's global bundle adjustment), :mod:`.motion_only` (one pose against fixed structure).
The contract of a frontend's measurement blocks (``Block``, ``LinearPiece``) is
:mod:`fgslam.factors.blocks`, below the backend; the services that add factors to it (loop
closure, IMU, plugins) are :mod:`fgslam.services`.
Importing this package imports no gtsam or torch (each module imports them where used; the names
below are resolved lazily).
"""

from __future__ import annotations

import importlib

_EXPORTS = {
    "Backend": ".graph", "OptimizeReport": ".optimizer",
    "BackendConfig": ".config", "GaugeConfig": ".config", "WindowConfig": ".config",
    "Block": "..factors.blocks", "LinearPiece": "..factors.blocks",
    "pose_key": ".keys", "key_name": ".keys",
}


def __getattr__(name: str):
    module = _EXPORTS.get(name)
    if module is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    return getattr(importlib.import_module(module, __name__), name)


__all__ = sorted(_EXPORTS)
