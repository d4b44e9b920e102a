"""Texture layout: which page each object samples, page resolutions, and the full index space.

Pages are square, power-of-two sized. With `texture_layout="pages"` every object has its own
page (its UVs span [0, 1] of that page); with "atlas" all objects share page 0. A texel is
addressed by (page, level, row, col); row 0 is the top of the image (v = 1), so a UV maps to
continuous texel coordinates x = u * S - 0.5, y = (1 - v) * S - 0.5 at a level of side S.
Parameters are allocated in B x B tiles (see gather_plan.py).
"""

from __future__ import annotations

import dataclasses
import math
from typing import Sequence

import numpy as np

from jaxdistill.errors import InputError

MIN_PAGE_SIZE = 8
FOOTPRINT_QUANTILE = 0.001  # robust minimum: ignore the smallest 0.1 % of pixel footprints


@dataclasses.dataclass(frozen=True)
class TextureLayout:
    """Page sizes (square, power of two), the page of each object, and mip levels on/off."""

    page_sizes: tuple[int, ...]
    object_page: tuple[int, ...]
    mipmaps: bool = False
    tile_size: int = 1

    def __post_init__(self):
        for size in tuple(self.page_sizes) + (self.tile_size,):
            if size < 1 or size & (size - 1):
                raise ValueError(f"page and tile sizes must be powers of two, got {size}")

    @property
    def tile(self) -> int:
        """Side B of the sparse tiles parameters are allocated in: tile_size, or the smallest page."""
        return min(self.tile_size, min(self.page_sizes))

    @property
    def num_pages(self) -> int:
        return len(self.page_sizes)

    def num_levels(self, page: int) -> int:
        """Mip levels of a page: log2(size) + 1 with mipmaps (down to 1x1), else 1."""
        return int(math.log2(self.page_sizes[page])) + 1 if self.mipmaps else 1

    def full_size(self) -> int:
        """Texels in all full level-0 pages."""
        return int(sum(s * s for s in self.page_sizes))


def pixel_footprint(uv_grad: np.ndarray) -> np.ndarray:
    """(...,) UV distance covered by one pixel: the longer of |d(u,v)/dx| and |d(u,v)/dy|."""
    return np.maximum(np.linalg.norm(uv_grad[..., 0, :], axis=-1), np.linalg.norm(uv_grad[..., 1, :], axis=-1))


def power_of_two_at_most(x: float) -> int:
    """Nearest power of two to x in log scale (so a page never exceeds ~1.41x the needed side)."""
    return 1 << max(0, int(round(math.log2(max(x, 1.0)))))


def page_footprints(frag, object_page: Sequence[int], num_pages: int) -> np.ndarray:
    """(num_pages,) float64: per page, how finely this view resolves it, the FOOTPRINT_QUANTILE
    quantile of its hit pixels' footprints there (`pixel_footprint`, UV units per pixel); inf on
    pages the view does not see. `auto_page_sizes` takes the smallest over the views."""
    object_page = np.asarray(object_page)
    finest = np.full(num_pages, np.inf)
    hit = frag.object_id >= 0
    if not hit.any():
        return finest
    page = object_page[frag.object_id[hit]]
    foot = pixel_footprint(frag.uv_grad[hit])
    keep = np.isfinite(foot) & (foot > 0)
    for p in np.unique(page[keep]):
        finest[p] = float(np.quantile(foot[keep & (page == p)], FOOTPRINT_QUANTILE))
    return finest


def auto_page_sizes(fragments: Sequence, object_page: Sequence[int], num_pages: int, max_size: int,
                    min_size: int = MIN_PAGE_SIZE, footprints: np.ndarray | None = None) -> tuple[int, ...]:
    """Per page, the side at which the closest view sees about one texel per pixel, capped to max_size.

    For every hit pixel the footprint (`pixel_footprint`, UV units per pixel) says how finely
    that view resolves the page; the page side is 1 / (robust minimum footprint) rounded to a
    power of two, clamped to [min_size, max_size]. Pages nobody sees get min_size. `footprints`:
    the views' `page_footprints` (V, num_pages) when they were taken as the fragments were made
    (`fragments.FragmentRows` without uv_grad); else they are taken from `fragments`.
    """
    finest = np.full(num_pages, np.inf)
    rows = footprints if footprints is not None else (page_footprints(f, object_page, num_pages) for f in fragments)
    for row in rows:
        finest = np.minimum(finest, row)
    sizes = []
    for p in range(num_pages):
        side = min_size if not np.isfinite(finest[p]) else power_of_two_at_most(1.0 / finest[p])
        sizes.append(int(min(max(side, min_size), max_size)))
    return tuple(sizes)


def make_layout(num_objects: int, texture_layout: str, texture_size, fragments: Sequence, *,
                max_size: int = 4096, mipmaps: bool = False, tile_size: int | None = None,
                footprints: np.ndarray | None = None) -> TextureLayout:
    """Layout for a scene: `texture_size` is an int (every page that side) or "auto" (sized by
    `auto_page_sizes`, from `footprints` when given).

    tile_size (parameter allocation granularity) defaults to 1 (texel-exact) without mipmaps
    and 16 with them: scripts/bench_render.py measured these as the smallest and the fastest.
    """
    object_page = object_pages(num_objects, texture_layout)
    num_pages = max(object_page) + 1
    if texture_size == "auto":
        sizes = auto_page_sizes(fragments, object_page, num_pages, max_size, footprints=footprints)
    else:
        size = int(texture_size)
        if size < 1 or size & (size - 1):
            raise InputError.single("flags", "texture_size", f"must be a power of two or 'auto', got {texture_size!r}")
        sizes = (size,) * num_pages
    return sized_layout(num_objects, texture_layout, sizes, mipmaps=mipmaps, tile_size=tile_size)


def object_pages(num_objects: int, texture_layout: str) -> tuple[int, ...]:
    """Each object's page: its own ("pages") or one shared page ("atlas")."""
    if texture_layout == "pages":
        return tuple(range(num_objects))
    if texture_layout == "atlas":
        return (0,) * num_objects
    raise InputError.single("scene", "texture_layout", f"unknown layout {texture_layout!r}; use pages or atlas")


def sized_layout(num_objects: int, texture_layout: str, page_sizes: Sequence[int], *, mipmaps: bool = False,
                 tile_size: int | None = None) -> TextureLayout:
    """The layout `make_layout` gives with these page sizes (e.g. sizes another process chose)."""
    if tile_size is None:
        tile_size = 16 if mipmaps else 1
    return TextureLayout(page_sizes=tuple(int(s) for s in page_sizes), object_page=object_pages(num_objects,
                         texture_layout), mipmaps=mipmaps, tile_size=tile_size)
