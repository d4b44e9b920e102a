"""Exporting results: texture maps (EXR + PNG), a textured glTF, loss plots and contact sheets.

Texture pages come in FILE space, as float32 NumPy arrays: `pages[map_name]` is a list with
one (S_p, S_p, C) array per page p (row 0 is v = 1, texel (r, c) centre at
u = (c + 0.5) / S, v = 1 - (r + 0.5) / S; all maps share the page sizes). Values:

    albedo      C=3  linear RGB in [0, 1]
    irradiance  C=3  linear, >= 0 (may exceed 1)
    roughness   C=1  perceptual roughness in [0, 1] (as glTF uses it)
    metallic    C=1  in [0, 1]
    normal      C=3  WORLD-space unit vectors in [-1, 1] (zero-length where unknown)

`object_page[i]` is the page of object i: every object its own page ("pages" layout) or all
on page 0 ("atlas" layout). matplotlib is imported only by the plotting functions.
"""

from __future__ import annotations

import json
import os
import re
import struct
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np

from jaxdistill import MAP_NAMES
from jaxdistill.io import images as imageio
from jaxdistill.scene.cameras import Camera, to_opengl
from jaxdistill.scene.maps import png_pixels
from jaxdistill.render.sampler import compact
from jaxdistill.scene.model import Mesh

MAP_CHANNELS = {"albedo": 3, "normal": 3, "roughness": 1, "metallic": 1, "irradiance": 3}
FLAT_NORMAL = np.array([0.5, 0.5, 1.0], np.float32)  # tangent-space (0, 0, 1) encoded (t + 1) / 2
NORMAL_EPS = 1e-6  # world normals shorter than this are "unknown"
SEAM_DILATION = 2  # texels a face's footprint grows by in tangent_space_normals
RASTER_CHUNK = 1 << 22  # candidate texels per rasterisation batch (bounds memory)


# ----------------------------------------------------------------------------- validation


def _num_pages(object_page: Sequence[int]) -> int:
    object_page = np.asarray(object_page, np.int64)
    if object_page.ndim != 1 or len(object_page) == 0:
        raise ValueError(f"object_page: expected one page index per object, got shape {object_page.shape}")
    if object_page.min() < 0:
        raise ValueError(f"object_page: page indices must be >= 0, got {object_page.tolist()}")
    return int(object_page.max()) + 1


def _check_pages(pages: Mapping[str, Sequence[np.ndarray]], object_page: Sequence[int]) -> dict:
    """The pages as float32 arrays after checking names, channel counts, page counts and sizes."""
    if not pages:
        raise ValueError("pages: no maps given")
    num_pages = _num_pages(object_page)
    checked, sizes, first = {}, None, None
    for name, maps in pages.items():
        if name not in MAP_CHANNELS:
            raise ValueError(f"pages: unknown map {name!r}; known maps: {', '.join(MAP_NAMES)}")
        if len(maps) != num_pages:
            raise ValueError(f"map {name!r}: {len(maps)} pages, but object_page uses {num_pages} "
                             f"(pages 0..{num_pages - 1})")
        arrays = []
        for p, page in enumerate(maps):
            page = np.asarray(page, np.float32)
            if page.ndim == 2 and MAP_CHANNELS[name] == 1:
                page = page[:, :, None]
            if page.ndim != 3 or page.shape[0] != page.shape[1] or page.shape[2] != MAP_CHANNELS[name]:
                raise ValueError(f"map {name!r} page {p}: expected a square (S, S, {MAP_CHANNELS[name]}) "
                                 f"array, got shape {page.shape}")
            arrays.append(page)
        page_sizes = [a.shape[0] for a in arrays]
        if sizes is None:
            sizes, first = page_sizes, name
        elif page_sizes != sizes:
            p = next(i for i, (a, b) in enumerate(zip(page_sizes, sizes)) if a != b)
            raise ValueError(f"map {name!r} page {p} is {page_sizes[p]}x{page_sizes[p]} but map {first!r} "
                             f"page {p} is {sizes[p]}x{sizes[p]}; all maps must share the page sizes")
        checked[name] = arrays
    return checked


