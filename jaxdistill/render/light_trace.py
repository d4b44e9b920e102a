"""Irradiance traced from the photos: the light a surface point receives, measured by the photos.

In a room the light that reaches a point comes from the room's own surfaces and emitters, and the
photos record that light: the radiance leaving a diffuse surface point y is what a photo shows at
y, whichever view it is seen from. So the irradiance at a point p with normal n (the map's units,
E/π) is, by cosine-weighted Monte Carlo over the hemisphere,

    E(p)/π = (1/π) ∫ L(y(p, ω)) cos θ dω  ≈  (1/R) Σ_k L(y(p, ω_k)),   ω_k ~ cos θ / π,

with y(p, ω) the first surface a ray from p along ω hits and L(y) the mean of the photos' values
at y over the views that see y (a depth test against each view's own ray cast). The photos'
overall exposure cancels in albedo = L(p) / (E(p)/π), so this gives the albedo's absolute scale
with no prior, which score distillation cannot (albedo ⊙ irradiance is all the photos fix).

What it cannot see: light from no surface a photo shows (a directional sun, point lights: their
patches read too bright an albedo; `export.photo_light` takes a median over objects), and rays
that leave through openings (counted as unknown unless the photos show what lies beyond: pixels
that hit no surface give one background radiance) or hit surfaces no view sees (unknown).

Primitives on arrays, no I/O (the caller reads the photos): `cosine_directions`, `visible_radiance`,
`face_radiance`, `find_emitters`, `emitted_irradiance`, `traced_irradiance`.
"""

from __future__ import annotations

import dataclasses
from typing import Callable, Sequence

import numpy as np

from jaxdistill.scene.cameras import Camera

DEPTH_TOLERANCE = 0.01      # a view sees y when its own depth at y's pixel is within 1 % of y's depth
CHUNK = 1 << 18             # points per projection pass
EMITTER_RATIO = 30.0        # a face is an emitter when its photos' luminance is this × the median face pixel's
DARK_FLOOR = 1e-5           # find_emitters' reference is at least this × the brightest face's luminance
LUMINANCE = np.array([0.2126, 0.7152, 0.0722])


