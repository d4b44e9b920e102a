"""Import a Mitsuba 3 scene as a jaxdistill scene with exact per-view ground truth.

Mitsuba 0.5/0.6 files (root `version` below 2, as Bitterli's Rendering Resources ship them) are
upgraded to Mitsuba 3 first by `jaxdistill.datasets.mitsuba.upgrade`; the changes are logged and the
upgraded XML is written to the output folder as `<stem>.mitsuba3.xml`.

`prepare_scene(xml, out_dir, num_views=..., width=..., height=..., spp=...)` (this module: the
orchestration and the files written; each step's code is in `source.py` (1), `materials.py` (2),
`shapes.py` (3), `views.py` (4), `ground_truth.py` (5, 6) and `bridge.py` (7)) does, in order:

1. **Load** the XML with `mi.load_file(optimize=False)` (optimisation would merge shapes that
   share a BSDF), in the `scalar_rgb` variant. Every shape becomes one object of our Mesh, named
   by its Mitsuba id (`<type>_<index>` when it has none). Meshes (obj, ply, serialized, cube,
   ...) give world-space `vertex_positions`, `faces`, `vertex_texcoords` and `vertex_normals`
   through `mi.traverse`. A `rectangle` is a two-triangle mesh in recent Mitsuba 3 (3.9 here)
   and is read through the shape's own accessors (older versions: built here from `to_world`,
   [-1, 1]^2 in xy, uv = (xy + 1) / 2); `disk`, `sphere` and `cylinder` are tessellated here from
   their `to_world` (unit disk in xy / unit sphere / unit open cylinder z in [0, 1]), and their
   original UVs are evaluated analytically at the hit point with Mitsuba's formulas, so they
   stay exact although the tessellation is not. Shapes whose BSDF is `null` are left out (they
   are invisible in the photos); emitters and glass (`dielectric`, `thindielectric`,
   `roughdielectric`) stay in the geometry, since they occlude, but are masked out of the
   ground truth.
2. **Ground-truth materials** (`twosided` is unwrapped to its front BSDF; `principled`,
   `diffuse`, `plastic`, `roughplastic`, `conductor`, `roughconductor`; `mask`, as for foliage:
   its nested BSDF's maps, and pixels where its opacity is below 0.5 masked): see `material_of`.
   Constants and textures of any Mitsuba type are evaluated by Mitsuba itself
   (`Texture.eval` at the original UV), so bitmaps get Mitsuba's own wrap mode, filter and
   sRGB decoding. Unsupported plugins raise one InputError listing every (shape, plugin).
3. **Reconstruction UVs**: an object keeps its UVs when they lie in [0, 1], are not collapsed
   (faces with zero UV area over > 1 % of its surface) and do not overlap (rasterised at
   256^2: < 2 % of covered texels covered twice); otherwise (and always for the tessellated
   analytic shapes) it is re-unwrapped with xatlas, 2-texel padding, for about a 1024^2 page
   (the rules are those of `jaxdistill.render.unwrap`). Layout "pages": one page per object.
4. **Views**: seeded random eyes inside the bounding box of the unmasked geometry (shrunk by
   5 %), kept when 26 probe rays mostly hit, none is closer than a clearance (1 % of the scene
   diagonal) and they see >= 3 distinct objects (inside a closed object they see only it);
   look-at targets are visible random surface points (area-weighted) with a pitch within
   +-50 deg; a 64-pixel-wide preview must be >= 90 % hits, >= 50 % unmasked, with a median
   depth >= 2 clearances. Views are then chosen greedily for surface coverage: a candidate
   earns the surface area it sees (per face, capped at the face area), halved per earlier view
   that saw that face. Horizontal fov uniform in [60, 75] deg, square pixels, principal point
   off-centre by up to 3 % of the image size.
5. **Ground truth per view** in image space: our rays (`compute_fragments` on the
   reconstruction mesh, the same triangles as Mitsuba's) give triangle id and barycentrics;
   the ORIGINAL texcoords of that triangle are interpolated and the material evaluated there,
   so the maps are exact whatever the new layout.
6. **Irradiance** per view (`render_irradiance`): E / pi at each pixel centre's first hit,
   the radiance a white Lambertian surface would reflect there under the scene's own light
   (original materials everywhere else), `spp` samples, in Mitsuba's `llvm_ad_rgb` variant.
   Written as ground truth (HDR) and, scaled by one scene-wide factor into [0, 1], as targets.
7. **Photos**: Mitsuba path traces each view (the scene's own integrator, `spp` samples,
   seed = seed + view index) through `mitsuba_bridge.render`.

scene.json is complete: every view has targets and ground truth for all five maps and its
mask. Conventions of the files written (also in the `import.json` and README.md written beside
scene.json): photos linear EXR + sRGB PNG; targets/albedo linear RGB EXR; roughness and
metallic single-channel EXR; normal = camera-space unit normal as RGB↔X uses it (x right,
y up, z towards the camera), flipped to face the camera, stored as (n + 1) / 2; albedo,
roughness and metallic are 0 outside the mask; masks/<view>.png is 1 where a ray hits a
surface that is neither an emitter nor glass nor cut out (mask BSDF opacity < 0.5). Roughness
is perceptual: GGX alpha = roughness^2, so roughness = sqrt(alpha) (sqrt of the geometric mean
for anisotropic alpha_u, alpha_v).
"""

