"""An LDR copy of a scene: its photos as a phone or any 8-bit capture would give them.

`write_ldr_scene(source, out)` writes a self-contained copy of a scene folder in which every
view's photo is the source's linear photo x 2**exposure (the view's stops, as the prior sees it),
clipped to [0, 1], sRGB-encoded and quantised into an 8-bit PNG, `photos/<view>.png`, with
`exposure` 0. Everything else the scene names is copied unchanged to the same relative path:
the mesh (or the `meshes` files), the views' masks, targets and ground_truth images, gt.json and
its texture pages; so the copy is scored exactly like the original. Files the source names
outside its folder (read with allow_outside_paths) are copied under `external/`. `ldr.json`
records the source and the share of clipped pixels per view.

With `exposure_jitter` and `white_balance_jitter` the copy is what a phone's auto-exposure and
auto white balance make of the room: view v's linear photo is multiplied by
2**(exposure + e_v) · w_v before the clip, e_v uniform in ±exposure_jitter stops and w_v per
channel exp(n_vc − mean_c n_vc), n_vc normal with standard deviation white_balance_jitter (a
colour cast that keeps the brightness), drawn from `seed`; `ldr.json` records e_v and w_v.

What the copy loses is what an LDR capture loses: highlights and lights above 1 after the
exposure clip (`view_images.read_photo_linear` drops pixels at 255 from the photo losses), and
the darks quantise to a few sRGB codes.
"""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import numpy as np

from jaxdistill.errors import read_json
from jaxdistill.io import images as imageio
from jaxdistill.scene.model import read_scene
from jaxdistill.scene.paths import is_inside

FORMAT = "jaxdistill-ldr-copy"
PHOTO_FOLDER = "photos"


def ldr_photo(linear: np.ndarray, exposure: float, gains=None) -> np.ndarray:
    """(H, W, 3) uint8 sRGB codes of a linear photo x 2**exposure (x per-channel `gains`, the white
    balance, when given), clipped to [0, 1] (round to nearest)."""
    scale = np.float32(2.0 ** exposure) * (np.ones(3, np.float32) if gains is None else np.asarray(gains, np.float32))
    exposed = np.clip(np.nan_to_num(np.asarray(linear, np.float32)[..., :3], nan=0.0, posinf=1.0, neginf=0.0)
                      * scale, 0.0, 1.0)
    return np.round(imageio.linear_to_srgb(exposed) * 255.0).astype(np.uint8)


class _Copier:
    """Copies files named relative to `source` into `out` at the same relative path (files
    outside `source` go under external/) and returns their new relative names; each file once."""

    def __init__(self, source: Path, out: Path):
        self.source, self.out, self.done = source, out, {}

    def __call__(self, value: str) -> str:
        path = self.source / value
        real = os.path.realpath(path)
        if real in self.done:
            return self.done[real]
        if is_inside(path, self.source):
            name = Path(os.path.relpath(real, os.path.realpath(self.source))).as_posix()
        else:
            name = f"external/{len(self.done):04d}_{Path(real).name}"
        target = self.out / name
        target.parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(real, target)
        self.done[real] = name
        return name


def camera_jitter(num_views: int, exposure_jitter: float, white_balance_jitter: float,
                  seed: int) -> tuple[np.ndarray, np.ndarray]:
    """((V,) exposure offsets in stops, uniform in ±exposure_jitter; (V, 3) white-balance gains
    exp(n − mean_c n), n normal with standard deviation white_balance_jitter), from `seed`."""
    rng = np.random.default_rng(seed)
    offsets = rng.uniform(-exposure_jitter, exposure_jitter, num_views) if exposure_jitter > 0 else np.zeros(num_views)
    n = rng.normal(0.0, white_balance_jitter, (num_views, 3)) if white_balance_jitter > 0 else np.zeros((num_views, 3))
    return offsets, np.exp(n - n.mean(axis=1, keepdims=True))


