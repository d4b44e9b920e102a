"""Image files through OpenImageIO: float32 HWC arrays, linear light inside the program.

Files: EXR/HDR/TIFF-float hold linear values; PNG/JPG (8/16-bit) hold sRGB-encoded values.
`read_image` returns linear light for both, `write_image` encodes sRGB for LDR formats.

Inside `with cached_reads():` each file's pixels are decoded once: validation reads every image
(a truncated file is caught before any compute) and the pipeline's later reads of the same
file reuse them, up to CACHE_BYTES (least recently used first out; larger sets are re-read).
"""

from __future__ import annotations

import contextlib
import os
import threading
from collections import OrderedDict
from pathlib import Path

import numpy as np
import OpenImageIO as oiio

from jaxdistill.errors import InputError

LINEAR_EXTENSIONS = (".exr", ".hdr", ".pfm")
CACHE_BYTES = 1 << 30

_cache: OrderedDict | None = None     # (path, inode, size, mtime) -> file values, inside cached_reads()
_cache_lock = threading.Lock()


def is_linear_format(path) -> bool:
    """True when the file format stores linear light (EXR, HDR, PFM); False for sRGB LDR files."""
    return Path(path).suffix.lower() in LINEAR_EXTENSIONS


def srgb_to_linear(x: np.ndarray) -> np.ndarray:
    """IEC 61966-2-1 sRGB decode of values in [0, 1] -> linear [0, 1]."""
    x = np.asarray(x, np.float32)
    return np.where(x <= 0.04045, x / 12.92, ((x + 0.055) / 1.055) ** 2.4).astype(np.float32)


def linear_to_srgb(x: np.ndarray) -> np.ndarray:
    """IEC 61966-2-1 sRGB encode of linear values (clipped to [0, 1]) -> [0, 1]."""
    x = np.clip(np.asarray(x, np.float32), 0.0, 1.0)
    return np.where(x <= 0.0031308, x * 12.92, 1.055 * x ** (1 / 2.4) - 0.055).astype(np.float32)


