"""Importing a Mitsuba 3 scene: geometry, UV layout, exact ground truth, views, errors."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from conftest import look_at_camera
from jaxdistill.io import images as imageio
from jaxdistill.errors import InputError
from jaxdistill.render import fragments as fr
from jaxdistill.scene.model import read_scene

mi = pytest.importorskip("mitsuba")
pytest.importorskip("xatlas")
from jaxdistill.datasets.mitsuba import bridge as mb
from jaxdistill.datasets.mitsuba import ground_truth as gt_lib
from jaxdistill.datasets.mitsuba import prepare
from jaxdistill.datasets.mitsuba import shapes as mitsuba_shapes
from jaxdistill.datasets.mitsuba.ground_truth import GroundTruthEvaluator, render_irradiance
from jaxdistill.datasets.mitsuba.shapes import reconstruction_mesh
from jaxdistill.datasets.mitsuba.source import load_source
from jaxdistill.render import uv_checks

REPO = Path(__file__).resolve().parents[1]
# Bitterli's "Modern Hall" (CC-BY 3.0, tests/data/staircase2/LICENSE.txt): the copy in tests/data (so CI
# runs it), else where $JAXDISTILL_STAIRCASE2 says, else beside the checkout (../shared)
STAIRCASE = next((p for p in [REPO / "tests" / "data" / "staircase2" / "scene.xml",
                              Path(os.environ.get("JAXDISTILL_STAIRCASE2", "/nonexistent")), *(
    parent / "shared" / "scenes" / "staircase2" / "scene.xml" for parent in REPO.parents)] if p.is_file()),
    REPO.parent / "shared" / "scenes" / "staircase2" / "scene.xml")
ROOM = np.array([4.0, 2.5, 3.0])                    # x, y (up), z
WALL_RGB = (0.2, 0.5, 0.7)
PLASTIC_ALPHA, PLASTIC_RGB = 0.09, (0.6, 0.3, 0.2)
METAL_ALPHA, METAL_ETA, METAL_K = 0.16, (0.2, 0.4, 1.4), (3.9, 2.4, 1.8)
BOX = (np.array([1.6, 0.0, 1.1]), np.array([2.4, 0.8, 1.9]))
GLASS = (np.array([3.0, 0.0, 0.4]), np.array([3.5, 0.5, 0.9]))
TEXELS = (np.arange(4 * 4 * 3).reshape(4, 4, 3) * 5 + 20).astype(np.uint8)   # sRGB codes, distinct
FLOOR_TILE = 2.0                                    # floor uv = (x, z) / 2: tiled, up to (2, 1.5)


# ----------------------------------------------------------------------------- the test scene


def rectangle(centre, a, b) -> str:
    """A <transform> mapping Mitsuba's [-1, 1]^2 rectangle to centre + s a + t b (normal a x b)."""
    a, b, c = (np.asarray(x, float) for x in (a, b, centre))
    n = np.cross(a, b)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = a, b, n / np.linalg.norm(n), c
    return f'<transform name="to_world"><matrix value="{" ".join(f"{x:.9g}" for x in m.ravel())}"/></transform>'


def write_obj(path: Path, vertices, faces, uv=None) -> None:
    """A small OBJ (faces 0-based here), with per-vertex vt when uv is given."""
    lines = [f"v {x:.9g} {y:.9g} {z:.9g}" for x, y, z in vertices]
    if uv is not None:
        lines += [f"vt {u:.9g} {v:.9g}" for u, v in uv]
    for f in faces:
        lines.append("f " + " ".join(f"{i + 1}/{i + 1}" if uv is not None else f"{i + 1}" for i in f))
    path.write_text("\n".join(lines) + "\n")


def box_mesh(lo, hi):
    import trimesh
    box = trimesh.creation.box(bounds=np.stack([lo, hi]))
    return np.asarray(box.vertices), np.asarray(box.faces)


def rgb(name, value) -> str:
    return f'<rgb name="{name}" value="{", ".join(map(str, value))}"/>'


