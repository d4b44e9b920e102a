"""Procedural meshes with exact, non-overlapping UVs, for tests and benchmarks.

Every quad patch is one object whose UVs span [0, 1]: u along `edge_u`, v along `edge_v`.
"""

from __future__ import annotations

import numpy as np

from jaxdistill.scene.cameras import look_at
from jaxdistill.scene.mesh import Mesh, join_objects


def quad_patch(origin, edge_u, edge_v, subdivisions: int = 1):
    """(vertices (N,3), faces (F,3), corner uv (F,3,2)) of a grid on the parallelogram origin + u*edge_u + v*edge_v."""
    n = int(subdivisions)
    s = np.linspace(0.0, 1.0, n + 1)
    u, v = np.meshgrid(s, s, indexing="xy")
    uv = np.stack([u.ravel(), v.ravel()], axis=1)
    verts = np.asarray(origin, np.float64) + uv[:, :1] * np.asarray(edge_u, np.float64) + uv[:, 1:] * np.asarray(edge_v, np.float64)
    i, j = np.meshgrid(np.arange(n), np.arange(n), indexing="xy")
    a = (j * (n + 1) + i).ravel()
    b, c, d = a + 1, a + n + 1, a + n + 2
    faces = np.concatenate([np.stack([a, b, d], 1), np.stack([a, d, c], 1)])
    return verts, faces, uv[faces]


def mesh_from_patches(patches, atlas: bool = False) -> Mesh:
    """A Mesh with one object per (name, origin, edge_u, edge_v, subdivisions) patch.

    atlas=True packs the patches' UVs into the cells of a square grid (with a margin of 1/16
    cell) so that all objects can share one texture page (`texture_layout="atlas"`).
    """
    parts = []
    grid = int(np.ceil(np.sqrt(len(patches))))
    for object_id, (_, origin, edge_u, edge_v, n) in enumerate(patches):
        v, f, uv = quad_patch(origin, edge_u, edge_v, n)
        if atlas:
            cell = np.array([object_id % grid, object_id // grid], np.float64)
            uv = (cell + 1 / 16 + uv * (1 - 2 / 16)) / grid
        parts.append((v, f, uv))
    return join_objects(parts, [name for name, *_ in patches])


def box_patches(name: str, lo, hi, subdivisions: int = 1):
    """Six patches of the axis-aligned box [lo, hi] (floor/ceiling/walls when seen from inside)."""
    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    dx, dy, dz = np.diag(hi - lo)
    x0, y0, z0 = lo
    n = subdivisions
    return [
        (f"{name}_floor", lo, dx, dz, n),                               # y = lo (y up)
        (f"{name}_ceiling", np.array([x0, hi[1], z0]), dz, dx, n),
        (f"{name}_wall_z0", lo, dy, dx, n),
        (f"{name}_wall_z1", np.array([x0, y0, hi[2]]), dx, dy, n),
        (f"{name}_wall_x0", lo, dz, dy, n),
        (f"{name}_wall_x1", np.array([hi[0], y0, z0]), dy, dz, n),
    ]


def plane(size: float = 2.0, subdivisions: int = 1, height: float = 0.0) -> Mesh:
    """A square on y = height spanning [-size/2, size/2] in x and z; u along +x, v along -z."""
    h = size / 2
    return mesh_from_patches([("plane", (-h, height, h), (size, 0, 0), (0, 0, -size), subdivisions)])


def box_room(size=(6.0, 3.0, 5.0), subdivisions: int = 4, furniture: bool = False, furniture_subdivisions: int = 2,
             atlas: bool = False) -> Mesh:
    """A room [0, size] (y up) of six patches, optionally with a bed, a table and a wardrobe as
    boxes; atlas=True packs all UVs into one page (see `mesh_from_patches`)."""
    sx, sy, sz = size
    patches = box_patches("room", (0, 0, 0), size, subdivisions)
    if furniture:
        n = furniture_subdivisions
        patches += box_patches("bed", (0.3, 0.0, 0.3), (0.3 + 0.4 * sx, 0.18 * sy, 0.3 + 0.4 * sz), n)
        patches += box_patches("table", (0.62 * sx, 0.0, 0.55 * sz), (0.85 * sx, 0.25 * sy, 0.8 * sz), n)
        patches += box_patches("wardrobe", (0.8 * sx, 0.0, 0.05 * sz), (0.97 * sx, 0.7 * sy, 0.35 * sz), n)
    return mesh_from_patches(patches, atlas=atlas)


def room_cameras(num_views: int, size=(6.0, 3.0, 5.0), resolution=512):
    """`num_views` square cameras inside a `box_room` of `size` at varied heights, looking at varied
    points (fx for about 70 degrees of field of view); seeded, so always the same."""
    rng = np.random.default_rng(0)
    sx, sy, sz = size
    K = np.array([[resolution * 0.7, 0, resolution / 2], [0, resolution * 0.7, resolution / 2], [0, 0, 1.0]])
    cams = []
    for _ in range(num_views):
        eye = rng.uniform([0.2 * sx, 0.3 * sy, 0.4 * sz], [0.5 * sx, 0.8 * sy, 0.9 * sz])
        target = rng.uniform([0.0, 0.0, 0.0], [sx, sy, sz])
        cams.append(look_at(eye, target, np.array([0.0, 1.0, 0.0]), K, resolution, resolution))
    return cams


def walkthrough_cameras(num_views: int, size=(6.0, 3.0, 5.0), width: int = 876, height: int = 584,
                        seed: int = 0, fov_deg: float = 70.0):
    """`num_views` cameras of a hand-held capture walking once round a `box_room` of `size`: eyes
    evenly spaced along an ellipse about the room's centre, at eye height with a little sway, each
    looking ahead along the walk and turned outwards (towards the walls and furniture) by a
    varying angle. Consecutive views overlap as a capture's frames do. `fov_deg` is the horizontal
    field of view; seeded, so the same arguments give the same cameras."""
    if num_views < 1 or width < 1 or height < 1:
        raise ValueError(f"walkthrough_cameras: need num_views, width, height >= 1, got {num_views}, {width}, {height}")
    rng = np.random.default_rng(seed)
    sx, sy, sz = size
    fx = 0.5 * width / np.tan(np.radians(fov_deg) / 2)
    K = np.array([[fx, 0, width / 2], [0, fx, height / 2], [0, 0, 1.0]])
    centre = np.array([sx / 2, 0.0, sz / 2])
    radius = np.array([0.3 * sx, 0.3 * sz])
    phase = rng.uniform(0, 2 * np.pi)
    turn = rng.uniform(0.3, 1.2, num_views)                     # radians from the path towards the walls
    cams = []
    for i in range(num_views):
        a = phase + 2 * np.pi * i / num_views
        eye = centre + np.array([radius[0] * np.cos(a), min(1.6, 0.6 * sy), radius[1] * np.sin(a)])
        eye = eye + rng.normal(0, [0.03, 0.04, 0.03])
        heading = np.array([-radius[0] * np.sin(a), 0.0, radius[1] * np.cos(a)])     # tangent of the ellipse
        heading /= np.linalg.norm(heading)
        outward = np.array([heading[2], 0.0, -heading[0]])                         # its outward normal
        look = np.cos(turn[i]) * heading + np.sin(turn[i]) * outward
        look = look + np.array([0.0, rng.uniform(-0.35, 0.1), 0.0])
        cams.append(look_at(eye, eye + look, np.array([0.0, 1.0, 0.0]), K, width, height))
    return cams
