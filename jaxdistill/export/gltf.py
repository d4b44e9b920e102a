"""The textured glTF: per-page PBR materials from the map pages, the binary glTF (.glb) of the mesh
with them, its vertex frames and the views as cameras; reading and completing a .glb.
"""

from __future__ import annotations

import json
import os
import struct
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np

from jaxdistill.export.pages import check_pages, page_names, to_uint8
from jaxdistill.export.tangents import tangent_space_normals, vertex_frames
from jaxdistill.io import images as imageio
from jaxdistill.render.charts import check_mesh_pages
from jaxdistill.scene.cameras import Camera, to_opengl
from jaxdistill.scene.model import Mesh


def material_layers(name: str, pages: Sequence[np.ndarray], mesh: Mesh, object_page: Sequence[int]):
    """What one map contributes to each page's glTF material, as uint8 arrays (one per page):
    albedo (S, S, 3) sRGB baseColor; roughness, metallic (S, S) linear; normal (S, S, 3)
    tangent-space (`tangent_space_normals`); None for irradiance (no place in a glTF material).
    Lets a caller expand, write and convert one map at a time (see `combine_material_layers`)."""
    if name == "albedo":
        return [to_uint8(imageio.linear_to_srgb(np.nan_to_num(page))) for page in pages]
    if name in ("roughness", "metallic"):
        return [to_uint8(np.asarray(page)[..., 0]) for page in pages]
    if name == "normal":
        return [to_uint8(page) for page in tangent_space_normals(pages, mesh, object_page)]
    return None


def combine_material_layers(layers: Mapping[str, Sequence[np.ndarray]], num_pages: int) -> list[dict]:
    """Per page the glTF images of its material from `material_layers` of some maps:
    baseColorTexture, packed metallicRoughnessTexture (R 255, G roughness, B metallic; a missing
    roughness is 255, a missing metallic 0) and normalTexture."""
    images = []
    for p in range(num_pages):
        page = {}
        if "albedo" in layers:
            page["baseColorTexture"] = layers["albedo"][p]
        if "roughness" in layers or "metallic" in layers:
            shape = (layers["roughness"] if "roughness" in layers else layers["metallic"])[p].shape
            rough = layers["roughness"][p] if "roughness" in layers else np.full(shape, 255, np.uint8)
            metal = layers["metallic"][p] if "metallic" in layers else np.zeros(shape, np.uint8)
            page["metallicRoughnessTexture"] = np.stack([np.full(shape, 255, np.uint8), rough, metal], axis=-1)
        if "normal" in layers:
            page["normalTexture"] = layers["normal"][p]
        images.append(page)
    return images


def _material_images(pages: Mapping[str, Sequence[np.ndarray]], mesh: Mesh, object_page: Sequence[int]) -> list[dict]:
    """Per page the glTF images (uint8 arrays) of its material, from float pages of every map."""
    layers = {m: material_layers(m, pages[m], mesh, object_page) for m in pages}
    return combine_material_layers({m: v for m, v in layers.items() if v is not None},
                                   len(next(iter(pages.values()))))


def write_gltf(path, mesh: Mesh, object_page: Sequence[int], pages: Mapping[str, Sequence[np.ndarray]],
               cameras: Sequence[tuple[str, Camera]] = ()) -> Path:
    """Writes a binary glTF (.glb) of the textured mesh with trimesh; returns the path.

    One node and geometry per object, named by the object (objects without faces are left
    out), vertices un-welded (three per face, the corners' UVs). Each page becomes one
    PBRMaterial named by `page_names`, shared by the objects on it: baseColorTexture = albedo
    (8-bit sRGB), metallicRoughnessTexture = (255, roughness, metallic) 8-bit linear, and
    normalTexture = `tangent_space_normals`; metallicFactor = roughnessFactor = 1. Maps absent
    from `pages` are left out: with roughness but no metallic the texture's B is 0 (and with
    metallic but no roughness G is 255); with neither there is no such texture and
    metallicFactor is 0 (a rough dielectric, not glTF's default full metal). Irradiance has no
    place in a glTF material and is not written. trimesh writes TEXCOORD_0 as (u, 1 - v), so a
    texel's row 0 (our v = 1) is the image's top row, as glTF samples it. Every primitive also
    carries NORMAL and TANGENT (`vertex_frames`, the frames `tangent_space_normals` encodes the
    normal pages in), and `cameras` ((name, Camera) pairs) become glTF cameras (`gltf_camera`).
    """
    if Path(path).suffix.lower() != ".glb":
        raise ValueError(f"{path}: write_gltf writes binary glTF; use a .glb file name")
    checked = check_pages(pages, object_page)
    check_mesh_pages(mesh, object_page, len(next(iter(checked.values()))))
    return write_gltf_images(path, mesh, object_page, _material_images(checked, mesh, object_page), cameras)


