"""COLMAP sparse models in text form (cameras.txt, images.txt) -> jaxdistill cameras.

Format (https://colmap.github.io/format.html), '#' starts a comment line:

- cameras.txt, one camera per line: `CAMERA_ID MODEL WIDTH HEIGHT PARAMS[]`.
- images.txt, TWO lines per image: `IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME`, then the
  image's 2D points `X Y POINT3D_ID ...` -- that second line is EMPTY for an image without
  points, and it is always present, so blank lines are not skipped blindly. NAME is everything
  after CAMERA_ID (stripped); it may hold sub-folders (and here even spaces).
- points3D.txt is not read.

Conventions: (QW, QX, QY, QZ) is a Hamilton unit quaternion (normalised here) of the
world-to-camera rotation R, and x_cam = R x_world + t with t = (TX, TY, TZ); the camera axes are
OpenCV's (x right, y down, z forward), the same as jaxdistill's, so `cameras.from_opencv_rt`
takes R, t as they are. COLMAP (3.x) puts the image's top-left corner at (0, 0) and the CENTRE
of the top-left pixel at (0.5, 0.5), as jaxdistill does, so the principal point (cx, cy) carries
over unchanged (no half-pixel shift). Intrinsics are in pixels of the WIDTH x HEIGHT image.

Supported camera models (params in COLMAP's order):
  SIMPLE_PINHOLE (f, cx, cy), PINHOLE (fx, fy, cx, cy), SIMPLE_RADIAL (f, cx, cy, k),
  RADIAL (f, cx, cy, k1, k2), OPENCV (fx, fy, cx, cy, k1, k2, p1, p2).
The distorting ones come with a `Distortion` (jaxdistill.datasets.undistort) to resample the
photos onto the pinhole camera. Other models (OPENCV_FISHEYE, FULL_OPENCV, FOV, the fisheye and
thin-prism ones) are refused: run `colmap image_undistorter`, which writes PINHOLE cameras and
undistorted images. Binary models (cameras.bin, images.bin) must first be converted with
`colmap model_converter --output_type TXT`.
"""

from __future__ import annotations

import dataclasses
import math
import os
from pathlib import Path

import numpy as np

from jaxdistill.scene import cameras
from jaxdistill.scene.cameras import Camera, quaternion_to_rotation
from jaxdistill.datasets.undistort import Distortion
from jaxdistill.errors import InputError, ProblemList

# Supported models: parameter names in COLMAP's order.
SUPPORTED_MODELS = {
    "SIMPLE_PINHOLE": ("f", "cx", "cy"),
    "PINHOLE": ("fx", "fy", "cx", "cy"),
    "SIMPLE_RADIAL": ("f", "cx", "cy", "k"),
    "RADIAL": ("f", "cx", "cy", "k1", "k2"),
    "OPENCV": ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2"),
}
# Parameter counts of COLMAP's other models, to check a file even where the model is unsupported.
_OTHER_MODELS = {"OPENCV_FISHEYE": 8, "FULL_OPENCV": 12, "FOV": 5, "SIMPLE_RADIAL_FISHEYE": 4,
                 "RADIAL_FISHEYE": 5, "THIN_PRISM_FISHEYE": 12, "RAD_TAN_THIN_PRISM_FISHEYE": 16}
_PARAM_COUNTS = {**{m: len(p) for m, p in SUPPORTED_MODELS.items()}, **_OTHER_MODELS}
_UNDISTORT_HINT = ("run `colmap image_undistorter --image_path IMAGES --input_path MODEL "
                   "--output_path OUT` (it writes PINHOLE cameras and undistorted images) and use "
                   "its output")
_POSE_FIELDS = "IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME"


@dataclasses.dataclass(frozen=True)
class ColmapImage:
    """One registered image: its pinhole `camera` (pose and K), and the lens `distortion` its
    photo `name` (relative to the image folder) still has (identity for pinhole models)."""

    image_id: int
    name: str
    camera: Camera
    distortion: Distortion
    camera_id: int


# ----------------------------------------------------------------------------- reading text


