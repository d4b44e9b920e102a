"""Rooms built from rectangles: packed UVs, one texture page per object, cameras aimed inside.

A room object is a list of `Rect`s (planar rectangles; `box`, `wall` with an opening, `legs`)
whose UVs are packed without overlap into the object's own texture page at a uniform texel
density (`pack_rects`, `page_size_for`); `build_scene_geometry` makes the `Mesh` of all objects
(one object id each). `rolled_camera` aims a camera with a little roll, `preview` ray casts it at
low resolution to check what it sees. Shared by the procedural training rooms
(`procedural_rooms`) and the embedded bedroom (`scripts/make_bedroom.py`).
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from jaxdistill.render import fragments as fr
from jaxdistill.scene import cameras
from jaxdistill.scene.mesh import Mesh, join_objects
from jaxdistill.scene.shapes import quad_patch

TEXELS_PER_METRE = 128
GUTTER_TEXELS = 4


@dataclasses.dataclass
class Rect:
    """A planar rectangle origin + a*edge_u + b*edge_v (a, b in [0, 1]); normal edge_u x edge_v.

    uv: fixed (u0, v0, du, dv) placement in the page, or None to be packed by `pack_rects`.
    """

    origin: np.ndarray
    edge_u: np.ndarray
    edge_v: np.ndarray
    uv: tuple | None = None


def rect(origin, edge_u, edge_v, uv=None) -> Rect:
    """A `Rect` of float arrays from anything array-like."""
    return Rect(np.asarray(origin, float), np.asarray(edge_u, float), np.asarray(edge_v, float), uv)


def box(lo, hi, skip=()) -> list[Rect]:
    """Outward-facing rectangles of the box [lo, hi]; skip names faces to leave out ('-y', '+x', ...)."""
    (x0, y0, z0), (x1, y1, z1) = lo, hi
    dx, dy, dz = x1 - x0, y1 - y0, z1 - z0
    faces = {
        "-y": rect((x0, y0, z0), (dx, 0, 0), (0, 0, dz)),
        "+y": rect((x0, y1, z1), (dx, 0, 0), (0, 0, -dz)),
        "-z": rect((x1, y0, z0), (-dx, 0, 0), (0, dy, 0)),
        "+z": rect((x0, y0, z1), (dx, 0, 0), (0, dy, 0)),
        "-x": rect((x0, y0, z0), (0, 0, dz), (0, dy, 0)),
        "+x": rect((x1, y0, z1), (0, 0, -dz), (0, dy, 0)),
    }
    return [r for name, r in faces.items() if name not in skip]


def wall(origin, edge_u, edge_v, hole=None) -> list[Rect]:
    """An inward-facing wall with planar UVs (u along edge_u, v up), optionally with a
    rectangular opening hole = (a0, a1, b0, b1) in fractions of the edges."""
    origin, eu, ev = (np.asarray(x, float) for x in (origin, edge_u, edge_v))
    if hole is None:
        return [rect(origin, eu, ev, (0.0, 0.0, 1.0, 1.0))]
    a0, a1, b0, b1 = hole
    cells = [(0, 1, 0, b0), (0, 1, b1, 1), (0, a0, b0, b1), (a1, 1, b0, b1)]
    return [rect(origin + p0 * eu + q0 * ev, (p1 - p0) * eu, (q1 - q0) * ev, (p0, q0, p1 - p0, q1 - q0))
            for p0, p1, q0, q1 in cells]


def pack_rects(sizes: np.ndarray, gutter: float) -> tuple[np.ndarray, float]:
    """Shelf-packs rectangles (n, 2) (width, height in metres) into the unit square.

    Returns lower-left corners (n, 2) and the largest common scale s (uv units per metre) at
    which all of them fit with `gutter` uv units between and around them.
    """
    order = np.argsort(-sizes[:, 1], kind="stable")

    def place(s):
        corners = np.zeros_like(sizes)
        x, y, shelf = gutter, gutter, 0.0
        for i in order:
            w, h = sizes[i] * s
            if x + w + gutter > 1.0:
                x, y, shelf = gutter, y + shelf + gutter, 0.0
            if x + w + gutter > 1.0 or y + h + gutter > 1.0:
                return None
            corners[i] = (x, y)
            x, shelf = x + w + gutter, max(shelf, h)
        return corners

    lo, hi = 0.0, 1.0 / sizes.max()
    for _ in range(40):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if place(mid) is not None else (lo, mid)
    return place(lo), lo


def page_size_for(rects: list[Rect]) -> int:
    """Power-of-two page side giving about TEXELS_PER_METRE over the object's area, in [64, 512]."""
    area = sum(np.linalg.norm(np.cross(r.edge_u, r.edge_v)) for r in rects)
    side = math.sqrt(area * 1.6) * TEXELS_PER_METRE
    return int(np.clip(2 ** round(math.log2(max(side, 1.0))), 64, 512))


