"""DROID-SLAM's network (Teed & Deng 2021, sections 3.1-3.2, appendix D) in plain torch.

Module and parameter names are those of the official ``droid_slam/droid_net.py`` so that ``droid.pth``
loads strictly (:mod:`fgslam.nets.checkpoint`):

- ``fnet``: feature encoder, 6 residual blocks, 3 downsamplings to 1/8, instance norm, 128-d;
  ``cnet``: context encoder, same layout without normalisation, 256-d, split into the hidden state
  (tanh, 128) and the input (relu, 128).
- correlation: all-pairs ``<f_i, f_j> / 16`` (features / 4 each), a 4-level pyramid (2x2 average
  pooling of the target dimensions, eq. 1), radius-3 lookup (49 values per level, 196 channels,
  channel ``level * 49 + x_offset * 7 + y_offset``). :class:`CorrVolume` builds the volume of every
  edge at once; :class:`AltCorr` (memory-efficient, for long edge lists) correlates ``chunk`` edges at a
  time, either through each chunk's volume or, never forming a volume, by pooling the target
  *features* and dotting the looked-up windows with the source features: the same numbers
  (correlation is linear in ``f_j``, so pooling and interpolation commute with it).
- ``update``: 1x1+3x3 correlation encoder, 7x7+3x3 motion encoder of ``[flow, target - coords]``
  (clamped to +-64), the 3x3 ConvGRU with global context pooling (``gru``), heads ``delta`` (flow
  revision r_ij), ``weight`` (confidence w_ij, sigmoid) and ``agg``: conv, mean over the edges that share
  the source frame, conv, then ``eta`` (per-pixel damping, 0.01 softplus) and ``upmask`` (8x8 convex
  upsampling, 9 weights per sub-pixel).

Coordinates are 1/8-resolution pixels of the feature maps; ``(N, 3, H, W)`` images are RGB in [0, 255].
"""

from __future__ import annotations

import torch
import torch.nn as nn
import torch.nn.functional as F

from .common import Encoder, GradientClip, scatter_mean, window_correlation, window_lookup

__all__ = ["AltCorr", "ConvGRU", "CorrVolume", "DroidNet", "GraphAgg", "UpdateModule", "convex_upsample",
           "coords_grid", "CORR_LEVELS", "CORR_RADIUS"]

CORR_LEVELS = 4  # pyramid levels (eq. 1)
CORR_RADIUS = 3  # lookup radius: 7 x 7 per level
FEATURE_SCALE = 4.0  # both feature maps are divided by this before the dot product
_MEAN = (0.485, 0.456, 0.406)  # ImageNet statistics the official encoders were trained with
_STD = (0.229, 0.224, 0.225)


def coords_grid(h: int, w: int, device=None, dtype=torch.float32) -> torch.Tensor:
    """``(h, w, 2)`` pixel coordinates ``(x, y)``."""
    y, x = torch.meshgrid(torch.arange(h, device=device, dtype=dtype), torch.arange(w, device=device, dtype=dtype),
                          indexing="ij")
    return torch.stack((x, y), -1)


class ConvGRU(nn.Module):
    """3x3 convolutional GRU whose gates also see a global context vector: the hidden state, gated
    by ``sigmoid(w h)``, averaged over the image (``convz_glo``...)."""

    def __init__(self, h_planes: int = 128, i_planes: int = 128 + 128 + 64):
        super().__init__()
        self.convz = nn.Conv2d(h_planes + i_planes, h_planes, 3, padding=1)
        self.convr = nn.Conv2d(h_planes + i_planes, h_planes, 3, padding=1)
        self.convq = nn.Conv2d(h_planes + i_planes, h_planes, 3, padding=1)
        self.w = nn.Conv2d(h_planes, h_planes, 1, padding=0)
        self.convz_glo = nn.Conv2d(h_planes, h_planes, 1, padding=0)
        self.convr_glo = nn.Conv2d(h_planes, h_planes, 1, padding=0)
        self.convq_glo = nn.Conv2d(h_planes, h_planes, 1, padding=0)

    def forward(self, net: torch.Tensor, *inputs: torch.Tensor) -> torch.Tensor:
        inp = torch.cat(inputs, dim=1)
        net_inp = torch.cat((net, inp), dim=1)
        glo = (torch.sigmoid(self.w(net)) * net).mean(dim=(2, 3), keepdim=True)
        z = torch.sigmoid(self.convz(net_inp) + self.convz_glo(glo))
        r = torch.sigmoid(self.convr(net_inp) + self.convr_glo(glo))
        q = torch.tanh(self.convq(torch.cat((r * net, inp), dim=1)) + self.convq_glo(glo))
        return (1 - z) * net + z * q


