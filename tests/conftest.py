"""Shared pytest fixtures."""

from pathlib import Path

import pytest

REPO_ROOT = Path(__file__).resolve().parents[1]
SHARED_DATA = REPO_ROOT.parent / "shared" / "data"
SHARED_REFERENCE = REPO_ROOT.parent / "shared" / "reference"


# The tests whose figures come from floating-point computations that another CPU's kernels round
# differently: real-data runs, the official-network references, loop closure and determinism. CI runs
# them a second time under tools/old-cpu.env (pytest -m numerical), so that a bound that holds on one
# CPU's last bits only fails before it lands.
NUMERICAL_FIXTURES = frozenset({"shared_data", "shared_reference", "room_loop_clip", "room_loop_rgbd_both"})
NUMERICAL_MODULES = frozenset({"test_determinism", "test_dense_loop", "test_patch_loop", "test_loop_closure",
                               "test_imu_loops", "test_nets_reference", "test_input_knife_edges"})


# The files whose tests take longest (pytest's --durations on CI, longest first: their module fixtures run
# whole loop clips). The suite runs on two worker processes, a file on one of them (pyproject.toml,
# addopts); these start first, so that none of them is what the other worker waits for at the end.
LONGEST_FIRST = ("test_dense_loop", "test_patch_loop", "test_maps", "test_determinism", "test_imu_families",
                 "test_dense_global_bg", "test_imu_runs", "test_loop_closure", "test_colmap_compare", "test_patch_rejoin")


# Files whose tests share a session fixture that takes long to build: each group runs on one worker, so the
# fixture is built once (xdist's loadfile unit is otherwise one file). test_determinism compares its runs
# against room_loop_rgbd_both, which test_patch_loop also checks (about 35 s a build).
SAME_WORKER = {"tests/test_determinism.py": "tests/test_patch_loop.py"}


def pytest_xdist_make_scheduler(config, log):
    """Under ``--dist loadfile`` (pyproject.toml, addopts): xdist's file scheduling with the files of
    ``SAME_WORKER`` joined to one unit. Other modes keep xdist's own scheduler."""
    if config.getvalue("dist") != "loadfile":
        return None
    from xdist.scheduler import LoadFileScheduling

    class _JoinedFileScheduling(LoadFileScheduling):
        def _split_scope(self, nodeid: str) -> str:
            scope = super()._split_scope(nodeid)
            return SAME_WORKER.get(scope, scope)

    return _JoinedFileScheduling(config, log)


def _module_name(item) -> str:
    return getattr(getattr(item, "module", None), "__name__", "").rsplit(".", 1)[-1]


def pytest_collection_modifyitems(config, items):
    """Mark the numerical tests (above) ``numerical``; put the files of ``LONGEST_FIRST`` first, in that
    order (the others keep theirs)."""
    for item in items:
        if NUMERICAL_FIXTURES.intersection(getattr(item, "fixturenames", ())) or _module_name(item) in NUMERICAL_MODULES:
            item.add_marker(pytest.mark.numerical)
    rank = {name: i for i, name in enumerate(LONGEST_FIRST)}
    items.sort(key=lambda item: rank.get(_module_name(item), len(rank)))  # stable: the rest keep their order


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """The read-only real data folder ``../shared/data``; skips the test when it is absent."""
    if not SHARED_DATA.is_dir():
        pytest.skip(f"real test data not found at {SHARED_DATA} (CI provides it; a fresh clone does not)")
    return SHARED_DATA


@pytest.fixture(scope="session")
def shared_reference() -> Path:
    """The read-only official network outputs ``../shared/reference`` (README there); skips the test
    when absent."""
    if not (SHARED_REFERENCE / "droid_official.npz").is_file():
        pytest.skip(f"official network reference outputs not found at {SHARED_REFERENCE} (CI provides them; "
                    "a fresh clone does not)")
    return SHARED_REFERENCE


@pytest.fixture(scope="session")
def repo_root() -> Path:
    return REPO_ROOT


