"""Multi-object scenes: a list of mesh files, each placed in the world by its own transform.

This is the thesis's `scene_config` option: a scene arrives as separate objects (a bed, a
lamp, the walls) plus the transform of each, instead of one conjoined mesh. Every object keeps
its own texture page (layout "pages"), so the exported textures and glTF stay per object.

Entries (in scene.json's "meshes", or in a stand-alone config file
`{"format": "jaxdistill-scene-config", "version": 1, "meshes": [...]}`):

    {"name": "bed", "file": "objects/bed.obj",
     "transform": {"translation": [x, y, z],                 # world units
                   "rotation_quaternion": [w, x, y, z],       # or "rotation_euler_deg": [x, y, z]
                   "scale": 1.0}}                             # a number or [sx, sy, sz]
    {"name": "wall", "file": "wall.ply", "transform": {"matrix": [[...4x4...]]}}

world = T R S p: scale first, then rotation, then translation (or `matrix`, acting on column
vectors). Euler angles are Blender's default "XYZ" order: R = Rz Ry Rx. No transform means
identity. A file with one geometry node becomes one object called `name`; a file with several
becomes `name/<node>` objects. A transform with a negative determinant (a mirror) reverses
the faces' corner order so that normals keep pointing the same way relative to the surface.
Mesh files may lack UVs (NaN UVs, see `unwrap.py`); file paths are relative to the config.
"""

from __future__ import annotations

import math
import os
from pathlib import Path

import numpy as np

from jaxdistill.scene.cameras import quaternion_to_rotation
from jaxdistill.errors import InputError, ProblemList, read_json
from jaxdistill.scene.mesh import Mesh, load_mesh
from jaxdistill.scene.paths import scene_file_path

CONFIG_FORMAT = "jaxdistill-scene-config"
CONFIG_VERSION = 1
_TRANSFORM_KEYS = ("matrix", "translation", "rotation_quaternion", "rotation_euler_deg", "scale")


def euler_xyz_matrix(degrees) -> np.ndarray:
    """(3, 3) rotation Rz @ Ry @ Rx of Euler angles (x, y, z) in degrees (Blender's XYZ order)."""
    ax, ay, az = (math.radians(float(a)) for a in degrees)
    cx, sx, cy, sy, cz, sz = math.cos(ax), math.sin(ax), math.cos(ay), math.sin(ay), math.cos(az), math.sin(az)
    rx = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    ry = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    rz = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
    return rz @ ry @ rx


def _vector(value, length: int, file, field, problems) -> np.ndarray | None:
    try:
        array = np.asarray(value, np.float64)
    except (TypeError, ValueError):
        array = None
    if array is None or array.shape != (length,) or not np.isfinite(array).all():
        problems.add(file, field, f"expected {length} finite numbers, got {value!r}")
        return None
    return array


def parse_transform(spec, file, field: str, problems: ProblemList) -> np.ndarray | None:
    """(4, 4) float64 object-to-world transform of an entry's "transform" (None: problems added)."""
    if spec is None:
        return np.eye(4)
    if not isinstance(spec, dict):
        problems.add(file, field, "expected an object with matrix, or translation/rotation_*/scale")
        return None
    unknown = sorted(set(spec) - set(_TRANSFORM_KEYS))
    if unknown:
        problems.add(file, field, f"unknown keys {unknown}; use {', '.join(_TRANSFORM_KEYS)}")
    if "matrix" in spec:
        if len(spec) > 1:
            problems.add(file, field, "give either \"matrix\" alone or translation/rotation_*/scale")
            return None
        try:
            m = np.asarray(spec["matrix"], np.float64)
        except (TypeError, ValueError):
            m = None
        if m is None or m.shape != (4, 4) or not np.isfinite(m).all():
            problems.add(file, f"{field}.matrix", "expected a finite 4x4 matrix (rows)")
            return None
        if np.abs(m[3] - [0, 0, 0, 1]).max() > 1e-9:
            problems.add(file, f"{field}.matrix", f"last row must be [0, 0, 0, 1], got {m[3].tolist()}")
            return None
    else:
        if "rotation_quaternion" in spec and "rotation_euler_deg" in spec:
            problems.add(file, field, "give one of rotation_quaternion or rotation_euler_deg, not both")
            return None
        rotation = np.eye(3)
        if "rotation_quaternion" in spec:
            q = _vector(spec["rotation_quaternion"], 4, file, f"{field}.rotation_quaternion", problems)
            if q is None:
                return None
            if np.linalg.norm(q) < 1e-12:
                problems.add(file, f"{field}.rotation_quaternion", "the quaternion is zero")
                return None
            rotation = quaternion_to_rotation(q)
        elif "rotation_euler_deg" in spec:
            e = _vector(spec["rotation_euler_deg"], 3, file, f"{field}.rotation_euler_deg", problems)
            if e is None:
                return None
            rotation = euler_xyz_matrix(e)
        scale = spec.get("scale", 1.0)
        scale = _vector([scale] * 3 if np.ndim(scale) == 0 else scale, 3, file, f"{field}.scale", problems)
        translation = _vector(spec.get("translation", [0, 0, 0]), 3, file, f"{field}.translation", problems)
        if scale is None or translation is None:
            return None
        m = np.eye(4)
        m[:3, :3], m[:3, 3] = rotation @ np.diag(scale), translation
    det = float(np.linalg.det(m[:3, :3]))
    if not abs(det) > 1e-12:
        problems.add(file, field, f"the transform is singular (determinant {det:.3g}): a zero scale?")
        return None
    return m


