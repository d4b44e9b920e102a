"""Photo exposure: how linear HDR photos are scaled before RGB<->X sees them.

RGB<->X takes an LDR sRGB photo in [0, 1]. It was trained mostly on Hypersim, whose images
are tone-mapped by one rule: scale the linear image so that the 90th percentile of its
brightness (0.3 R + 0.59 G + 0.11 B) becomes 0.8 after a 1/2.2 gamma, then clip. We apply the
same rule to HDR photos (EXR), with one scale for the whole scene, computed over the pixels of
all views together: per-view scales would tell the model that walls change brightness from
view to view. LDR photos (PNG/JPG) are already exposed by their camera and keep 0 stops.

An exposure is stored per view in stops (scene.json's "exposure"): the photo's linear values
are multiplied by 2**stops, clipped to [0, 1] and sRGB-encoded (`imageio.read_photo_srgb`).
"""

from __future__ import annotations

import math
from typing import Iterable

import numpy as np

BRIGHTNESS_WEIGHTS = np.array([0.3, 0.59, 0.11], np.float32)
HYPERSIM_PERCENTILE = 90.0
HYPERSIM_TARGET = 0.8 ** 2.2          # linear value of 0.8 after the 1/2.2 gamma
MAX_PIXELS_PER_VIEW = 1 << 16         # subsample views to this many pixels for the percentile
MAX_STOPS = 64.0                      # |exposure| accepted in scene.json and --exposure


def brightness(linear: np.ndarray) -> np.ndarray:
    """(H, W) Hypersim brightness 0.3 R + 0.59 G + 0.11 B of (H, W, >=3) linear RGB."""
    return np.asarray(linear[..., :3], np.float32) @ BRIGHTNESS_WEIGHTS


def scene_exposure(photos: Iterable[np.ndarray], masks: Iterable[np.ndarray | None] | None = None) -> float:
    """Stops that bring the scene's 90th-percentile brightness to 0.8^2.2 (Hypersim's rule).

    `photos` are (H, W, >=3) linear images, `masks` optional (H, W) bool (True = use). Each view
    contributes an evenly strided subsample of at most MAX_PIXELS_PER_VIEW valid pixels.
    Raises ValueError when no pixel is brighter than 0 (an all-black scene has no exposure).
    """
    masks = masks if masks is not None else iter(lambda: None, 0)
    samples = []
    for photo, mask in zip(photos, masks):
        values = brightness(photo)
        values = values[mask] if mask is not None else values.reshape(-1)
        values = values[np.isfinite(values)]
        step = max(1, len(values) // MAX_PIXELS_PER_VIEW)
        samples.append(values[::step])
    values = np.concatenate(samples) if samples else np.zeros(0, np.float32)
    p = float(np.percentile(values, HYPERSIM_PERCENTILE)) if len(values) else 0.0
    if not p > 0:
        raise ValueError("the photos' 90th-percentile brightness is 0 (black photos?): no exposure to derive")
    return round(math.log2(HYPERSIM_TARGET / p), 4)


def apply_exposure(linear: np.ndarray, stops: float) -> np.ndarray:
    """Linear pixels x 2**stops (float32, not clipped)."""
    return np.asarray(linear, np.float32) * np.float32(2.0 ** stops)