def linear_to_srgb_and_slope(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """`linear_to_srgb(x)` and x · d/dx of it (0 where x is clipped): the derivative of the
    encoding with respect to log x, for solving for a gain in log space."""
    x = np.maximum(np.asarray(x, np.float32), np.float32(0.0))
    low, mid = x <= 0.0031308, (x > 0.0031308) & (x < 1.0)
    y = np.power(np.where(mid, x, 1.0), np.float32(1 / 2.4))
    value = np.where(low, 12.92 * x, np.where(mid, 1.055 * y - 0.055, 1.0)).astype(np.float32)
    slope = np.where(low, 12.92 * x, np.where(mid, (1.055 / 2.4) * y, 0.0)).astype(np.float32)
    return value, slope


def image_size(path) -> tuple[int, int, int]:
    """(width, height, channels) from the file header, without reading pixels."""
    inp = oiio.ImageInput.open(os.fspath(path))
    if inp is None:
        raise OSError(f"{path}: cannot open image: {oiio.geterror()}")
    spec = inp.spec()
    inp.close()
    return spec.width, spec.height, spec.nchannels


@contextlib.contextmanager
def cached_reads():
    """Within the block, `read_image` decodes each file once (LRU, up to CACHE_BYTES of pixels);
    the cache is dropped on exit. Nested blocks share the outer cache."""
    global _cache
    if _cache is not None:
        yield
        return
    _cache = OrderedDict()
    try:
        yield
    finally:
        _cache = None


def _cache_key(path) -> tuple:
    st = os.stat(path)
    return os.path.realpath(path), st.st_ino, st.st_size, st.st_mtime_ns, st.st_ctime_ns


def _decode(path) -> np.ndarray:
    """(H, W, C) float32 values as stored in the file; OSError naming what the decoder said."""
    inp = oiio.ImageInput.open(os.fspath(path))
    if inp is None:
        raise OSError(f"{path}: cannot open image: {oiio.geterror()}")
    pixels = inp.read_image(format="float")
    failed, message = pixels is None or inp.has_error, inp.geterror()
    inp.close()
    if failed:   # truncated or damaged: some decoders return partial pixels and only flag the error
        detail = " ".join(message.split()) or oiio.geterror() or "the decoder gave no reason"
        raise OSError(f"{path}: cannot read pixels (truncated or damaged file?): {detail}")
    pixels = np.asarray(pixels, np.float32)
    return pixels[:, :, None] if pixels.ndim == 2 else pixels


def _file_values(path) -> np.ndarray:
    """`_decode(path)`, through the cache of `cached_reads` when one is open (a private copy)."""
    cache = _cache
    if cache is None:
        return _decode(path)
    key = _cache_key(path)
    with _cache_lock:
        hit = cache.get(key)
        if hit is not None:
            cache.move_to_end(key)
            return hit.copy()
    pixels = _decode(path)
    if pixels.nbytes <= CACHE_BYTES:
        with _cache_lock:
            cache[key] = pixels
            total = sum(a.nbytes for a in cache.values())
            while total > CACHE_BYTES:
                total -= cache.popitem(last=False)[1].nbytes
        return pixels.copy()
    return pixels


def read_image(path, *, linear: bool = True) -> np.ndarray:
    """(H, W, C) float32 pixels; LDR files are sRGB-decoded to linear unless `linear=False`.
    OSError (naming the file and the decoder's reason) when the file cannot be read in full."""
    pixels = _file_values(path)
    if linear and not is_linear_format(path):
        pixels = srgb_to_linear(pixels)
    return pixels


# zlib's level for PNGs (OpenImageIO's default is 6): the bedroom's 150 map pages encode in 0.46x
# the time, its 240 renders in 0.42x, for files 8 % and 4 % larger (lossless either way)
PNG_COMPRESSION_LEVEL = 4


def write_image(path, pixels: np.ndarray, *, encode_srgb: bool | None = None, half: bool = False,
                compression: str | None = None, timestamp: str | None = None) -> None:
    """Writes (H, W) or (H, W, C) linear float pixels; PNG/JPG get sRGB encoding by default.

    EXR is written as float32, or float16 with `half=True`; `compression` sets the EXR codec
    (e.g. "zip", "piz", "dwaa:45"; OpenImageIO's default otherwise). For LDR files
    `encode_srgb=False` writes values as-is (data maps such as normals, roughness, counts in [0, 1]).
    EXR headers carry the write time unless `timestamp` ("YYYY:MM:DD hh:mm:ss") fixes it, which
    makes the file byte-reproducible.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    pixels = np.asarray(pixels, np.float32)
    if pixels.ndim == 2:
        pixels = pixels[:, :, None]
    linear_file = is_linear_format(path)
    if encode_srgb is None:
        encode_srgb = not linear_file
    if not linear_file:
        pixels = linear_to_srgb(pixels) if encode_srgb else np.clip(pixels, 0.0, 1.0)
    ext = path.suffix.lower()
    dtype = ("half" if half else "float") if linear_file else ("uint16" if ext in (".tif", ".tiff") else "uint8")
    buf = oiio.ImageBuf(np.ascontiguousarray(pixels))
    if compression:
        buf.specmod().attribute("compression", compression)
    if ext == ".png":
        buf.specmod().attribute("png:compressionLevel", PNG_COMPRESSION_LEVEL)
    if timestamp:
        buf.specmod().attribute("DateTime", timestamp)
    tmp = path.with_name(path.name + ".tmp" + path.suffix)
    if not buf.write(os.fspath(tmp), dtype):
        raise OSError(f"{path}: cannot write image: {oiio.geterror()}")
    os.replace(tmp, path)


def read_photo_srgb(path: Path, exposure: float = 0.0) -> np.ndarray:
    """(H, W, 3) float32 sRGB-encoded values in [0, 1] from an LDR or HDR photo file, after
    scaling its linear values by 2**exposure (stops; `exposure.py`)."""
    if exposure:
        pixels = linear_to_srgb(np.clip(read_image(path) * np.float32(2.0 ** exposure), 0.0, 1.0))
    elif is_linear_format(path):
        pixels = linear_to_srgb(np.clip(read_image(path), 0.0, 1.0))
    else:
        pixels = read_image(path, linear=False)
    if pixels.shape[-1] < 3:
        raise InputError.single(path, "channels", f"has {pixels.shape[-1]} channels; RGB↔X needs a colour photo")
    return np.clip(pixels[..., :3], 0.0, 1.0)
