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

from jaxdistill.errors import InputError, ProblemList

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
        problems.add(file, field, f"{value!r} points outside the scene folder {root}; a scene file may only name "
                     f"files inside its folder, so nothing was read. If you trust this file (files shared "
                     f"between scenes), pass {ALLOW_FLAG}")
        return None
    return path
