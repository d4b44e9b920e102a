"""Per-view images beside the photo, read in file space and resampled: targets and masks.

Shared by the dataset loaders (exposure over unmasked pixels), the problem setup (loss weights,
per-view targets) and evaluation (ground truth, masks); it sits below all of them.
"""

from __future__ import annotations

from pathlib import Path

import jax
import numpy as np

from jaxdistill.io import images as imageio


def resize(image: np.ndarray, height: int, width: int) -> np.ndarray:
    """(H, W, C) float32 resized with an antialiased linear filter (area-like when shrinking)."""
    if image.shape[:2] == (height, width):
        return image
    return np.asarray(jax.image.resize(image, (height, width, image.shape[2]), "linear", antialias=True))


def read_target(name: str, path: Path) -> np.ndarray:
    """A per-view target image in file space, with the map's channels (`maps.CHANNELS`):
    albedo/irradiance linear RGB (sRGB files decoded; a grey file, accepted by validation, is
    used as R = G = B), roughness/metallic channel 0, normals as vectors (files hold (n + 1) / 2).
    Validation (`scene.channel_problem`) has refused the channel counts these cannot use."""
    if name in ("albedo", "irradiance"):
        values = imageio.read_image(path)
        return np.repeat(values, 3, axis=-1) if values.shape[-1] == 1 else values[..., :3]
    values = imageio.read_image(path, linear=False)
    return 2.0 * values[..., :3] - 1.0 if name == "normal" else values[..., :1]


def read_mask(path: Path, height: int, width: int) -> np.ndarray:
    """(height, width) bool: True where the view's mask image (first channel, resampled) is >= 0.5."""
    values = imageio.read_image(path, linear=False)[..., :1]
    return resize(values, height, width)[..., 0] >= 0.5


CLIPPED_LDR = 254.5 / 255.0   # an 8-bit channel at 255 (or a float LDR value this high) is clipped


def read_photo_linear(path: Path, exposure: float, height: int, width: int) -> tuple[np.ndarray, np.ndarray]:
    """((height, width, 3) float32 linear photo x 2**exposure, negatives clamped to 0; (height,
    width) float32 1 where the pixel is usable, 0 where it is not): LDR files (PNG/JPG, sRGB-encoded)
    are decoded with the inverse sRGB curve and their clipped pixels (any channel at 255) dropped,
    with every resampled pixel that a clipped one touches; HDR files are used as they are."""
    values = imageio.read_image(path, linear=False)[..., :3]
    if imageio.is_linear_format(path):
        linear = values
        valid = np.ones(values.shape[:2], np.float32)
    else:
        linear = imageio.srgb_to_linear(values)
        valid = np.all(values < CLIPPED_LDR, axis=-1).astype(np.float32)
    linear = np.maximum(np.nan_to_num(linear, nan=0.0, posinf=0.0), 0.0) * np.float32(2.0 ** exposure)
    valid = resize(valid[..., None], height, width)[..., 0] >= 1.0 - 1e-4
    return resize(linear.astype(np.float32), height, width), valid.astype(np.float32)
