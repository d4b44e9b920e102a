"""Generates the embedded bedroom scene: geometry, PBR ground truth, Mitsuba photos, estimates.

    python scripts/make_bedroom.py [--out=jaxdistill/scenes/bedroom] [--views=48] [--spp=64]
    python scripts/make_bedroom.py --verify      # regenerate into a temp dir, compare hashes

Needs the `scenes` extra (Mitsuba 3, scalar_rgb). Every random choice comes from one seed, so
the same versions on the same platform regenerate the folder bit for bit (`manifest.sha256`).

What it builds (units metres, y up; the room spans [0, 4.2] x [0, 2.6] x [0, 3.6]):
- A room with a window opening (sun and sky come in through it) and a door; a bed (frame,
  mattress, two pillows, blanket), two nightstands, a wardrobe, a desk and a chair, a rug, a
  bedside lamp (metal stand, fabric shade, emitting bulb), two picture frames, a radiator and
  metal handles. Each object is a set of rectangles whose UVs are packed without overlap into
  its own texture page at a uniform texel density (about 128 texels per metre).
- Spatially varying ground truth per object: albedo (wood grain, fabric weave, wallpaper,
  plaster, rug pattern, paintings, brushed metal), roughness and metallic maps, stored as 8-bit
  PNGs; the quantised values are the ground truth. Every material is Mitsuba's `principled`
  BSDF driven by exactly these textures, so the ground truth is exact.
- Views inside the room at varied heights, orientations and focal lengths, some close-ups,
  off-centre principal points; photos path traced with Mitsuba (EXR linear + PNG sRGB).
- Per-view irradiance ground truth E/pi in the photos' units (`ground_truth/irradiance/`, each
  view's `ground_truth`), from the photos' own Mitsuba scene (`write_irradiance`; the scene is
  `jaxdistill.datasets.mitsuba.bedroom.mitsuba_scene`, shared with `--irradiance_only`).
- Per-view stand-ins for a monocular estimator's output (the `views` prior's targets): the
  ground truth rendered by our own gather sampler, corrupted the way single-image estimators
  err; the parameters of every view are in `estimates.json`, described in the scene README.
- A check that our sampler agrees with Mitsuba's `aov` albedo for every camera.
"""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import json
import math
import os
import re
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from tqdm import tqdm

from jaxdistill.datasets.mitsuba import bridge as mb
from jaxdistill.io import images as imageio
from jaxdistill.io.exposure import scene_exposure
from jaxdistill.datasets.mitsuba import bedroom as bedroom_mitsuba
from jaxdistill.datasets.mitsuba.bedroom import EMITTER_OBJECTS, EMITTERS
from jaxdistill.models.training.room_geometry import Rect, box, build_scene_geometry, legs, preview, rect, rolled_camera, wall
from jaxdistill.models.training.scene_files import (EXR_TIMESTAMP, MAP_FILES, write_gt_json, write_map, write_preview,
                                                    write_texture_pages)
from jaxdistill.models.training.standins import ESTIMATE_MODEL, estimate_view
from jaxdistill.models.training.textures import gaussian_blur, grid, mix, smooth_noise, wood
from jaxdistill.render import fragments as fr
from jaxdistill.render.sampler import sample_pages
from jaxdistill.scene import cameras
from jaxdistill.scene.cameras import camera_normals       # GT normals exactly as evaluation makes them
from jaxdistill.scene.mesh import face_normals
from jaxdistill.evaluate.ground_truth import read_ground_truth
from jaxdistill.scene.model import Mesh, Scene, View, read_scene, write_scene

ROOM = np.array([4.2, 2.6, 3.6])
PIXEL_FILTER_SIGMA = 0.5   # Gaussian pixel filter applied after Mitsuba's box-filtered render (see generate)
IRRADIANCE_SPP = 32        # per-view irradiance ground truth (`write_irradiance`)
IRRADIANCE_COMPRESSION = "dwaa:90"     # as the photos: lossy, below the Monte Carlo noise
DEFAULT_OUT = Path(__file__).resolve().parents[1] / "jaxdistill" / "scenes" / "bedroom"

# ----------------------------------------------------------------------------- geometry