from __future__ import annotations

import json
import logging
import os
import time
from pathlib import Path

import numpy as np
from tqdm.auto import tqdm

from jaxdistill.datasets.mitsuba import bridge as mb
from jaxdistill.datasets.mitsuba.ground_truth import (IRRADIANCE_VARIANT, GroundTruthEvaluator, irradiance_mitsuba,
                                                      irradiance_target_scale, render_irradiance)
from jaxdistill.datasets.mitsuba.shapes import reconstruction_mesh
from jaxdistill.datasets.mitsuba.source import MitsubaSource, load_source
from jaxdistill.datasets.mitsuba.views import place_views
from jaxdistill.errors import ProblemList
from jaxdistill.io import exposure as exposure_rule
from jaxdistill.io import images as imageio
from jaxdistill.render import fragments as fr
from jaxdistill.scene.model import Mesh, Scene, View, read_scene, write_scene

log = logging.getLogger(__name__)

IMPORT_FORMAT = "jaxdistill-mitsuba-import"
IMPORT_VERSION = 2
IMPORT_FILE = "import.json"      # not gt.json: that name is per-object GT textures (evaluation.GT_FORMAT)


def _check_arguments(xml_path, num_views, width, height, spp) -> None:
    """InputError listing every bad argument (and a missing scene file) at once."""
    problems = ProblemList()
    if not Path(xml_path).is_file():
        problems.add(xml_path, "--mitsuba", "scene file not found")
    for flag, value, low in (("--views", num_views, 1), ("--width", width, 4), ("--height", height, 4),
                             ("--spp", spp, 1)):
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < low:
            problems.add("command line", flag, f"must be an integer >= {low}, got {value!r}")
        elif flag in ("--width", "--height") and value > 16384:
            problems.add("command line", flag, f"must be <= 16384, got {value!r}")
    problems.raise_if_any()


def _remove_stale_gt_json(out: Path) -> None:
    """Deletes the gt.json an earlier version of this import wrote (its metadata, no GT textures):
    evaluation reads gt.json as per-object GT textures and would refuse it."""
    path = out / "gt.json"
    if not path.is_file():
        return
    try:
        doc = json.loads(path.read_text())
    except (OSError, ValueError):
        return
    if isinstance(doc, dict) and "textures" not in doc and isinstance(doc.get("source"), dict) \
            and "mitsuba" in doc["source"]:
        path.unlink()
        log.warning("removed %s written by an earlier import (its metadata is now %s)", path, IMPORT_FILE)


def _licence_text(xml_path: Path) -> str | None:
    for name in ("LICENSE.txt", "LICENSE", "LICENSE.md", "COPYING"):
        path = xml_path.parent / name
        if path.is_file():
            return path.read_text(errors="replace").strip()
    return None


