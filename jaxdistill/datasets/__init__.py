"""Loaders for real datasets: each reads a format's own files and returns a jaxdistill Scene.

| format     | give                           | loader                          |
|------------|--------------------------------|---------------------------------|
| fipt       | FIPT scene folder (HDR .exr)   | `fipt.load_fipt`                |
| iris       | same layout, LDR .png photos   | `fipt.load_fipt(photos="iris")` |
| scannetpp  | ScanNet++ data/<scene_id>      | `scannetpp.load_scannetpp`      |
| nerfstudio | transforms.json or its folder  | `nerfstudio.load_nerfstudio`    |
| colmap     | folder with cameras.txt, images.txt (or sparse/0/) | `colmap.load_colmap` |
| scene      | our scene.json or its folder   | `scene.read_scene`              |

`--max_views` (`ImportOptions.max_views`) keeps that many views evenly spread, for every format,
our own scenes included (a quick trial run on a subset).

`open_scene("FORMAT:PATH")` loads any of them (a plain path is a jaxdistill scene), which is
what `--scene` of the main job and `scripts/import_scene.py` use. Shared steps (undistortion,
exposure, UV unwrap): `common.py`.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

from jaxdistill.datasets.common import ImportOptions, select_views
from jaxdistill.errors import InputError

FORMATS = ("fipt", "iris", "scannetpp", "nerfstudio", "colmap", "scene")


def load(fmt: str, path, options: ImportOptions = ImportOptions(), *, split: str | None = None,
         report: dict | None = None):
    """The Scene of dataset `path` in format `fmt` (one of FORMATS)."""
    if fmt == "scene":
        from jaxdistill.scene.model import read_scene
        from jaxdistill.scene.paths import resolve_scene_path

        scene = read_scene(resolve_scene_path(str(path)), allow_outside_paths=options.allow_outside_paths)
        kept = tuple(select_views(scene.views, options.max_views))      # --max_views: a quick run on fewer
        return scene if len(kept) == len(scene.views) else dataclasses.replace(scene, views=kept)
    if not Path(path).exists():
        raise InputError.single(str(path), "(path)", f"not found (a {fmt} dataset was expected there)")
    if fmt in ("fipt", "iris"):
        from jaxdistill.datasets.fipt import load_fipt

        return load_fipt(path, options, split=split or "train", photos=fmt, report=report)
    if fmt == "scannetpp":
        from jaxdistill.datasets.scannetpp import load_scannetpp

        return load_scannetpp(path, options, split=split or "train", report=report)
    if fmt == "nerfstudio":
        from jaxdistill.datasets.nerfstudio import load_nerfstudio

        return load_nerfstudio(path, options, report=report)
    if fmt == "colmap":
        from jaxdistill.datasets.colmap import load_colmap

        return load_colmap(path, options, report=report)
    raise InputError.single("options", "format", f"unknown format {fmt!r}; use one of {', '.join(FORMATS)}")


def split_spec(spec: str) -> tuple[str, str]:
    """("format", "path") of "FORMAT:PATH"; ("scene", spec) when spec names no known format."""
    head, sep, tail = spec.partition(":")
    if sep and head in FORMATS:
        return head, tail
    return "scene", spec


def open_scene(spec: str, options: ImportOptions = ImportOptions()):
    """The Scene `spec` names: "FORMAT:PATH" (e.g. "fipt:/data/kitchen") or a jaxdistill scene."""
    fmt, path = split_spec(spec)
    return load(fmt, path, options)
