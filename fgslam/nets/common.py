"""Pieces both networks share: gradient clipping, the encoders' residual blocks, bilinear window
lookup (the correlation kernels' sampling, in plain torch) and grouped reductions (scatter mean /
softmax / sum without torch_scatter).

Window lookup convention (both official CUDA kernels): around a point ``(x, y)`` the ``2r + 2``
integer samples ``floor(x) - r .. floor(x) + r + 1`` (zero outside the map) are combined bilinearly
into ``2r + 1`` values at ``x - r .. x + r``; results are ordered ``[x offset][y offset]``.
"""

from __future__ import annotations

import torch
import torch.nn as nn

__all__ = ["GradientClip", "ResidualBlock", "Encoder", "window_lookup", "group_index", "scatter_mean",
           "scatter_softmax", "scatter_sum", "window_correlation"]


class _GradClip(torch.autograd.Function):
    """Identity forward; backward replaces NaN by 0 and clips to +-0.01 (both papers' GradientClip)."""

    @staticmethod
    def forward(ctx, x):  # noqa: D401
        return x.view_as(x)

    @staticmethod
    def backward(ctx, grad):
        grad = torch.where(torch.isnan(grad), torch.zeros_like(grad), grad)
        return grad.clamp(-0.01, 0.01)


class GradientClip(nn.Module):
    """Parameter-free layer (it holds a slot in the heads' ``nn.Sequential`` numbering)."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return _GradClip.apply(x)


def _norm(kind: str, planes: int) -> nn.Module:
    if kind == "instance":
        return nn.InstanceNorm2d(planes)  # affine=False: no parameters, as in the official encoders
    if kind == "none":
        return nn.Sequential()
    raise ValueError(f"unknown norm {kind!r}")


class ResidualBlock(nn.Module):
    """Two 3x3 convolutions with a (strided 1x1) shortcut; names ``conv1, conv2, downsample.0``."""

    def __init__(self, in_planes: int, planes: int, norm: str, stride: int = 1):
        super().__init__()
        self.conv1 = nn.Conv2d(in_planes, planes, kernel_size=3, padding=1, stride=stride)
        self.conv2 = nn.Conv2d(planes, planes, kernel_size=3, padding=1)
        self.relu = nn.ReLU(inplace=True)
        self.norm1 = _norm(norm, planes)
        self.norm2 = _norm(norm, planes)
        if stride == 1:
            self.downsample = None
        else:
            self.norm3 = _norm(norm, planes)
            self.downsample = nn.Sequential(nn.Conv2d(in_planes, planes, kernel_size=1, stride=stride), self.norm3)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        y = self.relu(self.norm1(self.conv1(x)))
        y = self.relu(self.norm2(self.conv2(y)))
        if self.downsample is not None:
            x = self.downsample(x)
        return self.relu(x + y)


class Encoder(nn.Module):
    """7x7 stride-2 stem, ``len(widths)`` stages of two residual blocks (every stage after the first
    halves the resolution), 1x1 output convolution: the official ``BasicEncoder`` (DROID: widths 32, 64,
    128, six residual blocks, stride 8) and ``BasicEncoder4`` (DPVO: 32, 64, stride 4)."""

    def __init__(self, output_dim: int, norm: str, widths: tuple[int, ...]):
        super().__init__()
        self.norm1 = _norm(norm, widths[0])
        self.conv1 = nn.Conv2d(3, widths[0], kernel_size=7, stride=2, padding=3)
        self.relu1 = nn.ReLU(inplace=True)
        in_planes = widths[0]
        for n, width in enumerate(widths, start=1):
            stride = 1 if n == 1 else 2
            setattr(self, f"layer{n}", nn.Sequential(ResidualBlock(in_planes, width, norm, stride),
                                                     ResidualBlock(width, width, norm, 1)))
            in_planes = width
        self.n_layers = len(widths)
        self.conv2 = nn.Conv2d(in_planes, output_dim, kernel_size=1)
        for m in self.modules():
            if isinstance(m, nn.Conv2d):
                nn.init.kaiming_normal_(m.weight, mode="fan_out", nonlinearity="relu")

    @property
    def stride(self) -> int:
        return 2 ** self.n_layers

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """``(N, 3, H, W)`` normalised images -> ``(N, output_dim, H / stride, W / stride)``."""
        x = self.relu1(self.norm1(self.conv1(x)))
        for n in range(1, self.n_layers + 1):
            x = getattr(self, f"layer{n}")(x)
        return self.conv2(x)


def _window_gather(src, frame, coords, radius):
    """Integer samples of the windows: ``(B, Q, D, D, C)`` values (zero outside) ``[x][y]``, ``D = 2r + 2``,
    and the bilinear fractions ``dx``, ``dy`` ``(B, Q, 1, 1)``."""
    N, C, H, W = src.shape
    B, Q, _ = coords.shape
    D = 2 * radius + 2
    ok_pt = torch.isfinite(coords).all(-1)
    coords = torch.where(ok_pt[..., None], coords, torch.zeros_like(coords))
    x0, y0 = coords[..., 0], coords[..., 1]
    fx, fy = torch.floor(x0), torch.floor(y0)
    off = torch.arange(D, device=src.device) - radius
    xs = fx.long()[..., None] + off  # (B, Q, D)
    ys = fy.long()[..., None] + off
    xs2, ys2 = xs[..., :, None].expand(B, Q, D, D), ys[..., None, :].expand(B, Q, D, D)  # [x][y]
    inside = (xs2 >= 0) & (xs2 < W) & (ys2 >= 0) & (ys2 < H) & ok_pt[..., None, None]
    flat = (frame.long()[:, None, None, None] * (H * W) + ys2.clamp(0, H - 1) * W + xs2.clamp(0, W - 1))
    table = src.permute(0, 2, 3, 1).reshape(N * H * W, C)
    vals = table.index_select(0, flat.reshape(-1)).reshape(B, Q, D, D, C) * inside[..., None].to(src.dtype)
    return vals, (x0 - fx)[..., None, None], (y0 - fy)[..., None, None]


def _bilinear(vals: torch.Tensor, dx: torch.Tensor, dy: torch.Tensor) -> torch.Tensor:
    """Combine ``(B, Q, D, D, ...)`` integer samples into ``(B, Q, D-1, D-1, ...)`` bilinear values."""
    extra = vals.dim() - 4
    dx = dx.reshape(dx.shape + (1,) * extra)
    dy = dy.reshape(dy.shape + (1,) * extra)
    return ((1 - dx) * (1 - dy) * vals[:, :, :-1, :-1] + dx * (1 - dy) * vals[:, :, 1:, :-1]
            + (1 - dx) * dy * vals[:, :, :-1, 1:] + dx * dy * vals[:, :, 1:, 1:])


def window_lookup(src: torch.Tensor, frame: torch.Tensor, coords: torch.Tensor, radius: int) -> torch.Tensor:
    """Bilinear ``(2r+1) x (2r+1)`` windows of ``src`` around points (module docstring).

    ``src`` ``(N, C, H, W)`` maps; ``frame`` ``(B,)`` which map each batch row reads; ``coords``
    ``(B, Q, 2)`` points ``(x, y)`` in the map's pixels. Returns ``(B, Q, 2r+1 (x), 2r+1 (y), C)``.
    Non-finite points read zeros.
    """
    vals, dx, dy = _window_gather(src, frame, coords, radius)
    return _bilinear(vals, dx, dy)


def window_correlation(src: torch.Tensor, frame: torch.Tensor, coords: torch.Tensor, query: torch.Tensor,
                       radius: int) -> torch.Tensor:
    """Dot products of ``query`` ``(B, Q, C)`` with the bilinear windows of :func:`window_lookup`:
    ``(B, Q, 2r+1 (x), 2r+1 (y))``. The products are taken at the integer samples first (bilinear
    interpolation is linear), so the C-dimensional windows are never interpolated."""
    vals, dx, dy = _window_gather(src, frame, coords, radius)
    B, Q, D = vals.shape[:3]
    dots = torch.bmm(vals.reshape(B * Q, D * D, -1), query.reshape(B * Q, -1, 1)).reshape(B, Q, D, D)
    return _bilinear(dots, dx, dy)


def group_index(keys: torch.Tensor) -> tuple[torch.Tensor, int]:
    """Dense group ids ``(E,)`` in ``[0, G)`` of integer keys, and ``G``."""
    uniq, inverse = torch.unique(keys, return_inverse=True)
    return inverse, int(uniq.numel())


def scatter_sum(x: torch.Tensor, index: torch.Tensor, groups: int, dim: int = 0) -> torch.Tensor:
    shape = list(x.shape)
    shape[dim] = groups
    return torch.zeros(shape, dtype=x.dtype, device=x.device).index_add(dim, index, x)


def scatter_mean(x: torch.Tensor, index: torch.Tensor, groups: int, dim: int = 0) -> torch.Tensor:
    total = scatter_sum(x, index, groups, dim)
    count = torch.zeros(groups, dtype=x.dtype, device=x.device).index_add(0, index, torch.ones_like(index, dtype=x.dtype))
    shape = [1] * x.dim()
    shape[dim] = groups
    return total / count.clamp(min=1).view(shape)


def scatter_softmax(x: torch.Tensor, index: torch.Tensor, groups: int, dim: int = 0) -> torch.Tensor:
    """Softmax over the entries of each group along ``dim`` (per remaining coordinate)."""
    shape = list(x.shape)
    shape[dim] = groups
    full = torch.full(shape, float("-inf"), dtype=x.dtype, device=x.device)
    idx = index.view([-1 if d == dim else 1 for d in range(x.dim())]).expand_as(x)
    gmax = full.scatter_reduce(dim, idx, x, reduce="amax", include_self=True)
    e = torch.exp(x - gmax.index_select(dim, index).detach())
    return e / scatter_sum(e, index, groups, dim).index_select(dim, index)