def write_room(folder: Path, extra_shapes: str = "", *, light_down: bool = False, max_depth: int = 4) -> Path:
    """A closed room: tiled-UV bitmap floor (OBJ), rectangle walls/ceiling, a box, glass, a light
    (facing the ceiling 5 cm above it, or down into the room with `light_down`)."""
    folder.mkdir(parents=True, exist_ok=True)
    imageio.write_image(folder / "tex.png", TEXELS.astype(np.float32) / 255.0, encode_srgb=False)
    n = 2
    s = np.linspace(0.0, 1.0, n + 1)
    gx, gz = np.meshgrid(s * ROOM[0], s * ROOM[2])
    verts = np.stack([gx.ravel(), np.zeros(gx.size), gz.ravel()], 1)
    idx = np.arange((n + 1) ** 2).reshape(n + 1, n + 1)
    quads = [(idx[j, i], idx[j + 1, i], idx[j + 1, i + 1], idx[j, i + 1]) for j in range(n) for i in range(n)]
    faces = [f for a, b, c, d in quads for f in ((a, b, c), (a, c, d))]
    write_obj(folder / "floor.obj", verts, faces, uv=verts[:, [0, 2]] / FLOOR_TILE)
    write_obj(folder / "box.obj", *box_mesh(*BOX))
    write_obj(folder / "glass.obj", *box_mesh(*GLASS))
    X, Y, Z = ROOM
    xml = f"""<scene version="3.0.0">
  <integrator type="path"><integer name="max_depth" value="{max_depth}"/></integrator>
  <sensor type="perspective"><transform name="to_world"><lookat origin="2, 1.2, 2.5" target="2, 1.2, 0" up="0, 1, 0"/></transform></sensor>
  <bsdf type="twosided" id="plain"><bsdf type="diffuse">{rgb("reflectance", (0.8, 0.8, 0.8))}</bsdf></bsdf>
  <shape type="obj" id="floor"><string name="filename" value="floor.obj"/>
    <bsdf type="twosided"><bsdf type="diffuse"><texture type="bitmap" name="reflectance">
      <string name="filename" value="tex.png"/><string name="filter_type" value="nearest"/></texture></bsdf></bsdf></shape>
  <shape type="rectangle" id="ceiling">{rectangle((X / 2, Y, Z / 2), (X / 2, 0, 0), (0, 0, Z / 2))}<ref id="plain"/></shape>
  <shape type="rectangle" id="wall_x0">{rectangle((0, Y / 2, Z / 2), (0, 0, Z / 2), (0, Y / 2, 0))}
    <bsdf type="twosided"><bsdf type="diffuse">{rgb("reflectance", WALL_RGB)}</bsdf></bsdf></shape>
  <shape type="rectangle" id="wall_x1">{rectangle((X, Y / 2, Z / 2), (0, Y / 2, 0), (0, 0, Z / 2))}
    <bsdf type="twosided"><bsdf type="roughplastic"><float name="alpha" value="{PLASTIC_ALPHA}"/>
      {rgb("diffuse_reflectance", PLASTIC_RGB)}</bsdf></bsdf></shape>
  <shape type="rectangle" id="wall_z0">{rectangle((X / 2, Y / 2, 0), (X / 2, 0, 0), (0, Y / 2, 0))}
    <bsdf type="twosided"><bsdf type="roughconductor"><float name="alpha" value="{METAL_ALPHA}"/>
      {rgb("eta", METAL_ETA)}{rgb("k", METAL_K)}</bsdf></bsdf></shape>
  <shape type="rectangle" id="wall_z1">{rectangle((X / 2, Y / 2, Z), (0, Y / 2, 0), (X / 2, 0, 0))}<ref id="plain"/></shape>
  <shape type="obj" id="box"><string name="filename" value="box.obj"/><ref id="plain"/></shape>
  <shape type="obj" id="glass"><string name="filename" value="glass.obj"/><bsdf type="dielectric"/></shape>
  <shape type="rectangle" id="light">{rectangle((X / 2, Y - 0.05, Z / 2), *(((0.4, 0, 0), (0, 0, -0.4))[::-1 if light_down else 1]))}
    <emitter type="area">{rgb("radiance", (8, 8, 8))}</emitter></shape>
  {extra_shapes}
</scene>
"""
    path = folder / "scene.xml"
    path.write_text(xml)
    return path


@pytest.fixture(scope="module")
def room_xml(tmp_path_factory) -> Path:
    return write_room(tmp_path_factory.mktemp("room"))


@pytest.fixture(scope="module")
def imported(room_xml, tmp_path_factory):
    out = tmp_path_factory.mktemp("out")
    summary = prepare.prepare_scene(room_xml, out, num_views=3, width=32, height=24, spp=16, seed=1, progress=False)
    return out, summary


@pytest.fixture(scope="module")
def evaluator(room_xml):
    source = load_source(room_xml)
    mesh, decisions = reconstruction_mesh(source.objects)
    return source, mesh, decisions, GroundTruthEvaluator(source.objects, mesh)


def ground_truth(evaluator, cam):
    _, mesh, _, ev = evaluator
    frag = fr.compute_fragments(mesh, [cam], cache_dir=False, progress=False)[0]
    return frag, ev.evaluate(cam, frag), np.array(mesh.object_names)


