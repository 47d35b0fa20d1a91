"""DPVO's network (Teed, Lipson & Deng 2023; DPV-SLAM section 3.1) in plain torch.

Module and parameter names are those of the official ``dpvo/net.py`` (``VONet``) so that ``dpvo.pth``
loads strictly (:mod:`fgslam.nets.checkpoint`):

- ``patchify.fnet`` (instance norm, 128-d) and ``patchify.inet`` (no norm, 384-d): encoders at 1/4
  resolution (two stages of two residual blocks); maps are divided by 4. A patch keeps the ``p x p``
  (3 x 3) matching features around its centre (``gmap``) and the 1 x 1 context vector at its centre.
- correlation (eq. 4): for each edge ``(patch k of frame i, frame j)`` and each of the patch's ``p^2``
  pixels, the dot products with a 7 x 7 bilinear window of ``j``'s features around the pixel's
  reprojection, at two levels (the map and its 4x4 average pooling, coordinates / 4): ``2 * 49 * p^2``
  values, flattened as ``[x offset][y offset][patch row][patch col][level]`` (the CUDA kernel's order).
- ``update``: the hidden state per edge (384-d): ``net + inp + corr(corr)``, LayerNorm; messages from
  the same patch's edges to the previous and next target frames (``c1``, ``c2``); soft aggregation
  over the edges of one patch (``agg_kk``) and of one frame pair (``agg_ij``); two gated residual
  units (``gru``); heads ``d`` (Delta, 2) and ``w`` (weight, sigmoid, 2).

Coordinates are 1/4-resolution pixels (full-resolution pixel = 4 x this, the intrinsics / 4 convention
of the official code). Images ``(N, 3, H, W)`` in [0, 255] are mapped to ``2 x / 255 - 0.5``; the
official pipeline feeds them in OpenCV's **BGR** order, without a flip (the network was trained on BGR:
:func:`fgslam.nets.sources.network_image`).
"""

from __future__ import annotations

import torch
import torch.nn as nn
import torch.nn.functional as F

from .common import Encoder, GradientClip, group_index, scatter_softmax, scatter_sum, window_lookup

__all__ = ["DIM", "GatedResidual", "Patchifier", "SoftAgg", "Update", "VONet", "neighbors", "patch_correlation",
           "patch_window"]

DIM = 384  # hidden state per edge
PATCH = 3  # p
RADIUS = 3  # 7 x 7 lookup
LEVELS = (1, 4)  # pooling factors of the two correlation levels
MAP_SCALE = 4.0  # feature and context maps are divided by this


class GatedResidual(nn.Module):
    def __init__(self, dim: int):
        super().__init__()
        self.gate = nn.Sequential(nn.Linear(dim, dim), nn.Sigmoid())
        self.res = nn.Sequential(nn.Linear(dim, dim), nn.ReLU(inplace=True), nn.Linear(dim, dim))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x + self.gate(x) * self.res(x)


class SoftAgg(nn.Module):
    """Softmax-weighted aggregation over groups of edges, broadcast back to every edge of the group:
    ``h(sum_g softmax_g(g(x)) * f(x))``."""

    def __init__(self, dim: int = DIM):
        super().__init__()
        self.dim = dim
        self.f = nn.Linear(dim, dim)
        self.g = nn.Linear(dim, dim)
        self.h = nn.Linear(dim, dim)

    def forward(self, x: torch.Tensor, keys: torch.Tensor) -> torch.Tensor:
        """``x`` ``(E, dim)``, ``keys`` ``(E,)`` group keys."""
        index, groups = group_index(keys)
        w = scatter_softmax(self.g(x), index, groups, dim=0)
        y = scatter_sum(self.f(x) * w, index, groups, dim=0)
        return self.h(y)[index]