def _lines(path: Path) -> list[str]:
    """The file's lines (without line endings); InputError if missing or not UTF-8 text."""
    if not path.is_file():
        raise InputError.single(path, "(file)", "not found" + _missing_hint(path))
    try:
        text = path.read_text(encoding="utf-8-sig")
    except (OSError, UnicodeDecodeError) as err:
        raise InputError.single(path, "(file)", f"unreadable as UTF-8 text ({err})") from None
    return [line.rstrip("\r") for line in text.split("\n")]


def _missing_hint(path: Path) -> str:
    """What to do about a missing cameras.txt / images.txt."""
    folder = path.parent
    if path.with_suffix(".bin").is_file():
        return (f"; the model is binary ({path.stem}.bin): convert it with `colmap model_converter "
                f"--input_path {folder} --output_path {folder} --output_type TXT`")
    if (folder / "sparse").is_dir():
        return f"; COLMAP writes models to sparse/0, sparse/1, ...: pass {folder / 'sparse' / '0'}"
    return "; expected a COLMAP text model folder (cameras.txt, images.txt)"


def _is_comment(line: str) -> bool:
    return line.lstrip().startswith("#")


def _int(text: str, what: str) -> tuple[int | None, str | None]:
    """(value, None) or (None, why)."""
    try:
        return int(text), None
    except ValueError:
        return None, f"{what} must be an integer, got {text!r}"


def _floats(texts: list[str], names) -> tuple[np.ndarray | None, str | None]:
    """(float64 array, None) or (None, why) for finite decimal numbers `texts` named `names`."""
    values = []
    for text, name in zip(texts, names):
        try:
            v = float(text)
        except ValueError:
            return None, f"{name} must be a number, got {text!r}"
        if not math.isfinite(v):
            return None, f"{name} must be finite, got {text!r}"
        values.append(v)
    return np.array(values, dtype=np.float64), None


# ----------------------------------------------------------------------------- cameras.txt


def _parse_cameras(path: Path) -> dict[int, tuple[str, int, int, np.ndarray, int]]:
    """id -> (model, width, height, params, line number); InputError listing every bad line."""
    problems = ProblemList()
    out: dict[int, tuple[str, int, int, np.ndarray, int]] = {}
    for n, line in enumerate(_lines(path), start=1):
        if not line.strip() or _is_comment(line):
            continue
        where = f"line {n}"
        tokens = line.split()
        if len(tokens) < 4:
            problems.add(path, where, f"expected CAMERA_ID MODEL WIDTH HEIGHT PARAMS[], got "
                         f"{len(tokens)} value(s): {line.strip()!r}")
            continue
        cid, why = _int(tokens[0], "CAMERA_ID")
        if why:
            problems.add(path, where, why)
            continue
        model, params = tokens[1], tokens[4:]
        where = f"line {n} (camera {cid})"
        if cid in out:
            problems.add(path, where, f"duplicate CAMERA_ID {cid} (first on line {out[cid][4]})")
            continue
        size = []
        for text, name in ((tokens[2], "WIDTH"), (tokens[3], "HEIGHT")):
            v, why = _int(text, name)
            if why or v <= 0:
                problems.add(path, where, why or f"{name} must be > 0, got {v}")
            size.append(v)
        if model not in _PARAM_COUNTS and model.isdigit():
            problems.add(path, f"camera {cid} model (line {n})", f"numeric model id {model}: "
                         "cameras.txt names the model (e.g. PINHOLE)")
            continue
        expected = _PARAM_COUNTS.get(model)
        if model in SUPPORTED_MODELS and expected != len(params):
            problems.add(path, f"camera {cid} params (line {n})", f"model {model} takes {expected} "
                         f"parameters ({', '.join(SUPPORTED_MODELS[model])}), got {len(params)}")
            continue
        if expected is not None and expected != len(params):
            problems.add(path, f"camera {cid} params (line {n})",
                         f"model {model} takes {expected} parameters, got {len(params)}")
            continue
        values, why = _floats(params, [f"parameter {i + 1}" for i in range(len(params))])
        if why:
            problems.add(path, f"camera {cid} params (line {n})", why)
            continue
        if None not in size and all(v > 0 for v in size):
            out[cid] = (model, size[0], size[1], values, n)
    problems.raise_if_any()
    return out


