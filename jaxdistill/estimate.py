"""Per-view RGB→X estimates: run the full diffusion sampling on photos and write the maps.

    python -m jaxdistill.estimate --prior_dir=RGBX_DIR (--scene=SCENE | --photo=FILE) --out_dir=OUT
        [--maps=albedo,normal,roughness,metallic,irradiance] [--steps=50] [--seed=0]
        [--views=all|NAME,NAME] [--dtype=float32|bfloat16] [--convert_cache=DIR]
        [--mesh=FILE --exposure=auto --uv=auto --max_views=0 ...]   (the main job's dataset flags)

Writes OUT/<map>/<view>.png in the encoding of our scene targets, so that a scene can list them
as per-view targets for the `views` prior: albedo and irradiance sRGB-encoded (the model's
decoded values (x+1)/2 are linear; the authors' demo displays them with x**(1/2.2) instead),
roughness/metallic grey values, normals (n+1)/2 in camera space) and OUT/estimate.json (settings, load and sampling times). Photos:
PNG/JPG are taken as sRGB; EXR photos are clipped to [0, 1] and sRGB-encoded first. Width and
height must be multiples of 8. Noise is seeded per view and map (fold_in of --seed).
"""

from __future__ import annotations

from jaxdistill import huge_pages

if __name__ == "__main__":      # before JAX is imported: glibc reads its tunables at start-up
    huge_pages.run_again_with_huge_pages()

import dataclasses
import json
import time
from pathlib import Path

import jax
import numpy as np
from absl import app, flags, logging
from tqdm import tqdm

from jaxdistill.datasets import ImportOptions
from jaxdistill.engine import config as config_lib
from jaxdistill.io import images as imageio
from jaxdistill.errors import InputError
from jaxdistill.models import convert, prior
from jaxdistill.models.tokenizer import MAP_PROMPTS

FLAGS = flags.FLAGS


def define_flags(fv: flags.FlagValues = FLAGS) -> None:
    """Declares this command's flags (only when run as a command, so that importing this module
    next to other commands, e.g. in tests, declares nothing)."""
    flags.DEFINE_string("prior_dir", None, "RGB↔X folder in diffusers format (zheng95z/rgb-to-x)", flag_values=fv)
    flags.DEFINE_string("scene", None, "scene.json (or its folder), or a dataset read directly as FORMAT:PATH "
                        "(the main job's --scene): estimate every view's photo", flag_values=fv)
    flags.DEFINE_string("photo", None, "a single photo instead of a scene", flag_values=fv)
    flags.DEFINE_string("out_dir", None, "output folder", flag_values=fv)
    flags.DEFINE_list("maps", list(MAP_PROMPTS), "maps to estimate", flag_values=fv)
    flags.DEFINE_integer("steps", 50, "DDIM steps (the authors' demo uses 50)", flag_values=fv)
    flags.DEFINE_integer("seed", 0, "noise seed", flag_values=fv)
    flags.DEFINE_list("views", ["all"], "view names, or 'all'", flag_values=fv)
    flags.DEFINE_enum("dtype", "float32", ["float32", "bfloat16"], "activation dtype of the networks",
                      flag_values=fv)
    flags.DEFINE_string("convert_cache", None, "cache folder for converted weights (faster second load)",
                        flag_values=fv)
    flags.DEFINE_bool("allow_outside_paths", False, "let the scene file name files outside its folder", flag_values=fv)
    config_lib.define_dataset_flags(fv, main_module=True)   # listed by --helpshort with the rest


@dataclasses.dataclass(frozen=True)
class EstimateConfig:
    prior_dir: str
    out_dir: str
    scene: str | None = None
    photo: str | None = None
    maps: tuple[str, ...] = tuple(MAP_PROMPTS)
    steps: int = 50
    seed: int = 0
    views: tuple[str, ...] = ("all",)
    dtype: str = "float32"
    convert_cache: str | None = None
    allow_outside_paths: bool = False
    dataset: ImportOptions = ImportOptions()   # the dataset flags (--scene=FORMAT:PATH); allow_outside_paths: above