def _check_mesh_pages(mesh: Mesh, object_page: Sequence[int], num_pages: int) -> np.ndarray:
    """(F,) page of every face, after checking object_page against the mesh and the page count."""
    object_page = np.asarray(object_page, np.int64)
    if len(object_page) != len(mesh.object_names):
        raise ValueError(f"object_page: {len(object_page)} entries for {len(mesh.object_names)} mesh objects")
    if object_page.min() < 0 or object_page.max() >= num_pages:
        raise ValueError(f"object_page: page indices must lie in [0, {num_pages - 1}] "
                         f"({num_pages} pages given), got {object_page.tolist()}")
    return object_page[mesh.face_object]


# ----------------------------------------------------------------------------- names and maps


def page_names(object_names: Sequence[str], object_page: Sequence[int]) -> list[str]:
    """A file-name stem per page: the object's name when the page holds exactly one object,
    else `page_000` style. Characters outside [A-Za-z0-9._-] become '_'; a stem that would
    repeat another gets `_<page>` appended, so the stems are unique."""
    object_page = np.asarray(object_page, np.int64)
    if len(object_page) != len(object_names):
        raise ValueError(f"object_page: {len(object_page)} entries for {len(object_names)} object names")
    names, used = [], set()
    for p in range(_num_pages(object_page)):
        members = np.nonzero(object_page == p)[0]
        name = f"page_{p:03d}"
        if len(members) == 1:
            name = re.sub(r"[^A-Za-z0-9._-]", "_", str(object_names[members[0]])).strip(".") or name
        if name in used:
            name = f"{name}_{p:03d}"
        used.add(name)
        names.append(name)
    return names


def page_file(root, name: str, stems: Sequence[str], page: int, suffix: str) -> Path:
    """Where page `page` of map `name` lies under `root`: `root/<name><suffix>` with one page,
    else `root/<name>/<stem><suffix>` (`stems` from `page_names`)."""
    base = Path(root) / name if len(stems) == 1 else Path(root) / name / stems[page]
    return base.with_name(base.name + suffix)


EVIDENCE_DIR = "evidence"


def write_evidence(out_dir, pages: Mapping[str, Sequence[np.ndarray]], object_names: Sequence[str],
                   object_page: Sequence[int]) -> list[Path]:
    """Writes per-texel evidence pages, one float32 channel each, as EXR under
    `out_dir/evidence/` in the maps' page naming (`page_file`): e.g. `visibility` (view
    counts) and `disagreement_<map>` (the views' spread, NaN where fewer than two views)."""
    stems = page_names(object_names, object_page)
    root = Path(out_dir) / EVIDENCE_DIR
    written = []
    for name, per_page in pages.items():
        if len(per_page) != len(stems):
            raise ValueError(f"evidence {name!r}: {len(per_page)} pages, but object_page uses {len(stems)}")
        for p, page in enumerate(per_page):
            path = page_file(root, name, stems, p, ".exr")
            imageio.write_image(path, np.asarray(page, np.float32))
            written.append(path)
    return written


def write_maps(out_dir, pages: Mapping[str, Sequence[np.ndarray]], object_names: Sequence[str],
               object_page: Sequence[int]) -> list[Path]:
    """Writes every map as float32 EXR (linear, HDR kept) and 8-bit PNG; returns the paths.

    One page: `out_dir/maps/<map>.exr|.png`; several: `out_dir/maps/<map>/<page_name>.exr|.png`
    (`page_names`). PNGs: albedo and irradiance sRGB-encoded (irradiance clipped to [0, 1]),
    roughness and metallic grey values as they are, normal as (n + 1) / 2 (world space, no sRGB).
    """
    pages = _check_pages(pages, object_page)
    stems = page_names(object_names, object_page)
    root = Path(out_dir) / "maps"
    written = []
    for name in [m for m in MAP_NAMES if m in pages]:
        for p, page in enumerate(pages[name]):
            exr, png = page_file(root, name, stems, p, ".exr"), page_file(root, name, stems, p, ".png")
            imageio.write_image(exr, page)
            pixels, encode = png_pixels(name, page)
            imageio.write_image(png, pixels, encode_srgb=encode)
            written += [exr, png]
    return written