CENTRE = (2.0, 1.3, 1.5)


# ----------------------------------------------------------------------------- tests


def test_import_writes_a_valid_scene(imported):
    out, summary = imported
    scene = read_scene(out)
    assert len(scene.views) == 3 and scene.texture_layout == "pages"
    assert set(scene.mesh.object_names) == {"floor", "ceiling", "wall_x0", "wall_x1", "wall_z0", "wall_z1", "box",
                                            "glass", "light"}
    for object_id in range(scene.num_objects):
        uv = scene.mesh.uv[scene.mesh.face_object == object_id]
        assert uv.min() >= 0.0 and uv.max() <= 1.0
    assert "floor" in summary["reunwrapped"]                      # tiled UVs
    assert "wall_x0" not in summary["reunwrapped"]                # a rectangle's UVs are fine
    doc = json.loads((out / "import.json").read_text())
    assert doc["format"] == prepare.IMPORT_FORMAT and not (out / "gt.json").exists()   # gt.json: GT textures only
    maps = {"albedo", "normal", "roughness", "metallic", "irradiance"}
    for view in scene.views:
        assert set(view.targets) == maps and set(view.ground_truth) == maps
        assert view.mask == out / "masks" / f"{view.name}.png"
        assert imageio.read_image(view.targets["roughness"]).shape == (24, 32, 1)
        eye = view.camera.center
        assert ((eye > 0) & (eye < ROOM)).all()
        assert not ((eye > BOX[0]) & (eye < BOX[1])).all()        # not inside the box
        assert not ((eye > GLASS[0]) & (eye < GLASS[1])).all()
    readme = (out / "README.md").read_text()
    assert "Conventions" in readme and "spp" in readme


def test_imported_masks_and_constants_agree_with_geometry(imported):
    out, _ = imported
    scene = read_scene(out)
    names = np.array(scene.mesh.object_names)
    frags = fr.compute_fragments(scene.mesh, [v.camera for v in scene.views], cache_dir=False, progress=False)
    seen = set()
    for view, frag in zip(scene.views, frags):
        mask = imageio.read_image(out / "masks" / f"{view.name}.png", linear=False)[..., 0] > 0.5
        obj = np.where(frag.hit, names[np.maximum(frag.object_id, 0)], "")
        np.testing.assert_array_equal(mask, frag.hit & ~np.isin(obj, ["glass", "light"]))
        albedo = imageio.read_image(view.targets["albedo"])
        at = obj == "wall_x0"
        np.testing.assert_allclose(albedo[at], np.broadcast_to(WALL_RGB, albedo[at].shape), atol=1e-6)
        assert (albedo[~mask] == 0).all()
        seen |= set(obj[frag.hit])
    assert len(seen) >= 4                                          # the views look at several objects
    photo = imageio.read_image(scene.views[0].photo)
    assert photo.shape == (24, 32, 3) and photo.max() > 0


def test_constant_materials(evaluator):
    for target, name, check in (
            ((0.0, 1.3, 1.5), "wall_x0", "diffuse"), ((4.0, 1.3, 1.5), "wall_x1", "plastic"),
            ((2.0, 1.3, 0.0), "wall_z0", "metal")):
        cam = look_at_camera(CENTRE, target)
        frag, gt, names = ground_truth(evaluator, cam)
        at = frag.hit & (names[np.maximum(frag.object_id, 0)] == name)
        assert at.sum() > 100 and gt.mask[at].all()
        albedo, rough, metal = gt.albedo[at], gt.roughness[at][:, 0], gt.metallic[at][:, 0]
        if check == "diffuse":
            np.testing.assert_allclose(albedo, np.broadcast_to(WALL_RGB, albedo.shape), atol=1e-6)
            np.testing.assert_allclose(rough, 1.0)
            np.testing.assert_allclose(metal, 0.0)
        elif check == "plastic":
            np.testing.assert_allclose(albedo, np.broadcast_to(PLASTIC_RGB, albedo.shape), atol=1e-6)
            np.testing.assert_allclose(rough, np.sqrt(PLASTIC_ALPHA), atol=1e-6)
            np.testing.assert_allclose(metal, 0.0)
        else:
            eta, k = np.array(METAL_ETA), np.array(METAL_K)
            f0 = ((eta - 1) ** 2 + k ** 2) / ((eta + 1) ** 2 + k ** 2)
            np.testing.assert_allclose(albedo, np.broadcast_to(f0, albedo.shape), atol=1e-5)
            np.testing.assert_allclose(rough, np.sqrt(METAL_ALPHA), atol=1e-6)
            np.testing.assert_allclose(metal, 1.0)
        # the wall faces the camera: its normal points along camera +z (RGB<->X), stored (n + 1) / 2
        np.testing.assert_allclose(gt.normal[at], np.broadcast_to([0.5, 0.5, 1.0], albedo.shape), atol=1e-5)


