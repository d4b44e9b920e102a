"""What every dataset loader shares: options, one view's sources, and turning both into a Scene.

A loader reads its format's cameras and file layout into `ViewSource`s (canonical OpenCV
cameras, photo paths, optional distortion, mask and ground truth) and calls `build_scene`,
which in this order:

1. keeps every k-th view when `max_views` asks for fewer;
2. checks that every photo, mask and ground-truth image exists, has the camera's size and
   usable channels, and decodes in full (truncated files), reporting all problems at once
   (file and field named); each image is decoded once (`imageio.cached_reads`);
3. loads the mesh (`ImportOptions.mesh` overrides the dataset's: a mesh file, or a scene
   config .json listing objects with transforms, see `scene_config.py`) and casts a coarse
   grid of rays per view: the fraction of each view's rays that hit the mesh is logged and
   reported (min / median / max, the views that see least), views under 1 % are named in a
   warning, and a mesh no view sees stops the import (a camera convention or units mix-up);
4. undistorts photos whose camera has lens distortion into `<work_dir>/undistorted/` (same K,
   pinhole) and masks the pixels the source image could not fill (`<work_dir>/masks/`);
5. sets each view's exposure: "auto" gives HDR photos one scene-wide exposure by Hypersim's
   rule (`exposure.py`) and LDR photos 0 stops; a number sets every view;
6. makes the UVs usable (`unwrap.ensure_uvs`: keep good ones, xatlas where missing, tiled,
   collapsed or overlapping, at the texel density the cameras observe; cached by mesh hash).

Derived files go to `work_dir` (default: `<cache>/imports/<hash of the dataset path>`), the
dataset itself is never written to.
"""

from __future__ import annotations

import dataclasses
import hashlib
import logging
import os
import time
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np
from tqdm.auto import tqdm

from jaxdistill.io import exposure as exposure_rule
from jaxdistill.io import images as imageio
from jaxdistill.scene.cameras import Camera
from jaxdistill.errors import InputError, ProblemList
from jaxdistill.scene.model import Mesh, Scene, View, load_mesh, log_notes, validate_scene, view_problems
from jaxdistill.io.view_images import read_mask

log = logging.getLogger(__name__)

UV_POLICIES = ("auto", "keep", "unwrap")


@dataclasses.dataclass(frozen=True)
class ImportOptions:
    """Choices shared by every loader: flags of the same names of `jaxdistill import` and of the
    main job (`engine/config.py` IMPORT_FLAGS), so messages name them as `--NAME`."""

    mesh: str | None = None          # mesh file or scene config .json replacing the dataset's mesh
    exposure: str | float = "auto"   # "auto" or stops applied to every view
    uv: str = "auto"                 # unwrap.ensure_uvs policy: auto, keep, unwrap
    max_page_size: int = 4096        # largest texture page an unwrap is packed for
    max_views: int = 0               # 0: all views; else every k-th view, at most this many
    work_dir: str | None = None      # derived images (undistorted photos, masks)
    cache_dir: str | None | bool = None  # unwrap and fragment caches (None: the default cache)
    max_unwrap_faces: int = 4_000_000
    unwrap_time_limit: float = 1800.0
    progress: bool = True
    allow_outside_paths: bool = False  # scene files (scene.json, scene configs) may name files outside their folder

    def __post_init__(self):
        # problems name the flag: the import command and the main job spell these options the same
        if self.uv not in UV_POLICIES:
            raise InputError.single("flags", "--uv", f"unknown policy {self.uv!r}; use {', '.join(UV_POLICIES)}")
        if self.exposure != "auto":
            try:
                stops = float(self.exposure)
            except (TypeError, ValueError):
                stops = float("nan")
            if not abs(stops) <= exposure_rule.MAX_STOPS:
                raise InputError.single("flags", "--exposure", f"expected 'auto' or stops in [-{exposure_rule.MAX_STOPS:g}, "
                                        f"{exposure_rule.MAX_STOPS:g}], got {self.exposure!r}")
            object.__setattr__(self, "exposure", stops)
        if self.max_views < 0:
            raise InputError.single("flags", "--max_views", f"must be >= 0 (0 = all), got {self.max_views}")


