"""Shared helpers of the patch-frontend tests (importable because pytest puts tests/ on the path)."""

from fgslam.frontends.patch import PatchConfig


def light_patch_config(keyframe_threshold: float = 8.0) -> PatchConfig:
    """A lighter patch graph than the defaults, for small synthetic images (keeps the tests fast).

    ``keyframe_threshold`` is the mean-flow keyframe threshold in pixels, scaled down from the
    640-px default with the test images' width (8 px for 320 px, 6 px for 200 px).
    """
    cfg = PatchConfig()
    cfg.graph.patches_per_frame = 64
    cfg.graph.patch_lifetime = 5
    cfg.graph.removal_window = 9
    cfg.graph.optimization_window = 5
    cfg.tracking.keyframe_index = 2
    cfg.tracking.keyframe_threshold = keyframe_threshold
    return cfg


_RENDERED: dict = {}  # (tmp_path_factory, overrides) -> root: each clip rendered once per session


def render_room(tmp_path_factory, name: str, overrides: list[str]):
    """Render a synthetic room-loop clip (``load_synth_config`` overrides) into a fresh temp folder, once
    per session: the tests that ask for the same overrides share the folder (they only read it)."""
    from fgslam.io.synth import SynthSequence, write_sequence
    from fgslam.io.synth.scenarios import load_synth_config

    key = (id(tmp_path_factory), tuple(overrides))
    if key not in _RENDERED:
        root = tmp_path_factory.mktemp(name)
        write_sequence(SynthSequence(load_synth_config("room-loop", overrides=overrides)), root)
        _RENDERED[key] = root
    return _RENDERED[key]


def room_loop_slam_config(mode: str, sensor: str = "mono", threaded: bool = False):
    """The run config of the loop-closure tests on the 4 Hz room loop: the light patch graph, loop
    closure ``mode`` (``threaded``: in its worker threads and process, else synchronously), no plots."""
    from fgslam.loop.closure import LoopClosureConfig
    from fgslam.run.config import SlamConfig

    cfg = SlamConfig(sensor=sensor, patch=light_patch_config())
    cfg.loop_closure = LoopClosureConfig(mode=mode, run_in_thread=threaded)
    cfg.output.plot = False
    cfg.validate()
    return cfg


def open_frames(root, mode: str):
    """The dataset at ``root`` opened for sensor ``mode`` (right images for stereo, depth for RGB-D)
    and its frames as a list."""
    from fgslam.io.datasets import DatasetConfig, open_dataset

    ds = open_dataset(root, config=DatasetConfig(load_right=mode == "stereo", load_depth=mode == "rgbd", load_imu=False))
    return ds, list(ds)