def bedroom_objects() -> list[tuple[str, list[Rect], str]]:
    """(name, rectangles, material) of every object of the room."""
    X, Y, Z = ROOM
    win = (1.2 / Z, 2.4 / Z, 0.9 / Y, 2.1 / Y)             # window on the x = X wall
    door = (0.3, 1.2)                                      # door on the z = 0 wall (x range)
    objs = [
        ("floor", [rect((0, 0, Z), (X, 0, 0), (0, 0, -Z), (0, 0, 1, 1))], "floor_wood"),
        ("ceiling", [rect((0, Y, 0), (X, 0, 0), (0, 0, Z), (0, 0, 1, 1))], "plaster"),
        ("wall_door", wall((0, 0, 0), (X, 0, 0), (0, Y, 0)), "paint"),
        ("wall_bed", wall((X, 0, Z), (-X, 0, 0), (0, Y, 0)), "wallpaper"),
        ("wall_wardrobe", wall((0, 0, Z), (0, 0, -Z), (0, Y, 0)), "paint"),
        ("wall_window", wall((X, 0, 0), (0, 0, Z), (0, Y, 0), hole=win), "paint"),
    ]
    wz0, wz1, wy0, wy1 = win[0] * Z, win[1] * Z, win[2] * Y, win[3] * Y
    d = 0.18                                               # reveal depth, outwards
    frame = [rect((X + d, wy0, wz0), (-d, 0, 0), (0, 0, wz1 - wz0)),       # sill, facing up
             rect((X, wy1, wz0), (d, 0, 0), (0, 0, wz1 - wz0)),            # lintel, facing down
             rect((X + d, wy0, wz0), (0, wy1 - wy0, 0), (-d, 0, 0)),       # side z = wz0, facing +z
             rect((X, wy0, wz1), (0, wy1 - wy0, 0), (d, 0, 0))]            # side z = wz1, facing -z
    frame += box((X + 0.06, wy0, 0.5 * (wz0 + wz1) - 0.03), (X + 0.12, wy1, 0.5 * (wz0 + wz1) + 0.03), skip=("-y", "+y"))
    frame += box((X + 0.06, 0.5 * (wy0 + wy1) - 0.03, wz0), (X + 0.12, 0.5 * (wy0 + wy1) + 0.03, wz1), skip=("-z", "+z"))
    objs.append(("window_frame", frame, "white_wood"))
    objs.append(("door", box((door[0], 0.0, 0.0), (door[1], 2.05, 0.035), skip=("-z", "-y")), "door_wood"))
    objs.append(("door_handle", box((1.02, 1.0, 0.035), (1.14, 1.03, 0.09), skip=("-z",))
                 + box((1.1, 0.97, 0.035), (1.14, 1.06, 0.05), skip=("-z",)), "brass"))
    # bed against the far wall (z = Z)
    bx0, bx1, bz0, bz1 = 1.3, 2.9, 1.45, Z
    objs.append(("bed_frame", box((bx0, 0.12, bz0), (bx1, 0.35, bz1), skip=("+z", "-y"))
                 + box((bx0 - 0.04, 0.0, bz1 - 0.06), (bx1 + 0.04, 1.05, bz1), skip=("+z", "-y"))
                 + legs(bx0, bx1, bz0, bz1 - 0.06, 0.12, 0.07), "oak"))
    objs.append(("mattress", box((bx0 + 0.03, 0.35, bz0 + 0.03), (bx1 - 0.03, 0.55, bz1 - 0.07), skip=("-y", "+z")), "linen"))
    objs.append(("blanket", box((bx0 - 0.02, 0.3, bz0 - 0.02), (bx1 + 0.02, 0.58, bz1 - 0.75), skip=("-y", "+z")), "knit"))
    for k, (x0, x1) in enumerate(((bx0 + 0.1, bx0 + 0.75), (bx1 - 0.75, bx1 - 0.1))):
        objs.append((f"pillow_{k}", box((x0, 0.55, bz1 - 0.55), (x1, 0.7, bz1 - 0.12), skip=("-y",)), "pillow"))
    for k, (x0, x1) in enumerate(((0.75, 1.2), (3.0, 3.45))):
        objs.append((f"nightstand_{k}", box((x0, 0.0, Z - 0.45), (x1, 0.55, Z - 0.02), skip=("-y", "+z"))
                     + box((x0 + 0.04, 0.3, Z - 0.455), (x1 - 0.04, 0.5, Z - 0.45), skip=("+z",)), "walnut"))
        objs.append((f"nightstand_{k}_knob", box((0.5 * (x0 + x1) - 0.03, 0.38, Z - 0.49), (0.5 * (x0 + x1) + 0.03, 0.42, Z - 0.455), skip=("+z",)), "steel"))
    # lamp on nightstand 0
    lx, lz = 0.975, Z - 0.235
    objs.append(("lamp_stand", box((lx - 0.09, 0.55, lz - 0.09), (lx + 0.09, 0.57, lz + 0.09), skip=("-y",))
                 + box((lx - 0.012, 0.57, lz - 0.012), (lx + 0.012, 0.9, lz + 0.012), skip=("-y",)), "brushed_steel"))
    objs.append(("lamp_shade", box((lx - 0.14, 0.82, lz - 0.14), (lx + 0.14, 1.04, lz + 0.14), skip=("-y", "+y")), "shade"))
    objs.append(("lamp_bulb", box((lx - 0.04, 0.86, lz - 0.04), (lx + 0.04, 0.96, lz + 0.04)), "bulb"))
    objs.append(("ceiling_light", box((1.75, Y - 0.04, 1.45), (2.45, Y - 0.005, 2.15), skip=("+y",)), "panel"))
    # wardrobe against x = 0
    objs.append(("wardrobe", box((0.0, 0.0, 0.35), (0.6, 2.1, 1.85), skip=("-x", "-y")), "walnut"))
    objs.append(("wardrobe_handles", box((0.6, 0.95, 1.02), (0.63, 1.25, 1.05), skip=("-x",))
                 + box((0.6, 0.95, 1.15), (0.63, 1.25, 1.18), skip=("-x",)), "steel"))
    # desk and chair under the window side, near the door wall
    objs.append(("desk", box((3.4, 0.72, 0.2), (4.15, 0.76, 1.1)) + legs(3.4, 4.15, 0.2, 1.1, 0.72, 0.05), "varnished"))
    objs.append(("chair", box((2.9, 0.44, 0.45), (3.3, 0.48, 0.85)) + box((2.86, 0.44, 0.45), (2.9, 0.95, 0.85))
                 + legs(2.86, 3.3, 0.45, 0.85, 0.44, 0.035), "oak"))
    objs.append(("rug", box((1.0, 0.0, 0.6), (3.2, 0.012, 2.6), skip=("-y",)), "rug"))
    objs.append(("radiator", [r for k in range(8) for r in box((X - 0.1, 0.15, 1.35 + 0.12 * k),
                                                                (X - 0.02, 0.75, 1.35 + 0.12 * k + 0.06), skip=("+x",))], "radiator"))
    objs.append(("picture_0", box((0.0, 1.25, 2.3), (0.03, 1.85, 3.1), skip=("-x",)), "painting"))
    objs.append(("picture_1", box((1.75, 1.3, Z - 0.03), (2.45, 1.8, Z), skip=("+z",)), "painting"))
    return objs