def neighbors(kk: torch.Tensor, jj: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """For each edge, the edge of the same patch ``kk`` with the nearest smaller / larger target frame
    ``jj`` (-1 if none): DPVO's ``fastba.neighbors``."""
    E = kk.numel()
    if E == 0:
        return kk.new_empty(0), kk.new_empty(0)
    span = int(jj.max()) + 1
    order = torch.argsort(kk.long() * span + jj.long())
    ks = kk[order]
    prev = torch.full((E,), -1, dtype=torch.long, device=kk.device)
    nxt = torch.full((E,), -1, dtype=torch.long, device=kk.device)
    same = ks[1:] == ks[:-1]
    prev_sorted = torch.where(same, order[:-1], torch.full_like(order[:-1], -1))
    next_sorted = torch.where(same, order[1:], torch.full_like(order[1:], -1))
    prev[order[1:]] = prev_sorted
    nxt[order[:-1]] = next_sorted
    return prev, nxt


class Update(nn.Module):
    """DPVO's recurrent update operator over an edge list (module docstring)."""

    def __init__(self, p: int = PATCH):
        super().__init__()
        self.c1 = nn.Sequential(nn.Linear(DIM, DIM), nn.ReLU(inplace=True), nn.Linear(DIM, DIM))
        self.c2 = nn.Sequential(nn.Linear(DIM, DIM), nn.ReLU(inplace=True), nn.Linear(DIM, DIM))
        self.norm = nn.LayerNorm(DIM, eps=1e-3)
        self.agg_kk = SoftAgg(DIM)
        self.agg_ij = SoftAgg(DIM)
        self.gru = nn.Sequential(nn.LayerNorm(DIM, eps=1e-3), GatedResidual(DIM), nn.LayerNorm(DIM, eps=1e-3),
                                 GatedResidual(DIM))
        self.corr = nn.Sequential(nn.Linear(2 * 49 * p * p, DIM), nn.ReLU(inplace=True), nn.Linear(DIM, DIM),
                                  nn.LayerNorm(DIM, eps=1e-3), nn.ReLU(inplace=True), nn.Linear(DIM, DIM))
        self.d = nn.Sequential(nn.ReLU(inplace=False), nn.Linear(DIM, 2), GradientClip())
        self.w = nn.Sequential(nn.ReLU(inplace=False), nn.Linear(DIM, 2), GradientClip(), nn.Sigmoid())

    def forward(self, net, inp, corr, ii, jj, kk):
        """``net``, ``inp`` ``(E, 384)``; ``corr`` ``(E, 882)``; ``ii``, ``jj``, ``kk`` ``(E,)`` source frame,
        target frame, patch. Returns ``net``, ``delta`` ``(E, 2)``, ``weight`` ``(E, 2)``."""
        net = self.norm(net + inp + self.corr(corr))
        ix, jx = neighbors(kk, jj)
        mask_ix = (ix >= 0).to(net.dtype)[:, None]
        mask_jx = (jx >= 0).to(net.dtype)[:, None]
        net = net + self.c1(mask_ix * net[ix.clamp(min=0)])
        net = net + self.c2(mask_jx * net[jx.clamp(min=0)])
        net = net + self.agg_kk(net, kk)
        span = int(jj.max()) + 1 if jj.numel() else 1
        net = net + self.agg_ij(net, ii.long() * span + jj.long())
        net = self.gru(net)
        return net, self.d(net), self.w(net)


def patch_window(maps: torch.Tensor, frame: torch.Tensor, centres: torch.Tensor, radius: int) -> torch.Tensor:
    """Bilinear ``(2r+1)^2`` patches of ``maps`` ``(N, C, h, w)`` at ``centres`` ``(M, 2)`` of frames
    ``frame`` ``(M,)`` -> ``(M, C, 2r+1 (rows), 2r+1 (cols))``."""
    win = window_lookup(maps, frame, centres[:, None, :], radius)[:, 0]  # (M, x, y, C)
    return win.permute(0, 3, 2, 1)


class Patchifier(nn.Module):
    """Feature and context encoders at 1/4 resolution, and patch extraction."""

    def __init__(self, patch_size: int = PATCH):
        super().__init__()
        self.patch_size = patch_size
        self.fnet = Encoder(128, "instance", (32, 64))
        self.inet = Encoder(DIM, "none", (32, 64))

    def forward(self, images: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Normalised images ``(N, 3, H, W)`` -> matching maps ``(N, 128, H/4, W/4)`` and context maps
        ``(N, 384, H/4, W/4)`` (both / 4)."""
        return self.fnet(images) / MAP_SCALE, self.inet(images) / MAP_SCALE

    def patches(self, fmap, imap, frame, centres):
        """``gmap`` ``(M, 128, p, p)`` and context ``(M, 384)`` of patches at ``centres`` ``(M, 2)``
        (1/4-resolution pixels) of frames ``frame`` ``(M,)``."""
        gmap = patch_window(fmap, frame, centres, self.patch_size // 2)
        ctx = patch_window(imap, frame, centres, 0)[:, :, 0, 0]
        return gmap, ctx


def pyramid(fmap: torch.Tensor) -> list[torch.Tensor]:
    """The two correlation levels of matching maps ``(N, 128, h, w)``."""
    return [fmap if lvl == 1 else F.avg_pool2d(fmap, lvl, stride=lvl) for lvl in LEVELS]


def patch_correlation(gmap: torch.Tensor, levels: list[torch.Tensor], coords: torch.Tensor, kk: torch.Tensor,
                      jj: torch.Tensor, radius: int = RADIUS) -> torch.Tensor:
    """Correlation features ``(E, 2 * 49 * p^2)`` (eq. 4) of edges: patch ``kk`` (``gmap`` ``(M, C, p, p)``)
    looked up in frame ``jj``'s maps ``levels`` around ``coords`` ``(E, p, p, 2)`` (1/4-res pixels of
    every patch pixel's reprojection).

    Per target frame and level, one matrix product correlates the patch pixels of its edges with the
    whole map, and the 7 x 7 windows are read from those scalar maps (4x less CPU time than gathering
    128-d feature windows, the same numbers; memory: the frame's edges x p^2 x the map's pixels)."""
    E, p = coords.shape[0], coords.shape[1]
    q = p * p
    g = gmap[kk].permute(0, 2, 3, 1).reshape(E * q, -1)  # rows: edge, patch row, patch column
    out = torch.zeros(E, 2 * radius + 1, 2 * radius + 1, q, len(levels), dtype=g.dtype, device=g.device)
    for frame in torch.unique(jj).tolist():
        sel = torch.nonzero(jj == frame)[:, 0]
        rows = (sel[:, None] * q + torch.arange(q, device=g.device)).reshape(-1)
        gs = g[rows]
        for lvl, (scale, fl) in enumerate(zip(LEVELS, levels)):
            _, C, H, W = fl.shape
            maps = (gs @ fl[frame].reshape(C, H * W)).reshape(-1, 1, H, W)
            pts = coords[sel].reshape(-1, 1, 2) / scale
            win = window_lookup(maps, torch.arange(len(rows), device=g.device), pts, radius)[:, 0, :, :, 0]
            out[sel, :, :, :, lvl] = win.reshape(len(sel), q, 2 * radius + 1, 2 * radius + 1).permute(0, 2, 3, 1)
    return out.reshape(E, -1)


class VONet(nn.Module):
    """DPVO's network: ``patchify`` and ``update`` (module docstring)."""

    def __init__(self):
        super().__init__()
        self.P = PATCH
        self.DIM = DIM
        self.RES = 4
        self.patchify = Patchifier(self.P)
        self.update = Update(self.P)

    @staticmethod
    def normalize(images: torch.Tensor) -> torch.Tensor:
        """BGR ``(N, 3, H, W)`` in [0, 255] -> ``2 x / 255 - 0.5`` (the official input mapping)."""
        return 2.0 * (images.float() / 255.0) - 0.5

    def extract(self, images: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        return self.patchify(self.normalize(images))