def write_gltf_images(path, mesh: Mesh, object_page: Sequence[int], material_images: Sequence[dict],
                      cameras: Sequence[tuple[str, Camera]] = ()) -> Path:
    """`write_gltf` from per-page uint8 material images (`combine_material_layers`), so the
    float pages of every map never need to be in memory at once."""
    path = Path(path)
    if path.suffix.lower() != ".glb":
        raise ValueError(f"{path}: write_gltf writes binary glTF; use a .glb file name")
    data = gltf_bytes(mesh, object_page, material_images, cameras)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_bytes(data)
    os.replace(tmp, path)
    return path


def gltf_bytes(mesh: Mesh, object_page: Sequence[int], material_images: Sequence[dict],
               cameras: Sequence[tuple[str, Camera]] = ()) -> bytes:
    """The binary glTF that `write_gltf_images` writes (vertex normals, tangents, cameras: `complete_glb`)."""
    import PIL.Image
    import trimesh

    check_mesh_pages(mesh, object_page, len(material_images))
    stems = page_names(mesh.object_names, object_page)
    def texture(pixels: np.ndarray) -> PIL.Image.Image:
        image = PIL.Image.fromarray(pixels)
        # trimesh saves it as PNG with no options; Pillow reads the image's own encoderinfo
        image.encoderinfo = {"compress_level": imageio.PNG_COMPRESSION_LEVEL}
        return image

    materials = []
    for p, images in enumerate(material_images):
        has_mr = "metallicRoughnessTexture" in images
        materials.append(trimesh.visual.material.PBRMaterial(
            name=stems[p], metallicFactor=1.0 if has_mr else 0.0, roughnessFactor=1.0,
            **{key: texture(img) for key, img in images.items()}))
    scene = trimesh.Scene()
    for object_id, name in enumerate(mesh.object_names):
        face_ids = np.nonzero(mesh.face_object == object_id)[0]
        if len(face_ids) == 0:
            continue
        vertices = mesh.vertices[mesh.faces[face_ids]].reshape(-1, 3)
        uv = np.asarray(mesh.uv[face_ids], np.float64).reshape(-1, 2)
        visual = trimesh.visual.TextureVisuals(uv=uv, material=materials[int(object_page[object_id])])
        geom = trimesh.Trimesh(vertices=vertices, faces=np.arange(len(vertices)).reshape(-1, 3),
                               visual=visual, process=False)
        scene.add_geometry(geom, geom_name=name, node_name=name)
    return complete_glb(scene.export(file_type="glb"), mesh, cameras)


GLB_MAGIC, GLB_JSON, GLB_BIN = 0x46546C67, 0x4E4F534A, 0x004E4942
ARRAY_BUFFER, ELEMENT_ARRAY_BUFFER = 34962, 34963
ZNEAR_FRACTION = 1e-3  # a camera's znear, as a fraction of the mesh's bounding-box diagonal


def mesh_diagonal(mesh: Mesh) -> float:
    """The length of the mesh's bounding-box diagonal (at least 1e-6): the scale of camera clip planes."""
    lo, hi = mesh.vertices.min(axis=0), mesh.vertices.max(axis=0)
    return max(float(np.linalg.norm(hi - lo)), 1e-6)


def gltf_camera(name: str, camera: Camera, znear: float) -> tuple[dict, list[float]]:
    """(glTF camera object, node matrix column-major (16,)) of an OpenCV camera.

    glTF's perspective camera looks down its node's -Z with +Y up: the node matrix is
    `cameras.to_opengl(camera)`. yfov = 2 atan(H / (2 fy)) and aspectRatio = (W / fx) / (H / fy),
    so a point at the image's centre line projects as K does. glTF has no principal point: a
    camera whose (cx, cy) is off (W/2, H/2) is shifted by that many pixels in glTF viewers; its
    exact K, size and the shift in pixels are kept in the camera's `extras` (`jaxdistill_K`,
    `width`, `height`, `principal_point_offset_px`)."""
    K = np.asarray(camera.K, np.float64)
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    w, h = camera.width, camera.height
    perspective = {"yfov": float(2.0 * np.arctan(h / (2.0 * fy))), "aspectRatio": float((w / fx) / (h / fy)),
                   "znear": float(znear)}
    extras = {"jaxdistill_K": K.tolist(), "width": int(w), "height": int(h),
              "principal_point_offset_px": [float(cx - w / 2.0), float(cy - h / 2.0)]}
    obj = {"type": "perspective", "name": name, "perspective": perspective, "extras": extras}
    return obj, [float(x) for x in to_opengl(camera).T.reshape(-1)]


