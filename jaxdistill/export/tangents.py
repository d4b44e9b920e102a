"""Tangent frames of the mesh's faces: normal pages from world space to glTF tangent space, and
the per-corner NORMAL and TANGENT of the glTF primitives (the same frames).

Normal pages are in FILE space (`pages`): one (S, S, 3) array per page of world-space unit
vectors in [-1, 1]; `object_page[i]` is the page of object i.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from jaxdistill.render.charts import check_mesh_pages, dilate_ids, rasterise_uv
from jaxdistill.scene.model import Mesh

FLAT_NORMAL = np.array([0.5, 0.5, 1.0], np.float32)  # tangent-space (0, 0, 1) encoded (t + 1) / 2
NORMAL_EPS = 1e-6  # world normals shorter than this are "unknown"
SEAM_DILATION = 2  # texels a face's footprint grows by in tangent_space_normals


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
    face_page = check_mesh_pages(mesh, object_page, num_pages)
    tangent, bitangent, normal, valid = _face_frames(mesh)
    uv = np.asarray(mesh.uv, np.float64)
    out = []
    for p, page in enumerate(world_pages):
        page = np.asarray(page, np.float32)
        if page.ndim != 3 or page.shape[0] != page.shape[1] or page.shape[2] != 3:
            raise ValueError(f"map 'normal' page {p}: expected a square (S, S, 3) array, got shape {page.shape}")
        size = page.shape[0]
        ids = dilate_ids(rasterise_uv(uv, np.nonzero(face_page == p)[0], size), dilate)
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