# ----------------------------------------------------------------------------- textures


def albedo_and_maps(material: str, rng, size: int):
    """(albedo (S, S, 3) linear, roughness (S, S), metallic (S, S)) of a named material."""
    u, v = grid(size)
    n_low = smooth_noise(rng, size, size / 8)
    rough = np.full((size, size), 0.5)
    metal = np.zeros((size, size))
    if material in ("floor_wood", "oak", "walnut", "door_wood", "varnished"):
        colours = {"floor_wood": ((0.42, 0.26, 0.13), (0.22, 0.12, 0.05)), "oak": ((0.55, 0.38, 0.2), (0.33, 0.2, 0.09)),
                   "walnut": ((0.26, 0.15, 0.08), (0.12, 0.06, 0.03)), "door_wood": ((0.6, 0.5, 0.36), (0.42, 0.32, 0.2)),
                   "varnished": ((0.48, 0.3, 0.15), (0.28, 0.15, 0.06))}[material]
        albedo, t = wood(rng, size, *colours)
        if material == "floor_wood":                                    # planks
            plank = np.floor(u * 12)
            albedo *= (0.85 + 0.3 * np.random.default_rng(int(rng.integers(1 << 31))).random(12))[plank.astype(int)][..., None]
            albedo *= np.where(np.abs(u * 12 - np.round(u * 12)) < 0.02, 0.4, 1.0)[..., None]
        base = {"varnished": 0.25, "floor_wood": 0.35}.get(material, 0.55)
        rough = base + 0.15 * t + 0.03 * n_low
    elif material in ("plaster", "paint", "white_wood"):
        colour = {"plaster": (0.8, 0.79, 0.76), "paint": (0.62, 0.66, 0.58), "white_wood": (0.78, 0.78, 0.75)}[material]
        albedo = np.asarray(colour)[None, None] * (1 + 0.04 * n_low + 0.015 * smooth_noise(rng, size, 3.0))[..., None]
        rough = 0.8 + 0.05 * n_low if material != "white_wood" else 0.35 + 0.05 * n_low
    elif material == "wallpaper":
        stripe = (np.sin(2 * np.pi * u * 24) > 0.6).astype(float)
        motif = ((np.sin(2 * np.pi * u * 48) * np.sin(2 * np.pi * v * 30)) > 0.85).astype(float)
        albedo = mix((0.7, 0.62, 0.5), (0.45, 0.3, 0.3), np.clip(0.6 * stripe + motif, 0, 1))
        albedo *= (1 + 0.03 * n_low)[..., None]
        rough = 0.75 - 0.2 * motif
    elif material in ("linen", "knit", "pillow", "shade"):
        f = {"linen": 90, "knit": 60, "pillow": 110, "shade": 70}[material]
        weave = 0.5 + 0.5 * np.sin(2 * np.pi * u * f) * np.sin(2 * np.pi * v * f)
        colour, accent = {"linen": ((0.85, 0.84, 0.8), (0.7, 0.7, 0.68)), "knit": ((0.2, 0.3, 0.5), (0.12, 0.18, 0.34)),
                          "pillow": ((0.8, 0.68, 0.55), (0.62, 0.5, 0.4)), "shade": ((0.9, 0.85, 0.72), (0.75, 0.7, 0.6))}[material]
        albedo = mix(colour, accent, np.clip(weave + 0.2 * n_low, 0, 1))
        if material == "knit":                                         # cable stripes
            albedo = np.where((np.sin(2 * np.pi * v * 8) > 0.7)[..., None], albedo * 1.8, albedo)
        rough = 0.9 + 0.05 * weave
    elif material == "rug":
        d = np.minimum(np.minimum(u, 1 - u), np.minimum(v, 1 - v))
        border = (d < 0.08).astype(float) * (1 - (d < 0.06) + (d < 0.03))
        diamond = ((np.abs((u * 10) % 1 - 0.5) + np.abs((v * 8) % 1 - 0.5)) < 0.3).astype(float)
        albedo = mix((0.55, 0.12, 0.1), (0.85, 0.7, 0.45), np.clip(diamond * (d >= 0.08) + border, 0, 1))
        albedo = albedo * (1 + 0.08 * smooth_noise(rng, size, 0.8))[..., None]
        rough = 0.95 - 0.05 * diamond
    elif material == "painting":
        colours = np.array([(0.75, 0.3, 0.1), (0.1, 0.3, 0.6), (0.85, 0.75, 0.3), (0.15, 0.45, 0.25)])
        fields = np.stack([smooth_noise(rng, size, size / 10) for _ in colours])
        w = np.exp(2.5 * fields)
        albedo = np.einsum("kij,kc->ijc", w / w.sum(0), colours)
        d = np.minimum(np.minimum(u, 1 - u), np.minimum(v, 1 - v))
        gilded = d < 0.1                                               # gilt frame: metallic border
        albedo[gilded] = (0.85, 0.65, 0.3)
        metal = gilded.astype(float)
        rough = np.where(gilded, 0.3, 0.6)
    elif material in ("steel", "brushed_steel", "radiator", "brass"):
        brushed = smooth_noise(rng, size, 0.6, aspect=12.0)
        colour = {"brass": (0.9, 0.7, 0.35), "radiator": (0.85, 0.85, 0.83)}.get(material, (0.75, 0.75, 0.76))
        albedo = np.asarray(colour)[None, None] * (1 + 0.04 * brushed)[..., None]
        metal = np.ones((size, size))
        rough = {"steel": 0.3, "brushed_steel": 0.4, "radiator": 0.35, "brass": 0.25}[material] + 0.06 * brushed
    elif material in EMITTERS:
        albedo = np.full((size, size, 3), 0.9)
        rough = np.full((size, size), 0.2)
    else:
        raise ValueError(f"unknown material {material!r}")
    return np.clip(albedo, 0.02, 0.95), np.clip(rough, 0.02, 1.0), np.clip(metal, 0.0, 1.0)


