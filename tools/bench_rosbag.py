"""Reading a ROS bag vs the dataset folder: the same ``fgslam run`` from a folder and from ROS 1 / ROS 2
bags of it, one after the other; prints one JSON object.

The clips are written into bags here (also used by tests/test_rosbag.py through tests/tool_support.py):
the images go in as they are (EuRoC PNG pixels as mono8 ``Image``, 7-Scenes JPEG bytes as
``CompressedImage``, 7-Scenes depth as ``16UC1``), with a ``CameraInfo`` per image from the folder
loader's calibration (a stereo pair's ``R`` / ``P`` from its rectification).

Per case and source (folder, ROS 1 ``.bag``, ROS 2 sqlite3, ROS 2 mcap), ``--repeats`` runs in
turn (folder, bags, folder, bags, ...): wall seconds and CPU seconds (the child process's user +
system), medians, and the overhead of each bag source over the folder (``bag / folder - 1``); also
the dataset alone (open and read every frame, in this process: CPU seconds) and the load average
(``uptime``) before and after. The trajectories of folder and bag runs are compared byte for byte.

Usage:
  OMP_NUM_THREADS=1 .venv/bin/python tools/bench_rosbag.py [--cases euroc_stereo,7scenes_rgbd] [--repeats 2]
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Optional

import numpy as np

from fgslam.export.bag import BagWriter
from fgslam.io.undistort import Undistorter
from fgslam.io.datasets import DatasetConfig, EurocDataset, SevenScenesDataset

NS = 1_000_000_000
REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared" / "data"


def camera_info(bag: BagWriter, stamp_ns: int, frame_id: str, calib, R=None, P=None, model="plumb_bob"):
    """A CameraInfo message for a raw ``Calibration`` (plumb_bob D padded to 5 coefficients)."""
    T = bag.types
    fx, fy, cx, cy = calib.K
    K = np.array([fx, 0, cx, 0, fy, cy, 0, 0, 1], dtype=np.float64)
    D = np.zeros(5)
    if calib.distortion_model == "equidistant":
        model, D = "equidistant", calib.distortion.copy()
    else:
        D[: calib.distortion.size] = calib.distortion
    R = np.eye(3) if R is None else R
    P = np.hstack([calib.K_matrix(), np.zeros((3, 1))]) if P is None else P
    roi = T["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)
    arrays = dict(D=D, K=K, R=np.asarray(R, np.float64).reshape(-1), P=np.asarray(P, np.float64).reshape(-1))
    if not bag.ros1:
        arrays = {k.lower(): v for k, v in arrays.items()}
    return T["sensor_msgs/msg/CameraInfo"](
        header=bag.header(stamp_ns, frame_id), height=calib.height, width=calib.width, distortion_model=model,
        binning_x=0, binning_y=0, roi=roi, **arrays)


def image_msg(bag: BagWriter, stamp_ns: int, frame_id: str, img: np.ndarray, encoding: str):
    data = np.ascontiguousarray(img)
    h, w = data.shape[:2]
    return bag.types["sensor_msgs/msg/Image"](
        header=bag.header(stamp_ns, frame_id), height=h, width=w, encoding=encoding, is_bigendian=0,
        step=int(data.strides[0]), data=data.view(np.uint8).reshape(-1))


def compressed_msg(bag: BagWriter, stamp_ns: int, frame_id: str, data: bytes, fmt: str):
    return bag.types["sensor_msgs/msg/CompressedImage"](
        header=bag.header(stamp_ns, frame_id), format=fmt, data=np.frombuffer(data, dtype=np.uint8))


def imu_msg(bag: BagWriter, stamp_ns: int, gyro, accel):
    T = bag.types
    vec = T["geometry_msgs/msg/Vector3"]
    return T["sensor_msgs/msg/Imu"](
        header=bag.header(stamp_ns, "imu0"), orientation=T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0),
        orientation_covariance=np.zeros(9), angular_velocity=vec(x=float(gyro[0]), y=float(gyro[1]), z=float(gyro[2])),
        angular_velocity_covariance=np.zeros(9),
        linear_acceleration=vec(x=float(accel[0]), y=float(accel[1]), z=float(accel[2])),
        linear_acceleration_covariance=np.zeros(9))


def read_ns_stream(csv: Path) -> list[tuple[int, str]]:
    rows = []
    for line in csv.read_text().splitlines():
        if line.strip() and not line.startswith("#"):
            ts, name = (p.strip() for p in line.split(",")[:2])
            rows.append((int(ts), name))
    return rows


def write_euroc_bag(root: Path, out: Path, storage: str = "sqlite3", end: Optional[int] = None,
                    imu_margin_s: Optional[float] = 1.0) -> dict:
    """The EuRoC clip at ``root`` as a bag: /cam0, /cam1 mono8 + camera_info (rectified pair), /imu0 (the
    IMU rows within ``imu_margin_s`` of the images' time span; None: all, 145 s)."""
    import cv2

    ds = EurocDataset(root, DatasetConfig())
    calib = ds.raw_calibration
    R1, R2, P1, P2 = Undistorter(calib, rectify=True, alpha=0.0).rectification
    P1 = np.hstack([P1[:, :3], np.zeros((3, 1))])
    cams = [("cam0", calib, R1, P1), ("cam1", calib.right, R2, P2)]
    with BagWriter(out, storage) as bag:
        for name, cal, R, P in cams:
            rows = read_ns_stream(ds.mav / name / "data.csv")[:end]
            for ts, fname in rows:
                path = ds.mav / name / "data" / fname
                if not path.is_file():  # the clip lists cam1 rows past its last cam0 frame without files
                    continue
                img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
                bag.write(f"/{name}/image_raw", "sensor_msgs/msg/Image", ts, image_msg(bag, ts, name, img, "mono8"))
                bag.write(f"/{name}/camera_info", "sensor_msgs/msg/CameraInfo", ts, camera_info(bag, ts, name, cal, R, P))
        t0, t1 = read_ns_stream(ds.mav / "cam0" / "data.csv")[0][0], read_ns_stream(ds.mav / "cam0" / "data.csv")[:end][-1][0]
        margin = None if imu_margin_s is None else int(imu_margin_s * NS)
        if ds.imu is not None:
            for line in (ds.mav / "imu0" / "data.csv").read_text().splitlines():
                if line.strip() and not line.startswith("#"):
                    parts = line.split(",")
                    ts, values = int(parts[0]), [float(v) for v in parts[1:7]]
                    if margin is not None and not t0 - margin <= ts <= t1 + margin:
                        continue
                    bag.write("/imu0", "sensor_msgs/msg/Imu", ts, imu_msg(bag, ts, values[:3], values[3:]))
    return {"T_BC": calib.T_BC}


def write_7scenes_bag(root: Path, out: Path, storage: str = "sqlite3", end: Optional[int] = None) -> None:
    """The 7-Scenes clip at ``root`` as a bag: /camera/color/image_raw/compressed (JPEG bytes as they are),
    /camera/depth/image_raw (16UC1 mm), /camera/color/camera_info; stamps ``round(i / 30 Hz)`` ns."""
    import cv2

    ds = SevenScenesDataset(root, DatasetConfig())
    with BagWriter(out, storage) as bag:
        for i, (color, stem) in enumerate(list(zip(ds._color, ds._stems))[:end]):
            ts = int(round(float(ds.raw_timestamps[i]) * NS))
            fmt = "jpeg" if color.suffix.lower() in (".jpg", ".jpeg") else "png"
            bag.write("/camera/color/image_raw/compressed", "sensor_msgs/msg/CompressedImage", ts,
                      compressed_msg(bag, ts, "camera", color.read_bytes(), fmt))
            bag.write("/camera/color/camera_info", "sensor_msgs/msg/CameraInfo", ts,
                      camera_info(bag, ts, "camera", ds.raw_calibration))
            depth = cv2.imread(str(ds.seq / f"{stem}.depth.png"), cv2.IMREAD_UNCHANGED)
            bag.write("/camera/depth/image_raw", "sensor_msgs/msg/Image", ts, image_msg(bag, ts, "camera", depth, "16UC1"))


def write_small_bag(out: Path, images: dict, infos: dict | None = None, imu: Optional[str] = None, frames: int = 6,
                    size=(64, 48), stamps_ns: Optional[list[int]] = None, storage: str = "sqlite3",
                    rate_hz: float = 10.0) -> np.ndarray:
    """A small bag: ``images`` maps topic -> encoding (``compressed-png`` for a CompressedImage PNG) of
    textured ``size`` frames; ``infos`` maps CameraInfo topic -> ``(width, height)``; ``imu`` a topic
    of 200 Hz samples. Returns the grey base image (frame i is it rolled by i pixels)."""
    import cv2

    from fgslam.io.calibration import Calibration

    w, h = size
    rng = np.random.default_rng(0)
    base = cv2.GaussianBlur(rng.integers(0, 255, (h, w), dtype=np.uint8), (3, 3), 0)
    stamps = stamps_ns if stamps_ns is not None else [NS + int(i * NS / rate_hz) for i in range(frames)]
    with BagWriter(out, storage) as bag:
        for i, ts in enumerate(stamps):
            log = NS + int(i * NS / rate_hz)  # log time in order; the header stamp ts as given
            grey = np.roll(base, i, axis=1)
            for topic, enc in images.items():
                if enc == "compressed-png":
                    ok, buf = cv2.imencode(".png", grey)
                    bag.write(topic, "sensor_msgs/msg/CompressedImage", log, compressed_msg(bag, ts, "cam", buf.tobytes(), "png"))
                    continue
                img = {"mono8": grey, "bgr8": cv2.cvtColor(grey, cv2.COLOR_GRAY2BGR),
                       "rgb8": cv2.cvtColor(grey, cv2.COLOR_GRAY2RGB),
                       "16UC1": (grey.astype(np.uint16) * 10 + 500), "32FC1": grey.astype(np.float32) / 100 + 0.5,
                       }.get(enc, grey)
                bag.write(topic, "sensor_msgs/msg/Image", log, image_msg(bag, ts, "cam", img, enc))
            for topic, (iw, ih) in (infos or {}).items():
                cal = Calibration(iw, ih, [50.0, 50.0, iw / 2 - 0.5, ih / 2 - 0.5])
                bag.write(topic, "sensor_msgs/msg/CameraInfo", log, camera_info(bag, ts, "cam", cal))
        if imu:
            t_imu = range(stamps[0] - NS // 10, stamps[-1] + NS // 10, NS // 200) if stamps_ns is None else []
            for k, ts in enumerate(t_imu):
                bag.write(imu, "sensor_msgs/msg/Imu", ts, imu_msg(bag, ts, [0.01 * k, 0.2, 0.3], [0.0, 9.81, 0.1]))
    return base


# ------------------------------------------------------------------------------- benchmark
CASES = {  # name: (clip folder, writer, preset, overrides)
    "euroc_stereo": ("euroc_v101_micro", "euroc", "patch_euroc_stereo", ()),
    "7scenes_rgbd": ("7scenes_redkitchen_0-599", "7scenes", "patch_7scenes_rgbd", ("dataset.end=300",)),
}
SOURCES = ("folder", "ros1", "ros2_sqlite3", "ros2_mcap")
TRAJECTORY = "trajectory_kitti.txt"  # poses only: 7-Scenes folder times are i / 30 s, a bag's integer ns


def _loadavg() -> list[float]:
    return [round(v, 2) for v in os.getloadavg()]


def _child_cpu() -> float:
    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime


def _run(data: Path, out: Path, preset: str, overrides) -> dict:
    cmd = [str(Path(sys.executable).parent / "fgslam"), "-q", "run", preset, "--data", str(data), "--out", str(out),
           "--no-progress"]
    for o in overrides:
        cmd += ["-o", o]
    cpu0, t0 = _child_cpu(), time.perf_counter()
    proc = subprocess.run(cmd, capture_output=True, text=True)
    wall, cpu = time.perf_counter() - t0, _child_cpu() - cpu0
    if proc.returncode != 0:
        raise SystemExit(f"{' '.join(cmd)} failed ({proc.returncode}): {proc.stderr[-2000:]}")
    return {"wall_s": round(wall, 3), "cpu_s": round(cpu, 3), "trajectory": (out / TRAJECTORY).read_bytes()}


def _read_cpu(data: Path, overrides) -> dict:
    """CPU seconds to open the dataset and read every frame (in this process)."""
    from fgslam.core.config import load_config
    from fgslam.io.datasets import DatasetConfig, open_dataset

    config = load_config(DatasetConfig, None, [o.removeprefix("dataset.") for o in overrides if o.startswith("dataset.")])
    t0 = time.process_time()
    ds = open_dataset(data, config=config)
    t_open = time.process_time() - t0
    n = sum(1 for _ in ds)
    return {"open_cpu_s": round(t_open, 3), "read_cpu_s": round(time.process_time() - t0, 3), "frames": n}


def bench_case(name: str, repeats: int, work: Path) -> dict:
    clip, writer, preset, overrides = CASES[name]
    root = SHARED / clip
    sources = {"folder": root}
    end = next((int(o.split("=")[1]) for o in overrides if o.startswith("dataset.end=")), None)
    extra = list(overrides)
    for source in SOURCES[1:]:
        out = work / (f"{name}.bag" if source == "ros1" else f"{name}_{source}")
        storage = source.split("_")[-1]
        if writer == "euroc":
            T_BC = write_euroc_bag(root, out, storage, end=end, imu_margin_s=None)["T_BC"]  # all 145 s of IMU, as the folder
            extra_T = "dataset.T_BC=" + json.dumps(T_BC.reshape(-1).tolist())
        else:
            write_7scenes_bag(root, out, storage, end=end)
            extra_T = None
        sources[source] = out
    if writer == "euroc":
        extra.append(extra_T)
    runs: dict[str, list] = {s: [] for s in sources}
    for k in range(repeats):
        for source, data in sources.items():
            runs[source].append(_run(data, work / f"out_{name}_{source}_{k}", preset, extra))
    reads = {s: _read_cpu(d, extra) for s, d in sources.items()}
    folder_traj = runs["folder"][0]["trajectory"]
    out = {"preset": preset, "overrides": [o for o in extra if not o.startswith("dataset.T_BC")], "sources": {}}
    med = {}
    for source, rs in runs.items():
        wall = sorted(r["wall_s"] for r in rs)[len(rs) // 2]
        cpu = sorted(r["cpu_s"] for r in rs)[len(rs) // 2]
        med[source] = (wall, cpu)
        out["sources"][source] = {
            "wall_s": [r["wall_s"] for r in rs], "cpu_s": [r["cpu_s"] for r in rs], "median_wall_s": wall,
            "median_cpu_s": cpu, "same_trajectory_as_folder": all(r["trajectory"] == folder_traj for r in rs),
            **reads[source]}
    for source in SOURCES[1:]:
        out["sources"][source]["wall_overhead"] = round(med[source][0] / med["folder"][0] - 1, 4)
        out["sources"][source]["cpu_overhead"] = round(med[source][1] / med["folder"][1] - 1, 4)
    return out


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cases", default=",".join(CASES), help=f"comma-separated, of {', '.join(CASES)}")
    parser.add_argument("--repeats", type=int, default=2)
    args = parser.parse_args(argv)
    if not SHARED.is_dir():
        raise SystemExit(f"shared data not found at {SHARED}")
    report = {"uptime_before": subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip(),
              "load_before": _loadavg(), "cpus": os.cpu_count(), "cases": {}}
    with tempfile.TemporaryDirectory(prefix="bench_rosbag_") as tmp:
        for name in args.cases.split(","):
            report["cases"][name] = bench_case(name, args.repeats, Path(tmp))
    report["uptime_after"] = subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip()
    report["load_after"] = _loadavg()
    print(json.dumps(report, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
