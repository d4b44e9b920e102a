"""Gather plans: per pixel, which texels to read and with what weights (built once, in NumPy).

Bilinear: 4 taps at level 0. Trilinear: 4 taps at each of two adjacent levels of a 2x2-mean
mip pyramid, the level chosen from the pixel's UV footprint as nvdiffrast's `texture` does
(lambda = log2(footprint * side), clamped to the page's levels). Addressing clamps to the page
edge. Taps of weight 0 (exact texel centres, lambda <= 0, misses) point at index 0 and never
make a texel a parameter.

Compact texel space (sparse tiles, like GPU sparse-residency textures): pages are cut into
B x B tiles; a tile is a parameter block when some tap of some view reads it, directly or
through a coarser mip level built from it. Texels are stored tile after tile, row-major inside
a tile: `texels[(t * B + r) * B + c]`. The compact pyramid array that plans index is

    [tile levels 0..k (B = 2^k), each (N_tiles, B >> l, B >> l) flattened] +
    [coarse levels above one tile, only entries some tap needs, each the mean of 4 entries of
     the level below]

so in-tile levels are dense reshape-means and only the few coarse entries use index chains.
"""

from __future__ import annotations

import dataclasses
from typing import Callable, Sequence

import flax.struct
import jax.numpy as jnp
import numpy as np

from jaxdistill.io.view_rows import LazyViews
from jaxdistill.render.fragments import Fragments
from jaxdistill.render.layout import TextureLayout, pixel_footprint
from jaxdistill.threads import ordered_map, view_bar

SAMPLERS = ("bilinear", "trilinear")
TAPS = {"bilinear": 4, "trilinear": 8}        # texel reads per pixel


@flax.struct.dataclass
class MipChain:
    """How the compact pyramid is built from compact texels (N_tiles * B * B, C).

    children[j]: (N, 4) int32 indices of the children of level k+1+j's entries, counted within
    level k+j (level k: one entry per tile, so tile ids).
    """

    children: tuple = ()
    tile: int = flax.struct.field(pytree_node=False, default=1)
    in_tile_levels: int = flax.struct.field(pytree_node=False, default=1)


@flax.struct.dataclass
class GatherPlan:
    """Texel reads per pixel, for one view (P = H*W) or a batch of views (leading V axis).

    index (..., P, T) int32 into the compact pyramid; weight (..., P, T) float32, summing to 1
    on hit pixels and 0 on misses; hit (..., P) bool; chain: how coarser levels are built.
    A plan of all views may hold index, weight and hit in files read a few views at a time
    (`io.view_rows.ViewRows`): outside jit, take views with `select` (or `hit_images`) before
    computing on them.
    """

    index: jnp.ndarray
    weight: jnp.ndarray
    hit: jnp.ndarray
    chain: MipChain
    height: int = flax.struct.field(pytree_node=False, default=0)
    width: int = flax.struct.field(pytree_node=False, default=0)

    def hit_images(self) -> Sequence[np.ndarray]:
        """Per view, its (H, W) bool hit mask, read when asked for (a view at a time from a file)."""
        if self.index.ndim != 3:
            return [np.asarray(self.hit).reshape(self.height, self.width)]
        return LazyViews(self.num_views, lambda v: [np.asarray(self.hit[v]).reshape(self.height, self.width)])

    def select(self, views) -> "GatherPlan":
        """The plan restricted to `views` (int or index array), sharing the mip chain."""
        return self.replace(index=self.index[views], weight=self.weight[views], hit=self.hit[views])

    @property
    def num_views(self) -> int:
        return int(self.index.shape[0]) if self.index.ndim == 3 else 1


DENSE_GRID_CELLS = 1 << 20      # a grid of compact ids is held densely up to 4 MB of int32


def holds_dense(cells: int, entries: int) -> bool:
    """Whether a `TileGrid` of `cells` cells and `entries` ids is held as a dense table: when that
    is small, or no more than the sorted keys and ids would take (12 bytes an entry, 4 a cell)."""
    return cells <= DENSE_GRID_CELLS or 3 * entries >= cells