def config_from_flags(fv: flags.FlagValues = FLAGS) -> EstimateConfig:
    """The frozen config, with errors naming the flag."""
    for name in ("prior_dir", "out_dir"):
        if not getattr(fv, name):
            raise InputError.single("flags", f"--{name}", "is required")
    if bool(fv.scene) == bool(fv.photo):
        raise InputError.single("flags", "--scene/--photo", "give exactly one of them")
    bad = [m for m in fv.maps if m not in MAP_PROMPTS]
    if bad:
        raise InputError.single("flags", "--maps", f"unknown maps {bad}; choose from {list(MAP_PROMPTS)}")
    if fv.steps < 1:
        raise InputError.single("flags", "--steps", f"must be ≥ 1, got {fv.steps}")
    return EstimateConfig(prior_dir=fv.prior_dir, out_dir=fv.out_dir, scene=fv.scene, photo=fv.photo,
                          maps=tuple(fv.maps), steps=fv.steps, seed=fv.seed, views=tuple(fv.views),
                          dtype=fv.dtype, convert_cache=fv.convert_cache,
                          allow_outside_paths=fv.allow_outside_paths,
                          dataset=config_lib.dataset_options(fv.scene, fv))


def photos_to_estimate(cfg: EstimateConfig) -> list[tuple[str, Path, float]]:
    """(view name, photo path, exposure in stops) selected by the config."""
    if cfg.photo:
        path = Path(cfg.photo)
        if not path.is_file():
            raise InputError.single("flags", "--photo", f"{path} not found")
        return [(path.stem, path, 0.0)]
    from jaxdistill.datasets import open_scene

    scene = open_scene(cfg.scene, dataclasses.replace(cfg.dataset, allow_outside_paths=cfg.allow_outside_paths))
    views = [(v.name, v.photo, v.exposure) for v in scene.views]
    if cfg.views != ("all",):
        names = {n for n, _, _ in views}
        missing = [n for n in cfg.views if n not in names]
        if missing:
            raise InputError.single("flags", "--views", f"{missing} are not views of {cfg.scene}")
        views = [v for v in views if v[0] in cfg.views]
    return views


def run(cfg: EstimateConfig) -> dict:
    """Estimates every selected map of every selected photo; returns the summary it writes."""
    photos = photos_to_estimate(cfg)
    dtype = {"float32": np.float32, "bfloat16": jax.numpy.bfloat16}[cfg.dtype]
    loaded = convert.load_rgbx(cfg.prior_dir, dtype=dtype, cache_dir=cfg.convert_cache, flag="--prior_dir")
    rgbx = prior.load_prior(loaded)
    out = Path(cfg.out_dir)
    key = jax.random.key(cfg.seed)
    seconds = []
    with tqdm(total=len(photos) * len(cfg.maps), desc="RGB→X estimates", unit="map") as bar:
        for name, path, exposure in photos:
            image_latent = prior.encode_photo(rgbx, imageio.read_photo_srgb(path, exposure), str(path))   # c_v, shared by the maps
            for map_name in cfg.maps:
                t0 = time.perf_counter()
                view_key = prior.view_map_key(key, name, map_name)
                # linear values, sRGB-encoded into the PNG: exactly how scene targets are read back
                result = prior.estimate_from_latent(rgbx, image_latent, map_name, view_key, num_steps=cfg.steps,
                                                    gamma=False)
                imageio.write_image(out / map_name / f"{name}.png", result,
                                    encode_srgb=map_name in prior.GAMMA_MAPS)
                seconds.append(time.perf_counter() - t0)
                bar.update()
    summary = {"config": dataclasses.asdict(cfg), "load_seconds": loaded.seconds,
               "seconds_per_map": {"first (with compile)": seconds[0],
                                   "median": float(np.median(seconds[1:] or seconds))},
               "views": [p[0] for p in photos], "backend": jax.default_backend()}
    out.mkdir(parents=True, exist_ok=True)
    (out / "estimate.json").write_text(json.dumps(summary, indent=2))
    logging.info("wrote %d maps to %s", len(seconds), out)
    return summary


def main(argv):
    del argv
    try:
        run(config_from_flags())
    except InputError as err:
        raise app.UsageError(str(err)) from None


if __name__ == "__main__":
    define_flags()
    app.run(main)
