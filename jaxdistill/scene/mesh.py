"""Triangle meshes: the `Mesh` every module shares, and reading / writing mesh files.

Mesh files: any trimesh-readable file (GLB/GLTF, OBJ, PLY, ...). Each geometry node of the file
is one object (its node transform applied); object ids follow the given object names, else
sorted node names. UVs are per vertex in the file (vertices split at seams, as trimesh does)
and become per-corner `uv[faces]`. UV convention: u right, v up (OBJ/trimesh; glTF's flipped v
is undone by trimesh). Validation of a mesh against a scene is `scene.mesh_problems`.
"""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path

import numpy as np

from jaxdistill.errors import InputError


@dataclasses.dataclass(frozen=True, eq=False)
class Mesh:
    """Triangle mesh in world units.

    vertices (Nv, 3) float64; faces (F, 3) int64; uv (F, 3, 2) float64 per corner, in [0, 1],
    v up; face_object (F,) int32 object id per face; object_names one per object id.
    """

    vertices: np.ndarray
    faces: np.ndarray
    uv: np.ndarray
    face_object: np.ndarray
    object_names: tuple[str, ...]

    @property
    def num_faces(self) -> int:
        return int(self.faces.shape[0])

    def triangles(self) -> np.ndarray:
        """(F, 3, 3) float64 corner positions."""
        return self.vertices[self.faces]


def face_normals(mesh: Mesh) -> np.ndarray:
    """(F, 3) unit geometric normals, cross(e1, e2) of each triangle (as the mesh orients it)."""
    t = mesh.triangles()
    n = np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0])
    return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-30)


def join_objects(parts, names) -> Mesh:
    """One Mesh of per-object parts [(vertices (N, 3), faces (F, 3), corner uv (F, 3, 2))], object
    k being parts[k] named names[k] (faces re-indexed into the joined vertices)."""
    faces, face_object, offset = [], [], 0
    for k, (v, f, _) in enumerate(parts):
        faces.append(f + offset)
        face_object.append(np.full(len(f), k, np.int32))
        offset += len(v)
    return Mesh(vertices=np.concatenate([v for v, _, _ in parts]), faces=np.concatenate(faces).astype(np.int64),
                uv=np.concatenate([uv for _, _, uv in parts]), face_object=np.concatenate(face_object),
                object_names=tuple(names))


def load_mesh(path: Path, object_names: list[str] | None = None, *, require_uv: bool = True) -> Mesh:
    """Reads a trimesh-readable file; every geometry node becomes one object (transform applied).

    A node without texture coordinates is an InputError, or with `require_uv=False` gets NaN
    UVs (what `unwrap.ensure_uvs` replaces with an xatlas layout).
    """
    import trimesh

    path = Path(path)
    if not path.is_file():
        raise InputError.single(path, "mesh", "file not found")
    try:
        loaded = trimesh.load(os.fspath(path), force="scene", process=False)
    except IndexError as err:  # trimesh indexes UVs/vertices by face while loading
        raise InputError.single(path, "faces", f"a face indexes a vertex or UV that does not exist ({err})") from err
    except Exception as err:  # trimesh raises many exception types for unreadable files
        raise InputError.single(path, "mesh", f"trimesh cannot read it: {type(err).__name__}: {err}") from err
    nodes = {}
    for node in loaded.graph.nodes_geometry:
        transform, geom_name = loaded.graph[node]
        nodes[node] = (np.asarray(transform, np.float64), loaded.geometry[geom_name])
    if not nodes:
        raise InputError.single(path, "mesh", "the file contains no triangle geometry")
    if object_names is None:
        object_names = sorted(nodes)
    else:
        missing = [n for n in object_names if n not in nodes]
        extra = sorted(set(nodes) - set(object_names))
        if missing or extra:
            raise InputError.single(path, "objects", f"object names do not match the mesh nodes: "
                                    f"missing in mesh {missing}, not listed {extra}; nodes are {sorted(nodes)}")
    vertices, faces, uvs, face_object = [], [], [], []
    offset = 0
    for object_id, name in enumerate(object_names):
        transform, geom = nodes[name]
        if not hasattr(geom, "faces"):
            raise InputError.single(path, f"mesh node {name!r}", "is not a triangle mesh (point cloud or path)")
        uv = getattr(geom.visual, "uv", None)
        if uv is None and not require_uv:
            uv = np.full((len(geom.vertices), 2), np.nan)
        if uv is None:
            raise InputError.single(path, f"mesh node {name!r} uv", "has no texture coordinates (TEXCOORD_0/vt); "
                                    "unwrap the mesh (e.g. xatlas) before building a scene")
        v = np.asarray(geom.vertices, np.float64)
        v = v @ transform[:3, :3].T + transform[:3, 3]
        f = np.asarray(geom.faces, np.int64)
        vertices.append(v)
        uv = np.asarray(uv, np.float64)
        if len(uv) != len(v):
            raise InputError.single(path, f"mesh node {name!r} uv",
                                    f"{len(uv)} texture coordinates for {len(v)} vertices")
        valid = (f >= 0) & (f < len(v))
        uvs.append(np.where(valid[..., None], uv[np.clip(f, 0, len(v) - 1)], np.nan))
        faces.append(f + offset)
        face_object.append(np.full(len(f), object_id, np.int32))
        offset += len(v)
    return Mesh(vertices=np.concatenate(vertices), faces=np.concatenate(faces), uv=np.concatenate(uvs),
                face_object=np.concatenate(face_object), object_names=tuple(object_names))


def save_mesh(mesh: Mesh, path: Path) -> None:
    """Writes one node per object, with vertices split where corner UVs differ (GLB, OBJ, PLY...)."""
    import trimesh

    scene = trimesh.Scene()
    for object_id, name in enumerate(mesh.object_names):
        face_ids = np.nonzero(mesh.face_object == object_id)[0]
        corners_v = mesh.faces[face_ids].reshape(-1)
        corners_uv = mesh.uv[face_ids].reshape(-1, 2)
        key = np.concatenate([corners_v[:, None].astype(np.float64), corners_uv], axis=1)
        unique, inverse = np.unique(key, axis=0, return_inverse=True)
        geom = trimesh.Trimesh(vertices=mesh.vertices[unique[:, 0].astype(np.int64)],
                               faces=inverse.reshape(-1, 3),
                               visual=trimesh.visual.TextureVisuals(uv=unique[:, 1:]), process=False)
        scene.add_geometry(geom, geom_name=name, node_name=name)
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    scene.export(os.fspath(path))