@dataclasses.dataclass(frozen=True, eq=False)
class TileGrid:
    """An int32 grid of compact ids, -1 where there is no entry, indexed like the dense array:
    `grid[rows, cols]` with integer arrays of any shape (out of range is an IndexError).

    Held densely where that is small (`holds_dense`); otherwise as the entries' sorted flat keys
    (row * cols + col, int64) and ids (int32), looked up by binary search, so memory grows with
    the entries and not with the page: a 4096² page of 1 x 1 tiles (bilinear) is 64 MB as a dense
    grid, 12 bytes per tile read as keys."""

    shape: tuple
    table: np.ndarray | None = None       # (rows, cols) int32, or None when sparse
    keys: np.ndarray | None = None        # (N,) int64 ascending, when sparse
    ids: np.ndarray | None = None         # (N,) int32, when sparse

    @classmethod
    def from_entries(cls, shape, rows, cols, ids) -> "TileGrid":
        """The grid with ids[i] at (rows[i], cols[i]) and -1 elsewhere."""
        shape = (int(shape[0]), int(shape[1]))
        rows, cols = np.asarray(rows, np.int64), np.asarray(cols, np.int64)
        ids = np.asarray(ids, np.int32)
        if holds_dense(shape[0] * shape[1], len(ids)):
            table = np.full(shape, -1, np.int32)
            table[rows, cols] = ids
            return cls(shape=shape, table=table)
        keys = rows * shape[1] + cols
        order = np.argsort(keys, kind="stable")
        return cls(shape=shape, keys=keys[order], ids=ids[order])

    @property
    def sparse(self) -> bool:
        return self.table is None

    @property
    def nbytes(self) -> int:
        return int(self.table.nbytes if self.table is not None else self.keys.nbytes + self.ids.nbytes)

    def __getitem__(self, index) -> np.ndarray:
        rows, cols = np.broadcast_arrays(*(np.asarray(a, np.int64) for a in index))
        if rows.size and (rows.min() < 0 or cols.min() < 0 or rows.max() >= self.shape[0] or cols.max() >= self.shape[1]):
            raise IndexError(f"a cell outside the {self.shape[0]} x {self.shape[1]} grid")   # held either way
        if self.table is not None:
            return self.table[rows, cols]
        if not len(self.keys):
            return np.full(rows.shape, -1, np.int32)
        wanted = rows * self.shape[1] + cols
        at = np.minimum(np.searchsorted(self.keys, wanted), len(self.keys) - 1)
        return np.where(self.keys[at] == wanted, self.ids[at], np.int32(-1))

    def dense(self) -> np.ndarray:
        """The (rows, cols) int32 grid."""
        if self.table is not None:
            return self.table
        out = np.full(self.shape, -1, np.int32)
        out.reshape(-1)[self.keys] = self.ids
        return out


