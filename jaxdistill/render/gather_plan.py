"""Gather plans: per pixel, which texels to read and with what weights (built once, in NumPy).

Bilinear: 4 taps at level 0. Trilinear: 4 taps at each of two adjacent levels of a 2x2-mean
mip pyramid, the level chosen from the pixel's UV footprint as nvdiffrast's `texture` does
(lambda = log2(footprint * side), clamped to the page's levels). Addressing clamps to the page
edge. Taps of weight 0 (exact texel centres, lambda <= 0, misses) point at index 0 and never
make a texel a parameter.

Compact texel space: only texels that some tap of some view touches exist. A tap on level L
touches its level-(L-1) children (the pyramid is built from them), and so on down to level 0;
the level-0 texels reached this way are the parameters. The compact pyramid array stores level
0 (the parameters, sorted by full index) first, then every needed coarser texel, each defined
as the mean of 4 earlier entries (`MipChain.children`).
"""

from __future__ import annotations

import dataclasses
from typing import Sequence

import flax.struct
import jax.numpy as jnp
import numpy as np

from jaxdistill.render.fragments import Fragments
from jaxdistill.render.layout import TextureLayout, pixel_footprint

SAMPLERS = ("bilinear", "trilinear")


@flax.struct.dataclass
class MipChain:
    """children[L-1]: (N_L, 4) int32 indices into the compact pyramid of each level-L texel's children."""

    children: tuple = ()
    num_texels: int = flax.struct.field(pytree_node=False, default=0)


@flax.struct.dataclass
class GatherPlan:
    """Texel reads per pixel, for one view (P = H*W) or a batch of views (leading V axis).

    index (..., P, T) int32 into the compact pyramid; weight (..., P, T) float32, summing to 1
    on hit pixels and 0 on misses; hit (..., P) bool; chain: how coarser levels are built.
    """

    index: jnp.ndarray
    weight: jnp.ndarray
    hit: jnp.ndarray
    chain: MipChain
    height: int = flax.struct.field(pytree_node=False, default=0)
    width: int = flax.struct.field(pytree_node=False, default=0)

    def select(self, views) -> "GatherPlan":
        """The plan restricted to `views` (int or index array), sharing the mip chain."""
        return self.replace(index=self.index[views], weight=self.weight[views], hit=self.hit[views])

    @property
    def num_views(self) -> int:
        return int(self.index.shape[0]) if self.index.ndim == 3 else 1


@dataclasses.dataclass(frozen=True, eq=False)
class TexelSpace:
    """The compact texel set of a scene (NumPy, outside jit).

    texel_ids (N0,) int64 full level-0 indices of the parameters, sorted; texel_page,
    texel_row, texel_col (N0,) their address; level_ids[L] the sorted full indices of the
    compact level-L entries (level_ids[0] is texel_ids); level_start[L] their first position
    in the compact pyramid.
    """

    layout: TextureLayout
    level_ids: tuple[np.ndarray, ...]
    level_start: tuple[int, ...]
    texel_page: np.ndarray
    texel_row: np.ndarray
    texel_col: np.ndarray

    @property
    def texel_ids(self) -> np.ndarray:
        return self.level_ids[0]

    @property
    def num_texels(self) -> int:
        return int(len(self.level_ids[0]))

    @property
    def pyramid_size(self) -> int:
        return int(sum(len(ids) for ids in self.level_ids))

    def compact_index(self, level: int, full_ids: np.ndarray) -> np.ndarray:
        """Compact pyramid positions of level-`level` full indices (which must be in the set)."""
        pos = np.searchsorted(self.level_ids[level], full_ids)
        return (self.level_start[level] + pos).astype(np.int32)


def decode(layout: TextureLayout, full_ids: np.ndarray):
    """(page, level, row, col) int64 arrays of full-space indices."""
    table = layout.level_table()
    offsets = table[..., 0].ravel()
    sides = table[..., 1].ravel()
    present = np.nonzero(sides > 0)[0]
    order = present[np.argsort(offsets[present], kind="stable")]
    slot = order[np.searchsorted(offsets[order], full_ids, side="right") - 1]
    page, level = np.divmod(slot, layout.max_levels)
    local = full_ids - offsets[slot]
    row, col = np.divmod(local, sides[slot])
    return page, level, row, col


