"""Geometry of a Mitsuba 3 scene: each shape as world-space triangles (`SourceObject`), and our
reconstruction Mesh of them with UVs in [0, 1] per object.

Meshes come through `mi.traverse` or the shape's own accessors; `disk`, `sphere` and `cylinder`
(and `rectangle` in older Mitsuba versions) are tessellated here, with Mitsuba's exact UV as a
function of the hit point. `reconstruction_mesh` keeps an object's UVs when usable, else
re-unwraps it (`jaxdistill.render.unwrap`).
"""

from __future__ import annotations

import dataclasses
import time
from typing import Callable, Sequence

import numpy as np
from tqdm.auto import tqdm

from jaxdistill.datasets.mitsuba import bridge as mb
from jaxdistill.datasets.mitsuba.materials import GTMaterial
from jaxdistill.render.unwrap import UVDecision, unwrap_object
from jaxdistill.render.uv_checks import uv_problem
from jaxdistill.scene.model import Mesh

ANALYTIC_SHAPES = ("disk", "sphere", "cylinder")
TESSELLATION_SEGMENTS = 64


@dataclasses.dataclass(eq=False)
class SourceObject:
    """One Mitsuba shape as triangles in world space, with what its ground truth needs.

    texcoords (Nv, 2) are Mitsuba's (as its textures see them) or None (Mitsuba then uses the
    barycentrics b1, b2); normals (Nv, 3) are shading normals or None (face normals);
    uv_function maps world points (N, 3) to Mitsuba's exact UV for analytic shapes.
    """

    name: str
    shape: str
    vertices: np.ndarray
    faces: np.ndarray
    texcoords: np.ndarray | None
    normals: np.ndarray | None
    emitter: bool
    material: GTMaterial | None
    uv_function: Callable | None = None

    @property
    def masked(self) -> bool:
        return self.emitter or self.material is None or self.material.masked


def _array(params, key, width):
    if key not in params.keys():
        return None
    a = np.array(params[key], np.float64).reshape(-1, width)
    return a if len(a) else None


def _transform_points(m: np.ndarray, p: np.ndarray) -> np.ndarray:
    return p @ m[:3, :3].T + m[:3, 3]


def _tessellate(kind: str, to_world: np.ndarray):
    """(vertices, faces, texcoords, normals, uv_function) of a rectangle, disk, sphere or cylinder."""
    s = TESSELLATION_SEGMENTS
    phi = 2.0 * np.pi * np.arange(s) / s
    inv = np.linalg.inv(to_world)
    normal_m = np.linalg.inv(to_world[:3, :3]).T

    def angle(x, y):
        return np.mod(np.arctan2(y, x), 2.0 * np.pi) / (2.0 * np.pi)

    if kind == "rectangle":
        local = np.array([[-1.0, -1.0, 0.0], [1.0, -1.0, 0.0], [1.0, 1.0, 0.0], [-1.0, 1.0, 0.0]])
        faces = np.array([[0, 1, 2], [0, 2, 3]], np.int64)
        vertices = _transform_points(to_world, local)
        return vertices, faces, 0.5 * (local[:, :2] + 1.0), None, None  # affine uv: interpolation is exact
    if kind == "disk":
        local = np.concatenate([[[0.0, 0.0, 0.0]], np.stack([np.cos(phi), np.sin(phi), np.zeros(s)], 1)])
        faces = np.stack([np.zeros(s, np.int64), 1 + np.arange(s), 1 + (np.arange(s) + 1) % s], 1)
        normals = np.tile([0.0, 0.0, 1.0], (len(local), 1))

        def uv_function(p):
            q = _transform_points(inv, p)
            return np.stack([np.hypot(q[:, 0], q[:, 1]), angle(q[:, 0], q[:, 1])], 1)
    elif kind == "sphere":
        import trimesh
        ico = trimesh.creation.icosphere(subdivisions=3)
        local, faces = np.asarray(ico.vertices, np.float64), np.asarray(ico.faces, np.int64)
        normals = local.copy()

        def uv_function(p):
            q = _transform_points(inv, p)
            q /= np.linalg.norm(q, axis=1, keepdims=True)
            return np.stack([angle(q[:, 0], q[:, 1]), np.arccos(np.clip(q[:, 2], -1, 1)) / np.pi], 1)
    else:  # cylinder: radius 1, z in [0, 1], open
        ring = np.stack([np.cos(phi), np.sin(phi), np.zeros(s)], 1)
        local = np.concatenate([ring, ring + [0.0, 0.0, 1.0]])
        i = np.arange(s)
        j = (i + 1) % s
        faces = np.concatenate([np.stack([i, j, j + s], 1), np.stack([i, j + s, i + s], 1)])
        normals = np.concatenate([ring, ring])

        def uv_function(p):
            q = _transform_points(inv, p)
            return np.stack([angle(q[:, 0], q[:, 1]), q[:, 2]], 1)
    vertices = _transform_points(to_world, local)
    normals = normals @ normal_m.T
    normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-30)
    texcoords = uv_function(vertices)
    return vertices, faces, texcoords, normals, uv_function


