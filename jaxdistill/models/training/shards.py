"""The prior's training data on disk: splits and their room seeds, shard files, loading for training.

A shard `room_<seed>.npz` holds one rendered room's views (`room_render.render_room`), all
uint8 (V, H, W, C): photo, albedo, normal, roughness, metallic, irradiance, valid, and a JSON
`meta`. Training rooms use seeds 0, 1, ...; held-out rooms seeds HELDOUT_SEED + i, so the two
splits never share a room. Shards are written atomically (a killed run leaves no half shard).
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np

from jaxdistill.io import images as imageio
from jaxdistill.models.prior import photo_to_model_space
from jaxdistill.models.training.recipe import MAPS

HELDOUT_SEED = 1_000_000
SPLIT_ROOMS = {"train": HELDOUT_SEED, "heldout": 1_000_000}   # indices per split: seeds never overlap


def room_seed(split: str, index: int) -> int:
    """The seed of room `index` of `split`: train i -> i, heldout i -> HELDOUT_SEED + i.
    ValueError for an unknown split or an index outside [0, SPLIT_ROOMS[split])."""
    if split not in SPLIT_ROOMS:
        raise ValueError(f"unknown split {split!r}; use one of {', '.join(SPLIT_ROOMS)}")
    if not (isinstance(index, (int, np.integer)) and 0 <= index < SPLIT_ROOMS[split]):
        raise ValueError(f"room index {index!r} is outside the {split} split's range 0 .. {SPLIT_ROOMS[split] - 1}")
    return (HELDOUT_SEED if split == "heldout" else 0) + int(index)


def write_shard(path: Path, arrays, meta) -> None:
    """Atomic: written to a temporary name, then renamed, so a killed run leaves no half shard."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp.npz")
    np.savez_compressed(tmp, meta=np.frombuffer(json.dumps(meta).encode(), np.uint8), **arrays)
    os.replace(tmp, path)


def read_shard(path: Path):
    """(arrays, meta) of a shard."""
    with np.load(path) as z:
        arrays = {k: z[k] for k in z.files if k != "meta"}
        meta = json.loads(bytes(z["meta"]).decode())
    return arrays, meta


def shard_paths(folder: Path) -> list[Path]:
    """The finished shards `room_*.npz` of `folder`, in seed order (a run's temporary files left out)."""
    return sorted(p for p in Path(folder).glob("room_*.npz") if ".tmp" not in p.name)


def load_images(folder: Path):
    """(photos (N, H, W, 3) in model space, {map: (N, H, W, 3) in model space}, valid (N, H, W)):
    every shard of `folder`, in seed order; model space as `jaxdistill.scene.maps` defines it (albedo
    and irradiance linear, normals unit vectors, grey maps replicated to 3 channels)."""
    shards = shard_paths(folder)
    if not shards:
        raise SystemExit(f"{folder}: no room_*.npz shards; generate them with scripts/make_rgbx_data.py")
    parts = {k: [] for k in ("photo", "valid") + MAPS}
    for path in shards:
        with np.load(path) as z:
            for k in parts:
                parts[k].append(z[k])
    u8 = {k: np.concatenate(v) for k, v in parts.items()}
    photos = np.asarray(photo_to_model_space(u8["photo"].astype(np.float32) / 255))
    maps = {}
    for name in MAPS:
        x = u8[name].astype(np.float32) / 255
        if name in ("albedo", "irradiance"):
            x = imageio.srgb_to_linear(x)
        if x.shape[-1] == 1:
            x = np.repeat(x, 3, -1)
        maps[name] = (2.0 * x - 1.0).astype(np.float32)
    return photos.astype(np.float32), maps, u8["valid"][..., 0] > 0
