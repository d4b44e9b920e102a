"""Ground-truth self-consistency: the photo against albedo x irradiance on near-Lambertian pixels.

A scene whose views carry irradiance ground truth (E / pi in the photos' units, each view's
`ground_truth.irradiance`) should show photo = albedo x irradiance wherever the surface is
diffuse. `scene_consistency` measures it from the files with the package's own readers (gt.json
pages through our gather sampler at pixel centres, the views' ground_truth images), over
- diffuse pixels (`diffuse_mask`): evaluated (hit, not an emitter, not masked), metallic 0,
  roughness >= DIFFUSE_ROUGHNESS, seen within about 30 degrees of the normal;
- all evaluated dielectric pixels (metallic 0); all evaluated pixels.
Mitsuba's `principled` BSDF is not Lambertian (its diffuse lobe brightens rough surfaces at
grazing angles, dielectrics add a specular lobe), so only the diffuse figure is expected near 1.
"""

from __future__ import annotations

import dataclasses
from typing import Sequence

import numpy as np

from jaxdistill.io import exposure, images as imageio

DIFFUSE_ROUGHNESS = 0.5          # consistency pixels: metallic 0, roughness >= this,
DIFFUSE_COSINE = 0.85            # and seen within about 30 degrees of the normal (`diffuse_mask`)


def consistency(photos, albedos, irradiances, masks) -> dict:
    """photo against albedo x irradiance (all linear, same units) over the masked pixels of all
    views: brightness ratios (0.3 R + 0.59 G + 0.11 B) per pixel, their median and 10th/90th
    percentiles, and the ratio of the sums."""
    got, want = [], []
    for p, a, e, m in zip(photos, albedos, irradiances, masks):
        got.append(exposure.brightness(p)[m])
        want.append(exposure.brightness(a[..., :3] * e[..., :3])[m])
    got, want = np.concatenate(got), np.concatenate(want)
    keep = want > 1e-6
    ratio = got[keep] / want[keep]
    if not ratio.size:
        return {"pixels": 0, "median_ratio": float("nan"), "p10": float("nan"), "p90": float("nan"),
                "sum_ratio": float("nan")}
    return {"pixels": int(ratio.size), "median_ratio": float(np.median(ratio)), "p10": float(np.percentile(ratio, 10)),
            "p90": float(np.percentile(ratio, 90)), "sum_ratio": float(got[keep].sum() / want[keep].sum())}


def view_cosine(camera, normal) -> np.ndarray:
    """(H, W) cosine between each pixel's RGB<->X camera-space normal (x right, y up, z towards the
    camera) and the direction from its surface point to the camera."""
    u, v = np.meshgrid(np.arange(camera.width) + 0.5, np.arange(camera.height) + 0.5)
    rays = np.stack([u, v, np.ones_like(u)], -1) @ np.linalg.inv(camera.K).T      # OpenCV, z forward
    to_camera = rays * [-1.0, 1.0, 1.0]
    to_camera /= np.linalg.norm(to_camera, axis=-1, keepdims=True)
    return np.sum(normal[..., :3] * to_camera, -1)


def diffuse_mask(valid, roughness, metallic, cosine) -> np.ndarray:
    """(H, W) bool: valid pixels where the principled BSDF is closest to Lambertian: dielectric
    (metallic 0), rough (>= DIFFUSE_ROUGHNESS) and seen within about 30 degrees of the normal
    (cosine >= DIFFUSE_COSINE; at grazing views its diffuse lobe's retro-reflection and the
    specular Fresnel make the photo up to 1.6x albedo x irradiance)."""
    return valid & (metallic[..., 0] == 0) & (roughness[..., 0] >= DIFFUSE_ROUGHNESS) & (cosine >= DIFFUSE_COSINE)


def scene_consistency(scene, views: Sequence[int] | None = None) -> dict:
    """{"diffuse", "dielectric", "all_valid": `consistency` figures} of the scene's views (indices;
    default all) from its files: linear photos, gt.json albedo/roughness/metallic and geometry
    normals, each view's ground_truth irradiance. ValueError when a view has no irradiance GT or
    the scene no gt.json albedo."""
    from jaxdistill.evaluate.ground_truth import evaluation_masks, read_ground_truth, view_ground_truth
    from jaxdistill.render import fragments as fr

    chosen = [scene.views[i] for i in (range(len(scene.views)) if views is None else views)]
    missing = [v.name for v in chosen if "irradiance" not in v.ground_truth]
    if missing:
        raise ValueError(f"views without ground_truth irradiance: {', '.join(missing[:5])}")
    sub = dataclasses.replace(scene, views=tuple(chosen))
    frags = fr.compute_fragments(sub.mesh, [v.camera for v in chosen], cache_dir=False, progress=False)
    gt_doc, gt = view_ground_truth(sub, frags)
    if gt_doc is None or "albedo" not in gt_doc.pages:
        raise ValueError(f"{scene.root}: no gt.json albedo pages")
    masks = evaluation_masks(gt_doc, sub, frags)
    photos = [imageio.read_image(v.photo)[..., :3] for v in chosen]
    albedos = [g["albedo"] for g in gt]
    irradiances = [g["irradiance"] for g in gt]
    dielectric = [m & (g["metallic"][..., 0] == 0) for m, g in zip(masks, gt)]
    diffuse = [diffuse_mask(m, g["roughness"], g["metallic"], view_cosine(v.camera, g["normal"]))
               for m, g, v in zip(masks, gt, chosen)]
    return {"diffuse": consistency(photos, albedos, irradiances, diffuse),
            "dielectric": consistency(photos, albedos, irradiances, dielectric),
            "all_valid": consistency(photos, albedos, irradiances, masks)}
