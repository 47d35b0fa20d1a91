"""GPU check of the reprojection residual's element-wise path (issue 39): the learned networks' training
graph runs the residual's row functions (``fgslam.factors.reprojection_jit``) element-wise on CUDA
tensors, while every frontend runs them compiled on the CPU. JSON to stdout.

a. **parity**: ``ROWS`` random rows (generic motion, targets about 2 px from the prediction) through
   ``reproject_inv_depth``, once without and once with a stereo extrinsic: compiled on the CPU in float64
   against element-wise on the device in float64 and float32. Reports the valid masks' agreement and the
   largest difference of each output divided by ``1 +`` the output's largest magnitude.
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

Environment: ``DEVICE`` (cuda), ``ROWS`` (20000), ``TIMED_ROWS`` (262144, 2^18 rows), ``REPEATS`` (20).
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

logger = logging.getLogger("gpu_kernel_check")
OUTPUTS = ("residual", "J_Ti", "J_Tj", "J_d")
INTRINSICS = (420.0, 410.0, 319.5, 239.5)  # fx, fy, cx, cy of a 640x480 camera
IMAGE_SIZE = (640.0, 480.0)
STEREO_BASELINE_M = 0.11
MIN_DEPTH = 1e-3
WARMUP_CALLS = 3
DEFAULT_ROWS = 20000
DEFAULT_TIMED_ROWS = 2 ** 18
DEFAULT_REPEATS = 20
SEED_PARITY, SEED_GRADIENT, SEED_TIMING = 39, 40, 41
# the random rows: rotation angles (rad), translations, log-scales, inverse depths, target noise (px)
SOURCE_ANGLE, RELATIVE_ANGLE = 1.0, 0.1
RELATIVE_TRANSLATION, LOG_SCALE = 0.2, 0.3
INVERSE_DEPTH_RANGE = (0.05, 1.0)
TARGET_NOISE_PX = 2.0


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
    """Source pixels, inverse depths, both poses ``T_WCi``, ``T_WCj`` as ``(R, t, s)`` and noisy targets,
    float64 CPU tensors."""
    R_WCi = random_rotations(rng, n, SOURCE_ANGLE)
    R_WCj = R_WCi @ random_rotations(rng, n, RELATIVE_ANGLE)
    t_WCi = rng.normal(size=(n, 3))
    t_WCj = t_WCi + rng.normal(size=(n, 3)) * RELATIVE_TRANSLATION
    s_i, s_j = np.exp(rng.normal(size=n) * LOG_SCALE), np.exp(rng.normal(size=n) * LOG_SCALE)
    uv = rng.uniform((0.0, 0.0), IMAGE_SIZE, size=(n, 2))
    d = rng.uniform(*INVERSE_DEPTH_RANGE, n)
    target = uv + rng.normal(size=(n, 2)) * TARGET_NOISE_PX
    t = lambda x: torch.from_numpy(np.ascontiguousarray(x))  # noqa: E731
    return t(uv), t(d), (t(R_WCi), t(t_WCi), t(s_i)), (t(R_WCj), t(t_WCj), t(s_j)), t(target)


def move(x, device, dtype):
    if isinstance(x, tuple):
        return tuple(move(v, device, dtype) for v in x)
    return x.to(device=device, dtype=dtype)


def call(inputs, T_CRCL):
    uv, d, T_WCi, T_WCj, target = inputs
    K = torch.tensor(INTRINSICS, dtype=uv.dtype, device=uv.device)
    ext = {} if T_CRCL is None else {"T_CtCj": T_CRCL}
    return reproject_inv_depth(uv, d, T_WCi, T_WCj, K, target, config=ReprojectionConfig(min_depth=MIN_DEPTH), **ext)


def scaled_difference(a: torch.Tensor, b: torch.Tensor, valid: torch.Tensor) -> float:
    a, b = a[valid].double().cpu(), b[valid].double().cpu()
    return float((a - b).abs().max() / (1.0 + a.abs().max()))


def parity(device: torch.device, n: int) -> dict:
    inputs = rows(np.random.default_rng(SEED_PARITY), n)
    T_CRCL = np.eye(4)
    T_CRCL[0, 3] = -STEREO_BASELINE_M
    out = {}
    for name, extrinsic in (("mono", None), ("stereo", T_CRCL)):
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
    inputs = rows(np.random.default_rng(SEED_GRADIENT), n)
    ref = call(inputs, None)
    uv, d, T_WCi, T_WCj, target = move(inputs, device, torch.float64)
    d = d.clone().requires_grad_(True)
    res = call((uv, d, T_WCi, T_WCj, target), None)
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
    uv, d, T_WCi, T_WCj, target = move(rows(np.random.default_rng(SEED_TIMING), n), device, torch.float32)

    def forward():
        with torch.no_grad():
            call((uv, d, T_WCi, T_WCj, target), None)

    def forward_backward():
        leaves = [x.clone().requires_grad_(True) for x in (d, *T_WCi, *T_WCj)]
        res = call((uv, leaves[0], tuple(leaves[1:4]), tuple(leaves[4:7]), target), None)
        loss = sum((getattr(res, k) ** 2).sum() for k in OUTPUTS)
        loss.backward()

    return {"rows": n, "forward": timed(forward, device, repeats),
            "forward_backward": timed(forward_backward, device, repeats)}


def main() -> int:
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    device = torch.device(os.environ.get("DEVICE", "cuda"))
    n = int(os.environ.get("ROWS", DEFAULT_ROWS))
    n_timed = int(os.environ.get("TIMED_ROWS", DEFAULT_TIMED_ROWS))
    repeats = int(os.environ.get("REPEATS", DEFAULT_REPEATS))
    import fgslam  # here: which tree's package was imported (PYTHONPATH), for the report
    result = {"device": str(device), "fgslam": str(fgslam.__file__), "torch": torch.__version__,
              "gpu": torch.cuda.get_device_name() if device.type == "cuda" else None}
    for stage, run in (("parity", lambda: parity(device, n)), ("gradient", lambda: gradient(device, n)),
                       ("timing", lambda: timing(device, n_timed, repeats))):
        t0 = time.perf_counter()
        result[stage] = run()
        logger.info("%s: %.1f s", stage, time.perf_counter() - t0)
    print(json.dumps(result, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
