"""The networks as measurement sources: what the learned slot classes of the dense and patch frontends
run (:class:`fgslam.frontends.dense.source.LearnedDroidSource`,
:class:`fgslam.frontends.patch.source.LearnedDPVOSource`).

- :class:`DroidRunner`: per frame the features, hidden state and context (:meth:`DroidRunner.add_frame`);
  per edge ``(i, j)`` the recurrent state and the last target, kept across calls as in DROID-SLAM's
  frontend (the motion input ``target - coords1`` is the previous revision measured from the new
  reprojection); :meth:`DroidRunner.revise` runs ``iterations`` update steps from the induced field
  and returns targets, per-axis confidences and the damping eta of the source frame.
  Coordinates: the network's 1/8 maps are indexed like the frontend's grid (grid pixel ``(x, y)`` =
  feature pixel ``(x, y)``), so fields pass unchanged.
- :class:`DpvoRunner`: per frame the 1/4-resolution matching pyramid and context map; per request
  (one frame pair) the patches' ``3 x 3`` features at their centres and edges to the target frame;
  the hidden state of an edge is kept per (source frame, target frame, patch centre) while both
  frames' features live. The frontend gives each patch's centre reprojection only, so the patch's
  ``3 x 3`` pixels are placed around it at the 1/4 grid spacing (a fronto-parallel patch; DPVO
  reprojects each pixel with the patch's depth, which differs by the local rotation and scale of the
  warp). Full-resolution pixel = 4 x quarter pixel (DPVO's intrinsics / 4).

Everything runs under :func:`fgslam.nets.config.network_runtime` (inference mode, CPU threads) on the
configured device.
"""

from __future__ import annotations

import itertools
import logging
import weakref
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from ..core.errors import ConfigError, DataError
from .checkpoint import load_dpvo, load_droid
from .config import DpvoNetConfig, DroidNetConfig, network_runtime, resolve_device
from .droid import CORR_LEVELS, AltCorr, CorrVolume, coords_grid
from .dpvo import PATCH, patch_correlation, pyramid

logger = logging.getLogger(__name__)

__all__ = ["DPVO_CHANNELS", "DROID_CHANNELS", "DpvoFeatures", "DpvoRunner", "DroidRunner", "network_image"]

_DROID_STRIDE = 8
_DPVO_RES = 4
DROID_CHANNELS = "rgb"  # droid_slam extract_features: images[:, :, [2, 1, 0]] of cv2's BGR
DPVO_CHANNELS = "bgr"  # dpvo: cv2's BGR as read (its TartanAir training reader too)


def network_image(image: np.ndarray, order: str, who: str = "learned source", frame="") -> torch.Tensor:
    """The ``(3, H, W)`` float tensor in [0, 255] that the official pipeline hands its network, in channel
    ``order`` (``rgb``: DROID-SLAM, whose ``extract_features`` flips OpenCV's BGR to RGB; ``bgr``: DPVO,
    which feeds ``cv2.imread``'s BGR as it is and was trained on it), from a frame's image: colour
    ``(H, W, 3)`` in **RGB** order (:attr:`fgslam.io.frame.Frame.rgb`) or grey ``(H, W)``, repeated in
    the three channels as ``cv2.imread`` reads a grey file. The networks' ``normalize`` then applies the
    official normalisation (DROID: / 255, ImageNet mean and std; DPVO: ``2 x / 255 - 0.5``)."""
    image = np.asarray(image)
    if image.dtype != np.uint8 or image.ndim not in (2, 3) or (image.ndim == 3 and image.shape[2] != 3):
        raise DataError(f"{who}: frame {frame} must be a grey (H, W) or RGB (H, W, 3) uint8 image, got "
                        f"{image.dtype} {image.shape}")
    if order not in ("rgb", "bgr"):
        raise ValueError(f"channel order must be rgb or bgr, got {order!r}")
    t = torch.from_numpy(np.ascontiguousarray(image)).float()
    if t.ndim == 2:
        return t[None].expand(3, -1, -1)
    t = t.permute(2, 0, 1)
    return t.flip(0) if order == "bgr" else t


