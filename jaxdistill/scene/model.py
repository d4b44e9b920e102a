"""Scene model and its on-disk format (`scene.json` + a mesh file + images).

A `Scene` is a triangle mesh with per-corner UVs and an object id per face, a texture
layout mode, and posed views (canonical OpenCV cameras, see `cameras.py`) with their
photos and optional per-map target images.

Format, version 1 (paths relative to the folder holding scene.json):

    {
      "format": "jaxdistill-scene", "version": 1, "name": "bedroom",
      "mesh": "mesh.glb",                 # any trimesh-readable file: GLB/GLTF, OBJ, PLY, ...
      "objects": ["floor", "bed", ...],   # optional: mesh node names in object-id order
      "texture_layout": "pages",          # "pages": one texture page per object (default)
                                          # "atlas": one page shared by all objects
      "views": [{
        "name": "view_000", "width": 384, "height": 288,
        "K": [[fx, 0, cx], [0, fy, cy], [0, 0, 1]],     # pixels, pixel centres at +0.5
        "c2w": [[...], [...], [...], [0, 0, 0, 1]],     # OpenCV camera-to-world
        "photo": "photos/view_000.exr",                 # EXR linear, PNG/JPG sRGB
        "exposure": 0.0,                                # optional, stops: photo x 2**exposure
        "mask": "masks/view_000.png",                   # optional: pixels < 0.5 are ignored
        "targets": {"albedo": "targets/albedo/view_000.exr"},        # optional, per map
        "ground_truth": {"albedo": "gt/albedo/view_000.exr"}         # optional, evaluation only
      }]
    }

Instead of "mesh", a scene may list its objects with their transforms (the thesis's scene
config): "meshes": [{"name": "bed", "file": "bed.obj", "transform": {...}}, ...] — see
`scene_config.py`. Each object keeps its own texture page.

`exposure` scales the linear photo before RGB<->X sees it (clipped to [0, 1], sRGB-encoded),
so HDR photos can be brought into the range the model was trained on (`exposure.py`).
`mask` (grey, 1 = use) drops pixels from the loss and the metrics: emitters, anonymised
faces, pixels an undistortion could not fill. `ground_truth` images (file space of each map,
as targets) are what evaluation compares renders with when the scene has no gt.json.

Mesh files: each geometry node of the file is one object (its node transform applied);
object ids follow `objects` when given, else sorted node names. UVs are per vertex in the
file (vertices split at seams, as trimesh does) and become per-corner `uv[faces]`.
UV convention: u right, v up (OBJ/trimesh; glTF's flipped v is undone by trimesh),
and every UV must lie in [0, 1]: tiled UVs overlap in texture space and need a re-unwrap.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import os
import re
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np

from jaxdistill import MAP_NAMES
from jaxdistill.io import images as imageio
from jaxdistill.scene.cameras import Camera, intrinsics_problems, pose_problems
from jaxdistill.errors import InputError, ProblemList, read_json
from jaxdistill.io.exposure import MAX_STOPS, scene_exposure
from jaxdistill.scene.mesh import Mesh, load_mesh, save_mesh  # noqa: F401  (re-exported: the scene's mesh type and I/O)
from jaxdistill.scene.objects import load_objects
from jaxdistill.scene.paths import scene_json_path_problems

log = logging.getLogger(__name__)

FORMAT_NAME = "jaxdistill-scene"
FORMAT_VERSION = 1
TEXTURE_LAYOUTS = ("pages", "atlas")
UV_TOLERANCE = 1e-4
RGB_MAPS = ("albedo", "irradiance")     # a grey image is accepted for these: used as R = G = B
MAX_NOTES = 10                          # note lines logged; the rest are counted
NOTE_DETAILS = 5                        # images named per note line
EXPOSURE_NOTE_STOPS = 1.0              # HDR photos without exposure: warn when the rule is this far from 0
NEGATIVE_NOISE = 1e-3                   # photo negatives above -this x its 99th percentile: noise (info only)
MAX_NEGATIVE_SHARE = 0.5                # a photo with more of its non-black pixels below zero is refused


@dataclasses.dataclass(frozen=True)
class Note:
    """What is done with an accepted oddity of one image (logged by `log_notes`, grouped by message)."""

    file: str
    field: str
    message: str
    detail: str
    level: int = logging.INFO


@dataclasses.dataclass(frozen=True, eq=False)
class View:
    """One posed photo: canonical camera, photo path (x 2**exposure), optional per-map target
    images (what a per-view estimator says), mask (1 = use the pixel) and ground-truth images."""

    name: str
    camera: Camera
    photo: Path
    targets: Mapping[str, Path] = dataclasses.field(default_factory=dict)
    exposure: float = 0.0
    mask: Path | None = None
    ground_truth: Mapping[str, Path] = dataclasses.field(default_factory=dict)


@dataclasses.dataclass(frozen=True, eq=False)
class Scene:
    """A mesh, a texture layout mode ('pages' or 'atlas') and posed views; `root` holds the files."""

    name: str
    mesh: Mesh
    views: tuple[View, ...]
    texture_layout: str = "pages"
    root: Path | None = None

    @property
    def num_objects(self) -> int:
        return len(self.mesh.object_names)


# ----------------------------------------------------------------------------- validation


def mesh_problems(mesh: Mesh, file: str, problems: ProblemList) -> None:
    """Adds to `problems` what is wrong with `mesh` (non-finite data, bad indices, bad UVs)."""
    v, f, uv = mesh.vertices, mesh.faces, mesh.uv
    if v.ndim != 2 or v.shape[1] != 3 or len(v) == 0:
        problems.add(file, "vertices", f"expected a non-empty (N, 3) array, got shape {v.shape}")
        return
    bad = ~np.isfinite(v).all(axis=1)
    if bad.any():
        problems.add(file, "vertices", f"{bad.sum()} vertices are NaN/inf (first: vertex {np.argmax(bad)})")
    if f.ndim != 2 or f.shape[1] != 3 or len(f) == 0:
        problems.add(file, "faces", f"expected a non-empty (F, 3) triangle array, got shape {f.shape}")
        return
    out = (f < 0) | (f >= len(v))
    if out.any():
        face = int(np.argmax(out.any(axis=1)))
        problems.add(file, "faces", f"{out.any(axis=1).sum()} faces index vertices outside [0, {len(v) - 1}] "
                     f"(first: face {face} = {f[face].tolist()})")
    elif np.isfinite(v).all():
        corners = v[f]
        area2 = np.linalg.norm(np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]), axis=1)
        if not (area2 > 1e-12 * float(np.ptp(v, axis=0).max()) ** 2).any():
            problems.add(file, "faces", f"all {len(f)} faces have zero area (repeated or collinear corners), so no "
                         "ray can hit the mesh; check the face indices (0- or 1-based?) and the vertex data")
    if uv.shape != (len(f), 3, 2):
        problems.add(file, "uv", f"expected per-corner UVs of shape ({len(f)}, 3, 2), got {uv.shape}")
        return
    bad = ~np.isfinite(uv).all(axis=(1, 2))
    if bad.any():
        problems.add(file, "uv", f"{bad.sum()} faces have NaN/inf UVs (first: face {np.argmax(bad)}; NaN = no "
                     "texture coordinates): unwrap them with scripts/import_scene.py (or jaxdistill.render.unwrap.ensure_uvs)")
    outside = ((uv < -UV_TOLERANCE) | (uv > 1 + UV_TOLERANCE)).any(axis=(1, 2)) & ~bad
    if outside.any():
        problems.add(file, "uv", f"{outside.sum()} faces have UVs outside [0, 1] (first: face "
                     f"{np.argmax(outside)}); tiled UVs overlap in texture space: re-unwrap the mesh "
                     "(xatlas) so every chart lies inside [0, 1]")
    if mesh.face_object.shape != (len(f),):
        problems.add(file, "face_object", f"expected shape ({len(f)},), got {mesh.face_object.shape}")
    elif len(f) and (mesh.face_object.min() < 0 or mesh.face_object.max() >= len(mesh.object_names)):
        problems.add(file, "face_object", f"object ids must lie in [0, {len(mesh.object_names) - 1}]")


def view_problems(photo: Path, targets: Mapping[str, Path], cam: Camera | None, where: str, file: str,
                  problems: ProblemList, *, check_pixels: bool = True, mask: Path | None = None,
                  ground_truth: Mapping[str, Path] | None = None, exposure: float = 0.0,
                  notes: list | None = None) -> None:
    """Adds to `problems` what is wrong with a view's images: unknown map names, missing,
    unreadable, truncated or non-finite images, channels the image's role cannot use, and (given
    the view's camera) a size that differs from it. The camera itself is valid by construction
    (`Camera` validates K and c2w). What is done with acceptable oddities (a grey albedo, negative
    values in a linear photo) is appended to `notes` (`Note`)."""
    image_problems(photo, f"{where}.photo", cam, file, problems, check_pixels=check_pixels, role="photo",
                   notes=notes)
    if not (isinstance(exposure, (int, float)) and not isinstance(exposure, bool) and abs(exposure) <= MAX_STOPS):
        problems.add(file, f"{where}.exposure", f"expected a number of stops in [-{MAX_STOPS:g}, {MAX_STOPS:g}], "
                     f"got {exposure!r}")
    if mask is not None:
        image_problems(mask, f"{where}.mask", cam, file, problems, check_pixels=check_pixels, role="mask")
    for field, images in (("targets", targets), ("ground_truth", ground_truth or {})):
        for map_name, path in images.items():
            if map_name not in MAP_NAMES:
                problems.add(file, f"{where}.{field}.{map_name}",
                             f"unknown map name {map_name!r}; known maps: {', '.join(MAP_NAMES)}")
                continue
            image_problems(path, f"{where}.{field}.{map_name}", cam, file, problems, check_pixels=check_pixels,
                           role=map_name, notes=notes)


def channel_problem(role: str, channels: int) -> str | None:
    """What is wrong with an image of `channels` channels in `role` ("photo", "mask" or a map
    name), or None. Photos need RGB; RGB maps take RGB or grey; grey maps use channel 0."""
    if role == "mask" or channels >= 3:
        return None
    if channels == 2:
        return ("has 2 channels (grey + alpha): its use is ambiguous; save it without alpha, as "
                + ("grey" if role in ("roughness", "metallic") else "RGB") + (" or grey" if role in RGB_MAPS else ""))
    if role == "photo":
        return f"has {channels} channel (grey); RGB↔X needs a colour photo: save it as RGB"
    if role == "normal":
        return "is grey (1 channel); a normal map needs 3 channels, (n + 1) / 2 as RGB: save it as RGB"
    return None


def image_problems(path: Path, field: str, cam: Camera | None, file: str, problems: ProblemList, *,
                   check_pixels: bool, role: str = "mask", notes: list | None = None) -> None:
    """Adds a problem when the image is missing, unreadable, truncated, non-finite, has channels
    its `role` cannot use (`channel_problem`) or (with `cam`) the wrong size. With `check_pixels`
    every pixel is decoded (once: `imageio.cached_reads` lets the pipeline reuse it)."""
    if not Path(path).is_file():
        problems.add(file, field, f"file not found: {path}")
        return
    try:
        width, height, channels = imageio.image_size(path)
    except OSError as err:
        problems.add(file, field, f"cannot read image: {err}; re-export or re-download it")
        return
    if cam is not None and (width, height) != (cam.width, cam.height):
        problems.add(file, field, f"{path} is {width}x{height} but the view is {cam.width}x{cam.height}")
        return
    wrong = channel_problem(role, channels)
    if wrong:
        problems.add(file, field, f"{path} {wrong}")
        return
    if notes is not None and role in RGB_MAPS and channels == 1:
        notes.append(Note(file, field, "grey image used as R = G = B", Path(path).name))
    if not check_pixels:
        return
    try:
        pixels = imageio.read_image(path, linear=False)
    except OSError as err:
        problems.add(file, field, f"{err}; re-export or re-download it")
        return
    if role == "photo":
        dark = dark_photo_problem(pixels[..., :3])
        if dark:
            problems.add(file, field, f"{path} {dark}")
            return
    if not imageio.is_linear_format(path):
        return
    bad = ~np.isfinite(pixels)
    if bad.any():
        row, col = np.argwhere(bad)[0][:2]
        problems.add(file, field, f"{path} has {bad.any(axis=-1).sum()} NaN/inf pixels "
                     f"(first at row {row}, column {col}); fix or re-render the image")
    elif role == "photo" and notes is not None:
        rgb = pixels[..., :3]
        negative = rgb < 0
        if negative.any():
            low, scale = float(rgb.min()), max(float(np.percentile(rgb, 99)), 0.0)
            noise = scale > 0 and low >= -NEGATIVE_NOISE * scale
            message = (f"negative values at noise level (above -{NEGATIVE_NOISE:g} x the photo's 99th percentile) "
                       "clamped to 0" if noise else "negative values clamped to 0, as RGB↔X sees the photo x "
                       "2**exposure clipped to [0, 1]")
            notes.append(Note(file, field, message, f"{Path(path).name}: {int(negative.sum())}, min {low:.3g}",
                              logging.INFO if noise else logging.WARNING))


def dark_photo_problem(rgb: np.ndarray) -> str | None:
    """What is wrong with a photo that cannot be the evidence of a room (no pixel above zero, or
    more of its pixels below zero than above: a sign-flipped or broken HDR file), or None. The
    re-rendering term and the prior's condition both read the photo, so such a file is refused
    rather than clamped. Black pixels (a synthetic render's empty background) count for neither."""
    finite = np.isfinite(rgb).all(axis=-1)
    brightness = np.where(finite[..., None], rgb, 0.0).sum(axis=-1)
    lit, negative = int((brightness > 0).sum()), int((brightness < 0).sum())
    if lit == 0:
        return "has no pixel above zero (all black, or all negative): it shows nothing; re-export or re-render it"
    if negative > MAX_NEGATIVE_SHARE * (lit + negative):
        return (f"has more pixels below zero ({negative}) than above ({lit}): a sign-flipped or broken image, not a "
                "photo; check how it was written")
    return None


def log_notes(notes: Sequence[Note]) -> None:
    """Logs what is done with accepted oddities: notes of the same message and field pattern
    (views[*]) are one line naming up to NOTE_DETAILS images; at most MAX_NOTES lines."""
    groups: dict[tuple, list[Note]] = {}
    for note in notes:
        groups.setdefault((note.file, re.sub(r"\[\d+\]", "[*]", note.field), note.message, note.level),
                          []).append(note)
    for n, ((file, pattern, message, level), group) in enumerate(groups.items()):
        if n == MAX_NOTES:
            log.warning("... and %d more notes like these", len(groups) - MAX_NOTES)
            break
        where = group[0].field if len(group) == 1 else f"{pattern} ({len(group)} views)"
        details = "; ".join(note.detail for note in group[:NOTE_DETAILS])
        more = f"; and {len(group) - NOTE_DETAILS} more" if len(group) > NOTE_DETAILS else ""
        log.log(level, "%s: %s: %s (%s%s)", file, where, message, details, more)


def validate_scene(scene: Scene, *, scene_file: str = "scene.json", mesh_file: str = "mesh",
                   check_pixels: bool = True, problems: ProblemList | None = None,
                   view_index: list[int] | None = None, notes: list | None = None) -> None:
    """Raises InputError listing every problem of `scene` (each naming file and field).

    `problems` may carry problems found earlier (e.g. while parsing) to report them together;
    `view_index[i]` is the position of `scene.views[i]` in the file (when some were skipped).
    Notes on accepted oddities are logged (`log_notes`), or appended to `notes` when given.
    """
    problems = problems if problems is not None else ProblemList()
    collected = notes if notes is not None else []
    if scene.texture_layout not in TEXTURE_LAYOUTS:
        problems.add(scene_file, "texture_layout",
                     f"unknown layout {scene.texture_layout!r}; use one of {', '.join(TEXTURE_LAYOUTS)}")
    mesh_problems(scene.mesh, mesh_file, problems)
    if not scene.views and view_index is None:
        problems.add(scene_file, "views", "the scene has no views")
    names = [v.name for v in scene.views]
    for i, view in enumerate(scene.views):
        index = view_index[i] if view_index is not None else i
        if names.index(view.name) != i:
            problems.add(scene_file, f"views[{index}].name", f"duplicate view name {view.name!r}")
        view_problems(view.photo, view.targets, view.camera, f"views[{index}]", scene_file, problems,
                      check_pixels=check_pixels, mask=view.mask, ground_truth=view.ground_truth,
                      exposure=view.exposure, notes=collected)
    problems.raise_if_any()
    if notes is None:
        log_notes(collected)


# ----------------------------------------------------------------------------- scene I/O


def _matrix(value, shape, file, field, problems) -> np.ndarray | None:
    try:
        array = np.asarray(value, np.float64)
    except (TypeError, ValueError):
        problems.add(file, field, f"expected a {shape[0]}x{shape[1]} matrix of numbers")
        return None
    if array.shape != shape:
        problems.add(file, field, f"expected shape {shape}, got {array.shape}")
        return None
    return array


def _json_kind(value) -> str:
    """How JSON names the type of a parsed value: 'a list (of 3 items)', 'a string', ..."""
    if isinstance(value, list):
        return f"a list (of {len(value)} items)"
    kinds = {str: "a string", bool: "a boolean", int: "a number", float: "a number", type(None): "null"}
    return kinds.get(type(value), type(value).__name__)


def read_scene(path, *, check_pixels: bool = True, allow_outside_paths: bool = False) -> Scene:
    """Reads and fully validates `scene.json` (or a folder holding it); raises InputError.

    Every path it names (and its gt.json's) must stay inside its folder unless
    `allow_outside_paths` (`scene_paths.py`); that is checked before any of them is touched."""
    path = Path(path)
    if path.is_dir():
        path = path / "scene.json"
    file = os.fspath(path)
    doc = read_json(path, "scene file not found")
    if not isinstance(doc, dict):
        raise InputError.single(file, "(top level)", f"expected a JSON object {{\"format\": \"{FORMAT_NAME}\", "
                                f"\"version\": {FORMAT_VERSION}, \"mesh\": ..., \"views\": [...]}}, got "
                                f"{_json_kind(doc)}; see the scene format in README.md (Inputs)")
    root = path.parent
    problems = ProblemList()
    if doc.get("format") != FORMAT_NAME:
        problems.add(file, "format", f"expected {FORMAT_NAME!r}, got {doc.get('format')!r}")
    if doc.get("version") != FORMAT_VERSION:
        problems.add(file, "version", f"this jaxdistill reads version {FORMAT_VERSION}, got {doc.get('version')!r}")
    if "views" not in doc:
        problems.add(file, "views", "required field is missing")
    if ("mesh" in doc) == ("meshes" in doc):
        problems.add(file, "mesh", "give exactly one of \"mesh\" (one file) or \"meshes\" (objects with transforms)")
    problems.raise_if_any()
    scene_json_path_problems(doc, root, file, problems, allow_outside=allow_outside_paths)
    problems.raise_if_any()

    if "mesh" in doc:
        mesh_path = root / doc["mesh"]
        objects = doc.get("objects")
        mesh = load_mesh(mesh_path, list(objects) if objects is not None else None)
    else:
        mesh_path = path
        mesh = load_objects(doc["meshes"], root, file, "meshes", allow_outside_paths=allow_outside_paths)

    views, view_index = [], []
    if not isinstance(doc["views"], list):
        problems.add(file, "views", "expected a list of views")
        problems.raise_if_any()
    for i, entry in enumerate(doc["views"]):
        where = f"views[{i}]"
        if not isinstance(entry, dict):
            problems.add(file, where, "expected an object with width, height, K, c2w, photo")
            continue
        missing = [k for k in ("width", "height", "K", "c2w", "photo") if k not in entry]
        for key in missing:
            problems.add(file, f"{where}.{key}", "required field is missing")
        if missing:
            continue
        K = _matrix(entry["K"], (3, 3), file, f"{where}.K", problems)
        c2w = _matrix(entry["c2w"], (4, 4), file, f"{where}.c2w", problems)
        width, height = entry["width"], entry["height"]
        if not (isinstance(width, int) and isinstance(height, int) and width > 0 and height > 0):
            problems.add(file, f"{where}.width/height", f"must be positive integers, got {width!r}x{height!r}")
            continue
        if K is None or c2w is None:
            continue
        images = {}
        for key in ("targets", "ground_truth"):
            value = entry.get(key, {})
            if not isinstance(value, dict):
                problems.add(file, f"{where}.{key}", "expected an object {map name: image path}")
                value = {}
            images[key] = {k: root / p for k, p in value.items()}
        mask = root / entry["mask"] if entry.get("mask") is not None else None
        exposure = entry.get("exposure", 0.0)
        camera_problems = [(f"{where}.K", m) for m in intrinsics_problems(K)]
        camera_problems += [(f"{where}.c2w", m) for m in pose_problems(c2w)]
        for field, message in camera_problems:
            problems.add(file, field, message)
        if camera_problems:  # no Camera to build: check the images without their size
            view_problems(root / entry["photo"], images["targets"], None, where, file, problems,
                          check_pixels=check_pixels, mask=mask, ground_truth=images["ground_truth"],
                          exposure=exposure)
            continue
        camera = Camera(K=K, c2w=c2w, width=width, height=height)
        view_index.append(i)
        views.append(View(name=str(entry.get("name", f"view_{i:03d}")), camera=camera,
                          photo=root / entry["photo"], targets=images["targets"], exposure=exposure,
                          mask=mask, ground_truth=images["ground_truth"]))
    scene = Scene(name=str(doc.get("name", root.name)), mesh=mesh, views=tuple(views),
                  texture_layout=doc.get("texture_layout", "pages"), root=root)
    if not doc["views"]:
        problems.add(file, "views", "the scene has no views")
    validate_scene(scene, scene_file=file, mesh_file=os.fspath(mesh_path), check_pixels=check_pixels,
                   problems=problems, view_index=view_index)
    if check_pixels and not any(isinstance(e, dict) and "exposure" in e for e in doc["views"]):
        log_notes(exposure_notes(scene, file))
    return scene


def exposure_notes(scene: Scene, file: str) -> list[Note]:
    """A warning when the scene's photos are HDR, no view gives an exposure, and Hypersim's rule
    (what RGB<->X was trained with, and what the dataset importers apply) is a stop or more away
    from the 0 stops the photos are then shown with: the prior would see them far too dark or
    bright, and its estimates would be off in scale."""
    photos = [v.photo for v in scene.views]
    if not photos or not all(imageio.is_linear_format(p) for p in photos):
        return []
    try:
        stops = scene_exposure(imageio.read_image(p)[..., :3] for p in photos)
    except ValueError:
        return []
    if abs(stops) < EXPOSURE_NOTE_STOPS:
        return []
    return [Note(file, "views[*].exposure", "no view gives an exposure, so the prior sees these HDR photos as they "
                 f"are (0 stops), but Hypersim's rule, which RGB<->X was trained with, gives {stops:+.2f} stops: "
                 f"add \"exposure\": {stops:.2f} to every view (scripts/import_scene.py and the dataset loaders do), "
                 "or \"exposure\": 0 to every view to keep them as they are",
                 f"{len(photos)} HDR photos", logging.WARNING)]


def _relative(path: Path, root: Path) -> str:
    return os.path.relpath(os.fspath(path), os.fspath(root)).replace(os.sep, "/")


def write_scene(scene: Scene, folder, *, mesh_name: str = "mesh.glb") -> Path:
    """Writes scene.json and the mesh (one node per object) into `folder`; returns scene.json's path.

    Image paths are stored relative to `folder` (images outside it as ../ paths: keep them where
    they are, or move the whole tree together).
    """
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    save_mesh(scene.mesh, folder / mesh_name)
    views = []
    for view in scene.views:
        cam = view.camera
        entry = {"name": view.name, "width": int(cam.width), "height": int(cam.height),
                 "K": np.asarray(cam.K, np.float64).tolist(), "c2w": np.asarray(cam.c2w, np.float64).tolist(),
                 "photo": _relative(view.photo, folder)}
        if view.exposure:
            entry["exposure"] = float(view.exposure)
        if view.mask is not None:
            entry["mask"] = _relative(view.mask, folder)
        for key in ("targets", "ground_truth"):
            if getattr(view, key):
                entry[key] = {k: _relative(p, folder) for k, p in getattr(view, key).items()}
        views.append(entry)
    doc = {"format": FORMAT_NAME, "version": FORMAT_VERSION, "name": scene.name, "mesh": mesh_name,
           "objects": list(scene.mesh.object_names), "texture_layout": scene.texture_layout, "views": views}
    out = folder / "scene.json"
    tmp = out.with_suffix(".json.tmp")
    tmp.write_text(json.dumps(doc, indent=1))
    os.replace(tmp, out)
    return out

