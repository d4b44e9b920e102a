"""scene.usdc (export/usd.py): a tiny run's stage loaded back with pxr (meshes, UsdPreviewSurface
materials and their texture files, cameras against the views' K and c2w), the projection of an
off-centre camera, and the run without usd-core (one log line, no crash)."""

from __future__ import annotations

import ast
import logging
import math
import threading
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import PIL.Image
import pytest
import trimesh

from jaxdistill import pipeline
from jaxdistill.engine import config as config_lib
from jaxdistill.engine.config import DistillConfig
from jaxdistill.evaluate.summary import summary_table
from jaxdistill.export import outputs, usd
from jaxdistill.scene.model import read_scene
from conftest import look_at_camera
from test_export import quad_mesh
from tiny_scene import write_tiny_scene


@pytest.fixture(autouse=True)
def fragment_cache(tmp_path_factory, monkeypatch):
    monkeypatch.setenv("JAXDISTILL_CACHE", str(tmp_path_factory.getbasetemp() / "fragment_cache"))


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory):
    """(scene.json, out_dir) of a short views-prior run on the tiny scene, its folder then moved."""
    pytest.importorskip("pxr", reason="usd-core is not installed (pip install -e \".[usd]\")")
    root = tmp_path_factory.mktemp("tiny_usd")
    scene = write_tiny_scene(root / "scene")
    config = config_lib.validate(DistillConfig(scene=str(scene), out_dir=str(root / "run"), steps=2, views_per_step=2,
                                               prior="views", log_every=1, eval_every=0, renders=False,
                                               contact_views=0))
    with pytest.MonkeyPatch.context() as patch:
        patch.setenv("JAXDISTILL_CACHE", str(tmp_path_factory.getbasetemp() / "fragment_cache"))
        pipeline.run(config, progress=False)
    moved = root / "moved"
    (root / "run").rename(moved)            # relative texture paths: the folder moves whole
    return scene, moved


def world_matrix(prim) -> np.ndarray:
    """The prim's local-to-world transform as a column-vector (4, 4) matrix."""
    from pxr import Usd, UsdGeom

    return np.array(UsdGeom.Xformable(prim).ComputeLocalToWorldTransform(Usd.TimeCode.Default())).T