class GraphAgg(nn.Module):
    """Per-source-frame heads: damping ``eta`` and the convex-upsampling mask (pooled over the edges
    that share the source frame ``ii``)."""

    def __init__(self):
        super().__init__()
        self.conv1 = nn.Conv2d(128, 128, 3, padding=1)
        self.conv2 = nn.Conv2d(128, 128, 3, padding=1)
        self.relu = nn.ReLU(inplace=True)
        self.eta = nn.Sequential(nn.Conv2d(128, 1, 3, padding=1), GradientClip(), nn.Softplus())
        self.upmask = nn.Sequential(nn.Conv2d(128, 8 * 8 * 9, 1, padding=0))

    def forward(self, net: torch.Tensor, ii: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """``net`` ``(E, 128, h, w)``, ``ii`` ``(E,)`` -> ``eta`` ``(U, h, w)``, ``upmask`` ``(U, 576, h, w)``
        and the sorted unique source frames ``(U,)``."""
        frames, inverse = torch.unique(ii, return_inverse=True)
        x = self.relu(self.conv1(net))
        x = scatter_mean(x, inverse, int(frames.numel()), dim=0)
        x = self.relu(self.conv2(x))
        eta = self.eta(x)[:, 0]
        return 0.01 * eta, self.upmask(x), frames


class UpdateModule(nn.Module):
    """The update operator (module docstring)."""

    def __init__(self):
        super().__init__()
        cor_planes = CORR_LEVELS * (2 * CORR_RADIUS + 1) ** 2
        self.corr_encoder = nn.Sequential(nn.Conv2d(cor_planes, 128, 1, padding=0), nn.ReLU(inplace=True),
                                          nn.Conv2d(128, 128, 3, padding=1), nn.ReLU(inplace=True))
        self.flow_encoder = nn.Sequential(nn.Conv2d(4, 128, 7, padding=3), nn.ReLU(inplace=True),
                                          nn.Conv2d(128, 64, 3, padding=1), nn.ReLU(inplace=True))
        self.weight = nn.Sequential(nn.Conv2d(128, 128, 3, padding=1), nn.ReLU(inplace=True),
                                    nn.Conv2d(128, 2, 3, padding=1), GradientClip(), nn.Sigmoid())
        self.delta = nn.Sequential(nn.Conv2d(128, 128, 3, padding=1), nn.ReLU(inplace=True),
                                   nn.Conv2d(128, 2, 3, padding=1), GradientClip())
        self.gru = ConvGRU(128, 128 + 128 + 64)
        self.agg = GraphAgg()

    def forward(self, net, inp, corr, motion, ii=None):
        """``net``, ``inp`` ``(E, 128, h, w)``; ``corr`` ``(E, 196, h, w)``; ``motion`` ``(E, 4, h, w)``
        (``[coords1 - coords0, target - coords1]``, clamped to +-64); ``ii`` ``(E,)`` source frames.

        Returns ``net``, ``delta`` ``(E, h, w, 2)``, ``weight`` ``(E, h, w, 2)`` and, with ``ii``, the
        :class:`GraphAgg` outputs ``(eta, upmask, frames)``."""
        corr = self.corr_encoder(corr)
        flow = self.flow_encoder(motion)
        net = self.gru(net, inp, corr, flow)
        delta = self.delta(net).permute(0, 2, 3, 1)[..., :2]
        weight = self.weight(net).permute(0, 2, 3, 1)[..., :2]
        if ii is None:
            return net, delta, weight, None
        return net, delta, weight, self.agg(net, ii)


class CorrVolume:
    """All-pairs correlation pyramid of edges ``(f_i, f_j)`` (eq. 1), looked up around ``coords``."""

    def __init__(self, fmap_i: torch.Tensor, fmap_j: torch.Tensor, levels: int = CORR_LEVELS,
                 radius: int = CORR_RADIUS):
        E, C, h, w = fmap_i.shape
        self.radius = radius
        a = fmap_i.reshape(E, C, h * w) / FEATURE_SCALE
        b = fmap_j.reshape(E, C, h * w) / FEATURE_SCALE
        corr = torch.matmul(a.transpose(1, 2), b).reshape(E * h * w, 1, h, w)
        self.pyramid = [corr]
        for _ in range(levels - 1):
            corr = F.avg_pool2d(corr, 2, stride=2)
            self.pyramid.append(corr)
        self.shape = (E, h, w)

    def __call__(self, coords: torch.Tensor) -> torch.Tensor:
        """``coords`` ``(E, h, w, 2)`` in ``j``'s pixels -> ``(E, 196, h, w)``."""
        E, h, w = self.shape
        rows = torch.arange(E * h * w, device=coords.device)
        out = []
        for level, vol in enumerate(self.pyramid):
            pts = coords.reshape(E * h * w, 1, 2) / 2 ** level
            win = window_lookup(vol, rows, pts, self.radius)  # (E h w, 1, 7, 7, 1)
            out.append(win.reshape(E, h, w, -1))
        return torch.cat(out, -1).permute(0, 3, 1, 2)


class AltCorr:
    """Memory-efficient correlation for long edge lists (the same values as :class:`CorrVolume`):
    edges are correlated ``chunk`` at a time, so memory is bounded by the chunk, not the edge list.
    ``mode="volume"`` (default) builds each chunk's all-pairs pyramid (one matmul, fast, ``chunk (h w)^2``
    floats); ``mode="features"`` never forms a volume: it pools the target *features* and dots the
    looked-up windows with the source features (``chunk h w 64 C`` floats; slower on CPU, for large
    images)."""

    def __init__(self, fmaps: torch.Tensor, levels: int = CORR_LEVELS, radius: int = CORR_RADIUS, chunk: int = 16,
                 mode: str = "volume"):
        self.radius = radius
        self.levels = levels
        self.chunk = max(1, int(chunk))
        self.mode = mode
        self.fmaps = fmaps
        self.pyramid = [fmaps / FEATURE_SCALE]
        if mode == "features":
            for _ in range(levels - 1):
                self.pyramid.append(F.avg_pool2d(self.pyramid[-1], 2, stride=2))

    def __call__(self, coords: torch.Tensor, ii: torch.Tensor, jj: torch.Tensor) -> torch.Tensor:
        """``coords`` ``(E, h, w, 2)``; ``ii``, ``jj`` ``(E,)`` indices into ``fmaps`` -> ``(E, 196, h, w)``."""
        E, h, w, _ = coords.shape
        parts = []
        for lo in range(0, E, self.chunk):
            sl = slice(lo, min(E, lo + self.chunk))
            if self.mode == "volume":
                parts.append(CorrVolume(self.fmaps[ii[sl]], self.fmaps[jj[sl]], self.levels, self.radius)(coords[sl]))
                continue
            e = sl.stop - sl.start
            f_i = self.pyramid[0][ii[sl]].flatten(2).transpose(1, 2)  # (e, hw, C)
            levels = []
            for level, fl in enumerate(self.pyramid):
                pts = coords[sl].reshape(e, h * w, 2) / 2 ** level
                levels.append(window_correlation(fl, jj[sl], pts, f_i, self.radius).reshape(e, h, w, -1))
            parts.append(torch.cat(levels, -1).permute(0, 3, 1, 2))
        return torch.cat(parts, 0)


def convex_upsample(data: torch.Tensor, mask: torch.Tensor, factor: int = 8) -> torch.Tensor:
    """Upsample ``data`` ``(U, h, w, d)`` by ``factor`` with the convex combination ``mask``
    ``(U, factor^2 * 9, h, w)`` of each pixel's 3x3 neighbourhood -> ``(U, factor h, factor w, d)``."""
    U, h, w, d = data.shape
    mask = torch.softmax(mask.view(U, 1, 9, factor, factor, h, w), dim=2)
    up = F.unfold(data.permute(0, 3, 1, 2), [3, 3], padding=1).view(U, d, 9, 1, 1, h, w)
    up = (mask * up).sum(2)  # (U, d, f, f, h, w)
    return up.permute(0, 4, 2, 5, 3, 1).reshape(U, factor * h, factor * w, d)


class DroidNet(nn.Module):
    """DROID-SLAM's network: ``fnet``, ``cnet``, ``update`` (module docstring)."""

    def __init__(self):
        super().__init__()
        self.fnet = Encoder(128, "instance", (32, 64, 128))
        self.cnet = Encoder(256, "none", (32, 64, 128))
        self.update = UpdateModule()

    stride = 8

    @staticmethod
    def normalize(images: torch.Tensor) -> torch.Tensor:
        """RGB ``(N, 3, H, W)`` in [0, 255] -> the encoders' input (ImageNet mean / std)."""
        mean = torch.as_tensor(_MEAN, device=images.device, dtype=torch.float32)[:, None, None]
        std = torch.as_tensor(_STD, device=images.device, dtype=torch.float32)[:, None, None]
        return (images.float() / 255.0 - mean) / std

    def extract(self, images: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Features ``(N, 128, h, w)``, initial hidden state (tanh) and context input (relu)."""
        x = self.normalize(images)
        fmaps = self.fnet(x)
        net, inp = self.cnet(x).split([128, 128], dim=1)
        return fmaps, torch.tanh(net), torch.relu(inp)

    @staticmethod
    def motion(coords0: torch.Tensor, coords1: torch.Tensor, target: torch.Tensor, clamp: float = 64.0) -> torch.Tensor:
        """The motion features ``[coords1 - coords0, target - coords1]`` ``(E, 4, h, w)``, clamped."""
        m = torch.cat((coords1 - coords0, target - coords1), -1).permute(0, 3, 1, 2)
        return m.clamp(-clamp, clamp)

    def step(self, net, inp, corr_fn, coords0, coords1, target, ii, jj):
        """One update iteration on edges ``(ii, jj)``: correlation at ``coords1``, the operator, the new
        target ``coords1 + delta``. Returns ``net, target, weight, (eta, upmask, frames)``."""
        if isinstance(corr_fn, AltCorr):
            corr = corr_fn(coords1, ii, jj)
        else:
            corr = corr_fn(coords1)
        net, delta, weight, agg = self.update(net, inp, corr, self.motion(coords0, coords1, target), ii)
        return net, coords1 + delta, weight, agg
