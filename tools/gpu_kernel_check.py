"""GPU check of the reprojection residual's element-wise path (issue 39): the learned networks' training
graph runs the residual's row functions (``fgslam.factors.reprojection_jit``) element-wise on CUDA
tensors, while every frontend runs them compiled on the CPU. JSON to stdout.

a. **parity**: ``ROWS`` random rows (generic motion, a quarter of them with a stereo extrinsic) through
   ``reproject_inv_depth``: compiled on the CPU in float64 against element-wise on the device in float64
   and float32. Reports the valid masks' agreement and the largest difference of each output, scaled
   by the output's largest magnitude.
b. **gradient**: on the device, float64, the cost ``0.5 |r|^2`` back-propagated to the inverse depths
   against ``J_d^T r`` of the compiled rows.
c. **timing**: one call with Jacobians on the device at ``TIMED_ROWS`` rows (float32, the training's
   BA dtype on CUDA), the median of ``REPEATS`` calls after warm-up, synchronised; and the same call
   with gradients in the inverse depths and both poses, followed by the backward pass of a loss on the
   residual and every Jacobian (what the training graph does through the BA's linear system).

The tool imports whichever ``fgslam`` is on the path, so an older tree (``PYTHONPATH=old``) gives its
figures beside the current one (stages a and b compare its CPU path, torch then, the same way).

Usage, on the GPU machine from the repository root::

  python3 tools/gpu_kernel_check.py > kernel.json
  DEVICE=cpu python3 tools/gpu_kernel_check.py   # the script's own check, without a GPU

Environment: ``DEVICE`` (cuda), ``ROWS`` (20000), ``TIMED_ROWS`` (262144: 16 clips of a 128x96 grid
at 1/8 over 8 edges), ``REPEATS`` (20).
"""

from __future__ import annotations

import json
import logging
import os
import statistics
import time

import numpy as np
import torch

from fgslam.factors.reprojection import ReprojectionConfig, reproject_inv_depth

log = logging.getLogger("gpu_kernel_check")
OUTPUTS = ("residual", "J_Ti", "J_Tj", "J_d")
INTRINSICS = (420.0, 410.0, 319.5, 239.5)  # fx, fy, cx, cy of a 640x480 camera
IMAGE_SIZE = (640.0, 480.0)
STEREO_BASELINE_M = 0.11
MIN_DEPTH = 1e-3
WARMUP_CALLS = 3


def random_rotations(rng: np.random.Generator, n: int, angle: float) -> np.ndarray:
    """``(n, 3, 3)`` rotations about random axes by normal angles of deviation ``angle`` (rad)."""
    axis = rng.normal(size=(n, 3))
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    theta = rng.normal(size=(n, 1, 1)) * angle
    K = np.zeros((n, 3, 3))
    K[:, 0, 1], K[:, 0, 2], K[:, 1, 2] = -axis[:, 2], axis[:, 1], -axis[:, 0]
    K -= K.transpose(0, 2, 1)
    return np.eye(3) + np.sin(theta) * K + (1 - np.cos(theta)) * K @ K


def rows(rng: np.random.Generator, n: int):
    """Source pixels, inverse depths, both poses as ``(R, t, s)`` and noisy targets, float64 CPU tensors."""
    R_i = random_rotations(rng, n, 1.0)
    R_j = R_i @ random_rotations(rng, n, 0.1)
    t_i = rng.normal(size=(n, 3))
    t_j = t_i + rng.normal(size=(n, 3)) * 0.2
    s_i, s_j = np.exp(rng.normal(size=n) * 0.3), np.exp(rng.normal(size=n) * 0.3)
    uv = rng.uniform((0.0, 0.0), IMAGE_SIZE, size=(n, 2))
    d = rng.uniform(0.05, 1.0, n)
    target = uv + rng.normal(size=(n, 2)) * 2.0
    t = lambda x: torch.from_numpy(np.ascontiguousarray(x))  # noqa: E731
    return t(uv), t(d), (t(R_i), t(t_i), t(s_i)), (t(R_j), t(t_j), t(s_j)), t(target)


def move(x, device, dtype):
    if isinstance(x, tuple):
        return tuple(move(v, device, dtype) for v in x)
    return x.to(device=device, dtype=dtype)