def test_tiny_run_writes_a_stage_with_meshes_materials_and_cameras(tiny_run):
    from pxr import Usd, UsdGeom, UsdShade

    scene_file, out = tiny_run
    scene = read_scene(scene_file)
    mesh = scene.mesh
    stage = Usd.Stage.Open(str(out / "scene.usdc"))
    glb = trimesh.load(out / "scene.glb", force="scene")
    assert "scene.usdc (the same in USD)" in summary_table({}, out)           # the run's end summary names it
    assert UsdGeom.GetStageUpAxis(stage) == UsdGeom.Tokens.y and UsdGeom.GetStageMetersPerUnit(stage) == 1.0
    assert stage.GetDefaultPrim().GetPath() == "/World"

    meshes = {p.GetName(): UsdGeom.Mesh(p) for p in stage.Traverse() if p.IsA(UsdGeom.Mesh)}
    assert sorted(meshes) == sorted(mesh.object_names)
    for object_id, name in enumerate(mesh.object_names):
        face_ids = np.nonzero(mesh.face_object == object_id)[0]
        geom = meshes[name]
        points = np.array(geom.GetPointsAttr().Get())
        indices = np.array(geom.GetFaceVertexIndicesAttr().Get()).reshape(-1, 3)
        assert len(points) == len(np.unique(mesh.faces[face_ids])) and len(indices) == len(face_ids)
        assert set(geom.GetFaceVertexCountsAttr().Get()) == {3}
        np.testing.assert_allclose(points[indices], mesh.vertices[mesh.faces[face_ids]], atol=1e-6)
        st = UsdGeom.PrimvarsAPI(geom).GetPrimvar("st")
        assert st.GetInterpolation() == UsdGeom.Tokens.faceVarying
        np.testing.assert_allclose(np.array(st.Get()).reshape(-1, 3, 2), mesh.uv[face_ids], atol=1e-6)

        material, _ = UsdShade.MaterialBindingAPI(geom.GetPrim()).ComputeBoundMaterial()
        assert material, f"{name}: no material bound"
        surface = material.ComputeSurfaceSource()[0]
        assert surface.GetIdAttr().Get() == "UsdPreviewSurface"
        spaces = {"diffuseColor": "sRGB", "roughness": "raw", "metallic": "raw", "normal": "raw"}
        for input_name, space in spaces.items():
            source = surface.GetInput(input_name).GetConnectedSources()[0]
            assert source, f"{name}: {input_name} reads no texture"
            texture = UsdShade.Shader(source[0].source.GetPrim())
            assert texture.GetIdAttr().Get() == "UsdUVTexture"
            asset = texture.GetInput("file").Get()
            assert asset.path.startswith("./"), asset.path               # relative: the folder moves
            assert Path(asset.resolvedPath).is_file() and Path(asset.resolvedPath).is_relative_to(out), asset
            assert texture.GetInput("sourceColorSpace").Get() == space
            reader = UsdShade.Shader(texture.GetInput("st").GetConnectedSources()[0][0].source.GetPrim())
            assert reader.GetIdAttr().Get() == "UsdPrimvarReader_float2" and reader.GetInput("varname").Get() == "st"
            if input_name == "normal":
                assert tuple(texture.GetInput("scale").Get()) == (2, 2, 2, 1)
                assert tuple(texture.GetInput("bias").Get()) == (-1, -1, -1, 0)
                tangent_space = np.asarray(glb.geometry[name].visual.material.normalTexture.convert("RGB"))
                np.testing.assert_array_equal(np.asarray(PIL.Image.open(asset.resolvedPath).convert("RGB")),
                                              tangent_space)          # scene.glb's normal map, not maps/normal

    cams = {p.GetName(): p for p in stage.Traverse() if p.IsA(UsdGeom.Camera)}
    assert sorted(cams) == sorted(v.name for v in scene.views)
    for view in scene.views:
        prim, camera = cams[view.name], view.camera
        m = world_matrix(prim)
        np.testing.assert_allclose(m[:3, 3], camera.c2w[:3, 3], atol=1e-6)
        np.testing.assert_allclose(m[:3, :3] @ [0.0, 0.0, -1.0], camera.c2w[:3, 2], atol=1e-6)   # optical axis
        np.testing.assert_allclose(m[:3, :3] @ [0.0, 1.0, 0.0], -camera.c2w[:3, 1], atol=1e-6)   # image up
        gf = UsdGeom.Camera(prim).GetCamera(Usd.TimeCode.Default())
        fx = camera.K[0, 0]
        expected = math.degrees(2 * math.atan(camera.width / (2 * fx)))                     # pinhole formula
        assert gf.GetFieldOfView(gf.FOVHorizontal) == pytest.approx(expected, rel=1e-5)


def test_the_stage_projects_as_k_does_off_centre_and_with_non_square_pixels(tmp_path):
    pytest.importorskip("pxr", reason="usd-core is not installed (pip install -e \".[usd]\")")
    from pxr import Gf, Usd, UsdGeom

    camera = look_at_camera((0.4, 0.6, 3.0), (0.5, 0.5, 0.0), width=64, height=48, fx=70.0, fy=80.0, cx=25.0, cy=30.0)
    path = usd.write_usd(tmp_path / "scene.usda", quad_mesh(), [0], {}, [("cam 1", camera)])
    stage = Usd.Stage.Open(str(path))
    prim = stage.GetPrimAtPath("/World/Cameras/cam_1")
    assert prim.GetCustomDataByKey("jaxdistill:view") == "cam 1"
    frustum = UsdGeom.Camera(prim).GetCamera(Usd.TimeCode.Default()).frustum
    to_ndc = frustum.ComputeViewMatrix() * frustum.ComputeProjectionMatrix()
    points = np.random.default_rng(0).uniform([0, 0, -0.5], [1, 1, 0.5], (20, 3))
    expected, depth = camera.project(points)
    assert (depth > 0).all()
    ndc = np.array([to_ndc.Transform(Gf.Vec3d(*p)) for p in points])
    pixels = np.stack([(ndc[:, 0] + 1) / 2 * camera.width, (1 - ndc[:, 1]) / 2 * camera.height], axis=-1)
    np.testing.assert_allclose(pixels, expected, atol=1e-4)
    surface = stage.GetPrimAtPath("/World/Materials/quad/PreviewSurface")       # no textures: constants
    assert surface.GetAttribute("inputs:roughness").Get() == 1.0 and surface.GetAttribute("inputs:metallic").Get() == 0


