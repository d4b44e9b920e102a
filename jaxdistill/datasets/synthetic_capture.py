"""A capture-sized synthetic room, written as a scene folder, for scale benchmarks and tests.

`write_capture_room` builds a `box_room` with furniture whose walls are subdivided to the face
count asked for (2 n² triangles per wall patch; n = 300 gives about 1.1M faces), the cameras of a
walk round it (`shapes.walkthrough_cameras`) at the resolution asked for, and, per view, photos
and exact per-view maps (the `views` prior's targets) made by our own ray casts, with no path
tracer: the albedo is a per-object colour times a checker of the object's UVs, the irradiance
falls off with distance from the camera (a head lamp) and is warm-tinted, and the photo is
albedo × irradiance, sRGB-encoded. Every random choice comes from `seed`, so the same arguments
write the same files (the same pixels in the EXRs, whose headers hold a write time). It is a
scale test's scene: its maps are simple, and it has no texture ground truth (`gt.json`), so a
run on it is timed and sized, not scored (`python -m jaxdistill.main --scene=DIR --prior=views`).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from tqdm import tqdm

from jaxdistill.io import images as imageio
from jaxdistill.render import fragments as fr
from jaxdistill.scene import shapes
from jaxdistill.scene.cameras import Camera, camera_normals
from jaxdistill.scene.mesh import Mesh, face_normals
from jaxdistill.scene.model import Scene, View, write_scene
from jaxdistill.threads import ordered_map

ROOM_SIZE = (6.0, 3.0, 5.0)          # metres, y up


def capture_room_mesh(faces_per_side: int) -> Mesh:
    """The room (walls subdivided `faces_per_side` times) with a bed, a table and a wardrobe."""
    if faces_per_side < 1:
        raise ValueError(f"faces_per_side must be >= 1, got {faces_per_side}")
    return shapes.box_room(ROOM_SIZE, subdivisions=faces_per_side, furniture=True,
                           furniture_subdivisions=max(1, faces_per_side // 8), atlas=False)


def write_capture_room(folder: str | Path, *, faces_per_side: int = 300, views: int = 50, width: int = 876,
                       height: int = 584, seed: int = 0, cameras: list[Camera] | None = None,
                       mesh: Mesh | None = None, progress: bool = True) -> dict:
    """Writes the scene folder (mesh.glb, scene.json, photos/, targets/); returns a summary.
    `cameras` and `mesh` replace the walk and the room (a benchmark that keeps its own)."""
    folder = Path(folder)
    mesh = capture_room_mesh(faces_per_side) if mesh is None else mesh
    cams = shapes.walkthrough_cameras(views, ROOM_SIZE, width, height, seed=seed) if cameras is None else cameras
    rng = np.random.default_rng(seed)
    objects = len(mesh.object_names)
    base = rng.uniform(0.15, 0.85, (objects, 3)).astype(np.float32)
    rough = rng.uniform(0.2, 0.9, objects).astype(np.float32)
    metal = (rng.uniform(size=objects) < 0.2).astype(np.float32) * 0.9
    tint = np.array([1.0, 0.95, 0.85], np.float32)
    normals = face_normals(mesh)
    caster = fr.RayCaster(mesh)              # the mesh's ray-cast structure, built once

    def write_view(item) -> View:
        i, cam, hits = item
        frag = fr.derive_fragments(mesh, cam, *hits)
        hit = frag.hit
        obj = np.where(hit, frag.object_id, 0)
        u, v = frag.uv[..., 0], frag.uv[..., 1]
        checker = ((np.floor(u * 16) + np.floor(v * 16)) % 2).astype(np.float32)
        albedo = base[obj] * (0.75 + 0.25 * checker[..., None]) * hit[..., None]
        depth = np.where(hit, frag.depth, 0.0)
        irradiance = (1.5 / (1.0 + 0.1 * depth ** 2))[..., None] * tint * hit[..., None]
        name = f"view_{i:03d}"
        paths = {"albedo": folder / "targets/albedo" / f"{name}.png",
                 "normal": folder / "targets/normal" / f"{name}.png",
                 "roughness": folder / "targets/roughness" / f"{name}.png",
                 "metallic": folder / "targets/metallic" / f"{name}.png",
                 "irradiance": folder / "targets/irradiance" / f"{name}.exr"}
        imageio.write_image(paths["albedo"], albedo)
        imageio.write_image(paths["normal"], 0.5 * (camera_normals(normals, frag.triangle, cam) + 1.0),
                            encode_srgb=False)
        imageio.write_image(paths["roughness"], rough[obj] * hit, encode_srgb=False)
        imageio.write_image(paths["metallic"], metal[obj] * hit, encode_srgb=False)
        imageio.write_image(paths["irradiance"], irradiance, half=True)
        photo = folder / "photos" / f"{name}.png"
        imageio.write_image(photo, np.clip(albedo * irradiance, 0.0, 1.0))
        return View(name=name, camera=cam, photo=photo, targets=paths)

    # a view at a time (memory does not grow with the views): cast here, the rest of a view (NumPy and
    # the image writes, each view's own files) in `ordered_map`'s two threads, the views in order
    bar = tqdm(cams, desc="capture views", unit="view", disable=not progress, dynamic_ncols=True)
    casts = ((i, cam, fr.cast_view(caster, cam)) for i, cam in enumerate(bar))
    out_views = list(ordered_map(write_view, casts))
    write_scene(Scene(name=f"capture_room_{mesh.num_faces}", mesh=mesh, views=tuple(out_views),
                      texture_layout="pages", root=folder), folder)
    return {"faces": int(mesh.num_faces), "objects": objects, "views": len(out_views),
            "width": int(cams[0].width), "height": int(cams[0].height)}
