"""Tests for jaxdistill.datasets.undistort: lens distortion formulas and image undistortion."""

import math

import numpy as np
import pytest

from jaxdistill.io import images as imageio
from jaxdistill.datasets.undistort import (Distortion, distort_normalized, undistort_image,
                                           undistort_normalized, undistort_photo)
from jaxdistill.errors import InputError

W, H = 96, 72
K = np.array([[80.0, 0.0, 48.3], [0.0, 83.0, 35.9], [0.0, 0.0, 1.0]])  # off-centre, non-square
BARREL = Distortion("opencv", k1=-0.25, k2=0.05, p1=0.002, p2=-0.003)
PINCUSHION = Distortion("radial", k1=0.3, k2=0.1)
DISTORTIONS = [Distortion("radial", k1=-0.12), Distortion("radial", k1=0.08, k2=-0.03), BARREL,
               Distortion("opencv", k1=0.1, k2=0.02, p1=-0.004, p2=0.006)]


def _hand_opencv(x, y, k1=0.0, k2=0.0, p1=0.0, p2=0.0):
    """OpenCV/COLMAP distortion polynomial, written out independently of the module."""
    rr = x ** 2 + y ** 2
    factor = 1 + k1 * rr + k2 * rr ** 2
    return (x * factor + 2 * p1 * x * y + p2 * (rr + 2 * x ** 2),
            y * factor + p1 * (rr + 2 * y ** 2) + 2 * p2 * x * y)


def _pixel_grid(width, height):
    """(H*W, 2) pixel centres (col + 0.5, row + 0.5), row-major."""
    u, v = np.meshgrid(np.arange(width) + 0.5, np.arange(height) + 0.5)
    return np.stack([u.ravel(), v.ravel()], axis=-1)


def _to_normalized(uv):
    return (uv - K[:2, 2]) / [K[0, 0], K[1, 1]]


def _to_pixels(xy):
    return xy * [K[0, 0], K[1, 1]] + K[:2, 2]


def _pattern(uv):
    """A smooth analytic test image in undistorted pixel coordinates: (N, 3) values."""
    u, v = uv[:, 0], uv[:, 1]
    return np.stack([0.5 + 0.3 * np.sin(2 * math.pi * u / 29) * np.cos(2 * math.pi * v / 23),
                     0.1 + 0.004 * u + 0.003 * v,
                     0.5 + 0.4 * np.cos(2 * math.pi * (u + v) / 37)], axis=-1)


def _distorted_photo(d):
    """The photo a lens with distortion `d` takes of `_pattern` (H, W, 3), float32."""
    xy = undistort_normalized(_to_normalized(_pixel_grid(W, H)), d)
    assert np.all(np.isfinite(xy))
    return _pattern(_to_pixels(xy)).reshape(H, W, 3).astype(np.float32)


# ----------------------------------------------------------------------------- formulas


@pytest.mark.parametrize("d", DISTORTIONS)
def test_distort_matches_hand_formula(d):
    xy = np.random.default_rng(1).uniform(-0.8, 0.8, (200, 2))
    xd, yd = _hand_opencv(xy[:, 0], xy[:, 1], d.k1, d.k2, d.p1, d.p2)
    np.testing.assert_allclose(distort_normalized(xy, d), np.stack([xd, yd], -1), rtol=0, atol=1e-14)


def test_distort_known_values():
    # radial: x = 0.5, y = 0, k1 = 0.1 -> 0.5 (1 + 0.1 * 0.25) = 0.5125
    np.testing.assert_allclose(distort_normalized([[0.5, 0.0]], Distortion("radial", 0.1)),
                               [[0.5125, 0.0]], atol=1e-15)
    # tangential only at (0.5, 0.5): dx = 2 p1 xy + p2 (r2 + 2x^2) = 0.5 p1 + p2, dy = p1 + 0.5 p2
    out = distort_normalized([[0.5, 0.5]], Distortion("opencv", p1=0.01, p2=0.02))
    np.testing.assert_allclose(out, [[0.5 + 0.005 + 0.02, 0.5 + 0.01 + 0.01]], atol=1e-15)


