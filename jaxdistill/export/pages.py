"""Map pages on disk: page names and file paths, maps as float32 EXR and 8-bit PNG, evidence pages.

Texture pages come in FILE space, as float32 NumPy arrays: `pages[map_name]` is a list with
one (S_p, S_p, C) array per page p (row 0 is v = 1, texel (r, c) centre at
u = (c + 0.5) / S, v = 1 - (r + 0.5) / S; all maps share the page sizes). Values:

    albedo      C=3  linear RGB in [0, 1]
    irradiance  C=3  linear, >= 0 (may exceed 1)
    roughness   C=1  perceptual roughness in [0, 1] (as glTF uses it)
    metallic    C=1  in [0, 1]
    normal      C=3  WORLD-space unit vectors in [-1, 1] (zero-length where unknown)

`object_page[i]` is the page of object i: every object its own page ("pages" layout) or all
on page 0 ("atlas" layout).
"""

from __future__ import annotations

import re
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np

from jaxdistill import MAP_NAMES
from jaxdistill.io import images as imageio
from jaxdistill.scene.maps import png_pixels

MAP_CHANNELS = {"albedo": 3, "normal": 3, "roughness": 1, "metallic": 1, "irradiance": 3}


def _num_pages(object_page: Sequence[int]) -> int:
    object_page = np.asarray(object_page, np.int64)
    if object_page.ndim != 1 or len(object_page) == 0:
        raise ValueError(f"object_page: expected one page index per object, got shape {object_page.shape}")
    if object_page.min() < 0:
        raise ValueError(f"object_page: page indices must be >= 0, got {object_page.tolist()}")
    return int(object_page.max()) + 1


def check_pages(pages: Mapping[str, Sequence[np.ndarray]], object_page: Sequence[int]) -> dict:
    """The pages as float32 arrays after checking names, channel counts, page counts and sizes."""
    if not pages:
        raise ValueError("pages: no maps given")
    num_pages = _num_pages(object_page)
    checked, sizes, first = {}, None, None
    for name, maps in pages.items():
        if name not in MAP_CHANNELS:
            raise ValueError(f"pages: unknown map {name!r}; known maps: {', '.join(MAP_NAMES)}")
        if len(maps) != num_pages:
            raise ValueError(f"map {name!r}: {len(maps)} pages, but object_page uses {num_pages} "
                             f"(pages 0..{num_pages - 1})")
        arrays = []
        for p, page in enumerate(maps):
            page = np.asarray(page, np.float32)
            if page.ndim == 2 and MAP_CHANNELS[name] == 1:
                page = page[:, :, None]
            if page.ndim != 3 or page.shape[0] != page.shape[1] or page.shape[2] != MAP_CHANNELS[name]:
                raise ValueError(f"map {name!r} page {p}: expected a square (S, S, {MAP_CHANNELS[name]}) "
                                 f"array, got shape {page.shape}")
            arrays.append(page)
        page_sizes = [a.shape[0] for a in arrays]
        if sizes is None:
            sizes, first = page_sizes, name
        elif page_sizes != sizes:
            p = next(i for i, (a, b) in enumerate(zip(page_sizes, sizes)) if a != b)
            raise ValueError(f"map {name!r} page {p} is {page_sizes[p]}x{page_sizes[p]} but map {first!r} "
                             f"page {p} is {sizes[p]}x{sizes[p]}; all maps must share the page sizes")
        checked[name] = arrays
    return checked


def page_names(object_names: Sequence[str], object_page: Sequence[int]) -> list[str]:
    """A file-name stem per page: the object's name when the page holds exactly one object,
    else `page_000` style. Characters outside [A-Za-z0-9._-] become '_'; a stem that would
    repeat another gets `_<page>` appended, so the stems are unique."""
    object_page = np.asarray(object_page, np.int64)
    if len(object_page) != len(object_names):
        raise ValueError(f"object_page: {len(object_page)} entries for {len(object_names)} object names")
    names, used = [], set()
    for p in range(_num_pages(object_page)):
        members = np.nonzero(object_page == p)[0]
        name = f"page_{p:03d}"
        if len(members) == 1:
            name = re.sub(r"[^A-Za-z0-9._-]", "_", str(object_names[members[0]])).strip(".") or name
        if name in used:
            name = f"{name}_{p:03d}"
        used.add(name)
        names.append(name)
    return names


def page_file(root, name: str, stems: Sequence[str], page: int, suffix: str) -> Path:
    """Where page `page` of map `name` lies under `root`: `root/<name><suffix>` with one page,
    else `root/<name>/<stem><suffix>` (`stems` from `page_names`)."""
    base = Path(root) / name if len(stems) == 1 else Path(root) / name / stems[page]
    return base.with_name(base.name + suffix)


EVIDENCE_DIR = "evidence"


def write_evidence(out_dir, pages: Mapping[str, Sequence[np.ndarray]], object_names: Sequence[str],
                   object_page: Sequence[int]) -> list[Path]:
    """Writes per-texel evidence pages, one float32 channel each, as EXR under
    `out_dir/evidence/` in the maps' page naming (`page_file`): e.g. `visibility` (view
    counts) and `disagreement_<map>` (the views' spread, NaN where fewer than two views)."""
    stems = page_names(object_names, object_page)
    root = Path(out_dir) / EVIDENCE_DIR
    written = []
    for name, per_page in pages.items():
        if len(per_page) != len(stems):
            raise ValueError(f"evidence {name!r}: {len(per_page)} pages, but object_page uses {len(stems)}")
        for p, page in enumerate(per_page):
            path = page_file(root, name, stems, p, ".exr")
            imageio.write_image(path, np.asarray(page, np.float32))
            written.append(path)
    return written


def write_maps(out_dir, pages: Mapping[str, Sequence[np.ndarray]], object_names: Sequence[str],
               object_page: Sequence[int]) -> list[Path]:
    """Writes every map as float32 EXR (linear, HDR kept) and 8-bit PNG; returns the paths.

    One page: `out_dir/maps/<map>.exr|.png`; several: `out_dir/maps/<map>/<page_name>.exr|.png`
    (`page_names`). PNGs: albedo and irradiance sRGB-encoded (irradiance clipped to [0, 1]),
    roughness and metallic grey values as they are, normal as (n + 1) / 2 (world space, no sRGB).
    """
    pages = check_pages(pages, object_page)
    stems = page_names(object_names, object_page)
    root = Path(out_dir) / "maps"
    jobs = [(name, page, page_file(root, name, stems, p, ".exr"), page_file(root, name, stems, p, ".png"))
            for name in [m for m in MAP_NAMES if m in pages] for p, page in enumerate(pages[name])]

    def write(job):
        name, page, exr, png = job
        imageio.write_image(exr, page)
        pixels, encode = png_pixels(name, page)
        imageio.write_image(png, pixels, encode_srgb=encode)

    # two pages at a time: OpenImageIO encodes PNGs in the calling thread, outside the GIL (its EXR
    # writes are threaded already); the bedroom's 150 pages 11.8 s -> 7.3 s on 2 cores
    with ThreadPoolExecutor(max_workers=2) as pool:
        list(pool.map(write, jobs))                 # re-raises a page's error
    return [path for _, _, exr, png in jobs for path in (exr, png)]


def to_uint8(x: np.ndarray) -> np.ndarray:
    return np.round(np.clip(np.nan_to_num(x), 0.0, 1.0) * 255.0).astype(np.uint8)
