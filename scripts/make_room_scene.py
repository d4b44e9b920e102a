"""Writes a held-out procedural room as a jaxdistill scene folder with exact ground truth.

    python scripts/make_room_scene.py --split=heldout --index=0 --out=DIR [--views=24]
        [--width=128 --height=96] [--spp=64] [--max_depth=5] [--variant=auto]
    python scripts/make_room_scene.py --split=heldout --index=0 --out=DIR --targets_from=ESTIMATE_OUT

The room is `procedural_rooms.random_room(seed)` with seed = `shards.room_seed(split, index)`
(`jaxdistill/models/training/`), rendered exactly as the prior's training data is
(`room_render.render_linear`: the same textures, cameras placed by the same rule, Mitsuba's
`intrinsic_integrator` giving the photo and the irradiance E / pi in one pass, isolated
fireflies removed), but kept linear.
Only held-out rooms (seeds 1_000_000 + index) are written: the training rooms are the prior's
training data. DIR gets:

- `scene.json`, `mesh.glb`: one object (texture page) per room object;
- `photos/<view>.exr`: linear radiance (half float); each view's `exposure` in scene.json is
  the training data's rule (Hypersim's, one value for the room over its valid pixels), so the
  prior sees the photo as it saw its training photos; `photos/<view>.png`: that exposed photo;
- `gt/textures/<map>/<object>.png` + `gt.json`: albedo, roughness, metallic pages (the 8-bit
  values Mitsuba rendered with), normals from the geometry, emitters excluded (as the bedroom);
- `ground_truth/irradiance/<view>.exr`: E / pi, linear, in the photos' units (each view's
  `ground_truth`), so photo = albedo x irradiance on diffuse surfaces;
- `targets/<map>/<view>.png`: stand-ins for a monocular estimator, made as the bedroom's
  (`standins.estimate_view`), parameters in `estimates.json`; or, with `--targets_from`,
  the images `python -m jaxdistill.estimate --scene=DIR --out_dir=ESTIMATE_OUT` wrote
  (ESTIMATE_OUT/<map>/<view>.png; referenced in place when inside DIR, else copied to
  DIR/estimates/). On a folder this script already made with the same settings,
  `--targets_from` only relinks the targets (no rendering);
- `room.json` (settings, seed, exposure, consistency, times), `README.md`, `preview.jpg`.

Deterministic from (split, index) and the settings (same versions and platform).
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import shutil
import sys
import time
from pathlib import Path

import numpy as np

from jaxdistill import MAP_NAMES
from jaxdistill.evaluate.consistency import (DIFFUSE_COSINE, DIFFUSE_ROUGHNESS, consistency, diffuse_mask,  # noqa: F401
                                             view_cosine)
from jaxdistill.datasets.mitsuba import bridge as mb
from jaxdistill.evaluate import metrics
from jaxdistill.io import exposure, images as imageio
from jaxdistill.models.training.room_render import render_linear
from jaxdistill.models.training.scene_files import (EXR_TIMESTAMP, MAP_FILES, write_gt_json, write_map, write_preview,
                                                    write_texture_pages)
from jaxdistill.models.training.shards import room_seed
from jaxdistill.models.training.standins import estimate_view
from jaxdistill.scene.model import Scene, View, read_scene, write_scene

ROOM_FILE = "room.json"
ROOM_FORMAT = "jaxdistill-room-scene"
SETTINGS = ("split", "index", "views", "width", "height", "spp", "max_depth")
# ----------------------------------------------------------------------------- generation


def generate(out: Path, settings: dict, command: str) -> dict:
    """Renders the room and writes the scene folder (stand-in targets); returns room.json's content."""
    seed = room_seed(settings["split"], settings["index"])
    times = {}
    t0 = time.perf_counter()
    r = render_linear(seed, views=settings["views"], width=settings["width"], height=settings["height"],
                      spp=settings["spp"], max_depth=settings["max_depth"], progress=True)
    times["render_s"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    names = [f"view_{i:03d}" for i in range(len(r.cameras))]
    objects = r.mesh.object_names
    pages = write_texture_pages(objects, zip(r.textures["albedo"], r.textures["roughness"], r.textures["metallic"]),
                                out / "gt" / "textures")
    for key, values in pages.items():           # the PNGs decode to exactly what Mitsuba rendered with
        worst = max(float(np.abs(a - b).max()) for a, b in zip(values, r.textures[key]))
        if worst > 1e-6:
            raise RuntimeError(f"GT {key} pages differ from the rendered textures by {worst}")
    emitters = [objects[k] for k in r.emitter_ids]
    write_gt_json(out, objects, emitters)
    valid = [v[..., 0] for v in r.gt["valid"]]
    stops = exposure.scene_exposure(r.photos, valid)

    views, params, baseline = [], {}, []
    for i, (name, cam, photo, irr) in enumerate(zip(names, r.cameras, r.photos, r.irradiance)):
        imageio.write_image(out / "photos" / f"{name}.exr", photo, half=True, timestamp=EXR_TIMESTAMP)
        imageio.write_image(out / "photos" / f"{name}.png", np.clip(exposure.apply_exposure(photo, stops), 0, 1))
        imageio.write_image(out / "ground_truth" / "irradiance" / f"{name}.exr", irr, timestamp=EXR_TIMESTAMP)
        gt = {k: r.gt[k][i] for k in ("albedo", "normal", "roughness", "metallic")}
        est, params[name] = estimate_view(np.random.default_rng([seed, i]), gt, photo, valid[i])
        baseline.append(metrics.evaluate_view({k: est[k] for k in gt}, gt, valid[i]))
        targets = {}
        for key, values in est.items():
            targets[key] = out / "targets" / key / f"{name}{MAP_FILES[key]}"
            write_map(targets[key], key, values)
        views.append(View(name=name, camera=cam, photo=out / "photos" / f"{name}.exr", targets=targets,
                          exposure=stops, ground_truth={"irradiance": out / "ground_truth" / "irradiance" / f"{name}.exr"}))
    write_scene(Scene(name=f"room_{seed}", mesh=r.mesh, views=tuple(views), texture_layout="pages"), out)
    (out / "estimates.json").write_text(json.dumps({"seed": seed, "model": "standins.estimate_view",
                                                    "views": params}, indent=1))
    dielectric = [v & (r.gt["metallic"][i][..., 0] == 0) for i, v in enumerate(valid)]
    diffuse = [diffuse_mask(v, r.gt["roughness"][i], r.gt["metallic"][i], view_cosine(cam, r.gt["normal"][i]))
               for i, (v, cam) in enumerate(zip(valid, r.cameras))]
    check = {"diffuse": consistency(r.photos, r.gt["albedo"], r.irradiance, diffuse),
             "dielectric": consistency(r.photos, r.gt["albedo"], r.irradiance, dielectric),
             "all_valid": consistency(r.photos, r.gt["albedo"], r.irradiance, valid)}
    times["write_s"] = time.perf_counter() - t0
    room = r.room
    return {"format": ROOM_FORMAT, "version": 1, **settings, "seed": seed, "variant": mb.load_mitsuba().variant(),
            "command": command, "room_size": [round(float(x), 3) for x in room.size], "objects": len(objects),
            "faces": int(r.mesh.num_faces), "emitters": emitters, "sun": room.sun_irradiance is not None,
            "sky": room.sky_radiance is not None, "exposure_stops": stops,
            "valid_fraction": float(np.mean([v.mean() for v in valid])), "consistency": check,
            "standin_baseline": metrics.aggregate(baseline), "targets": {"source": "stand-ins", "maps": list(MAP_FILES)},
            "times": {k: round(v, 1) for k, v in times.items()}}


# ----------------------------------------------------------------------------- targets from estimates


def link_targets(out: Path, source: Path) -> dict:
    """Points every view's targets at ESTIMATE_OUT/<map>/<view>.png for the maps it has (in place
    when it lies inside `out`, else copied to out/estimates/); returns room.json's `targets`.
    ValueError naming what is missing."""
    source = source.resolve()
    doc = json.loads((out / "scene.json").read_text())
    names = [v["name"] for v in doc["views"]]
    maps = [m for m in MAP_NAMES if (source / m).is_dir()]
    if not maps:
        raise ValueError(f"{source}: no map folders ({', '.join(MAP_NAMES)}); expected the output of "
                         f"python -m jaxdistill.estimate --scene={out} --out_dir={source}")
    missing = [f"{m}/{n}.png" for m in maps for n in names if not (source / m / f"{n}.png").is_file()]
    if missing:
        raise ValueError(f"{source}: {len(missing)} estimates missing, e.g. {', '.join(missing[:4])}")
    inside = out.resolve() in source.parents
    copied = out / "estimates"
    if not inside:
        shutil.rmtree(copied, ignore_errors=True)
    for entry in doc["views"]:
        targets = {}
        for m in maps:
            path = source / m / f"{entry['name']}.png"
            if not inside:
                (copied / m).mkdir(parents=True, exist_ok=True)
                path = Path(shutil.copyfile(path, copied / m / path.name))
            targets[m] = os.path.relpath(path, out.resolve()).replace(os.sep, "/")
        entry["targets"] = targets
    tmp = out / "scene.json.tmp"
    tmp.write_text(json.dumps(doc, indent=1))
    os.replace(tmp, out / "scene.json")
    read_scene(out)                    # sizes, channels and paths of the new targets are valid
    return {"source": os.fspath(source), "maps": maps, "copied_to": "estimates/" if not inside else None}


# ----------------------------------------------------------------------------- README


def readme(info: dict) -> str:
    c, t = info["consistency"], info["times"]
    d, e, a = c["diffuse"], c["dielectric"], c["all_valid"]
    lights = ", ".join(x for x in ("sun" if info["sun"] else "", "sky" if info["sky"] else "",
                                   f"{len(info['emitters'])} emitting objects" if info["emitters"] else "") if x)
    targets = info["targets"]
    if targets["source"] == "stand-ins":
        target_text = ("stand-ins for a monocular estimator, made as the bedroom's (`standins.estimate_view`: "
                       "GT corrupted by gain, shading leak, blur, noise, offsets, tilted normals; parameters in "
                       "`estimates.json`). They are not a learned model's estimates. Replace them with\n\n"
                       f"    python -m jaxdistill.estimate --prior_dir=... --scene=DIR --out_dir=ESTIMATE_OUT\n"
                       f"    {info['command']} --targets_from=ESTIMATE_OUT")
    else:
        where = f"copied to `{targets['copied_to']}`" if targets["copied_to"] else "referenced in place"
        target_text = (f"a model's estimates from `{targets['source']}` ({', '.join(targets['maps'])}; {where}); "
                       "the stand-ins of `targets/` and `estimates.json` are no longer referenced")
    base = info["standin_baseline"]
    rows = "\n".join(f"| {k} | {v:.4g} |" for k, v in base.items() if k != "num_views")
    return f"""# Held-out procedural room {info['index']} (seed {info['seed']})

`procedural_rooms.random_room({info['seed']})`, the generator of the prior's training data
(`make_rgbx_data.py`; its `--split={info['split']}` room {info['index']}, never a training room):
{info['objects']} objects, {info['faces']} triangles, room {' x '.join(f'{x:g}' for x in info['room_size'])} m,
light: {lights}. {info['views']} views of {info['width']}x{info['height']}, path traced by Mitsuba 3
(`{info['variant']}`, `room_render.render_linear`: intrinsic integrator, max depth {info['max_depth']},
{info['spp']} spp, box pixel filter, isolated fireflies removed), photo and irradiance E/pi in one pass.

    {info['command']}

Rendering took {t['render_s']:.0f} s, writing {t['write_s']:.0f} s (2 shared CPU cores).

![exposed photo and the albedo, normal, roughness, irradiance targets of four views](preview.jpg)

## Files
- `scene.json`, `mesh.glb`: the scene (one texture page per object); each view's `exposure`
  ({info['exposure_stops']:+.4f} stops) is the training data's rule (Hypersim's, one value for the room).
- `photos/<view>.exr` linear radiance (half float), `photos/<view>.png` the exposed photo (sRGB).
- `gt.json` + `gt/textures/<map>/<object>.png`: albedo (sRGB), roughness, metallic pages, the
  values Mitsuba rendered with; normals from the geometry; emitters excluded
  ({', '.join(info['emitters']) or 'none'}).
- `ground_truth/irradiance/<view>.exr`: E/pi, linear, in the photos' units (each view's `ground_truth`).
- targets (the `views` prior's per-view inputs): {target_text}
- `room.json`: settings, seed, exposure, the figures below.

## Ground truth self-consistency
photo = albedo x irradiance (x 2^exposure on both sides) on diffuse pixels: valid (fully covered,
not an emitter), metallic 0, roughness >= {DIFFUSE_ROUGHNESS}, seen within about 30 degrees of the
normal (cosine >= {DIFFUSE_COSINE}); albedo supersampled 2x2 like the photo's pixel box. Per-pixel
brightness ratio photo / (albedo x irradiance) over {d['pixels']} pixels: median **{d['median_ratio']:.3f}**
(10th-90th percentile {d['p10']:.3f}-{d['p90']:.3f}; Monte Carlo noise of both at {info['spp']} spp), ratio of sums {d['sum_ratio']:.3f}.

The materials are Mitsuba's `principled` BSDF, which is not Lambertian: its (Disney) diffuse
lobe brightens rough surfaces where the view or the light is grazing (walls lit by a ceiling
panel) and darkens smooth ones, and dielectrics add a specular lobe; so the figure is not 1 to
the Monte Carlo noise as for Lambertian scenes (staircase2: 0.996; the integrator's own test: a
Lambertian plane within 3 %). Over all {e['pixels']} valid dielectric pixels the median is
{e['median_ratio']:.3f} (ratio of sums {e['sum_ratio']:.3f}); over all {a['pixels']} valid pixels, metals
included, {a['median_ratio']:.3f}. The same holds for the training data, rendered by the same code.

## Stand-in targets against GT (mean over views, valid pixels, supersampled GT)

| metric | value |
|---|---|
{rows}
"""


def finish(out: Path, info: dict) -> None:
    (out / ROOM_FILE).write_text(json.dumps(info, indent=1))
    n = info["views"]
    doc = json.loads((out / "scene.json").read_text())
    if all(m in v.get("targets", {}) for v in doc["views"] for m in ("albedo", "normal", "roughness", "irradiance")):
        write_preview(out, views=sorted({0, n // 4, n // 2, 3 * n // 4}))
    (out / "README.md").write_text(readme(info))


# ----------------------------------------------------------------------------- main


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--split", choices=("train", "heldout"), default="heldout")
    parser.add_argument("--index", type=int, required=True, help="room index in the split (seed 1_000_000 + index)")
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--views", type=int, default=24)
    parser.add_argument("--width", type=int, default=128)
    parser.add_argument("--height", type=int, default=96)
    parser.add_argument("--spp", type=int, default=64)
    parser.add_argument("--max_depth", type=int, default=5, help="path length of the photo and the irradiance's rays")
    parser.add_argument("--variant", choices=("auto", "llvm_ad_rgb", "scalar_rgb"), default="auto")
    parser.add_argument("--targets_from", type=Path, help="folder OUT/<map>/<view>.png of jaxdistill.estimate")
    args = parser.parse_args(argv)
    if args.split != "heldout":
        parser.error("--split=train: training rooms are the prior's training data; scenes are made of held-out rooms only")
    try:
        room_seed(args.split, args.index)
    except ValueError as err:
        parser.error(f"--index: {err}")
    for name in ("views", "spp", "max_depth"):
        if getattr(args, name) < 1:
            parser.error(f"--{name} must be >= 1, got {getattr(args, name)}")
    for name in ("width", "height"):
        value = getattr(args, name)
        if value < 8 or value % 8:
            parser.error(f"--{name} must be a positive multiple of 8 (the prior's VAE), got {value}")
    if args.targets_from is not None and not args.targets_from.is_dir():
        parser.error(f"--targets_from: {args.targets_from} is not a folder")
    settings = {k: getattr(args, k) for k in SETTINGS}
    words = ["--" + f"{k}={getattr(args, k)}" for k in SETTINGS] + [f"--out={args.out}"]
    command = "python scripts/make_room_scene.py " + " ".join(shlex.quote(w) for w in words)

    out = args.out
    previous = None
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        marker = out / ROOM_FILE
        if not marker.is_file():
            parser.error(f"--out: {out} exists and is not a scene this script made (no {ROOM_FILE}); "
                         "give a new or empty folder")
        previous = json.loads(marker.read_text())
    start = time.perf_counter()
    if previous is not None and args.targets_from is not None and all(previous.get(k) == v for k, v in settings.items()):
        info = previous                          # same room, same renders: relink the targets only
    else:
        if previous is not None:
            shutil.rmtree(out)
        mb.load_mitsuba(mb.llvm_variant() if args.variant == "auto" else args.variant)
        print(f"room {args.split} {args.index} (seed {room_seed(args.split, args.index)}): {args.views} views at "
              f"{args.width}x{args.height}, {args.spp} spp, Mitsuba {mb.load_mitsuba().variant()} -> {out}")
        out.mkdir(parents=True, exist_ok=True)
        info = generate(out, settings, command)
    if args.targets_from is not None:
        try:
            info["targets"] = link_targets(out, args.targets_from)
        except ValueError as err:
            print(f"--targets_from: {err}", file=sys.stderr)
            return 2
    finish(out, info)
    d = info["consistency"]["diffuse"]
    print(f"photo / (albedo x irradiance) on {d['pixels']} diffuse pixels: median {d['median_ratio']:.3f} "
          f"(p10 {d['p10']:.3f}, p90 {d['p90']:.3f}), ratio of sums {d['sum_ratio']:.3f}; all valid pixels: median "
          f"{info['consistency']['all_valid']['median_ratio']:.3f}, dielectric {info['consistency']['dielectric']['median_ratio']:.3f}")
    print(f"targets: {info['targets']['source']}; wrote {out} in {time.perf_counter() - start:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
