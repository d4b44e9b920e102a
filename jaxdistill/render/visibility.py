"""Visibility (thesis §4.3.1): per-texel view counts V and per-pixel loss weights W.

V(p) counts the views whose gather plan reads texel p with a non-zero weight (directly or
through a coarser mip level), i.e. where the transpose of `render` is positive. Per pixel,
V is sampled through the view's own plan and turned into W = clip(1 / (2 clip(V, 1, 6)), 0.1, 10);
missed pixels get W = 0.
"""

from __future__ import annotations

from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from jaxdistill import imageio
from jaxdistill.render.gather_plan import GatherPlan, TexelSpace
from jaxdistill.render.sampler import expand, render


def visibility_weights(counts):
    """W = clip(1 / (2 clip(V, 1, 6)), 0.1, 10) for view counts V (any shape, float32)."""
    counts = jnp.asarray(counts, jnp.float32)
    return jnp.clip(1.0 / (2.0 * jnp.clip(counts, 1.0, 6.0)), 0.1, 10.0)


@jax.jit
def _touched(plan: GatherPlan, num_texels_like: jnp.ndarray) -> jnp.ndarray:
    """(N,) bool: texels that the single-view `plan` reads with positive weight."""
    _, transpose = jax.vjp(lambda t: render(t, plan), num_texels_like)
    (grad,) = transpose(plan.hit.reshape(plan.height, plan.width, 1).astype(jnp.float32))
    return grad[:, 0] > 0


def view_counts(plan: GatherPlan, num_texels: int) -> np.ndarray:
    """(N,) int32: number of views whose plan touches each compact texel."""
    zeros = jnp.zeros((num_texels, 1), jnp.float32)
    counts = np.zeros(num_texels, np.int32)
    for v in range(plan.num_views):
        counts += np.asarray(_touched(plan.select(v), zeros))
    return counts


def pixel_weights(plan: GatherPlan, counts: np.ndarray) -> jnp.ndarray:
    """(V, H, W) float32 loss weights per view and pixel (0 on missed pixels)."""
    sampled = render(jnp.asarray(counts, jnp.float32)[:, None], plan)[..., 0]
    hit = plan.hit.reshape(sampled.shape)
    return jnp.where(hit, visibility_weights(sampled), 0.0)


def write_visibility_pages(counts: np.ndarray, space: TexelSpace, folder, object_names=None) -> list[Path]:
    """Writes V per page as `visibility_<page>.exr` (raw counts) and `.png` (counts / max, grey)."""
    folder = Path(folder)
    pages = expand(counts.astype(np.float32)[:, None], space, 0.0, dilation=0)
    peak = max(1.0, float(counts.max(initial=0)))
    written = []
    for page, image in enumerate(pages):
        name = object_names[page] if object_names and space.layout.num_pages == len(object_names) else f"page{page:03d}"
        stem = folder / f"visibility_{page:03d}_{name}"
        imageio.write_image(stem.with_suffix(".exr"), image)
        imageio.write_image(stem.with_suffix(".png"), image / peak, encode_srgb=False)
        written += [stem.with_suffix(".exr"), stem.with_suffix(".png")]
    return written
