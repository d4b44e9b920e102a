"""Relighting: the room under a new light, rendered with the ground-truth materials and with a run's.

A distilled material is only as good as the pictures it gives under light it was not fitted
to. `relight` removes every light of the scene (sun, sky, emitting objects) and places one
point light inside the room, at `LIGHTS[name]`: fractions of the mesh's axis-aligned bounding
box, away from the walls (or any fractions given). It then path traces the same views twice
with Mitsuba, the same seeds, the same mesh and UVs, every object a `principled` BSDF with
base_color = albedo, roughness and metallic from texture pages and normals from the geometry
(two-sided: a face shades the same from either side, as meshes are not all oriented):

- once with the scene's ground-truth pages (gt.json: albedo, roughness, metallic),
- once with a run's distilled pages (OUT_DIR/maps/<map>/<object>.exr, or the .png when there is
  no EXR; a one-page atlas run's OUT_DIR/maps/<map>.exr serves every object). Export writes
  them as the GT pages are laid out (row 0 at v = 1, texel centres at (c + 0.5) / S), one page per
  object over that object's UVs, at the run's own page size: both map through the mesh's UVs.
  A map the run lacks takes the optimiser's initial value (roughness 1, metallic 0), reported.

Both renders get ONE exposure, Hypersim's rule (`exposure.scene_exposure`) on the GT renders
over the evaluated pixels, are clipped to [0, 1] and sRGB-encoded, and are compared by PSNR per
view over the evaluated pixels (hit, not an excluded emitter, not masked: `evaluation_masks`).
With identical pages the two renders are identical (same samples), so the PSNR is infinite.
"""

from __future__ import annotations

import dataclasses
import math
import time
from pathlib import Path
from typing import Sequence

import numpy as np

from jaxdistill.datasets.mitsuba import bridge as mb
from jaxdistill.evaluate import metrics
from jaxdistill.evaluate.ground_truth import evaluation_masks, read_ground_truth
from jaxdistill.io import images as imageio
from jaxdistill.io.exposure import scene_exposure
from jaxdistill.render import fragments as fr

LIGHTS = {"centre": (0.5, 0.5, 0.5), "offset": (0.55, 0.6, 0.25)}
"""Named light positions, fractions of the mesh's bounding box per axis (x, y, z). 'centre': the
middle of the box (the bedroom, box [0, 4.38] x [0, 2.6] x [0, 3.6] m with the window reveal:
(2.19, 1.30, 1.80) m, 0.7 m above the foot of the bed); 'offset': (2.41, 1.56, 0.90) m in the
bedroom, over the floor between the bed and the door wall, 0.9 m from that wall and 0.6 m above
the chair's back (y is up in the bedroom and the generated rooms)."""
RELIT_MAPS = ("albedo", "roughness", "metallic")
MISSING_MAP_VALUE = {"roughness": 1.0, "metallic": 0.0}   # the optimiser's initial values (maps.INITIAL_VALUE)
LIGHT_INTENSITY = 10.0                                     # W/sr, white; the shared exposure makes it moot


@dataclasses.dataclass
class Relit:
    """Per view: names, GT and run renders (linear, H x W x 3), masks; the shared exposure (stops)."""

    names: list
    gt: list
    run: list
    masks: list
    stops: float
    psnr_db: list
    seconds: dict
    variant: str = ""


def light_position(mesh, light) -> np.ndarray:
    """World position of `light`: a LIGHTS name or 3 fractions of the mesh's bounding box."""
    fractions = LIGHTS[light] if isinstance(light, str) else tuple(float(x) for x in light)
    if len(fractions) != 3 or not all(0.0 < f < 1.0 for f in fractions):
        raise ValueError(f"light: expected a name ({', '.join(LIGHTS)}) or 3 fractions in (0, 1), got {light!r}")
    corners = np.asarray(mesh.vertices, np.float64)
    lo, hi = corners.min(0), corners.max(0)
    return lo + np.asarray(fractions) * (hi - lo)


def parse_light(text: str):
    """--light: a LIGHTS name, or 'fx,fy,fz' fractions of the bounding box."""
    if text in LIGHTS:
        return text
    parts = text.split(",")
    try:
        values = tuple(float(p) for p in parts)
    except ValueError:
        values = ()
    if len(values) != 3:
        raise ValueError(f"--light: expected one of {', '.join(LIGHTS)} or three fractions 'fx,fy,fz', got {text!r}")
    return values