@dataclasses.dataclass(frozen=True)
class ViewSource:
    """One photo as a dataset describes it: canonical camera, photo, optional lens distortion
    (`datasets.undistort.Distortion`), mask (1 = use), per-map targets and ground truth."""

    name: str
    camera: Camera
    photo: Path
    distortion: object | None = None
    mask: Path | None = None
    targets: Mapping[str, Path] = dataclasses.field(default_factory=dict)
    ground_truth: Mapping[str, Path] = dataclasses.field(default_factory=dict)


def default_work_dir(dataset_path) -> Path:
    """<cache>/imports/<16 hex of the dataset's absolute path>."""
    from jaxdistill.render.fragments import default_cache_dir

    digest = hashlib.sha256(os.fspath(Path(dataset_path).resolve()).encode()).hexdigest()[:16]
    return default_cache_dir() / "imports" / digest


def select_views(views: Sequence[ViewSource], max_views: int) -> list[ViewSource]:
    """All views, or `max_views` of them evenly spread over the sequence (first and last kept)."""
    if not max_views or len(views) <= max_views:
        return list(views)
    picks = np.unique(np.linspace(0, len(views) - 1, max_views).round().astype(int))
    return [views[i] for i in picks]


def check_sources(views: Sequence[ViewSource], file: str) -> None:
    """InputError listing every missing, unreadable, truncated or wrongly sized image of `views`
    at once (every pixel decoded); notes on accepted oddities (grey albedo...) are logged."""
    problems, notes = ProblemList(), []
    if not views:
        problems.add(file, "frames", "no views to import")
    names = [v.name for v in views]
    for i, view in enumerate(views):
        if names.index(view.name) != i:
            problems.add(file, f"view {view.name}", "two frames have the same image name")
        view_problems(view.photo, view.targets, view.camera, f"view {view.name}", file, problems,
                      mask=view.mask, ground_truth=view.ground_truth, notes=notes)
    problems.raise_if_any()
    log_notes(notes)


def load_scene_mesh(path, *, allow_outside_paths: bool = False) -> Mesh:
    """A mesh file (objects = geometry nodes, UVs may be missing) or a scene config .json (whose
    object files stay inside its folder unless `allow_outside_paths`)."""
    path = Path(path)
    if path.suffix.lower() == ".json":
        from jaxdistill.scene.objects import read_scene_config

        return read_scene_config(path, allow_outside_paths=allow_outside_paths)
    return load_mesh(path, require_uv=False)


def _undistort(views: list[ViewSource], work_dir: Path, progress: bool) -> list[ViewSource]:
    """Views whose photos were undistorted into work_dir (pinhole, same K), unfilled pixels masked."""
    from jaxdistill.datasets.undistort import undistort_image

    todo = [i for i, v in enumerate(views) if v.distortion is not None and not v.distortion.is_identity()]
    out = list(views)
    for i in tqdm(todo, desc="undistort photos", unit="photo", disable=not progress or not todo):
        view = views[i]
        ext = ".exr" if imageio.is_linear_format(view.photo) else ".png"
        photo = work_dir / "undistorted" / f"{view.name}{ext}"
        mask = work_dir / "masks" / f"{view.name}.png"
        image, valid = undistort_image(imageio.read_image(view.photo), view.camera.K, view.distortion)
        imageio.write_image(photo, image)
        if view.mask is not None:
            old, _ = undistort_image(imageio.read_image(view.mask, linear=False)[..., :1], view.camera.K,
                                     view.distortion)
            valid &= old[..., 0] >= 0.5
        imageio.write_image(mask, valid.astype(np.float32), encode_srgb=False)
        out[i] = dataclasses.replace(view, photo=photo, mask=mask, distortion=None)
    return out


def view_exposures(views: Sequence[ViewSource], setting, progress: bool) -> tuple[list[float], str]:
    """(stops per view, how they were chosen): "auto" = Hypersim rule over the HDR photos, LDR 0."""
    if setting != "auto":
        return [float(setting)] * len(views), f"{float(setting):+.3f} stops for every view (given)"
    hdr = [v for v in views if imageio.is_linear_format(v.photo)]
    if not hdr:
        return [0.0] * len(views), "LDR photos: 0 stops (exposed by their camera)"
    def photos():
        for v in tqdm(hdr, desc="exposure", unit="photo", disable=not progress):
            yield imageio.read_image(v.photo)

    def masks():
        for v in hdr:
            yield read_mask(v.mask, v.camera.height, v.camera.width) if v.mask is not None else None

    try:
        stops = exposure_rule.scene_exposure(photos(), masks())
    except ValueError as err:
        raise InputError.single(os.fspath(hdr[0].photo.parent), "photos", f"{err}; give --exposure=STOPS") from None
    how = (f"{stops:+.3f} stops for the {len(hdr)} HDR photos (Hypersim rule: 90th-percentile brightness "
           f"-> 0.8 after gamma), LDR photos 0")
    return [stops if imageio.is_linear_format(v.photo) else 0.0 for v in views], how