def prepare_scene(xml_path, out_dir, *, num_views: int, width: int, height: int, spp: int, seed: int = 0,
                  up=None, command: str | None = None, progress: bool = True) -> dict:
    """Imports a Mitsuba 3 scene into `out_dir` (scene.json, mesh, photos, targets, ground truth,
    masks, import.json, README.md).

    Returns a summary (also in import.json): objects, UV decisions, view statistics, timings.
    """
    _check_arguments(xml_path, num_views, width, height, spp)
    previous = mb.load_mitsuba().variant()
    irradiance_mitsuba()                       # before any compute: the irradiance needs LLVM
    mb.load_mitsuba(previous)
    out = Path(out_dir)
    if out.is_dir() and any(out.iterdir()):
        log.warning("%s is not empty: files of an earlier import that this one does not rewrite stay there", out)
    timings = {}
    t0 = time.perf_counter()
    source = load_source(xml_path, up=up, upgraded_dir=out)
    timings["load_s"] = time.perf_counter() - t0
    log.info("loaded %s: %d objects (%d faces), dropped %s in %.1f s", xml_path, len(source.objects),
             sum(len(o.faces) for o in source.objects), source.dropped or "none", timings["load_s"])

    t = time.perf_counter()
    mesh, decisions = reconstruction_mesh(source.objects, progress=progress, source_file=os.fspath(xml_path))
    timings["uv_layout_s"] = time.perf_counter() - t
    reunwrapped = [d for d in decisions if d.reunwrapped]
    log.info("UV layout in %.1f s: re-unwrapped %d of %d objects: %s", timings["uv_layout_s"], len(reunwrapped),
             len(decisions), ", ".join(f"{d.name} ({d.reason}, {d.seconds:.2f} s)" for d in reunwrapped) or "none")

    gt_eval = GroundTruthEvaluator(source.objects, mesh)
    t = time.perf_counter()
    cams, view_stats = place_views(mesh, gt_eval.masked_face, num_views, width, height, up=source.up, seed=seed,
                                   progress=progress)
    timings["view_placement_s"] = time.perf_counter() - t
    log.info("placed %d views in %.1f s (%d candidates)", len(cams), timings["view_placement_s"],
             view_stats["candidates"])

    _remove_stale_gt_json(out)
    t = time.perf_counter()
    frags = fr.compute_fragments(mesh, cams, cache_dir=False, progress=progress)
    names = [f"view_{i:03d}" for i in range(len(cams))]
    per_view, masks = [], []
    for name, cam, frag in zip(tqdm(names, desc="ground truth", unit="view", disable=not progress), cams, frags):
        gt = gt_eval.evaluate(cam, frag)
        imageio.write_image(out / "targets" / "albedo" / f"{name}.exr", gt.albedo)
        imageio.write_image(out / "targets" / "roughness" / f"{name}.exr", gt.roughness)
        imageio.write_image(out / "targets" / "metallic" / f"{name}.exr", gt.metallic)
        imageio.write_image(out / "targets" / "normal" / f"{name}.exr", gt.normal)
        imageio.write_image(out / "masks" / f"{name}.png", gt.mask.astype(np.float32), encode_srgb=False)
        masks.append(gt.mask)
        per_view.append({"name": name, "hit_fraction": float(gt.hit.mean()), "valid_fraction": float(gt.mask.mean()),
                         "fov_x_deg": float(np.degrees(2 * np.arctan(cam.width / (2 * cam.K[0, 0]))))})
    timings["ground_truth_s"] = time.perf_counter() - t
    log.info("ground truth for %d views in %.1f s", len(cams), timings["ground_truth_s"])

    t = time.perf_counter()
    irradiance = [np.where(m[..., None], e, 0.0) for e, m in zip(render_irradiance(source.path, cams, spp=spp, seed=seed,
                                                                                   xml_text=source.xml_text,
                                                                                   progress=progress),
                                                                 masks)]
    scale = irradiance_target_scale(irradiance, masks)
    for name, image in zip(names, irradiance):
        imageio.write_image(out / "ground_truth" / "irradiance" / f"{name}.exr", image)
        imageio.write_image(out / "targets" / "irradiance" / f"{name}.exr", np.clip(image * scale, 0.0, 1.0))
    timings["irradiance_s"] = time.perf_counter() - t
    log.info("irradiance (E / pi, %s) of %d views in %.1f s", IRRADIANCE_VARIANT, len(cams), timings["irradiance_s"])

    t = time.perf_counter()
    bar = tqdm(list(zip(names, cams)), desc=f"render (spp {spp})", unit="view", disable=not progress)
    for i, (name, cam) in enumerate(bar):
        image = mb.render(source.scene, cam, spp=spp, seed=seed + i)[..., :3]
        image = np.nan_to_num(image, nan=0.0, posinf=0.0, neginf=0.0)
        imageio.write_image(out / "photos" / f"{name}.exr", image, half=True)
        imageio.write_image(out / "photos" / f"{name}.png", image)
    timings["render_s"] = time.perf_counter() - t
    log.info("rendered %d views at %dx%d, spp %d in %.1f s", len(cams), width, height, spp, timings["render_s"])

    # the photos as RGB<->X sees them: one scene-wide exposure by Hypersim's rule over the valid
    # pixels, measured on the EXR files as written (half float), as the dataset loaders do
    stops = exposure_rule.scene_exposure((imageio.read_image(out / "photos" / f"{n}.exr")[..., :3] for n in names),
                                         masks)
    log.info("exposure: %+.2f stops (Hypersim's rule: 90th-percentile brightness to 0.8 after gamma)", stops)
    exact = ("albedo", "normal", "roughness", "metallic")     # the targets of these maps ARE the ground truth
    views = tuple(View(name=name, camera=cam, photo=out / "photos" / f"{name}.exr", exposure=stops,
                       targets={m: out / "targets" / m / f"{name}.exr" for m in exact + ("irradiance",)},
                       mask=out / "masks" / f"{name}.png",
                       ground_truth={**{m: out / "targets" / m / f"{name}.exr" for m in exact},
                                     "irradiance": out / "ground_truth" / "irradiance" / f"{name}.exr"})
                  for name, cam in zip(names, cams))
    scene_name = source.path.parent.name or source.path.stem
    write_scene(Scene(name=scene_name, mesh=mesh, views=views, texture_layout="pages"), out)
    timings["total_s"] = time.perf_counter() - t0

    summary = {
        "format": IMPORT_FORMAT, "version": IMPORT_VERSION,
        "source": {"mitsuba": os.fspath(Path(xml_path).resolve()), "integrator": source.integrator,
                   "up": source.up.tolist(), "dropped_shapes": source.dropped},
        "settings": {"views": num_views, "width": width, "height": height, "spp": spp, "seed": seed},
        "command": command,
        "conventions": {
            "photos": "photos/<view>.exr linear RGB radiance (half float); photos/<view>.png the same, sRGB-encoded",
            "albedo": "targets/albedo/<view>.exr linear RGB; 0 outside the mask",
            "roughness": "targets/roughness/<view>.exr one channel, perceptual roughness = sqrt(GGX alpha); "
                         "0 outside the mask",
            "metallic": "targets/metallic/<view>.exr one channel; 0 outside the mask",
            "normal": "targets/normal/<view>.exr camera-space unit normal, x right, y up, z towards the camera "
                      "(RGB<->X), flipped to face the camera, stored as (n + 1) / 2; (0.5, 0.5, 0.5) where no "
                      "surface is hit; defined on emitters and glass too",
            "irradiance": "ground_truth/irradiance/<view>.exr linear RGB E / pi (the radiance a white Lambertian "
                          "surface would reflect: photo = albedo x irradiance on diffuse surfaces), HDR, same units as "
                          "the photos; targets/irradiance/<view>.exr the same x irradiance_target_scale, clipped to "
                          "[0, 1] (RGB<->X's output range); 0 outside the mask",
            "mask": "masks/<view>.png 1 where a ray hits a surface that is neither an emitter nor glass; "
                    "scene.json references it as each view's mask (out of loss and metrics)",
            "ground_truth": "scene.json views[].ground_truth: albedo, normal, roughness, metallic are the targets' "
                            "files (exact), irradiance ground_truth/irradiance/<view>.exr",
            "materials": "diffuse: albedo = reflectance, roughness 1, metallic 0; plastic: diffuse_reflectance, 0, "
                         "0; roughplastic: diffuse_reflectance, sqrt(alpha), 0; principled: base_color, roughness, "
                         "metallic; conductor: albedo = specular_reflectance x F0(eta, k), roughness 0 "
                         "(roughconductor: sqrt(alpha)), metallic 1; twosided: its front BSDF",
        },
        "irradiance_target_scale": scale,
        "objects": [{"name": o.name, "shape": o.shape, "faces": int(len(o.faces)), "emitter": o.emitter,
                     "masked": o.masked, "uv": d.reason if d.reunwrapped else "kept",
                     "uv_seconds": round(d.seconds, 3), **(o.material.describe() if o.material else {})}
                    for o, d in zip(source.objects, decisions)],
        "reunwrapped": [d.name for d in reunwrapped],
        "view_placement": view_stats,
        "views": per_view,
        "statistics": {"hit_fraction": float(np.mean([v["hit_fraction"] for v in per_view])),
                       "valid_fraction": float(np.mean([v["valid_fraction"] for v in per_view]))},
        "timings": {k: round(v, 2) for k, v in timings.items()},
    }
    (out / IMPORT_FILE).write_text(json.dumps(summary, indent=1))
    _write_readme(out, source, summary, mesh)
    read_scene(out)          # self-check: the written scene validates
    return summary