@pytest.fixture(scope="session")
def room_loop_clip(tmp_path_factory):
    """``clip(rate_hz, extra_frames)``: the room-loop clip (320x240) rendered at ``rate_hz`` once round
    the room and ``extra_frames`` on past its start, as (dataset root, SynthSequence). Rendered once per
    session for the loop-closure tests that run on it (test_patch_loop, test_determinism,
    test_dense_loop); read only."""
    clips = {}

    def clip(rate_hz: float, extra_frames: int):
        if (rate_hz, extra_frames) not in clips:
            from fgslam.io.synth import SynthSequence, write_sequence
            from fgslam.io.synth.scenarios import load_synth_config

            cfg = load_synth_config("room-loop", overrides=[f"camera.rate_hz={rate_hz}", "camera.width=320",
                                                            "camera.height=240"])
            cfg.frames = int(round(cfg.loop_duration_s() * rate_hz)) + 1 + extra_frames
            seq = SynthSequence(cfg)
            root = tmp_path_factory.mktemp("room_loop") / "seq"
            write_sequence(seq, root)
            clips[rate_hz, extra_frames] = root, seq
        return clips[rate_hz, extra_frames]

    return clip


@pytest.fixture(scope="session")
def room_loop_rgbd_both(room_loop_clip, tmp_path_factory):
    """The RGB-D run of the 4 Hz room loop (19 frames past the return) with loop closure ``both`` in
    its worker threads and process (the default), as (output folder, summary.json). One run for two
    claims: the reference of test_determinism's byte comparison, and test_patch_loop's RGB-D loop
    closure against the run without."""
    import json

    from fgslam.io.run_files import SUMMARY_FILE
    from fgslam.run.prepare import open_slam_dataset
    from fgslam.run.runner import run_slam
    from patch_support import room_loop_slam_config

    root, _ = room_loop_clip(4.0, 19)
    cfg = room_loop_slam_config("both", sensor="rgbd", threaded=True)
    folder = tmp_path_factory.mktemp("room_loop_rgbd_both")
    run_slam(open_slam_dataset(root, cfg), cfg, folder, progress=False)
    return folder, json.loads((folder / SUMMARY_FILE).read_text())


@pytest.fixture(scope="session")
def depth_room(tmp_path_factory):
    """The RGB-D room clip of the depth-alignment tests of the three families (tests/depth_support.py)."""
    from depth_support import render_depth_room

    return render_depth_room(tmp_path_factory)


# the KITTI clip as a video (live input: tests/test_live.py, examples/live_camera.py)
CLIP_FRAMES = 40
CLIP_RATE_HZ = 10.0
_KITTI_K = (718.856, 718.856, 607.1928, 185.2157)
_WIDTH_MULTIPLE = 16  # the MJPG writer keeps widths of a multiple of 16: the clip is cropped to one


@pytest.fixture(scope="session")
def video_clip(shared_data, tmp_path_factory):
    """KITTI 00's first frames as an MJPG video at 10 Hz with its calibration YAML beside it."""
    import cv2
    import numpy as np

    folder = tmp_path_factory.mktemp("live")
    images = sorted((shared_data / "kitti00_0-199" / "image_0").glob("*.png"))[:CLIP_FRAMES]
    first = cv2.imread(str(images[0]))
    height, width = first.shape[0], first.shape[1] // _WIDTH_MULTIPLE * _WIDTH_MULTIPLE
    path = folder / "drive.avi"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), CLIP_RATE_HZ, (width, height))
    for image in images:
        writer.write(np.ascontiguousarray(cv2.imread(str(image))[:, :width]))
    writer.release()
    fx, fy, cx, cy = _KITTI_K
    (folder / "drive.yaml").write_text(f"width: {width}\nheight: {height}\nintrinsics: [{fx}, {fy}, {cx}, {cy}]\n")
    return path


@pytest.fixture
def noise_images():
    """``make(folder, n)``: an image folder of ``n`` 320x240 grey noise images (seeded) with its
    ``calibration.yaml``: a sequence that loads but on which no SLAM run initialises."""
    def make(folder: Path, n: int) -> Path:
        import cv2
        import numpy as np

        folder.mkdir(parents=True)
        rng = np.random.default_rng(0)
        for i in range(n):
            cv2.imwrite(str(folder / f"{i:04d}.png"), (rng.random((240, 320)) * 255).astype(np.uint8))
        (folder / "calibration.yaml").write_text("width: 320\nheight: 240\nintrinsics: [256, 256, 160, 120]\n")
        return folder

    return make
