"""The official parameter tables of ``droid.pth`` and ``dpvo.pth`` (names and shapes), written out from
the public sources (princeton-vl/DROID-SLAM ``droid_slam/droid_net.py``, ``modules/extractor.py``,
``modules/gru.py``; princeton-vl/DPVO ``dpvo/net.py``, ``dpvo/extractor.py``, ``dpvo/blocks.py``), and
state dicts in the files' own form (``module.`` prefix, DROID's 3-channel heads, DPVO's ``update.lmbda``).
Independent of :mod:`fgslam.nets`: the tests check the networks against these tables."""

from __future__ import annotations

from collections import OrderedDict

import pytest
import torch


def _conv(name, cout, cin, k):
    return [(f"{name}.weight", (cout, cin, k, k)), (f"{name}.bias", (cout,))]


def _linear(name, cout, cin):
    return [(f"{name}.weight", (cout, cin)), (f"{name}.bias", (cout,))]


def _encoder(prefix, out_dim, widths):
    """BasicEncoder / BasicEncoder4: InstanceNorm2d without affine and 'none' norms have no parameters."""
    rows = _conv(f"{prefix}.conv1", widths[0], 3, 7)
    cin = widths[0]
    for n, w in enumerate(widths, start=1):
        rows += _conv(f"{prefix}.layer{n}.0.conv1", w, cin, 3) + _conv(f"{prefix}.layer{n}.0.conv2", w, w, 3)
        if n > 1:
            rows += _conv(f"{prefix}.layer{n}.0.downsample.0", w, cin, 1)
        rows += _conv(f"{prefix}.layer{n}.1.conv1", w, w, 3) + _conv(f"{prefix}.layer{n}.1.conv2", w, w, 3)
        cin = w
    return rows + _conv(f"{prefix}.conv2", out_dim, cin, 1)


def droid_table() -> list[tuple[str, tuple[int, ...]]]:
    rows = _encoder("fnet", 128, (32, 64, 128)) + _encoder("cnet", 256, (32, 64, 128))
    u = "update"
    rows += _conv(f"{u}.corr_encoder.0", 128, 4 * 49, 1) + _conv(f"{u}.corr_encoder.2", 128, 128, 3)
    rows += _conv(f"{u}.flow_encoder.0", 128, 4, 7) + _conv(f"{u}.flow_encoder.2", 64, 128, 3)
    rows += _conv(f"{u}.weight.0", 128, 128, 3) + _conv(f"{u}.weight.2", 2, 128, 3)
    rows += _conv(f"{u}.delta.0", 128, 128, 3) + _conv(f"{u}.delta.2", 2, 128, 3)
    for g in ("convz", "convr", "convq"):
        rows += _conv(f"{u}.gru.{g}", 128, 128 + 320, 3)
    rows += _conv(f"{u}.gru.w", 128, 128, 1)
    for g in ("convz_glo", "convr_glo", "convq_glo"):
        rows += _conv(f"{u}.gru.{g}", 128, 128, 1)
    rows += _conv(f"{u}.agg.conv1", 128, 128, 3) + _conv(f"{u}.agg.conv2", 128, 128, 3)
    rows += _conv(f"{u}.agg.eta.0", 1, 128, 3) + _conv(f"{u}.agg.upmask.0", 576, 128, 1)
    return rows


def dpvo_table() -> list[tuple[str, tuple[int, ...]]]:
    D = 384
    rows = _encoder("patchify.fnet", 128, (32, 64)) + _encoder("patchify.inet", D, (32, 64))
    u = "update"
    for c in ("c1", "c2"):
        rows += _linear(f"{u}.{c}.0", D, D) + _linear(f"{u}.{c}.2", D, D)
    rows += [(f"{u}.norm.weight", (D,)), (f"{u}.norm.bias", (D,))]
    for a in ("agg_kk", "agg_ij"):
        rows += _linear(f"{u}.{a}.f", D, D) + _linear(f"{u}.{a}.g", D, D) + _linear(f"{u}.{a}.h", D, D)
    for n in (0, 2):
        rows += [(f"{u}.gru.{n}.weight", (D,)), (f"{u}.gru.{n}.bias", (D,))]
    for n in (1, 3):
        rows += _linear(f"{u}.gru.{n}.gate.0", D, D) + _linear(f"{u}.gru.{n}.res.0", D, D) + _linear(f"{u}.gru.{n}.res.2", D, D)
    rows += _linear(f"{u}.corr.0", D, 2 * 49 * 9) + _linear(f"{u}.corr.2", D, D)
    rows += [(f"{u}.corr.3.weight", (D,)), (f"{u}.corr.3.bias", (D,))] + _linear(f"{u}.corr.5", D, D)
    rows += _linear(f"{u}.d.1", 2, D) + _linear(f"{u}.w.1", 2, D)
    return rows


def official_droid_file(seed: int = 0, extra_channels: int = 1) -> "OrderedDict[str, torch.Tensor]":
    """A state dict shaped like ``droid.pth``: ``module.`` keys, heads with ``2 + extra_channels`` outputs."""
    g = torch.Generator().manual_seed(seed)
    out = OrderedDict()
    for name, shape in droid_table():
        if name.startswith(("update.weight.2", "update.delta.2")):
            shape = (shape[0] + extra_channels,) + shape[1:]
        out["module." + name] = 0.05 * torch.randn(shape, generator=g)
    return out


def official_dpvo_file(seed: int = 0) -> "OrderedDict[str, torch.Tensor]":
    """A state dict shaped like ``dpvo.pth``: ``module.`` keys plus ``update.lmbda``."""
    g = torch.Generator().manual_seed(seed)
    out = OrderedDict(("module." + name, 0.05 * torch.randn(shape, generator=g)) for name, shape in dpvo_table())
    out["module.update.lmbda"] = torch.tensor([1e-3])
    return out


@pytest.fixture(autouse=True)
def one_thread():
    """Autouse in the test modules that import it: torch on one thread (the machine is shared)."""
    previous = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(previous)