@pytest.mark.parametrize("d", DISTORTIONS)
def test_round_trip(d):
    xy = np.random.default_rng(2).uniform(-0.7, 0.7, (500, 2))
    np.testing.assert_allclose(undistort_normalized(distort_normalized(xy, d), d), xy, atol=1e-10)
    np.testing.assert_allclose(distort_normalized(undistort_normalized(xy, d), d), xy, atol=1e-10)


def test_undistort_nan_where_not_invertible():
    d = Distortion("radial", k1=-0.5)  # r_d = r (1 - 0.5 r^2) peaks at r_d = 0.544 (r = 0.816)
    out = undistort_normalized([[0.3, 0.0], [0.7, 0.0]], d)
    assert np.all(np.isfinite(out[0])) and np.all(np.isnan(out[1]))


def test_identity_and_validation():
    assert Distortion("none").is_identity() and Distortion("radial").is_identity()
    assert not Distortion("radial", k1=1e-9).is_identity()
    xy = np.array([[0.1, -0.2]])
    assert np.array_equal(distort_normalized(xy, Distortion("none")), xy)
    with pytest.raises(ValueError, match="model"):
        Distortion("fisheye")
    with pytest.raises(ValueError, match="p1"):
        Distortion("radial", p1=0.1)
    with pytest.raises(ValueError, match="k1"):
        Distortion("opencv", k1=float("nan"))
    with pytest.raises(ValueError, match="shape"):
        distort_normalized(np.zeros((3, 3)), BARREL)


# ----------------------------------------------------------------------------- images


@pytest.mark.parametrize("d", [BARREL, Distortion("radial", k1=-0.12)])
def test_undistort_image_recovers_pattern(d):
    photo = _distorted_photo(d)
    out, valid = undistort_image(photo, K, d)
    assert out.shape == (H, W, 3) and out.dtype == np.float32 and valid.shape == (H, W)
    truth = _pattern(_pixel_grid(W, H)).reshape(H, W, 3)
    interior = np.zeros((H, W), bool)
    interior[3:-3, 3:-3] = True
    assert valid[interior].all()
    err = np.abs(out - truth)[interior]
    assert err.max() < 0.01, err.max()
    # the distortion really matters: the distorted photo itself is far from the truth
    assert np.abs(photo - truth)[interior].max() > 0.1


def test_wrong_distortion_is_detected():
    photo = _distorted_photo(BARREL)
    wrong = Distortion("opencv", k1=-0.2, k2=0.05, p1=0.002, p2=-0.003)
    out, _ = undistort_image(photo, K, wrong)
    truth = _pattern(_pixel_grid(W, H)).reshape(H, W, 3)
    assert np.abs(out - truth)[3:-3, 3:-3].max() > 0.03


def test_identity_gives_image_back():
    img = np.random.default_rng(3).uniform(0, 4, (H, W, 4)).astype(np.float32)
    for d in (Distortion("none"), Distortion("opencv")):
        out, valid = undistort_image(img, K, d)
        assert np.array_equal(out, img) and valid.all() and out is not img
    out2d, valid2d = undistort_image(img[:, :, 0], K, Distortion("radial", -0.1))
    assert out2d.shape == (H, W) and valid2d.shape == (H, W)


def test_tiny_distortion_is_nearly_identity():
    img = np.random.default_rng(4).uniform(0, 1, (H, W, 3)).astype(np.float32)
    out, valid = undistort_image(img, K, Distortion("radial", k1=1e-12))
    assert valid.all()
    np.testing.assert_allclose(out, img, atol=1e-6)


