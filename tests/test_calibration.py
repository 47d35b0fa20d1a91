"""Tests of fgslam.io.calibration (Calibration validation/YAML) and fgslam.io.undistort (the OpenCV Undistorter)."""

import re

import cv2
import numpy as np
import pytest
import yaml

from fgslam.core.errors import DataError
from fgslam.io.calibration import Calibration
from fgslam.io.undistort import Undistorter

W, H = 320, 240
K_RAW = [260.0, 255.0, 161.3, 118.7]
RADTAN = [-0.28, 0.07, 0.0008, -0.0005]
EQUI = [0.05, -0.01, 0.004, -0.001]


def _project_raw(X, calib, rvec=np.zeros(3), tvec=np.zeros(3)):
    """Raw (distorted) pixels of points X (N,3) given in the frame (rvec,tvec) maps from."""
    pts = np.asarray(X, dtype=np.float64).reshape(-1, 1, 3)
    D = np.zeros(4) if calib.distortion_model == "none" else calib.distortion
    if calib.distortion_model == "equidistant":
        uv, _ = cv2.fisheye.projectPoints(pts, rvec.reshape(3, 1), tvec.reshape(3, 1), calib.K_matrix(), D)
    else:
        uv, _ = cv2.projectPoints(pts, rvec, tvec, calib.K_matrix(), D)
    return uv.reshape(-1, 2)


def _pinhole(X, K):
    X = np.asarray(X, dtype=np.float64).reshape(-1, 3)
    return np.stack([K[0] * X[:, 0] / X[:, 2] + K[2], K[1] * X[:, 1] / X[:, 2] + K[3]], axis=1)


def _render_distorted(calib, pattern, K_ideal):
    """Raw image whose pixel (u, v) shows ``pattern`` at the ideal pinhole pixel of its ray."""
    u, v = np.meshgrid(np.arange(calib.width, dtype=np.float64), np.arange(calib.height, dtype=np.float64))
    pts = np.stack([u.ravel(), v.ravel()], axis=1).reshape(-1, 1, 2)
    if calib.distortion_model == "equidistant":
        und = cv2.fisheye.undistortPoints(pts, calib.K_matrix(), calib.distortion, P=np.array(
            [[K_ideal[0], 0, K_ideal[2]], [0, K_ideal[1], K_ideal[3]], [0, 0, 1]]))
    else:
        und = cv2.undistortPoints(pts, calib.K_matrix(), calib.distortion, P=np.array(
            [[K_ideal[0], 0, K_ideal[2]], [0, K_ideal[1], K_ideal[3]], [0, 0, 1]]))
    und = und.reshape(calib.height, calib.width, 2)
    return pattern(und[..., 0], und[..., 1]).astype(np.uint8)


def _edge_columns(img, threshold=128):
    """For each row, columns where the stripe image changes from dark to bright."""
    b = img > threshold
    rows = []
    for r in range(img.shape[0]):
        rows.append(np.flatnonzero(~b[r, :-1] & b[r, 1:]))
    return rows


