"""The textured USD stage (scene.usdc): the mesh per object, UsdPreviewSurface materials reading the
run's texture files, and the views as cameras. Needs usd-core (`pip install -e ".[usd]"`).
"""

from __future__ import annotations

import importlib
import os
import re
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np

from jaxdistill.export.gltf import ZNEAR_FRACTION, mesh_diagonal
from jaxdistill.export.pages import page_names
from jaxdistill.export.tangents import vertex_frames
from jaxdistill.render.charts import check_mesh_pages
from jaxdistill.scene.cameras import Camera, to_opengl
from jaxdistill.scene.model import Mesh

USD_INSTALL = 'pip install -e ".[usd]"'
FILM_WIDTH = 36.0    # horizontalAperture of every camera (a full-frame sensor's width in mm); focalLength scales with it
ZFAR_FACTOR = 100.0  # a camera's far clip, in bounding-box diagonals
# UsdPreviewSurface input: (texture output, input type name, the texture's colour space)
SURFACE_INPUTS = {"albedo": ("diffuseColor", "rgb", "Color3f", "sRGB"),
                  "roughness": ("roughness", "r", "Float", "raw"),
                  "metallic": ("metallic", "r", "Float", "raw"),
                  "normal": ("normal", "rgb", "Normal3f", "raw")}


PXR_MODULES = ("Gf", "Sdf", "Usd", "UsdGeom", "UsdShade", "Vt")   # every pxr module this file imports


def usd_available() -> bool:
    """Whether usd-core's `pxr` can be imported; imports the modules this file's writer uses.

    Call it on the thread that starts other threads, before they may write USD: a pxr module's first
    import runs its C++ registries inside the dynamic loader's lock and there waits for the GIL
    (`TfPyLock`), so if it happens on one thread while another loads any extension module (seen:
    matplotlib's, for the loss plot), each waits on the other for ever. Once loaded, they are not
    loaded again."""
    try:
        for name in PXR_MODULES:
            importlib.import_module(f"pxr.{name}")
    except ImportError:
        return False
    return True


def prim_names(names: Sequence[str]) -> list[str]:
    """Valid, unique USD prim names for `names` (characters outside [A-Za-z0-9_] become '_', a
    leading digit gets '_' before it, a repeat gets `_<index>` appended)."""
    out, used = [], set()
    for i, name in enumerate(names):
        name = re.sub(r"[^A-Za-z0-9_]", "_", str(name)) or "_"
        name = "_" + name if name[0].isdigit() else name
        if name in used:
            name = f"{name}_{i}"
        used.add(name)
        out.append(name)
    return out


def camera_film(camera: Camera) -> dict[str, float]:
    """UsdGeom.Camera's lens and film of an OpenCV camera, in the units of a FILM_WIDTH-wide film.

    horizontalAperture / focalLength = W / fx and verticalAperture / focalLength = H / fy, so
    the fields of view are K's; the aperture offsets move the film window so the optical axis
    meets the image at (cx, cy): horizontal (W/2 - cx), vertical (cy - H/2) pixels (USD's film y
    is up, image rows go down), in film units."""
    K = np.asarray(camera.K, np.float64)
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    unit = FILM_WIDTH / camera.width            # film units per pixel, horizontally
    v_unit = unit * fx / fy                     # and vertically (non-square pixels)
    return {"focalLength": fx * unit, "horizontalAperture": camera.width * unit,
            "verticalAperture": camera.height * v_unit, "horizontalApertureOffset": (camera.width / 2.0 - cx) * unit,
            "verticalApertureOffset": (cy - camera.height / 2.0) * v_unit}


