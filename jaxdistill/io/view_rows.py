"""Per-view arrays kept in a file and read a batch of rows at a time.

A step reads the images of its few views only (the `views` prior's targets, the re-rendering
term's photos), yet they were held for every view: (V, H, W, C) float32, 1 GB at 50 views of
876x584 and growing with the view count. `ViewRows` keeps such a (V, ...) array in a file
instead: rows are written once, as the precompute makes them (`rows[v] = image`), and
`rows[ids]` reads the rows of `ids` alone with positioned reads (`os.preadv`) into a new array,
so the process holds one batch, never every view. The file is not memory-mapped: pages of a
mapping stay in the process's resident set once read. Reads overlap the step: the loop
assembles the next batch while the device still runs the previous one (JAX dispatches
asynchronously).

`view_array(name, shape, dtype, folder)` gives either a NumPy array or a `ViewRows`, which
both support the two operations above; `placement` says which --view_data asks for. A file is
unlinked as soon as it is opened (it has no name in the cache folder): the disk space is the
open file's, freed when the array is garbage-collected or the process ends, however it ends,
so a killed run leaves nothing behind. `LazyViews` is the same idea for values that are cheaper
to make again than to keep (a view's renders, its estimates read from their files), and
`SourceRows` for rows that are the scene's own image files (targets and photos at their own size:
read again from them, not copied into a file at 4 bytes a channel).
"""

from __future__ import annotations

import errno
import math
import os
import shutil
import socket
import threading
import weakref
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Callable

import numpy as np

from jaxdistill.errors import InputError

VIEW_DATA = ("auto", "memory", "disk")
AUTO_DISK_BYTES = 1 << 30       # --view_data=auto: on disk when the per-view arrays would take more than 1 GiB
DISK_HEADROOM = 1 << 28         # 256 MiB left free on the disk after the files are written


def placement(view_data: str, nbytes: int) -> bool:
    """Whether per-view arrays of `nbytes` in all go on disk under --view_data (auto: above
    AUTO_DISK_BYTES). The choice never changes a result: a batch read from disk is the batch
    held in memory, bit for bit."""
    if view_data not in VIEW_DATA:
        raise ValueError(f"view_data must be one of {VIEW_DATA}, got {view_data!r}")
    return view_data == "disk" or (view_data == "auto" and nbytes > AUTO_DISK_BYTES)


def _reserve(fd: int, nbytes: int, path: Path) -> None:
    """Takes the file's disk space now (not a sparse file that fails half-way
    through a run), with an InputError naming the folder when the disk is full."""
    try:
        if hasattr(os, "posix_fallocate"):
            os.posix_fallocate(fd, 0, nbytes)
        else:                                       # (macOS) sparse: the space check before compute stands
            os.ftruncate(fd, nbytes)
    except OSError as err:
        if err.errno not in DISK_FULL:
            raise
        raise _disk_full(path, f"{nbytes / 2 ** 30:.2f} GB for {path.name.split('-')[0]} do not fit") from err


DISK_FULL = (errno.ENOSPC, errno.EDQUOT)


def _disk_full(path: Path, what: str) -> InputError:
    """The InputError a full disk (or quota) under `path` is to the user."""
    return InputError.single(str(path.parent), "disk space", (
        f"{what} on this disk; free space there, point $JAXDISTILL_CACHE at a folder on a larger disk, or hold "
        "the per-view arrays in memory with --view_data=memory"))


def _open_unlinked(path: Path) -> int:
    """A new file at `path`, unlinked at once: its space lives as long as the descriptor."""
    fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_EXCL, 0o600)
    os.unlink(path)
    return fd


class _UnlinkedFile:
    """A file created at `path` and unlinked at once: its descriptor is closed, and its disk space
    freed, when the object is collected or `close`d."""

    def _open(self, path: Path) -> None:
        self.path = Path(path)
        self._fd = _open_unlinked(self.path)
        self._finalizer = weakref.finalize(self, os.close, self._fd)

    def _check_open(self) -> None:
        if not self._finalizer.alive:
            raise ValueError(f"{self.path.name} is closed")

    def close(self) -> None:
        """Closes the file now, which frees its disk space (collecting the object does too)."""
        self._finalizer()


def _read_rows(ids, name: str, row_shape: tuple, dtype, read: Callable) -> np.ndarray:
    """Rows `ids` (an int: one row; a 1-D int array: a new (len(ids), ...) array), each filled by
    `read(v, out_row)`."""
    ids = np.asarray(ids)
    if ids.ndim == 0:
        return _read_rows(ids[None], name, row_shape, dtype, read)[0]
    if ids.dtype.kind not in "iu" or ids.ndim != 1:
        raise TypeError(f"{name} reads rows by an int or a 1-D int array, got {ids.dtype} {ids.shape}")
    out = np.empty((len(ids),) + row_shape, dtype)
    for k, v in enumerate(ids):
        read(v, out[k])
    return out