# ----------------------------------------------------------------------------- tangent space


def _face_frames(mesh: Mesh) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Per face the orthonormal tangent frame (T, B, N), each (F, 3), and (F,) bool valid.

    T = dP/du and B = dP/dv from positions and UVs; N is the unit geometric normal, oriented
    like cross(e1, e2). T is Gram-Schmidt orthonormalised against N and B = sign * cross(N, T),
    the sign saying whether the UVs are mirrored (MikkTSpace's frame for a flat face).
    Faces with no area in space or in UV, or T parallel to N, are not valid.
    """
    tri = mesh.triangles()
    uv = np.asarray(mesh.uv, np.float64)
    e1, e2 = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    d1, d2 = uv[:, 1] - uv[:, 0], uv[:, 2] - uv[:, 0]
    det = d1[:, 0] * d2[:, 1] - d2[:, 0] * d1[:, 1]
    safe_det = np.where(np.abs(det) > 1e-20, det, 1.0)[:, None]
    dpdu = (e1 * d2[:, 1:2] - e2 * d1[:, 1:2]) / safe_det
    dpdv = (e2 * d1[:, 0:1] - e1 * d2[:, 0:1]) / safe_det
    normal = np.cross(e1, e2)
    n_len = np.linalg.norm(normal, axis=1, keepdims=True)
    normal = normal / np.maximum(n_len, 1e-300)
    tangent = dpdu - normal * np.sum(normal * dpdu, axis=1, keepdims=True)
    t_len = np.linalg.norm(tangent, axis=1, keepdims=True)
    tangent = tangent / np.maximum(t_len, 1e-300)
    cross = np.cross(normal, tangent)
    sign = np.where(np.sum(cross * dpdv, axis=1, keepdims=True) < 0.0, -1.0, 1.0)
    bitangent = sign * cross
    scale = np.linalg.norm(e1, axis=1) + np.linalg.norm(e2, axis=1)
    valid = ((np.abs(det) > 1e-20) & (n_len[:, 0] > 1e-12 * np.maximum(scale, 1e-300) ** 2)
             & (t_len[:, 0] > 1e-9 * np.linalg.norm(dpdu, axis=1)) & np.isfinite(tri).all(axis=(1, 2)))
    return tangent, bitangent, normal, valid


def _rasterise_uv(uv: np.ndarray, face_ids: np.ndarray, size: int) -> np.ndarray:
    """(S, S) int64 id of the face whose UV triangle covers each texel centre, -1 where none.

    uv (F, 3, 2) per corner, v up; only faces `face_ids` are drawn. Edges count as inside;
    where faces overlap the texel goes to the face it lies deepest in (the largest smallest
    barycentric), ties to the lower face id.
    """
    best_face = np.full(size * size, -1, np.int64)
    best_score = np.full(size * size, -np.inf)
    if len(face_ids) == 0:
        return best_face.reshape(size, size)
    xy = np.stack([uv[face_ids, :, 0] * size - 0.5, (1.0 - uv[face_ids, :, 1]) * size - 0.5], axis=-1)
    lo = np.clip(np.ceil(xy.min(axis=1) - 1e-9), 0, size).astype(np.int64)  # (F, 2) first col/row
    hi = np.clip(np.floor(xy.max(axis=1) + 1e-9), -1, size - 1).astype(np.int64)
    extent = np.maximum(hi - lo + 1, 0)
    count = extent[:, 0] * extent[:, 1]
    (a, b, c) = (xy[:, 0], xy[:, 1], xy[:, 2])
    area = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (c[:, 0] - a[:, 0]) * (b[:, 1] - a[:, 1])
    count = np.where(np.abs(area) > 1e-12, count, 0)
    ends = np.cumsum(count)
    start = 0
    while start < len(face_ids):
        # a batch of whole faces holding about RASTER_CHUNK candidate texels
        base = ends[start - 1] if start else 0
        stop = max(int(np.searchsorted(ends, base + RASTER_CHUNK, side="right")), start + 1)
        local = np.arange(start, stop)
        n = count[local]
        which = np.repeat(local, n)
        k = np.arange(int(n.sum())) - np.repeat(np.cumsum(n) - n, n)
        col = lo[which, 0] + k % extent[which, 0]
        row = lo[which, 1] + k // extent[which, 0]
        px, py = col.astype(np.float64), row.astype(np.float64)
        pa, pb, pc = a[which], b[which], c[which]
        w_a = ((pb[:, 0] - px) * (pc[:, 1] - py) - (pc[:, 0] - px) * (pb[:, 1] - py)) / area[which]
        w_b = ((pc[:, 0] - px) * (pa[:, 1] - py) - (pa[:, 0] - px) * (pc[:, 1] - py)) / area[which]
        score = np.minimum(np.minimum(w_a, w_b), 1.0 - w_a - w_b)
        inside = score >= -1e-9
        texel = (row * size + col)[inside]
        score, which = score[inside], which[inside]
        shared = np.bincount(texel, minlength=size * size)[texel] > 1
        if shared.any():  # texels claimed by several faces of this batch (edges): sort only those
            order = np.nonzero(shared)[0]
            order = order[np.lexsort((which[order], -score[order], texel[order]))]
            first = np.ones(len(order), bool)
            first[1:] = texel[order[1:]] != texel[order[:-1]]
            keep = np.concatenate([np.nonzero(~shared)[0], order[first]])
            texel, score, which = texel[keep], score[keep], which[keep]
        better = score > best_score[texel]
        best_score[texel[better]] = score[better]
        best_face[texel[better]] = face_ids[which[better]]
        start = stop
    return best_face.reshape(size, size)


def _dilate_ids(ids: np.ndarray, passes: int) -> np.ndarray:
    """Grows the covered region (ids >= 0) by `passes` texels: each pass an empty texel takes
    the id of its first covered neighbour (4-neighbours first, then diagonals)."""
    offsets = [(-1, 0), (1, 0), (0, -1), (0, 1), (-1, -1), (-1, 1), (1, -1), (1, 1)]
    for _ in range(passes):
        padded = np.pad(ids, 1, constant_values=-1)
        out = ids.copy()
        for dr, dc in offsets:
            neighbour = padded[1 + dr:1 + dr + ids.shape[0], 1 + dc:1 + dc + ids.shape[1]]
            take = (out < 0) & (neighbour >= 0)
            out[take] = neighbour[take]
        if np.array_equal(out, ids):
            break
        ids = out
    return ids


EVIDENCE_FULL = 1.0  # texel evidence (summed tap weight, visibility.texel_evidence) at which a texel is fully trusted


def chart_coverage(mesh: Mesh, object_page: Sequence[int], page_sizes: Sequence[int], *,
                   dilate: int = 1) -> list[np.ndarray]:
    """Per page, (S, S) bool: texels whose centre some face of the page's objects covers in UV
    space, grown by `dilate` texels (the neighbours a bilinear lookup inside a chart reads).
    Texels outside are never seen through the mesh at level 0: only mip levels blend them in."""
    face_page = _check_mesh_pages(mesh, object_page, len(page_sizes))
    uv = np.asarray(mesh.uv, np.float64)
    return [_dilate_ids(_rasterise_uv(uv, np.nonzero(face_page == p)[0], int(size)), dilate) >= 0
            for p, size in enumerate(page_sizes)]


def page_trust(evidence_pages: Sequence[np.ndarray], coverage: Sequence[np.ndarray]) -> list[np.ndarray]:
    """Per page, (S, S) float32 in [0, 1]: how far a texel's distilled value is kept in the
    exported page (`sampler.push_pull` fills the rest from its neighbours): evidence /
    EVIDENCE_FULL clipped to 1 inside the charts (`chart_coverage`), 0 outside them."""
    return [np.where(c, np.clip(np.asarray(e, np.float32).reshape(c.shape) / EVIDENCE_FULL, 0.0, 1.0), 0.0)
            .astype(np.float32) for e, c in zip(evidence_pages, coverage)]


def texel_trust(evidence: np.ndarray, coverage: Sequence[np.ndarray], space) -> np.ndarray:
    """`page_trust` per compact texel (N,) float32: evidence (N,) / EVIDENCE_FULL clipped to 1,
    0 where the texel lies outside its page's charts (`chart_coverage` pages). Expanded to pages
    (fill 0, no dilation) it equals `page_trust` of the expanded evidence."""
    inside = compact([c[..., None].astype(np.float32) for c in coverage], space)[:, 0] > 0
    return np.where(inside, np.clip(np.asarray(evidence, np.float32) / EVIDENCE_FULL, 0.0, 1.0), 0.0).astype(np.float32)


def tangent_space_normals(world_pages: Sequence[np.ndarray], mesh: Mesh, object_page: Sequence[int], *,
                          dilate: int = SEAM_DILATION) -> list[np.ndarray]:
    """World-space normal pages -> glTF tangent-space normal pages, encoded (t + 1) / 2.

    world_pages: one (S, S, 3) array per page of world-space normals in [-1, 1] (normalised
    here; length ~0 means unknown). Returns one (S, S, 3) float32 array per page in [0, 1].

    Every face of the objects on a page is rasterised into the page's UV space (texel (r, c)
    centre at u = (c + 0.5) / S, v = 1 - (r + 0.5) / S); the face covering a texel gives the
    frame (T, B, N) of `_face_frames` (MikkTSpace for flat, un-welded faces, as `write_gltf`
    exports them) and the texel stores (n.T, n.B, n.N): +X along +u, +Y along +v, +Z out of
    the surface. The covered region is then grown `dilate` texels (empty texels take a
    neighbouring face), so bilinear lookups at UV seams see converted normals. Texels still
    covered by no face, unknown normals and degenerate faces give (0, 0, 1) -> (0.5, 0.5, 1).
    """
    num_pages = len(world_pages)
    face_page = _check_mesh_pages(mesh, object_page, num_pages)
    tangent, bitangent, normal, valid = _face_frames(mesh)
    uv = np.asarray(mesh.uv, np.float64)
    out = []
    for p, page in enumerate(world_pages):
        page = np.asarray(page, np.float32)
        if page.ndim != 3 or page.shape[0] != page.shape[1] or page.shape[2] != 3:
            raise ValueError(f"map 'normal' page {p}: expected a square (S, S, 3) array, got shape {page.shape}")
        size = page.shape[0]
        ids = _dilate_ids(_rasterise_uv(uv, np.nonzero(face_page == p)[0], size), dilate)
        world = np.nan_to_num(page.astype(np.float64).reshape(-1, 3))
        length = np.linalg.norm(world, axis=1)
        flat_ids = ids.reshape(-1)
        use = (flat_ids >= 0) & (length > NORMAL_EPS)
        use[use] = valid[flat_ids[use]]
        result = np.tile(FLAT_NORMAL, (size * size, 1))
        f = flat_ids[use]
        n = world[use] / length[use, None]
        local = np.stack([np.sum(n * tangent[f], axis=1), np.sum(n * bitangent[f], axis=1),
                          np.sum(n * normal[f], axis=1)], axis=1)
        result[use] = np.clip((local + 1.0) * 0.5, 0.0, 1.0)
        out.append(result.reshape(size, size, 3).astype(np.float32))
    return out


# ----------------------------------------------------------------------------- glTF


def _to_uint8(x: np.ndarray) -> np.ndarray:
    return np.round(np.clip(np.nan_to_num(x), 0.0, 1.0) * 255.0).astype(np.uint8)


def material_layers(name: str, pages: Sequence[np.ndarray], mesh: Mesh, object_page: Sequence[int]):
    """What one map contributes to each page's glTF material, as uint8 arrays (one per page):
    albedo (S, S, 3) sRGB baseColor; roughness, metallic (S, S) linear; normal (S, S, 3)
    tangent-space (`tangent_space_normals`); None for irradiance (no place in a glTF material).
    Lets a caller expand, write and convert one map at a time (see `combine_material_layers`)."""
    if name == "albedo":
        return [_to_uint8(imageio.linear_to_srgb(np.nan_to_num(page))) for page in pages]
    if name in ("roughness", "metallic"):
        return [_to_uint8(np.asarray(page)[..., 0]) for page in pages]
    if name == "normal":
        return [_to_uint8(page) for page in tangent_space_normals(pages, mesh, object_page)]
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
    checked = _check_pages(pages, object_page)
    _check_mesh_pages(mesh, object_page, len(next(iter(checked.values()))))
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

    _check_mesh_pages(mesh, object_page, len(material_images))
    stems = page_names(mesh.object_names, object_page)
    materials = []
    for p, images in enumerate(material_images):
        has_mr = "metallicRoughnessTexture" in images
        materials.append(trimesh.visual.material.PBRMaterial(
            name=stems[p], metallicFactor=1.0 if has_mr else 0.0, roughnessFactor=1.0,
            **{key: PIL.Image.fromarray(img) for key, img in images.items()}))
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


def vertex_frames(mesh: Mesh, face_ids) -> tuple[np.ndarray, np.ndarray]:
    """(normals (3n, 3), tangents (3n, 4)) float32 of the un-welded corners of faces `face_ids`
    (three per face, in face order, as `write_gltf_images` writes them).

    A corner gets its face's frame from `_face_frames`: NORMAL = N, TANGENT = (T, w) with
    w = +1 when B = cross(N, T) and -1 when the UVs are mirrored (glTF's bitangent is
    cross(N, T) * w). For flat faces this is MikkTSpace's frame, the one `tangent_space_normals`
    encodes the normal pages in. Degenerate faces (no area in space or UV) get a unit normal
    (their own when it exists, else +Z) and any unit tangent perpendicular to it, w = +1."""
    tangent, bitangent, normal, valid = _face_frames(mesh)
    face_ids = np.asarray(face_ids, np.int64)
    t, b, n, ok = tangent[face_ids], bitangent[face_ids], normal[face_ids], valid[face_ids]
    n_ok = np.isfinite(n).all(axis=1) & (np.abs(np.linalg.norm(n, axis=1) - 1.0) < 1e-6)
    n = np.where(n_ok[:, None], n, [0.0, 0.0, 1.0])
    other = np.where(np.abs(n[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
    fallback = np.cross(n, other)
    fallback /= np.linalg.norm(fallback, axis=1, keepdims=True)
    t = np.where(ok[:, None], t, fallback)
    w = np.where(ok, np.sign(np.sum(np.cross(n, t) * b, axis=1)), 1.0)
    tangents = np.concatenate([t, w[:, None]], axis=1)
    return (np.repeat(n, 3, axis=0).astype(np.float32), np.repeat(tangents, 3, axis=0).astype(np.float32))


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
        lo, hi = mesh.vertices.min(axis=0), mesh.vertices.max(axis=0)
        znear = ZNEAR_FRACTION * max(float(np.linalg.norm(hi - lo)), 1e-6)
        nodes, scene_nodes = doc.setdefault("nodes", []), doc["scenes"][doc.get("scene", 0)].setdefault("nodes", [])
        for name, camera in cameras:
            obj, matrix = gltf_camera(name, camera, znear)
            doc.setdefault("cameras", []).append(obj)
            nodes.append({"name": name, "camera": len(doc["cameras"]) - 1, "matrix": matrix})
            scene_nodes.append(len(nodes) - 1)
    doc["buffers"] = [{"byteLength": len(binary) + (-len(binary) % 4)}]
    return _glb_bytes(doc, bytes(binary))


# ----------------------------------------------------------------------------- plots


def _smooth(values: np.ndarray) -> np.ndarray:
    """Centred moving average over ~4 % of the points (window shrinks at the ends)."""
    half = max(1, len(values) // 50)
    sums = np.concatenate([[0.0], np.cumsum(values)])
    idx = np.arange(len(values))
    lo, hi = np.maximum(idx - half, 0), np.minimum(idx + half + 1, len(values))
    return (sums[hi] - sums[lo]) / (hi - lo)


def _series(name: str, steps, values) -> tuple[np.ndarray, np.ndarray]:
    steps, values = np.asarray(steps, np.float64).reshape(-1), np.asarray(values, np.float64).reshape(-1)
    if len(steps) != len(values):
        raise ValueError(f"{name}: {len(steps)} steps but {len(values)} values")
    keep = np.isfinite(steps) & np.isfinite(values)
    return steps[keep], values[keep]


def write_loss_plot(path, steps, values, *, extra: Mapping[str, tuple] | None = None,
                    title: str | None = None) -> Path:
    """Writes a PNG line plot of loss vs step; returns the path.

    The raw curve is drawn faint with a lightly smoothed one over it (smoothing in log space
    when the y axis is logarithmic, which it is when every value is > 0). `extra` maps a name
    to (steps, values) drawn on a second y axis (e.g. albedo PSNR in dB). Non-finite points
    are dropped. Uses matplotlib's Agg canvas directly (no pyplot state).
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    steps, values = _series("loss", steps, values)
    if len(values) == 0:
        raise ValueError("loss: no finite (step, value) points to plot")
    fig = Figure(figsize=(8, 4.5), dpi=100)
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(1, 1, 1)
    log_y = bool(np.all(values > 0))
    smooth = np.exp(_smooth(np.log(values))) if log_y else _smooth(values)
    ax.plot(steps, values, color="tab:blue", alpha=0.3, linewidth=0.8, label="loss")
    ax.plot(steps, smooth, color="tab:blue", linewidth=1.8, label="loss (smoothed)",
            marker="o" if len(values) == 1 else None)
    if log_y:
        ax.set_yscale("log")
    ax.set_xlabel("step")
    ax.set_ylabel("loss")
    ax.grid(True, which="major", alpha=0.3)
    handles, labels = ax.get_legend_handles_labels()
    if extra:
        ax2 = ax.twinx()
        colours = ["tab:orange", "tab:green", "tab:red", "tab:purple", "tab:brown"]
        for i, (name, (x, y)) in enumerate(extra.items()):
            x, y = _series(name, x, y)
            ax2.plot(x, y, color=colours[i % len(colours)], linewidth=1.5, label=name,
                     marker="o" if len(y) < 20 else None, markersize=3)
        ax2.set_ylabel(", ".join(extra))
        h2, l2 = ax2.get_legend_handles_labels()
        handles, labels = handles + h2, labels + l2
    ax.legend(handles, labels, loc="best", fontsize="small", framealpha=0.8)
    if title:
        ax.set_title(title)
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(os.fspath(path), format="png")
    return path