def read_cameras_txt(path) -> dict[int, tuple[str, int, int, np.ndarray]]:
    """id -> (model, width, height, params (float64)) of a COLMAP cameras.txt.

    Any COLMAP model name is read (parameter counts checked for the known ones); which are
    supported is checked by `read_colmap_model`. InputError naming the file and line otherwise.
    """
    return {cid: rec[:4] for cid, rec in _parse_cameras(Path(path)).items()}


# ----------------------------------------------------------------------------- images.txt


def _points_line_problem(line: str) -> str | None:
    """Why `line` cannot be an image's 2D points line (X Y POINT3D_ID triples), or None."""
    tokens = line.split()
    if not tokens:
        return None
    if len(tokens) % 3 == 0:
        try:
            float(tokens[0]), float(tokens[1]), int(tokens[-1])
            return None
        except ValueError:
            pass
    return (f"expected the 2D points line (X Y POINT3D_ID triples; empty for an image without "
            f"points) after the image line above, got {line.strip()[:60]!r}; every image takes two "
            "lines -- were the points lines removed?")


def _parse_images(path: Path) -> list[tuple[int, np.ndarray, np.ndarray, int, str, int]]:
    """[(image_id, q (4,), t (3,), camera_id, name, line number)]; InputError listing bad lines."""
    problems = ProblemList()
    out = []
    ids: dict[int, int] = {}
    names: dict[str, int] = {}
    lines = _lines(path)
    n = 0
    while n < len(lines):
        line = lines[n]
        n += 1
        if not line.strip() or _is_comment(line):
            continue  # between records only: the points line after a pose line is consumed below
        lineno = n
        if n < len(lines):  # the points line (may be empty); absent only at the end of the file
            why = _points_line_problem(lines[n])
            if why:
                problems.add(path, f"line {n + 1}", why)
            n += 1
        where = f"line {lineno}"
        parts = line.split(maxsplit=9)
        if len(parts) < 10 or not parts[9].strip():
            problems.add(path, where, f"expected {_POSE_FIELDS} (10 values), got {len(parts)}: "
                         f"{line.strip()[:80]!r}")
            continue
        iid, why = _int(parts[0], "IMAGE_ID")
        cid, why2 = _int(parts[8], "CAMERA_ID")
        values, why3 = _floats(parts[1:8], ("QW", "QX", "QY", "QZ", "TX", "TY", "TZ"))
        if why or why2 or why3:
            problems.add(path, where, "; ".join(w for w in (why, why2, why3) if w))
            continue
        name = parts[9].strip()
        if iid in ids:
            problems.add(path, where, f"duplicate IMAGE_ID {iid} (first on line {ids[iid]})")
            continue
        ids[iid] = lineno
        if name in names:
            problems.add(path, where, f"duplicate image NAME {name!r} (first on line {names[name]})")
            continue
        names[name] = lineno
        q = values[:4]
        norm = float(np.linalg.norm(q))
        if not norm > 1e-12:
            problems.add(path, where, "quaternion QW QX QY QZ is zero; it must be a rotation")
            continue
        out.append((iid, q / norm, values[4:], cid, name, lineno))
    problems.raise_if_any()
    return out


def read_images_txt(path) -> list[tuple[int, np.ndarray, np.ndarray, int, str]]:
    """[(image_id, q = (qw, qx, qy, qz) normalised, t (3,), camera_id, name)] of a COLMAP
    images.txt, in file order; InputError naming the file and line otherwise."""
    return [rec[:5] for rec in _parse_images(Path(path))]


# ----------------------------------------------------------------------------- model


def _intrinsics(model: str, p: np.ndarray) -> tuple[np.ndarray, Distortion]:
    """(K, distortion) of a supported model's params."""
    if model in ("SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL"):
        fx = fy = p[0]
        cx, cy, rest = p[1], p[2], p[3:]
    else:
        fx, fy, cx, cy, rest = p[0], p[1], p[2], p[3], p[4:]
    K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
    if model in ("SIMPLE_PINHOLE", "PINHOLE"):
        return K, Distortion("none")
    if model == "OPENCV":
        return K, Distortion("opencv", *rest)
    return K, Distortion("radial", *rest)  # SIMPLE_RADIAL (k) or RADIAL (k1, k2)