@pytest.mark.parametrize("model,coeffs", [("radtan", RADTAN), ("equidistant", EQUI)])
def test_distorted_grid_becomes_straight(model, coeffs):
    calib = Calibration(W, H, K_RAW, model, coeffs).validate()
    und = Undistorter(calib, alpha=0.0)
    out = und.calibration
    period = 0.1  # stripes of constant normalised x: straight vertical lines in a pinhole image

    def stripes(u, v):
        x = (u - out.K[2]) / out.K[0]
        return np.where(np.floor(x / period) % 2 == 0, 30, 220)

    raw = _render_distorted(calib, stripes, out.K)
    img = und.left(raw)
    assert img.shape == (out.height, out.width)
    # expected edge columns: x = k * period (dark for floor even -> bright at odd boundaries)
    margin = 6
    edges_out = _edge_columns(img[margin:-margin, :])
    edges_raw = _edge_columns(raw[margin:-margin, :])
    spread_out = _column_spread(edges_out)
    spread_raw = _column_spread(edges_raw)
    assert spread_out <= 1.0, f"undistorted stripes still bend by {spread_out} px"
    if model == "radtan":
        assert spread_raw >= 5.0, "the raw stripes should be visibly curved"
    # and the edges sit where the output pinhole model puts them
    first = edges_out[len(edges_out) // 2]
    for c in first:
        x = (c + 0.5 - out.K[2]) / out.K[0]
        assert abs(x / period - round(x / period)) * period * out.K[0] < 1.0


def _column_spread(edges_per_row):
    """Largest across-rows range of the column of the same edge (edges matched by order)."""
    counts = [len(e) for e in edges_per_row]
    n = max(set(counts), key=counts.count)
    cols = np.array([e for e in edges_per_row if len(e) == n], dtype=np.float64)
    return float((cols.max(axis=0) - cols.min(axis=0)).max())


@pytest.mark.parametrize("model,coeffs", [("none", []), ("radtan", RADTAN), ("equidistant", EQUI)])
def test_resize_crop_keeps_projection_consistent(model, coeffs):
    calib = Calibration(W, H, K_RAW, model, coeffs).validate()
    und = Undistorter(calib, out_size=(203, 157), crop_multiple=8)
    out = und.calibration
    assert (out.width, out.height) == (200, 152)
    assert out.width % 8 == 0 and out.height % 8 == 0
    rng = np.random.default_rng(3)
    X = np.column_stack([rng.uniform(-0.3, 0.3, 20), rng.uniform(-0.2, 0.2, 20), rng.uniform(1.5, 3.0, 20)])
    uv_raw = _project_raw(X, calib)
    # points: raw pixel -> output pixel equals pinhole projection with the output intrinsics
    np.testing.assert_allclose(und.points(uv_raw), _pinhole(X, out.K), atol=2e-3)
    # images: a bright blob at the raw projection of one point lands at its output projection
    Xp = np.array([[0.12, -0.07, 2.0]])
    u0, v0 = _project_raw(Xp, calib)[0]
    uu, vv = np.meshgrid(np.arange(W), np.arange(H))
    blob = 255 * np.exp(-((uu - u0) ** 2 + (vv - v0) ** 2) / (2 * 3.0**2))
    img = und.left(blob.astype(np.float32))
    w = np.clip(img - 0.05 * img.max(), 0, None)
    vv2, uu2 = np.mgrid[0 : img.shape[0], 0 : img.shape[1]]
    found = np.array([(w * uu2).sum() / w.sum(), (w * vv2).sum() / w.sum()])
    np.testing.assert_allclose(found, _pinhole(Xp, out.K)[0], atol=0.25)


def test_resized_and_cropped_intrinsics():
    calib = Calibration(640, 480, [500, 510, 319.5, 239.5]).validate()
    half = calib.resized(320, 240)
    np.testing.assert_allclose(half.K, [250, 255, 159.5, 119.5])
    crop = calib.cropped(4, 6, 632, 472)
    np.testing.assert_allclose(crop.K, [500, 510, 315.5, 233.5])
    assert (crop.width, crop.height) == (632, 472)


def test_identity_undistorter_only_crops():
    calib = Calibration(101, 50, [80, 80, 50, 25]).validate()
    und = Undistorter(calib, crop_multiple=8)
    img = np.arange(50 * 101, dtype=np.uint16).reshape(50, 101).astype(np.uint8)
    out = und.left(img)
    assert out.shape == (48, 96)
    x0, y0 = und.crop_offset
    np.testing.assert_array_equal(out, img[y0 : y0 + 48, x0 : x0 + 96])
    np.testing.assert_allclose(und.calibration.K, [80, 80, 50 - x0, 25 - y0])


def _stereo_rig(model, coeffs):
    R_LR = cv2.Rodrigues(np.array([0.01, -0.02, 0.015]))[0]
    T_CLCR = np.eye(4)
    T_CLCR[:3, :3] = R_LR
    T_CLCR[:3, 3] = [0.11, 0.002, -0.001]
    right = Calibration(W, H, [258.0, 257.0, 158.0, 121.0], model, coeffs)
    return Calibration(W, H, K_RAW, model, coeffs, T_BC=np.eye(4), right=right, T_CLCR=T_CLCR).validate(), T_CLCR


@pytest.mark.parametrize("model,coeffs", [("radtan", RADTAN), ("equidistant", EQUI)])
def test_stereo_rectification_rows_and_disparity(model, coeffs):
    calib, T_CLCR = _stereo_rig(model, coeffs)
    und = Undistorter(calib, rectify=True)
    out = und.calibration
    assert out.has_stereo and out.distortion_model == "none"
    np.testing.assert_allclose(out.T_CLCR[:3, :3], np.eye(3), atol=1e-12)
    assert abs(out.baseline - np.linalg.norm(T_CLCR[:3, 3])) < 1e-6
    rng = np.random.default_rng(5)
    X_L = np.column_stack([rng.uniform(-0.4, 0.4, 15), rng.uniform(-0.3, 0.3, 15), rng.uniform(2, 4, 15)])
    T_CRCL = np.linalg.inv(T_CLCR)
    X_R = X_L @ T_CRCL[:3, :3].T + T_CRCL[:3, 3]
    uvL = und.points(_project_raw(X_L, calib))
    uvR = und.points(_project_raw(X_R, calib.right), right=True)
    np.testing.assert_allclose(uvL[:, 1], uvR[:, 1], atol=5e-3)  # same rows
    # disparity = fx * b / z with z in the rectified left frame
    X_out = (np.linalg.inv(und.T_C_Cout) @ np.column_stack([X_L, np.ones(15)]).T).T[:, :3]
    np.testing.assert_allclose(uvL[:, 0] - uvR[:, 0], out.K[0] * out.baseline / X_out[:, 2], atol=5e-3)
    np.testing.assert_allclose(uvL, _pinhole(X_out, out.K), atol=5e-3)
    # T_BC follows the rectified camera
    np.testing.assert_allclose(out.T_BC, calib.T_BC @ und.T_C_Cout)


def test_rectified_depth_is_z_in_output_frame():
    calib, _ = _stereo_rig("none", [])
    und = Undistorter(calib, rectify=True, crop_multiple=1)
    out = und.calibration
    # a fronto-parallel plane z_raw = 2 in the raw left frame
    depth_raw = np.full((H, W), 2.0, dtype=np.float32)
    d = und.depth(depth_raw)
    R1 = und.T_C_Cout[:3, :3].T  # X_out = R1 X_raw
    v, u = 120, 200
    ray_out = np.array([(u - out.K[2]) / out.K[0], (v - out.K[3]) / out.K[1], 1.0])
    ray_raw = R1.T @ ray_out
    X_out = ray_out * (2.0 / ray_raw[2])
    assert d[v, u] == pytest.approx(X_out[2], rel=1e-5)


def test_calibration_yaml_roundtrip_and_errors(tmp_path):
    calib, _ = _stereo_rig("radtan", RADTAN)
    path = tmp_path / "calib.yaml"
    path.write_text(yaml.safe_dump(calib.to_dict()))
    back = Calibration.from_yaml(path)
    np.testing.assert_allclose(back.K, calib.K)
    np.testing.assert_allclose(back.right.distortion, calib.right.distortion)
    np.testing.assert_allclose(back.T_CLCR, calib.T_CLCR)
    bad = {"width": 10, "height": 10, "intrinsics": [1, 1, 5, 5], "distortion_model": "radtan", "distortion": [0.1]}
    path.write_text(yaml.safe_dump(bad))
    with pytest.raises(DataError, match=r"calib\.yaml.*radtan needs 4 or 5"):
        Calibration.from_yaml(path)
    path.write_text(yaml.safe_dump({"width": 10, "height": 10, "intrinsics": [1, 1, 5, 5], "focal": 3}))
    with pytest.raises(DataError, match="unknown calibration key 'focal'"):
        Calibration.from_yaml(path)
    path.write_text(yaml.safe_dump({"width": 10, "intrinsics": [1, 1, 5, 5]}))
    with pytest.raises(DataError, match="missing calibration key 'height'"):
        Calibration.from_yaml(path)
    with pytest.raises(DataError, match="T_CLCR"):
        Calibration(10, 10, [1, 1, 5, 5], right=Calibration(10, 10, [1, 1, 5, 5])).validate()
    T = np.eye(4)
    T[0, 0] = 2.0
    with pytest.raises(DataError, match="T_BC .*not a rotation"):
        Calibration(10, 10, [1, 1, 5, 5], T_BC=T).validate()
    with pytest.raises(DataError, match="does not match the calibration"):
        Calibration(10, 10, [1, 1, 5, 5]).check_image_size(12, 10, "img.png")


def test_calibration_files_are_read_as_utf8_with_the_config_files_messages(tmp_path):
    """A calibration is read by the one UTF-8 YAML reader (fgslam.core.config.read_yaml): a binary file is one
    line saying so (a DataError: the file is the dataset's), and a UTF-8 file reads the same under a C locale."""
    import os
    import subprocess
    import sys

    binary = tmp_path / "calibration.yaml"
    binary.write_bytes(bytes(range(256)))
    with pytest.raises(DataError) as info:
        Calibration.from_yaml(binary)
    assert str(info.value).startswith(f"{binary}: not a UTF-8 YAML text file (byte 128") and "\n" not in str(info.value)
    with pytest.raises(DataError, match=r"^YAML file not found: "):
        Calibration.from_yaml(tmp_path / "missing.yaml")
    text = tmp_path / "calib_utf8.yaml"  # OpenCV's header line and a non-ASCII comment
    text.write_text("%YAML:1.0\n# Kalibrierung für Kamera Ø 3 mm\nwidth: 64\nheight: 48\nintrinsics: [50, 50, 32, 24]\n",
                    encoding="utf-8")
    assert Calibration.from_yaml(text).width == 64
    env = {**os.environ, "LC_ALL": "C", "LANG": "C", "PYTHONUTF8": "0", "PYTHONCOERCECLOCALE": "0"}
    code = ("import sys, locale; from fgslam.io.calibration import Calibration; "
            "print(locale.getpreferredencoding(False), Calibration.from_yaml(sys.argv[1]).width)")
    done = subprocess.run([sys.executable, "-c", code, str(text)], capture_output=True, text=True, env=env, timeout=120)
    assert done.returncode == 0, done.stderr
    encoding, width = done.stdout.split()
    assert width == "64" and encoding.upper().replace("-", "") != "UTF8"  # the locale's encoding was not UTF-8


# ------------------------------------------------------------------ calibrations that cannot be right
def _folder_with_calibration(root, calib: dict, n=2):
    root.mkdir(parents=True)
    rng = np.random.default_rng(0)
    for i in range(n):
        cv2.imwrite(str(root / f"img_{i:04d}.png"), rng.integers(0, 255, (calib["height"], calib["width"]), dtype=np.uint8))
    (root / "calibration.yaml").write_text(yaml.safe_dump(calib))
    return root / "calibration.yaml"


@pytest.mark.parametrize(
    "model, coeffs, pattern",
    [
        # pincushion so strong that OpenCV's inverse fails: the output would zoom onto the centre
        ("radtan", [50.0, 0.0, 0.0, 0.0], r"maps the image outside itself: the undistorted image shows only 0\.\d+% of the raw image"),
        # barrel beyond its turning point inside the image: the image folds onto itself
        ("radtan", [-1.0, 0.0, 0.0, 0.0], "is not one-to-one over the image: the undistortion folds the image onto itself"),
        ("equidistant", [-1.0, 0.0, 0.0, 0.0], "OpenCV finds no undistorted camera .*cannot be inverted over the image"),
    ],
)
def test_distortion_that_maps_the_image_outside_itself_is_an_error(tmp_path, model, coeffs, pattern):
    from fgslam.io.datasets import open_dataset

    calib = {"width": W, "height": H, "intrinsics": K_RAW, "distortion_model": model, "distortion": coeffs}
    path = _folder_with_calibration(tmp_path / "seq", calib)
    with pytest.raises(DataError, match=rf"^{re.escape(str(path))}: .*{pattern}"):
        open_dataset(tmp_path / "seq", "folder")
    with pytest.raises(DataError, match=pattern):  # also with every source pixel kept
        Undistorter(Calibration(W, H, K_RAW, model, coeffs).validate(), alpha=1.0)


@pytest.mark.parametrize("model, coeffs", [("radtan", RADTAN), ("equidistant", EQUI), ("radtan", [0.3, 0.0, 0.0, 0.0])])
@pytest.mark.parametrize("alpha", [0.0, 1.0])
def test_sane_distortions_pass_the_undistortion_checks(model, coeffs, alpha):
    und = Undistorter(Calibration(W, H, K_RAW, model, coeffs).validate(), alpha=alpha)
    assert und.calibration.width == W


def test_principal_point_outside_the_image_is_an_error(tmp_path):
    from fgslam.io.datasets import open_dataset

    calib = {"width": 64, "height": 48, "intrinsics": [40.0, 40.0, 500.0, 24.0]}
    path = _folder_with_calibration(tmp_path / "seq", calib)
    with pytest.raises(DataError, match=rf"^{re.escape(str(path))}: principal point \(500, 24\) lies outside the 64x48 image"):
        open_dataset(tmp_path / "seq", "folder")
    with pytest.raises(DataError, match=r"principal point \(32, -3\) lies outside"):
        Calibration(64, 48, [40.0, 40.0, 32.0, -3.0]).validate()
    with pytest.raises(DataError, match=r"right camera\): principal point \(70, 24\)"):
        Calibration(64, 48, [40.0, 40.0, 32.0, 24.0], right=Calibration(64, 48, [40.0, 40.0, 70.0, 24.0]),
                    T_CLCR=np.eye(4)).validate("rig")
    # the extreme pixel centres (and the image border half a pixel beyond them) are inside
    Calibration(64, 48, [40.0, 40.0, -0.5, 47.5]).validate()
