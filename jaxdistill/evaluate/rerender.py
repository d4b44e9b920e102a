"""How well the distilled maps explain the photos: every view re-rendered as albedo x irradiance.

For each view at the photos' own size: the diffuse image d = a ⊙ E of the maps (file space,
linear), the photo's scale s against it (weighted least squares, per view: the maps carry no
absolute unit), and the PSNR (dB) of sRGB(clip(s·d)) against sRGB(clip(photo)) over the
covered, unmasked, unclipped pixels, weighted by 1 − metallic as the re-rendering term weighs
them (`engine/photo.py`). Reported for every run that distils albedo and irradiance, with or
without the term, so the two can be compared.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from jaxdistill.engine.problem import Problem
from jaxdistill.evaluate.metrics import psnr
from jaxdistill.io.images import linear_to_srgb
from jaxdistill.io.view_images import read_mask, read_photo_linear


def rerender_scores(renders: Sequence[dict], problem: Problem, plan) -> dict | None:
    """{"psnr_db": mean over views, "per_view": {view: PSNR}, "scale": {view: s}} of the photos
    re-rendered from the run's `renders` (per view {map: (H, W, C) file-space image} through `plan`,
    the views at native size: `ground_truth.render_views`, a list or lazy), or None when albedo or
    irradiance is not distilled."""
    if not {"albedo", "irradiance"} <= set(problem.channels.maps):
        return None
    hits = plan.hit_images()
    per_view, scales = {}, {}
    for view, render, hit in zip(problem.scene.views, renders, hits):
        height, width = hit.shape
        photo, usable = read_photo_linear(view.photo, view.exposure, height, width)
        weight = hit * usable
        if view.mask is not None:
            weight = weight * read_mask(view.mask, height, width)
        if "metallic" in render:
            weight = weight * (1.0 - np.clip(render["metallic"][..., 0], 0.0, 1.0))
        diffuse = np.asarray(render["albedo"], np.float64) * np.asarray(render["irradiance"], np.float64)
        w = weight[..., None]
        den = float(np.sum(w * diffuse * diffuse))
        scale = float(np.sum(w * diffuse * photo) / den) if den > 0 else 1.0
        keep = weight > 0
        if not keep.any():
            continue
        ours = linear_to_srgb(np.clip(scale * diffuse, 0.0, 1.0).astype(np.float32))[keep]
        seen = linear_to_srgb(np.clip(photo, 0.0, 1.0))[keep]
        per_view[view.name] = psnr(ours, seen)
        scales[view.name] = scale
    if not per_view:
        return None
    return {"psnr_db": float(np.mean(list(per_view.values()))), "per_view": per_view, "scale": scales}
