"""gtsam keys of the backend's variables: one character and an index (``gtsam.symbol``)."""

from __future__ import annotations

POSE_CHAR = "x"  # keyframe Sim(3) poses T_WC
VELOCITY_CHAR = "v"  # keyframe velocities (IMU)
BIAS_CHAR = "b"  # IMU biases


def symbol(char: str, index: int) -> int:
    """gtsam key of variable ``index`` of kind ``char``."""
    import gtsam  # deferred: gtsam

    return int(gtsam.symbol(char, int(index)))


def pose_key(kf_id: int) -> int:
    """gtsam key of keyframe ``kf_id``'s pose (``gtsam.symbol('x', kf_id)``)."""
    return symbol(POSE_CHAR, kf_id)


def velocity_key(kf_id: int) -> int:
    return symbol(VELOCITY_CHAR, kf_id)


def bias_key(kf_id: int) -> int:
    return symbol(BIAS_CHAR, kf_id)


def key_name(key: int) -> str:
    """Readable name of a key for error messages: ``x12`` (symbol keys) or the integer."""
    import gtsam  # deferred: gtsam

    sym = gtsam.Symbol(int(key))
    char = chr(sym.chr()) if 32 < sym.chr() < 127 else ""
    return f"{char}{sym.index()}" if char else str(int(key))


def kf_id_of(key: int) -> int:
    """Keyframe id of a pose key."""
    import gtsam  # deferred: gtsam

    return int(gtsam.Symbol(int(key)).index())
