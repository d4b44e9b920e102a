"""The texture sampler: a pure gather over compact texels, and the way back to full pages.

`render(texels, plan)` is jit-able and differentiable; its gradient w.r.t. texels is the exact
transpose of the gather (a scatter-add), through the mip chain when the plan is trilinear.
`expand` writes compact texels back into full pages for export (with seam dilation), and
`compact` takes full pages to compact texels.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from jaxdistill.render.gather_plan import GatherPlan, MipChain, TexelSpace


def build_pyramid(texels: jnp.ndarray, chain: MipChain) -> jnp.ndarray:
    """(N_total, C): the compact texels followed by every needed coarser level (2x2 means)."""
    pyramid = texels
    for children in chain.children:
        pyramid = jnp.concatenate([pyramid, jnp.mean(pyramid[children], axis=1)], axis=0)
    return pyramid


def render(texels: jnp.ndarray, plan: GatherPlan) -> jnp.ndarray:
    """Samples compact texels (N, C) through `plan`: (H, W, C), or (V, H, W, C) for a batch.

    Values keep the texels' space (e.g. [-1, 1] while optimising); missed pixels are 0.
    """
    pyramid = build_pyramid(texels, plan.chain)
    values = pyramid[plan.index]                                   # (..., P, T, C)
    image = jnp.einsum("...pt,...ptc->...pc", plan.weight.astype(values.dtype), values)
    return image.reshape(*plan.index.shape[:-2], plan.height, plan.width, texels.shape[-1])


def compact(pages, space: TexelSpace) -> np.ndarray:
    """(N, C) texels read from full pages (a list of (S, S, C) arrays, one per page)."""
    channels = np.asarray(pages[0]).shape[-1]
    out = np.zeros((space.num_texels, channels), np.float32)
    for page in range(space.layout.num_pages):
        sel = space.texel_page == page
        out[sel] = np.asarray(pages[page])[space.texel_row[sel], space.texel_col[sel]]
    return out


def coverage(space: TexelSpace) -> list[np.ndarray]:
    """Per page, (S, S) bool: the texel is a parameter (observed by some view)."""
    masks = [np.zeros((s, s), bool) for s in space.layout.page_sizes]
    for page, mask in enumerate(masks):
        sel = space.texel_page == page
        mask[space.texel_row[sel], space.texel_col[sel]] = True
    return masks


def dilate(page: np.ndarray, known: np.ndarray, iterations: int) -> np.ndarray:
    """Grows known texels into unknown ones: each pass gives an unknown texel next to known ones
    (8-neighbourhood) the mean of those neighbours. (S, S, C) float32, (S, S) bool."""
    page = page.copy()
    known = known.copy()
    size_y, size_x = known.shape
    for _ in range(iterations):
        if known.all() or not known.any():
            break
        padded_v = np.pad(page * known[..., None], ((1, 1), (1, 1), (0, 0)))
        padded_k = np.pad(known.astype(np.float32), 1)
        total = np.zeros_like(page)
        count = np.zeros(known.shape, np.float32)
        for dy in (-1, 0, 1):
            for dx in (-1, 0, 1):
                if dy == 0 and dx == 0:
                    continue
                total += padded_v[1 + dy:1 + dy + size_y, 1 + dx:1 + dx + size_x]
                count += padded_k[1 + dy:1 + dy + size_y, 1 + dx:1 + dx + size_x]
        grow = ~known & (count > 0)
        page[grow] = total[grow] / count[grow, None]
        known |= grow
    return page


def expand(texels, space: TexelSpace, fill, *, dilation: int = 8) -> list[np.ndarray]:
    """Full pages (S, S, C) float32 from compact texels (N, C).

    Unobserved texels get `fill` (scalar or (C,)), except within `dilation` texels of an
    observed one, where seam dilation copies neighbouring values so that bilinear and mip
    sampling across chart borders in other renderers does not bleed the fill colour in.
    """
    texels = np.asarray(texels, np.float32)
    channels = texels.shape[-1]
    fill = np.broadcast_to(np.asarray(fill, np.float32), (channels,))
    pages = []
    for page, mask in enumerate(coverage(space)):
        size = space.layout.page_sizes[page]
        image = np.empty((size, size, channels), np.float32)
        image[:] = fill
        sel = space.texel_page == page
        image[space.texel_row[sel], space.texel_col[sel]] = texels[sel]
        if dilation > 0:
            image = dilate(image, mask, dilation)
        pages.append(image)
    return pages