def call(inputs, extrinsic):
    uv, d, T_i, T_j, target = inputs
    K = torch.tensor(INTRINSICS, dtype=uv.dtype, device=uv.device)
    ext = {} if extrinsic is None else {"T_CtCj": extrinsic}
    return reproject_inv_depth(uv, d, T_i, T_j, K, target, config=ReprojectionConfig(min_depth=MIN_DEPTH), **ext)


def scaled_difference(a: torch.Tensor, b: torch.Tensor, valid: torch.Tensor) -> float:
    a, b = a[valid].double().cpu(), b[valid].double().cpu()
    return float((a - b).abs().max() / (1.0 + a.abs().max()))


def parity(device: torch.device, n: int) -> dict:
    rng = np.random.default_rng(39)
    inputs = rows(rng, n)
    rig = np.eye(4)
    rig[0, 3] = -STEREO_BASELINE_M
    out = {}
    for name, extrinsic in (("mono", None), ("stereo", rig)):
        with torch.no_grad():
            cpu = call(inputs, extrinsic)
            for dtype in (torch.float64, torch.float32):
                dev = call(move(inputs, device, dtype), extrinsic)
                valid = cpu.valid & dev.valid.cpu()
                out[f"{name}_{str(dtype).split('.')[-1]}"] = {
                    "valid_rows": int(cpu.valid.sum()), "valid_disagree": int((cpu.valid != dev.valid.cpu()).sum()),
                    **{k: scaled_difference(getattr(cpu, k), getattr(dev, k), valid) for k in OUTPUTS}}
    return out


def gradient(device: torch.device, n: int) -> dict:
    inputs = rows(np.random.default_rng(40), n)
    ref = call(inputs, None)
    uv, d, T_i, T_j, target = move(inputs, device, torch.float64)
    d = d.clone().requires_grad_(True)
    res = call((uv, d, T_i, T_j, target), None)
    (0.5 * (res.residual ** 2).sum()).backward()
    expected = (ref.J_d * ref.residual).sum(-1)
    got = d.grad.cpu()
    return {"max_abs_difference": float((got - expected).abs().max()), "scale": float(expected.abs().max())}


def timed(fn, device: torch.device, repeats: int) -> dict:
    sync = torch.cuda.synchronize if device.type == "cuda" else (lambda: None)
    times = []
    for k in range(WARMUP_CALLS + repeats):
        sync()
        t0 = time.perf_counter()
        fn()
        sync()
        if k >= WARMUP_CALLS:
            times.append(time.perf_counter() - t0)
    return {"median_ms": 1e3 * statistics.median(times), "min_ms": 1e3 * min(times)}


def timing(device: torch.device, n: int, repeats: int) -> dict:
    uv, d, T_i, T_j, target = move(rows(np.random.default_rng(41), n), device, torch.float32)

    def forward():
        with torch.no_grad():
            call((uv, d, T_i, T_j, target), None)

    def forward_backward():
        leaves = [x.clone().requires_grad_(True) for x in (d, *T_i, *T_j)]
        res = call((uv, leaves[0], tuple(leaves[1:4]), tuple(leaves[4:7]), target), None)
        loss = sum((getattr(res, k) ** 2).sum() for k in OUTPUTS)
        loss.backward()

    return {"rows": n, "forward": timed(forward, device, repeats),
            "forward_backward": timed(forward_backward, device, repeats)}


def main() -> int:
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    device = torch.device(os.environ.get("DEVICE", "cuda"))
    n, n_timed = int(os.environ.get("ROWS", 20000)), int(os.environ.get("TIMED_ROWS", 262144))
    repeats = int(os.environ.get("REPEATS", 20))
    import fgslam
    result = {"device": str(device), "fgslam": str(fgslam.__file__), "torch": torch.__version__,
              "gpu": torch.cuda.get_device_name() if device.type == "cuda" else None}
    for stage, run in (("parity", lambda: parity(device, n)), ("gradient", lambda: gradient(device, n)),
                       ("timing", lambda: timing(device, n_timed, repeats))):
        t0 = time.perf_counter()
        result[stage] = run()
        log.info("%s: %.1f s", stage, time.perf_counter() - t0)
    print(json.dumps(result, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