def test_glass_and_emitter_are_masked(evaluator):
    for target, name in (((3.25, 0.25, 0.65), "glass"), ((2.0, 2.5, 1.5), "light")):
        cam = look_at_camera((2.6, 1.0, 1.9), target, up=(0.0, 0.0, 1.0) if name == "light" else (0.0, 1.0, 0.0))
        frag, gt, names = ground_truth(evaluator, cam)
        at = frag.hit & (names[np.maximum(frag.object_id, 0)] == name)
        assert at.sum() > 20
        assert not gt.mask[at].any() and (gt.albedo[at] == 0).all()
        assert gt.mask[frag.hit & ~at].all()


def test_bitmap_albedo_is_the_texture_at_the_original_uv(evaluator):
    cam = look_at_camera((0.6, 1.6, 2.6), (1.8, 0.0, 1.6), width=48, height=36)
    frag, gt, names = ground_truth(evaluator, cam)
    at = frag.hit & (names[np.maximum(frag.object_id, 0)] == "floor")
    assert at.sum() > 200
    # Independently: the ray meets the plane y = 0; the OBJ's vt is (x, z) / 2; Mitsuba flips v on load;
    # the bitmap repeats, row 0 at v = 0, nearest filter, sRGB decoded.
    o, d = cam.pixel_rays()
    t = -o[:, 1] / d[:, 1]
    p = (o + t[:, None] * d).reshape(cam.height, cam.width, 3)[at]
    u, v = p[:, 0] / FLOOR_TILE, 1.0 - p[:, 2] / FLOOR_TILE
    h, w = TEXELS.shape[:2]
    x, y = np.mod(u, 1.0) * w, np.mod(v, 1.0) * h
    inner = (np.abs(x - np.round(x)) > 0.05) & (np.abs(y - np.round(y)) > 0.05)   # off texel borders
    expected = imageio.srgb_to_linear(TEXELS[y.astype(int), x.astype(int)] / 255.0)
    assert inner.sum() > 100 and len(np.unique(expected[inner], axis=0)) >= 4
    np.testing.assert_allclose(gt.albedo[at][inner], expected[inner], atol=2e-3)


def test_reconstruction_uvs(evaluator):
    source, mesh, decisions, _ = evaluator
    by_name = {d.name: d for d in decisions}
    assert by_name["floor"].reunwrapped and "tiled" in by_name["floor"].reason
    assert by_name["box"].reunwrapped                              # no texcoords in its OBJ
    assert not by_name["wall_x0"].reunwrapped
    assert mesh.uv.min() >= 0 and mesh.uv.max() <= 1
    np.testing.assert_array_equal(mesh.triangles(), np.concatenate([o.vertices[o.faces] for o in source.objects]))
    floor = mesh.uv[mesh.face_object == mesh.object_names.index("floor")]
    assert uv_checks.uv_overlap_fraction(floor) == 0.0


def test_uv_problems():
    tri = np.array([[[0, 0, 0], [1, 0, 0], [0, 1, 0]]] * 2, float)
    uv = np.array([[[0, 0], [1, 0], [0, 1]]] * 2, float)
    assert uv_checks.uv_problem(uv[:1], tri[:1]) is None
    assert "overlapping" in uv_checks.uv_problem(uv, tri)
    assert "tiled" in uv_checks.uv_problem(uv * 2, tri)
    assert "collapsed" in uv_checks.uv_problem(uv * 0, tri)


def test_unsupported_plugins_are_listed_together(tmp_path):
    extra = """
  <shape type="rectangle" id="bumpy"><bsdf type="bumpmap"><texture type="checkerboard"/><bsdf type="diffuse"/></bsdf></shape>
  <shape type="rectangle" id="blended"><bsdf type="blendbsdf"><float name="weight" value="0.5"/><bsdf type="diffuse"/>
    <bsdf type="plastic"/></bsdf></shape>"""
    xml = write_room(tmp_path, extra)
    with pytest.raises(InputError) as err:
        prepare.prepare_scene(xml, tmp_path / "out", num_views=1, width=32, height=24, spp=1, progress=False)
    message = str(err.value)
    assert "'bumpy'" in message and "bumpmap" in message and "'blended'" in message and "'blendbsdf'" in message
    assert len(err.value.problems) == 2
    assert not (tmp_path / "out").exists()


