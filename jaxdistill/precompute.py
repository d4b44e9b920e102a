"""Geometry precompute for a scene: fragments, texture layout, gather plans and visibility.

    python -m jaxdistill.precompute --scene=DIR_OR_scene.json --out_dir=OUT [--texture_size=auto]
        [--max_texture_size=4096] [--sampler=bilinear|trilinear] [--tile_size=0] [--cache_dir=DIR]
        [--mesh=FILE --exposure=auto --uv=auto --max_views=0 ...]   (the main job's dataset flags)

Writes to OUT: `visibility/visibility_<page>_<object>.{exr,png}` (view counts V per texel, the
thesis's Visibility Accumulation Map), `weights/<view>.png` (per-pixel loss weights W, x2 so
that the largest weight 0.5 is white) and `precompute.json` (layout, parameter counts, timings).
Everything is also what the distillation step consumes; this command lets you inspect it.
"""

from __future__ import annotations

from jaxdistill import huge_pages

if __name__ == "__main__":      # before JAX is imported: glibc reads its tunables at start-up
    huge_pages.run_again_with_huge_pages()

import dataclasses
import json
import time
from pathlib import Path

import numpy as np
from absl import app, flags, logging

from jaxdistill.io import images as imageio
from jaxdistill.errors import InputError
from jaxdistill.render import fragments as fr
from jaxdistill.render.gather_plan import SAMPLERS, build_gather_plans, build_texel_space
from jaxdistill.render.layout import make_layout
from jaxdistill.render.visibility import pixel_weights, view_counts, write_visibility_pages
from jaxdistill.datasets import ImportOptions, open_scene
from jaxdistill.engine import config as config_lib

FLAGS = flags.FLAGS


def define_flags(fv: flags.FlagValues = FLAGS) -> None:
    """Declares this command's flags (only when run as a command, so that importing this module
    next to other commands, e.g. in tests, declares nothing)."""
    flags.DEFINE_string("scene", None, "scene.json or the folder holding it, or a dataset read directly as "
                        "FORMAT:PATH (the main job's --scene)", flag_values=fv)
    flags.DEFINE_string("out_dir", None, "where to write visibility images and precompute.json", flag_values=fv)
    flags.DEFINE_string("texture_size", "auto", "page side (power of two) or 'auto' (from the closest view)",
                        flag_values=fv)
    flags.DEFINE_integer("max_texture_size", 4096, "cap for --texture_size=auto", flag_values=fv)
    flags.DEFINE_enum("sampler", "bilinear", list(SAMPLERS), "texture sampler", flag_values=fv)
    flags.DEFINE_integer("tile_size", 0, "parameter tile side (power of two); 0 picks 1 (bilinear) or 16 "
                         "(trilinear)", flag_values=fv)
    flags.DEFINE_string("cache_dir", None, "fragment cache (default $JAXDISTILL_CACHE or ~/.cache/jaxdistill)",
                        flag_values=fv)
    flags.DEFINE_bool("allow_outside_paths", False, "let the scene file name files outside its folder", flag_values=fv)
    config_lib.define_dataset_flags(fv, main_module=True)   # listed by --helpshort with the rest


@dataclasses.dataclass(frozen=True)
class PrecomputeConfig:
    scene: str
    out_dir: str
    texture_size: str = "auto"
    max_texture_size: int = 4096
    sampler: str = "bilinear"
    tile_size: int = 0
    cache_dir: str | None = None
    allow_outside_paths: bool = False
    dataset: ImportOptions = ImportOptions()   # the dataset flags (--scene=FORMAT:PATH); allow_outside_paths: above