def read_glb(data: bytes) -> tuple[dict, bytes]:
    """(JSON document, BIN chunk) of a binary glTF; ValueError when it is not one."""
    if len(data) < 20 or struct.unpack_from("<I", data, 0)[0] != GLB_MAGIC:
        raise ValueError("not a binary glTF (no glTF magic)")
    length, kind = struct.unpack_from("<II", data, 12)
    if kind != GLB_JSON:
        raise ValueError("binary glTF: the first chunk is not JSON")
    doc = json.loads(data[20:20 + length])
    offset, binary = 20 + length, b""
    if offset + 8 <= len(data):
        bin_length, bin_kind = struct.unpack_from("<II", data, offset)
        if bin_kind == GLB_BIN:
            binary = data[offset + 8:offset + 8 + bin_length]
    return doc, binary


def _glb_bytes(doc: dict, binary: bytes) -> bytes:
    """A binary glTF of `doc` and its BIN chunk (chunks padded to 4 bytes: JSON with spaces)."""
    text = json.dumps(doc, separators=(",", ":")).encode()
    text += b" " * (-len(text) % 4)
    binary += b"\0" * (-len(binary) % 4)
    chunks = struct.pack("<II", len(text), GLB_JSON) + text + struct.pack("<II", len(binary), GLB_BIN) + binary
    return struct.pack("<III", GLB_MAGIC, 2, 12 + len(chunks)) + chunks


def complete_glb(data: bytes, mesh: Mesh, cameras: Sequence[tuple[str, Camera]] = ()) -> bytes:
    """trimesh's glb of `write_gltf_images` with what it lacks for glTF-Validator and viewers:
    NORMAL and TANGENT on every object's primitive (`vertex_frames`), buffer-view targets, and a
    camera node per (name, Camera) (`gltf_camera`), added to the scene."""
    doc, binary = read_glb(data)
    binary = bytearray(binary)
    views, accessors = doc.setdefault("bufferViews", []), doc.setdefault("accessors", [])

    def append(array: np.ndarray, kind: str) -> int:
        binary.extend(b"\0" * (-len(binary) % 4))
        views.append({"buffer": 0, "byteOffset": len(binary), "byteLength": array.nbytes, "target": ARRAY_BUFFER})
        binary.extend(np.ascontiguousarray(array, "<f4").tobytes())
        accessors.append({"bufferView": len(views) - 1, "componentType": 5126, "count": len(array), "type": kind})
        return len(accessors) - 1

    objects = {name: i for i, name in enumerate(mesh.object_names)}
    for node in doc.get("nodes", []):
        if "mesh" not in node or node.get("name") not in objects:
            continue
        face_ids = np.nonzero(mesh.face_object == objects[node["name"]])[0]
        normals, tangents = vertex_frames(mesh, face_ids)
        for primitive in doc["meshes"][node["mesh"]]["primitives"]:
            count = accessors[primitive["attributes"]["POSITION"]]["count"]
            if count != len(normals):
                raise AssertionError(f"glTF mesh {node['name']!r}: {count} vertices, expected {len(normals)} "
                                     "(three per face, un-welded)")
            primitive["attributes"]["NORMAL"] = append(normals, "VEC3")
            primitive["attributes"]["TANGENT"] = append(tangents, "VEC4")
    for primitive in (p for m in doc.get("meshes", []) for p in m["primitives"]):
        for accessor, target in [(a, ARRAY_BUFFER) for a in primitive["attributes"].values()] + (
                [(primitive["indices"], ELEMENT_ARRAY_BUFFER)] if "indices" in primitive else []):
            views[accessors[accessor]["bufferView"]].setdefault("target", target)
    if cameras:
        znear = ZNEAR_FRACTION * mesh_diagonal(mesh)
        nodes, scene_nodes = doc.setdefault("nodes", []), doc["scenes"][doc.get("scene", 0)].setdefault("nodes", [])
        for name, camera in cameras:
            obj, matrix = gltf_camera(name, camera, znear)
            doc.setdefault("cameras", []).append(obj)
            nodes.append({"name": name, "camera": len(doc["cameras"]) - 1, "matrix": matrix})
            scene_nodes.append(len(nodes) - 1)
    doc["buffers"] = [{"byteLength": len(binary) + (-len(binary) % 4)}]
    return _glb_bytes(doc, bytes(binary))