def test_write_usd_refuses_what_it_cannot_write(tmp_path):
    pytest.importorskip("pxr", reason="usd-core is not installed (pip install -e \".[usd]\")")
    with pytest.raises(ValueError, match="use a .usdc or .usda file name"):
        usd.write_usd(tmp_path / "scene.glb", quad_mesh(), [0], {})
    with pytest.raises(ValueError, match="no UsdPreviewSurface input for irradiance"):
        usd.write_usd(tmp_path / "scene.usdc", quad_mesh(), [0], {"irradiance": [tmp_path / "i.png"]})
    with pytest.raises(ValueError, match=r"textures\['albedo'\]: 2 files for 1 pages"):
        usd.write_usd(tmp_path / "scene.usdc", quad_mesh(), [0], {"albedo": [tmp_path / "a.png"] * 2})


def test_without_usd_core_the_run_says_how_to_get_it_and_goes_on(tmp_path, monkeypatch, caplog):
    monkeypatch.setattr(usd, "usd_available", lambda: False)
    with caplog.at_level(logging.WARNING):
        written = outputs.write_usd_scene(tmp_path, quad_mesh(), [0], {}, [])
    assert written == [] and not (tmp_path / "scene.usdc").exists()
    lines = [r.getMessage() for r in caplog.records if "scene.usdc" in r.getMessage()]
    assert len(lines) == 1 and 'pip install -e ".[usd]"' in lines[0], lines


def test_blender_imports_the_stage(tiny_run, tmp_path):
    bpy = pytest.importorskip("bpy", reason="Blender's bpy module is not installed")
    _, out = tiny_run
    bpy.ops.wm.read_factory_settings(use_empty=True)
    bpy.ops.wm.usd_import(filepath=str(out / "scene.usdc"))
    names = {o.name for o in bpy.data.objects}
    assert {o.type for o in bpy.data.objects} >= {"MESH", "CAMERA"}, names


def test_pxr_modules_names_every_pxr_module_the_writer_imports():
    """`usd_available` loads `PXR_MODULES` up front (see the next test): every pxr module usd.py imports
    anywhere must be among them, or its first import could still happen on the outputs' thread."""
    tree = ast.parse(Path(usd.__file__).read_text())
    imported = {alias.name for node in ast.walk(tree) if isinstance(node, ast.ImportFrom) and node.module == "pxr"
                for alias in node.names}
    imported |= {alias.name.split(".")[1] for node in ast.walk(tree) if isinstance(node, ast.Import)
                 for alias in node.names if alias.name.startswith("pxr.")}
    assert imported and imported <= set(usd.PXR_MODULES), imported - set(usd.PXR_MODULES)


def test_the_outputs_load_pxr_on_the_calling_thread_before_they_start_their_thread(tmp_path, monkeypatch):
    """pxr's first import on the outputs' thread, while the calling thread imported matplotlib for the
    loss plot, deadlocked a run (both threads in dlopen: pxr's registries waiting for the GIL inside
    the loader's lock). `write_outputs` loads pxr on the calling thread before it starts that thread."""
    events = []

    class Pool(ThreadPoolExecutor):
        def __init__(self, *args, **kwargs):
            events.append(("thread started", threading.current_thread()))
            super().__init__(*args, **kwargs)

    class Stop(Exception):
        pass

    def stop(*args):
        raise Stop

    monkeypatch.setattr(usd, "usd_available", lambda: events.append(("pxr", threading.current_thread())) or True)
    monkeypatch.setattr(outputs, "ThreadPoolExecutor", Pool)
    monkeypatch.setattr(outputs, "map_files_beside", lambda problem: True)
    monkeypatch.setattr(outputs, "write_map_files", lambda *args: [])
    monkeypatch.setattr(outputs, "_main_line", stop)            # the outputs' own line stops at once
    with pytest.raises(Stop):
        outputs.write_outputs(DistillConfig(scene="unused", out_dir=str(tmp_path)), None, None, {}, None, None, None)
    assert events[:2] == [("pxr", threading.current_thread()), ("thread started", threading.current_thread())], events
