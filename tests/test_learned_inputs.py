"""What reaches the learned networks: the official pipelines' inputs (docs/architecture.md section 15).

Both official pipelines read frames with ``cv2.imread`` (colour, BGR). DROID-SLAM flips to RGB, divides
by 255 and applies the ImageNet mean and std; DPVO feeds BGR as read, mapped to ``2 x / 255 - 0.5``. A
grey file is read as its grey value in all three channels. Here a colour file and a grey file go
through fgslam's loader, the run's dataset settings and the frontends' source routing, and the tensor
that enters each network's first convolution is compared with that mapping, computed from the file's
BGR pixels."""

from __future__ import annotations

from types import SimpleNamespace

import cv2
import numpy as np
import pytest
import torch
import yaml

from fgslam.frontends.dense.state import DenseState
from fgslam.frontends.dense.source import DenseSourceConfig, make_dense_source
from fgslam.frontends.patch import PatchConfig, make_source
from fgslam.frontends.patch.patches import PatchMeasurer
from fgslam.io.datasets import open_dataset
from fgslam.run.config import dataset_config_for, load_slam_config
from nets_support import official_dpvo_file, official_droid_file
from nets_support import one_thread  # noqa: F401 (autouse fixture)

H, W = 64, 96  # DROID: multiples of 8, at least 64
IMAGENET_MEAN = np.array([0.485, 0.456, 0.406])  # the official RGB statistics, written out independently
IMAGENET_STD = np.array([0.229, 0.224, 0.225])


@pytest.fixture(scope="module")
def ckpts(tmp_path_factory):
    root = tmp_path_factory.mktemp("ckpt")
    torch.save(official_droid_file(seed=1), root / "droid.pth")
    torch.save(official_dpvo_file(seed=2), root / "dpvo.pth")
    return root


def _write_folder(root, image: np.ndarray) -> None:
    root.mkdir(parents=True)
    assert cv2.imwrite(str(root / "img_0000.png"), image)  # cv2 writes BGR (or grey) as given
    (root / "calibration.yaml").write_text(yaml.safe_dump(
        {"width": W, "height": H, "intrinsics": [50.0, 50.0, W / 2, H / 2], "rate_hz": 10}))


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    """A colour file whose three channels differ everywhere, and a grey file: (root, BGR pixels)."""
    rng = np.random.default_rng(3)
    bgr = rng.integers(0, 256, (H, W, 3), dtype=np.uint8)
    bgr[..., 0] = np.minimum(bgr[..., 0], 80)  # blue low, red high: a flip moves every pixel
    bgr[..., 2] = np.maximum(bgr[..., 2], 170)
    grey = rng.integers(0, 256, (H, W), dtype=np.uint8)
    root = tmp_path_factory.mktemp("inputs")
    _write_folder(root / "colour", bgr)
    _write_folder(root / "grey", grey)
    return {"colour": (root / "colour", bgr), "grey": (root / "grey", np.repeat(grey[..., None], 3, -1))}


def _first_frame(root, overrides):
    config = load_slam_config(None, overrides)
    return open_dataset(root, "folder", dataset_config_for(config))[0]


def _capture(module: torch.nn.Module) -> list:
    seen = []
    module.register_forward_pre_hook(lambda _m, args: seen.append(args[0].detach().clone()))
    return seen


def _droid_expected(bgr: np.ndarray) -> torch.Tensor:
    rgb = bgr[..., ::-1].astype(np.float64) / 255.0
    return torch.from_numpy(((rgb - IMAGENET_MEAN) / IMAGENET_STD).transpose(2, 0, 1)[None].copy()).float()


def _dpvo_expected(bgr: np.ndarray) -> torch.Tensor:
    return torch.from_numpy((2.0 * (bgr.astype(np.float64) / 255.0) - 0.5).transpose(2, 0, 1)[None].copy()).float()


@pytest.mark.parametrize("kind", ["colour", "grey"])
def test_droid_source_gets_rgb_with_imagenet_normalisation(ckpts, files, kind):
    root, bgr = files[kind]
    checkpoint = str(ckpts / "droid.pth")
    frame = _first_frame(root, ["frontend=dense", "dense.source.kind=droid", f"dense.source.checkpoint={checkpoint}"])
    assert (frame.rgb is not None) == (kind == "colour")  # the learned run loads colour; a grey file has none
    source = make_dense_source(DenseSourceConfig(kind="droid", checkpoint=checkpoint))
    fnet_in, cnet_in = _capture(source._runner.net.fnet), _capture(source._runner.net.cnet)
    # the dense frontend's routing (its crop is the whole 64 x 96 image here)
    stub = SimpleNamespace(source=source, crop=(H, W), cropped=lambda image: DenseState.cropped(stub, image))
    source.add_frame(0, DenseState.source_image(stub, frame))
    expected = _droid_expected(bgr)
    torch.testing.assert_close(fnet_in[0], expected, rtol=0, atol=1e-5)
    torch.testing.assert_close(cnet_in[0], expected, rtol=0, atol=1e-5)
    if kind == "colour":  # BGR fed as it is would be another input
        assert (fnet_in[0] - _droid_expected(bgr[..., ::-1])).abs().max() > 1.0


@pytest.mark.parametrize("kind", ["colour", "grey"])
def test_dpvo_source_gets_bgr_mapped_to_its_range(ckpts, files, kind):
    root, bgr = files[kind]
    checkpoint = str(ckpts / "dpvo.pth")
    frame = _first_frame(root, ["frontend=patch", "patch.source=dpvo", f"patch.checkpoint={checkpoint}"])
    assert (frame.rgb is not None) == (kind == "colour")
    source = make_source(PatchConfig(source="dpvo", checkpoint=checkpoint))
    patchify = source._runner.net.patchify
    fnet_in, inet_in = _capture(patchify.fnet), _capture(patchify.inet)
    state = SimpleNamespace(source=source, sensor_mode="mono", times={"flow": 0.0})
    feats, _ = PatchMeasurer(state).prepare(frame)  # the patch frontend's routing
    expected = _dpvo_expected(bgr)
    torch.testing.assert_close(fnet_in[0], expected, rtol=0, atol=1e-6)
    torch.testing.assert_close(inet_in[0], expected, rtol=0, atol=1e-6)
    if kind == "colour":
        assert (fnet_in[0] - _dpvo_expected(bgr[..., ::-1])).abs().max() > 1.0
        np.testing.assert_array_equal(source.pack(feats), frame.rgb)  # loop edges recompute from the colour image


def test_built_in_sources_keep_the_grey_image_and_load_no_colour(files):
    root, _ = files["colour"]
    for overrides in (["frontend=dense"], ["frontend=patch"]):
        frame = _first_frame(root, overrides)
        assert frame.rgb is None  # the built-in runs do not decode colour (no PLY output)
    config = load_slam_config(None, ["frontend=patch", "output.write_ply=true"])
    assert dataset_config_for(config).load_rgb
    assert not make_source(PatchConfig()).colour and not make_dense_source(DenseSourceConfig()).colour
