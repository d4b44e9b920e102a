"""Scenes shipped with the package; `scene_path("bedroom")` is the embedded default scene."""

from __future__ import annotations

from pathlib import Path

SCENES_DIR = Path(__file__).resolve().parent


def scene_path(name: str) -> Path:
    """The folder of an embedded scene (holding scene.json); a clear error for unknown names."""
    folder = SCENES_DIR / name
    if not (folder / "scene.json").is_file():
        known = sorted(p.name for p in SCENES_DIR.iterdir() if (p / "scene.json").is_file())
        raise FileNotFoundError(f"no embedded scene {name!r} in {SCENES_DIR}; embedded scenes: {known}")
    return folder
