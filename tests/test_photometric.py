"""The gain model of the built-in sources (``photometric: gain``) and the dataset's width cap
(``dataset.max_width``, the dense family at KITTI size): a gain of an image cancels, and Lucas-Kanade
keeps a track through an auto-exposure step that brightness constancy loses."""

import numpy as np
import pytest

from fgslam.core.errors import ConfigError
from fgslam.frontends.flow import DenseFlowConfig
from fgslam.frontends.patch.config import LKConfig
from fgslam.frontends.patch.lk import LKSource
from fgslam.frontends.photometric import BrightnessModel
from fgslam.io.datasets.common import DatasetConfig
from fgslam.run.config import load_slam_config

SIZE = 160
SHIFT = np.array([2.6, -1.8])   # px: the second image is the first moved by this
GAIN = 1.3                      # an auto-exposure step: both images stay inside 0..255


def _texture(seed: int = 0) -> np.ndarray:
    """Smooth random texture in 60..190 grey levels (room for the gain without clipping)."""
    import cv2

    rng = np.random.default_rng(seed)
    noise = cv2.GaussianBlur(rng.normal(0, 1, (SIZE, SIZE)).astype(np.float32), (0, 0), 2.0)
    return 60.0 + 130.0 * (noise - noise.min()) / (noise.max() - noise.min())


def _shifted(image: np.ndarray, shift: np.ndarray) -> np.ndarray:
    import cv2

    M = np.float32([[1, 0, shift[0]], [0, 1, shift[1]]])
    return cv2.warpAffine(image.astype(np.float32), M, (SIZE, SIZE), flags=cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT)


def test_a_gain_of_the_image_cancels_and_the_first_image_is_kept():
    base = _texture().astype(np.uint8)
    model = BrightnessModel("gain", floor=4.0)
    first = model(base)
    assert np.abs(first.astype(int) - base).max() == 0  # the first image sets the reference
    later = model(np.clip(_texture() * GAIN, 0, 255).astype(np.uint8)).astype(int)
    assert np.abs(later - base).max() <= 2  # rounding of the 8-bit inputs only
    raw = BrightnessModel("raw", floor=4.0)
    assert raw(base) is base


def test_the_floor_bounds_the_gain_of_a_nearly_black_image():
    model = BrightnessModel("gain", floor=4.0)
    model(np.full((8, 8), 100, np.uint8))
    dark = np.zeros((8, 8), np.uint8)
    dark[0, 0] = 2
    out = model(dark)
    assert int(out.max()) <= round(2 * 104 / 4.0) and int(out.min()) == 0


@pytest.mark.parametrize("model", ["raw", "gain"])
def test_lucas_kanade_keeps_the_track_through_an_exposure_step_only_with_the_gain_model(model):
    src_img = _texture().astype(np.uint8)
    tgt_img = np.clip(_shifted(_texture(), SHIFT) * GAIN, 0, 255).astype(np.uint8)
    lk = LKSource(LKConfig(scale=1.0, photometric=model), window=21)
    src, tgt = lk.prepare(src_img), lk.prepare(tgt_img)
    grid = np.stack(np.meshgrid(np.arange(40, 121, 20), np.arange(40, 121, 20)), -1).reshape(-1, 2).astype(np.float64)
    m = lk.measure(src, tgt, grid, grid)
    good = m.confidence > 0
    if model == "raw":  # the photometric confidence (error_sigma 12 grey levels) falls for every track
        assert m.confidence.max() < 0.4
    else:
        assert good.all() and m.confidence.min() > 0.5
        assert np.abs(m.uv - (grid + SHIFT)).max() < 0.2


def test_the_photometric_model_is_a_checked_config_key():
    assert load_slam_config("driving_stereo", []).patch.lk.photometric == "gain"
    assert load_slam_config("dense_stereo", []).dense.source.flow.photometric == "gain"
    assert DenseFlowConfig().photometric == "raw" and LKConfig().photometric == "raw"
    with pytest.raises(ConfigError, match="patch.lk.photometric"):
        load_slam_config("patch_mono", ["patch.lk.photometric=global"])
    with pytest.raises(ConfigError, match="dense.source.flow.photometric"):
        load_slam_config("dense_mono", ["dense.source.flow.photometric=affine"])


def test_max_width_scales_wider_outputs_down_and_keeps_narrower_ones():
    cfg = DatasetConfig(max_width=640)
    assert cfg.output_size(1241, 376) == (640, 194)
    assert cfg.output_size(752, 480) == (640, 409)
    assert cfg.output_size(640, 480) == (640, 480)
    assert DatasetConfig(max_width=640, resize_scale=2.0).output_size(640, 480) == (640, 480)
    assert DatasetConfig().output_size(1241, 376) == (1241, 376)
    assert "dataset.max_width=640" in cfg.resize_text()
    assert load_slam_config("dense_stereo", []).dataset.max_width == 640
