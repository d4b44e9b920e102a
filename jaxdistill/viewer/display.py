"""What the viewer shows, as plain arrays and bytes (no viser here): display images of map and
evidence pages, the unlit glTF that carries them to the browser, and camera poses.

Display encodings of file-space pages (export.py's conventions):
    albedo      sRGB of the linear values, clipped to [0, 1]
    normal      (n + 1) / 2 of the world-space normal
    roughness,  grey values as they are
    metallic
    irradiance  scaled so that the 99th percentile of the seen texels is 0.9 (irradiance is
                known up to scale), then sRGB
    evidence    a colour map over [0, max] (view counts) or [0, 99th percentile] (disagreement);
                NaN (no or too few views) dark grey
"""

from __future__ import annotations

import json
import struct
from typing import Sequence

import numpy as np

from jaxdistill import evaluation, export
from jaxdistill.cameras import Camera
from jaxdistill.scene import Mesh

NO_DATA = np.array([0.25, 0.25, 0.25], np.float32)     # evidence texels without data
IRRADIANCE_PERCENTILE, IRRADIANCE_TARGET = 99.0, 0.9
COLOUR_MAPS = {"visibility": "viridis", "disagreement": "magma"}


def irradiance_scale(pages: Sequence[np.ndarray]) -> float:
    """The factor that puts the 99th percentile of the pages' non-zero luminance at 0.9."""
    lum = np.concatenate([np.asarray(p, np.float32).mean(axis=-1).ravel() for p in pages])
    lum = lum[np.isfinite(lum) & (lum > 0)]
    top = float(np.percentile(lum, IRRADIANCE_PERCENTILE)) if len(lum) else 0.0
    return IRRADIANCE_TARGET / top if top > 0 else 1.0


def display_values(name: str, image: np.ndarray, scale: float = 1.0) -> np.ndarray:
    """(H, W, 3) float32 display values in [0, 1] of a file-space map image: its PNG encoding
    (`evaluation.display_image`), irradiance multiplied by `scale` first."""
    image = np.asarray(image, np.float32)
    return evaluation.display_image(name, image * scale if name == "irradiance" else image)


def map_display_pages(name: str, pages: Sequence[np.ndarray]) -> list[np.ndarray]:
    """uint8 (S, S, 3) display images of a map's pages."""
    scale = irradiance_scale(pages) if name == "irradiance" else 1.0
    return [to_uint8(display_values(name, p, scale)) for p in pages]


def evidence_range(kind: str, pages: Sequence[np.ndarray]) -> tuple[float, float]:
    """(0, top) the colour map spans: the largest view count, or the 99th percentile of the
    finite disagreement values (1 when there is none)."""
    values = np.concatenate([np.asarray(p, np.float32).ravel() for p in pages])
    values = values[np.isfinite(values)]
    if kind == "visibility":
        top = float(values.max(initial=0.0))
    else:
        top = float(np.percentile(values, 99.0)) if len(values) else 0.0
    return 0.0, top if top > 0 else 1.0


def evidence_display_pages(kind: str, pages: Sequence[np.ndarray]) -> tuple[list[np.ndarray], tuple[float, float]]:
    """(uint8 (S, S, 3) colour-mapped pages, the value range of the colour map)."""
    from matplotlib import colormaps

    low, high = evidence_range(kind, pages)
    cmap = colormaps[COLOUR_MAPS[kind]]
    out = []
    for page in pages:
        values = np.asarray(page, np.float32)[..., 0]
        rgb = cmap(np.clip((np.nan_to_num(values) - low) / (high - low), 0.0, 1.0))[..., :3].astype(np.float32)
        rgb[~np.isfinite(values)] = NO_DATA
        out.append(to_uint8(rgb))
    return out, (low, high)