def view_taps(frag: Fragments, layout: TextureLayout, sampler: str):
    """Full-space taps of one view: (full (P, T) int64, weight (P, T) float32, level (P, T) int64)."""
    if sampler not in SAMPLERS:
        raise ValueError(f"unknown sampler {sampler!r}; use one of {SAMPLERS}")
    hit = frag.object_id.ravel() >= 0
    p_count = hit.size
    taps = 4 if sampler == "bilinear" else 8
    full = np.zeros((p_count, taps), np.int64)
    weight = np.zeros((p_count, taps), np.float32)
    level_out = np.zeros((p_count, taps), np.int64)
    if not hit.any():
        return full, weight, level_out
    page = np.asarray(layout.object_page)[frag.object_id.ravel()[hit]]
    uv = frag.uv.reshape(-1, 2)[hit].astype(np.float64)
    size = np.asarray(layout.page_sizes, np.int64)[page]
    levels = np.array([layout.num_levels(p) for p in range(layout.num_pages)])[page]
    table = layout.level_table()
    if sampler == "bilinear":
        plan = [(np.zeros_like(page), np.ones(len(page)))]
    else:
        foot = pixel_footprint(frag.uv_grad.reshape(-1, 2, 2)[hit]).astype(np.float64)
        with np.errstate(divide="ignore"):
            lam = np.log2(foot * size)
        lam = np.clip(np.nan_to_num(lam, nan=0.0, neginf=0.0, posinf=levels - 1.0), 0.0, levels - 1.0)
        base = np.floor(lam).astype(np.int64)
        frac = lam - base
        frac[base >= levels - 1] = 0.0
        base = np.minimum(base, levels - 1)
        plan = [(base, 1.0 - frac), (np.minimum(base + 1, levels - 1), frac)]
    for slot, (level, level_weight) in enumerate(plan):
        offset, side = table[page, level, 0], table[page, level, 1]
        x = uv[:, 0] * side - 0.5
        y = (1.0 - uv[:, 1]) * side - 0.5
        x0, y0 = np.floor(x), np.floor(y)
        fx, fy = x - x0, y - y0
        x0, y0 = x0.astype(np.int64), y0.astype(np.int64)
        corners = ((0, 0, (1 - fx) * (1 - fy)), (1, 0, fx * (1 - fy)), (0, 1, (1 - fx) * fy), (1, 1, fx * fy))
        for k, (dx, dy, w) in enumerate(corners):
            col = np.clip(x0 + dx, 0, side - 1)
            row = np.clip(y0 + dy, 0, side - 1)
            full[hit, 4 * slot + k] = offset + row * side + col
            weight[hit, 4 * slot + k] = w * level_weight
            level_out[hit, 4 * slot + k] = level
    full[weight == 0] = 0
    level_out[weight == 0] = 0
    return full, weight, level_out


def build_texel_space(fragments: Sequence[Fragments], layout: TextureLayout, sampler: str) -> TexelSpace:
    """The compact texel set touched by all views' taps (and the children of coarse taps)."""
    touched = [[] for _ in range(layout.max_levels)]
    for frag in fragments:
        full, weight, level = view_taps(frag, layout, sampler)
        used = weight > 0
        for lv in np.unique(level[used]):
            touched[lv].append(np.unique(full[used & (level == lv)]))
    level_ids = [np.unique(np.concatenate(t)) if t else np.zeros(0, np.int64) for t in touched]
    table = layout.level_table()
    for lv in range(layout.max_levels - 1, 0, -1):
        if len(level_ids[lv]) == 0:
            continue
        page, _, row, col = decode(layout, level_ids[lv])
        offset, side = table[page, lv - 1, 0], table[page, lv - 1, 1]
        kids = [offset + (2 * row + dy) * side + (2 * col + dx) for dy in (0, 1) for dx in (0, 1)]
        level_ids[lv - 1] = np.union1d(level_ids[lv - 1], np.concatenate(kids))
    while len(level_ids) > 1 and len(level_ids[-1]) == 0:
        level_ids.pop()
    starts = np.concatenate([[0], np.cumsum([len(ids) for ids in level_ids])[:-1]]).astype(np.int64)
    page, _, row, col = decode(layout, level_ids[0])
    return TexelSpace(layout=layout, level_ids=tuple(level_ids), level_start=tuple(int(s) for s in starts),
                      texel_page=page, texel_row=row, texel_col=col)


def mip_chain(space: TexelSpace) -> MipChain:
    """Children indices (compact) of every compact texel above level 0."""
    layout = space.layout
    table = layout.level_table()
    children = []
    for lv in range(1, len(space.level_ids)):
        page, _, row, col = decode(layout, space.level_ids[lv])
        offset, side = table[page, lv - 1, 0], table[page, lv - 1, 1]
        kids = np.stack([offset + (2 * row + dy) * side + (2 * col + dx) for dy in (0, 1) for dx in (0, 1)], axis=1)
        children.append(jnp.asarray(space.compact_index(lv - 1, kids)))
    return MipChain(children=tuple(children), num_texels=space.num_texels)


def build_gather_plans(fragments: Sequence[Fragments], space: TexelSpace, sampler: str) -> GatherPlan:
    """Batched gather plan of all views, indexing the compact pyramid of `space`."""
    if not fragments:
        raise ValueError("no views to plan")
    heights = {f.shape for f in fragments}
    if len(heights) != 1:
        raise ValueError(f"all views of one plan must share a resolution, got {sorted(heights)}")
    height, width = fragments[0].shape
    index, weight, hit = [], [], []
    for frag in fragments:
        full, w, level = view_taps(frag, space.layout, sampler)
        idx = np.zeros(full.shape, np.int32)
        for lv in np.unique(level[w > 0]):
            sel = (w > 0) & (level == lv)
            idx[sel] = space.compact_index(int(lv), full[sel])
        index.append(idx)
        weight.append(w)
        hit.append(frag.object_id.ravel() >= 0)
    return GatherPlan(index=jnp.asarray(np.stack(index)), weight=jnp.asarray(np.stack(weight)),
                      hit=jnp.asarray(np.stack(hit)), chain=mip_chain(space), height=height, width=width)