def run_page_files(run_dir, object_names: Sequence[str], name: str) -> list[Path] | None:
    """Per object, the run's page file of map `name` (EXR preferred, else PNG), or None when
    the run has no such map. FileNotFoundError naming the object when only some pages exist."""
    import re

    root = Path(run_dir) / "maps"
    for suffix in (".exr", ".png"):
        single = root / f"{name}{suffix}"
        if single.is_file():
            return [single] * len(object_names)
    if not (root / name).is_dir():
        return None
    out = []
    for obj in object_names:
        stem = re.sub(r"[^A-Za-z0-9._-]", "_", str(obj)).strip(".")
        found = [root / name / f"{stem}{s}" for s in (".exr", ".png") if (root / name / f"{stem}{s}").is_file()]
        if not found:
            raise FileNotFoundError(f"{root / name}: no page for object {obj!r} ({stem}.exr or .png)")
        out.append(found[0])
    return out


def read_run_pages(run_dir, object_names: Sequence[str]) -> tuple[dict, dict]:
    """({map: per object (S, S, C) float32 file-space page} for albedo, roughness, metallic,
    {map: 'exr' | 'png' | 'constant <value>'}) from a finished run's maps/ folder."""
    pages, source = {}, {}
    for name in RELIT_MAPS:
        files = run_page_files(run_dir, object_names, name)
        channels = 3 if name == "albedo" else 1
        if files is None:
            if name == "albedo":
                raise FileNotFoundError(f"{Path(run_dir) / 'maps'}: no albedo pages (maps/albedo/<object>.exr|.png "
                                        "or maps/albedo.exr|.png): is it a finished run's folder?")
            pages[name] = [np.full((1, 1, 1), MISSING_MAP_VALUE[name], np.float32)] * len(object_names)
            source[name] = f"constant {MISSING_MAP_VALUE[name]:g}"
            continue
        cache = {}
        for path in files:
            if path not in cache:
                values = imageio.read_image(path, linear=name == "albedo")
                values = np.repeat(values, 3, -1) if values.shape[-1] == 1 and channels == 3 else values
                cache[path] = np.clip(np.nan_to_num(values[..., :channels]), 0.0, 1.0).astype(np.float32)
        pages[name] = [cache[p] for p in files]
        source[name] = files[0].suffix[1:]
    return pages, source


def relit_scene(mesh, pages: dict, position, *, intensity: float = LIGHT_INTENSITY):
    """The loaded Mitsuba scene: the mesh with principled BSDFs on `pages`, one point light."""
    mi = mb.load_mitsuba()
    shapes = mb.principled_shapes(mesh, pages, two_sided=True)
    return mi.load_dict({"type": "scene", **shapes,
                         "relight_point_light": {"type": "point", "position": [float(x) for x in position],
                                   "intensity": {"type": "rgb", "value": [intensity] * 3}}})


def default_views(count: int, total: int) -> list[int]:
    """`count` view indices evenly spaced over `total` views (all of them when fewer)."""
    if count >= total:
        return list(range(total))
    return sorted({int(round(x)) for x in np.linspace(0, total - 1, count)})