# ----------------------------------------------------------------------------- scene


def write_textures(objs, sizes, rng, folder: Path) -> dict[str, list[np.ndarray]]:
    """Writes 8-bit GT textures and returns what they decode to (the exact ground truth):
    albedo (S, S, 3) linear, roughness and metallic (S, S, 1) in [0, 1]."""
    maps = [albedo_and_maps(material, rng, size) for (_, _, material), size in zip(objs, sizes)]
    return write_texture_pages([name for name, _, _ in objs], maps, folder)


def mitsuba_scene(mesh: Mesh, objs, gt):
    """The loaded Mitsuba scene: principled BSDFs on the GT textures, sun, sky and the lamp
    (`jaxdistill.datasets.mitsuba.bedroom.mitsuba_scene`, which the irradiance GT renders too)."""
    emitting = {name: material for name, _, material in objs if material in EMITTERS}
    if emitting != bedroom_mitsuba.EMITTER_MATERIALS:
        raise ValueError(f"emitting objects {emitting} differ from the package's {bedroom_mitsuba.EMITTER_MATERIALS}")
    return bedroom_mitsuba.mitsuba_scene(mesh, gt)


def object_boxes(mesh: Mesh, names) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Axis-aligned bounds of the named objects."""
    out = {}
    for name in names:
        tri = mesh.triangles()[mesh.face_object == mesh.object_names.index(name)].reshape(-1, 3)
        out[name] = (tri.min(0), tri.max(0))
    return out


def place_views(mesh: Mesh, rng, count: int, width: int, height: int) -> list[cameras.Camera]:
    """`count` cameras inside the room, aimed at objects in turn (so all are seen), about a third
    of them close-ups; fov 55-75 degrees, off-centre principal point, a little roll.

    A candidate is kept when its eye is at least 0.2 m outside every piece of furniture and a
    low-resolution preview sees geometry in >= 90 % of pixels at a median depth >= 0.4 m.
    """
    room_objects = {"floor", "ceiling", "wall_door", "wall_bed", "wall_wardrobe", "wall_window", "window_frame"}
    furniture = [n for n in mesh.object_names if n not in room_objects]
    boxes = object_boxes(mesh, mesh.object_names)
    caster = fr.RayCaster(mesh)
    targets = [n for n in mesh.object_names if n not in EMITTER_OBJECTS]
    order = list(rng.permutation(targets))
    out = []
    while len(out) < count:
        name = order[len(out) % len(order)]
        lo, hi = boxes[name]
        target = lo + rng.uniform(0.2, 0.8, 3) * (hi - lo)
        close_up = name in furniture and rng.random() < 0.35
        if close_up:
            direction = rng.normal(size=3)
            direction[1] = abs(direction[1]) + 0.3
            eye = target + direction / np.linalg.norm(direction) * rng.uniform(0.6, 1.0)
        else:
            eye = rng.uniform([0.35, 0.6, 0.35], ROOM - [0.35, 0.7, 0.35])
        if not (np.all(eye > [0.15, 0.3, 0.15]) and np.all(eye < ROOM - 0.15)):
            continue
        if any(np.all(eye > bl - 0.2) and np.all(eye < bh + 0.2) for n, (bl, bh) in boxes.items() if n in furniture):
            continue
        fov = rng.uniform(55.0, 75.0) if not close_up else rng.uniform(50.0, 62.0)
        fx = width / (2 * math.tan(math.radians(fov) / 2))
        cx, cy = width / 2 + rng.normal(0, 0.02 * width), height / 2 + rng.normal(0, 0.02 * height)
        K = np.array([[fx, 0, cx], [0, fx, cy], [0, 0, 1.0]])
        forward = (target - eye) / np.linalg.norm(target - eye)
        if abs(forward[1]) > 0.9:
            continue
        cam = rolled_camera(eye, target, K, width, height, math.radians(rng.normal(0, 3.0)))
        coverage, depth = preview(caster, cam, 8)
        if coverage < 0.9 or depth < 0.4:
            continue
        out.append(cam)
    return out


# ----------------------------------------------------------------------------- main


def psnr_and_match(a: np.ndarray, b: np.ndarray, mask: np.ndarray, tol: float) -> tuple[float, float]:
    """PSNR of a vs b over mask (range 1) and the fraction of masked pixels within tol in every channel."""
    d = (a - b)[mask]
    mse = float(np.mean(d ** 2))
    return (10 * math.log10(1 / mse) if mse > 0 else math.inf), float(np.mean(np.all(np.abs(d) <= tol, axis=-1)))


def generate(out: Path, *, seed: int, views: int, width: int, height: int, spp: int,
             irradiance_spp: int = IRRADIANCE_SPP) -> dict:
    """Builds the whole scene folder; returns the summary written to the README."""
    from jaxdistill.evaluate import metrics

    times = {}
    t0 = time.perf_counter()
    rng = np.random.default_rng(seed)
    objs = bedroom_objects()
    mesh, sizes = build_scene_geometry(objs)
    gt_tex = write_textures(objs, sizes, rng, out / "gt" / "textures")
    cams = place_views(mesh, rng, views, width, height)
    names = [f"view_{i:03d}" for i in range(len(cams))]
    times["geometry_textures_views_s"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    frags = fr.compute_fragments(mesh, cams, cache_dir=False, progress=True)
    stacked = [np.concatenate([gt_tex[k][o] for k in ("albedo", "roughness", "metallic")], -1) for o in range(len(objs))]
    gt_views = sample_pages(stacked, frags, range(len(objs)))
    normals = face_normals(mesh)
    times["gt_maps_s"] = time.perf_counter() - t0

    scene = mitsuba_scene(mesh, objs, gt_tex)
    emitter_ids = [mesh.object_names.index(n) for n in EMITTER_OBJECTS]
    aov = mb.aov_integrator("albedo:albedo", "obj:shape_index")
    path_tracer = {"type": "path", "max_depth": 6}
    agreement, baseline, estimates, view_list = [], [], {}, []
    t_render = t_aov = 0.0
    for i, (name, cam, frag, g) in enumerate(tqdm(list(zip(names, cams, frags, gt_views)), desc="render", unit="view")):
        t0 = time.perf_counter()
        photo = mb.render(scene, cam, spp=spp, seed=seed * 100003 + i, integrator=path_tracer)[..., :3]
        photo = gaussian_blur(photo, PIXEL_FILTER_SIGMA)
        t_render += time.perf_counter() - t0
        t0 = time.perf_counter()
        check = mb.render(scene, cam, centre_samples=True, integrator=aov)
        t_aov += time.perf_counter() - t0
        hit = frag.object_id >= 0
        mitsuba_hit = check[..., 3] > 0
        both = hit & mitsuba_hit
        p, match = psnr_and_match(check[..., :3], g[..., :3], both, 2.0 / 255)
        agreement.append({"view": name, "psnr_db": p, "match_fraction": match,
                          "hit_agreement": float(np.mean(hit == mitsuba_hit))})

        gt = {"albedo": g[..., :3], "roughness": g[..., 3:4], "metallic": g[..., 4:5],
              "normal": camera_normals(normals, frag.triangle, cam)}
        est, params = estimate_view(np.random.default_rng([seed, i]), gt, photo, hit)
        estimates[name] = params
        mask = metrics.evaluation_mask(hit, np.isin(frag.object_id, emitter_ids))
        baseline.append(metrics.evaluate_view({k: est[k] for k in gt}, gt, mask))

        imageio.write_image(out / "photos" / f"{name}.exr", photo, half=True, compression="dwaa:90",
                            timestamp=EXR_TIMESTAMP)
        imageio.write_image(out / "photos" / f"{name}.png", photo)
        targets = {}
        for key, values in est.items():
            targets[key] = out / "targets" / key / f"{name}{MAP_FILES[key]}"
            write_map(targets[key], key, values)
        view_list.append(View(name=name, camera=cam, photo=out / "photos" / f"{name}.exr", targets=targets))
    times["render_s"], times["aov_check_s"] = t_render, t_aov

    t0 = time.perf_counter()
    irradiance = write_irradiance(out, names, cams, mesh, gt_tex, spp=irradiance_spp, seed=seed)
    view_list = [dataclasses.replace(v, ground_truth={"irradiance": path}) for v, path in zip(view_list, irradiance)]
    times["irradiance_s"] = time.perf_counter() - t0

    # the photos as RGB<->X sees them: one scene-wide exposure by Hypersim's rule (as every HDR
    # import gets), measured on the EXR files as written (half float, DWAA)
    stops = scene_exposure(imageio.read_image(v.photo)[..., :3] for v in view_list)
    view_list = [dataclasses.replace(v, exposure=stops) for v in view_list]
    write_scene(Scene(name="bedroom", mesh=mesh, views=tuple(view_list), texture_layout="pages"), out)
    write_gt_json(out, [n for n, _, _ in objs], EMITTER_OBJECTS)
    (out / "estimates.json").write_text(json.dumps({"seed": seed, "model": ESTIMATE_MODEL, "views": estimates}, indent=1))
    write_preview(out)
    check = irradiance_check(out)
    return {"objects": len(objs), "faces": mesh.num_faces, "page_sizes": dict(zip(mesh.object_names, sizes)),
            "views": len(cams), "exposure": stops, "agreement": agreement, "baseline": metrics.aggregate(baseline),
            "irradiance": {"spp": irradiance_spp, "seconds": times["irradiance_s"], "consistency": check},
            "times": times}


def write_irradiance(out: Path, names, cams, mesh: Mesh, pages, *, spp: int, seed: int, progress: bool = True) -> list[Path]:
    """Renders every view's irradiance E / pi (`jaxdistill.datasets.mitsuba.bedroom.render_irradiance`:
    the photos' Mitsuba scene, paths one bounce shorter than theirs), applies the photos' Gaussian
    pixel filter and writes out/ground_truth/irradiance/<view>.exr (half float, linear, the photos'
    units: not exposed); returns the paths."""
    images = bedroom_mitsuba.render_irradiance(mesh, pages, cams, spp=spp, seed=seed, progress=progress)
    paths = []
    for name, image in zip(names, images):
        path = out / "ground_truth" / "irradiance" / f"{name}.exr"
        imageio.write_image(path, gaussian_blur(image, PIXEL_FILTER_SIGMA), half=True, compression=IRRADIANCE_COMPRESSION,
                            timestamp=EXR_TIMESTAMP)
        paths.append(path)
    return paths


def irradiance_check(folder: Path, views=None) -> dict:
    """photo against albedo x irradiance GT of the folder's views, from the files
    (`jaxdistill.evaluate.consistency.scene_consistency`)."""
    from jaxdistill.evaluate.consistency import scene_consistency
    from jaxdistill.scene.model import read_scene

    return scene_consistency(read_scene(folder), views)


def irradiance_section(info: dict) -> str:
    """The README's section on the irradiance ground truth (`info`: spp, seconds, consistency)."""
    from jaxdistill.evaluate.consistency import DIFFUSE_COSINE, DIFFUSE_ROUGHNESS

    c = info["consistency"]
    d, e, a = c["diffuse"], c["dielectric"], c["all_valid"]
    return f"""## Irradiance ground truth
`ground_truth/irradiance/<view>.exr` (each view's `ground_truth.irradiance`): E/pi at each pixel's
first hit, linear, in the photos' units (not exposed; half float, DWAA level 90), so a diffuse
pixel of the photo is albedo x irradiance. Rendered from the photos' own Mitsuba scene
(`jaxdistill.datasets.mitsuba.bedroom`) with the intrinsic integrator's irradiance estimator
(`bridge.intrinsic_integrator(photo=False)`: emitter sampling and a cosine-sampled ray traced on
by `path`, MIS-combined; paths one bounce shorter than the photos' max depth 6), `llvm_ad_rgb`,
{info['spp']} spp, box filter, then the photos' Gaussian pixel filter (sigma {PIXEL_FILTER_SIGMA} px);
{info['seconds']:.0f} s for all views here. `python scripts/make_bedroom.py --irradiance_only` rebuilds them alone.

photo / (albedo x irradiance), brightness per pixel, albedo from gt.json through our sampler at
pixel centres: on {d['pixels']} diffuse pixels (evaluated, metallic 0, roughness >= {DIFFUSE_ROUGHNESS},
view cosine >= {DIFFUSE_COSINE}) median **{d['median_ratio']:.3f}** (10th-90th percentile {d['p10']:.3f}-{d['p90']:.3f}),
ratio of sums {d['sum_ratio']:.3f}; all {e['pixels']} dielectric pixels: median {e['median_ratio']:.3f};
all {a['pixels']} evaluated pixels, metals included: median {a['median_ratio']:.3f}. Mitsuba's principled
BSDF is not Lambertian: its dielectric specular lobe adds reflection on top of albedo x E/pi (the
darker the albedo, the larger its share: median ratio 1.46 below albedo brightness 0.1, 1.08 above
0.5) and its diffuse lobe brightens rough surfaces lit or seen at grazing angles. The estimator
itself is exact: the same scene with Lambertian `diffuse` BSDFs on the same albedo, photo and
irradiance rendered alike (views 0 and 24 at 160x120, 128 spp), gives medians 1.002 and 0.999
on these pixels, where the principled scene gives 1.098 and 1.076.
"""