def write_ldr_scene(source, out, *, allow_outside_paths: bool = False, exposure_jitter: float = 0.0,
                    white_balance_jitter: float = 0.0, seed: int = 0) -> Path:
    """Writes the LDR copy of the scene at `source` (scene.json or its folder) into the new or
    empty folder `out`; returns the new scene.json's path. With `exposure_jitter` (stops) or
    `white_balance_jitter` (log-gain standard deviation) each view gets its own random exposure
    and white balance (`camera_jitter`, from `seed`). ValueError when `out` is not empty, a
    jitter is negative or not finite, or a copied file would land where an LDR photo goes."""
    for name, value in (("exposure_jitter", exposure_jitter), ("white_balance_jitter", white_balance_jitter)):
        if not np.isfinite(value) or value < 0:
            raise ValueError(f"{name} is {value}: give a finite value >= 0")
    scene = read_scene(source, allow_outside_paths=allow_outside_paths)
    root = Path(scene.root)
    out = Path(out)
    if out.exists() and any(out.iterdir()):
        raise ValueError(f"{out} is not empty: give a new or empty folder")
    if os.path.realpath(out) == os.path.realpath(root):
        raise ValueError("the LDR copy must go to another folder than the scene's")
    out.mkdir(parents=True, exist_ok=True)
    doc = read_json(root / "scene.json", "missing")
    copy = _Copier(root, out)
    if "mesh" in doc:
        doc["mesh"] = copy(doc["mesh"])
    for entry in doc.get("meshes", []) or []:
        if isinstance(entry, dict) and "file" in entry:
            entry["file"] = copy(entry["file"])
    photos = {}
    for entry, view in zip(doc["views"], scene.views):
        if entry.get("mask") is not None:
            entry["mask"] = copy(entry["mask"])
        for key in ("targets", "ground_truth"):
            if isinstance(entry.get(key), dict):
                entry[key] = {name: copy(value) for name, value in entry[key].items()}
        photos[view.name] = f"{PHOTO_FOLDER}/{view.name}.png"
    gt_path = root / "gt.json"
    if gt_path.is_file():
        gt = read_json(gt_path, "missing")
        if isinstance(gt, dict) and isinstance(gt.get("textures"), dict):
            gt["textures"] = {m: {o: copy(p) for o, p in per_object.items()} for m, per_object in gt["textures"].items()}
        (out / "gt.json").write_text(json.dumps(gt, indent=1))
    clash = sorted(set(photos.values()) & set(copy.done.values()))
    if clash:
        shutil.rmtree(out)
        raise ValueError(f"files of the scene lie where the LDR photos go ({', '.join(clash[:3])}): copy by hand")
    record = {"format": FORMAT, "version": 1, "source": scene.name, "source_views": len(scene.views),
              "rule": "sRGB(clip(linear photo x 2**(exposure + exposure_offset) x white_balance, 0, 1)) as "
                      "8-bit PNG, exposure 0",
              "exposure_jitter": float(exposure_jitter), "white_balance_jitter": float(white_balance_jitter),
              "seed": int(seed), "views": {}}
    offsets, balance = camera_jitter(len(scene.views), exposure_jitter, white_balance_jitter, seed)
    for v, (entry, view) in enumerate(zip(doc["views"], scene.views)):
        linear = imageio.read_image(view.photo)
        codes = ldr_photo(linear, view.exposure + offsets[v], balance[v])
        imageio.write_image(out / photos[view.name], codes.astype(np.float32) / 255.0, encode_srgb=False)
        entry["photo"] = photos[view.name]
        entry["exposure"] = 0.0
        record["views"][view.name] = {"source_exposure": float(view.exposure),
                                      "exposure_offset": round(float(offsets[v]), 6),
                                      "white_balance": [round(float(g), 6) for g in balance[v]],
                                      "clipped_fraction": round(float(np.mean(np.any(codes == 255, axis=-1))), 5),
                                      "black_fraction": round(float(np.mean(np.all(codes == 0, axis=-1))), 5)}
    tmp = out / "scene.json.tmp"
    tmp.write_text(json.dumps(doc, indent=1))
    os.replace(tmp, out / "scene.json")
    (out / "ldr.json").write_text(json.dumps(record, indent=1))
    return out / "scene.json"
