"""Lens distortion (COLMAP's RADIAL and OPENCV models) and undistortion of photos to pinhole images.

Distortion acts on normalised image coordinates x = (u - cx) / fx, y = (v - cy) / fy of the ideal
pinhole projection, with the formulas COLMAP and OpenCV use:

    r2 = x^2 + y^2,  radial = k1 r2 + k2 r2^2
    x_d = x (1 + radial) + 2 p1 x y + p2 (r2 + 2 x^2)
    y_d = y (1 + radial) + p1 (r2 + 2 y^2) + 2 p2 x y

so a camera-space point (X, Y, Z) appears in the photo at u = fx x_d + cx, v = fy y_d + cy with
x = X / Z, y = Y / Z. The jaxdistill cameras are pinholes, so photos taken through a distorting
lens are resampled by `undistort_image` / `undistort_photo` onto the pinhole image with the SAME
K and size. Pixel centres are at +0.5 (the first pixel's centre is at (0.5, 0.5)), as in
jaxdistill.scene.cameras and COLMAP.

Only these models are supported: "none", "radial" (k1, k2; COLMAP SIMPLE_RADIAL is k2 = 0) and
"opencv" (k1, k2, p1, p2). Everything is NumPy with float64 coordinates; pixels are float32 linear.
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np

from jaxdistill.io import images as imageio
from jaxdistill.scene.cameras import validate_intrinsics
from jaxdistill.errors import InputError

MODELS = ("none", "radial", "opencv")
_ROWS_PER_CHUNK = 128  # rows of output resampled at once (bounds memory for large photos)
_CONVERGED = 1e-10  # max |distort(x) - x_d| (normalised units) accepted by undistort_normalized


@dataclasses.dataclass(frozen=True)
class Distortion:
    """Lens distortion of normalised image coordinates (x = (u - cx) / fx, y = (v - cy) / fy).

    `model` is "none", "radial" (k1, k2) or "opencv" (k1, k2, p1, p2); COLMAP's SIMPLE_RADIAL
    is "radial" with k2 = 0. Coefficients a model does not have must be zero.
    """

    model: str
    k1: float = 0.0
    k2: float = 0.0
    p1: float = 0.0
    p2: float = 0.0

    def __post_init__(self):
        if self.model not in MODELS:
            raise ValueError(f"Distortion.model: expected one of {MODELS}, got {self.model!r}")
        for name in ("k1", "k2", "p1", "p2"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)) \
                    or not math.isfinite(value):
                raise ValueError(f"Distortion.{name}: expected a finite number, got {value!r}")
            object.__setattr__(self, name, float(value))
        unused = {"none": ("k1", "k2", "p1", "p2"), "radial": ("p1", "p2"), "opencv": ()}[self.model]
        nonzero = [n for n in unused if getattr(self, n) != 0.0]
        if nonzero:
            raise ValueError(f"Distortion: model {self.model!r} has no coefficient(s) {nonzero}, "
                             "but they are non-zero")

    def is_identity(self) -> bool:
        """True when the distortion changes nothing (all coefficients zero)."""
        return self.k1 == 0.0 and self.k2 == 0.0 and self.p1 == 0.0 and self.p2 == 0.0


def _as_points(xy) -> np.ndarray:
    """`xy` as a float64 (N, 2) array; ValueError otherwise."""
    a = np.asarray(xy, dtype=np.float64)
    if a.ndim != 2 or a.shape[1] != 2:
        raise ValueError(f"xy: expected shape (N, 2), got {a.shape}")
    return a


def _distort_xy(x: np.ndarray, y: np.ndarray, d: Distortion) -> tuple[np.ndarray, np.ndarray]:
    """(x_d, y_d) of undistorted normalised coordinates (any equal shapes)."""
    r2 = x * x + y * y
    radial = 1.0 + r2 * (d.k1 + d.k2 * r2)
    xy = x * y
    return (x * radial + 2.0 * d.p1 * xy + d.p2 * (r2 + 2.0 * x * x),
            y * radial + d.p1 * (r2 + 2.0 * y * y) + 2.0 * d.p2 * xy)


def _jacobian(x: np.ndarray, y: np.ndarray, d: Distortion):
    """(dxd/dx, dxd/dy, dyd/dx, dyd/dy) of the distortion at (x, y)."""
    r2 = x * x + y * y
    radial = 1.0 + r2 * (d.k1 + d.k2 * r2)
    g2 = 2.0 * (d.k1 + 2.0 * d.k2 * r2)  # 2 * d(radial)/d(r2)
    cross = g2 * x * y
    return (radial + g2 * x * x + 2.0 * d.p1 * y + 6.0 * d.p2 * x,
            cross + 2.0 * d.p1 * x + 2.0 * d.p2 * y,
            cross + 2.0 * d.p1 * x + 2.0 * d.p2 * y,
            radial + g2 * y * y + 6.0 * d.p1 * y + 2.0 * d.p2 * x)


def _fold_r2(d: Distortion) -> float:
    """The smallest r2 = x^2 + y^2 where the radial part r (1 + k1 r2 + k2 r2^2) stops growing.

    Beyond it the lens model folds back (several undistorted points share a distorted one), so
    those points cannot be on the photo; inf when the radial part grows everywhere.
    """
    roots = np.roots([5.0 * d.k2, 3.0 * d.k1, 1.0]) if (d.k1 or d.k2) else np.array([])
    positive = [r.real for r in np.atleast_1d(roots) if abs(r.imag) < 1e-12 and r.real > 0]
    return min(positive) if positive else math.inf


def distort_normalized(xy: np.ndarray, d: Distortion) -> np.ndarray:
    """(N, 2) distorted normalised coordinates of (N, 2) undistorted ones (COLMAP/OpenCV formulas)."""
    p = _as_points(xy)
    xd, yd = _distort_xy(p[:, 0], p[:, 1], d)
    return np.stack([xd, yd], axis=-1)


def undistort_normalized(xy: np.ndarray, d: Distortion, iterations: int = 50) -> np.ndarray:
    """(N, 2) undistorted normalised coordinates of (N, 2) distorted ones: the inverse of
    `distort_normalized`, by Newton's method (analytic Jacobian) started at the distorted point.

    Points where it does not converge to 1e-10 within `iterations` steps (outside the region the
    lens model maps one-to-one, e.g. beyond a fold of a strong barrel distortion) come back NaN.
    """
    target = _as_points(xy)
    if d.is_identity():
        return target.copy()
    x, y = target[:, 0].copy(), target[:, 1].copy()
    with np.errstate(all="ignore"):
        for _ in range(max(int(iterations), 1)):
            xd, yd = _distort_xy(x, y, d)
            ex, ey = xd - target[:, 0], yd - target[:, 1]
            if not np.any(np.abs(ex) + np.abs(ey) > 0.1 * _CONVERGED):
                break
            a, b, c, e = _jacobian(x, y, d)
            det = a * e - b * c
            x = x - (e * ex - b * ey) / det
            y = y - (a * ey - c * ex) / det
        xd, yd = _distort_xy(x, y, d)
        bad = ~(np.maximum(np.abs(xd - target[:, 0]), np.abs(yd - target[:, 1])) <= _CONVERGED)
    out = np.stack([x, y], axis=-1)
    out[bad] = np.nan
    return out


def _intrinsics(K) -> tuple[float, float, float, float]:
    """(fx, fy, cx, cy) of a zero-skew K (3, 3); ValueError otherwise."""
    K = validate_intrinsics(K, "K")
    return K[0, 0], K[1, 1], K[0, 2], K[1, 2]


def _bilinear(image: np.ndarray, xs: np.ndarray, ys: np.ndarray) -> np.ndarray:
    """(N, C) bilinear samples of (H, W, C) `image` at array coordinates (xs, ys) (pixel centres
    at integers), clamped to the edge pixels; xs, ys must be finite."""
    H, W = image.shape[:2]
    x0, y0 = np.floor(xs), np.floor(ys)
    wx, wy = (xs - x0).astype(np.float32)[:, None], (ys - y0).astype(np.float32)[:, None]
    x0, y0 = x0.astype(np.int64), y0.astype(np.int64)
    xa, xb = np.clip(x0, 0, W - 1), np.clip(x0 + 1, 0, W - 1)
    ya, yb = np.clip(y0, 0, H - 1), np.clip(y0 + 1, 0, H - 1)
    top = image[ya, xa] * (1.0 - wx) + image[ya, xb] * wx
    bottom = image[yb, xa] * (1.0 - wx) + image[yb, xb] * wx
    return top * (1.0 - wy) + bottom * wy


def undistort_image(image: np.ndarray, K: np.ndarray, d: Distortion) -> tuple[np.ndarray, np.ndarray]:
    """(undistorted (H, W, C) float32 linear, valid (H, W) bool): same K and size as the input (a
    pinhole camera with the same intrinsics); each output pixel centre is mapped through
    distort_normalized to the source image and sampled bilinearly (in linear light); valid is
    False where that falls outside the source.

    "Outside" means outside the source rectangle [0, W] x [0, H] (the outer half pixel is
    sampled by clamping to the edge pixels) or beyond the radius where the lens model folds
    back; invalid pixels are 0. A (H, W) image gives a (H, W) result. Identity distortion
    returns a copy of the image, all valid.
    """
    image = np.asarray(image, dtype=np.float32)
    if image.ndim not in (2, 3) or image.shape[0] < 1 or image.shape[1] < 1:
        raise ValueError(f"image: expected shape (H, W) or (H, W, C), got {image.shape}")
    fx, fy, cx, cy = _intrinsics(K)
    H, W = image.shape[:2]
    if d.is_identity():
        return image.copy(), np.ones((H, W), dtype=bool)
    src = image if image.ndim == 3 else image[:, :, None]
    out = np.zeros(src.shape, dtype=np.float32)
    valid = np.zeros((H, W), dtype=bool)
    fold = _fold_r2(d)
    x = (np.arange(W, dtype=np.float64) + 0.5 - cx) / fx
    for row0 in range(0, H, _ROWS_PER_CHUNK):
        rows = np.arange(row0, min(row0 + _ROWS_PER_CHUNK, H))
        y = (rows.astype(np.float64) + 0.5 - cy) / fy
        xx, yy = np.broadcast_to(x[None, :], (len(rows), W)).ravel(), np.repeat(y, W)
        with np.errstate(all="ignore"):
            xd, yd = _distort_xy(xx, yy, d)
            us, vs = fx * xd + cx, fy * yd + cy
            a, b, c, e = _jacobian(xx, yy, d)
            ok = ((xx * xx + yy * yy < fold) & (a * e - b * c > 0)
                  & (us >= 0) & (us <= W) & (vs >= 0) & (vs <= H))
        samples = _bilinear(src, us[ok] - 0.5, vs[ok] - 0.5)
        block = np.zeros((len(rows) * W, src.shape[2]), dtype=np.float32)
        block[ok] = samples
        out[rows[0]:rows[-1] + 1] = block.reshape(len(rows), W, -1)
        valid[rows[0]:rows[-1] + 1] = ok.reshape(len(rows), W)
    return (out if image.ndim == 3 else out[:, :, 0]), valid


def undistorted_suffix(src) -> str:
    """The file suffix `undistort_photo` writes for photo `src`: ".exr" for linear formats
    (EXR, HDR, PFM), ".png" for sRGB ones (PNG, JPG, ...)."""
    return ".exr" if imageio.is_linear_format(src) else ".png"


def undistort_photo(src: Path, dst: Path, K, d: Distortion, expected_size=None) -> float:
    """Undistorts photo `src` onto the pinhole camera with the same K and size, writes `dst`, and
    returns the fraction of pixels that had no source (written as 0, black).

    `dst` keeps the encoding family: a linear `src` (EXR, HDR, PFM) needs an EXR `dst` (float32,
    linear); an sRGB `src` (PNG, JPG, ...) needs a PNG `dst` (8-bit sRGB; no second JPEG loss).
    Resampling happens in linear light. `expected_size` (width, height), when given, is checked
    against the photo (InputError naming `src` if it differs: the intrinsics would not fit).
    """
    src, dst = Path(src), Path(dst)
    want = undistorted_suffix(src)
    if dst.suffix.lower() != want:
        raise ValueError(f"dst: {dst.name} must end in {want} for a "
                         f"{'linear' if want == '.exr' else 'sRGB'} source photo {src.name}")
    if not src.is_file():
        raise InputError.single(src, "(file)", "photo not found; check the image folder and the "
                                "image names in the camera file")
    try:
        pixels = imageio.read_image(src)
    except OSError as err:
        raise InputError.single(src, "(file)", f"cannot read the photo ({err})") from None
    if expected_size is not None:
        width, height = (int(v) for v in expected_size)
        if (pixels.shape[1], pixels.shape[0]) != (width, height):
            raise InputError.single(src, "image size", f"is {pixels.shape[1]}x{pixels.shape[0]} but "
                                    f"its camera is {width}x{height}; the intrinsics refer to the "
                                    "original full-size photo (use the unresized images)")
    undistorted, valid = undistort_image(pixels, K, d)
    imageio.write_image(dst, undistorted)
    return float(1.0 - valid.mean())