def manifest(folder: Path) -> dict[str, str]:
    """sha256 of every file under folder except README.md and the manifest itself."""
    return {p.relative_to(folder).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file() and p.name not in ("README.md", "manifest.sha256")}


def readme(summary: dict, args, total_s: float) -> str:
    """The scene folder's README: what is in it, how it was made, agreement and baseline figures."""
    agree = summary["agreement"]
    psnr = np.array([a["psnr_db"] for a in agree])
    match = np.array([a["match_fraction"] for a in agree])
    hits = np.array([a["hit_agreement"] for a in agree])
    base = summary["baseline"]
    rows = "\n".join(f"| {k} | {v:.4g} |" for k, v in base.items() if k != "num_views")
    pages = ", ".join(f"{n} {s}" for n, s in summary["page_sizes"].items())
    t = summary["times"]
    return f"""# Embedded bedroom scene

Procedural bedroom generated by `scripts/make_bedroom.py` (seed {args.seed}):
{summary['objects']} objects, {summary['faces']} triangles, {summary['views']} views of {args.width}x{args.height},
photos path traced by Mitsuba 3 (`scalar_rgb`, `path`, max depth 6, {args.spp} spp, box pixel filter),
then a Gaussian pixel filter (sigma {PIXEL_FILTER_SIGMA} px) in NumPy, like Mitsuba's default filter but
deterministic (Mitsuba's own adds overlapping image blocks in thread order, so the last bits vary).
Light: sun and sky through the window opening, a ceiling light panel and the bedside lamp's bulb.
Every view's `exposure` ({summary['exposure']:+.2f} stops) is Hypersim's rule on these photos (90th-percentile
brightness to 0.8 after gamma), as RGB<->X was trained and as every HDR import gets it.

    python scripts/make_bedroom.py --seed={args.seed} --views={args.views} --spp={args.spp} --width={args.width} --height={args.height} --irradiance_spp={args.irradiance_spp}

Generation took {total_s / 60:.1f} min on the machine that made this folder (2 CPU cores):
geometry, textures and views {t['geometry_textures_views_s']:.0f} s, GT maps {t['gt_maps_s']:.0f} s,
photos {t['render_s']:.0f} s, Mitsuba AOV check {t['aov_check_s']:.0f} s, irradiance {t['irradiance_s']:.0f} s. `manifest.sha256` lists
every file but this README; `python scripts/make_bedroom.py --verify` regenerates the folder in a
temporary directory and compares (same versions and platform: bit for bit).

![photo, albedo, normal, roughness and irradiance targets of four views](preview.jpg)

## Files
- `preview.jpg`: four views; columns photo, then the albedo, normal, roughness and irradiance targets.
- `scene.json`, `mesh.glb`: the scene in jaxdistill's format (one texture page per object).
- `photos/<view>.exr` (linear, half float, lossy DWAA compression at level 90, below the Monte Carlo noise) and `photos/<view>.png` (sRGB).
- `targets/<map>/<view>`: per-view estimates for the `views` prior, standing in for a monocular
  estimator (see below). albedo PNG sRGB; roughness, metallic PNG values in [0, 1]; normal PNG
  (n+1)/2, camera space x right, y up, z towards the camera; irradiance PNG sRGB (exposed into [0, 1]).
- `gt/textures/<map>/<object>.png`: ground-truth albedo (sRGB PNG), roughness and metallic (linear
  PNG); the 8-bit values are the ground truth, and Mitsuba rendered exactly these.
  Page sizes: {pages}.
- `gt.json`: how to evaluate: sample the GT textures through the scene's UVs with the bilinear
  sampler; normals come from the geometry; pixels of the emitters (`lamp_bulb`, `ceiling_light`) are excluded.
- `estimates.json`: the corruption parameters of every view.
- `ground_truth/irradiance/<view>.exr`: per-view irradiance E/pi (see below).

{irradiance_section(summary['irradiance'])}
## Our sampler against Mitsuba
Mitsuba's `aov` albedo at pixel centres against GT albedo from our gather sampler, over pixels
both hit ({len(agree)} views): PSNR median {np.median(psnr):.1f} dB (min {psnr.min():.1f}),
pixels within 2/255 in every channel: median {np.median(match):.4f} (min {match.min():.4f}),
hit masks agree on {np.median(hits):.5f} of pixels (median). Cameras, UVs and texture
orientation therefore match an independent renderer.

## Per-view estimates (the baseline distillation must beat)
{ESTIMATE_MODEL}
Their error against GT, mean over views (albedo metrics on sRGB-encoded values):

| metric | value |
|---|---|
{rows}

Licence: generated content of jaxdistill, same licence as the package.
"""


