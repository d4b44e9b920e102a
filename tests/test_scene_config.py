"""Multi-object scenes: objects with transforms (the thesis's scene_config), one page per object."""

from __future__ import annotations

import json

import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

from jaxdistill.errors import InputError
from jaxdistill.scene.model import read_scene
from jaxdistill.scene.cameras import quaternion_to_rotation
from jaxdistill.scene.objects import euler_xyz_matrix, read_scene_config
from tiny_scene import write_tiny_scene


def write_object(path, offset=0.0):
    """A UV-mapped unit square in z = 0 (two triangles, normals +z)."""
    v = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], np.float64) + offset
    f = np.array([[0, 1, 2], [0, 2, 3]])
    uv = v[:, :2] - offset
    trimesh.Trimesh(v, f, visual=trimesh.visual.TextureVisuals(uv=uv), process=False).export(path)
    return v, f


def test_rotations_match_scipy():
    q = np.array([0.3, -0.2, 0.8, 0.4])
    np.testing.assert_allclose(quaternion_to_rotation(q), Rotation.from_quat(np.roll(q, -1)).as_matrix(), atol=1e-12)
    e = [30.0, -45.0, 110.0]
    np.testing.assert_allclose(euler_xyz_matrix(e), Rotation.from_euler("xyz", e, degrees=True).as_matrix(), atol=1e-12)


def test_objects_are_placed_by_their_transforms_and_keep_their_own_names(tmp_path):
    v, f = write_object(tmp_path / "a.obj")
    write_object(tmp_path / "b.ply")
    q = [0.9, 0.1, 0.3, -0.2]
    m = np.eye(4)
    m[:3, :3] = np.diag([-1.0, 1.0, 1.0])            # a mirror
    m[:3, 3] = [5, 0, 0]
    doc = {"format": "jaxdistill-scene-config", "version": 1, "meshes": [
        {"name": "table", "file": "a.obj", "transform": {"translation": [1, 2, 3], "rotation_quaternion": q, "scale": 2}},
        {"name": "lamp", "file": "b.ply", "transform": {"rotation_euler_deg": [0, 90, 0], "scale": [1, 2, 3]}},
        {"name": "mirror", "file": "a.obj", "transform": {"matrix": m.tolist()}},
        {"name": "plain", "file": "a.obj"}]}
    (tmp_path / "objects.json").write_text(json.dumps(doc))
    mesh = read_scene_config(tmp_path / "objects.json")
    assert mesh.object_names == ("table", "lamp", "mirror", "plain")
    R = Rotation.from_quat(np.roll(np.array(q) / np.linalg.norm(q), -1)).as_matrix()
    expected = {"table": v * 2 @ R.T + [1, 2, 3],
                "lamp": (v * [1, 2, 3]) @ Rotation.from_euler("xyz", [0, 90, 0], degrees=True).as_matrix().T,
                "mirror": v @ m[:3, :3].T + m[:3, 3], "plain": v}
    for o, name in enumerate(mesh.object_names):
        faces = mesh.faces[mesh.face_object == o]
        points = mesh.vertices[np.unique(faces)]
        np.testing.assert_allclose(np.sort(points, axis=0), np.sort(expected[name], axis=0), atol=1e-12)
        tri = mesh.vertices[faces]
        normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        # the mirror keeps the surface's normal direction in world space (+z here), not flipped
        if name in ("mirror", "plain"):
            assert (normal[:, 2] > 0).all(), name
    assert np.isfinite(mesh.uv).all() and mesh.uv.min() >= 0 and mesh.uv.max() <= 1


def test_scene_json_lists_objects_and_gets_one_page_per_object(tmp_path):
    scene_json = write_tiny_scene(tmp_path / "tiny", views=2, targets=False, gt=False)
    doc = json.loads(scene_json.read_text())
    write_object(tmp_path / "tiny" / "sq.obj")
    del doc["mesh"], doc["objects"]
    doc["meshes"] = [{"name": f"tile{i}", "file": "sq.obj", "transform": {"translation": [0.5 + i, 0.5, 0.01]}}
                     for i in range(3)]
    scene_json.write_text(json.dumps(doc))
    scene = read_scene(scene_json)
    assert scene.mesh.object_names == ("tile0", "tile1", "tile2") and scene.texture_layout == "pages"
    from jaxdistill.render.layout import make_layout

    layout = make_layout(scene.num_objects, scene.texture_layout, 16, [])
    assert layout.object_page == (0, 1, 2)


@pytest.mark.parametrize("entry, message", [
    ({"name": "x", "file": "missing.obj"}, r"meshes\[0\]\.file: file not found"),
    ({"name": "x", "file": "a.obj", "transform": {"scale": 0}}, r"meshes\[0\]\.transform: the transform is singular"),
    ({"name": "x", "file": "a.obj", "transform": {"rotation_quaternion": [0, 0, 0, 0]}}, r"quaternion is zero"),
    ({"name": "x", "file": "a.obj", "transform": {"matrix": [[1, 0, 0], [0, 1, 0]]}}, r"transform\.matrix: expected a finite 4x4"),
    ({"name": "x", "file": "a.obj", "transform": {"rotate": [1, 2, 3]}}, r"unknown keys \['rotate'\]"),
    ({"file": "a.obj"}, r"meshes\[0\]: expected an object with \"name\""),
])
def test_bad_entries_name_the_field(tmp_path, entry, message):
    write_object(tmp_path / "a.obj")
    (tmp_path / "c.json").write_text(json.dumps({"format": "jaxdistill-scene-config", "version": 1, "meshes": [entry]}))
    with pytest.raises(InputError, match=message):
        read_scene_config(tmp_path / "c.json")


def test_duplicate_names_and_wrong_format_are_refused(tmp_path):
    write_object(tmp_path / "a.obj")
    doc = {"format": "jaxdistill-scene-config", "version": 1,
           "meshes": [{"name": "x", "file": "a.obj"}, {"name": "x", "file": "a.obj"}]}
    (tmp_path / "c.json").write_text(json.dumps(doc))
    with pytest.raises(InputError, match=r"meshes\[1\]\.name: duplicate object name 'x'"):
        read_scene_config(tmp_path / "c.json")
    (tmp_path / "c.json").write_text(json.dumps({"meshes": []}))
    with pytest.raises(InputError, match=r"format: expected 'jaxdistill-scene-config'"):
        read_scene_config(tmp_path / "c.json")


def test_object_files_outside_the_config_folder_are_refused_unless_allowed(tmp_path):
    (tmp_path / "shared").mkdir()
    (tmp_path / "cfg").mkdir()
    write_object(tmp_path / "shared" / "a.obj")
    doc = {"format": "jaxdistill-scene-config", "version": 1,
           "meshes": [{"name": "x", "file": "../shared/a.obj"}, {"name": "y", "file": str(tmp_path / "nowhere.obj")}]}
    (tmp_path / "cfg" / "c.json").write_text(json.dumps(doc))
    with pytest.raises(InputError) as err:
        read_scene_config(tmp_path / "cfg" / "c.json")
    fields = [field for _, field, _ in err.value.problems]
    assert fields == ["meshes[0].file", "meshes[1].file"]
    # the same words whether the file exists or not: the message tells nothing about the machine
    assert all("resolves outside the scene folder" in m and "--allow_outside_paths" in m and "not found" not in m
               for _, _, m in err.value.problems)
    doc["meshes"] = doc["meshes"][:1]
    (tmp_path / "cfg" / "c.json").write_text(json.dumps(doc))
    assert read_scene_config(tmp_path / "cfg" / "c.json", allow_outside_paths=True).object_names == ("x",)
