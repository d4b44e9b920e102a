"""xatlas charts and packing: one xatlas call per chunk of an object at a texel density, spatial
chunks of large objects, and the packing of several chunk atlases into one (xatlas again, or a
shelf packer). Texel coordinates here have xatlas's v down.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from typing import Sequence

import numpy as np

log = logging.getLogger(__name__)

CHART_FACES = 1000              # chart growth cap (in mean face areas): keeps xatlas linear in faces


def xatlas_version() -> str:
    try:
        from importlib.metadata import version

        return version("xatlas")
    except Exception:   # noqa: BLE001 - an unknown version only weakens the cache key
        return "unknown"


def face_areas(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    tri = vertices[faces]
    return 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)


@dataclasses.dataclass(frozen=True, eq=False)
class _Atlas:
    """One xatlas result: per-vertex texel coordinates (V', 2) float64 in [0, w] x [0, h] with
    xatlas's v down, faces (F, 3) into them (same order as the input faces), atlas size w x h."""

    texels: np.ndarray
    faces: np.ndarray
    width: int
    height: int


def _atlas_result(atlas, faces: np.ndarray) -> _Atlas:
    if atlas.atlas_count != 1:
        raise RuntimeError(f"xatlas made {atlas.atlas_count} atlases, expected one")
    vmapping, indices, uvs = atlas[0]
    indices = np.asarray(indices, np.int64).reshape(-1, 3)
    if indices.shape != faces.shape or not (np.asarray(vmapping)[indices] == faces).all():
        raise RuntimeError("xatlas changed the faces (order or count); cannot map UVs back")
    w, h = int(atlas.width), int(atlas.height)
    return _Atlas(np.asarray(uvs, np.float64) * (w, h), indices, w, h)   # xatlas: normalised by w, h


def xatlas_chunk(vertices: np.ndarray, faces: np.ndarray, texels_per_unit: float, padding: int) -> _Atlas:
    """One xatlas call (charts and packing) on a mesh (V, 3), (F, 3) at `texels_per_unit`.

    Coordinates are centred and scaled so that the median face area is about 1 before they
    reach xatlas (float32, area epsilons), the density rescaled to match.
    """
    import xatlas

    areas = face_areas(vertices, faces)
    positive = areas[areas > 0]
    scale = math.sqrt(float(np.median(positive))) if len(positive) else 1.0
    local = (vertices - vertices.mean(axis=0)) / scale
    atlas = xatlas.Atlas()
    atlas.add_mesh(np.ascontiguousarray(local, np.float32), np.ascontiguousarray(faces, np.uint32))
    chart = xatlas.ChartOptions()
    chart.max_chart_area = float(CHART_FACES * areas.mean() / scale**2) if len(faces) > CHART_FACES else 0.0
    pack = xatlas.PackOptions()
    pack.padding = int(padding)
    pack.texels_per_unit = float(texels_per_unit * scale)
    atlas.generate(chart_options=chart, pack_options=pack)
    return _atlas_result(atlas, faces)


def merge_atlases(parts: Sequence[_Atlas], padding: int) -> tuple[np.ndarray, int, int]:
    """Per-corner texel coordinates (sum F, 3, 2) of chunk atlases packed into one (v down), w, h.

    xatlas repacks the charts of all chunks together (a UV mesh at one texel per unit, so the
    density stays); if that fails, the chunk rectangles are shelf-packed instead.
    """
    try:
        return _repack(parts, padding)
    except RuntimeError as err:
        log.warning("xatlas could not repack the chunk atlases (%s): shelf-packing them instead", err)
    corner, width, height = shelf_pack([(p.width, p.height) for p in parts], padding)
    out = np.concatenate([p.texels[p.faces] + c for p, c in zip(parts, corner)])
    return out, width, height


def _repack(parts: Sequence[_Atlas], padding: int) -> tuple[np.ndarray, int, int]:
    """xatlas packing of the charts (UV islands) of all chunk atlases at one texel per unit."""
    import xatlas

    offsets = np.cumsum([0] + [len(p.texels) for p in parts])[:-1]
    texels = np.concatenate([p.texels for p in parts])
    faces = np.concatenate([p.faces + o for p, o in zip(parts, offsets)])
    atlas = xatlas.Atlas()
    atlas.add_uv_mesh(np.ascontiguousarray(texels, np.float32), np.ascontiguousarray(faces, np.uint32))
    pack = xatlas.PackOptions()
    pack.padding = int(padding)
    pack.texels_per_unit = 1.0
    atlas.generate(pack_options=pack)
    merged = _atlas_result(atlas, faces)
    return merged.texels[merged.faces], merged.width, merged.height


def split_chunks(centroids: np.ndarray, chunk_faces: int) -> list[np.ndarray]:
    """Face index arrays of spatial chunks of <= chunk_faces faces each: recursive median split
    of the centroids (F, 3) along the longest axis of their bounding box (deterministic order)."""
    out, stack = [], [np.arange(len(centroids))]
    while stack:
        idx = stack.pop()
        if len(idx) <= chunk_faces:
            out.append(np.sort(idx))
            continue
        c = centroids[idx]
        axis = int(np.argmax(c.max(axis=0) - c.min(axis=0)))
        half = len(idx) // 2
        order = np.argpartition(c[:, axis], half, kind="introselect")
        stack += [idx[order[half:]], idx[order[:half]]]           # lower half popped first
    return out


def _shelves(sizes: np.ndarray, order: np.ndarray, padding: int, target: int) -> tuple[np.ndarray, int, int]:
    """Rows of rectangles (in `order`) filled left to right up to `target` wide: (offsets, width, height)."""
    offsets = np.zeros_like(sizes)
    x = y = shelf = width = 0
    for i in order:
        if x > 0 and x + sizes[i, 0] > target:
            x, y, shelf = 0, y + shelf + padding, 0
        offsets[i] = (x, y)
        width = max(width, x + int(sizes[i, 0]))
        x += int(sizes[i, 0]) + padding
        shelf = max(shelf, int(sizes[i, 1]))
    return offsets, width, y + shelf


def shelf_pack(sizes: Sequence[tuple[int, int]], padding: int) -> tuple[np.ndarray, int, int]:
    """Places rectangles (w, h) without overlap, `padding` apart: (offsets (N, 2) int, width, height).

    Shelves of the tallest-first rectangles, rows filled left to right up to a width limit; of
    the limits that end a row after 1, 2, ... rectangles, the one with the smallest square
    (max(width, height), then area) wins: the result goes into a square page.
    """
    sizes = np.asarray(sizes, np.int64).reshape(-1, 2)
    order = np.argsort(-sizes[:, 1], kind="stable")
    targets = np.unique(np.cumsum(sizes[order, 0] + padding) - padding)
    best = None
    for target in targets:
        offsets, width, height = _shelves(sizes, order, padding, int(target))
        score = (max(width, height), width * height)
        if best is None or score < best[0]:
            best = (score, offsets, width, height)
    return best[1], best[2], best[3]