class DroidRunner:
    """DROID-SLAM's update operator on a frame graph (module docstring)."""

    def __init__(self, checkpoint: str | Path, config: DroidNetConfig | None = None, stride: int = _DROID_STRIDE):
        if int(stride) != _DROID_STRIDE:
            raise ConfigError(f"dense.source.stride must be {_DROID_STRIDE} for the DROID network (got {stride})")
        self.config = config or DroidNetConfig()
        self.device = resolve_device(self.config.device)
        self.net = load_droid(checkpoint, self.device)
        self._frames: dict[int, tuple[torch.Tensor, torch.Tensor, torch.Tensor]] = {}
        self._edges: dict[tuple[int, int], tuple[torch.Tensor, torch.Tensor]] = {}
        self._shape: tuple[int, int] | None = None

    def add_frame(self, frame_id: int, image: np.ndarray) -> None:
        x = network_image(image, DROID_CHANNELS, "DROID source", frame_id)
        H, W = x.shape[1:]
        minimum = _DROID_STRIDE * 2 ** (CORR_LEVELS - 1)
        if H % _DROID_STRIDE or W % _DROID_STRIDE or H < minimum or W < minimum:
            raise DataError(f"DROID source: image size {W}x{H} must be a multiple of {_DROID_STRIDE} and at least "
                            f"{minimum}x{minimum} (the 4-level correlation pyramid; dataset.crop_multiple)")
        if self._shape is not None and self._shape != (H, W):
            raise DataError(f"DROID source: frame {frame_id} is {W}x{H}, earlier frames {self._shape[1]}x{self._shape[0]}")
        self._shape = (H, W)
        with network_runtime(self.config):
            fmap, net, inp = self.net.extract(x[None].to(self.device))
        self._frames[int(frame_id)] = (fmap[0], net[0], inp[0])

    def remove_frame(self, frame_id: int) -> None:
        fid = int(frame_id)
        self._frames.pop(fid, None)
        for key in [k for k in self._edges if fid in k]:
            del self._edges[key]

    def _frame(self, fid: int):
        try:
            return self._frames[int(fid)]
        except KeyError:
            raise DataError(f"DROID source: frame {fid} was not added (add_frame) or was removed") from None

    def revise(self, edges: Sequence[tuple[int, int]], uv_induced: np.ndarray):
        """Per edge ``(target (h, w, 2), weight (h, w, 2), eta (h, w))`` as float64 arrays."""
        if self._shape is None:
            raise DataError("DROID source: no frame added")
        h, w = self._shape[0] // _DROID_STRIDE, self._shape[1] // _DROID_STRIDE
        uv = np.asarray(uv_induced, np.float64)
        if uv.shape != (len(edges), h, w, 2):
            raise DataError(f"DROID source: uv_induced has shape {uv.shape}, expected {(len(edges), h, w, 2)}")
        if not len(edges):
            return []
        cfg, dev = self.config, self.device
        frames = sorted({int(f) for e in edges for f in e})
        pos = {f: n for n, f in enumerate(frames)}
        for f in frames:
            self._frame(f)
        ii = torch.tensor([pos[int(i)] for i, _ in edges], device=dev)
        jj = torch.tensor([pos[int(j)] for _, j in edges], device=dev)
        src = torch.tensor([int(i) for i, _ in edges], device=dev)
        with network_runtime(cfg):
            fmaps = torch.stack([self._frames[f][0] for f in frames])
            coords0 = coords_grid(h, w, device=dev)[None].expand(len(edges), h, w, 2)
            induced = torch.as_tensor(uv, dtype=torch.float32, device=dev)
            ok = torch.isfinite(induced).all(-1)
            coords1 = torch.where(ok[..., None], induced, coords0)
            nets, targets = [], []
            for n, (i, j) in enumerate(edges):
                state = self._edges.get((int(i), int(j)))
                if state is None:
                    nets.append(self._frames[int(i)][1])
                    targets.append(coords1[n])
                else:
                    nets.append(state[0])
                    targets.append(torch.where(ok[n, ..., None], state[1], coords1[n]))
            net = torch.stack(nets)
            target = torch.stack(targets)
            inp = torch.stack([self._frames[int(i)][2] for i, _ in edges])
            if cfg.correlation == "volume":
                volume = CorrVolume(fmaps[ii], fmaps[jj])
                corr_fn = lambda c: volume(c)  # noqa: E731
            else:
                alt = AltCorr(fmaps, chunk=cfg.chunk_edges, mode="volume" if cfg.correlation == "alt" else "features")
                corr_fn = lambda c: alt(c, ii, jj)  # noqa: E731
            for _ in range(cfg.iterations):
                corr = corr_fn(coords1)
                motion = self.net.motion(coords0, coords1, target, cfg.motion_clamp)
                net, delta, weight, (eta, _mask, eta_frames) = self.net.update(net, inp, corr, motion, src)
                target = coords1 + delta
            weight = torch.where(ok[..., None], weight, torch.zeros_like(weight))
            eta_of = {int(f): n for n, f in enumerate(eta_frames.tolist())}
            for n, (i, j) in enumerate(edges):
                self._edges[(int(i), int(j))] = (net[n].clone(), target[n].clone())
            out = []
            tgt_np = target.double().cpu().numpy()
            w_np = weight.double().cpu().numpy()
            eta_np = eta.double().cpu().numpy()
            for n, (i, _) in enumerate(edges):
                out.append((tgt_np[n], w_np[n], eta_np[eta_of[int(i)]]))
        return out


@dataclass(eq=False)
class DpvoFeatures:
    """One frame's DPVO maps (1/4 resolution) and the image they came from (for :meth:`DpvoRunner.pack`)."""

    uid: int
    image: np.ndarray
    levels: list  # matching pyramid [(128, h, w), (128, h/4, w/4)]
    imap: torch.Tensor  # (384, h, w)