def load_objects(entries, root: Path, file, field: str = "meshes", *, allow_outside_paths: bool = False) -> Mesh:
    """One Mesh of all entries' objects, transformed to world space; InputError naming file and field.
    Object files must lie inside `root` unless `allow_outside_paths` (checked before any is read)."""
    problems = ProblemList()
    if not isinstance(entries, list) or not entries:
        raise InputError.single(file, field, "expected a non-empty list of {name, file, transform} objects")
    parsed, names = [], set()
    for i, entry in enumerate(entries):
        where = f"{field}[{i}]"
        if not isinstance(entry, dict) or "file" not in entry or "name" not in entry:
            problems.add(file, where, "expected an object with \"name\", \"file\" and optionally \"transform\"")
            continue
        name = str(entry["name"])
        if name in names:
            problems.add(file, f"{where}.name", f"duplicate object name {name!r}")
        names.add(name)
        path = scene_file_path(root, entry["file"], file, f"{where}.file", problems,
                               allow_outside=allow_outside_paths)
        if path is None:
            continue
        if not path.is_file():
            problems.add(file, f"{where}.file", f"file not found: {path}")
        transform = parse_transform(entry.get("transform"), file, f"{where}.transform", problems)
        parsed.append((name, path, transform))
    problems.raise_if_any()

    vertices, faces, uvs, face_object, object_names = [], [], [], [], []
    offset = 0
    for name, path, transform in parsed:
        part = load_mesh(path, require_uv=False)
        v = part.vertices @ transform[:3, :3].T + transform[:3, 3]
        f = part.faces[:, ::-1] if np.linalg.det(transform[:3, :3]) < 0 else part.faces
        uv = part.uv[:, ::-1] if np.linalg.det(transform[:3, :3]) < 0 else part.uv
        vertices.append(v)
        faces.append(f + offset)
        uvs.append(uv)
        face_object.append(part.face_object + len(object_names))
        single = len(part.object_names) == 1
        object_names += [name if single else f"{name}/{node}" for node in part.object_names]
        offset += len(v)
    return Mesh(vertices=np.concatenate(vertices), faces=np.concatenate(faces), uv=np.concatenate(uvs),
                face_object=np.concatenate(face_object).astype(np.int32), object_names=tuple(object_names))


def read_scene_config(path, *, allow_outside_paths: bool = False) -> Mesh:
    """The Mesh of a stand-alone scene config file (format "jaxdistill-scene-config"); its object
    files must lie inside its folder unless `allow_outside_paths`."""
    path = Path(path)
    doc = read_json(path, "scene config not found")
    file = os.fspath(path)
    if not isinstance(doc, dict) or doc.get("format") != CONFIG_FORMAT:
        raise InputError.single(file, "format", f"expected {CONFIG_FORMAT!r}, got "
                                f"{doc.get('format') if isinstance(doc, dict) else type(doc).__name__!r}")
    if doc.get("version") != CONFIG_VERSION:
        raise InputError.single(file, "version", f"this jaxdistill reads version {CONFIG_VERSION}, got {doc.get('version')!r}")
    return load_objects(doc.get("meshes"), path.parent, file, "meshes", allow_outside_paths=allow_outside_paths)