def _define_mesh(stage, prim_path: str, mesh: Mesh, face_ids: np.ndarray):
    """One object's UsdGeom.Mesh: its vertices (welded, as the scene has them), faces, the `st`
    primvar per face corner (faceVarying) and the flat normals the normal maps are encoded against."""
    from pxr import Sdf, UsdGeom, Vt

    corners = mesh.faces[face_ids]
    used, local = np.unique(corners, return_inverse=True)
    geom = UsdGeom.Mesh.Define(stage, prim_path)
    geom.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
    geom.CreateOrientationAttr(UsdGeom.Tokens.rightHanded)
    points = np.asarray(mesh.vertices[used], np.float32)
    geom.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(points))
    geom.CreateExtentAttr(Vt.Vec3fArray.FromNumpy(np.stack([points.min(axis=0), points.max(axis=0)])))
    geom.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(np.full(len(face_ids), 3, np.int32)))
    geom.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(local.reshape(-1).astype(np.int32)))
    normals, _ = vertex_frames(mesh, face_ids)
    geom.CreateNormalsAttr(Vt.Vec3fArray.FromNumpy(normals))
    geom.SetNormalsInterpolation(UsdGeom.Tokens.faceVarying)
    st = UsdGeom.PrimvarsAPI(geom).CreatePrimvar("st", Sdf.ValueTypeNames.TexCoord2fArray,
                                                 UsdGeom.Tokens.faceVarying)
    st.Set(Vt.Vec2fArray.FromNumpy(np.asarray(mesh.uv[face_ids], np.float32).reshape(-1, 2)))
    return geom


def _define_material(stage, prim_path: str, textures: Mapping[str, str]):
    """A UsdShade.Material with a UsdPreviewSurface whose inputs read UsdUVTexture nodes of
    `textures` ({map: asset path}) through one UsdPrimvarReader_float2 of `st`. A missing
    roughness is 1 and a missing metallic 0 (as scene.glb has them)."""
    from pxr import Gf, Sdf, UsdShade

    material = UsdShade.Material.Define(stage, prim_path)
    surface = UsdShade.Shader.Define(stage, f"{prim_path}/PreviewSurface")
    surface.CreateIdAttr("UsdPreviewSurface")
    surface.CreateInput("useSpecularWorkflow", Sdf.ValueTypeNames.Int).Set(0)
    material.CreateSurfaceOutput().ConnectToSource(surface.ConnectableAPI(), "surface")
    if "roughness" not in textures:
        surface.CreateInput("roughness", Sdf.ValueTypeNames.Float).Set(1.0)
    if "metallic" not in textures:
        surface.CreateInput("metallic", Sdf.ValueTypeNames.Float).Set(0.0)
    if not textures:
        return material
    reader = UsdShade.Shader.Define(stage, f"{prim_path}/stReader")
    reader.CreateIdAttr("UsdPrimvarReader_float2")
    reader.CreateInput("varname", Sdf.ValueTypeNames.String).Set("st")
    st = reader.CreateOutput("result", Sdf.ValueTypeNames.Float2)
    for name, asset in textures.items():
        input_name, output, kind, space = SURFACE_INPUTS[name]
        texture = UsdShade.Shader.Define(stage, f"{prim_path}/{name}Texture")
        texture.CreateIdAttr("UsdUVTexture")
        texture.CreateInput("file", Sdf.ValueTypeNames.Asset).Set(Sdf.AssetPath(asset))
        texture.CreateInput("sourceColorSpace", Sdf.ValueTypeNames.Token).Set(space)
        texture.CreateInput("st", Sdf.ValueTypeNames.Float2).ConnectToSource(st)
        for wrap in ("wrapS", "wrapT"):
            texture.CreateInput(wrap, Sdf.ValueTypeNames.Token).Set("clamp")
        if name == "normal":     # 8-bit (n + 1) / 2 back to [-1, 1]
            texture.CreateInput("scale", Sdf.ValueTypeNames.Float4).Set(Gf.Vec4f(2.0, 2.0, 2.0, 1.0))
            texture.CreateInput("bias", Sdf.ValueTypeNames.Float4).Set(Gf.Vec4f(-1.0, -1.0, -1.0, 0.0))
        value_type = getattr(Sdf.ValueTypeNames, kind)
        source = texture.CreateOutput(output, Sdf.ValueTypeNames.Float3 if output == "rgb" else Sdf.ValueTypeNames.Float)
        surface.CreateInput(input_name, value_type).ConnectToSource(source)
    return material


