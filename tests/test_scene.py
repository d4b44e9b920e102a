"""Scene format: round trip, and every validation rule's error naming the file and field."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from conftest import look_at_camera
from jaxdistill.io import images as imageio
from jaxdistill.scene import shapes as synthetic
from jaxdistill.errors import InputError
from jaxdistill.scene.model import Mesh, Scene, View, read_scene, validate_scene, write_scene


def make_scene_folder(folder, mesh_name="mesh.glb"):
    """A two-view box-room scene on disk (EXR and PNG photos, one albedo target)."""
    mesh = synthetic.box_room((4.0, 2.5, 3.0), subdivisions=2, furniture=True)
    cams = [look_at_camera((1.0, 1.4, 0.7), (3.5, 0.4, 2.6), 32, 24, fx=22.0, cx=15.0, cy=13.0),
            look_at_camera((3.2, 1.0, 2.5), (0.5, 0.9, 0.4), 32, 24, fx=30.0)]
    rng = np.random.default_rng(0)
    imageio.write_image(folder / "photos" / "a.exr", rng.uniform(0, 4, (24, 32, 3)))
    imageio.write_image(folder / "photos" / "b.png", rng.uniform(0, 1, (24, 32, 3)))
    imageio.write_image(folder / "targets" / "albedo_a.png", rng.uniform(0, 1, (24, 32, 3)))
    views = (View("a", cams[0], folder / "photos" / "a.exr", {"albedo": folder / "targets" / "albedo_a.png"}),
             View("b", cams[1], folder / "photos" / "b.png"))
    scene = Scene(name="room", mesh=mesh, views=views)
    return scene, write_scene(scene, folder, mesh_name=mesh_name)


@pytest.mark.parametrize("mesh_name", ["mesh.glb", "mesh.gltf"])
def test_round_trip(tmp_path, mesh_name):
    scene, path = make_scene_folder(tmp_path, mesh_name)
    back = read_scene(path)
    assert back.name == "room" and back.texture_layout == "pages"
    assert back.mesh.object_names == scene.mesh.object_names
    # Per-corner positions and UVs survive (float32 storage in glTF), face order per object too.
    np.testing.assert_allclose(back.mesh.triangles(), scene.mesh.triangles(), atol=1e-6)
    np.testing.assert_allclose(back.mesh.uv, scene.mesh.uv, atol=1e-6)
    np.testing.assert_array_equal(back.mesh.face_object, scene.mesh.face_object)
    for a, b in zip(scene.views, back.views):
        assert a.name == b.name and a.photo == b.photo and dict(a.targets) == dict(b.targets)
        np.testing.assert_array_equal(a.camera.K, b.camera.K)
        np.testing.assert_array_equal(a.camera.c2w, b.camera.c2w)
        assert (a.camera.width, a.camera.height) == (b.camera.width, b.camera.height)
    again = write_scene(back, tmp_path / "copy_dir" / "..", mesh_name="mesh2.glb")
    assert read_scene(again).mesh.num_faces == scene.mesh.num_faces


def test_reads_plain_obj_single_object(tmp_path):
    (tmp_path / "m.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 0 -1\nvt 0 0\nvt 1 0\nvt 0 1\nf 1/1 2/2 3/3\n")
    imageio.write_image(tmp_path / "p.png", np.full((8, 8, 3), 0.5))       # a photo shows something
    cam = look_at_camera((0.2, 1.0, -0.2), (0.2, 0.0, -0.3), 8, 8)
    doc = {"format": "jaxdistill-scene", "version": 1, "mesh": "m.obj",
           "views": [{"width": 8, "height": 8, "K": cam.K.tolist(), "c2w": cam.c2w.tolist(), "photo": "p.png"}]}
    (tmp_path / "scene.json").write_text(json.dumps(doc))
    scene = read_scene(tmp_path)
    assert scene.mesh.num_faces == 1 and len(scene.mesh.object_names) == 1
    np.testing.assert_allclose(scene.mesh.uv[0], [[0, 0], [1, 0], [0, 1]])


def edit(path, change):
    doc = json.loads(path.read_text())
    change(doc)
    path.write_text(json.dumps(doc))


def problems_of(path):
    with pytest.raises(InputError) as info:
        read_scene(path)
    return info.value.problems, str(info.value)


def test_errors_name_file_and_field(tmp_path):
    _, path = make_scene_folder(tmp_path)

    def breaks(doc):
        doc["views"][0]["K"][0][0] = -5.0                       # focal <= 0
        doc["views"][1]["c2w"][0][0] = 2.0                      # non-rigid
        doc["views"][0]["targets"]["glossiness"] = "photos/a.exr"  # unknown map
        doc["views"][1]["photo"] = "photos/missing.png"         # missing photo

    edit(path, breaks)
    problems, message = problems_of(path)
    fields = {field for _, field, _ in problems}
    assert fields == {"views[0].K", "views[1].c2w", "views[0].targets.glossiness", "views[1].photo"}, message
    assert all(file == str(path) for file, _, _ in problems), message
    assert "focal" in message and "glossiness" in message and "known maps: albedo" in message
    # A missing photo of an otherwise valid view is reported alone.
    _, path2 = make_scene_folder(tmp_path / "b")
    edit(path2, lambda d: d["views"][1].__setitem__("photo", "photos/missing.png"))
    problems, message = problems_of(path2)
    assert problems == [(str(path2), "views[1].photo", problems[0][2])] and "file not found" in message


def test_singular_pose_and_wrong_image_size(tmp_path):
    _, path = make_scene_folder(tmp_path)

    def breaks(doc):
        doc["views"][0]["c2w"] = [[0, 0, 0, 0]] * 3 + [[0, 0, 0, 1]]
        doc["views"][1]["width"] = 33

    edit(path, breaks)
    problems, message = problems_of(path)
    fields = {field for _, field, _ in problems}
    assert fields == {"views[0].c2w", "views[1].photo"}, message
    assert "32x24 but the view is 33x24" in message


def test_nan_photo_and_missing_fields(tmp_path):
    _, path = make_scene_folder(tmp_path)
    bad = np.ones((24, 32, 3), np.float32)
    bad[5, 7, 1] = np.nan
    imageio.write_image(tmp_path / "photos" / "a.exr", bad)
    edit(path, lambda d: d["views"][1].pop("K"))
    problems, message = problems_of(path)
    assert {f for _, f, _ in problems} == {"views[0].photo", "views[1].K"}, message
    assert "NaN/inf pixels (first at row 5, column 7)" in message and "required field is missing" in message


def test_mesh_rules(tmp_path):
    scene, _ = make_scene_folder(tmp_path)
    mesh = scene.mesh

    def with_mesh(**changes):
        return dataclasses.replace(scene, mesh=dataclasses.replace(mesh, **changes))

    cases = {
        "vertices": with_mesh(vertices=np.where(np.arange(len(mesh.vertices))[:, None] == 3, np.nan, mesh.vertices)),
        "faces": with_mesh(faces=np.where(np.arange(mesh.num_faces)[:, None] == 2, len(mesh.vertices), mesh.faces)),
    }
    uv = mesh.uv.copy()
    uv[4, 1, 0] = np.inf
    cases["uv"] = with_mesh(uv=uv)
    tiled = mesh.uv.copy()
    tiled[6] *= 3.0
    for field, broken in list(cases.items()) + [("uv", with_mesh(uv=tiled))]:
        with pytest.raises(InputError) as info:
            validate_scene(broken, mesh_file="room.glb")
        assert info.value.problems[0][:2] == ("room.glb", field), str(info.value)
    with pytest.raises(InputError, match="outside \\[0, 1\\].*re-unwrap"):
        validate_scene(with_mesh(uv=tiled), mesh_file="room.glb")


def test_unreadable_mesh_and_json(tmp_path):
    _, path = make_scene_folder(tmp_path)
    edit(path, lambda d: d.__setitem__("objects", ["floor"]))
    with pytest.raises(InputError, match="objects: object names do not match"):
        read_scene(path)
    (tmp_path / "bad.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nvt 0 0\nvt 1 0\nvt 0 1\nf 1/1 2/2 7/3\n")
    edit(path, lambda d: d.__setitem__("mesh", "bad.obj"))
    with pytest.raises(InputError, match="bad.obj: faces: a face indexes a vertex"):
        read_scene(path)
    (tmp_path / "nouv.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    edit(path, lambda d: (d.__setitem__("mesh", "nouv.obj"), d.pop("objects")))
    with pytest.raises(InputError, match="no texture coordinates"):
        read_scene(path)
    path.write_text("{ not json")
    with pytest.raises(InputError, match="not valid JSON"):
        read_scene(path)
    with pytest.raises(InputError, match="scene file not found"):
        read_scene(tmp_path / "nowhere" / "scene.json")


def test_paths_outside_the_scene_folder_are_refused_before_anything_is_read(tmp_path, monkeypatch):
    """../, absolute paths and symlinks out of the folder: refused by default, naming file and field,
    before any file is opened (so the messages cannot tell which files exist); read with the opt-in."""
    from jaxdistill.scene import model as scene_lib

    scene, path = make_scene_folder(tmp_path / "scene")
    shared = tmp_path / "shared"
    imageio.write_image(shared / "photo.png", np.full((24, 32, 3), 0.5))
    (path.parent / "mesh.glb").rename(shared / "mesh.glb")
    (path.parent / "photos" / "link.png").symlink_to(shared / "photo.png")
    (path.parent / "gt.json").write_text(json.dumps({"format": "jaxdistill-gt", "textures": {
        "albedo": {scene.mesh.object_names[0]: "../shared/albedo.exr"}}}))

    def outside(doc):
        doc["mesh"] = str(shared / "mesh.glb")                            # absolute, exists
        doc["views"][0]["photo"] = "../shared/photo.png"                  # ../, exists
        doc["views"][1]["photo"] = "/no/such/secret.png"                  # absolute, does not exist
        doc["views"][1]["mask"] = "photos/link.png"                       # a symlink pointing out
        doc["views"][0]["targets"]["albedo"] = "targets/../../../etc/passwd"

    edit(path, outside)

    def never(*args, **kwargs):
        raise AssertionError("a file was read before the path check")

    with monkeypatch.context() as m:
        for name in ("read_image", "image_size"):
            m.setattr(imageio, name, never)
        m.setattr(scene_lib, "load_mesh", never)
        problems, message = problems_of(path)
    assert {field for _, field, _ in problems} == {
        "mesh", "views[0].photo", "views[1].photo", "views[1].mask", "views[0].targets.albedo",
        f"textures.albedo.{scene.mesh.object_names[0]}"}, message
    assert all("resolves outside the scene folder" in m and "--allow_outside_paths" in m and "not found" not in m
               for _, _, m in problems), message
    assert {file for file, _, _ in problems} == {str(path), str(path.parent / "gt.json")}

    # sharing files between scenes on purpose: the opt-in reads them
    (path.parent / "gt.json").unlink()
    edit(path, lambda d: (d["views"][1].__setitem__("photo", "../shared/photo.png"),
                          d["views"][0]["targets"].__setitem__("albedo", "targets/albedo_a.png")))
    with pytest.raises(InputError, match=r"scene\.json: mesh: '/.*/shared/mesh\.glb' resolves outside"):
        read_scene(path)
    back = read_scene(path, allow_outside_paths=True)
    assert back.views[0].photo.resolve() == back.views[1].photo.resolve() == shared / "photo.png"
    assert back.mesh.num_faces == scene.mesh.num_faces
