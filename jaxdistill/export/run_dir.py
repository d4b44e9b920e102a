"""What a run keeps beside its outputs so that they can be looked at while it goes on.

`texel_space.npz` in the run's out_dir (written once, before the first step): the level-0 tile
set of the texel space, how far each texel is trusted (`charts.texel_trust`), and the distilled maps. With it, the
texels of any checkpoint become the same file-space map pages that `maps/` holds at the end
(`map_pages`; the final checkpoint's after `as_exported`, which applies the `--anchor` gains the
run recorded in metrics.json), without the scene, the ray casts or the prior.
"""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

import numpy as np

from jaxdistill.export.anchor import anchored_texels
from jaxdistill.errors import InputError
from jaxdistill.scene.maps import MapChannels, model_to_file
from jaxdistill.engine.problem import initial_file_values
from jaxdistill.render.gather_plan import TexelSpace, space_from_tile_set, tile_set_arrays
from jaxdistill.render.sampler import expand, push_pull

TEXEL_SPACE_FILE = "texel_space.npz"


def map_pages(name: str, texels: np.ndarray, channels: MapChannels, space: TexelSpace,
              trust: np.ndarray) -> list[np.ndarray]:
    """File-space pages (S, S, C) of map `name` from model-space texels (N, channels): each
    texel kept as far as `trust` (N,) in [0, 1] says (`charts.texel_trust`: its evidence inside
    the charts), the rest filled from its neighbours by push-pull (`sampler.push_pull`)."""
    values = model_to_file(name, np.asarray(texels)[:, channels.slice(name)])
    pages = expand(values, space, initial_file_values([name])[name], dilation=0)
    weights = expand(np.asarray(trust, np.float32)[:, None], space, 0.0, dilation=0)
    return [push_pull(page, w[..., 0]) for page, w in zip(pages, weights)]


def as_exported(out_dir, texels: np.ndarray, channels: MapChannels, step: int) -> np.ndarray:
    """The texels of the checkpoint at `step` as the finished run exported them: with the
    per-channel gains of `--anchor` (metrics.json `anchor`) applied; unchanged when no finished
    run wrote maps from that step (still running, resumed past it) or the run did not anchor."""
    path = Path(out_dir) / "metrics.json"
    doc = json.loads(path.read_text()) if path.is_file() else {}
    anchor = doc.get("anchor") if doc.get("steps") == step else None
    if not anchor:
        return texels
    gains = {m: np.asarray(g, np.float64) for m, g in anchor["gains"].items()}
    return anchored_texels(texels, gains, channels)


@dataclasses.dataclass(frozen=True)
class TexelSpaceFile:
    """What `texel_space.npz` holds: the level-0 texel space, each texel's trust in the export,
    the distilled maps' channels and the run's recorded flags."""

    space: TexelSpace
    trust: np.ndarray
    channels: MapChannels
    config: dict


def write_texel_space(out_dir, space: TexelSpace, trust: np.ndarray, maps, config: dict) -> Path:
    path = Path(out_dir) / TEXEL_SPACE_FILE
    tmp = path.with_name(path.name + ".tmp.npz")
    np.savez(tmp, **tile_set_arrays(space), trust=np.asarray(trust, np.float32), maps=np.asarray(list(maps)),
             config=np.asarray(json.dumps(config)))
    tmp.replace(path)
    return path


def read_texel_space(out_dir) -> TexelSpaceFile:
    """`write_texel_space`'s file read back; InputError naming the file when it is missing (a
    run not started yet, or made before this file existed)."""
    path = Path(out_dir) / TEXEL_SPACE_FILE
    if not path.is_file():
        raise InputError.single(path, "(file)", "missing: the run has not finished its set-up yet, or was made by "
                                "an older jaxdistill (rerun it to follow it while it runs)")
    with np.load(path) as data:
        arrays = {k: data[k] for k in data.files}
    return TexelSpaceFile(space_from_tile_set(arrays), arrays["trust"].astype(np.float32),
                          MapChannels(tuple(str(m) for m in arrays["maps"])), json.loads(str(arrays["config"])))


def json_safe(value):
    """`value` with NumPy scalars as Python numbers and non-finite floats as None (JSON null)."""
    if isinstance(value, dict):
        return {k: json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [json_safe(v) for v in value]
    if isinstance(value, (np.floating, float)):
        return float(value) if math.isfinite(value) else None
    if isinstance(value, np.integer):
        return int(value)
    return value
