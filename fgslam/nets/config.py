"""Runtime settings of the learned measurement sources (``dense.source.droid``, ``patch.dpvo``)."""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from dataclasses import dataclass
from typing import TYPE_CHECKING, Literal

from ..core.config import MAX_COUNT, MAX_ITERATIONS, MAX_SCALAR, MAX_THREADS, ranged
from ..core.errors import ConfigError

if TYPE_CHECKING:  # torch is imported where the functions below run (the configs load without it)
    import torch

__all__ = ["DpvoNetConfig", "DroidNetConfig", "NetRuntimeConfig", "network_runtime", "resolve_device"]


@dataclass
class NetRuntimeConfig:
    """How a learned update operator runs."""

    iterations: int = ranged(1, ge=1, le=MAX_ITERATIONS)  # update-operator iterations per measurement call (per new frame's update)
    threads: int = ranged(1, ge=0, le=MAX_THREADS)  # torch CPU threads while the network runs (0: leave torch's setting)
    device: Literal["auto", "cpu", "cuda"] = "auto"  # auto: CUDA when present, else CPU


@dataclass
class DroidNetConfig(NetRuntimeConfig):
    """DROID-SLAM's network as the dense source (``dense.source.kind: droid``)."""

    correlation: Literal["alt", "features", "volume"] = "alt"  # alt: chunk_edges edges' all-pairs volumes at a time; features: chunked, no volume (pooled target features, slower); volume: every edge's volume at once
    chunk_edges: int = ranged(8, ge=1, le=MAX_COUNT)  # alt / features: edges correlated at a time (memory: chunk * (h w)^2 or chunk * h w * 64 * 128 floats)
    motion_clamp: float = ranged(64.0, gt=0, le=MAX_SCALAR)  # grid px: the motion features are clamped to +- this (DROID: 64)


@dataclass
class DpvoNetConfig(NetRuntimeConfig):
    """DPVO's network as the patch source (``patch.source: dpvo``)."""

    min_confidence: float = ranged(0.0, ge=0, le=1)  # measurements whose weight (smaller axis) is below this are rejected (0)


def resolve_device(device: str) -> torch.device:
    """``auto`` -> CUDA when available, else CPU; ``cuda`` without CUDA is a ConfigError."""
    import torch  # deferred: the configs above load without torch

    if device == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if device == "cuda" and not torch.cuda.is_available():
        raise ConfigError("learned source: device=cuda but torch sees no CUDA device (use device: auto or cpu)")
    if device not in ("cpu", "cuda"):
        raise ConfigError(f"learned source: device must be auto, cpu or cuda, got {device!r}")
    return torch.device(device)


@contextlib.contextmanager
def network_runtime(config: NetRuntimeConfig) -> Iterator[None]:
    """``torch.inference_mode`` with the configured CPU thread count, restored afterwards."""
    import torch  # deferred: the configs above load without torch

    previous = torch.get_num_threads()
    if config.threads > 0:
        torch.set_num_threads(config.threads)
    try:
        with torch.inference_mode():
            yield
    finally:
        torch.set_num_threads(previous)