# ----------------------------------------------------------------------------- irradiance alone

GEOMETRY_TOLERANCE = 1e-5     # metres / uv units: the folder's mesh.glb (float32) against the rebuilt one


def rebuilt_mesh(scene):
    """The generator's own mesh (float64, as make_bedroom renders it), checked against the folder's."""
    objs = bedroom_objects()
    mesh, _ = build_scene_geometry(objs)
    if tuple(mesh.object_names) != tuple(scene.mesh.object_names) or mesh.faces.shape != scene.mesh.faces.shape:
        raise ValueError(f"{scene.root}: its objects or faces differ from py's bedroom")
    corners = [(np.asarray(m.vertices)[np.asarray(m.faces)], np.asarray(m.uv), np.asarray(m.face_object))
               for m in (mesh, scene.mesh)]
    (a, ua, oa), (b, ub, ob) = corners
    if not (np.array_equal(oa, ob) and np.abs(a - b).max() < GEOMETRY_TOLERANCE and np.abs(ua - ub).max() < GEOMETRY_TOLERANCE):
        raise ValueError(f"{scene.root}: its mesh differs from py's bedroom")
    return mesh


def add_ground_truth(folder: Path, paths: dict[str, Path]) -> None:
    """Adds `ground_truth.irradiance` to every view of folder/scene.json, as write_scene writes it
    (after `targets`, relative paths), every other byte unchanged."""
    file = folder / "scene.json"
    text = file.read_text()
    doc = json.loads(text)
    if json.dumps(doc, indent=1) != text:
        raise ValueError(f"{file}: not in write_scene's layout (json indent 1); refusing to rewrite it")
    for entry in doc["views"]:
        ground_truth = {k: v for k, v in entry.get("ground_truth", {}).items() if k != "irradiance"}
        ground_truth["irradiance"] = os.path.relpath(paths[entry["name"]], folder).replace(os.sep, "/")
        entry.pop("ground_truth", None)
        entry["ground_truth"] = ground_truth
    tmp = file.with_suffix(".json.tmp")
    tmp.write_text(json.dumps(doc, indent=1))
    os.replace(tmp, file)