def _write_readme(out: Path, source: MitsubaSource, summary: dict, mesh: Mesh) -> None:
    licence = _licence_text(source.path)
    s, st, tm = summary["settings"], summary["statistics"], summary["timings"]
    lines = [
        f"# {out.name}: imported from a Mitsuba 3 scene",
        "",
        f"Source: `{summary['source']['mitsuba']}`, imported by `jaxdistill.datasets.mitsuba.prepare`"
        " (`scripts/prepare_scene.py`).",
        "",
        "## Source and licence",
        "",
    ]
    if licence:
        lines += ["The source scene comes with this licence notice, which applies to everything derived from it "
                  "here (mesh, photos, ground truth):", "", *["> " + line for line in licence.splitlines()], ""]
    else:
        lines += ["No licence file was found beside the source XML: check its terms before sharing this folder.", ""]
    lines += [
        "## Command",
        "",
        "```",
        summary["command"] or (f"prepare_scene(--mitsuba={summary['source']['mitsuba']} --views={s['views']} "
                               f"--width={s['width']} --height={s['height']} --spp={s['spp']} --seed={s['seed']})"),
        "```",
        "",
        "Distil it (from the jaxdistill checkout; all five maps have targets and ground truth):",
        "",
        "```",
        f"python -m jaxdistill.main --flagfile=configs/bedroom.cfg --scene={out} --out_dir={out}_run "
        f"--views_per_step={min(8, s['views'])}",
        "```",
        "",
        "## Contents",
        "",
        f"- `scene.json`, `mesh.glb`: {len(mesh.object_names)} objects, {mesh.num_faces} triangles, texture layout "
        "`pages` (one page per object). Reconstruction UVs lie in [0, 1]; re-unwrapped with xatlas: "
        f"{', '.join(summary['reunwrapped']) or 'none'}.",
        f"- {s['views']} views at {s['width']}x{s['height']}, path traced by Mitsuba "
        f"({summary['source']['integrator']}, {s['spp']} spp).",
        "- `targets/<map>/<view>.exr` (albedo, normal, roughness, metallic: the exact ground truth; irradiance: "
        "scaled into [0, 1]), `ground_truth/irradiance/<view>.exr`, `masks/<view>.png` (each view's `mask` in "
        "scene.json), `import.json` (conventions, per-object materials and UV decisions, per-view statistics, "
        "timings).",
        "- The targets of albedo, normal, roughness and metallic are the ground truth itself: a run with the "
        "`views` prior on them is an upper bound, not a method result; for a real test, replace them with "
        "estimates (`python -m jaxdistill.estimate`) or use `--prior=rgbx`.",
        "",
        "## Conventions",
        "",
        *[f"- {k}: {v}" for k, v in summary["conventions"].items()],
        "- Cameras: OpenCV (x right, y down, z forward), square pixels, off-centre principal points.",
        "- Ground truth is evaluated per pixel at the ORIGINAL texture coordinates of the triangle our ray hits, "
        "so it is exact whatever the reconstruction UV layout.",
        "",
        "## Statistics and timings",
        "",
        f"- Mean hit fraction {st['hit_fraction']:.3f}, mean valid (unmasked) fraction {st['valid_fraction']:.3f}.",
        f"- Unmasked surface area seen by some view (low-res estimate): "
        f"{summary['view_placement']['unmasked_area_seen_fraction']:.3f}.",
        "- " + ", ".join(f"{k[:-2]} {v:.1f} s" for k, v in tm.items()) + ".",
        "",
    ]
    (out / "README.md").write_text("\n".join(lines))
