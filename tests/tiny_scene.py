"""A tiny distillation scene written by the tests: a box room, GT textures, photos and noisy targets.

Six walls (one page each, 16x16 GT textures), `views` cameras inside the room looking at
different walls, photos = albedo x a smooth shading, per-view targets = GT maps with a per-view
gain and noise (what a monocular estimator gives), and gt.json in the embedded bedroom's format.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from jaxdistill.scene import cameras
from jaxdistill.io import images as imageio
from jaxdistill.evaluate.ground_truth import camera_normals, face_normals
from jaxdistill.render import fragments as fr
from jaxdistill.render.sampler import sample_pages
from jaxdistill.scene.model import Scene, View, write_scene
from jaxdistill.scene.shapes import box_room

PAGE = 16


def write_tiny_scene(folder, *, views: int = 4, width: int = 32, height: int = 24, seed: int = 0,
                     targets: bool = True, gt: bool = True) -> Path:
    """Writes the scene into `folder`; returns the path of scene.json."""
    folder = Path(folder)
    rng = np.random.default_rng(seed)
    mesh = box_room(size=(4.0, 2.5, 3.0), subdivisions=1)
    n = len(mesh.object_names)
    albedo = [np.clip(rng.uniform(0.2, 0.8, 3) + 0.1 * rng.normal(size=(PAGE, PAGE, 3)), 0.05, 0.95) for _ in range(n)]
    rough = [np.full((PAGE, PAGE, 1), rng.uniform(0.3, 0.9)) for _ in range(n)]
    metal = [np.full((PAGE, PAGE, 1), rng.uniform(0.0, 0.2)) for _ in range(n)]
    K = cameras.intrinsics_from_fov(70.0, width, height)
    cams = []
    centre = np.array([2.0, 1.25, 1.5])
    for i in range(views):
        angle = 2 * np.pi * i / views
        target = centre + np.array([np.cos(angle), -0.2, np.sin(angle)])
        eye = centre + 0.3 * np.array([-np.cos(angle), 0.0, -np.sin(angle)])
        cams.append(cameras.look_at(eye, target, np.array([0.0, 1.0, 0.0]), K, width, height))
    frags = fr.compute_fragments(mesh, cams, cache_dir=False, progress=False)
    pages = [np.concatenate([a, r, m], -1).astype(np.float32) for a, r, m in zip(albedo, rough, metal)]
    gt_views = sample_pages(pages, frags, range(n))
    scene_views = []
    for i, (cam, frag, g) in enumerate(zip(cams, frags, gt_views)):
        name = f"v{i}"
        yy, xx = np.mgrid[0:height, 0:width] / max(width, height)
        shading = (0.6 + 0.8 * np.exp(-((xx - 0.3) ** 2 + (yy - 0.4) ** 2) * 4))[..., None]
        photo = np.where(frag.hit[..., None], g[..., :3] * shading, 0.0)
        imageio.write_image(folder / "photos" / f"{name}.exr", photo)
        paths = {}
        if targets:
            gain = np.exp(rng.normal(0, 0.1, 3))
            est = {"albedo": np.clip(g[..., :3] * gain + 0.03 * rng.normal(size=(height, width, 3)), 0, 1),
                   "roughness": np.clip(g[..., 3:4] + 0.05 * rng.normal(size=(height, width, 1)), 0, 1),
                   "metallic": np.clip(g[..., 4:5] + 0.03 * rng.normal(size=(height, width, 1)), 0, 1),
                   "irradiance": np.clip(np.repeat(shading, 3, -1) / 2.0, 0, 1),
                   "normal": 0.5 * (camera_normals(face_normals(mesh), frag.triangle, cam) + 1.0)}
            for key, values in est.items():
                paths[key] = folder / "targets" / key / f"{name}.png"
                imageio.write_image(paths[key], np.where(frag.hit[..., None], values, 0.0),
                                    encode_srgb=key in ("albedo", "irradiance"))
        scene_views.append(View(name=name, camera=cam, photo=folder / "photos" / f"{name}.exr", targets=paths))
    path = write_scene(Scene(name="tiny", mesh=mesh, views=tuple(scene_views), texture_layout="pages"), folder)
    if gt:
        for k, obj in enumerate(mesh.object_names):
            imageio.write_image(folder / "gt" / "albedo" / f"{obj}.png", albedo[k])
            imageio.write_image(folder / "gt" / "roughness" / f"{obj}.png", rough[k], encode_srgb=False)
            imageio.write_image(folder / "gt" / "metallic" / f"{obj}.png", metal[k], encode_srgb=False)
        doc = {"format": "jaxdistill-gt", "version": 1,
               "textures": {m: {o: f"gt/{m}/{o}.png" for o in mesh.object_names}
                            for m in ("albedo", "roughness", "metallic")},
               "texture_encoding": {"albedo": "srgb", "roughness": "linear", "metallic": "linear"},
               "normal": "geometry", "exclude_objects": [], "sampler": "bilinear"}
        (folder / "gt.json").write_text(json.dumps(doc))
    return path