def read_colmap_model(folder) -> list[ColmapImage]:
    """The images of the COLMAP text model in `folder` (cameras.txt, images.txt), sorted by name.

    InputError naming the file and line for a bad line, an image whose camera is missing or
    unsupported, or a model without images.
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise InputError.single(folder, "(folder)", "COLMAP model folder not found; pass the folder "
                                "holding cameras.txt and images.txt (e.g. sparse/0)")
    cam_path, img_path = folder / "cameras.txt", folder / "images.txt"
    cams = _parse_cameras(cam_path)
    records = _parse_images(img_path)
    if not records:
        raise InputError.single(img_path, "(file)", "contains no images; reconstruct (or "
                                "register) images with COLMAP first")
    problems = ProblemList()
    intrinsics: dict[int, tuple[np.ndarray, Distortion]] = {}
    for cid in sorted({rec[3] for rec in records} & set(cams)):
        model, width, height, params, n = cams[cid]
        field = f"camera {cid} model (line {n})"
        if model not in SUPPORTED_MODELS:
            problems.add(cam_path, field, f"camera model {model} is not supported (supported: "
                         f"{', '.join(SUPPORTED_MODELS)}); {_UNDISTORT_HINT}")
            continue
        K, distortion = _intrinsics(model, params)
        bad = [f"{name} = {v:g}" for name, v in zip(SUPPORTED_MODELS[model], params)
               if name in ("f", "fx", "fy") and not v > 0]
        if bad:
            problems.add(cam_path, f"camera {cid} params (line {n})",
                         f"focal length must be > 0, got {', '.join(bad)}")
            continue
        intrinsics[cid] = (K, distortion)
    out = []
    for iid, q, t, cid, name, n in records:
        if cid not in cams:
            known = ", ".join(map(str, sorted(cams))) or "none"
            problems.add(img_path, f"line {n} (image {iid} CAMERA_ID)", f"camera {cid} is not in "
                         f"{cam_path.name} (camera ids there: {known})")
            continue
        if cid not in intrinsics:
            continue  # its camera's problem is reported above
        K, distortion = intrinsics[cid]
        _, width, height, _, _ = cams[cid]
        camera = cameras.from_opencv_rt(quaternion_to_rotation(q), t, K, width, height)
        out.append(ColmapImage(image_id=iid, name=name, camera=camera, distortion=distortion,
                               camera_id=cid))
    problems.raise_if_any()
    return sorted(out, key=lambda im: im.name)


def find_model_folder(path) -> Path:
    """The folder holding cameras.txt: `path`, else path/sparse/0, else path/sparse."""
    path = Path(path)
    for folder in (path, path / "sparse" / "0", path / "sparse"):
        if (folder / "cameras.txt").is_file():
            return folder
    return path


def load_colmap(path, options=None, *, images: str | None = None, report: dict | None = None):
    """Scene of a COLMAP text model: `path` holds cameras.txt + images.txt (or sparse/0/ does),
    photos are in `images` (default: <path>/images, else beside the model); the mesh comes from
    options.mesh. Distorting cameras get their photos undistorted (`datasets.common`)."""
    import os

    from jaxdistill.datasets.common import ImportOptions, ViewSource, build_scene

    options = options or ImportOptions()
    root = Path(path)
    folder = find_model_folder(root)
    records = read_colmap_model(folder)
    image_dir = Path(images) if images else next((d for d in (root / "images", folder / "images") if d.is_dir()), folder)
    stems_unique = len({Path(r.name).stem for r in records}) == len(records)
    views = [ViewSource(name=Path(r.name).stem if stems_unique else r.name.replace("/", "_"), camera=r.camera,
                        photo=image_dir / r.name, distortion=None if r.distortion.is_identity() else r.distortion)
             for r in records]
    return build_scene(root.name, root, None, views, options, source_file=os.fspath(folder / "images.txt"),
                       report=report)