def config_from_flags(fv: flags.FlagValues = FLAGS) -> PrecomputeConfig:
    """The frozen config of this command, with flag errors that name the flag."""
    for name in ("scene", "out_dir"):
        if not getattr(fv, name):
            raise InputError.single("flags", f"--{name}", "is required")
    size = fv.texture_size
    if size != "auto" and not (size.isdigit() and int(size) > 0 and int(size) & (int(size) - 1) == 0):
        raise InputError.single("flags", "--texture_size", f"must be 'auto' or a power of two, got {size!r}")
    return PrecomputeConfig(scene=fv.scene, out_dir=fv.out_dir, texture_size=size,
                            max_texture_size=fv.max_texture_size, sampler=fv.sampler,
                            tile_size=fv.tile_size, cache_dir=fv.cache_dir,
                            allow_outside_paths=fv.allow_outside_paths,
                            dataset=config_lib.dataset_options(fv.scene, fv))


def run(config: PrecomputeConfig) -> dict:
    """Runs the precompute and writes its outputs; returns the summary written to precompute.json."""
    out = Path(config.out_dir)
    timings = {}
    start = time.perf_counter()
    options = dataclasses.replace(config.dataset, allow_outside_paths=config.allow_outside_paths)
    scene = open_scene(config.scene, options)
    timings["read_scene_s"] = time.perf_counter() - start
    logging.info("scene %s: %d faces, %d objects, %d views", scene.name, scene.mesh.num_faces,
                 scene.num_objects, len(scene.views))

    start = time.perf_counter()
    frags = fr.compute_fragments(scene.mesh, [v.camera for v in scene.views],
                                 cache_dir=Path(config.cache_dir) if config.cache_dir else None)
    timings["fragments_s"] = time.perf_counter() - start

    start = time.perf_counter()
    trilinear = config.sampler == "trilinear"
    texture_size = config.texture_size if config.texture_size == "auto" else int(config.texture_size)
    layout = make_layout(scene.num_objects, scene.texture_layout, texture_size, frags,
                         max_size=config.max_texture_size, mipmaps=trilinear, tile_size=config.tile_size or None)
    space = build_texel_space(frags, layout, config.sampler)
    timings["texel_space_s"] = time.perf_counter() - start

    start = time.perf_counter()
    counts = np.zeros(space.num_texels, np.int32)
    by_shape: dict[tuple[int, int], list[int]] = {}
    for i, frag in enumerate(frags):
        by_shape.setdefault(frag.shape, []).append(i)
    plans = [build_gather_plans([frags[i] for i in ids], space, config.sampler)  # one per resolution
             for ids in by_shape.values()]
    for plan in plans:
        counts += view_counts(plan, space.num_texels)
    timings["plans_and_counts_s"] = time.perf_counter() - start
    for plan, ids in zip(plans, by_shape.values()):
        weights = np.asarray(pixel_weights(plan, counts))
        for j, i in enumerate(ids):
            imageio.write_image(out / "weights" / f"{scene.views[i].name}.png", 2.0 * weights[j], encode_srgb=False)
    write_visibility_pages(counts, space, out / "visibility", scene.mesh.object_names)

    summary = {
        "scene": scene.name, "faces": scene.mesh.num_faces, "views": len(scene.views),
        "page_sizes": list(layout.page_sizes), "sampler": config.sampler, "tile": layout.tile,
        "parameters": space.num_texels, "full_page_texels": layout.full_size(),
        "observed_texels": int((counts > 0).sum()),
        "hit_fraction": float(np.mean([f.hit.mean() for f in frags])),
        "view_count_histogram": np.bincount(np.minimum(counts, 10), minlength=11).tolist(),
        "timings": timings,
    }
    out.mkdir(parents=True, exist_ok=True)
    (out / "precompute.json").write_text(json.dumps(summary, indent=1))
    logging.info("parameters %d of %d full-page texels (%.1fx fewer); outputs in %s", space.num_texels,
                 layout.full_size(), layout.full_size() / max(space.num_texels, 1), out)
    return summary


def main(argv):
    del argv
    try:
        run(config_from_flags())
    except InputError as err:
        raise app.UsageError(str(err)) from err


if __name__ == "__main__":
    define_flags()
    app.run(main)
