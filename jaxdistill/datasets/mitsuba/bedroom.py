"""The embedded bedroom's Mitsuba scene: its lights, and the scene built from its mesh and GT pages.

`scripts/make_bedroom.py` renders the bedroom's photos from `mitsuba_scene` and
`scripts/make_bedroom.py --irradiance_only` its per-view irradiance ground truth (`render_irradiance`),
so both see the same scene: every object a `principled` BSDF on its GT pages (albedo linear,
roughness, metallic), the lamp's bulb and the ceiling panel area lights, sun and sky through
the window. Everything here takes the mesh and pages as arguments (the folder's `mesh.glb` and
`gt/textures` pages, or the generator's own arrays, give the same scene).
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from jaxdistill.datasets.mitsuba import bridge as mb

EMITTERS = {"bulb": [14.0, 10.0, 5.5], "panel": [7.0, 6.6, 6.0]}   # material -> area radiance (linear RGB)
EMITTER_MATERIALS = {"lamp_bulb": "bulb", "ceiling_light": "panel"}  # emitting object -> its material
EMITTER_OBJECTS = tuple(EMITTER_MATERIALS)                         # excluded from evaluation
SUN_IRRADIANCE = [4.0, 3.7, 3.2]
SUN_DIRECTION = (-1.0, -0.55, 0.35)                                # towards which the sunlight travels
SKY_RADIANCE = [0.45, 0.55, 0.75]
PHOTO_MAX_DEPTH = 6                                                # the photos' `path` integrator
IRRADIANCE_SEED_OFFSET = 50_021                                    # irradiance seeds apart from the photos'


def emitter_radiance() -> dict[str, list[float]]:
    """{emitting object name: area radiance (linear RGB)}."""
    return {name: EMITTERS[material] for name, material in EMITTER_MATERIALS.items()}


def mitsuba_scene(mesh, pages: dict):
    """The loaded Mitsuba scene (current variant) of the bedroom `mesh` with GT `pages`
    {albedo, roughness, metallic: per object (S, S, C) arrays}: principled BSDFs, the two
    emitting objects, sun and sky."""
    mi = mb.load_mitsuba()
    shapes = mb.principled_shapes(mesh, pages, emitters=emitter_radiance())
    sun = np.array(SUN_DIRECTION)
    return mi.load_dict({
        "type": "scene", **shapes,
        "sun": {"type": "directional", "direction": (sun / np.linalg.norm(sun)).tolist(),
                "irradiance": {"type": "rgb", "value": SUN_IRRADIANCE}},
        "sky": {"type": "constant", "radiance": {"type": "rgb", "value": SKY_RADIANCE}},
    })


def irradiance_seeds(seed: int, count: int) -> list[int]:
    """Mitsuba seeds of the irradiance renders of views 0..count-1 for the bedroom of `seed`
    (the photos use seed * 100003 + i)."""
    return [seed * 100003 + IRRADIANCE_SEED_OFFSET + i for i in range(count)]


def render_irradiance(mesh, pages: dict, cameras: Sequence, *, spp: int, seed: int = 0,
                      progress: bool = False) -> list[np.ndarray]:
    """Per view (H, W, 3) float32 E / pi at each pixel's first hit, in the photos' units (linear,
    not exposed), for the bedroom of generator seed `seed`: `bridge.render_irradiance` with paths
    one bounce shorter than the photos' (so a diffuse pixel of the photo is albedo x E / pi).

    Runs in Mitsuba's `llvm_ad_rgb` variant when LLVM 19 is found (`bridge.llvm_variant`; several
    times faster), else `scalar_rgb`; the variant set before is set back.
    """
    mi = mb.load_mitsuba()
    previous = mi.variant()
    mb.load_mitsuba(mb.llvm_variant())
    try:
        scene = mitsuba_scene(mesh, pages)
        return mb.render_irradiance(scene, cameras, spp=spp, seeds=irradiance_seeds(seed, len(cameras)),
                                    max_depth=PHOTO_MAX_DEPTH - 1, progress=progress)
    finally:
        if previous:
            mb.load_mitsuba(previous)