def test_input_errors(tmp_path, room_xml):
    def problems(xml, **kw):
        args = dict(num_views=1, width=32, height=24, spp=1)
        args.update(kw)
        with pytest.raises(InputError) as err:
            prepare.prepare_scene(xml, tmp_path / "out", progress=False, **args)
        return str(err.value)

    assert "scene file not found" in problems(tmp_path / "missing.xml")
    message = problems(room_xml, num_views=0, width=0)
    assert "--views" in message and "--width" in message
    not_scene = tmp_path / "bsdf.xml"
    not_scene.write_text('<bsdf version="3.0.0" type="diffuse"/>')
    assert "not a Mitsuba scene" in problems(not_scene)
    broken = tmp_path / "broken.xml"
    broken.write_text('<scene version="3.0.0"><shape type="rectangle">')
    assert "Mitsuba cannot load it" in problems(broken)
    empty = tmp_path / "empty.xml"
    empty.write_text('<scene version="3.0.0"/>')
    assert "no shapes" in problems(empty)
    folder = tmp_path / "notex"
    xml = write_room(folder)
    (folder / "tex.png").unlink()
    message = problems(xml)
    assert str(folder / "tex.png") in message and "file not found" in message


@pytest.mark.skipif(not STAIRCASE.is_file(), reason="staircase2 scene not present")
def test_staircase2_imports(tmp_path):
    summary = prepare.prepare_scene(STAIRCASE, tmp_path, num_views=2, width=48, height=32, spp=1, progress=False)
    scene = read_scene(tmp_path)
    assert len(scene.views) == 2 and scene.num_objects == 32
    objects = {o["name"]: o for o in summary["objects"]}
    assert objects["Glass"]["masked"] and objects["FloorTiles"]["albedo"] == "texture"
    assert {"FloorTiles", "Wall_0002", "SpotHolder_0001"} <= set(summary["reunwrapped"])
    assert objects["Metal"]["metallic"] == [1.0]
    assert summary["statistics"]["valid_fraction"] > 0.5


def test_analytic_shape_uvs_match_mitsuba():
    """Tessellated shapes: our UV of a surface point equals Mitsuba's own hit UV there."""
    from jaxdistill.datasets.mitsuba import bridge as mitsuba_bridge
    mitsuba_bridge.load_mitsuba()
    m = np.eye(4)
    angle = 0.7
    m[:3, :3] = np.array([[np.cos(angle), 0, np.sin(angle)], [0, 1, 0], [-np.sin(angle), 0, np.cos(angle)]]) * 1.7
    m[:3, 3] = [0.3, -0.2, 1.1]
    rng = np.random.default_rng(0)
    for kind in ("rectangle", "disk", "sphere", "cylinder"):
        shape = mi.load_dict({"type": kind, "to_world": mi.ScalarTransform4f(m.tolist())})
        vertices, faces, texcoords, _, uv_function = mitsuba_shapes._tessellate(kind, m)
        for _ in range(8):
            phi, r, z = rng.uniform(0.1, 6.2), rng.uniform(0.2, 0.9), rng.uniform(0.1, 0.9)
            if kind == "rectangle":
                origin, target = [r * 2 - 1, z * 2 - 1, 1.0], [r * 2 - 1, z * 2 - 1, 0.0]
            elif kind == "disk":
                origin, target = [r * np.cos(phi), r * np.sin(phi), 1.0], [r * np.cos(phi), r * np.sin(phi), 0.0]
            elif kind == "sphere":
                d = np.array([np.cos(phi) * np.sin(z * 3), np.sin(phi) * np.sin(z * 3), np.cos(z * 3)])
                origin, target = 2 * d, d
            else:
                origin, target = [2 * np.cos(phi), 2 * np.sin(phi), z], [np.cos(phi), np.sin(phi), z]
            o, t = mitsuba_shapes._transform_points(m, np.array([origin, target], float))
            si = shape.ray_intersect(mi.Ray3f(mi.Point3f(*o), mi.Vector3f(*((t - o) / np.linalg.norm(t - o)))))
            assert si.is_valid()
            p = np.array(si.p, float)[None]
            if uv_function is not None:
                ours = uv_function(p)[0]
            else:  # rectangle: barycentric interpolation of its corner texcoords is exact
                local = mitsuba_shapes._transform_points(np.linalg.inv(m), p)[0]
                ours = (local[:2] + 1) / 2
                local_vertices = mitsuba_shapes._transform_points(np.linalg.inv(m), vertices)
                np.testing.assert_allclose(texcoords, (local_vertices[:, :2] + 1) / 2, atol=1e-12)
            np.testing.assert_allclose(ours, np.array(si.uv, float), atol=1e-4)


# ----------------------------------------------------------------------------- irradiance