def _define_camera(stage, prim_path: str, camera: Camera, clipping: tuple[float, float]):
    """A UsdGeom.Camera of an OpenCV camera: transform `to_opengl` (USD cameras look down -Z with
    +Y up, as OpenGL's), film from `camera_film`, K and the image size kept in customData."""
    from pxr import Gf, UsdGeom

    geom = UsdGeom.Camera.Define(stage, prim_path)
    geom.AddTransformOp().Set(Gf.Matrix4d(to_opengl(camera).T.tolist()))   # USD: row vectors, translation in row 3
    geom.CreateProjectionAttr(UsdGeom.Tokens.perspective)
    for key, value in camera_film(camera).items():
        geom.GetPrim().GetAttribute(key).Set(float(value))
    geom.CreateClippingRangeAttr(Gf.Vec2f(*clipping))
    geom.GetPrim().SetCustomDataByKey("jaxdistill:K", str(np.asarray(camera.K).tolist()))
    geom.GetPrim().SetCustomDataByKey("jaxdistill:size", f"{camera.width}x{camera.height}")
    return geom


def write_usd(path, mesh: Mesh, object_page: Sequence[int], textures: Mapping[str, Sequence[Path]],
              cameras: Sequence[tuple[str, Camera]] = ()) -> Path:
    """Writes a USD stage (.usdc crate, .usda text) of the textured mesh and the cameras; returns the path.

    /World (the default prim; upAxis Y, metersPerUnit 1, as scene.glb) holds /World/Geometry/<object>,
    one UsdGeom.Mesh per object (objects without faces left out), bound to
    /World/Materials/<page>, one UsdShade.Material per texture page (`page_names`: per object
    with the "pages" layout) whose UsdPreviewSurface reads `textures` ({map: one file per page}:
    albedo 8-bit sRGB, roughness and metallic grey, normal TANGENT-space (n + 1) / 2 in
    `vertex_frames`' frames, which the mesh's normals are). Texture paths are relative to the
    stage's folder, so the folder moves whole. Each (name, Camera) becomes /World/Cameras/<name>."""
    from pxr import Usd, UsdGeom, UsdShade

    path = Path(path)
    if path.suffix.lower() not in (".usdc", ".usda", ".usd"):
        raise ValueError(f"{path}: write_usd writes a USD layer; use a .usdc or .usda file name")
    num_pages = len(page_names(mesh.object_names, object_page))
    check_mesh_pages(mesh, object_page, num_pages)
    unknown = sorted(set(textures) - set(SURFACE_INPUTS))
    if unknown:
        raise ValueError(f"textures: no UsdPreviewSurface input for {', '.join(unknown)}")
    for name, files in textures.items():
        if len(files) != num_pages:
            raise ValueError(f"textures[{name!r}]: {len(files)} files for {num_pages} pages")
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(".tmp_" + path.name)
    stage = Usd.Stage.CreateNew(str(tmp))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    stage.SetDefaultPrim(UsdGeom.Xform.Define(stage, "/World").GetPrim())
    for group in ("Geometry", "Materials", "Cameras"):
        UsdGeom.Scope.Define(stage, f"/World/{group}")

    def asset(file) -> str:
        return "./" + Path(os.path.relpath(Path(file).absolute(), path.parent.absolute())).as_posix()

    materials = [_define_material(stage, f"/World/Materials/{name}",
                                  {m: asset(files[p]) for m, files in textures.items()})
                 for p, name in enumerate(prim_names(page_names(mesh.object_names, object_page)))]
    for object_id, name in enumerate(prim_names(mesh.object_names)):
        face_ids = np.nonzero(mesh.face_object == object_id)[0]
        if len(face_ids) == 0:
            continue
        geom = _define_mesh(stage, f"/World/Geometry/{name}", mesh, face_ids)
        geom.GetPrim().SetCustomDataByKey("jaxdistill:object", str(mesh.object_names[object_id]))
        UsdShade.MaterialBindingAPI.Apply(geom.GetPrim()).Bind(materials[int(object_page[object_id])])
    if cameras:
        clipping = (ZNEAR_FRACTION * mesh_diagonal(mesh), ZFAR_FACTOR * mesh_diagonal(mesh))
        for (name, camera), prim in zip(cameras, prim_names([n for n, _ in cameras])):
            _define_camera(stage, f"/World/Cameras/{prim}", camera, clipping).GetPrim().SetCustomDataByKey(
                "jaxdistill:view", str(name))
    stage.GetRootLayer().Save()
    del stage
    os.replace(tmp, path)
    return path
