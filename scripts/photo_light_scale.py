"""Can the photos themselves give albedo its absolute scale? A measurement (README "Re-rendering
against the photos", the overall scale): on scenes with ground truth, the albedo the photos imply,
photo / E with E the one-bounce irradiance the photos show, against the GT albedo.

The re-rendering term fixes only the product albedo ⊙ irradiance, and the prior decides the
split, including its overall scale (a · k, E / k explain the same photos). The photos could hold
the missing unit: on a Lambertian surface the irradiance (in the map's units, E/π) at a point p is
the cosine-weighted mean of the radiance arriving over its hemisphere,

    E(p) = (1/π) ∫ L(q(p, ω)) cos θ dω,

and the radiance L(q) leaving a surface point q is what the photos show there (mean over the
views that see q; a light source in the mesh is seen as its bright pixels). Then a(p) =
photo(p) / E(p) in absolute units. Light from outside the mesh (sun and sky through an opening)
and surfaces no photo sees are unknown, so only points whose hemisphere is mostly seen count.
Two estimators of E: `rays` (cosine-distributed rays, mean over the rays that hit a seen
surface) and `area` (a sum over area samples of the whole mesh, at least one per face, so a small
bright bulb is never missed; one shadow ray each). For each scene this prints, over the sampled
pixels that count, the ratio photo / (E · GT albedo) — 1 where the photos' light explains the
photo — as quantiles and per-channel medians:

    python scripts/photo_light_scale.py --scenes=data/val/room_0,data/val/room_1,data/val/room_2 \
        --json=docs/data/photo_light_scale.json
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path
from typing import Sequence

import numpy as np

from jaxdistill.evaluate import ground_truth as evaluation
from jaxdistill.io.view_images import read_mask, read_photo_linear
from jaxdistill.render.fragments import RayCaster, compute_fragments
from jaxdistill.scene.mesh import Mesh, face_normals
from jaxdistill.scene.model import read_scene
from jaxdistill.scene.paths import resolve_scene_path

DEPTH_TOLERANCE = 0.01   # relative camera-depth difference under which a projected point is the pixel's surface
RAY_OFFSET = 1e-4        # ray origins leave the surface by this fraction of the scene's size


def surface_points(mesh: Mesh, triangle: np.ndarray, barycentric: np.ndarray) -> np.ndarray:
    """(N, 3) world positions of hits (triangle (N,), barycentric (N, 2) of corners 1 and 2)."""
    corners = mesh.vertices[mesh.faces[triangle]]
    b1, b2 = barycentric[:, 0:1].astype(np.float64), barycentric[:, 1:2].astype(np.float64)
    return corners[:, 0] * (1.0 - b1 - b2) + corners[:, 1] * b1 + corners[:, 2] * b2


def facing_normals(mesh: Mesh, triangle: np.ndarray, points: np.ndarray, eye: np.ndarray) -> np.ndarray:
    """(N, 3) unit geometric normals of the hit triangles, turned towards `eye` (3,): the side
    the camera sees is the side the light arrives on."""
    n = face_normals(mesh)[triangle]
    flip = np.einsum("nc,nc->n", n, np.asarray(eye, np.float64) - points) < 0
    return np.where(flip[:, None], -n, n)


def cosine_directions(normals: np.ndarray, count: int, rng: np.random.Generator) -> np.ndarray:
    """(N, count, 3) unit directions over each normal's hemisphere with density cos θ / π."""
    n = np.asarray(normals, np.float64)
    u1, u2 = rng.random((len(n), count)), rng.random((len(n), count))
    r, phi = np.sqrt(u1), 2.0 * np.pi * u2
    helper = np.where(np.abs(n[:, :1]) < 0.9, np.array([[1.0, 0.0, 0.0]]), np.array([[0.0, 1.0, 0.0]]))
    t1 = np.cross(n, helper)
    t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
    t2 = np.cross(n, t1)
    return ((r * np.cos(phi))[..., None] * t1[:, None] + (r * np.sin(phi))[..., None] * t2[:, None]
            + np.sqrt(np.maximum(1.0 - u1, 0.0))[..., None] * n[:, None])


