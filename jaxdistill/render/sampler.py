"""The texture sampler: a pure gather over compact texels, and the way back to full pages.

`render(texels, plan)` is jit-able and differentiable; its gradient w.r.t. texels is the exact
transpose of the gather (a scatter-add), through the mip chain when the plan is trilinear.
`expand` writes compact texels back into full pages for export (with seam dilation), and
`compact` takes full pages to compact texels.
"""

from __future__ import annotations

from typing import Iterator, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxdistill.render.gather_plan import (GatherPlan, MipChain, TexelSpace, build_gather_plans,
                                           build_texel_space)
from jaxdistill.render.layout import TextureLayout


class SplitPyramid(NamedTuple):
    """A pyramid as its two parts: the texels themselves (level 0, rows [0, N) of the index) and
    the entries above them (rows N and up). `sample` reads each from its own array, so building
    it copies no texel and its cotangent's level 0 is the texels' gradient itself: one array of
    the texels' size less in a step's memory than the concatenated pyramid, for a second gather
    (`build_pyramid(split=True)`)."""

    texels: jnp.ndarray
    coarse: jnp.ndarray


def build_pyramid(texels: jnp.ndarray, chain: MipChain, *, split: bool = False):
    """(N_pyramid, C): in-tile levels 0..k of the compact texels (dense 2x2 means inside each
    tile), then the coarse entries above one tile (means of 4 entries of the level below).
    One concatenation at the end: no level is copied more than once. With `split` (and any level
    above the texels) a `SplitPyramid` of the same entries instead, with no concatenation."""
    with jax.named_scope("pyramid"):          # the profile's stage (scripts/bench_profile.py)
        return _pyramid(texels, chain, split)


def _pyramid(texels: jnp.ndarray, chain: MipChain, split: bool):
    b, channels = chain.tile, texels.shape[-1]
    level = texels.reshape(-1, b, b, channels)
    parts = [texels]
    for _ in range(1, chain.in_tile_levels):
        n, side = level.shape[0], level.shape[1] // 2
        level = level.reshape(n, side, 2, side, 2, channels).mean(axis=(2, 4))
        parts.append(level.reshape(-1, channels))
    below = parts[-1]  # level k: one entry per tile
    for children in chain.children:
        below = jnp.mean(below[children], axis=1)
        parts.append(below)
    if len(parts) == 1:
        return texels
    if split:
        return SplitPyramid(texels, jnp.concatenate(parts[1:], axis=0) if len(parts) > 2 else parts[1])
    return jnp.concatenate(parts, axis=0)


def render(texels: jnp.ndarray, plan: GatherPlan) -> jnp.ndarray:
    """Samples compact texels (N, C) through `plan`: (H, W, C), or (V, H, W, C) for a batch.

    Values keep the texels' space (e.g. [-1, 1] while optimising); missed pixels are 0.
    """
    return sample(build_pyramid(texels, plan.chain), plan)


# `render` as one compiled program (per texel count and plan shape), for callers outside a jitted function:
# run eagerly, its dozen operations compile one by one, and each first compilation can wait seconds for a
# large program compiling in another thread (the main job's step, compiled beside the evaluation context)
render_compiled = jax.jit(render)


def sample(pyramid, plan: GatherPlan) -> jnp.ndarray:
    """`render` from a pyramid already built (`build_pyramid` with the plan's chain): plans that
    share a chain (a step's renders and its photos) share one pyramid, and one transpose of it.
    A `SplitPyramid` is read tap by tap from the part its row lies in (the other part's read is
    out of bounds and gives 0; its transpose drops it)."""
    return _weighted(plan, _taps(pyramid, plan.index))


