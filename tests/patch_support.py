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