def comparison_grid(cells: Sequence[np.ndarray | None], width: int, columns: int = 2, gap: int = 4) -> np.ndarray:
    """The (H, W, 3) display images `cells` side by side, `columns` a row, each resized
    (nearest) to `width` pixels across, on white with `gap` pixels between; None is grey."""
    first = next(c for c in cells if c is not None)
    height = max(1, round(first.shape[0] * width / first.shape[1]))
    rows = -(-len(cells) // columns)
    out = np.ones((rows * height + (rows - 1) * gap, columns * width + (columns - 1) * gap, 3), np.float32)
    for i, cell in enumerate(cells):
        r, c = divmod(i, columns)
        y, x = r * (height + gap), c * (width + gap)
        if cell is None:
            out[y:y + height, x:x + width] = 0.5
            continue
        cell = np.asarray(cell, np.float32)
        ys = (np.arange(height) * cell.shape[0] // height).clip(0, cell.shape[0] - 1)
        xs = (np.arange(width) * cell.shape[1] // width).clip(0, cell.shape[1] - 1)
        out[y:y + height, x:x + width] = cell[ys][:, xs, :3]
    return out


def to_uint8(values: np.ndarray) -> np.ndarray:
    return np.round(np.clip(np.nan_to_num(values), 0.0, 1.0) * 255.0).astype(np.uint8)


# ----------------------------------------------------------------------------- glTF


def mark_unlit(glb: bytes) -> bytes:
    """The binary glTF with every material made KHR_materials_unlit: the browser shows the base
    colour texture as it is, without lights or shading."""
    magic, version, _ = struct.unpack_from("<III", glb, 0)
    json_length, json_type = struct.unpack_from("<II", glb, 12)
    if magic != 0x46546C67 or json_type != 0x4E4F534A:
        raise ValueError("not a binary glTF (bad magic or first chunk not JSON)")
    doc = json.loads(glb[20:20 + json_length])
    for material in doc.get("materials", []):
        material.setdefault("extensions", {})["KHR_materials_unlit"] = {}
    used = doc.setdefault("extensionsUsed", [])
    if "KHR_materials_unlit" not in used:
        used.append("KHR_materials_unlit")
    text = json.dumps(doc, separators=(",", ":")).encode()
    text += b" " * (-len(text) % 4)
    rest = glb[20 + json_length:]
    total = 12 + 8 + len(text) + len(rest)
    return struct.pack("<III", magic, version, total) + struct.pack("<II", len(text), json_type) + text + rest


def unlit_glb(mesh: Mesh, object_page: Sequence[int], images: Sequence[np.ndarray]) -> bytes:
    """The mesh as binary glTF whose page p shows `images[p]` (uint8 (S, S, 3) display values) unlit."""
    return mark_unlit(export.gltf_bytes(mesh, object_page, [{"baseColorTexture": img} for img in images]))


def pbr_glb(mesh: Mesh, object_page: Sequence[int], pages: dict[str, Sequence[np.ndarray]]) -> bytes:
    """The mesh as binary glTF with PBR materials from file-space pages of albedo, roughness,
    metallic and normal (those present), as scene.glb has them: for relighting in the browser."""
    layers = {m: export.material_layers(m, pages[m], mesh, object_page) for m in pages if m != "irradiance"}
    num_pages = len(next(iter(pages.values())))
    return export.gltf_bytes(mesh, object_page, export.combine_material_layers(layers, num_pages))


# ----------------------------------------------------------------------------- cameras


def rotation_to_wxyz(rotation: np.ndarray) -> np.ndarray:
    """(4,) unit quaternion (w, x, y, z) of a (3, 3) rotation matrix (Shepperd's method)."""
    m = np.asarray(rotation, np.float64)
    trace = np.trace(m)
    if trace > 0:
        s = 2.0 * np.sqrt(trace + 1.0)
        q = [0.25 * s, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s]
    elif m[0, 0] > m[1, 1] and m[0, 0] > m[2, 2]:
        s = 2.0 * np.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2])
        q = [(m[2, 1] - m[1, 2]) / s, 0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s]
    elif m[1, 1] > m[2, 2]:
        s = 2.0 * np.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2])
        q = [(m[0, 2] - m[2, 0]) / s, (m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s]
    else:
        s = 2.0 * np.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1])
        q = [(m[1, 0] - m[0, 1]) / s, (m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s]
    q = np.asarray(q)
    return q / np.linalg.norm(q) * (1.0 if q[0] >= 0 else -1.0)


def vertical_fov(camera: Camera) -> float:
    """The vertical field of view (radians) of the pinhole camera."""
    return float(2.0 * np.arctan(0.5 * camera.height / camera.K[1, 1]))


def up_direction(cameras: Sequence[Camera]) -> np.ndarray:
    """(3,) the scene's up: the cameras' mean up axis (-y of OpenCV camera axes), normalised."""
    up = -np.mean([np.asarray(c.c2w)[:3, 1] for c in cameras], axis=0)
    norm = np.linalg.norm(up)
    return up / norm if norm > 1e-9 else np.array([0.0, 0.0, 1.0])