def sample_many(pyramid, plans) -> tuple:
    """`sample` of each of several plans that share the pyramid's chain, their taps read by one
    gather: its transpose is one scatter-add into the pyramid (into each part of a split one),
    where a gather per plan would leave a cotangent of the pyramid's size per plan, all of them
    added up by every reader of the gradient. The taps are weighted together too, and the pixels
    (not the taps) split into the plans' images: slicing the (sum P, T, C) taps per plan would
    copy them, and its transpose pad each plan's part back to the taps' size and add the parts,
    three passes over T times the pixels' bytes in every step (docs/benchmarks.md §7). One plan:
    `sample` itself."""
    if len(plans) == 1:
        return (sample(pyramid, plans[0]),)
    taps = [p.index.shape[-1] for p in plans]
    if len(set(taps)) != 1:
        raise ValueError(f"sample_many: the plans read {taps} taps a pixel; one gather needs the same count")
    rows = [int(np.prod(p.index.shape[:-1])) for p in plans]
    values = _taps(pyramid, jnp.concatenate([p.index.reshape(n, -1) for p, n in zip(plans, rows)]))  # (sum P, T, C)
    with jax.named_scope("weighting"):
        weights = jnp.concatenate([p.weight.reshape(n, -1) for p, n in zip(plans, rows)]).astype(values.dtype)
        pixels = jnp.einsum("pt,ptc->pc", weights, values)                                        # (sum P, C)
    # split (its transpose a concatenation), not sliced (each slice's transpose a pixels-sized pad, then their sum)
    parts = jnp.split(pixels, np.cumsum(rows)[:-1], axis=0)
    return tuple(part.reshape(*plan.index.shape[:-2], plan.height, plan.width, values.shape[-1])
                 for plan, part in zip(plans, parts))


def _taps(pyramid, index: jnp.ndarray) -> jnp.ndarray:
    """(..., T, C): the pyramid's rows at `index` (..., T)."""
    with jax.named_scope("taps"):
        return _rows(pyramid, index)


def _rows(pyramid, index: jnp.ndarray) -> jnp.ndarray:
    if isinstance(pyramid, SplitPyramid):
        n, n_coarse = pyramid.texels.shape[0], pyramid.coarse.shape[0]
        fine = index < n
        return (pyramid.texels.at[jnp.where(fine, index, n)].get(mode="fill", fill_value=0)
                + pyramid.coarse.at[jnp.where(fine, n_coarse, index - n)].get(mode="fill", fill_value=0))
    return pyramid[index]


def _weighted(plan: GatherPlan, values: jnp.ndarray) -> jnp.ndarray:
    """The plan's image (..., H, W, C) from its taps' values (..., P, T, C)."""
    with jax.named_scope("weighting"):
        image = jnp.einsum("...pt,...ptc->...pc", plan.weight.astype(values.dtype), values)
    return image.reshape(*plan.index.shape[:-2], plan.height, plan.width, values.shape[-1])


def _tile_view(page: np.ndarray, b: int) -> np.ndarray:
    """(S/B, S/B, B, B, C) view of an (S, S, C) page."""
    g = page.shape[0] // b
    return page.reshape(g, b, g, b, -1).swapaxes(1, 2)


def compact(pages, space: TexelSpace) -> np.ndarray:
    """(N, C) texels read from full pages (a list of (S, S, C) arrays, one per page)."""
    b = space.tile
    channels = np.asarray(pages[0]).shape[-1]
    out = np.zeros((space.num_tiles, b, b, channels), np.float32)
    for page in range(space.layout.num_pages):
        sel = space.tile_page == page
        out[sel] = _tile_view(np.asarray(pages[page], np.float32), b)[space.tile_row[sel], space.tile_col[sel]]
    return out.reshape(-1, channels)


def coverage(space: TexelSpace) -> list[np.ndarray]:
    """Per page, (S, S) bool: the texel is a parameter (lies in a compact tile)."""
    masks = []
    for page in range(space.layout.num_pages):
        grid = np.zeros(space.tile_map[page].shape, bool)
        sel = space.tile_page == page
        grid[space.tile_row[sel], space.tile_col[sel]] = True
        masks.append(np.repeat(np.repeat(grid, space.tile, axis=0), space.tile, axis=1))
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