def observed_radiance(points: np.ndarray, cameras: Sequence, depths: Sequence[np.ndarray],
                      photos: Sequence[np.ndarray], usable: Sequence[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """(radiance (N, 3), seen (N,) bool): the mean over the views that see each point of the
    photo's pixel there. A view sees a point when it projects inside the image onto a usable
    pixel (unclipped, unmasked) whose surface depth (`depths`, the view's camera z, inf on a miss)
    is the point's within DEPTH_TOLERANCE."""
    total = np.zeros((len(points), 3))
    count = np.zeros(len(points))
    for camera, depth, photo, ok in zip(cameras, depths, photos, usable):
        pixel, z = camera.project(points)
        with np.errstate(invalid="ignore"):
            col, row = np.floor(pixel[:, 0]), np.floor(pixel[:, 1])
        inside = (z > 0) & (col >= 0) & (row >= 0) & (col < camera.width) & (row < camera.height)
        idx = np.nonzero(inside)[0]
        r, c = row[idx].astype(np.int64), col[idx].astype(np.int64)
        same = (np.abs(depth[r, c] - z[idx]) <= DEPTH_TOLERANCE * z[idx]) & ok[r, c]
        idx, r, c = idx[same], r[same], c[same]
        total[idx] += photo[r, c, :3]
        count[idx] += 1
    return total / np.maximum(count, 1)[:, None], count > 0


def photo_irradiance(mesh: Mesh, caster: RayCaster, points: np.ndarray, normals: np.ndarray, cameras: Sequence,
                     depths: Sequence[np.ndarray], photos: Sequence[np.ndarray], usable: Sequence[np.ndarray], *,
                     rays: int, seed: int = 0, chunk: int = 4096) -> tuple[np.ndarray, np.ndarray]:
    """(irradiance (N, 3) in the photos' units (E/π), seen_fraction (N,)) at `points` with unit
    `normals`: the mean observed radiance over `rays` cosine-distributed rays per point, over the
    rays that hit a seen surface (irradiance 0 where none does)."""
    rng = np.random.default_rng(seed)
    points, normals = np.asarray(points, np.float64), np.asarray(normals, np.float64)
    offset = RAY_OFFSET * caster.scale
    irradiance = np.zeros((len(points), 3))
    fraction = np.zeros(len(points))
    for start in range(0, len(points), chunk):
        sl = slice(start, min(len(points), start + chunk))
        directions = cosine_directions(normals[sl], rays, rng).reshape(-1, 3)
        origins = np.repeat(points[sl] + offset * normals[sl], rays, axis=0)
        triangle, bary, _ = caster.intersect(origins, directions)
        hit = np.nonzero(triangle >= 0)[0]
        radiance = np.zeros((len(origins), 3))
        seen = np.zeros(len(origins), bool)
        radiance[hit], seen[hit] = observed_radiance(surface_points(mesh, triangle[hit], bary[hit]),
                                                     cameras, depths, photos, usable)
        seen = seen.reshape(-1, rays)
        n_seen = seen.sum(1)
        irradiance[sl] = (radiance.reshape(-1, rays, 3) * seen[..., None]).sum(1) / np.maximum(n_seen, 1)[:, None]
        fraction[sl] = n_seen / rays
    return irradiance, fraction


def area_samples(mesh: Mesh, count: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """About `count` points spread over the mesh's surface by area, at least one per face (so a
    small bright face, a lamp's bulb, is never missed): (points (M, 3), normals (M, 3) unit,
    areas (M,) the surface each stands for, face (M,))."""
    tri = mesh.triangles()
    cross = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    area = 0.5 * np.linalg.norm(cross, axis=1)
    keep = area > 0
    per_face = np.where(keep, np.maximum(1, np.round(count * area / max(area.sum(), 1e-30))), 0).astype(np.int64)
    face = np.repeat(np.arange(len(tri)), per_face)
    u, v = rng.random(len(face)), rng.random(len(face))
    flip = u + v > 1.0
    u, v = np.where(flip, 1.0 - u, u), np.where(flip, 1.0 - v, v)
    points = tri[face, 0] * (1.0 - u - v)[:, None] + tri[face, 1] * u[:, None] + tri[face, 2] * v[:, None]
    normals = cross[face] / np.maximum(2.0 * area[face], 1e-30)[:, None]
    return points, normals, (area / np.maximum(per_face, 1))[face], face


def photo_irradiance_area(caster: RayCaster, points: np.ndarray, normals: np.ndarray, sources: tuple,
                          radiance: np.ndarray, seen: np.ndarray, *, chunk: int = 64) -> tuple[np.ndarray, np.ndarray]:
    """(irradiance (N, 3), seen_fraction (N,)) at `points` with unit `normals` by summing over
    area samples `sources` = (points, normals, areas) with their observed `radiance` (M, 3) and
    `seen` (M,): E(p) = Σ_q L_q cos θ_p |cos θ_q| A_q / (π r²) over the q visible from p (one
    shadow ray each; r² at least A_q, so a near sample cannot blow up), taken over the seen q and
    divided by their total geometric factor (the cosine-weighted share of the hemisphere they
    cover, which is the seen fraction, at most 1): E is the mean radiance over the seen part."""
    q, nq, aq = (np.asarray(x, np.float64) for x in sources)
    offset = RAY_OFFSET * caster.scale
    irradiance = np.zeros((len(points), 3))
    fraction = np.zeros(len(points))
    for start in range(0, len(points), chunk):
        p, n = points[start:start + chunk], normals[start:start + chunk]
        d = q[None] - p[:, None]                                   # (P, M, 3)
        r2 = np.einsum("pmc,pmc->pm", d, d)
        r = np.sqrt(np.maximum(r2, 1e-30))
        cos_p = np.einsum("pmc,pc->pm", d, n) / r
        cos_q = np.abs(np.einsum("pmc,mc->pm", d, nq)) / r
        geo = np.where(cos_p > 0, cos_p * cos_q * aq[None] / (np.pi * np.maximum(r2, aq[None])), 0.0)
        pi, mi = np.nonzero(geo > 0)
        origin = p[pi] + offset * n[pi]
        to = q[mi] - origin
        length = np.linalg.norm(to, axis=1)
        _, _, dist = caster.intersect(origin, to / np.maximum(length, 1e-30)[:, None])
        visible = dist >= length * (1.0 - 1e-3) - offset
        g = np.zeros_like(geo)
        g[pi[visible], mi[visible]] = geo[pi[visible], mi[visible]]
        gs = g * seen[None]
        covered = gs.sum(1)
        irradiance[start:start + chunk] = (gs @ radiance) / np.maximum(covered, 1e-30)[:, None]
        fraction[start:start + chunk] = np.minimum(covered, 1.0)
    return irradiance, fraction


def scene_ratios(path, *, points: int, rays: int, sources: int, seed: int = 0) -> dict:
    scene = read_scene(resolve_scene_path(path))
    cameras = [v.camera for v in scene.views]
    frags = compute_fragments(scene.mesh, cameras, progress=False)
    gt, gt_maps = evaluation.view_ground_truth(scene, frags)
    if not gt_maps or not all("albedo" in g for g in gt_maps):
        raise SystemExit(f"{path}: no albedo ground truth to compare with")
    masks = evaluation.evaluation_masks(gt, scene, frags)
    loaded = [read_photo_linear(v.photo, v.exposure, c.height, c.width) for v, c in zip(scene.views, cameras)]
    photos, usable = [p for p, _ in loaded], [u > 0 for _, u in loaded]
    weights = [m & u & (read_mask(v.mask, *m.shape) if v.mask else True) for m, u, v in zip(masks, usable, scene.views)]
    covered = sum(int(w.sum()) for w in weights)
    stride = max(1, int(np.ceil(np.sqrt(covered / points))))
    pts, nrm, pho, alb = [], [], [], []
    for frag, camera, photo, weight, g in zip(frags, cameras, photos, weights, gt_maps):
        grid = np.zeros(weight.shape, bool)
        grid[stride // 2::stride, stride // 2::stride] = True
        rows, cols = np.nonzero(grid & weight)
        tri = frag.triangle[rows, cols]
        p = surface_points(scene.mesh, tri, frag.barycentric[rows, cols])
        pts.append(p)
        nrm.append(facing_normals(scene.mesh, tri, p, camera.center))
        pho.append(photo[rows, cols, :3])
        alb.append(g["albedo"][rows, cols, :3])
    pts, nrm, pho, alb = map(np.concatenate, (pts, nrm, pho, alb))
    caster = RayCaster(scene.mesh)
    depths = [f.depth for f in frags]
    out = {"points": int(len(pts))}
    for method in ("rays", "area"):
        t = time.perf_counter()
        if method == "rays":
            e, seen = photo_irradiance(scene.mesh, caster, pts, nrm, cameras, depths, photos, usable, rays=rays, seed=seed)
        else:
            q, nq, aq, _ = area_samples(scene.mesh, sources, np.random.default_rng(seed))
            radiance, seen_q = observed_radiance(q, cameras, depths, photos, usable)
            e, seen = photo_irradiance_area(caster, pts, nrm, (q, nq, aq), radiance, seen_q.astype(np.float64))
        row = {"seconds": round(time.perf_counter() - t, 1),
               "seen_fraction_median": round(float(np.median(seen)), 3)}
        for min_seen in (0.8, 0.9):
            keep = (seen >= min_seen) & np.all(alb > 0.02, 1) & np.all(e > 0, 1)
            ratio = pho[keep] / (e[keep] * alb[keep])
            row[f"seen>={min_seen}"] = {
                "points": int(keep.sum()),
                "median_per_channel": np.median(ratio, 0).round(3).tolist() if keep.any() else None,
                "quantiles_10_25_50_75_90": np.quantile(ratio.mean(1), [.1, .25, .5, .75, .9]).round(3).tolist()
                if keep.any() else None}
        out[method] = row
    return out


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scenes", required=True, help="comma-separated scene folders (or names) with GT albedo")
    parser.add_argument("--points", type=int, default=2000, help="sampled pixels over all views")
    parser.add_argument("--rays", type=int, default=64, help="rays per point (rays estimator)")
    parser.add_argument("--sources", type=int, default=20000, help="area samples over the mesh (area estimator)")
    parser.add_argument("--json", type=Path, help="write the results here")
    args = parser.parse_args()
    results = {}
    for path in args.scenes.split(","):
        results[Path(path).name] = scene_ratios(path, points=args.points, rays=args.rays, sources=args.sources)
        print(Path(path).name, json.dumps(results[Path(path).name]), flush=True)
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps({"command": "python scripts/photo_light_scale.py --scenes=" + ",".join(
            Path(p).name for p in args.scenes.split(",")), "results": results}, indent=1) + "\n")


if __name__ == "__main__":
    main()