def orthonormal_frames(normals: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(t, b) (N, 3) each with (t, b, n) right-handed orthonormal, for unit normals n (N, 3)
    (the branchless construction of Duff et al. 2017, no singularity at n = ±z)."""
    n = np.asarray(normals, np.float64)
    sign = np.where(n[:, 2] >= 0, 1.0, -1.0)
    a = -1.0 / (sign + n[:, 2])
    b = n[:, 0] * n[:, 1] * a
    t = np.stack([1.0 + sign * n[:, 0] ** 2 * a, sign * b, -sign * n[:, 0]], axis=1)
    bt = np.stack([b, sign + n[:, 1] ** 2 * a, -n[:, 1]], axis=1)
    return t, bt


def cosine_directions(normals: np.ndarray, count: int, rng: np.random.Generator) -> np.ndarray:
    """(N, count, 3) unit directions about each unit normal with density cos θ / π (Malley's
    method: uniform points on the unit disc lifted to the hemisphere), stratified on a
    √count × √count grid when count is a square."""
    n = np.asarray(normals, np.float64)
    side = int(round(np.sqrt(count)))
    u = rng.random((len(n), count, 2))
    if side * side == count:
        cells = np.stack(np.meshgrid(np.arange(side), np.arange(side), indexing="ij"), -1).reshape(count, 2)
        u = (cells[None] + u) / side
    r, phi = np.sqrt(u[..., 0]), 2.0 * np.pi * u[..., 1]
    x, y = r * np.cos(phi), r * np.sin(phi)
    z = np.sqrt(np.maximum(0.0, 1.0 - u[..., 0]))
    t, b = orthonormal_frames(n)
    return x[..., None] * t[:, None] + y[..., None] * b[:, None] + z[..., None] * n[:, None]


def visible_radiance(points: np.ndarray, cameras: Sequence[Camera], depths: Sequence[np.ndarray],
                     radiance: Sequence[np.ndarray], *, tolerance: float = DEPTH_TOLERANCE) -> tuple[np.ndarray, np.ndarray]:
    """(mean (N, 3) float64, views (N,) int) of the photos' radiance at world points (N, 3) over
    the views that see them: the point projects inside the view, in front of it, onto a pixel
    whose own camera depth (depths[v] (H, W), inf where nothing is hit) is within `tolerance`
    (relative) of the point's. A point no view sees gets mean 0 and views 0."""
    pts = np.asarray(points, np.float64).reshape(-1, 3)
    total = np.zeros((len(pts), 3), np.float64)
    views = np.zeros(len(pts), np.int64)
    for cam, depth, image in zip(cameras, depths, radiance):
        h, w = depth.shape
        for start in range(0, len(pts), CHUNK):
            sl = slice(start, min(len(pts), start + CHUNK))
            pix, z = cam.project(pts[sl])
            with np.errstate(invalid="ignore"):
                col, row = np.floor(pix[:, 0]), np.floor(pix[:, 1])
                inside = (z > 0) & (col >= 0) & (col < w) & (row >= 0) & (row < h)
            idx = np.flatnonzero(inside)
            c, r = col[idx].astype(np.int64), row[idx].astype(np.int64)
            seen = np.abs(depth[r, c].astype(np.float64) - z[idx]) <= tolerance * z[idx]
            idx, c, r = idx[seen], c[seen], r[seen]
            total[start + idx] += image[r, c, :3]
            views[start + idx] += 1
    mean = np.divide(total, views[:, None], out=np.zeros_like(total), where=views[:, None] > 0)
    return mean, views


@dataclasses.dataclass(frozen=True)
class Emitters:
    """The faces that emit (`find_emitters`): index (K,), corners (K, 3, 3), unit normals (K, 3),
    areas (K,), radiance (K, 3) and the cumulative probability (K,) of choosing each, by power."""

    faces: np.ndarray
    corners: np.ndarray
    normals: np.ndarray
    areas: np.ndarray
    radiance: np.ndarray
    cdf: np.ndarray


def face_radiance(num_faces: int, triangles: Sequence[np.ndarray], radiance: Sequence[np.ndarray]
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(mean (F, 3), pixels (F,), peak (F, 3)) of the photos' radiance over the pixels whose ray
    hit each face (triangles[v] (H, W), -1 on a miss; radiance[v] (H, W, 3)): the mean, the
    count, and the brightest pixel's (by luminance; 0 where none)."""
    total = np.zeros((num_faces, 3), np.float64)
    pixels = np.zeros(num_faces, np.int64)
    peak = np.zeros((num_faces, 3), np.float64)
    peak_lum = np.full(num_faces, -np.inf)
    for tri, image in zip(triangles, radiance):
        hit = tri >= 0
        if not hit.any():                                    # a view that sees no surface
            continue
        faces, values = tri[hit], image[hit].astype(np.float64)
        pixels += np.bincount(faces, minlength=num_faces)
        for c in range(3):
            total[:, c] += np.bincount(faces, weights=values[:, c], minlength=num_faces)
        lum = values @ LUMINANCE
        order = np.lexsort((lum, faces))                     # by face, brightest last
        last = np.r_[faces[order][1:] != faces[order][:-1], True]
        top, top_lum = faces[order][last], lum[order][last]
        better = top_lum > peak_lum[top]
        peak[top[better]], peak_lum[top[better]] = values[order][last][better], top_lum[better]
    return np.divide(total, pixels[:, None], out=np.zeros_like(total), where=pixels[:, None] > 0), pixels, peak


def find_emitters(vertices: np.ndarray, faces: np.ndarray, face_object: np.ndarray, mean: np.ndarray,
                  pixels: np.ndarray, peak: np.ndarray | None = None, *, ratio: float = EMITTER_RATIO) -> Emitters | None:
    """The faces that emit, or None: those whose photos' mean luminance exceeds `ratio` × the
    median luminance of all seen faces' pixels (a lamp or a light panel: far brighter than anything
    they light), and every face of an object whose seen pixels are mostly on such faces (a bulb
    whose back no photo shows), with the object's mean radiance over its emitting pixels. With
    `peak` (F, 3), each emitting face's brightest pixel instead of its mean, and the object's
    brightest for the faces no photo shows: a small light's pixels mostly cover its edge and
    something darker beside it, and the brightest is the one that covers only the light. A
    bright sun patch taken for one is sampled towards instead of found by the hemisphere's rays:
    with its mean, the same expectation; with its peak, more light than it sends where its
    brightness varies (a panel brighter at its rim reads too bright, README "the overall scale")."""
    lum = mean @ LUMINANCE
    seen = pixels > 0
    if not seen.any():
        return None
    order = np.argsort(lum[seen])
    cumulative = np.cumsum(pixels[seen][order])
    reference = lum[seen][order][np.searchsorted(cumulative, 0.5 * cumulative[-1])]      # the median pixel's
    # most pixels black: a floor under the brightest face's, so that not every lit face is a light
    reference = max(reference, DARK_FLOOR * float(lum[seen].max()))
    if reference <= 0:
        return None
    bright = seen & (lum > ratio * reference)
    if not bright.any():
        return None
    objects = int(face_object.max()) + 1
    bright_pixels = np.bincount(face_object, weights=np.where(bright, pixels, 0), minlength=objects)
    emitting_object = bright_pixels > 0.5 * np.bincount(face_object, weights=pixels, minlength=objects)
    face_value = mean if peak is None else peak
    if peak is None:
        radiance = np.stack([np.bincount(face_object, weights=np.where(bright, mean[:, c] * pixels, 0),
                                         minlength=objects) for c in range(3)], axis=1) / np.maximum(bright_pixels, 1)[:, None]
    else:                       # the object's brightest pixel on an emitting face
        radiance = np.zeros((objects, 3))
        faces_lit = np.flatnonzero(bright)
        order = faces_lit[np.lexsort((peak[faces_lit] @ LUMINANCE, face_object[faces_lit]))]   # by object, brightest last
        last = np.r_[face_object[order][1:] != face_object[order][:-1], True]
        radiance[face_object[order][last]] = peak[order][last]
    fill = ~seen & emitting_object[face_object]
    chosen = np.flatnonzero(bright | fill)
    corners = np.asarray(vertices, np.float64)[np.asarray(faces)[chosen]]
    normal = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    area = 0.5 * np.linalg.norm(normal, axis=1)
    normal /= np.maximum(2.0 * area[:, None], 1e-300)
    value = np.where(bright[chosen, None], face_value[chosen], radiance[face_object[chosen]])
    power = area * (value @ LUMINANCE)
    keep = power > 0
    if not keep.any():
        return None
    cdf = np.cumsum(power[keep]) / power[keep].sum()
    return Emitters(chosen[keep], corners[keep], normal[keep], area[keep], value[keep], cdf)


def emitted_irradiance(intersect: Callable, points: np.ndarray, normals: np.ndarray, emitters: Emitters, *,
                       samples: int, rng: np.random.Generator, offset: float) -> np.ndarray:
    """(N, 3) irradiance (E/π) from the emitters' faces straight onto the points, by sampling
    points on them (face by power, uniform by area) with a shadow ray each:

        E/π ≈ (1/π)(1/S) Σ_s L_f cos θ_p cos θ_y / r² / pdf(y),   pdf(y) = P(f) / A_f.

    Emitters shine from both sides of their faces (a bulb's box seen from inside its shade)."""
    n_pts = len(points)
    f = np.minimum(np.searchsorted(emitters.cdf, rng.random((n_pts, samples))), len(emitters.cdf) - 1)
    u, v = rng.random((2, n_pts, samples))
    flip = u + v > 1
    u, v = np.where(flip, 1 - u, u), np.where(flip, 1 - v, v)
    c = emitters.corners[f]                                                   # (N, S, 3, 3)
    y = c[..., 0, :] + u[..., None] * (c[..., 1, :] - c[..., 0, :]) + v[..., None] * (c[..., 2, :] - c[..., 0, :])
    o = points[:, None] + offset * normals[:, None]
    to = y - o
    r = np.linalg.norm(to, axis=-1)
    w = to / np.maximum(r[..., None], 1e-300)
    cos_p = np.einsum("nsc,nc->ns", w, normals)
    cos_y = np.abs(np.einsum("nsc,nsc->ns", w, emitters.normals[f]))
    prob = np.diff(emitters.cdf, prepend=0.0)[f] / emitters.areas[f]
    tri, _, dist = intersect(np.broadcast_to(o, to.shape).reshape(-1, 3), w.reshape(-1, 3))
    tri, dist = tri.reshape(f.shape), dist.reshape(f.shape)
    visible = (cos_p > 0) & ((tri == emitters.faces[f]) | (dist >= r * (1 - 1e-4)))
    contrib = np.where(visible, cos_p * cos_y / np.maximum(r * r * prob, 1e-300), 0.0)
    return (contrib[..., None] * emitters.radiance[f]).mean(axis=1) / np.pi


def traced_irradiance(intersect: Callable, points: np.ndarray, normals: np.ndarray, lookup: Callable, *,
                      rays: int, rng: np.random.Generator, offset: float, background: np.ndarray | None = None,
                      emitters: Emitters | None = None, emitter_samples: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(irradiance (N, 3) float64 in the map's units E/π, known (N,), escaped (N,)) at points
    (N, 3) with unit normals (N, 3) facing the light's side; known is the fraction of rays whose
    radiance is known, escaped the fraction that hit nothing.

    intersect(origins (M, 3), directions (M, 3)) → (triangle (M,), barycentric, distance (M,)),
    -1 / inf on a miss (`fragments.RayCaster.intersect`); lookup(points (M, 3), triangles (M,))
    → (radiance (M, 3), known (M,) bool) at hit points. A hit of unknown radiance takes the mean
    of the point's known hits (emitters aside); a ray that hits nothing takes `background` (3,) if given (and is
    known), else adds nothing: the caller may add escaped × its own background. With `emitters`,
    their light is sampled directly (`emitted_irradiance`, `emitter_samples` shadow rays per
    point) and a hemisphere ray that hits one adds nothing (it is counted there). Origins move
    `offset` (world units) along the normal so that a ray does not hit its own surface."""
    if rays < 1:
        raise ValueError(f"traced_irradiance: rays must be at least 1, got {rays}")
    if emitters is not None and emitter_samples < 1:
        raise ValueError("traced_irradiance: emitters given with emitter_samples < 1: the rays that hit them add "
                         "nothing, so their light would be lost")
    pts = np.asarray(points, np.float64).reshape(-1, 3)
    nrm = np.asarray(normals, np.float64).reshape(-1, 3)
    irradiance = np.zeros((len(pts), 3), np.float64)
    known = np.zeros(len(pts), np.float64)
    escaped = np.zeros(len(pts), np.float64)
    emitting = None
    if emitters is not None:
        emitting = np.zeros(int(emitters.faces.max()) + 1, bool)
        emitting[emitters.faces] = True
    per_pass = max(1, CHUNK // rays)
    for start in range(0, len(pts), per_pass):
        sl = slice(start, min(len(pts), start + per_pass))
        d = cosine_directions(nrm[sl], rays, rng)                                  # (n, R, 3)
        o = np.broadcast_to((pts[sl] + offset * nrm[sl])[:, None], d.shape)
        tri, _, dist = intersect(o.reshape(-1, 3), d.reshape(-1, 3))
        hit = tri >= 0
        value = np.zeros((len(tri), 3), np.float64)
        ok = np.zeros(len(tri), bool)
        y = o.reshape(-1, 3)[hit] + dist[hit, None] * d.reshape(-1, 3)[hit]
        value[hit], ok[hit] = lookup(y, tri[hit])
        on = np.zeros(len(tri), bool)
        if emitting is not None:
            on = hit & (tri < len(emitting))
            on[on] = emitting[tri[on]]
            value[on], ok[on] = 0.0, False          # counted by the direct sampling below
        shape = d.shape[:2]
        value, ok, hit, on = value.reshape(d.shape), ok.reshape(shape), hit.reshape(shape), on.reshape(shape)
        surfaces, found = (hit & ~on).sum(axis=1), ok.sum(axis=1)
        hit_mean = np.divide((value * ok[..., None]).sum(axis=1), found[:, None], out=np.zeros((len(found), 3)),
                             where=found[:, None] > 0)
        irradiance[sl] = hit_mean * (surfaces / rays)[:, None]      # unknown surfaces at the known ones' mean
        escaped[sl] = (rays - hit.sum(axis=1)) / rays
        known[sl] = (found + on.sum(axis=1)) / rays
        if background is not None:
            irradiance[sl] += np.asarray(background, np.float64)[:3] * escaped[sl, None]
            known[sl] += escaped[sl]
        if emitters is not None and emitter_samples:
            irradiance[sl] += emitted_irradiance(intersect, pts[sl], nrm[sl], emitters, samples=emitter_samples,
                                                 rng=rng, offset=offset)
    return irradiance, known, escaped
