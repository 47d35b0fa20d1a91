"""Loading the official checkpoints ``droid.pth`` (DROID-SLAM) and ``dpvo.pth`` (DPVO) strictly.

No renaming by the user: the file's state dict is read with ``torch.load(weights_only=True)`` and
adapted exactly as the authors' own loaders do, nothing more:

- a leading ``module.`` (``torch.nn.DataParallel``) is stripped from every key;
- a ``{"model_state_dict": ...}`` wrapper (DPV-SLAM's newer files) is unwrapped;
- ``droid.pth``: the heads ``update.weight.2`` and ``update.delta.2`` were trained with more output
  channels than the two used (``droid_slam/droid.py`` keeps ``[:2]``); extra channels are dropped;
- ``dpvo.pth``: the entry ``update.lmbda`` (a training-time damping parameter the network does not
  use) is dropped (``dpvo/dpvo.py`` skips it).

Then ``load_state_dict(strict=True)``: any other missing or unexpected key, or a shape that differs,
is a :class:`CheckpointError` naming the file and the first offending keys. Files written by
``tools/train.py`` (:func:`save_checkpoint`) are in the same format.
"""

from __future__ import annotations

import logging
from collections import OrderedDict
from pathlib import Path

import torch
import torch.nn as nn

from ..core.errors import DataError
from .dpvo import VONet
from .droid import DroidNet

logger = logging.getLogger(__name__)

__all__ = ["CheckpointError", "adapt_state_dict", "load_dpvo", "load_droid", "load_network", "read_state_dict",
           "save_checkpoint"]

_DROID_SLICED = ("update.weight.2.weight", "update.weight.2.bias", "update.delta.2.weight", "update.delta.2.bias")
_DPVO_DROPPED = ("update.lmbda",)
_SHOW = 5  # offending keys named in an error


class CheckpointError(DataError):
    """A checkpoint file that is missing, unreadable or not the expected network."""


def read_state_dict(path: str | Path) -> "OrderedDict[str, torch.Tensor]":
    """The tensors of a ``.pth`` file (``weights_only``: no code from the file runs)."""
    path = Path(path).expanduser()
    if path.is_dir():
        raise CheckpointError(f"checkpoint {path} is a folder; a file (.pth) is expected")
    if not path.is_file():
        raise CheckpointError(f"checkpoint {path} not found")
    try:
        obj = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # noqa: BLE001 - torch.load raises many types on a foreign file (IndexError, UnpicklingError...)
        raise CheckpointError(f"checkpoint {path} is not a readable torch state dict "
                              f"(torch.load with weights_only: {type(exc).__name__})") from None
    if isinstance(obj, dict) and "model_state_dict" in obj and isinstance(obj["model_state_dict"], dict):
        obj = obj["model_state_dict"]
    if not isinstance(obj, dict) or not obj or not all(isinstance(v, torch.Tensor) for v in obj.values()):
        raise CheckpointError(f"checkpoint {path} does not hold a state dict of tensors "
                              f"(got {type(obj).__name__})")
    return OrderedDict(obj)


def adapt_state_dict(state: dict, network: str) -> "OrderedDict[str, torch.Tensor]":
    """The official loaders' adaptations (module docstring); ``network`` is ``droid`` or ``dpvo``."""
    out = OrderedDict()
    for key, value in state.items():
        key = key[len("module."):] if key.startswith("module.") else key
        if network == "dpvo" and key in _DPVO_DROPPED:
            continue
        if network == "droid" and key in _DROID_SLICED and value.shape[0] > 2:
            value = value[:2]
        out[key] = value
    return out


def _check(net: nn.Module, state: dict, path: Path, title: str) -> None:
    expected = net.state_dict()
    missing = [k for k in expected if k not in state]
    unexpected = [k for k in state if k not in expected]
    shapes = [f"{k} {tuple(state[k].shape)} (expected {tuple(v.shape)})" for k, v in expected.items()
              if k in state and tuple(state[k].shape) != tuple(v.shape)]
    problems = []
    if missing:
        problems.append(f"{len(missing)} missing keys ({', '.join(missing[:_SHOW])}{', ...' if len(missing) > _SHOW else ''})")
    if unexpected:
        problems.append(f"{len(unexpected)} unexpected keys ({', '.join(unexpected[:_SHOW])}"
                        f"{', ...' if len(unexpected) > _SHOW else ''})")
    if shapes:
        problems.append(f"{len(shapes)} shape mismatches ({'; '.join(shapes[:_SHOW])})")
    if problems:
        raise CheckpointError(f"checkpoint {path} is not a {title} state dict: {'; '.join(problems)}")


def load_network(path: str | Path, network: str, device: torch.device | str = "cpu") -> nn.Module:
    """Build ``network`` (``droid`` or ``dpvo``), load ``path`` strictly, move to ``device``, eval mode."""
    builders = {"droid": (DroidNet, "DROID-SLAM (droid.pth)"), "dpvo": (VONet, "DPVO (dpvo.pth)")}
    if network not in builders:
        raise ValueError(f"unknown network {network!r}")
    cls, title = builders[network]
    path = Path(path).expanduser()
    state = adapt_state_dict(read_state_dict(path), network)
    net = cls()
    _check(net, state, path, title)
    net.load_state_dict(state, strict=True)
    logger.info("loaded %s weights from %s (%d tensors)", title, path, len(state))
    return net.to(device).eval()


def load_droid(path: str | Path, device: torch.device | str = "cpu") -> nn.Module:
    """:class:`fgslam.nets.droid.DroidNet` with the weights of ``path``."""
    return load_network(path, "droid", device)


def load_dpvo(path: str | Path, device: torch.device | str = "cpu") -> nn.Module:
    """:class:`fgslam.nets.dpvo.VONet` with the weights of ``path``."""
    return load_network(path, "dpvo", device)


def save_checkpoint(net: nn.Module, path: str | Path) -> Path:
    """Write ``net``'s state dict in the official format (plain names, CPU tensors)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    state = OrderedDict((k, v.detach().cpu()) for k, v in net.state_dict().items())
    tmp = path.with_suffix(path.suffix + ".tmp")
    torch.save(state, tmp)
    tmp.replace(path)
    return path