def build_object(rects: list[Rect], size: int):
    """(vertices, faces, corner uv) of one object; packed rects share one texel density."""
    packed = [i for i, r in enumerate(rects) if r.uv is None]
    placement = {}
    if packed:
        sizes = np.array([[np.linalg.norm(rects[i].edge_u), np.linalg.norm(rects[i].edge_v)] for i in packed])
        corners, scale = pack_rects(sizes, GUTTER_TEXELS / size)
        for k, i in enumerate(packed):
            placement[i] = (*corners[k], *(sizes[k] * scale))
    verts, faces, uvs, offset = [], [], [], 0
    for i, r in enumerate(rects):
        v, f, uv = quad_patch(r.origin, r.edge_u, r.edge_v, 1)
        u0, v0, du, dv = r.uv if r.uv is not None else placement[i]
        verts.append(v)
        faces.append(f + offset)
        uvs.append(np.stack([u0 + uv[..., 0] * du, v0 + uv[..., 1] * dv], -1))
        offset += len(v)
    return np.concatenate(verts), np.concatenate(faces), np.concatenate(uvs)


def legs(x0, x1, z0, z1, height, thickness) -> list[Rect]:
    """Four square legs under the rectangle [x0, x1] x [z0, z1]."""
    t = thickness
    out = []
    for x in (x0, x1 - t):
        for z in (z0, z1 - t):
            out += box((x, 0.0, z), (x + t, height, z + t), skip=("-y", "+y"))
    return out


def build_scene_geometry(objs) -> tuple[Mesh, list[int]]:
    """The Mesh of all objects (one object id each) and each object's page size."""
    sizes = [page_size_for(rects) for _, rects, _ in objs]
    parts = [build_object(rects, size) for (_, rects, _), size in zip(objs, sizes)]
    return join_objects(parts, [name for name, _, _ in objs]), sizes


def rolled_camera(eye, target, K, width, height, roll: float) -> cameras.Camera:
    """A camera at eye looking at target, rolled by `roll` radians from level."""
    forward = (target - eye) / np.linalg.norm(target - eye)
    side = np.cross(forward, [0.0, 1.0, 0.0])
    side /= np.linalg.norm(side)
    up = math.cos(roll) * np.cross(side, forward) + math.sin(roll) * side
    return cameras.look_at(eye, target, up, K, width, height)


def preview(caster, cam: cameras.Camera, factor: int) -> tuple[float, float]:
    """(fraction of pixels that hit geometry, median hit depth) of `cam` at 1/factor resolution."""
    small = cameras.Camera(np.diag([1 / factor, 1 / factor, 1.0]) @ cam.K, cam.c2w, cam.width // factor, cam.height // factor)
    tri, _, depth = fr.cast_view(caster, small)[:3]
    hit = tri >= 0
    return float(hit.mean()), float(np.median(depth[hit])) if hit.any() else 0.0