def expand(texels, space: TexelSpace, fill, *, observed=None, dilation: int = 8) -> list[np.ndarray]:
    """Full pages (S, S, C) float32 from compact texels (N, C).

    Texels outside `observed` ((N,) bool, e.g. view count > 0; default: every parameter) get
    `fill` (scalar or (C,)), except within `dilation` texels of an observed one, where seam
    dilation copies neighbouring values so that bilinear and mip sampling across chart borders
    in other renderers does not bleed the fill colour in.
    """
    b = space.tile
    texels = np.asarray(texels, np.float32)
    channels = texels.shape[-1]
    fill = np.broadcast_to(np.asarray(fill, np.float32), (channels,))
    tiles = texels.reshape(-1, b, b, channels)
    seen = np.ones(len(texels), bool) if observed is None else np.asarray(observed, bool)
    seen_tiles = seen.reshape(-1, b, b)
    pages = []
    for page, size in enumerate(space.layout.page_sizes):
        image = np.empty((size, size, channels), np.float32)
        image[:] = fill
        known = np.zeros((size, size), bool)
        sel = space.tile_page == page
        rows, cols = space.tile_row[sel], space.tile_col[sel]
        view, known_view = _tile_view(image, b), _tile_view(known[..., None], b)[..., 0]
        view[rows, cols] = np.where(seen_tiles[sel][..., None], tiles[sel], fill)
        known_view[rows, cols] = seen_tiles[sel]
        if dilation > 0:
            image = dilate(image, known, dilation)
        pages.append(image)
    return pages


def _neighbour_sum(x: np.ndarray, out: np.ndarray) -> np.ndarray:
    """out = the sum of the 4 neighbours of every texel of (S, S, C) x (S >= 2), edges clamped (a
    Neumann border), written in place: no padded copy, a few passes over memory per sweep."""
    np.add(x[:-2], x[2:], out=out[1:-1])
    np.add(x[0], x[1], out=out[0])
    np.add(x[-2], x[-1], out=out[-1])
    out[:, 1:-1] += x[:, :-2]
    out[:, 1:-1] += x[:, 2:]
    out[:, 0] += x[:, 0]
    out[:, 0] += x[:, 1]
    out[:, -1] += x[:, -2]
    out[:, -1] += x[:, -1]
    return out


def _relax(filled: np.ndarray, x: np.ndarray, w: np.ndarray, sweeps: int) -> np.ndarray:
    """`sweeps` of filled <- w x + (1 - w) mean4(filled) ((S, S, C) float32, w (S, S, 1)), in place."""
    if not sweeps:
        return filled
    own, rest = w * x, 1.0 - w
    if filled.shape[0] < 2:          # one texel: its own (clamped) neighbours are itself
        for _ in range(sweeps):
            filled = own + rest * filled
        return filled
    quarter, buffer = (0.25 * rest).astype(filled.dtype), np.empty_like(filled)
    for _ in range(sweeps):
        _neighbour_sum(filled, buffer)
        buffer *= quarter
        np.add(buffer, own, out=filled)
    return filled


def _upsample_bilinear(x: np.ndarray) -> np.ndarray:
    """(2S, 2S, C) bilinear upsampling of (S, S, C) with texel centres aligned (taps 3/4, 1/4)."""
    p = np.pad(x, ((1, 1), (1, 1), (0, 0)), mode="edge")
    rows = np.empty((2 * x.shape[0], x.shape[1] + 2, x.shape[2]), x.dtype)
    rows[0::2] = 0.75 * p[1:-1] + 0.25 * p[:-2]
    rows[1::2] = 0.75 * p[1:-1] + 0.25 * p[2:]
    out = np.empty((2 * x.shape[0], 2 * x.shape[1], x.shape[2]), x.dtype)
    out[:, 0::2] = 0.75 * rows[:, 1:-1] + 0.25 * rows[:, :-2]
    out[:, 1::2] = 0.75 * rows[:, 1:-1] + 0.25 * rows[:, 2:]
    return out


PUSH_PULL_SMOOTHING = 8     # relaxation sweeps at the finest level after the push; x2 per coarser level (<= 64)


