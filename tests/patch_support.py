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


def render_room(tmp_path_factory, name: str, overrides: list[str]):
    """Render a synthetic room-loop clip (``load_synth_config`` overrides) into a fresh temp folder."""
    from fgslam.io.synth import SynthSequence, write_sequence
    from fgslam.io.synth.scenarios import load_synth_config

    root = tmp_path_factory.mktemp(name)
    write_sequence(SynthSequence(load_synth_config("room-loop", overrides=overrides)), root)
    return root


def open_frames(root, mode: str):
    """The dataset at ``root`` opened for sensor ``mode`` (right images for stereo, depth for RGB-D)
    and its frames as a list."""
    from fgslam.io.datasets import DatasetConfig, open_dataset

    ds = open_dataset(root, config=DatasetConfig(load_right=mode == "stereo", load_depth=mode == "rgbd", load_imu=False))
    return ds, list(ds)
