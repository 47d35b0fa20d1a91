"""Live SLAM from a camera: any OpenCV capture (a webcam, a video device, an RTSP or HTTP stream, a file).

    python examples/live_camera.py camera:0 --calibration my_camera.yaml --preset handheld_mono

The calibration YAML has ``width``, ``height``, ``intrinsics: [fx, fy, cx, cy]`` and, when the lens
distorts, ``distortion_model`` and ``distortion`` (OpenCV's order). Frames come at the camera's pace;
when SLAM is slower the oldest waiting frame is dropped, so the pose you read is always recent.
Ctrl-C stops; the trajectory so far is written to ``--out``.
"""

from __future__ import annotations

import argparse
import time

import fgslam

MS_PER_S = 1000.0


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("source", help="camera:0, camera:rtsp://..., or camera:PATH/TO/VIDEO")
    parser.add_argument("--calibration", required=True, help="calibration YAML of the camera")
    parser.add_argument("--preset", default="handheld_mono", help="preset name (fgslam run --help lists them)")
    parser.add_argument("--frames", type=int, default=None, help="stop after this many frames (default: Ctrl-C)")
    parser.add_argument("--speed", type=float, default=1.0, help="a video file replays at this many times its rate")
    parser.add_argument("--queue", type=int, default=1, help="frames waiting at most before the oldest is dropped")
    parser.add_argument("--out", default="live_trajectory.txt", help="where to write the trajectory")
    args = parser.parse_args()

    overrides = {"dataset.calibration_file": args.calibration}
    if args.frames is not None:
        overrides["dataset.end"] = args.frames
    capture = fgslam.open_dataset(args.source, args.preset, overrides=overrides)
    slam = fgslam.Slam.from_preset(args.preset, capture.camera, overrides=overrides, keep_frames=False)  # no save_map
    live = fgslam.LiveFrames(capture, fgslam.LiveConfig(speed=args.speed, queue=args.queue))
    stopped = False
    try:
        for frame in live:
            result = slam.track_frame(frame)
            latency_ms = MS_PER_S * (time.perf_counter() - live.arrival_s[frame.index])
            if result.index % 10 == 0:
                pose = "no pose yet" if result.T_WC is None else " ".join(f"{v:+.2f}" for v in result.T_WC[:3, 3])
                print(f"frame {result.index:5d}  {result.status:<12} {pose}  latency {latency_ms:4.0f} ms  "
                      f"dropped {live.dropped}")
    except KeyboardInterrupt:  # a frame may have been cut short: no final optimisation, the per-frame poses
        print("stopping")
        stopped = True
        slam.abort()
    if not len(slam.trajectory()):
        raise SystemExit(f"no pose in {live.delivered} frames: nothing to write")
    trajectory = slam.trajectory() if stopped else slam.finish()
    trajectory.write(args.out, "tum")  # t tx ty tz qx qy qz qw, camera-to-world
    print(f"{len(trajectory)} poses ({live.delivered} frames tracked, {live.dropped} dropped): {args.out}")


if __name__ == "__main__":
    main()