def build_scene(name: str, root: Path, mesh_path, views: Sequence[ViewSource], options: ImportOptions, *,
                source_file: str, report: dict | None = None) -> Scene:
    """The Scene of a dataset's views and mesh (see the module docstring for the steps)."""
    with imageio.cached_reads():
        return _build_scene(name, root, mesh_path, views, options, source_file=source_file, report=report)


def _build_scene(name: str, root: Path, mesh_path, views: Sequence[ViewSource], options: ImportOptions, *,
                 source_file: str, report: dict | None) -> Scene:
    from jaxdistill.render import unwrap
    from jaxdistill.render.visibility import cast_hit_fractions, check_coverage, coverage_summary

    timings = {}
    t0 = time.perf_counter()
    views = select_views(views, options.max_views)
    check_sources(views, source_file)
    mesh_path = Path(options.mesh) if options.mesh else mesh_path
    if mesh_path is None:
        raise InputError.single(source_file, "mesh", "this format has no mesh of its own: give one with --mesh "
                                "(a mesh file or a scene config .json)")
    mesh = load_scene_mesh(mesh_path, allow_outside_paths=options.allow_outside_paths)
    timings["read_s"] = time.perf_counter() - t0

    t0 = time.perf_counter()          # lens distortion moves pixels, not the fraction that hits: cast pinholes
    names, cameras = [v.name for v in views], [v.camera for v in views]
    fractions = cast_hit_fractions(mesh, cameras)
    blind = check_coverage(names, fractions, cameras, mesh, source_file, what_to_check=(
        "check that the cameras follow the format's convention (README: Real datasets) and that the mesh is in "
        "the cameras' world and units (--mesh replaces the dataset's)"))
    timings["coverage_s"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    work_dir = Path(options.work_dir) if options.work_dir else default_work_dir(root)
    views = _undistort(list(views), work_dir, options.progress)
    stops, exposure_note = view_exposures(views, options.exposure, options.progress)
    timings["photos_s"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    mesh, decisions = unwrap.ensure_uvs(mesh, [v.camera for v in views], policy=options.uv,
                                        max_page_size=options.max_page_size, cache_dir=options.cache_dir,
                                        progress=options.progress, max_faces=options.max_unwrap_faces,
                                        time_limit_s=options.unwrap_time_limit, mesh_file=os.fspath(mesh_path))
    timings["uv_s"] = time.perf_counter() - t0

    scene_views = tuple(View(name=v.name, camera=v.camera, photo=v.photo, targets=dict(v.targets),
                             exposure=s, mask=v.mask, ground_truth=dict(v.ground_truth))
                        for v, s in zip(views, stops))
    scene = Scene(name=name, mesh=mesh, views=scene_views, texture_layout="pages", root=Path(root))
    validate_scene(scene, scene_file=source_file, mesh_file=os.fspath(mesh_path), check_pixels=False,
                   notes=[])          # check_sources logged the notes on these images already
    log.info("%s: %d views, %d faces in %d objects; exposure %s; UVs: %d kept, %d unwrapped (%.1f s)", name,
             len(scene_views), mesh.num_faces, len(mesh.object_names), exposure_note,
             sum(not d.reunwrapped for d in decisions), sum(d.reunwrapped for d in decisions), timings["uv_s"])
    if report is not None:
        report.update({"name": name, "source": source_file, "mesh": os.fspath(mesh_path), "views": len(scene_views),
                       "faces": mesh.num_faces, "objects": list(mesh.object_names), "exposure": exposure_note,
                       "uv_decisions": [dataclasses.asdict(d) for d in decisions],
                       "uv_table": unwrap.format_decisions(decisions), "work_dir": os.fspath(work_dir),
                       "hit_fractions": dict(zip(names, fractions.round(4).tolist())),
                       "coverage": coverage_summary(names, fractions), "blind_views": blind,
                       "timings": timings})
    return scene