class ViewRows(_UnlinkedFile):
    """A (V, ...) array of `dtype` in a file created at `path` and unlinked at once (its space is
    freed when the object is collected or `close`d). `rows[v] = row` writes row v; `rows[ids]`
    reads rows `ids` (an int or an int array) into a new array."""

    def __init__(self, path: Path, shape: tuple[int, ...], dtype):
        self.path = Path(path)
        self.shape = tuple(int(s) for s in shape)
        self.dtype = np.dtype(dtype)
        self.row_shape = self.shape[1:]
        if not self.row_shape:
            raise ValueError(f"{self.path.name}: rows of shape () are not supported; hold a (V,) array in memory")
        self.row_bytes = math.prod(self.row_shape) * self.dtype.itemsize
        self._open(self.path)
        try:
            _reserve(self._fd, self.nbytes, self.path)
        except BaseException:
            self.close()
            raise

    @property
    def ndim(self) -> int:
        return len(self.shape)

    @property
    def nbytes(self) -> int:
        """Bytes on disk (none in memory)."""
        return self.shape[0] * self.row_bytes

    def __len__(self) -> int:
        return self.shape[0]

    def __iter__(self):
        """Row by row, each read when reached."""
        return (self[v] for v in range(self.shape[0]))

    def _row(self, v) -> int:
        self._check_open()
        v = int(v)
        if not -self.shape[0] <= v < self.shape[0]:
            raise IndexError(f"row {v} of {self.shape[0]}")
        return v % self.shape[0]

    def __setitem__(self, v, row) -> None:
        row = np.ascontiguousarray(row, self.dtype)
        if row.shape != self.row_shape:
            raise ValueError(f"a row of {self.path.name} is {self.row_shape}, got {row.shape}")
        written = os.pwrite(self._fd, row.data.cast("B"), self._row(v) * self.row_bytes)
        if written != self.row_bytes:
            raise OSError(f"wrote {written} of {self.row_bytes} bytes of row {v} to {self.path}")

    def __getitem__(self, ids) -> np.ndarray:
        def read(v, out):
            got = os.preadv(self._fd, [out.data.cast("B")], self._row(v) * self.row_bytes)
            if got != self.row_bytes:
                raise OSError(f"read {got} of {self.row_bytes} bytes of row {v} from {self.path}")

        return _read_rows(ids, self.path.name, self.row_shape, self.dtype, read)


def _stamp(path: Path) -> tuple[int, int]:
    st = os.stat(path)
    return st.st_size, st.st_mtime_ns


class SourceRows:
    """A (V, ...) per-view array whose rows are the scene's own files, read again when asked for
    (`rows[ids]`: `read(v)` for each view, into a new array), not copied into a file: the `views`
    prior's targets and the re-rendering term's photos, float32 images that a `ViewRows` file
    would hold at 4 bytes a channel (44 bytes a pixel for 11 channels) where their 8-bit or
    half-float files take a few. Used only where a row is the file's pixels without resampling
    (`read` is NumPy, a function of the file alone), so a row read in a step is the row the set-up
    read, bit for bit. Each file's size and modification time are taken when the array is made;
    a read that finds them changed is an InputError naming the file, never a different image."""

    def __init__(self, shape: tuple[int, ...], dtype, read: Callable[[int], np.ndarray],
                 sources: Sequence[Sequence[Path]], name: str = "rows"):
        self.shape = tuple(int(s) for s in shape)
        self.dtype = np.dtype(dtype)
        self.row_shape = self.shape[1:]
        if len(sources) != self.shape[0]:
            raise ValueError(f"{name}: {len(sources)} views' files for {self.shape[0]} rows")
        self.read, self.name = read, name
        self.stamps = [[(Path(p), _stamp(p)) for p in paths] for paths in sources]

    ndim = property(lambda self: len(self.shape))
    nbytes = 0                  # on disk of its own: none (the scene's files are the rows)

    def __len__(self) -> int:
        return self.shape[0]

    def __iter__(self):
        return (self[v] for v in range(self.shape[0]))

    def _row(self, v: int) -> np.ndarray:
        v = int(v)
        if not -self.shape[0] <= v < self.shape[0]:
            raise IndexError(f"row {v} of {self.shape[0]}")
        v %= self.shape[0]
        for path, stamp in self.stamps[v]:
            if not path.is_file() or _stamp(path) != stamp:
                raise InputError.single(str(path), self.name, (
                    "the file changed (or went) after the set-up read it: the run reads it again for each batch "
                    "that has its view; restore it, or start the run again to use the new file"))
        row = self.read(v)
        if row.shape != self.row_shape:
            raise ValueError(f"{self.name}: view {v} read as {row.shape}, not {self.row_shape}")
        return row

    def __getitem__(self, ids) -> np.ndarray:
        def read(v, out):
            out[...] = self._row(v)

        return _read_rows(ids, self.name, self.row_shape, self.dtype, read)


def free_bytes(path: Path) -> int | None:
    """Free bytes on the disk that `path` (or its closest existing parent) is on; None if none exists."""
    existing = next((p for p in (Path(path), *Path(path).parents) if p.exists()), None)
    return None if existing is None else shutil.disk_usage(existing).free