class DpvoRunner:
    """DPVO's update operator on patch edges (module docstring)."""

    def __init__(self, checkpoint: str | Path, config: DpvoNetConfig | None = None):
        self.config = config or DpvoNetConfig()
        self.device = resolve_device(self.config.device)
        self.net = load_dpvo(checkpoint, self.device)
        self._ids = itertools.count()
        self._states: dict[tuple[int, int], dict[tuple[float, float], torch.Tensor]] = {}
        self._offsets = torch.stack(torch.meshgrid(torch.arange(PATCH, dtype=torch.float32) - PATCH // 2,
                                                   torch.arange(PATCH, dtype=torch.float32) - PATCH // 2,
                                                   indexing="ij")[::-1], -1).to(self.device)  # (p, p, (dx, dy))

    def prepare(self, image: np.ndarray) -> DpvoFeatures:
        x = network_image(image, DPVO_CHANNELS, "DPVO source")
        with network_runtime(self.config):
            fmap, imap = self.net.extract(x[None].to(self.device))
        feats = DpvoFeatures(next(self._ids), np.asarray(image), [lv[0] for lv in pyramid(fmap)], imap[0])
        weakref.finalize(feats, DpvoRunner._forget, weakref.ref(self), feats.uid)
        return feats

    @staticmethod
    def _forget(runner_ref, uid: int) -> None:
        runner = runner_ref()
        if runner is not None:
            for key in [k for k in runner._states if uid in k]:
                del runner._states[key]

    def pack(self, features: DpvoFeatures) -> np.ndarray:
        """Only the image is kept for long-range edges; the maps are recomputed on :meth:`unpack`."""
        return features.image

    def unpack(self, packed: np.ndarray) -> DpvoFeatures:
        return self.prepare(packed)

    def measure_batch(self, requests: list) -> list[tuple[np.ndarray, np.ndarray]]:
        """``[(src, tgt, uv_src (n, 2), uv_pred (n, 2)), ...]`` (full-resolution pixels) -> per request
        ``(uv (n, 2), confidence (n,))``."""
        if not requests:
            return []
        cfg, dev = self.config, self.device
        feats = {}
        for src, tgt, _, _ in requests:
            feats.setdefault(src.uid, src)
            feats.setdefault(tgt.uid, tgt)
        order = list(feats)
        pos = {u: n for n, u in enumerate(order)}
        sizes = [len(r[2]) for r in requests]
        with network_runtime(cfg):
            levels = [torch.stack([feats[u].levels[k] for u in order]) for k in range(2)]
            imaps = torch.stack([feats[u].imap for u in order])
            uv_src = torch.as_tensor(np.concatenate([np.asarray(r[2], np.float64) for r in requests]), dtype=torch.float32,
                                     device=dev)
            uv_pred = torch.as_tensor(np.concatenate([np.asarray(r[3], np.float64) for r in requests]),
                                      dtype=torch.float32, device=dev)
            ii = torch.tensor(np.repeat([pos[r[0].uid] for r in requests], sizes), device=dev)
            jj = torch.tensor(np.repeat([pos[r[1].uid] for r in requests], sizes), device=dev)
            # one patch per (source frame, centre): the same patch measured in several targets shares kk
            keys = [(r[0].uid, float(x), float(y)) for r in requests for x, y in np.asarray(r[2], np.float64)]
            patch_of: dict = {}
            kk = torch.tensor([patch_of.setdefault(k, len(patch_of)) for k in keys], device=dev)
            first = {}
            for e, k in enumerate(keys):
                first.setdefault(k, e)
            rep = torch.tensor(list(first.values()), device=dev)
            centres = uv_src[rep] / _DPVO_RES
            gmap, ctx = self.net.patchify.patches(levels[0], imaps, ii[rep], centres)
            coords = uv_pred[:, None, None, :] / _DPVO_RES + self._offsets  # (E, p, p, 2)
            corr = patch_correlation(gmap, levels, coords, kk, jj)
            net = torch.zeros(len(keys), self.net.DIM, device=dev)
            pair_keys = [(r[0].uid, r[1].uid) for r, n in zip(requests, sizes) for _ in range(n)]
            for e, (pk, k) in enumerate(zip(pair_keys, keys)):
                state = self._states.get(pk, {}).get(k[1:])
                if state is not None:
                    net[e] = state
            for _ in range(cfg.iterations):
                net, delta, weight = self.net.update(net, ctx[kk], corr, ii, jj, kk)
            uv = (uv_pred / _DPVO_RES + delta) * _DPVO_RES
            conf = weight.min(-1).values
            conf = torch.where(conf >= cfg.min_confidence, conf, torch.zeros_like(conf))
            for e, (pk, k) in enumerate(zip(pair_keys, keys)):
                self._states.setdefault(pk, {})[k[1:]] = net[e].clone()
            uv_np, conf_np = uv.double().cpu().numpy(), conf.double().cpu().numpy()
        out, lo = [], 0
        for n in sizes:
            out.append((uv_np[lo:lo + n], conf_np[lo:lo + n]))
            lo += n
        return out
