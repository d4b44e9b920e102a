"""Checks of an object's existing UVs: why per-corner texture coordinates cannot be kept as they are
(missing, non-finite, tiled, collapsed or overlapping; rule 1 of `unwrap`), and the overlap raster.
"""

from __future__ import annotations

import numpy as np

UV_RASTER = 256
UV_OVERLAP_LIMIT = 0.02
UV_COLLAPSED_LIMIT = 0.01
OVERLAP_MAX_TESTS = 1 << 24     # texel-centre tests of one overlap check (resolution lowered beyond)
OVERLAP_BATCH = 1 << 21         # texel-centre tests per vectorised batch
MIN_OVERLAP_RASTER = 16


def _uv_areas(uv: np.ndarray) -> np.ndarray:
    """Signed areas (F,) of UV triangles (F, 3, 2); > 0 counter-clockwise."""
    e1, e2 = uv[:, 1] - uv[:, 0], uv[:, 2] - uv[:, 0]
    return 0.5 * (e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0])


def _raster_counts(p: np.ndarray, resolution: int) -> np.ndarray:
    """(resolution^2,) how many triangles p (F, 3, 2, texel units, centre of texel i at i) cover each centre."""
    count = np.zeros(resolution * resolution, np.int64)
    area = _uv_areas(p)
    p, area = p[np.abs(area) >= 1e-12], area[np.abs(area) >= 1e-12]
    lo = np.maximum(np.ceil(p.min(axis=1)), 0).astype(np.int64)
    hi = np.minimum(np.floor(p.max(axis=1)), resolution - 1).astype(np.int64)
    span = np.maximum(hi - lo + 1, 0)
    n = span[:, 0] * span[:, 1]
    keep = n > 0
    p, area, lo, span, n = p[keep], area[keep], lo[keep], span[keep], n[keep]
    ends = np.cumsum(n)
    start = 0
    while start < len(n):
        base = ends[start - 1] if start else 0
        stop = max(int(np.searchsorted(ends, base + OVERLAP_BATCH, side="right")), start + 1)
        counts = n[start:stop]
        tri = np.repeat(np.arange(start, stop), counts)
        k = np.arange(int(counts.sum())) - np.repeat(np.cumsum(counts) - counts, counts)
        xs = lo[tri, 0] + k % span[tri, 0]
        ys = lo[tri, 1] + k // span[tri, 0]
        corners = p[tri]
        sign = np.sign(area[tri])
        inside = np.ones(len(tri), bool)
        for a in range(3):
            (x0, y0), (x1, y1) = corners[:, a].T, corners[:, (a + 1) % 3].T
            inside &= ((x1 - x0) * (ys - y0) - (y1 - y0) * (xs - x0)) * sign > 1e-9
        count += np.bincount(ys[inside] * resolution + xs[inside], minlength=resolution * resolution)
        start = stop
    return count


def uv_overlap_fraction(uv: np.ndarray, resolution: int = UV_RASTER, *, max_tests: int = OVERLAP_MAX_TESTS) -> float:
    """Fraction of covered texel centres (of a resolution^2 raster of [0, 1]^2) covered twice or more.

    uv (F, 3, 2); non-finite and zero-area triangles are ignored. Vectorised: the cost is the
    number of (triangle, texel centre in its bounding box) tests, at most `max_tests`; beyond
    it (stacked or huge overlapping triangles) the raster is halved (down to 16^2), then a
    seeded random subset of the triangles is tested (which can only under-count overlaps).
    """
    uv = np.asarray(uv, np.float64).reshape(-1, 3, 2)
    uv = uv[np.isfinite(uv).all(axis=(1, 2))]
    resolution = int(resolution)
    while True:
        p = uv * resolution - 0.5                        # texel i has its centre at coordinate i
        lo = np.maximum(np.ceil(p.min(axis=1)), 0)
        hi = np.minimum(np.floor(p.max(axis=1)), resolution - 1)
        tests = np.prod(np.maximum(hi - lo + 1, 0), axis=1)
        if tests.sum() <= max_tests or resolution <= MIN_OVERLAP_RASTER:
            break
        resolution //= 2
    if tests.sum() > max_tests:
        rng = np.random.default_rng(0)
        p = p[rng.random(len(p)) < max_tests / tests.sum()]
    count = _raster_counts(p, resolution)
    covered = (count > 0).sum()
    return float((count > 1).sum() / covered) if covered else 0.0


def uv_problem(uv: np.ndarray, triangles: np.ndarray) -> str | None:
    """Why per-corner UVs (F, 3, 2) of triangles (F, 3, 3) cannot be kept, or None if they can.

    Reasons: 'no texture coordinates' (all NaN), 'non-finite', 'tiled (outside [0, 1])',
    'collapsed (zero UV area)', 'overlapping (N % of texels)'.
    """
    finite = np.isfinite(uv)
    if not finite.any():
        return "no texture coordinates"
    if not finite.all():
        return f"non-finite ({(~finite.all(axis=(1, 2))).sum()} faces)"
    if (uv < -1e-6).any() or (uv > 1 + 1e-6).any():
        return "tiled (outside [0, 1])"
    edges = triangles[:, 1:] - triangles[:, :1]
    area3d = 0.5 * np.linalg.norm(np.cross(edges[:, 0], edges[:, 1]), axis=1)
    degenerate = np.abs(_uv_areas(uv)) < 1e-12
    if area3d[degenerate].sum() > UV_COLLAPSED_LIMIT * max(area3d.sum(), 1e-300):
        return "collapsed (zero UV area)"
    overlap = uv_overlap_fraction(uv)
    if overlap > UV_OVERLAP_LIMIT:
        return f"overlapping ({100 * overlap:.0f} % of texels)"
    return None
