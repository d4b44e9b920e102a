"""The rgbx prior's own per-view estimates: the baseline a distillation with that model is scored against.

Each view's photo, at the run's render size, sampled by the model with the authors' demo
settings (`jaxdistill.estimate`: 50 DDIM steps, noise per view and map from the seed), in batches of
(map, view) pairs of one size. They are written as scene-target PNGs (the encoding `estimate` writes,
read back by `view_images.read_target`, so the cache can also be listed as a scene's targets for
the `views` prior) into a cache folder keyed by the model's weights, the photos, the size and
the settings: computed once, reused by every run that would compute the same thing.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import time
from pathlib import Path
from typing import Sequence

import jax
import numpy as np
from absl import logging
from tqdm.auto import tqdm

from jaxdistill.io import images as imageio
from jaxdistill.models import prior as rgbx
from jaxdistill.models.layers import FUSED_CUDNN
from jaxdistill.models.shipped import model_info
from jaxdistill.render.fragments import default_cache_dir
from jaxdistill.io.view_images import read_target, resize
from jaxdistill.io.view_rows import LazyViews

ESTIMATE_STEPS = 50          # the authors' demo: weights a user brings
SHIPPED_ESTIMATE_STEPS = 10  # the shipped model's: chosen on the validation rooms (README "The model's own estimates
                             # in 10 steps"), where 50 / 20 / 10 / 5 / 2 steps gave estimates of albedo 14.91 /
                             # 15.07 / 15.26 / 15.59 / 16.18 dB and anchored runs of 17.474 / 17.470 / 17.461 /
                             # 17.443 / 17.411 dB
BATCH = 16                   # (map, view) pairs per sampling call, at least
BATCH_LATENT_PIXELS = 9216   # and up to this many latent pixels a call: 48 at the shipped model's 16 x 12 latents,
                             # where the bedroom's 240 estimates took 0.94x the time of 16 a call
                             # (scripts/bench_estimates.py, docs/benchmarks.md §7)


def default_steps(folder: str | Path | None) -> int:
    """DDIM steps of the model's own estimates when --estimate_steps is 0 (auto): the shipped
    model's `SHIPPED_ESTIMATE_STEPS`, else the demo's 50 (weights a user brings, or a model a user
    trained: nothing was measured for them)."""
    shipped = folder is not None and model_info(folder)["source"] == "shipped"
    return SHIPPED_ESTIMATE_STEPS if shipped else ESTIMATE_STEPS


def batch_size(latent_pixels: int, items: int, cap: int | None = None) -> int:
    """(map, view) pairs per sampling call: as few calls as `cap` pairs a call allows (default: as
    many as fill `BATCH_LATENT_PIXELS` latent pixels, at least `BATCH`), shared evenly, so the last
    call's padding is less than one pair per call; at most `items`."""
    cap = max(cap or max(BATCH, BATCH_LATENT_PIXELS // max(latent_pixels, 1)), 1)
    calls = max(1, -(-items // cap))
    return max(1, -(-items // calls))


def cache_key(model_folder: Path, photos: Sequence[tuple[str, Path, float]], height: int, width: int, steps: int,
              seed: int, dtype: str, attention: str = "chunked") -> str:
    """A digest of what determines the estimates: the weights files (name, size, mtime), each
    photo (name, path, size, mtime, exposure), the size and the sampling settings (the UNet's
    attention only when it is cuDNN's fused one, so keys made before that option stay valid)."""
    settings = {"v": 1, "size": [height, width], "steps": steps, "seed": seed, "dtype": dtype}
    if attention != "chunked":
        settings["attention"] = attention
    h = hashlib.sha256(json.dumps(settings).encode())
    for p in sorted(Path(model_folder).rglob("*")):
        if p.is_file() and p.suffix in (".safetensors", ".json", ".txt"):
            st = p.stat()
            h.update(f"{p.relative_to(model_folder)}:{st.st_size}:{st.st_mtime_ns}".encode())
    for name, path, exposure in photos:
        st = Path(path).stat()
        h.update(f"{name}:{Path(path).resolve()}:{st.st_size}:{st.st_mtime_ns}:{exposure}".encode())
    return h.hexdigest()[:20]


def estimate_views(model: rgbx.RgbxPrior, photos: Sequence[tuple[str, Path, float]], maps: Sequence[str],
                   height: int, width: int, folder: Path, *, steps: int = ESTIMATE_STEPS, seed: int = 0,
                   progress: bool = True, max_batch: int | None = None) -> dict:
    """Writes folder/<map>/<view>.png for every photo (name, path, exposure in stops) resized to
    height x width; returns the summary also written to folder/estimate.json. `max_batch`: at most
    this many (map, view) pairs a sampling call (default `batch_size`'s)."""
    key = jax.random.key(seed)
    factor = model.networks.vae.config.downsampling_factor
    latent_shape = (1, height // factor, width // factor, 4)
    start = time.perf_counter()
    latents = []
    for name, path, exposure in photos:
        photo = resize(imageio.read_photo_srgb(path, exposure), height, width)
        latents.append(rgbx.encode_photo(model, photo, str(path)))
    latents = np.concatenate([np.asarray(x) for x in latents])
    # every (map, view) in batches of one size (the last padded by repeating its last item), each
    # sample with its own prompt: one compiled sampling program per run, whatever the view count
    items = [(m, v) for m in maps for v in range(len(photos))]
    size = batch_size(latent_shape[1] * latent_shape[2], len(items), max_batch)
    with tqdm(total=len(items), desc="model's per-view estimates", unit="map", disable=not progress,
              dynamic_ncols=True) as bar:
        for i in range(0, len(items), size):
            chunk = items[i:i + size]
            padded = chunk + chunk[-1:] * (size - len(chunk))
            noise = np.concatenate([np.asarray(jax.random.normal(rgbx.view_map_key(key, photos[v][0], m), latent_shape))
                                    for m, v in padded])
            images = rgbx.estimate_batch(model, latents[[v for _, v in padded]], [m for m, _ in padded], noise, steps,
                                         gamma=False)
            for (m, v), image in zip(chunk, images):
                imageio.write_image(folder / m / f"{photos[v][0]}.png", image, encode_srgb=m in rgbx.GAMMA_MAPS)
            bar.update(len(chunk))
    summary = {"model": str(model.loaded.folder), "views": [n for n, _, _ in photos], "maps": list(maps),
               "size": [height, width], "steps": steps, "seed": seed,
               "seconds": time.perf_counter() - start}
    (folder / "estimate.json").write_text(json.dumps(summary, indent=1))
    return summary


def compile_ahead(model: rgbx.RgbxPrior, maps: Sequence[str], num_views: int, height: int, width: int, *,
                  steps: int = ESTIMATE_STEPS, max_batch: int | None = None) -> float:
    """Compiles the programs `estimate_views` runs for these sizes (`prior.compile_estimate_batch`,
    and the noise's) and returns the seconds it took. XLA compiles on one core: started in a
    thread while other work runs, it leaves the estimates only their sampling (on the bedroom,
    13 s of their 24-30 s were compilation)."""
    start = time.perf_counter()
    factor = model.networks.vae.config.downsampling_factor
    latent_shape = (1, height // factor, width // factor, 4)
    size = batch_size(latent_shape[1] * latent_shape[2], len(maps) * num_views, max_batch)
    jax.random.normal(rgbx.view_map_key(jax.random.key(0), "", maps[0]), latent_shape).block_until_ready()
    rgbx.compile_estimate_batch(model, [maps[i % len(maps)] for i in range(size)], (size,) + latent_shape[1:], steps)
    return time.perf_counter() - start


def cache_folder(model: rgbx.RgbxPrior, photos: Sequence[tuple[str, Path, float]], height: int, width: int, *,
                 dtype: str = "float32", steps: int = ESTIMATE_STEPS, seed: int = 0,
                 cache_dir: Path | None = None) -> Path:
    """Where `cached_estimates` keeps (or will keep) these estimates."""
    fused = model.loaded.networks.unet.chunk_size == FUSED_CUDNN
    key = cache_key(model.loaded.folder, photos, height, width, steps, seed, dtype, "cudnn" if fused else "chunked")
    return Path(cache_dir or default_cache_dir() / "estimates") / key


def is_cached(model: rgbx.RgbxPrior, photos: Sequence[tuple[str, Path, float]], maps: Sequence[str], height: int,
              width: int, **settings) -> bool:
    """Whether `cached_estimates` with these arguments finds every map in the cache."""
    return _covers(cache_folder(model, photos, height, width, **settings) / "estimate.json", maps)


def _covers(done: Path, maps: Sequence[str]) -> bool:
    """Whether the cache entry whose summary is `done` holds every map of `maps`."""
    return done.is_file() and set(maps) <= set(json.loads(done.read_text())["maps"])


def cached_estimates(model: rgbx.RgbxPrior, photos: Sequence[tuple[str, Path, float]], maps: Sequence[str],
                     height: int, width: int, *, dtype: str = "float32", steps: int = ESTIMATE_STEPS, seed: int = 0,
                     cache_dir: Path | None = None, progress: bool = True) -> Path:
    """The folder of the model's estimates (see `estimate_views`), computed only when the cache
    (`cache_dir`, default `default_cache_dir()/estimates`) lacks them."""
    folder = cache_folder(model, photos, height, width, dtype=dtype, steps=steps, seed=seed, cache_dir=cache_dir)
    done = folder / "estimate.json"
    if _covers(done, maps):
        logging.info("the model's per-view estimates: cached in %s", folder)
        return folder
    # a folder of this process's own, then renamed into place: concurrent runs sharing the cache
    # never see (or write into) a half-written folder
    tmp = folder.with_name(f"{folder.name}.{os.getpid()}.tmp")
    summary = estimate_views(model, photos, maps, height, width, tmp, steps=steps, seed=seed, progress=progress)
    if _covers(done, maps):             # another run finished the same estimates meanwhile: keep those
        shutil.rmtree(tmp)
    else:
        if folder.exists():             # an earlier entry with fewer maps: replaced by this one
            stale = folder.with_name(f"{folder.name}.{os.getpid()}.old")
            folder.replace(stale)
            shutil.rmtree(stale)
        tmp.replace(folder)
    logging.info("the model's per-view estimates: %d views x %d maps in %.0f s, cached in %s", len(photos), len(maps),
                 summary["seconds"], folder)
    return folder


def read_estimates(folder: Path, names: Sequence[str], maps: Sequence[str],
                   shapes: Sequence[tuple[int, int]], lazy: bool = False) -> Sequence[dict]:
    """Per view, the cached estimates in file space (as `evaluation.read_baseline` gives targets),
    resized to `shapes`; a list, or with `lazy` a `LazyViews` reading a view's files when asked for."""
    def load(v: int) -> list[dict]:
        (h, w), name = shapes[v], names[v]
        return [{m: resize(read_target(m, folder / m / f"{name}.png"), h, w) for m in maps}]

    views = LazyViews(len(names), load)
    return views if lazy else list(views)
