"""Files of a synthetic scene folder: ground-truth pages, gt.json, per-view maps, a preview.

What the embedded bedroom (`scripts/make_bedroom.py`) and the held-out room scenes
(`scripts/make_room_scene.py`) write beside scene.json: the exact GT texture pages as 8-bit PNGs
(read back, so the returned values are what the files decode to), gt.json saying how to evaluate
against them, per-view map images in the scene-target encoding, and preview.jpg. EXR files get a
fixed capture date, so the folders are byte-reproducible.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from jaxdistill.io import images as imageio

EXR_TIMESTAMP = "2026:11:21 00:00:00"   # fixed EXR capDate: files are byte-reproducible
MAP_FILES = {name: ".png" for name in ("albedo", "roughness", "metallic", "normal", "irradiance")}


def write_texture_pages(names, maps, folder: Path) -> dict[str, list[np.ndarray]]:
    """Writes each object's (albedo linear, roughness, metallic) pages as 8-bit PNGs
    folder/<map>/<name>.png (albedo sRGB-encoded) and returns what they decode to:
    albedo (S, S, 3) linear, roughness and metallic (S, S, 1)."""
    gt = {"albedo": [], "roughness": [], "metallic": []}
    for name, (albedo, rough, metal) in zip(names, maps):
        for key, values, srgb in (("albedo", albedo, True), ("roughness", rough, False), ("metallic", metal, False)):
            path = folder / key / f"{name}.png"
            imageio.write_image(path, values, encode_srgb=srgb)
            gt[key].append(imageio.read_image(path, linear=srgb))
    return gt


def write_gt_json(out: Path, names, exclude_objects) -> None:
    """gt.json: the GT pages gt/textures/<map>/<object>.png of `write_texture_pages`, normals from
    the geometry, `exclude_objects` (emitters) out of the metrics."""
    doc = {"format": "jaxdistill-gt", "version": 1,
           "textures": {k: {n: f"gt/textures/{k}/{n}.png" for n in names} for k in ("albedo", "roughness", "metallic")},
           "texture_encoding": {"albedo": "srgb", "roughness": "linear", "metallic": "linear"},
           "normal": "geometry", "exclude_objects": list(exclude_objects), "sampler": "bilinear"}
    (out / "gt.json").write_text(json.dumps(doc, indent=1))


def write_map(path: Path, name: str, values: np.ndarray) -> None:
    """Per-view map files: albedo, irradiance PNG sRGB; roughness, metallic PNG values; normals PNG (n+1)/2."""
    if name in ("albedo", "irradiance"):
        imageio.write_image(path, values)
    elif name == "normal":
        imageio.write_image(path, 0.5 * (values + 1.0), encode_srgb=False)
    else:
        imageio.write_image(path, values, encode_srgb=False)


def write_preview(folder: Path, views=(0, 12, 24, 36)) -> Path:
    """preview.jpg: rows of views, columns photo | albedo | normal | roughness | irradiance targets,
    at half resolution (read back from the written files, so it is deterministic)."""
    doc = json.loads((folder / "scene.json").read_text())
    rows = []
    for i in views:
        if i >= len(doc["views"]):
            continue
        v = doc["views"][i]
        tiles = [imageio.read_image(folder / v["photo"].replace(".exr", ".png"), linear=False)]
        for key in ("albedo", "normal", "roughness", "irradiance"):
            img = imageio.read_image(folder / v["targets"][key], linear=False)
            tiles.append(np.repeat(img, 3, axis=-1) if img.shape[-1] == 1 else img)
        rows.append(np.concatenate([t[::2, ::2, :3] for t in tiles], axis=1))
    path = folder / "preview.jpg"
    imageio.write_image(path, np.concatenate(rows, axis=0), encode_srgb=False, compression="jpeg:85")
    return path