class ViewFolder:
    """Where `ViewRows` files are opened: `cache`/view_rows (created on first use)."""

    def __init__(self, cache: Path):
        self.root = Path(cache) / "view_rows"
        self._count = 0
        self.nbytes = 0          # of every file opened or written here (on disk while their arrays live)

    def check_space(self, nbytes: int, what: str) -> None:
        """InputError naming the folder, before anything is written, when `nbytes` would not fit
        on its disk with DISK_HEADROOM to spare."""
        free = free_bytes(self.root)
        if free is not None and nbytes + DISK_HEADROOM > free:
            gb = 2 ** 30
            raise InputError.single(str(self.root), "disk space", (
                f"{what} need {nbytes / gb:.2f} GB here (plus {DISK_HEADROOM / gb:.2f} GB kept free), and its disk "
                f"has {free / gb:.2f} GB free; free space there, point $JAXDISTILL_CACHE at a folder on a larger "
                "disk, or hold them in memory with --view_data=memory"))

    def _path(self, name: str) -> Path:
        """A unique name (host, process, folder, count) for the moment before the file is unlinked."""
        self.root.mkdir(parents=True, exist_ok=True)
        self._count += 1
        return self.root / f"{name}-{socket.gethostname()}-{os.getpid()}-{id(self)}-{self._count}.bin"

    def rows(self, name: str, shape: tuple[int, ...], dtype) -> ViewRows:
        rows = ViewRows(self._path(name), shape, dtype)
        self.nbytes += rows.nbytes
        return rows


def view_array(name: str, shape: tuple[int, ...], dtype, folder: ViewFolder | None):
    """A zeroed (V, ...) NumPy array when `folder` is None, else a `ViewRows` file in it."""
    if folder is None:
        return np.zeros(shape, dtype)
    return folder.rows(name, shape, dtype)


class MapRows(Sequence):
    """Per view a dict {map: (H, W, C) float32 image} (a view's ground-truth maps), each map's
    images in a `ViewRows` file (V, H, W, C) of `folder`: `rows[v] = {map: image}` writes view v's
    (a map its first time takes its whole file: `maps` {map: C} names every map a view may have),
    `rows[v]` reads back the maps view v has. Which views have which map stays in memory (a bool a
    view a map)."""

    def __init__(self, folder: ViewFolder, name: str, count: int, shape: tuple[int, int], maps: dict[str, int]):
        self.folder, self.name, self.count, self.shape, self.maps = folder, name, int(count), tuple(shape), dict(maps)
        self.rows: dict[str, ViewRows] = {}
        self.present = {m: np.zeros(self.count, bool) for m in self.maps}

    def __len__(self) -> int:
        return self.count

    def __setitem__(self, v: int, maps: dict) -> None:
        unknown = sorted(set(maps) - set(self.maps))
        if unknown:
            raise ValueError(f"{self.name}: maps {unknown} were not among those its files were sized for "
                             f"({sorted(self.maps)})")
        for m, image in maps.items():
            image = np.asarray(image)
            if image.dtype != np.float32:
                raise TypeError(f"{self.name}: {m} of view {v} is {image.dtype}, not float32 (kept as it is in memory)")
            if m not in self.rows:
                self.rows[m] = self.folder.rows(f"{self.name}_{m}", (self.count, *self.shape, self.maps[m]), np.float32)
            self.rows[m][v] = image
            self.present[m][v] = True

    def __getitem__(self, v):
        if isinstance(v, slice):
            return [self[i] for i in range(*v.indices(self.count))]
        return _ViewMaps(self, range(self.count)[v])


class _ViewMaps(Mapping):
    """View v's maps of a `MapRows`: its map names without a read, a map's image read from its file
    when asked for (each time: nothing is kept)."""

    def __init__(self, rows: MapRows, v: int):
        self._rows, self._v = rows, v

    def __getitem__(self, m: str) -> np.ndarray:
        if m not in self:
            raise KeyError(m)
        return self._rows.rows[m][self._v]

    def __contains__(self, m) -> bool:
        return m in self._rows.rows and bool(self._rows.present[m][self._v])

    def __iter__(self):
        return (m for m in self._rows.rows if self._rows.present[m][self._v])

    def __len__(self) -> int:
        return sum(1 for _ in self)


class LazyViews(Sequence):
    """Per-view values made when asked for, `chunk` views at a time: `load(first)` returns the
    values of views first, ..., first + chunk - 1 (fewer at the end), e.g. their images read from
    files or rendered in one batch. Going through the views holds one chunk; the last chunk is
    kept (callers often ask for the same view again at once). Safe to share between threads."""

    def __init__(self, count: int, load: Callable[[int], list], chunk: int = 1):
        self.count, self.load, self.chunk = count, load, chunk
        self._lock = threading.Lock()
        self._kept: tuple[int, list] | None = None

    def __len__(self) -> int:
        return self.count

    def __getitem__(self, v):
        if isinstance(v, slice):
            return [self[i] for i in range(*v.indices(self.count))]
        v = int(v)
        if not -self.count <= v < self.count:
            raise IndexError(f"view {v} of {self.count}")
        v %= self.count
        first = v - v % self.chunk
        with self._lock:
            if self._kept is None or self._kept[0] != first:
                self._kept = (first, list(self.load(first)))
            return self._kept[1][v - first]
