"""What the viewer shows, as plain arrays and bytes (no viser here): display images of map and
evidence pages, the unlit glTF that carries them to the browser, and camera poses.

Display encodings of file-space pages (export/pages.py's conventions):
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

from jaxdistill.evaluate import ground_truth as evaluation
from jaxdistill.export import gltf
from jaxdistill.io import images as imageio
from jaxdistill.scene.cameras import Camera
from jaxdistill.scene.model import Mesh

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


# ----------------------------------------------------------------------------- tone mapping

# The browser draws through three.js with ACES filmic tone mapping (viser's renderer sets it; no
# option turns it off), unlit materials included: a texture of sRGB 17/255 would show as 3/255 and
# white as 226/255. Unlit textures are therefore pre-distorted by the curve's inverse, and stored
# divided by TONE_HEADROOM with that as the material's baseColorFactor (three.js multiplies it in),
# so that display values up to `tone_mapped(TONE_HEADROOM)` (sRGB 0.98) come out as they are.
ACES_IN = np.array([[0.59719, 0.35458, 0.04823], [0.07600, 0.90834, 0.01566], [0.02840, 0.13383, 0.83777]])
ACES_OUT = np.array([[1.60475, -0.53108, -0.07367], [-0.10208, 1.10813, -0.00605], [-0.00327, -0.07276, 1.07602]])
TONE_EXPOSURE = 1.0 / 0.6          # three.js: color *= toneMappingExposure / 0.6, exposure 1
TONE_HEADROOM = 4.0


def tone_mapped(linear: np.ndarray) -> np.ndarray:
    """three.js's ACESFilmicToneMapping of linear RGB (..., 3) (what the browser shows, linear)."""
    v = (np.asarray(linear, np.float64) * TONE_EXPOSURE) @ ACES_IN.T
    v = (v * (v + 0.0245786) - 0.000090537) / (v * (0.983729 * v + 0.4329510) + 0.238081)
    return np.clip(v @ ACES_OUT.T, 0.0, 1.0)


def untone_mapped(display: np.ndarray) -> np.ndarray:
    """Linear RGB (..., 3) that `tone_mapped` turns into `display` (sRGB-encoded values in [0, 1]),
    clipped to what [0, TONE_HEADROOM] can reach."""
    target = imageio.srgb_to_linear(np.clip(np.asarray(display, np.float64), 0.0, 1.0))
    t = np.clip(target @ np.linalg.inv(ACES_OUT).T, 0.0, 0.999 / 0.983729)
    a, b, c = 1.0 - 0.983729 * t, 0.0245786 - 0.4329510 * t, -(0.000090537 + 0.238081 * t)
    v = (-b + np.sqrt(b * b - 4.0 * a * c)) / (2.0 * a)
    return np.clip((v @ np.linalg.inv(ACES_IN).T) / TONE_EXPOSURE, 0.0, TONE_HEADROOM)


# ----------------------------------------------------------------------------- glTF


def mark_unlit(glb: bytes, factor: float = 1.0) -> bytes:
    """The binary glTF with every material made KHR_materials_unlit, its base colour texture
    multiplied by `factor` (beyond glTF's [0, 1]; three.js applies it): no lights, no shading."""
    magic, version, _ = struct.unpack_from("<III", glb, 0)
    json_length, json_type = struct.unpack_from("<II", glb, 12)
    if magic != 0x46546C67 or json_type != 0x4E4F534A:
        raise ValueError("not a binary glTF (bad magic or first chunk not JSON)")
    doc = json.loads(glb[20:20 + json_length])
    for material in doc.get("materials", []):
        material.setdefault("extensions", {})["KHR_materials_unlit"] = {}
        material.setdefault("pbrMetallicRoughness", {})["baseColorFactor"] = [factor, factor, factor, 1.0]
    used = doc.setdefault("extensionsUsed", [])
    if "KHR_materials_unlit" not in used:
        used.append("KHR_materials_unlit")
    text = json.dumps(doc, separators=(",", ":")).encode()
    text += b" " * (-len(text) % 4)
    rest = glb[20 + json_length:]
    total = 12 + 8 + len(text) + len(rest)
    return struct.pack("<III", magic, version, total) + struct.pack("<II", len(text), json_type) + text + rest


def unlit_glb(mesh: Mesh, object_page: Sequence[int], images: Sequence[np.ndarray]) -> bytes:
    """The mesh as binary glTF whose page p shows `images[p]` (uint8 (S, S, 3) display values)
    unlit, pre-distorted so that the browser's tone mapping gives them back (`untone_mapped`)."""
    textures = [to_uint8(imageio.linear_to_srgb(untone_mapped(np.asarray(img) / 255.0) / TONE_HEADROOM))
                for img in images]
    return mark_unlit(gltf.gltf_bytes(mesh, object_page, [{"baseColorTexture": t} for t in textures]),
                      TONE_HEADROOM)


def pbr_glb(mesh: Mesh, object_page: Sequence[int], pages: dict[str, Sequence[np.ndarray]]) -> bytes:
    """The mesh as binary glTF with PBR materials from file-space pages of albedo, roughness,
    metallic and normal (those present), as scene.glb has them: for relighting in the browser."""
    layers = {m: gltf.material_layers(m, pages[m], mesh, object_page) for m in pages if m != "irradiance"}
    num_pages = len(next(iter(pages.values())))
    return gltf.gltf_bytes(mesh, object_page, gltf.combine_material_layers(layers, num_pages))


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