def relight(scene, run_pages: dict, *, views: Sequence[int], light="centre", spp: int = 32, seed: int = 0,
            max_depth: int = 5, progress: bool = False) -> Relit:
    """Renders `views` (indices) of `scene` under the new `light` with the GT pages and with
    `run_pages` (as `read_run_pages` gives), same seeds; the shared exposure and per-view PSNR."""
    from tqdm import tqdm

    gt = read_ground_truth(scene)
    if gt is None or not all(m in gt.pages for m in RELIT_MAPS):
        raise ValueError(f"{scene.root}: relighting needs gt.json pages of {', '.join(RELIT_MAPS)}")
    chosen = [scene.views[i] for i in views]
    cams = [v.camera for v in chosen]
    seconds = {}
    t = time.perf_counter()
    frags = fr.compute_fragments(scene.mesh, cams, cache_dir=False, progress=False)
    sub = dataclasses.replace(scene, views=tuple(chosen))
    masks = evaluation_masks(gt, sub, frags)
    seconds["fragments_s"] = time.perf_counter() - t
    position = light_position(scene.mesh, light)
    previous = mb.load_mitsuba().variant()
    variant = mb.load_mitsuba(mb.llvm_variant()).variant()
    integrator = {"type": "path", "max_depth": int(max_depth)}
    try:
        images = {}
        for key, pages in (("gt", gt.pages), ("run", run_pages)):
            t = time.perf_counter()
            mi_scene = relit_scene(scene.mesh, pages, position)
            out = []
            for i, cam in tqdm(list(zip(views, cams)), desc=f"relight {key} ({spp} spp)", unit="view",
                               disable=not progress):
                out.append(mb.render(mi_scene, cam, spp=spp, seed=seed * 100003 + int(i), integrator=integrator)[..., :3])
            images[key] = out
            seconds[f"render_{key}_s"] = time.perf_counter() - t
    finally:
        mb.load_mitsuba(previous)
    stops = scene_exposure(images["gt"], masks)
    psnr = [relit_psnr(a, b, m, stops) for a, b, m in zip(images["gt"], images["run"], masks)]
    return Relit(names=[v.name for v in chosen], gt=images["gt"], run=images["run"], masks=masks, stops=stops,
                 psnr_db=psnr, seconds=seconds, variant=variant)


def display(linear: np.ndarray, stops: float) -> np.ndarray:
    """sRGB values in [0, 1] of a linear render x 2**stops, clipped."""
    return imageio.linear_to_srgb(np.clip(np.asarray(linear, np.float32) * np.float32(2.0 ** stops), 0.0, 1.0))


def relit_psnr(gt: np.ndarray, run: np.ndarray, mask: np.ndarray, stops: float) -> float:
    """PSNR (dB) of the run's render against the GT render, both exposed by `stops`, clipped and
    sRGB-encoded, over `mask`; capped at metrics.PSNR_CAP_DB (identical renders)."""
    value = metrics.psnr(display(run, stops), display(gt, stops), mask)
    return min(value, metrics.PSNR_CAP_DB) if not math.isnan(value) else value


def summary(result: Relit, *, scene_name: str, run_dir, light, position, spp: int, seed: int, max_depth: int,
            sources: dict) -> dict:
    """The JSON report: settings, per-view and mean PSNR, timings."""
    finite = [p for p in result.psnr_db if not math.isnan(p)]
    return {"scene": scene_name, "run": str(run_dir), "light": light if isinstance(light, str) else list(light),
            "light_position": [round(float(x), 4) for x in position], "light_type": "point",
            "light_intensity": LIGHT_INTENSITY, "spp": spp, "seed": seed, "max_depth": max_depth,
            "variant": result.variant, "exposure_stops": result.stops, "run_maps": sources,
            "psnr_db": dict(zip(result.names, result.psnr_db)),
            "mean_psnr_db": float(np.mean(finite)) if finite else math.nan,
            "seconds": {k: round(v, 2) for k, v in result.seconds.items()}}


def write_figures(folder, result: Relit) -> list[Path]:
    """<view>_gt.png, <view>_run.png (exposed sRGB) and sheet.png (rows: views; columns: GT, run,
    |difference| x 4 in sRGB over the evaluated pixels) into `folder`."""
    folder = Path(folder)
    written, rows = [], []
    for name, a, b, m in zip(result.names, result.gt, result.run, result.masks):
        da, db = display(a, result.stops), display(b, result.stops)
        for tag, image in (("gt", da), ("run", db)):
            path = folder / f"{name}_{tag}.png"
            imageio.write_image(path, image, encode_srgb=False)
            written.append(path)
        diff = np.clip(4.0 * np.abs(da - db), 0.0, 1.0) * m[..., None]
        rows.append(np.concatenate([da, db, diff], axis=1))
    if rows:
        width = max(r.shape[1] for r in rows)
        rows = [np.pad(r, ((0, 0), (0, width - r.shape[1]), (0, 0))) for r in rows]
        path = folder / "sheet.png"
        imageio.write_image(path, np.concatenate(rows, axis=0), encode_srgb=False)
        written.append(path)
    return written
