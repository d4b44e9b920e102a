"""FIPT / IRIS synthetic scenes (Bitterli's kitchen, bathroom, bedroom, living room as FIPT ships them).

Layout of one scene folder:

    scene.obj                          the geometry (objects = OBJ groups; UVs kept if usable)
    <split>/transforms.json            camera_angle_x (radians) + frames[i].transform_matrix
    <split>/Image/{i:03d}_0001.exr     HDR photo of frame i (IRIS's LDR scenes: .png, sRGB)
    <split>/DiffCol/{i:03d}_0001.exr   GT diffuse colour  -> our albedo ground truth
    <split>/Roughness/{i:03d}_0001.exr GT roughness       -> our roughness ground truth
    <split>/albedo/{i:03d}.exr         GT reflectance integral (kept out: not a texture value)
    <split>/Emit/{i:03d}_0001.exr      emission: pixels > 0 are emitters, masked out

Camera convention (checked against FIPT's ray generation, `get_ray_directions` / `get_rays`):
the ray of pixel (i, j) is R [-(i + .5 - W/2) / f, -(j + .5 - H/2) / f, 1], f = W / 2 /
tan(camera_angle_x / 2): camera x left, y up, z forward (`cameras.from_fipt`). Frames are
numbered by their position in `frames`. Emitter masks are written to `<work_dir>/masks/`.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from jaxdistill.scene import cameras
from jaxdistill.io import images as imageio
from jaxdistill.datasets.common import ImportOptions, ViewSource, build_scene, default_work_dir
from jaxdistill.errors import InputError, ProblemList, read_json

PHOTO_EXTENSIONS = {"fipt": (".exr", ".png"), "iris": (".png", ".exr")}
EMITTER_THRESHOLD = 1e-6      # emission above this (any channel) marks an emitter pixel


def frame_stem(index: int) -> str:
    return f"{index:03d}_0001"


def load_fipt(path, options: ImportOptions = ImportOptions(), *, split: str = "train", photos: str = "fipt",
              report: dict | None = None):
    """Scene of a FIPT/IRIS scene folder; photos "fipt" prefers the HDR .exr, "iris" the LDR .png."""
    root = Path(path)
    split_dir = root / split
    transforms = split_dir / "transforms.json"
    file = os.fspath(transforms)
    if photos not in PHOTO_EXTENSIONS:
        raise InputError.single("options", "photos", f"expected fipt or iris, got {photos!r}")
    meta = read_json(transforms, f"not found: give a FIPT scene folder holding {split}/transforms.json")
    problems = ProblemList()
    frames = meta.get("frames") if isinstance(meta, dict) else None
    if not isinstance(frames, list) or not frames:
        raise InputError.single(file, "frames", "expected a non-empty list of frames")
    if "camera_angle_x" not in meta:
        problems.add(file, "camera_angle_x", "required field is missing (horizontal field of view, radians)")
    image_dir = split_dir / "Image"
    work_dir = Path(options.work_dir) if options.work_dir else default_work_dir(root)
    views = []
    for i, frame in enumerate(frames):
        where = f"frames[{i}]"
        stem = frame_stem(i)
        photo = next((image_dir / (stem + ext) for ext in PHOTO_EXTENSIONS[photos]
                      if (image_dir / (stem + ext)).is_file()), None)
        if photo is None:
            problems.add(file, where, f"photo not found: {image_dir / stem}"
                         f"{{{','.join(PHOTO_EXTENSIONS[photos])}}} (frame {i} of {len(frames)}: "
                         f"{len(list(image_dir.glob('*_0001.*'))) if image_dir.is_dir() else 0} photos in {image_dir})")
            continue
        if not isinstance(frame, dict) or "transform_matrix" not in frame or "camera_angle_x" not in meta:
            if isinstance(frame, dict) and "transform_matrix" not in frame:
                problems.add(file, f"{where}.transform_matrix", "required field is missing")
            continue
        try:
            width, height, _ = imageio.image_size(photo)
            camera = cameras.from_fipt(frame["transform_matrix"], meta["camera_angle_x"], width, height)
        except (ValueError, OSError) as err:
            problems.add(file, where, str(err))
            continue
        ground_truth = {m: split_dir / folder / f"{stem}.exr" for m, folder in (("albedo", "DiffCol"),
                                                                               ("roughness", "Roughness"))
                        if (split_dir / folder / f"{stem}.exr").is_file()}
        emit = split_dir / "Emit" / f"{stem}.exr"
        mask = _emitter_mask(emit, work_dir / "masks" / f"{stem}.png") if emit.is_file() else None
        views.append(ViewSource(name=stem, camera=camera, photo=photo, mask=mask, ground_truth=ground_truth))
    problems.raise_if_any()
    return build_scene(root.name, root, root / "scene.obj", views, options, source_file=file, report=report)


def _emitter_mask(emit: Path, out: Path) -> Path:
    """Writes out (grey PNG, 1 = not an emitter) from an emission image; returns out."""
    emission = imageio.read_image(emit)
    keep = ~(np.nan_to_num(emission[..., :3], nan=0.0) > EMITTER_THRESHOLD).any(axis=-1)
    imageio.write_image(out, keep.astype(np.float32), encode_srgb=False)
    return out