def write_xml(folder: Path, shapes: str) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / "scene.xml"
    path.write_text(f'<scene version="3.0.0"><integrator type="path"/>{shapes}</scene>')
    return path


def test_irradiance_under_a_disk_light_is_the_analytic_formula(tmp_path, monkeypatch):
    """A black floor under a downward disk emitter (radius r, height h, radiance L): E / pi at a
    floor point at distance rho from the axis is L/2 (1 - (h^2 + rho^2 - r^2) / sqrt((h^2 + rho^2 +
    r^2)^2 - 4 r^2 rho^2)) (the configuration factor of a parallel disk)."""
    r, h, radiance = 0.5, 1.0, np.array([2.0, 1.0, 0.5])
    xml = write_xml(tmp_path, f"""
  <shape type="rectangle"><transform name="to_world"><scale value="5"/></transform>
    <bsdf type="diffuse">{rgb("reflectance", (0, 0, 0))}</bsdf></shape>
  <shape type="disk"><transform name="to_world"><scale value="{r}"/><rotate x="1" angle="180"/>
    <translate z="{h}"/></transform><emitter type="area">{rgb("radiance", radiance)}</emitter></shape>""")
    cam = look_at_camera((0.0, 0.0, 0.6), (0.0, 0.0, 0.0), up=(0.0, 1.0, 0.0), width=24, height=18)
    before = mb.load_mitsuba().variant()
    image = render_irradiance(xml, [cam], spp=32, seed=3)[0].reshape(-1, 3)       # one wavefront of 32 samples
    assert mi.variant() == before                     # the llvm variant is left again
    # wavefronts of 5 samples: 6 of them and one of the 2 left (each pixel's samples summed across them)
    monkeypatch.setattr(gt_lib, "IRRADIANCE_LANES", 5 * cam.height * cam.width + 3)
    split = render_irradiance(xml, [cam], spp=32, seed=3)[0].reshape(-1, 3)
    o, d = cam.pixel_rays()
    rho = np.hypot(*(o + d * (-o[:, 2:] / d[:, 2:]))[:, :2].T)
    expected = 0.5 * (1 - (h ** 2 + rho ** 2 - r ** 2) / np.sqrt((h ** 2 + rho ** 2 + r ** 2) ** 2
                                                                  - 4 * r ** 2 * rho ** 2))
    expected = expected[:, None] * radiance
    for estimate in (image, split):
        np.testing.assert_allclose(estimate.mean(0), expected.mean(0), rtol=0.02)     # unbiased
        assert np.median(np.abs(estimate - expected) / expected) < 0.1                  # per pixel, 32 samples
    assert not np.array_equal(image, split)            # other seeds: other samples, the same estimate


def test_irradiance_in_a_closed_glowing_box_counts_every_bounce(tmp_path):
    """Inside a closed box whose walls emit L and reflect rho diffusely, every wall's radiance is
    L / (1 - rho), and so is E / pi everywhere: interreflections of the original materials count."""
    xml = write_xml(tmp_path, f"""
  <shape type="cube"><boolean name="flip_normals" value="true"/>
    <bsdf type="diffuse">{rgb("reflectance", (0.5, 0.25, 0.0))}</bsdf>
    <emitter type="area">{rgb("radiance", (1, 1, 1))}</emitter></shape>""")
    cam = look_at_camera((0.1, 0.2, 0.0), (1.0, 0.3, 0.2), up=(0.0, 1.0, 0.0), width=16, height=12)
    image = render_irradiance(xml, [cam], spp=32, seed=0)[0]
    np.testing.assert_allclose(image.reshape(-1, 3).mean(0), [2.0, 4.0 / 3.0, 1.0], rtol=0.02)
    # the same scene given as text (an upgraded Mitsuba 0.x file), with max_depth 2: direct light only
    text = xml.read_text().replace('<integrator type="path"/>',
                                   '<integrator type="path"><integer name="max_depth" value="2"/></integrator>')
    direct = render_irradiance(tmp_path / "absent.xml", [cam], spp=32, seed=0, xml_text=text)[0]
    np.testing.assert_allclose(direct.reshape(-1, 3).mean(0), 1.0, rtol=0.02)