def push_pull(page, weight, *, smoothing: int = PUSH_PULL_SMOOTHING) -> np.ndarray:
    """(S, S, C) float32 page whose low-evidence texels are filled from the others (pull-push).

    weight (S, S) in [0, 1] is how far each texel's own value is to be trusted (1: kept exactly,
    0: unobserved, replaced). Pull: level l+1 holds the weight-averaged value of each 2x2 block
    and the weight min(1, sum of the 4 weights). Push, coarse to fine: every texel gets
    w x + (1 - w) u, u the bilinear upsampling of the filled level above; then `smoothing` sweeps
    of x <- w x_own + (1 - w) mean4(x) relax the filled texels towards the harmonic fill (the
    discrete Laplace equation with the trusted texels fixed), which a linear ramp solves: a hole
    inside a ramp is filled with the ramp. A page with no weight anywhere is returned as it is.
    Computed in float32 with the sweeps in place (3x faster than float64 on a 4096² page, within
    2e-6 of it: below what a half-float or 8-bit page resolves).
    """
    page = np.asarray(page, np.float32)
    weight = np.clip(np.nan_to_num(np.asarray(weight, np.float32)), 0.0, 1.0)
    if page.ndim == 2:
        return push_pull(page[..., None], weight, smoothing=smoothing)[..., 0]
    if not weight.any() or weight.all() and (weight == 1.0).all():
        return page.copy()
    page = np.where(weight[..., None] > 0, np.nan_to_num(page), np.float32(0.0))
    levels = [(page, weight)]
    while levels[-1][0].shape[0] > 1 and levels[-1][0].shape[0] % 2 == 0:
        x, w = levels[-1]
        s = x.shape[0] // 2
        wx = (x * w[..., None]).reshape(s, 2, s, 2, -1).sum(axis=(1, 3))
        total = w.reshape(s, 2, s, 2).sum(axis=(1, 3))
        levels.append((np.where(total[..., None] > 0, wx / np.maximum(total, 1e-30)[..., None], np.float32(0.0)),
                       np.minimum(total, np.float32(1.0))))
    filled = levels[-1][0]
    if not (levels[-1][1] > 0).all():       # a coarsest level that is not one texel: its weighted mean
        x, w = levels[-1]
        filled = np.where(w[..., None] > 0, x, np.sum(x * w[..., None], axis=(0, 1)) / w.sum())
    for level, (x, w) in reversed(list(enumerate(levels[:-1]))):
        w3 = w[..., None]
        filled = w3 * x + (1.0 - w3) * _upsample_bilinear(filled)
        filled = _relax(filled, x, w3, smoothing * 2 ** min(level, 3) if (w < 1.0).any() else 0)
    return filled.astype(np.float32, copy=False)


def sample_pages(pages, fragments, object_page, *, sampler: str = "bilinear") -> list[np.ndarray]:
    """Per view, (H, W, C) float32 images of full texture pages seen through `fragments`.

    pages: one (S, S, C) array per page (square, power-of-two sides, row 0 at v = 1);
    object_page: the page of each object. Values keep the pages' space; missed pixels are 0.
    This is how ground-truth per-view maps are made from ground-truth textures: with exactly
    the gather the distillation renders with.
    """
    return list(iter_sample_pages(pages, fragments, object_page, sampler=sampler))


def iter_sample_pages(pages, fragments, object_page, *, sampler: str = "bilinear") -> Iterator[np.ndarray]:
    """`sample_pages`' images a view at a time (one view's image in memory, the rest the caller's)."""
    layout = TextureLayout(tuple(int(np.asarray(p).shape[0]) for p in pages), tuple(object_page),
                           mipmaps=sampler == "trilinear", tile_size=16 if sampler == "trilinear" else 1)
    space = build_texel_space(fragments, layout, sampler)
    texels = jnp.asarray(compact(pages, space))
    for frag in fragments:
        plan = build_gather_plans([frag], space, sampler)
        yield np.asarray(render_compiled(texels, plan))[0]

