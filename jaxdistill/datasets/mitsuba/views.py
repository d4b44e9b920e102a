"""Camera placement for an imported scene: seeded random eyes inside the unmasked geometry,
checked with probe rays and a low-resolution preview, then chosen greedily for surface coverage
(`place_views`; the rules are step 4 of `prepare.py`'s docstring).
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
from tqdm.auto import tqdm

from jaxdistill.errors import InputError
from jaxdistill.render import fragments as fr
from jaxdistill.scene.cameras import Camera, look_at
from jaxdistill.scene.model import Mesh

FOV_RANGE = (60.0, 75.0)
PRINCIPAL_OFFSET = 0.03
PREVIEW_WIDTH = 64
MAX_PITCH_DEG = 50.0


def _probe_directions() -> np.ndarray:
    """(26, 3) unit directions: the faces, edges and corners of a cube."""
    d = np.array([(x, y, z) for x in (-1, 0, 1) for y in (-1, 0, 1) for z in (-1, 0, 1) if (x, y, z) != (0, 0, 0)],
                 np.float64)
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def _intrinsics(fov_deg: float, offset: np.ndarray, width: int, height: int) -> np.ndarray:
    f = 0.5 * width / math.tan(math.radians(fov_deg) / 2.0)
    return np.array([[f, 0.0, width * (0.5 + offset[0])], [0.0, f, height * (0.5 + offset[1])], [0.0, 0.0, 1.0]])


@dataclasses.dataclass(frozen=True)
class _Candidate:
    eye: np.ndarray
    target: np.ndarray
    fov: float
    offset: np.ndarray
    seen: np.ndarray      # (F,) surface area seen per face (capped at the face area)


def place_views(mesh: Mesh, masked_face: np.ndarray, num_views: int, width: int, height: int, *, up: np.ndarray,
                seed: int = 0, progress: bool = False) -> tuple[list[Camera], dict]:
    """`num_views` cameras inside the scene chosen for surface coverage; (cameras, statistics)."""
    rng = np.random.default_rng(seed)
    caster = fr.RayCaster(mesh)
    tri = mesh.triangles()
    cross = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    face_area = 0.5 * np.linalg.norm(cross, axis=1)
    face_normal = cross / np.maximum(2.0 * face_area, 1e-300)[:, None]
    solid = ~masked_face & (face_area > 0)
    if not solid.any():
        raise InputError.single("scene", "shapes", "every surface is an emitter or glass: nothing to view")
    pts = tri[solid].reshape(-1, 3)
    lo, hi = pts.min(0), pts.max(0)
    extent = hi - lo
    diagonal = float(np.linalg.norm(extent))
    clearance = 0.01 * diagonal
    box_lo, box_hi = lo + 0.05 * extent, hi - 0.05 * extent
    probes = _probe_directions()
    target_p = np.where(solid, face_area, 0.0)
    target_p /= target_p.sum()
    max_pitch = math.sin(math.radians(MAX_PITCH_DEG))
    pw = PREVIEW_WIDTH
    ph = max(1, round(pw * height / width))
    pool = max(6 * num_views, 24)
    candidates: list[_Candidate] = []
    eyes_tried = eyes_ok = 0
    bar = tqdm(total=pool, desc="view candidates", unit="view", disable=not progress)
    for _ in range(200):                                  # batches of eyes
        if len(candidates) >= pool:
            break
        eyes = rng.uniform(box_lo, box_hi, (128, 3))
        eyes_tried += len(eyes)
        o = np.repeat(eyes, len(probes), axis=0)
        d = np.tile(probes, (len(eyes), 1))
        hit_tri, _, dist = caster.intersect(o, d)
        hit_tri, dist = hit_tri.reshape(len(eyes), -1), dist.reshape(len(eyes), -1)
        for e in range(len(eyes)):
            hits = hit_tri[e] >= 0
            if hits.mean() < 0.9 or dist[e][hits].min() < clearance:
                continue
            if len(np.unique(mesh.face_object[hit_tri[e][hits]])) < min(3, len(mesh.object_names)):
                continue
            eyes_ok += 1
            candidate = _try_eye(eyes[e], rng, caster, mesh, tri, face_area, face_normal, masked_face, target_p, up,
                                 clearance, max_pitch, pw, ph)
            if candidate is not None:
                candidates.append(candidate)
                bar.update(1)
                if len(candidates) >= pool:
                    break
    bar.close()
    if len(candidates) < num_views:
        raise InputError.single("scene", "--views", f"found only {len(candidates)} acceptable viewpoints "
                                f"({eyes_ok} of {eyes_tried} random eyes had clearance); ask for fewer views or "
                                "check that the scene is an enclosed interior with its up axis given (--up)")
    # Greedy coverage: gain = seen area, halved per earlier view that saw the face.
    seen = np.stack([c.seen for c in candidates])          # (C, F)
    looks = np.zeros(len(face_area))
    chosen = []
    for _ in range(num_views):
        gains = seen @ (0.5 ** looks)
        gains[chosen] = -1.0
        best = int(np.argmax(gains))
        chosen.append(best)
        looks += np.minimum(1.0, seen[best] / np.maximum(face_area, 1e-300))
    cams = []
    for i in chosen:
        c = candidates[i]
        cams.append(look_at(c.eye, c.target, up, _intrinsics(c.fov, c.offset, width, height), width, height))
    seen_any = (seen[chosen] > 0).any(axis=0)
    stats = {"candidates": len(candidates), "eyes_tried": eyes_tried, "eyes_with_clearance": eyes_ok,
             "clearance": clearance, "scene_diagonal": diagonal,
             "unmasked_area_seen_fraction": float(face_area[seen_any & solid].sum() / face_area[solid].sum())}
    return cams, stats


def _try_eye(eye, rng, caster, mesh, tri, face_area, face_normal, masked_face, target_p, up, clearance, max_pitch,
             pw, ph) -> _Candidate | None:
    """A candidate view from `eye` at a visible random surface point, or None (3 target tries)."""
    for _ in range(3):
        f = rng.choice(len(face_area), p=target_p)
        r1, r2 = rng.random(2)
        s = math.sqrt(r1)
        target = (1 - s) * tri[f, 0] + s * (1 - r2) * tri[f, 1] + s * r2 * tri[f, 2]
        to = target - eye
        dist = float(np.linalg.norm(to))
        if dist < 2 * clearance or abs(to @ up) / dist > max_pitch:
            continue
        hit, _, hit_dist = caster.intersect(eye[None], (to / dist)[None])
        if hit[0] < 0 or hit_dist[0] < 0.98 * dist:
            continue
        fov = float(rng.uniform(*FOV_RANGE))
        offset = rng.uniform(-PRINCIPAL_OFFSET, PRINCIPAL_OFFSET, 2)
        cam = look_at(eye, target, up, _intrinsics(fov, offset, pw, ph), pw, ph)
        o, d = cam.pixel_rays()
        t, _, t_dist = caster.intersect(o, d)
        hits = t >= 0
        if hits.mean() < 0.9 or (hits & ~masked_face[np.maximum(t, 0)]).mean() < 0.5:
            continue
        depth = t_dist[hits] * (d[hits] @ cam.c2w[:3, 2])
        if np.median(depth) < 2 * clearance:
            continue
        # Surface area per pixel: dist^2 * (pixel solid angle) / |cos(incidence)|.
        cos_axis = d[hits] @ cam.c2w[:3, 2]
        solid_angle = cos_axis ** 3 / (cam.K[0, 0] * cam.K[1, 1])
        cos_in = np.maximum(np.abs(np.einsum("nc,nc->n", face_normal[t[hits]], d[hits])), 0.2)
        footprint = t_dist[hits] ** 2 * solid_angle / cos_in
        valid = ~masked_face[t[hits]]
        seen = np.bincount(t[hits][valid], weights=footprint[valid], minlength=len(face_area))
        return _Candidate(eye=eye, target=target, fov=fov, offset=offset, seen=np.minimum(seen, face_area))
    return None
