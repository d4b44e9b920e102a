"""UV charts on texture pages: which texels the faces of a page's objects cover, how far each is trusted.

Every object's UV triangles are rasterised into its page (texel (r, c) centre at
u = (c + 0.5) / S, v = 1 - (r + 0.5) / S, row 0 is v = 1) and the covered region grown by a few
texels (`chart_coverage`); a texel's distilled value is kept as far as its evidence says inside
the charts (`page_trust`, `texel_trust`). `object_page[i]` is the page of object i.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from jaxdistill.render.sampler import compact
from jaxdistill.scene.model import Mesh

RASTER_CHUNK = 1 << 22  # candidate texels per rasterisation batch (bounds memory)


def check_mesh_pages(mesh: Mesh, object_page: Sequence[int], num_pages: int) -> np.ndarray:
    """(F,) page of every face, after checking object_page against the mesh and the page count."""
    object_page = np.asarray(object_page, np.int64)
    if len(object_page) != len(mesh.object_names):
        raise ValueError(f"object_page: {len(object_page)} entries for {len(mesh.object_names)} mesh objects")
    if object_page.min() < 0 or object_page.max() >= num_pages:
        raise ValueError(f"object_page: page indices must lie in [0, {num_pages - 1}] "
                         f"({num_pages} pages given), got {object_page.tolist()}")
    return object_page[mesh.face_object]


def rasterise_uv(uv: np.ndarray, face_ids: np.ndarray, size: int) -> np.ndarray:
    """(S, S) int64 id of the face whose UV triangle covers each texel centre, -1 where none.

    uv (F, 3, 2) per corner, v up; only faces `face_ids` are drawn. Edges count as inside;
    where faces overlap the texel goes to the face it lies deepest in (the largest smallest
    barycentric), ties to the lower face id.
    """
    best_face = np.full(size * size, -1, np.int64)
    best_score = np.full(size * size, -np.inf)
    if len(face_ids) == 0:
        return best_face.reshape(size, size)
    xy = np.stack([uv[face_ids, :, 0] * size - 0.5, (1.0 - uv[face_ids, :, 1]) * size - 0.5], axis=-1)
    lo = np.clip(np.ceil(xy.min(axis=1) - 1e-9), 0, size).astype(np.int64)  # (F, 2) first col/row
    hi = np.clip(np.floor(xy.max(axis=1) + 1e-9), -1, size - 1).astype(np.int64)
    extent = np.maximum(hi - lo + 1, 0)
    count = extent[:, 0] * extent[:, 1]
    (a, b, c) = (xy[:, 0], xy[:, 1], xy[:, 2])
    area = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (c[:, 0] - a[:, 0]) * (b[:, 1] - a[:, 1])
    count = np.where(np.abs(area) > 1e-12, count, 0)
    ends = np.cumsum(count)
    start = 0
    while start < len(face_ids):
        # a batch of whole faces holding about RASTER_CHUNK candidate texels
        base = ends[start - 1] if start else 0
        stop = max(int(np.searchsorted(ends, base + RASTER_CHUNK, side="right")), start + 1)
        local = np.arange(start, stop)
        n = count[local]
        which = np.repeat(local, n)
        k = np.arange(int(n.sum())) - np.repeat(np.cumsum(n) - n, n)
        col = lo[which, 0] + k % extent[which, 0]
        row = lo[which, 1] + k // extent[which, 0]
        px, py = col.astype(np.float64), row.astype(np.float64)
        pa, pb, pc = a[which], b[which], c[which]
        w_a = ((pb[:, 0] - px) * (pc[:, 1] - py) - (pc[:, 0] - px) * (pb[:, 1] - py)) / area[which]
        w_b = ((pc[:, 0] - px) * (pa[:, 1] - py) - (pa[:, 0] - px) * (pc[:, 1] - py)) / area[which]
        score = np.minimum(np.minimum(w_a, w_b), 1.0 - w_a - w_b)
        inside = score >= -1e-9
        texel = (row * size + col)[inside]
        score, which = score[inside], which[inside]
        shared = np.bincount(texel, minlength=size * size)[texel] > 1
        if shared.any():  # texels claimed by several faces of this batch (edges): sort only those
            order = np.nonzero(shared)[0]
            order = order[np.lexsort((which[order], -score[order], texel[order]))]
            first = np.ones(len(order), bool)
            first[1:] = texel[order[1:]] != texel[order[:-1]]
            keep = np.concatenate([np.nonzero(~shared)[0], order[first]])
            texel, score, which = texel[keep], score[keep], which[keep]
        better = score > best_score[texel]
        best_score[texel[better]] = score[better]
        best_face[texel[better]] = face_ids[which[better]]
        start = stop
    return best_face.reshape(size, size)


def dilate_ids(ids: np.ndarray, passes: int) -> np.ndarray:
    """Grows the covered region (ids >= 0) by `passes` texels: each pass an empty texel takes
    the id of its first covered neighbour (4-neighbours first, then diagonals)."""
    offsets = [(-1, 0), (1, 0), (0, -1), (0, 1), (-1, -1), (-1, 1), (1, -1), (1, 1)]
    for _ in range(passes):
        padded = np.pad(ids, 1, constant_values=-1)
        out = ids.copy()
        for dr, dc in offsets:
            neighbour = padded[1 + dr:1 + dr + ids.shape[0], 1 + dc:1 + dc + ids.shape[1]]
            take = (out < 0) & (neighbour >= 0)
            out[take] = neighbour[take]
        if np.array_equal(out, ids):
            break
        ids = out
    return ids


EVIDENCE_FULL = 1.0  # texel evidence (summed tap weight, visibility.texel_evidence) at which a texel is fully trusted


def chart_coverage(mesh: Mesh, object_page: Sequence[int], page_sizes: Sequence[int], *,
                   dilate: int = 1) -> list[np.ndarray]:
    """Per page, (S, S) bool: texels whose centre some face of the page's objects covers in UV
    space, grown by `dilate` texels (the neighbours a bilinear lookup inside a chart reads).
    Texels outside are never seen through the mesh at level 0: only mip levels blend them in."""
    face_page = check_mesh_pages(mesh, object_page, len(page_sizes))
    uv = np.asarray(mesh.uv, np.float64)
    return [dilate_ids(rasterise_uv(uv, np.nonzero(face_page == p)[0], int(size)), dilate) >= 0
            for p, size in enumerate(page_sizes)]


def page_trust(evidence_pages: Sequence[np.ndarray], coverage: Sequence[np.ndarray]) -> list[np.ndarray]:
    """Per page, (S, S) float32 in [0, 1]: how far a texel's distilled value is kept in the
    exported page (`sampler.push_pull` fills the rest from its neighbours): evidence /
    EVIDENCE_FULL clipped to 1 inside the charts (`chart_coverage`), 0 outside them."""
    return [np.where(c, np.clip(np.asarray(e, np.float32).reshape(c.shape) / EVIDENCE_FULL, 0.0, 1.0), 0.0)
            .astype(np.float32) for e, c in zip(evidence_pages, coverage)]


def texel_trust(evidence: np.ndarray, coverage: Sequence[np.ndarray], space) -> np.ndarray:
    """`page_trust` per compact texel (N,) float32: evidence (N,) / EVIDENCE_FULL clipped to 1,
    0 where the texel lies outside its page's charts (`chart_coverage` pages). Expanded to pages
    (fill 0, no dilation) it equals `page_trust` of the expanded evidence."""
    inside = compact([c[..., None].astype(np.float32) for c in coverage], space)[:, 0] > 0
    return np.where(inside, np.clip(np.asarray(evidence, np.float32) / EVIDENCE_FULL, 0.0, 1.0), 0.0).astype(np.float32)
