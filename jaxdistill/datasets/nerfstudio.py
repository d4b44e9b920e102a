"""NeRF / nerfstudio `transforms.json` scenes (also what ScanNet++ ships for its DSLR photos).

Format: intrinsics at the top level or per frame (a frame's keys win): `fl_x, fl_y, cx, cy,
w, h` in pixels, or `camera_angle_x` (radians, centred principal point; Blender/NeRF
synthetic); `camera_model` "PINHOLE" (default) or "OPENCV" with `k1, k2, p1, p2` (photos are
undistorted, see `undistort.py`); frames `{"file_path", "transform_matrix", "mask_path"?}`
with OpenGL camera-to-world matrices (x right, y up, looking along -z). Paths are relative to
the json's folder; a file_path without extension (Blender NeRF scenes) gets the first of
.png/.jpg/.exr that exists. The mesh must be in the frames' world space: nerfstudio's
`ns-process-data` writes poses after its `applied_transform`, so a mesh from the original
COLMAP frame needs `applied_transform` too (we do not guess; the pose check says so).
"""

from __future__ import annotations

import os
from pathlib import Path

from jaxdistill.scene import cameras
from jaxdistill.datasets.common import ImportOptions, ViewSource, build_scene
from jaxdistill.errors import InputError, ProblemList, read_json

SUPPORTED_MODELS = ("PINHOLE", "OPENCV")
_GUESS_EXTENSIONS = (".png", ".jpg", ".jpeg", ".exr", ".JPG", ".PNG")


def _resolve(root: Path, relative: str) -> Path:
    path = root / relative
    if path.suffix or path.is_file():
        return path
    for ext in _GUESS_EXTENSIONS:
        if path.with_suffix(ext).is_file():
            return path.with_suffix(ext)
    return path


def _distortion(params: dict, file: str, where: str, problems: ProblemList):
    """Distortion of a frame's merged parameters (None for pinhole); problems for unsupported models."""
    from jaxdistill.datasets.undistort import Distortion

    model = str(params.get("camera_model", "PINHOLE")).upper()
    if model not in SUPPORTED_MODELS:
        problems.add(file, f"{where}.camera_model", f"{model} is not supported (supported: "
                     f"{', '.join(SUPPORTED_MODELS)}); undistort the photos to a pinhole camera first "
                     "(e.g. ScanNet++'s transforms_undistorted.json, or `colmap image_undistorter`)")
        return None
    extra = [k for k in ("k3", "k4") if float(params.get(k, 0.0) or 0.0) != 0.0]
    if extra:
        problems.add(file, f"{where}.{extra[0]}", f"non-zero {extra} need a fisheye/full OpenCV model, which is "
                     "not supported; undistort the photos first")
        return None
    coefficients = {k: float(params.get(k, 0.0) or 0.0) for k in ("k1", "k2", "p1", "p2")}
    if model == "PINHOLE" or not any(coefficients.values()):
        return None
    return Distortion("opencv", **coefficients)


def read_transforms(path, *, image_folder: str | None = None, pose: str = "opengl",
                    frame_keys: tuple[str, ...] = ("frames",), skip_bad: bool = True) -> tuple[list[ViewSource], Path]:
    """(views, the json's path) of a transforms.json (file or folder holding it).

    image_folder: photos are looked up there (relative to the json) instead of beside it.
    pose: "opengl" (NeRF/nerfstudio: flip y and z) or "scannetpp" (thesis B.2: re-orthogonalise,
    invert X and Z, Algorithm 1 -- the same camera for a rigid matrix). frame_keys: the lists of
    frames to read ("frames", and e.g. ScanNet++'s "test_frames"). Frames with "is_bad": true are
    skipped when skip_bad.
    """
    path = Path(path)
    if path.is_dir():
        path = path / "transforms.json"
    file = os.fspath(path)
    meta = read_json(path, "transforms file not found (give transforms.json or its folder)")
    problems = ProblemList()
    if not isinstance(meta, dict):
        raise InputError.single(file, "(top level)", "expected an object with \"frames\"")
    root = path.parent / image_folder if image_folder else path.parent
    views = []
    for key in frame_keys:
        frames = meta.get(key)
        if frames is None:
            if key == "frames":
                problems.add(file, "frames", "required field is missing")
            continue
        if not isinstance(frames, list):
            problems.add(file, key, "expected a list of frames")
            continue
        for i, frame in enumerate(frames):
            where = f"{key}[{i}]"
            if not isinstance(frame, dict) or "file_path" not in frame:
                problems.add(file, where, "expected an object with file_path and transform_matrix")
                continue
            if skip_bad and frame.get("is_bad"):
                continue
            params = {**meta, **frame}
            distortion = _distortion(params, file, where, problems)
            photo = _resolve(root, str(frame["file_path"]))
            try:
                if pose == "scannetpp":
                    missing = [k for k in ("fl_x", "fl_y", "cx", "cy", "w", "h") if k not in params]
                    if missing:
                        raise ValueError(f"missing key(s) {missing}")
                    if "transform_matrix" not in frame:
                        raise ValueError("missing key 'transform_matrix' (4x4 camera-to-world)")
                    camera = cameras.from_scannetpp(frame["transform_matrix"], params["fl_x"], params["fl_y"],
                                                    params["cx"], params["cy"], params["w"], params["h"])
                else:
                    size = {}
                    if not all(k in params for k in ("w", "h")) and photo.is_file():
                        from jaxdistill.io.images import image_size    # Blender NeRF scenes give no size

                        size = dict(zip(("width", "height"), image_size(photo)[:2]))
                    camera = cameras.from_nerf_frame(meta, frame, **size)
            except ValueError as err:
                problems.add(file, where, str(err))
                continue
            mask = root / frame["mask_path"] if frame.get("mask_path") else None
            views.append(ViewSource(name=Path(str(frame["file_path"])).stem, camera=camera, photo=photo,
                                    distortion=distortion, mask=mask))
    problems.raise_if_any()
    return views, path


def load_nerfstudio(path, options: ImportOptions = ImportOptions(), *, report: dict | None = None):
    """Scene of a NeRF/nerfstudio transforms.json (file or folder); the mesh comes from
    options.mesh (transforms.json has none)."""
    views, json_path = read_transforms(path)
    return build_scene(json_path.parent.name, json_path.parent, None, views, options, source_file=os.fspath(json_path),
                       report=report)