def test_imported_irradiance_times_albedo_is_the_photo_on_diffuse_surfaces(tmp_path):
    """Mitsuba's own path-traced photo is albedo x E / pi wherever the surface is Lambertian: the
    room's diffuse walls and floor (not the OBJ box: Mitsuba smooths its vertex normals)."""
    xml = write_room(tmp_path / "room", light_down=True, max_depth=3)
    out = tmp_path / "out"
    summary = prepare.prepare_scene(xml, out, num_views=2, width=32, height=24, spp=64, seed=2, progress=False)
    scene = read_scene(out)
    frags = fr.compute_fragments(scene.mesh, [v.camera for v in scene.views], cache_dir=False, progress=False)
    flat = [i for i, name in enumerate(scene.mesh.object_names) if name in ("floor", "wall_x0", "wall_z1")]
    photo, product = [], []
    for view, frag in zip(scene.views, frags):
        gt = {m: imageio.read_image(p) for m, p in view.ground_truth.items()}
        mask = imageio.read_image(view.mask, linear=False)[..., 0] > 0.5
        target = imageio.read_image(view.targets["irradiance"])
        np.testing.assert_allclose(target, np.clip(gt["irradiance"] * summary["irradiance_target_scale"], 0, 1),
                                   rtol=1e-3, atol=1e-3)                            # half-float EXR
        assert (gt["irradiance"][~mask] == 0).all()
        diffuse = mask & np.isin(frag.object_id, flat) & (gt["roughness"][..., 0] == 1.0)
        photo.append(imageio.read_image(view.photo)[diffuse])
        product.append(gt["albedo"][diffuse] * gt["irradiance"][diffuse])
    photo, product = np.concatenate(photo), np.concatenate(product)
    assert len(photo) > 300
    print("photo / (albedo x irradiance):", photo.sum(0) / product.sum(0))
    np.testing.assert_allclose(photo.sum(0) / product.sum(0), 1.0, rtol=0.05)     # both Monte Carlo estimates


# ----------------------------------------------------------------------------- the README's commands


def run_command(command: list[str], cwd: Path, cache: Path | None = None, timeout: float = 300) -> str:
    """Runs a README command from the repository root; its output, or a failure that shows it."""
    env = {**os.environ, "PYTHONPATH": str(REPO), "JAX_PLATFORMS": "cpu"}
    if cache is not None:
        env["JAXDISTILL_CACHE"] = str(cache)
    env.pop("JAXDISTILL_RGBX_DIR", None)
    env["PYTHONFAULTHANDLER"] = "1"          # SIGABRT prints every thread's Python stack (a stalled command, below)
    child = subprocess.Popen([sys.executable, *command], cwd=cwd, env=env, stdout=subprocess.PIPE,
                             stderr=subprocess.PIPE, text=True)
    try:
        stdout, stderr = child.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:       # say where it stalled, not only that it did
        child.send_signal(signal.SIGABRT)
        try:
            stdout, stderr = child.communicate(timeout=60)
        except subprocess.TimeoutExpired:
            child.kill()
            stdout, stderr = child.communicate()
        pytest.fail(f"{' '.join(command)} ran past {timeout} s; its threads' stacks at SIGABRT:\n{stdout}\n{stderr}")
    assert child.returncode == 0, f"{' '.join(command)} exited {child.returncode}:\n{stdout}\n{stderr}"
    return stdout + stderr


