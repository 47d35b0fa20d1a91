"""``fgslam synth``: generate a synthetic stereo + depth + IMU sequence in the EuRoC layout."""

from __future__ import annotations

import argparse
import json
import time

from . import add_config_arguments


def add_arguments(parser: argparse.ArgumentParser) -> None:
    # no choices= here: the preset names live with the scenarios, whose import pulls in OpenCV, and
    # building the CLI's parser must stay light (tests/test_cli.py); an unknown name is a ConfigError
    # that lists the valid ones when the config loads
    parser.add_argument("--preset", default=None, metavar="NAME",
                        help="scene and motion preset: room-loop (the config's default), street-loop, orbit, "
                             "highway, low-texture, panel-room, rotation-sweep, kitti00-drive; panel-room: "
                             "texture-poor RGB-D room (near-white wall panels with thin joints, tiled floor, doors; "
                             "point-light shading and vignetting; camera 0.5-2 m from the walls, 184 deg of yaw "
                             "over 189 frames at 10 Hz); rotation-sweep: hand-held roll/pitch/yaw sweep "
                             "(69 deg/s mean, fastest first, 30 Hz, 12 ms motion blur) over a small translation "
                             "in a textured room, raw images and depth with radial distortion k1=-0.30, k2=0.09 "
                             "(written to sensor.yaml; the loaders undistort); kitti00-drive: KITTI 00's 4,541 camera "
                             "poses (kitti_drive.poses, default ../shared/data/kitti_gt/00.txt) at 10 Hz, 320x96, "
                             "through a street built along the path; see docs/architecture.md section 17")
    parser.add_argument("--out", required=True, metavar="DIR", help="output sequence root (DIR/mav0/...)")
    parser.add_argument("--frames", type=int, default=None, help="number of frames (default: one loop + 1)")
    parser.add_argument("--seed", type=int, default=None, help="random seed of layout, textures and noise")
    parser.add_argument("--width", type=int, default=None, help="image width in pixels")
    parser.add_argument("--height", type=int, default=None, help="image height in pixels")
    parser.add_argument("--colour", action="store_true", help="write RGB images instead of grey")
    parser.add_argument("--layout", choices=("euroc", "tumvi"), default="euroc",
                        help="euroc (default: mav0 with depth0 and sensor.yaml files) or tumvi (TUM-VI "
                             "dataset-*_512_16: 16-bit PNGs, mav0/mocap0, dso/camchain.yaml; fisheye with "
                             "-o camera.distortion_model=equidistant -o camera.distortion=[k1,k2,k3,k4])")
    add_config_arguments(parser, "SynthConfig", "fgslam/configs/synth.yaml")


def run(args: argparse.Namespace) -> int:
    from ..io.synth import SynthSequence, write_sequence, write_tumvi_sequence  # deferred: cv2 (fgslam --help stays fast)
    from ..io.synth.scenarios import load_synth_config  # deferred: cv2

    overrides = list(args.overrides or [])
    for key, value in (("frames", args.frames), ("seed", args.seed), ("camera.width", args.width),
                       ("camera.height", args.height)):
        if value is not None:
            overrides.append(f"{key}={value}")
    if args.colour:
        overrides.append("camera.colour=true")
    cfg = load_synth_config(args.preset, args.config, overrides)
    t0 = time.perf_counter()
    seq = SynthSequence(cfg)
    t_build = time.perf_counter() - t0
    summary = (write_tumvi_sequence if args.layout == "tumvi" else write_sequence)(seq, args.out)
    t_total = time.perf_counter() - t0
    result = {"preset": cfg.preset, "out": str(summary.root), "frames": summary.frames,
              "imu_samples": summary.imu_samples, "duration_s": summary.duration_s,
              "path_length_m": round(summary.path_length_m, 3), "width": cfg.camera.width,
              "height": cfg.camera.height, "K": list(seq.K), "baseline": cfg.camera.baseline,
              "seed": cfg.seed, "scene_build_s": round(t_build, 3), "total_s": round(t_total, 3)}
    if args.json:
        print(json.dumps(result))
        return 0
    print(f"{cfg.preset}: {summary.frames} frames {cfg.camera.width}x{cfg.camera.height}, "
          f"{summary.imu_samples} IMU samples, {summary.duration_s:.2f} s, path {summary.path_length_m:.1f} m")
    print(f"  wrote {summary.root}/mav0 in {t_total:.1f} s (scene build {t_build:.1f} s)")
    return 0
