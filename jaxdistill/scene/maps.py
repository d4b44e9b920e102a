"""The PBR maps as the optimiser holds them: channels, initial values and value spaces.

Model space (what texels hold and the prior sees, thesis §4.2): every map in [-1, 1].
- albedo, irradiance: 2 x - 1 of linear RGB (RGB<->X's decoder output before its x**(1/2.2)
  display encoding, and our targets' sRGB PNGs decoded to linear).
- roughness, metallic: 2 x - 1 of the grey value, ONE channel (RGB<->X writes grey images;
  channel 0 is the value, so only one channel is modelled).
- normal: unit vector components. Texels hold WORLD-space normals (one texture for all views);
  renders are rotated per view into RGB<->X's camera space (x right, y up, z towards the camera)
  before the prior and the loss see them.
File space (maps/, renders/): albedo linear [0, 1], irradiance linear, roughness/metallic [0, 1],
normals unit vectors.
"""

from __future__ import annotations

import dataclasses

import jax.numpy as jnp
import numpy as np

from jaxdistill import MAP_NAMES

CHANNELS = {"albedo": 3, "normal": 3, "roughness": 1, "metallic": 1, "irradiance": 3}
INITIAL_VALUE = {"albedo": 0.0, "normal": 0.0, "roughness": 1.0, "metallic": -1.0, "irradiance": 0.0}
"""Thesis initialisation in model space: albedo, normal, irradiance 0; metallic -1; roughness +1."""
GREY_MAPS = ("roughness", "metallic")


@dataclasses.dataclass(frozen=True)
class MapChannels:
    """Where each requested map lives in the texel array's channel axis (static, hashable)."""

    maps: tuple[str, ...]

    def __post_init__(self):
        unknown = [m for m in self.maps if m not in MAP_NAMES]
        if unknown:
            raise ValueError(f"unknown maps {unknown}; expected some of {MAP_NAMES}")

    @property
    def num_channels(self) -> int:
        return sum(CHANNELS[m] for m in self.maps)

    def slice(self, name: str) -> slice:
        """Channel slice of map `name`."""
        start = 0
        for m in self.maps:
            if m == name:
                return slice(start, start + CHANNELS[m])
            start += CHANNELS[m]
        raise KeyError(name)

    def split(self, x) -> dict:
        """{map: x[..., its channels]} for an array whose last axis is `num_channels`."""
        return {m: x[..., self.slice(m)] for m in self.maps}

    def join(self, parts: dict):
        """Inverse of `split`: concatenates per-map arrays along the last axis, in map order."""
        return jnp.concatenate([parts[m] for m in self.maps], axis=-1)

    def initial_texels(self, num_texels: int) -> np.ndarray:
        """(N, num_channels) float32 texels at the thesis's initial values."""
        row = np.concatenate([np.full(CHANNELS[m], INITIAL_VALUE[m], np.float32) for m in self.maps])
        return np.tile(row, (num_texels, 1))


def file_to_model(name: str, values: np.ndarray) -> np.ndarray:
    """Per-view target or map in file space (H, W, C>=CHANNELS) → model space (H, W, CHANNELS[name])."""
    values = np.asarray(values, np.float32)
    if name == "normal":
        return values[..., :3]
    if name in GREY_MAPS:
        return 2.0 * values[..., :1] - 1.0
    return 2.0 * values[..., :3] - 1.0


def model_to_file(name: str, values) -> np.ndarray:
    """Model space → file space (float32): [0, 1] values clipped; normals normalised (0 stays 0)."""
    values = np.asarray(values, np.float32)
    if name == "normal":
        length = np.linalg.norm(values, axis=-1, keepdims=True)
        return np.where(length > 1e-6, values / np.maximum(length, 1e-6), 0.0).astype(np.float32)
    return np.clip(0.5 * (values + 1.0), 0.0, 1.0).astype(np.float32)


def png_pixels(name: str, page: np.ndarray) -> tuple[np.ndarray, bool]:
    """(pixels in what write_image expects, encode_srgb) for the PNG of one map page."""
    page = np.nan_to_num(page, nan=0.0, posinf=1.0, neginf=0.0)
    if name in ("albedo", "irradiance"):
        return np.clip(page, 0.0, 1.0), True  # linear, sRGB-encoded by write_image
    if name == "normal":
        return np.clip((page + 1.0) * 0.5, 0.0, 1.0), False
    return np.clip(page, 0.0, 1.0), False  # roughness / metallic: grey values as they are