def _cell_image(image, where: str) -> np.ndarray:
    image = np.asarray(image, np.float32)
    if image.ndim == 3 and image.shape[2] == 1:
        image = image[:, :, 0]
    if image.ndim == 2:
        image = np.repeat(image[:, :, None], 3, axis=2)
    if image.ndim != 3 or image.shape[2] not in (3, 4) or image.shape[0] == 0 or image.shape[1] == 0:
        raise ValueError(f"{where}: expected an (H, W, 3) image, got shape {image.shape}")
    return np.clip(np.nan_to_num(image[:, :, :3]), 0.0, 1.0)


CHAR_PX = 7  # approximate width of one character of the sheet's 11 px font


def write_contact_sheet(path, rows: Sequence[Sequence], column_names: Sequence[str],
                        row_names: Sequence[str] | None = None, *, gap: int = 4, title_px: int = 20,
                        label_px: int | None = None) -> Path:
    """Writes a PNG grid of images with column titles and row names; returns the path.

    rows: one list per row (view) of (H, W, 3) float images in DISPLAY space [0, 1] (the
    caller encodes; grey (H, W) images are accepted), None for a missing cell (drawn grey).
    Images are drawn 1:1 at the top left of their cell; a column is as wide as its widest
    image, a row as tall as its tallest. Layout in pixels, with a white background:

        width  = label + sum(column widths) + gap * (columns + 1)
        height = title + sum(row heights)   + gap * (rows + 1)

    title = `title_px`; label = `label_px`, or (without it) enough for the longest row name,
    or 0 without row names.
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    n_cols = len(column_names)
    if not rows or n_cols == 0:
        raise ValueError("contact sheet: needs at least one row and one column")
    if row_names is not None and len(row_names) != len(rows):
        raise ValueError(f"contact sheet: {len(row_names)} row names for {len(rows)} rows")
    cells = []
    for r, row in enumerate(rows):
        if len(row) != n_cols:
            raise ValueError(f"contact sheet row {r}: {len(row)} images for {n_cols} columns")
        cells.append([None if img is None else _cell_image(img, f"contact sheet row {r} column {c}")
                      for c, img in enumerate(row)])
    sizes = [img.shape[:2] for row in cells for img in row if img is not None]
    default = (int(np.median([s[0] for s in sizes])), int(np.median([s[1] for s in sizes]))) if sizes else (64, 64)
    heights = [max((img.shape[0] for img in row if img is not None), default=default[0]) for row in cells]
    widths = [max((row[c].shape[1] for row in cells if row[c] is not None), default=default[1])
              for c in range(n_cols)]
    if label_px is None:
        label_px = 0 if row_names is None else 2 * gap + CHAR_PX * max(len(str(n)) for n in row_names)
    x0 = label_px + gap + np.concatenate([[0], np.cumsum(np.asarray(widths) + gap)])
    y0 = title_px + gap + np.concatenate([[0], np.cumsum(np.asarray(heights) + gap)])
    width, height = int(x0[-1]), int(y0[-1])
    sheet = np.ones((height, width, 3), np.float32)
    for r, row in enumerate(cells):
        for c, img in enumerate(row):
            if img is None:
                sheet[y0[r]:y0[r] + heights[r], x0[c]:x0[c] + widths[c]] = 0.5
            else:
                sheet[y0[r]:y0[r] + img.shape[0], x0[c]:x0[c] + img.shape[1]] = img

    dpi = 72  # 1 pt = 1 px
    fig = Figure(figsize=(width / dpi, height / dpi), dpi=dpi)
    canvas = FigureCanvasAgg(fig)
    fig.figimage(_to_uint8(sheet), xo=0, yo=0, origin="upper", resize=False)  # uint8: no requantising

    def fit(text, px):
        text = str(text)
        most = max(1, px // CHAR_PX)
        return text if len(text) <= most else text[:max(1, most - 1)] + "…"

    for c, name in enumerate(column_names):
        fig.text((x0[c] + widths[c] / 2) / width, 1.0 - (title_px / 2 + gap / 2) / height, fit(name, widths[c]),
                 ha="center", va="center", fontsize=11)
    if row_names is not None and label_px > 0:
        for r, name in enumerate(row_names):
            fig.text(gap / width, 1.0 - (y0[r] + heights[r] / 2) / height, fit(name, label_px - gap),
                     ha="left", va="center", fontsize=11)
    canvas.draw()
    pixels = np.asarray(canvas.buffer_rgba())[:, :, :3].astype(np.float32) / 255.0
    if pixels.shape[:2] != (height, width):  # figure size rounding: keep the arithmetic exact
        padded = np.ones((height, width, 3), np.float32)
        h, w = min(height, pixels.shape[0]), min(width, pixels.shape[1])
        padded[:h, :w] = pixels[:h, :w]
        pixels = padded
    path = Path(path)
    imageio.write_image(path, pixels, encode_srgb=False)
    return path
