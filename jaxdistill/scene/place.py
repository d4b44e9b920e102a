"""Puts an imported dataset's files inside the scene folder, so that its scene.json names only
files inside it: the main job then reads it without --allow_outside_paths, and the folder can
be moved or copied whole.

`--link` of `jaxdistill import` chooses how (`place_files`); every photo, mask, target and
ground-truth image outside the folder goes to `photos/`, `masks/`, `targets/MAP/` or
`ground_truth/MAP/` under it, named after its view:

- `hardlink` (default): a hard link (no bytes copied; the file is the capture's own, so editing
  one edits both); a copy where the file system allows none (another device, EPERM, ...);
- `copy`: a copy (the capture may then be changed or deleted);
- `symlink`: a symlink to the file's absolute path. The scene reader follows symlinks, so these
  lead outside the folder and are refused like `../` paths unless the main job is given
  --allow_outside_paths (a marker in the folder cannot vouch for them: a scene from elsewhere
  could carry it too);
- `none`: nothing placed: scene.json names the files where the dataset keeps them (../ paths),
  read only with --allow_outside_paths.

Derived images (undistorted photos, their masks) and the mesh are written into the folder by
the import itself.
"""

from __future__ import annotations

import dataclasses
import errno
import os
import shutil
from pathlib import Path

from jaxdistill.errors import InputError
from jaxdistill.scene.paths import is_inside

LINK_MODES = ("hardlink", "symlink", "copy", "none")
# errors of os.link that mean "not here": fall back to a copy
_NO_HARD_LINK = {errno.EXDEV, errno.EPERM, errno.EMLINK, errno.ENOTSUP, errno.EOPNOTSUPP, errno.ENOSYS, errno.EACCES}


@dataclasses.dataclass
class Placement:
    """What `place_files` did: files linked (hard or symbolic), copied (bytes), left in place."""

    mode: str
    linked: int = 0
    copied: int = 0
    bytes_copied: int = 0
    kept: int = 0
    fallback: str = ""            # why hard links gave way to copies (the first OSError)

    def summary(self, out) -> str:
        """One line: what was placed in `out`, and how many bytes were copied."""
        if self.mode == "none":
            return f"files: {self.kept} left where the dataset keeps them (--link=none)"
        kinds = []
        if self.linked:
            kinds.append(f"{self.linked} {'hard links' if self.mode == 'hardlink' else 'symlinks'}")
        if self.copied or not kinds:
            why = f" (hard links not possible: {self.fallback})" if self.fallback else ""
            kinds.append(f"{self.copied} copies{why}")
        return (f"files: {self.linked + self.copied} placed in {out} (--link={self.mode}): {', '.join(kinds)}; "
                f"{format_bytes(self.bytes_copied)} copied")


def format_bytes(n: int) -> str:
    """'N bytes', with the size in kB/MB/GB beside it from 1000 bytes on."""
    size, unit = float(n), "bytes"
    for larger in ("kB", "MB", "GB"):
        if size < 1000:
            break
        size, unit = size / 1000, larger
    return f"{n} bytes" if unit == "bytes" else f"{n} bytes ({size:.1f} {unit})"


def place_files(scene, out, mode: str = "hardlink"):
    """(scene naming its files inside `out`, Placement): each photo, mask, target and ground-truth
    image of `scene` outside `out` linked or copied per `mode` (see the module docstring); a file
    that several fields name is placed once. InputError naming --link when one cannot be placed."""
    if mode not in LINK_MODES:
        raise InputError.single("flags", "--link", f"unknown mode {mode!r}; use {', '.join(LINK_MODES)}")
    out = Path(out)
    placement, placed = Placement(mode), {}

    def place(path, folder: str, view: str):
        if path is None or is_inside(path, out):
            return path
        source = Path(os.path.abspath(path))
        if mode == "none":
            placement.kept += source not in placed
            placed.setdefault(source, path)
            return path
        if source not in placed:
            name = view if view.endswith(source.suffix) else view + source.suffix
            placed[source] = _place(source, out / folder / name, placement)
        return placed[source]

    views = []
    for v in scene.views:
        views.append(dataclasses.replace(
            v, photo=place(v.photo, "photos", v.name), mask=place(v.mask, "masks", v.name),
            targets={k: place(p, f"targets/{k}", v.name) for k, p in v.targets.items()},
            ground_truth={k: place(p, f"ground_truth/{k}", v.name) for k, p in v.ground_truth.items()}))
    return dataclasses.replace(scene, views=tuple(views)), placement


def _place(source: Path, dest: Path, placement: Placement) -> Path:
    """`dest`, now a link to or copy of `source` per placement.mode (an older file there replaced)."""
    try:
        dest.parent.mkdir(parents=True, exist_ok=True)
        if dest.is_symlink() or dest.exists():
            dest.unlink()
        if placement.mode == "symlink":
            os.symlink(source, dest)
            placement.linked += 1
            return dest
        if placement.mode == "hardlink":
            try:
                os.link(source, dest)
                placement.linked += 1
                return dest
            except OSError as err:
                if err.errno not in _NO_HARD_LINK:
                    raise
                placement.fallback = placement.fallback or err.strerror
        shutil.copyfile(source, dest)
        placement.copied += 1
        placement.bytes_copied += dest.stat().st_size
        return dest
    except OSError as err:
        raise InputError.single(os.fspath(dest), "--link", f"could not place {source} there ({err.strerror}); "
                                "free space or choose another --out, or --link=none to leave the files in place") \
            from None
