"""Procedural texture building blocks: smooth noise, blur, colour mixing, wood grain.

Pure NumPy on square texture pages (or images): `smooth_noise` is periodic Gaussian-filtered
white noise of unit std, `gaussian_blur` a separable blur, `grid` the texel centres of a page,
`mix` a per-texel blend of two colours, `wood` a grain pattern. Every random draw comes from the
generator passed in, so a seed gives the same textures.
"""

from __future__ import annotations

import math

import numpy as np

def smooth_noise(rng, shape, sigma: float, aspect: float = 1.0) -> np.ndarray:
    """Periodic Gaussian-filtered white noise of `shape` (int for square), zero mean, unit std;
    sigma in texels across rows, sigma * aspect along rows."""
    shape = (shape, shape) if np.isscalar(shape) else tuple(shape)
    white = rng.standard_normal(shape)
    gy, gx = np.meshgrid(np.fft.fftfreq(shape[0]), np.fft.fftfreq(shape[1]), indexing="ij")
    kernel = np.exp(-2 * np.pi ** 2 * ((gy * sigma) ** 2 + (gx * sigma * aspect) ** 2))
    out = np.real(np.fft.ifft2(np.fft.fft2(white) * kernel))
    return (out - out.mean()) / (out.std() + 1e-12)


def gaussian_blur(image: np.ndarray, sigma: float) -> np.ndarray:
    """(H, W, C) image blurred with a separable Gaussian (edge-replicated borders)."""
    if sigma <= 0:
        return image
    r = int(math.ceil(3 * sigma))
    k = np.exp(-0.5 * (np.arange(-r, r + 1) / sigma) ** 2)
    k /= k.sum()
    out = np.pad(image, ((r, r), (r, r), (0, 0)), mode="edge")
    out = sum(k[i] * out[i:i + image.shape[0]] for i in range(2 * r + 1))
    return sum(k[i] * out[:, i:i + image.shape[1]] for i in range(2 * r + 1))


def mix(a, b, t):
    """(..., 3): colour `a` where t is 0, `b` where it is 1, linear in between (t (...) per texel)."""
    return np.asarray(a)[None, None] * (1 - t[..., None]) + np.asarray(b)[None, None] * t[..., None]


def grid(size: int):
    """(u, row) texel-centre coordinates in (0, 1) of a `size` x `size` page, row 0 on top."""
    s = (np.arange(size) + 0.5) / size
    return np.meshgrid(s, s, indexing="xy")          # (u, row) with row 0 on top


def wood(rng, size, light, dark, rings=38.0):
    """(albedo (S, S, 3) from `light` to `dark` along warped grain rings, grain t (S, S) in [0, 1])."""
    u, v = grid(size)
    warp = smooth_noise(rng, size, size / 10, aspect=0.25)
    grain = 0.5 + 0.5 * np.sin(2 * np.pi * (v * rings + 0.8 * warp))
    fine = smooth_noise(rng, size, 0.7, aspect=6.0)
    t = np.clip(grain ** 3 + 0.12 * fine, 0, 1)
    return mix(light, dark, t), t