def test_valid_mask_outside_source():
    img = np.ones((H, W, 3), np.float32)
    out, valid = undistort_image(img, K, PINCUSHION)
    # expected: valid where the distorted pixel centre lies inside the source rectangle
    xd, yd = _hand_opencv(*_to_normalized(_pixel_grid(W, H)).T, k1=PINCUSHION.k1, k2=PINCUSHION.k2)
    ud, vd = _to_pixels(np.stack([xd, yd], -1)).T
    expected = ((ud >= 0) & (ud <= W) & (vd >= 0) & (vd <= H)).reshape(H, W)
    assert np.array_equal(valid, expected)
    assert not valid[0, 0] and not valid[-1, -1] and valid[H // 2, W // 2]
    assert 0.05 < 1 - valid.mean() < 0.6
    assert np.all(out[~valid] == 0) and np.allclose(out[valid], 1.0)


def test_valid_mask_beyond_fold():
    d = Distortion("radial", k1=-0.9)  # folds at r^2 = 1 / 2.7, inside this wide image's corners
    wide = np.array([[40.0, 0.0, 48.0], [0.0, 40.0, 36.0], [0.0, 0.0, 1.0]])
    _, valid = undistort_image(np.ones((H, W), np.float32), wide, d)
    xy = (_pixel_grid(W, H) - [48.0, 36.0]) / 40.0
    r2 = (xy ** 2).sum(-1).reshape(H, W)
    assert valid[r2 < 0.99 / 2.7].all() and not valid[r2 > 1.01 / 2.7].any()


# ----------------------------------------------------------------------------- files


def test_undistort_photo_exr(tmp_path):
    img = np.random.default_rng(5).uniform(0, 3, (H, W, 3)).astype(np.float32)  # HDR values > 1
    imageio.write_image(tmp_path / "a.exr", img)
    assert undistort_photo(tmp_path / "a.exr", tmp_path / "b.exr", K, Distortion("none")) == 0.0
    np.testing.assert_array_equal(imageio.read_image(tmp_path / "b.exr"), img)

    photo = _distorted_photo(BARREL)
    imageio.write_image(tmp_path / "p.exr", photo)
    invalid = undistort_photo(tmp_path / "p.exr", tmp_path / "out" / "p.exr", K, BARREL,
                              expected_size=(W, H))
    _, valid = undistort_image(photo, K, BARREL)
    assert invalid == pytest.approx(1 - valid.mean())
    back = imageio.read_image(tmp_path / "out" / "p.exr")
    truth = _pattern(_pixel_grid(W, H)).reshape(H, W, 3)
    assert np.abs(back - truth)[3:-3, 3:-3].max() < 0.01


def test_undistort_photo_png(tmp_path):
    photo = _distorted_photo(BARREL)
    imageio.write_image(tmp_path / "p.jpg", photo)
    imageio.write_image(tmp_path / "q.png", photo)
    invalid = undistort_photo(tmp_path / "q.png", tmp_path / "q_u.png", K, BARREL)
    assert 0.0 <= invalid < 0.05
    back = imageio.read_image(tmp_path / "q_u.png")  # sRGB-decoded to linear
    truth = _pattern(_pixel_grid(W, H)).reshape(H, W, 3)
    assert back.shape == (H, W, 3)
    assert np.abs(back - truth)[3:-3, 3:-3].max() < 0.03  # 8-bit quantisation twice + bilinear
    raw = imageio.read_image(tmp_path / "q_u.png", linear=False)  # stored sRGB-encoded
    np.testing.assert_allclose(raw[H // 2, W // 2], imageio.linear_to_srgb(back[H // 2, W // 2]), atol=1e-6)
    assert undistort_photo(tmp_path / "p.jpg", tmp_path / "p.png", K, BARREL) < 0.05
    assert imageio.read_image(tmp_path / "p.png").shape == (H, W, 3)


def test_undistort_photo_errors(tmp_path):
    imageio.write_image(tmp_path / "a.png", np.zeros((H, W, 3), np.float32))
    with pytest.raises(ValueError, match=r"\.png"):
        undistort_photo(tmp_path / "a.png", tmp_path / "a.exr", K, BARREL)
    with pytest.raises(ValueError, match=r"\.png"):
        undistort_photo(tmp_path / "a.png", tmp_path / "a.jpg", K, BARREL)
    with pytest.raises(InputError, match=r"a\.png: image size: is 96x72 but its camera is 100x72"):
        undistort_photo(tmp_path / "a.png", tmp_path / "b.png", K, BARREL, expected_size=(100, 72))
    with pytest.raises(InputError, match=r"missing\.exr: \(file\): photo not found"):
        undistort_photo(tmp_path / "missing.exr", tmp_path / "b.exr", K, BARREL)
    assert not (tmp_path / "b.png").exists()