@pytest.mark.parametrize("source", ["room", "staircase2"])
def test_prepared_scene_runs_in_the_main_job_with_evaluation(source, tmp_path, monkeypatch):
    """prepare_scene.py, then the main job with the default five-map config for two steps, as the
    README gives them: targets, ground truth and masks for all five maps, metrics for all five, a
    PSNR curve from --eval_every on per-view ground truth. The synthetic room runs the README's
    default prior (the shipped model); staircase2, the real scene, runs the `views` prior: what it
    adds is a real scene's import scored end to end, and the prior does not depend on the scene
    (the room's run proves it on a prepared scene), while its networks and estimates are most of a
    run's time at this size."""
    if source == "staircase2" and not STAIRCASE.is_file():
        pytest.skip(f"staircase2 not found ({STAIRCASE}); set JAXDISTILL_STAIRCASE2")
    xml = STAIRCASE if source == "staircase2" else write_room(tmp_path / "room", light_down=True)
    scene_dir, run_dir = tmp_path / "scene", tmp_path / "run"
    run_command(["scripts/prepare_scene.py", f"--mitsuba={xml}", f"--out={scene_dir}", "--views=3", "--width=48",
                 "--height=32", "--spp=4", "--quiet"], REPO)
    assert not (scene_dir / "gt.json").exists()
    scene = read_scene(scene_dir)
    maps = {"albedo", "normal", "roughness", "metallic", "irradiance"}
    assert all(set(v.targets) == maps == set(v.ground_truth) and v.mask is not None for v in scene.views)
    # the photos carry Hypersim's exposure over the valid pixels (as the dataset loaders give it), written out:
    # 90th percentile of 0.3 R + 0.59 G + 0.11 B to 0.8 after a 1/2.2 gamma
    brightness = np.concatenate([(imageio.read_image(v.photo)[..., :3] @ np.array([0.3, 0.59, 0.11]))[
        imageio.read_image(v.mask, linear=False)[..., 0] > 0.5] for v in scene.views])
    stops = np.log2(0.8 ** 2.2 / np.percentile(brightness, 90))
    assert all(abs(v.exposure - stops) < 0.01 for v in scene.views), ([v.exposure for v in scene.views], stops)
    prior = ["--prior=views", "--reuse_steps=1"] if source == "staircase2" else []
    log = run_command(["-m", "jaxdistill.main", "--flagfile=configs/bedroom.cfg", f"--scene={scene_dir}",
                       f"--out_dir={run_dir}", "--steps=2", "--views_per_step=3", "--eval_every=1",
                       "--max_texture_size=64", "--estimate_steps=4", *prior], REPO, cache=tmp_path / "cache")
    doc = json.loads((run_dir / "metrics.json").read_text())
    for key in ("albedo_psnr", "albedo_ssim", "normal_angular_deg", "roughness_mse", "metallic_mse",
                "irradiance_si_psnr"):
        assert np.isfinite(doc["ours"][key]), (key, log)
    assert doc["history"]["eval_step"] == [1, 2] and np.isfinite(doc["history"]["albedo_psnr"]).all()
    # the README's command: SDS with the default prior, the shipped model unless weights are given
    if source == "room":
        assert doc["prior"]["kind"] == "rgbx" and doc["prior"]["model"]["source"] == "shipped", doc["prior"]
        assert doc["baseline_source"].startswith("the model's own per-view estimates (4 DDIM steps")
    else:
        assert doc["prior"]["kind"] == "views", doc["prior"]
        assert doc["baseline_source"] == "the scene's per-view target images", doc["baseline_source"]
    # Independently: the albedo PSNR over each view's mask from the written renders (8-bit sRGB PNGs)
    psnrs = []
    for view in scene.views:
        mask = imageio.read_image(view.mask, linear=False)[..., 0] > 0.5
        ours = imageio.read_image(run_dir / "renders" / "albedo" / f"{view.name}.png", linear=False)[mask]
        gt = imageio.linear_to_srgb(np.clip(imageio.read_image(view.ground_truth["albedo"]), 0, 1))[mask]
        psnrs.append(10 * np.log10(1.0 / np.mean((ours - gt) ** 2)))
    assert abs(np.mean(psnrs) - doc["ours"]["albedo_psnr"]) < 0.02 * doc["ours"]["albedo_psnr"]   # 8-bit PNGs


def test_irradiance_without_llvm_is_a_clear_error_before_any_compute(tmp_path, monkeypatch, room_xml):
    from jaxdistill.datasets.mitsuba import bridge as mitsuba_bridge
    real = mitsuba_bridge.load_mitsuba

    def no_llvm(variant=mitsuba_bridge.VARIANT):
        if variant != mitsuba_bridge.VARIANT:
            raise ImportError(f"variant {variant} is not available: libLLVM not found")
        return real(variant)

    monkeypatch.setattr(mb, "load_mitsuba", no_llvm)
    cam = look_at_camera((0.0, 0.0, 1.0), (0.0, 0.0, 0.0), width=8, height=6)
    with pytest.raises(InputError, match="llvm_ad_rgb variant, which cannot start here .*install LLVM"):
        render_irradiance(write_xml(tmp_path, ""), [cam], spp=1)
    monkeypatch.setattr(prepare, "load_source", lambda *a, **k: pytest.fail("the import started before the check"))
    with pytest.raises(InputError, match="install LLVM"):
        prepare.prepare_scene(room_xml, tmp_path / "out", num_views=1, width=16, height=12, spp=1, progress=False)
    assert not (tmp_path / "out").exists()


def test_reimport_removes_the_gt_json_an_earlier_import_wrote(room_xml, tmp_path):
    """Earlier imports wrote their metadata as gt.json (no textures), which evaluation refuses; a
    new import into the same folder removes it, but never a gt.json with GT textures."""
    old, textured = tmp_path / "old", tmp_path / "textured"
    for folder, doc in ((old, {"format": "jaxdistill-gt", "version": 1, "source": {"mitsuba": str(room_xml)}}),
                        (textured, {"format": "jaxdistill-gt", "version": 1, "source": {"mitsuba": str(room_xml)},
                                    "textures": {"albedo": {}}})):
        folder.mkdir()
        (folder / "gt.json").write_text(json.dumps(doc))
        prepare.prepare_scene(room_xml, folder, num_views=1, width=16, height=12, spp=1, progress=False)
    assert not (old / "gt.json").exists() and (textured / "gt.json").is_file()