@dataclasses.dataclass(frozen=True, eq=False)
class TexelSpace:
    """The compact tile set of a scene (NumPy, outside jit).

    tile_page, tile_row, tile_col (N_tiles,) int64: page and tile-grid position of each tile,
    sorted by (page, row, col). tile_map[p]: a (S_p / B, S_p / B) `TileGrid` of compact tile ids or -1.
    coarse_maps[p][j]: index of each level-(k+1+j) entry of page p within that level, or -1;
    children[j]: (N, 4) indices, within level k+j, of the children of level k+1+j's entries.
    """

    layout: TextureLayout
    tile_page: np.ndarray
    tile_row: np.ndarray
    tile_col: np.ndarray
    tile_map: tuple
    coarse_maps: tuple
    children: tuple

    @property
    def tile(self) -> int:
        return self.layout.tile

    @property
    def num_tiles(self) -> int:
        return int(len(self.tile_page))

    @property
    def num_texels(self) -> int:
        return self.num_tiles * self.tile * self.tile

    @property
    def in_tile_levels(self) -> int:
        """Levels stored inside a tile: log2(B) + 1 with mipmaps, else 1."""
        return int(np.log2(self.tile)) + 1 if self.layout.mipmaps else 1

    @property
    def pyramid_size(self) -> int:
        fine = sum(self.num_tiles * (self.tile >> lv) ** 2 for lv in range(self.in_tile_levels))
        return int(fine + sum(len(c) for c in self.children))

    def level_offset(self, level: int) -> int:
        """Start of in-tile level `level` in the compact pyramid."""
        return int(sum(self.num_tiles * (self.tile >> lv) ** 2 for lv in range(level)))

    def coarse_offset(self, j: int) -> int:
        """Start of coarse level k + j (j >= 1) in the compact pyramid."""
        return self.level_offset(self.in_tile_levels) + int(sum(len(c) for c in self.children[:j - 1]))

    def texel_index(self, page, row, col) -> np.ndarray:
        """Compact level-0 texel index of (page, row, col) arrays; -1 where not a parameter."""
        page, row, col = (np.asarray(a, np.int64) for a in (page, row, col))
        b = self.tile
        out = np.full(page.shape, -1, np.int64)
        for p in np.unique(page):
            sel = page == p
            t = self.tile_map[p][row[sel] // b, col[sel] // b].astype(np.int64)
            out[sel] = np.where(t >= 0, (t * b + row[sel] % b) * b + col[sel] % b, -1)
        return out


def view_taps(frag: Fragments, layout: TextureLayout, sampler: str):
    """Taps of one view, each (P, T): page, level, row, col (int64) and weight (float32)."""
    if sampler not in SAMPLERS:
        raise ValueError(f"unknown sampler {sampler!r}; use one of {SAMPLERS}")
    if sampler == "trilinear" and not layout.mipmaps:
        raise ValueError("the trilinear sampler needs a layout with mipmaps=True")
    hit = frag.object_id.ravel() >= 0
    taps = TAPS[sampler]
    shape = (hit.size, taps)
    if not hit.any():
        return tuple(np.zeros(shape, np.int64) for _ in range(4)) + (np.zeros(shape, np.float32),)
    page = np.asarray(layout.object_page)[frag.object_id.ravel()[hit]]
    uv = frag.uv.reshape(-1, 2)[hit].astype(np.float64)
    size = np.asarray(layout.page_sizes, np.int64)[page]
    levels = np.array([layout.num_levels(p) for p in range(layout.num_pages)])[page]
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
    # the hit pixels' taps (n, T), tap j = 4 * slot + corner, written into the (P, T) arrays once
    level_hit = np.repeat(np.stack([level for level, _ in plan], axis=1), 4, axis=1)
    row_hit, col_hit = np.empty(level_hit.shape, np.int64), np.empty(level_hit.shape, np.int64)
    weight_hit = np.empty(level_hit.shape, np.float32)
    for slot, (level, level_weight) in enumerate(plan):
        side = size >> level
        x = uv[:, 0] * side - 0.5
        y = (1.0 - uv[:, 1]) * side - 0.5
        x0, y0 = np.floor(x), np.floor(y)
        fx, fy = x - x0, y - y0
        x0, y0 = x0.astype(np.int64), y0.astype(np.int64)
        corners = ((0, 0, (1 - fx) * (1 - fy)), (1, 0, fx * (1 - fy)), (0, 1, (1 - fx) * fy), (1, 1, fx * fy))
        for k, (dx, dy, w) in enumerate(corners):
            j = 4 * slot + k
            col_hit[:, j] = np.clip(x0 + dx, 0, side - 1)
            row_hit[:, j] = np.clip(y0 + dy, 0, side - 1)
            weight_hit[:, j] = w * level_weight
    page_hit = np.repeat(page[:, None], taps, axis=1)
    unused = weight_hit == 0
    out = []
    for a in (page_hit, level_hit, row_hit, col_hit, weight_hit):
        a[unused] = 0
        full = np.zeros(shape, a.dtype)
        full[hit] = a
        out.append(full)
    return tuple(out)


def _upsample(mask: np.ndarray) -> np.ndarray:
    return np.repeat(np.repeat(mask, 2, axis=0), 2, axis=1)


def build_texel_space(fragments: Sequence[Fragments], layout: TextureLayout, sampler: str) -> TexelSpace:
    """The compact tiles read by all views' taps, directly or through coarse mip entries."""
    return space_from_needs(texel_needs(fragments, layout, sampler), layout)


def texel_needs(fragments: Sequence[Fragments], layout: TextureLayout, sampler: str, *,
                count: int | None = None) -> list[list[np.ndarray]]:
    """need[p][j]: bool grid of the level-(k+j) entries of page p (j = 0: the tile grid) that the
    views' taps read. Views' needs combine by OR (`space_from_needs` takes the union): processes
    holding different views can take each other's. `count`: how many views `fragments` yields
    (the progress bar's total), where it has no length (a chain of several sizes' views)."""
    b = layout.tile
    k = int(np.log2(b))
    need = [[np.zeros((s >> (k + j), s >> (k + j)), bool) for j in range(layout.num_levels(p) - k if layout.mipmaps else 1)]
            for p, s in enumerate(layout.page_sizes)]

    def marks(frag):          # per (page, j) the entries of need[page][j] that the view's taps read
        page, level, row, col, weight = view_taps(frag, layout, sampler)
        used = np.flatnonzero(weight.reshape(-1) > 0)
        page, level, row, col = (a.reshape(-1)[used] for a in (page, level, row, col))
        fine = level <= k
        shift = np.where(fine, k - level, 0)                 # level <= k: the tile of the entry
        j = np.where(fine, 0, level - k)
        out = []
        for group in _groups(page * (int(j.max(initial=0)) + 1) + j):
            out.append((int(page[group[0]]), int(j[group[0]]), row[group] >> shift[group], col[group] >> shift[group]))
        return out

    total = count if count is not None else len(fragments)
    for view_marks in view_bar(ordered_map(marks, fragments), "texel needs", total):
        for p, j, rows, cols in view_marks:
            need[p][j][rows, cols] = True
    return need


def space_from_needs(need: list[list[np.ndarray]], layout: TextureLayout) -> TexelSpace:
    """The compact texel space of `texel_needs`' grids (modified in place: a needed coarse entry
    needs its 4 children, down to the tiles; a page's tile grid is let go once numbered)."""
    for grids in need:  # a needed coarse entry needs its 4 children, down to the tiles
        for j in range(len(grids) - 1, 0, -1):
            grids[j - 1] |= _upsample(grids[j])
    tile_page, tile_row, tile_col, tile_map = [], [], [], []
    count = 0
    for p, grids in enumerate(need):
        rows, cols = np.nonzero(grids[0])
        tile_map.append(TileGrid.from_entries(grids[0].shape, rows, cols, np.arange(count, count + len(rows))))
        count += len(rows)
        tile_page.append(np.full(len(rows), p, np.int64))
        tile_row.append(rows.astype(np.int64))
        tile_col.append(cols.astype(np.int64))
        grids[0] = None                                  # the page's bool grid is no longer needed
    num_tiles = count
    # Coarse levels k+1, k+2, ...: entries numbered within their level; children index the
    # level below (level k has one entry per tile, in tile order, so tile ids index it).
    coarse_maps = [[] for _ in need]
    children = []
    prev_maps = tile_map
    for j in range(1, max(len(g) for g in need)):
        kids, maps, count = [], [], 0
        for p, grids in enumerate(need):
            if j >= len(grids):
                maps.append(None)
                continue
            rows, cols = np.nonzero(grids[j])
            ids = TileGrid.from_entries(grids[j].shape, rows, cols, np.arange(count, count + len(rows)))
            count += len(rows)
            below = prev_maps[p]
            kids.append(np.stack([below[2 * rows + dy, 2 * cols + dx] for dy in (0, 1) for dx in (0, 1)], axis=1))
            maps.append(ids)
            coarse_maps[p].append(ids)
        children.append(np.concatenate(kids).astype(np.int32) if kids else np.zeros((0, 4), np.int32))
        prev_maps = maps
    return TexelSpace(layout=layout, tile_page=np.concatenate(tile_page), tile_row=np.concatenate(tile_row),
                      tile_col=np.concatenate(tile_col), tile_map=tuple(tile_map),
                      coarse_maps=tuple(tuple(m) for m in coarse_maps), children=tuple(children))


def _groups(key: np.ndarray) -> list[np.ndarray]:
    """The positions of each distinct value of the small non-negative int `key`, ascending by
    value, each group in position order: one stable sort (a counting sort for int16 keys)."""
    if not len(key):
        return []
    order = np.argsort(key.astype(np.int16) if key.max() < 2 ** 15 else key, kind="stable")
    return np.split(order, np.flatnonzero(np.diff(key[order])) + 1)


def tap_indices(space: TexelSpace, page, level, row, col, weight) -> np.ndarray:
    """Compact pyramid index of each tap (0 where weight is 0). The used taps are grouped by
    (page, level) (`_groups`), so each group's lookup reads only its own taps."""
    b = space.tile
    k = int(np.log2(b))
    out = np.zeros(np.shape(page), np.int64)
    used = np.flatnonzero(np.asarray(weight).ravel() > 0)
    if not used.size:
        return out
    page, level, row, col = (np.asarray(a).ravel()[used] for a in (page, level, row, col))
    values = np.empty(len(used), np.int64)
    for group in _groups(page * (int(level.max()) + 1) + level):
        p, lv = int(page[group[0]]), int(level[group[0]])
        r, c = row[group], col[group]
        if lv <= k:
            side = b >> lv
            t = space.tile_map[p][r // side, c // side].astype(np.int64)
            values[group] = space.level_offset(lv) + (t * side + r % side) * side + c % side
        else:
            entry = space.coarse_maps[p][lv - k - 1][r, c].astype(np.int64)
            values[group] = np.where(entry >= 0, space.coarse_offset(lv - k) + entry, -1)
    if (values < 0).any():
        raise AssertionError("a tap reads a texel outside the compact space (plan and space disagree)")
    out.reshape(-1)[used] = values
    return out


def build_gather_plans(fragments: Sequence[Fragments], space: TexelSpace, sampler: str, *,
                       empty: Callable | None = None) -> GatherPlan:
    """Batched gather plan of all views (same resolution), indexing the compact pyramid of `space`,
    built one view at a time into its arrays: `empty(name, shape, dtype)` allocates the (V, P, T)
    "plan_index" and "plan_weight" arrays and the (V, P) "plan_hit" mask (default NumPy; anything
    that takes `a[v] = row` and gives rows by `a[ids]`, such as the file-backed `io.view_rows.ViewRows`)."""
    if not fragments:
        raise ValueError("no views to plan")
    shapes = {f.shape for f in fragments}
    if len(shapes) != 1:
        raise ValueError(f"all views of one plan must share a resolution, got {sorted(shapes)}")
    if sampler not in SAMPLERS:
        raise ValueError(f"unknown sampler {sampler!r}; use one of {SAMPLERS}")
    height, width = fragments[0].shape
    shape = (len(fragments), height * width, TAPS[sampler])
    empty = empty or (lambda name, shape, dtype: np.empty(shape, dtype))
    index, weight = empty("plan_index", shape, np.int32), empty("plan_weight", shape, np.float32)
    hit = empty("plan_hit", shape[:2], bool)

    def plan_view(frag):
        page, level, row, col, w = view_taps(frag, space.layout, sampler)
        return tap_indices(space, page, level, row, col, w).astype(np.int32), w, frag.object_id.ravel() >= 0

    planned = view_bar(ordered_map(plan_view, fragments), "gather plans", len(fragments))
    for v, (view_index, view_weight, view_hit) in enumerate(planned):   # in order
        index[v], weight[v], hit[v] = view_index, view_weight, view_hit
    chain = MipChain(children=tuple(jnp.asarray(c) for c in space.children), tile=space.tile,
                     in_tile_levels=space.in_tile_levels)
    return GatherPlan(index=index, weight=weight, hit=hit, chain=chain, height=height, width=width)


def tile_set_arrays(space: TexelSpace) -> dict[str, np.ndarray]:
    """The level-0 tile set of `space` as plain arrays (for np.savez): enough to expand and
    compact texels (`sampler.expand` / `compact`) without the scene, e.g. in a viewer."""
    return {"page_sizes": np.asarray(space.layout.page_sizes, np.int64),
            "object_page": np.asarray(space.layout.object_page, np.int64),
            "tile": np.asarray(space.tile, np.int64), "tile_page": space.tile_page,
            "tile_row": space.tile_row, "tile_col": space.tile_col}


def space_from_tile_set(arrays) -> TexelSpace:
    """The TexelSpace of `tile_set_arrays`' output: level 0 only (no mip levels)."""
    page_sizes = tuple(int(s) for s in arrays["page_sizes"])
    tile = int(arrays["tile"])
    layout = TextureLayout(page_sizes=page_sizes, object_page=tuple(int(p) for p in arrays["object_page"]),
                           mipmaps=False, tile_size=tile)
    tile_page, tile_row, tile_col = (np.asarray(arrays[k], np.int64) for k in ("tile_page", "tile_row", "tile_col"))
    tile_map = []
    for p, size in enumerate(page_sizes):
        ids = np.nonzero(tile_page == p)[0]
        tile_map.append(TileGrid.from_entries((size // tile, size // tile), tile_row[ids], tile_col[ids], ids))
    return TexelSpace(layout=layout, tile_page=tile_page, tile_row=tile_row, tile_col=tile_col,
                      tile_map=tuple(tile_map), coarse_maps=tuple(() for _ in page_sizes), children=())
