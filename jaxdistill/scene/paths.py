"""Where a scene's files are: `--scene` as a path, and the paths inside scene files.

Scene files (scene.json, its gt.json, a scene config such as objects.json) name their mesh,
photos, masks, targets, ground truth and object files relative to their own folder. A path that
resolves outside that folder (`../`, an absolute path, a symlink pointing out of it) is refused
by default: a scene from elsewhere could otherwise read any file on the machine, and the
messages would tell which files exist. The check looks at the names only, before any file is
opened or tested. Users who share files between scenes opt in with `--allow_outside_paths`
(`ImportOptions.allow_outside_paths`, `read_scene(..., allow_outside_paths=True)`).
"""

from __future__ import annotations

import os
from pathlib import Path

from jaxdistill.errors import InputError, ProblemList, read_json

ALLOW_FLAG = "--allow_outside_paths"


def resolve_scene_path(scene: str) -> Path:
    """--scene as a path; a bare embedded-scene name (e.g. 'bedroom') resolves to the package's copy."""
    path = Path(scene).expanduser()
    if path.exists():
        return path
    from jaxdistill.scenes import SCENES_DIR

    if (SCENES_DIR / scene / "scene.json").is_file():
        return SCENES_DIR / scene
    raise InputError.single("flags", "--scene", f"{scene} not found (give scene.json, its folder, or an embedded "
                            "scene name such as 'bedroom')")


def is_inside(path, folder) -> bool:
    """True when `path` (symlinks followed as far as they exist) lies in `folder` or below."""
    real_folder = Path(os.path.realpath(folder))
    real = Path(os.path.realpath(path))
    return real == real_folder or real_folder in real.parents


def scene_file_path(root, value, file, field: str, problems: ProblemList, *,
                    allow_outside: bool = False) -> Path | None:
    """root / value for a path field of a scene file; None (a problem added) when it is not a
    path, or resolves outside `root` and `allow_outside` is False. Nothing is read."""
    if not isinstance(value, str) or not value.strip():
        problems.add(file, field, f"expected a file path relative to {root}, got {value!r}")
        return None
    path = Path(root) / value
    if not allow_outside and not is_inside(path, root):
        problems.add(file, field, f"{value!r} resolves outside the scene folder {root}, so it was not read "
                     f"(scene files may name only files inside their folder); if you trust this file and share "
                     f"files between scenes, pass {ALLOW_FLAG}")
        return None
    return path


def scene_json_path_problems(doc: dict, root: Path, file, problems: ProblemList, *, allow_outside: bool) -> None:
    """Adds a problem for each path field of a parsed scene.json (mesh, meshes[].file, views'
    photo, mask, targets, ground_truth) and of the scene's gt.json textures that is not a path or
    leaves `root`."""
    def check(value, field):
        scene_file_path(root, value, file, field, problems, allow_outside=allow_outside)

    if "mesh" in doc:
        check(doc["mesh"], "mesh")
    for i, entry in enumerate(doc["meshes"] if isinstance(doc.get("meshes"), list) else []):
        if isinstance(entry, dict) and "file" in entry:
            check(entry["file"], f"meshes[{i}].file")
    for i, entry in enumerate(doc["views"] if isinstance(doc.get("views"), list) else []):
        if not isinstance(entry, dict):
            continue
        if "photo" in entry:
            check(entry["photo"], f"views[{i}].photo")
        if entry.get("mask") is not None:
            check(entry["mask"], f"views[{i}].mask")
        for key in ("targets", "ground_truth"):
            for name, value in (entry[key].items() if isinstance(entry.get(key), dict) else ()):
                check(value, f"views[{i}].{key}.{name}")
    gt_json_path_problems(root, problems, allow_outside=allow_outside)


def gt_json_path_problems(root: Path, problems: ProblemList, *, allow_outside: bool) -> None:
    """Adds a problem for each texture path of `root`/gt.json ({"textures": {map: {object: path}}})
    that is not a path or leaves `root`; nothing when there is no gt.json."""
    path = Path(root) / "gt.json"
    if not path.is_file():
        return
    doc = read_json(path, "missing")
    textures = doc.get("textures") if isinstance(doc, dict) else None
    for name, per_object in (textures.items() if isinstance(textures, dict) else ()):
        for obj, value in (per_object.items() if isinstance(per_object, dict) else ()):
            scene_file_path(root, value, path, f"textures.{name}.{obj}", problems, allow_outside=allow_outside)