def update_readme(folder: Path, section: str) -> None:
    """Replaces (or inserts before '## Our sampler against Mitsuba') the README's irradiance section."""
    path = folder / "README.md"
    text = path.read_text() if path.is_file() else ""
    pattern = re.compile(r"## Irradiance ground truth\n.*?(?=\n## |\Z)", re.S)
    if pattern.search(text):
        text = pattern.sub(lambda _: section, text)
    elif "## Our sampler against Mitsuba" in text:
        text = text.replace("## Our sampler against Mitsuba", section + "\n## Our sampler against Mitsuba")
    else:
        text += "\n" + section
    if "- `ground_truth/irradiance/<view>.exr`" not in text:
        text = text.replace("- `estimates.json`: the corruption parameters of every view.\n",
                            "- `estimates.json`: the corruption parameters of every view.\n"
                            "- `ground_truth/irradiance/<view>.exr`: per-view irradiance E/pi (see below).\n")
    path.write_text(text)


def irradiance_main(argv=None) -> int:
    parser = argparse.ArgumentParser(description="re-renders the bedroom's irradiance ground truth alone")
    parser.add_argument("--scene", type=Path, default=DEFAULT_OUT, help="the bedroom's folder")
    parser.add_argument("--seed", type=int, default=0, help="the seed py made the folder with")
    parser.add_argument("--spp", type=int, default=IRRADIANCE_SPP)
    args = parser.parse_args(argv)
    if args.spp < 1:
        parser.error("--spp must be >= 1")
    folder = args.scene
    scene = read_scene(folder)
    mesh = rebuilt_mesh(scene)
    pages = read_ground_truth(scene).pages            # what make_bedroom's write_textures returned
    names = [v.name for v in scene.views]
    start = time.perf_counter()
    paths = write_irradiance(folder, names, [v.camera for v in scene.views], mesh, pages,
                             spp=args.spp, seed=args.seed)
    seconds = time.perf_counter() - start
    add_ground_truth(folder, dict(zip(names, paths)))
    check = irradiance_check(folder)
    hashes = manifest(folder)
    (folder / "manifest.sha256").write_text("".join(f"{h}  {p}\n" for p, h in hashes.items()))
    update_readme(folder, irradiance_section({"spp": args.spp, "seconds": seconds, "consistency": check}))
    d = check["diffuse"]
    size = sum(p.stat().st_size for p in paths)
    print(f"{len(paths)} views, {args.spp} spp in {seconds:.0f} s ({size / 2**20:.2f} MiB); photo / (albedo x irradiance) "
          f"on {d['pixels']} diffuse pixels: median {d['median_ratio']:.3f} (p10 {d['p10']:.3f}, p90 {d['p90']:.3f}), "
          f"ratio of sums {d['sum_ratio']:.3f}; dielectric median {check['dielectric']['median_ratio']:.3f}, "
          f"all {check['all_valid']['median_ratio']:.3f}")
    return 0


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    if "--irradiance_only" in argv:        # re-render the irradiance ground truth of an existing folder
        return irradiance_main([a for a in argv if a != "--irradiance_only"])
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--out", type=Path, default=DEFAULT_OUT)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--views", type=int, default=48)
    parser.add_argument("--width", type=int, default=320)
    parser.add_argument("--height", type=int, default=240)
    parser.add_argument("--spp", type=int, default=64)
    parser.add_argument("--irradiance_spp", type=int, default=IRRADIANCE_SPP, help="samples of the irradiance ground truth")
    parser.add_argument("--verify", action="store_true", help="regenerate in a temp dir and compare with --out")
    args = parser.parse_args(argv)
    for name in ("views", "width", "height", "spp", "irradiance_spp"):
        if getattr(args, name) < 1:
            parser.error(f"--{name} must be >= 1")
    if args.verify:
        expected = (args.out / "manifest.sha256").read_text().split("\n") if (args.out / "manifest.sha256").exists() else None
        if expected is None:
            parser.error(f"{args.out / 'manifest.sha256'}: missing; generate the scene first")
        with tempfile.TemporaryDirectory() as tmp:
            start = time.perf_counter()
            generate(Path(tmp), seed=args.seed, views=args.views, width=args.width, height=args.height, spp=args.spp,
                     irradiance_spp=args.irradiance_spp)
            got = [f"{h}  {p}" for p, h in manifest(Path(tmp)).items()]
        want = [line for line in expected if line]
        diff = sorted(set(got) ^ set(want))
        print(f"regenerated in {(time.perf_counter() - start) / 60:.1f} min: {len(got)} files, "
              f"{len(diff)} lines differ" + "".join(f"\n  {d}" for d in diff[:20]))
        return 1 if diff else 0
    start = time.perf_counter()
    if args.out.exists():
        shutil.rmtree(args.out)
    summary = generate(args.out, seed=args.seed, views=args.views, width=args.width, height=args.height, spp=args.spp,
                       irradiance_spp=args.irradiance_spp)
    total = time.perf_counter() - start
    (args.out / "manifest.sha256").write_text("".join(f"{h}  {p}\n" for p, h in manifest(args.out).items()))
    (args.out / "README.md").write_text(readme(summary, args, total))
    size = sum(p.stat().st_size for p in args.out.rglob("*") if p.is_file())
    print(json.dumps({k: summary[k] for k in ("objects", "faces", "views", "baseline", "times")}, indent=1))
    print(f"wrote {args.out} ({size / 2**20:.1f} MiB) in {total / 60:.1f} min")
    return 0


if __name__ == "__main__":
    sys.exit(main())