def shape_geometry(shape, plugin: str):
    """(vertices, faces, texcoords, normals, uv_function) in world space, or None if unsupported."""
    mi = mb.load_mitsuba()
    params = mi.traverse(shape)
    if shape.is_mesh() and "vertex_positions" in params.keys():
        vertices = _array(params, "vertex_positions", 3)
        faces = np.array(params["faces"], np.int64).reshape(-1, 3)
        texcoords = _array(params, "vertex_texcoords", 2)
        normals = _array(params, "vertex_normals", 3)
        return vertices, faces, texcoords, normals, None
    if shape.is_mesh():  # rectangle (a two-triangle mesh in Mitsuba 3.6+) and other built-in meshes
        nv, nf = shape.vertex_count(), shape.face_count()
        vertices = np.array([list(shape.vertex_position(i)) for i in range(nv)], np.float64)
        faces = np.array([list(shape.face_indices(i)) for i in range(nf)], np.int64)
        texcoords = (np.array([list(shape.vertex_texcoord(i)) for i in range(nv)], np.float64)
                     if shape.has_vertex_texcoords() else None)
        return vertices, faces, texcoords, None, None
    if plugin in ANALYTIC_SHAPES or plugin == "rectangle":
        return _tessellate(plugin, np.array(params["to_world"].matrix, np.float64))
    return None


def reconstruction_mesh(objects: Sequence[SourceObject], *, progress: bool = False, cache_dir=False,
                        source_file: str = "mitsuba scene") -> tuple[Mesh, list[UVDecision]]:
    """Our Mesh (same triangles, in order) with UVs in [0, 1] per object, and the UV decisions.

    Objects are checked with `uv_checks.uv_problem` and re-unwrapped with `unwrap.unwrap_object`
    (no cameras yet: about a DEFAULT_RESOLUTION page each; cache_dir as there, off by default);
    an object too large to unwrap is an InputError naming `source_file`.
    """
    vertices, faces, uvs, face_object, decisions = [], [], [], [], []
    offset = 0
    for object_id, obj in enumerate(tqdm(objects, desc="uv layout", unit="object", disable=not progress)):
        start = time.perf_counter()
        result = None
        if obj.uv_function is not None:
            reason = f"analytic {obj.shape} (tessellated)"
        elif obj.texcoords is None:
            reason = "no texture coordinates"
        else:
            ours = obj.texcoords[obj.faces].copy()
            ours[..., 1] = 1.0 - ours[..., 1]        # Mitsuba (v down) -> ours (v up)
            reason = uv_problem(ours, obj.vertices[obj.faces])
        if reason is None:
            uv = ours
        else:
            result = unwrap_object(obj.vertices, obj.faces, name=obj.name, cache_dir=cache_dir, progress=progress,
                                   mesh_file=source_file)
            uv = result.uv
            reason += f"; {result.note}" if result.note else ""
        decisions.append(UVDecision(obj.name, reason is not None, reason or "kept", time.perf_counter() - start,
                                    page_size=result.page_size if result else None,
                                    texels_per_unit=result.texels_per_unit if result else None,
                                    cached=bool(result and result.cached), faces=len(obj.faces)))
        vertices.append(obj.vertices)
        faces.append(obj.faces + offset)
        uvs.append(uv)
        face_object.append(np.full(len(obj.faces), object_id, np.int32))
        offset += len(obj.vertices)
    mesh = Mesh(vertices=np.concatenate(vertices), faces=np.concatenate(faces).astype(np.int64),
                uv=np.concatenate(uvs), face_object=np.concatenate(face_object),
                object_names=tuple(o.name for o in objects))
    return mesh, decisions
