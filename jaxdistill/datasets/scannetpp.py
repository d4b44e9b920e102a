"""ScanNet++ DSLR scenes: the laser-scan mesh, undistorted DSLR photos and their nerfstudio poses.

Layout of one scene of the release (`data/<scene_id>/`):

    scans/mesh_aligned_0.05.ply                     laser scan, no UVs (unwrapped on import)
    dslr/nerfstudio/transforms_undistorted.json     PINHOLE fl_x, fl_y, cx, cy, w, h; frames with
                                                    file_path, transform_matrix, is_bad; test_frames
    dslr/undistorted_images/*.JPG                   (or resized_undistorted_images/, whichever has
                                                    the json's w x h)
    dslr/undistorted_anon_masks/*.png               anonymisation masks, optional, read as 1 = use the
                                                    pixel, 0 = anonymised (a warning when most are 0)

Poses: ScanNet++ writes `transform_matrix` from its COLMAP poses (common/utils/nerfstudio.py::
convert_frames) with the camera's y and z negated AND the world permuted (rows x and y swapped,
z negated), so the json's poses are not in the mesh's world. `cameras.from_scannetpp`
re-orthogonalises the rotation (the poses are slightly non-orthogonal), undoes the world
permutation (`cameras.SCANNETPP_WORLD`), inverts the camera's X and Z axes as the thesis's
appendix B.2 does (a PyTorch3D camera, x left, y up, z forward), then Algorithm 1. Algorithm 2
turns pixel intrinsics into PyTorch3D NDC; ours stay in pixels, the same camera. The mesh is
read as released. Bad frames (`is_bad`)
are skipped; split "train" reads `frames`, "test" `test_frames`, "all" both.
"""

from __future__ import annotations

import dataclasses
import logging
import os
from pathlib import Path

from jaxdistill.io import images as imageio
from jaxdistill.datasets.common import ImportOptions, build_scene
from jaxdistill.datasets.nerfstudio import read_transforms
from jaxdistill.errors import InputError

MESH = Path("scans") / "mesh_aligned_0.05.ply"
TRANSFORMS = Path("dslr") / "nerfstudio" / "transforms_undistorted.json"
DISTORTED = Path("dslr") / "nerfstudio" / "transforms.json"
UNDISTORT_HINT = ("run ScanNet++'s undistortion first: in a checkout of github.com/scannetpp/scannetpp, set "
                  "data_root (and scene_ids: [<scene_id>]) in dslr/configs/undistort.yml and run "
                  "`python -m dslr.undistort dslr/configs/undistort.yml`; it writes "
                  "dslr/undistorted_images/, dslr/undistorted_anon_masks/ and this file")
IMAGE_FOLDERS = ("undistorted_images", "resized_undistorted_images")
MASK_FOLDERS = {"undistorted_images": "undistorted_anon_masks", "resized_undistorted_images": "resized_undistorted_masks"}
log = logging.getLogger(__name__)
SPLITS = {"train": ("frames",), "test": ("test_frames",), "all": ("frames", "test_frames")}


def load_scannetpp(path, options: ImportOptions = ImportOptions(), *, split: str = "train",
                   report: dict | None = None):
    """Scene of a ScanNet++ scene folder (`data/<scene_id>`), DSLR photos of `split`."""
    root = Path(path)
    transforms = root / TRANSFORMS
    if split not in SPLITS:
        raise InputError.single("options", "split", f"unknown split {split!r}; use {', '.join(SPLITS)}")
    if not transforms.is_file() and (root / DISTORTED).is_file():
        raise InputError.single(os.fspath(transforms), "(file)", f"not found; only the distorted (fisheye) "
                                f"{DISTORTED.as_posix()} is there, which jaxdistill does not read: {UNDISTORT_HINT}")
    if not transforms.is_file():
        raise InputError.single(os.fspath(transforms), "(file)", "not found: give the scene folder data/<scene_id> "
                                "holding dslr/nerfstudio/transforms_undistorted.json")
    views, _ = read_transforms(transforms, pose="scannetpp", frame_keys=SPLITS[split])
    if not views:
        raise InputError.single(os.fspath(transforms), SPLITS[split][0], "no usable frames (all is_bad or none)")
    dslr = root / "dslr"
    folder = _image_folder(dslr, views[0], os.fspath(transforms))
    placed = []
    for v in views:
        name = Path(v.photo).name
        mask = dslr / MASK_FOLDERS[folder] / f"{Path(name).stem}.png"
        placed.append(dataclasses.replace(v, photo=dslr / folder / name, mask=mask if mask.is_file() else None))
    first_mask = next((v.mask for v in placed if v.mask is not None), None)
    if first_mask is not None:
        kept = float((imageio.read_image(first_mask, linear=False)[..., 0] >= 0.5).mean())
        if kept < 0.5:
            log.warning("%s keeps only %.0f %% of the pixels: masks are read as 1 = use the pixel, 0 = anonymised; "
                        "invert them if yours mark the anonymised pixels with 1", first_mask, 100 * kept)
    return build_scene(root.name, root, root / MESH, placed, options, source_file=os.fspath(transforms), report=report)


def _image_folder(dslr: Path, first, file: str) -> str:
    """The image folder whose copy of the first frame has the json's size."""
    name = Path(first.photo).name
    seen = []
    for folder in IMAGE_FOLDERS:
        candidate = dslr / folder / name
        if candidate.is_file():
            width, height, _ = imageio.image_size(candidate)
            if (width, height) == (first.camera.width, first.camera.height):
                return folder
            seen.append(f"{folder}/{name} is {width}x{height}")
    found = "; ".join(seen) if seen else f"{name} is in none of {', '.join(IMAGE_FOLDERS)}"
    raise InputError.single(file, "w/h", f"no undistorted image folder matches {first.camera.width}x"
                            f"{first.camera.height} ({found}) under {dslr}")
