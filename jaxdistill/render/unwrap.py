"""UV layout for meshes whose texture coordinates cannot be used as they are.

Every object gets its own square, power-of-two texture page (layout "pages"), so its UVs
must lie in [0, 1] (u right, v up) and must not overlap. `ensure_uvs(mesh, cameras)` decides
per object and returns the mesh with new UVs where needed (vertices, faces, face ids and
object names are the very same arrays) and one `UVDecision` per object.

Rules:

1. **Detection** (`uv_checks.uv_problem`): an object keeps its UVs unless they are missing (all
   NaN: "no texture coordinates"; `scene.load_mesh(require_uv=False)` gives those), partly
   non-finite, tiled (outside [0, 1]), collapsed (faces with zero UV area over more than
   UV_COLLAPSED_LIMIT = 1 % of its surface) or overlapping (more than UV_OVERLAP_LIMIT = 2 % of
   the covered texel centres of a UV_RASTER^2 = 256^2 raster covered twice). Policy "auto"
   re-unwraps exactly those objects, "unwrap" every object, "keep" refuses (InputError naming
   the file, every such object and why).
2. **Texel density** (`observed_texels_per_unit`): for each object, a robust maximum (the
   99.9th percentile) over the pixels that see it of f / depth, texels per world unit at one
   texel per pixel (f the camera's focal in pixels, depth its z of the hit). Only a grid of at
   most OBSERVE_WIDTH = 160 pixels across per camera is cast; f stays the native focal. The
   density is quantised to the nearest power of two (in log scale) so that a slightly different
   set of cameras gives the same layout (and reuses the cache). Objects no camera sees get the
   median of the others; without any camera an object gets the density that fills about a
   DEFAULT_RESOLUTION = 1024 page (not quantised).
3. **Unwrap** (`unwrap_object`; the xatlas calls and the packing are in `atlas`): xatlas packs
   the charts at that density with XATLAS_PADDING = 2 texels between charts. Chart growth is
   capped at about CHART_FACES = 1000 faces per chart (in area: CHART_FACES x the mean face
   area; objects of <= CHART_FACES faces are uncapped), which keeps xatlas linear in the face
   count at the price of more seams (one uncapped chart of a noisy 12k-face grid takes 22-43 s,
   capped 1.6 s). The page side is the next power of two >= the atlas side (at least 8), at most
   `max_page_size` (4096): when the area estimate (EXPECTED_FILL) or the result says the atlas
   would be larger, it is made at a lower density (said in the decision's reason; after
   CAP_RETRIES the layout is scaled down, padding with it). The atlas rectangle sits in the
   page's corner [0, w / page] x [0, h / page] with square texels. xatlas's v points down
   (image rows) and is flipped to our v up.
   Orientation: xatlas parameterises each chart without folds but leaves some charts mirrored
   (about half the faces of an icosphere; a flat grid comes out unmirrored, a slightly noisy
   one mirrored). We keep its charts as they are, since mirroring one in place could make it
   overlap a neighbour: a page may hold mirrored charts, each consistent in itself.
4. **Large objects**: above `chunk_faces` (CHUNK_FACES) faces an object is split into spatial
   chunks (recursive median split of the face centroids along the longest axis), each
   unwrapped by its own xatlas call at the same density; xatlas then packs the charts of all
   chunks together (as a UV mesh at one texel per unit, `padding` apart: 3 s for 327k faces
   into 4258^2, fill as good as one call; should that fail, the chunk rectangles go into a
   shelf packer). Before starting, the time is estimated as faces x SECONDS_PER_FACE
   (refined after the first chunk); an object with more than `max_faces` faces, or whose
   estimate exceeds `time_limit_s`, is refused with an InputError that says how to decimate
   it. A tqdm bar per object (faces, with ETA) and a log line per object with the time taken
   report progress; `ensure_uvs` checks every object's limits before unwrapping any.
5. **Cache**: the new UVs of an object are stored in `<cache_dir>/unwrap/<key>.npz`, key =
   sha256 of the object's own vertices and faces and of what changes the result (requested
   density, padding, max_page_size, chunk_faces, CHART_FACES, xatlas version, CACHE_VERSION).
   A hit takes no xatlas time and says so in the decision (`cached=True`).
"""

from __future__ import annotations

import dataclasses
import hashlib
import logging
import math
import os
import time
import zipfile
from pathlib import Path
from typing import Sequence

import numpy as np
from tqdm.auto import tqdm

from jaxdistill.errors import InputError, ProblemList
from jaxdistill.render.atlas import CHART_FACES, face_areas, merge_atlases, split_chunks, xatlas_chunk, xatlas_version
from jaxdistill.render.uv_checks import uv_problem
from jaxdistill.scene.cameras import Camera
from jaxdistill.scene.model import Mesh

log = logging.getLogger(__name__)

XATLAS_PADDING = 2
OBSERVE_WIDTH = 160
DENSITY_QUANTILE = 0.999
DEFAULT_RESOLUTION = 1024
MIN_PAGE_SIZE = 8
EXPECTED_FILL = 0.5             # conservative xatlas utilisation (measured 0.55-0.75) for size estimates
CHUNK_PACKING = 0.9             # chunk charts repacked together: a little below one xatlas call
CHUNK_FACES = 100_000           # faces per xatlas call: 20k-200k measured linear with the cap, 320k not
SECONDS_PER_FACE = 2.5e-4       # xatlas time per face (upper end of scripts/bench_unwrap.py), for the estimate in logs
MAX_FACES = 4_000_000
TIME_LIMIT_S = 1800.0
CAP_RETRIES = 3
CACHE_VERSION = 1
POLICIES = ("auto", "unwrap", "keep")
DECIMATE_HINT = ("decimate it to <= {n} faces, e.g. MeshLab 'Quadric Edge Collapse Decimation', Blender's Decimate "
                 "modifier or trimesh's simplify_quadric_decimation; or raise --max_unwrap_faces / "
                 "--unwrap_time_limit")


@dataclasses.dataclass(frozen=True)
class UVDecision:
    """What happened to one object's UVs: kept, or re-unwrapped because of `reason`.

    page_size: side of the page the unwrap was packed for (None when kept); texels_per_unit:
    the density it was packed at; cached: the UVs came from the cache; faces: the object's faces.
    """

    name: str
    reunwrapped: bool
    reason: str
    seconds: float
    page_size: int | None = None
    texels_per_unit: float | None = None
    cached: bool = False
    faces: int | None = None


@dataclasses.dataclass(frozen=True)
class UnwrapResult:
    """uv (F, 3, 2) float64 in [0, 1], v up; the page side it was packed for; the density used
    (texels per world unit, lower than requested when capped); chunks; cached; a note (cap)."""

    uv: np.ndarray
    page_size: int
    texels_per_unit: float
    chunks: int
    cached: bool
    note: str = ""


# ----------------------------------------------------------------------------- texel density


def observed_texels_per_unit(mesh: Mesh, cameras: Sequence[Camera], *, max_width: int = OBSERVE_WIDTH,
                             quantile: float = DENSITY_QUANTILE) -> np.ndarray:
    """(num_objects,) float64: per object, the `quantile` over the pixels that hit it of f / depth.

    f / depth is texels per world unit at one texel per pixel (f = max(fx, fy) of the native
    camera, depth = camera z of the hit). Per camera only a grid of at most `max_width` pixels
    across (same aspect) is cast. NaN for objects no camera sees.
    """
    from jaxdistill.render.fragments import RayCaster

    num_objects = len(mesh.object_names)
    out = np.full(num_objects, np.nan)
    if not cameras:
        return out
    caster = RayCaster(mesh)
    objects, densities = [], []
    for cam in cameras:
        gw = max(1, min(cam.width, int(max_width)))
        gh = max(1, int(round(cam.height * gw / cam.width)))
        xs = (np.arange(gw) + 0.5) * (cam.width / gw)
        ys = (np.arange(gh) + 0.5) * (cam.height / gh)
        px, py = np.meshgrid(xs, ys)
        origins, dirs = cam.pixel_rays(np.stack([px.ravel(), py.ravel()], axis=1))
        tri, _, dist = caster.intersect(origins, dirs)
        hit = tri >= 0
        depth = dist[hit] * (dirs[hit] @ cam.c2w[:3, 2])
        ok = np.isfinite(depth) & (depth > 0)
        objects.append(mesh.face_object[tri[hit]][ok])
        densities.append(max(cam.K[0, 0], cam.K[1, 1]) / depth[ok])
    objects, densities = np.concatenate(objects), np.concatenate(densities)
    for o in np.unique(objects):
        out[o] = float(np.quantile(densities[objects == o], quantile))
    return out


def quantise_density(texels_per_unit: float) -> float:
    """The power of two nearest to texels_per_unit (> 0) in log scale (2^k, k may be negative)."""
    return float(2.0 ** round(math.log2(texels_per_unit)))


def default_texels_per_unit(area: float, resolution: int = DEFAULT_RESOLUTION) -> float:
    """Density at which a surface of `area` (world units^2) fills about a resolution^2 page."""
    return resolution * math.sqrt(EXPECTED_FILL / max(area, 1e-300))


def _next_power_of_two(x: float) -> int:
    return 1 << max(0, int(math.ceil(math.log2(max(x, 1.0)))))


def _object_key(vertices: np.ndarray, faces: np.ndarray, texels_per_unit: float, padding: int, max_page_size: int,
                chunk_faces: int) -> str:
    h = hashlib.sha256(f"unwrap v{CACHE_VERSION} xatlas {xatlas_version()} chart {CHART_FACES} pad {padding} "
                       f"max {max_page_size} chunk {chunk_faces} tpu {float(texels_per_unit).hex()}".encode())
    for array in (vertices.astype(np.float64), faces.astype(np.int64)):
        h.update(str(array.shape).encode())
        h.update(np.ascontiguousarray(array).tobytes())
    return h.hexdigest()


def _cache_folder(cache_dir) -> Path | None:
    if cache_dir is False:
        return None
    from jaxdistill.render.fragments import default_cache_dir

    return Path(cache_dir or default_cache_dir()) / "unwrap"


def _read_cache(path: Path, num_faces: int) -> UnwrapResult | None:
    """The cached result at `path`, or None when absent or unreadable (then it is recomputed)."""
    if not path.is_file():
        return None
    try:
        with np.load(path) as data:
            result = UnwrapResult(uv=data["uv"], page_size=int(data["page_size"]),
                                  texels_per_unit=float(data["texels_per_unit"]), chunks=int(data["chunks"]),
                                  cached=True, note=str(data["note"]))
    except (OSError, ValueError, KeyError, zipfile.BadZipFile) as err:
        log.warning("unreadable unwrap cache file %s (%s): unwrapping again", path, err)
        return None
    return result if result.uv.shape == (num_faces, 3, 2) else None


def compact(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The vertices (V', 3) used by `faces` and faces (F, 3) re-indexed into them (order kept)."""
    used, inverse = np.unique(faces, return_inverse=True)
    return vertices[used], inverse.reshape(faces.shape).astype(np.int64)


def refusal(name: str, faces: int, estimate_s: float | None, *, max_faces: int, time_limit_s: float) -> str | None:
    """Why unwrapping `faces` faces (estimated `estimate_s` seconds) is refused, or None."""
    if faces > max_faces:
        return (f"object {name!r} has {faces} faces, more than the {max_faces} this unwrap accepts (about "
                f"{faces * SECONDS_PER_FACE / 60:.0f} min of xatlas); " + DECIMATE_HINT.format(n=max_faces))
    if estimate_s is not None and estimate_s > time_limit_s:
        n = max(1, int(faces * time_limit_s / estimate_s))
        return (f"object {name!r} has {faces} faces: unwrapping it would take about {estimate_s:.0f} s, more than "
                f"the limit of {time_limit_s:.0f} s; " + DECIMATE_HINT.format(n=n))
    return None


def unwrap_object(vertices: np.ndarray, faces: np.ndarray, *, texels_per_unit: float | None = None,
                  name: str = "object", max_page_size: int = 4096, padding: int = XATLAS_PADDING,
                  chunk_faces: int = CHUNK_FACES, cache_dir=None, progress: bool = True,
                  max_faces: int = MAX_FACES, time_limit_s: float = TIME_LIMIT_S, mesh_file: str = "mesh",
                  ) -> UnwrapResult:
    """New UVs (F, 3, 2) in [0, 1], v up, for one object (vertices (V, 3), faces (F, 3) into them).

    texels_per_unit: the density to pack at (None: `default_texels_per_unit` of its area). See
    the module docstring for chunking, capping, limits (InputError naming `mesh_file`) and cache.
    """
    start = time.perf_counter()
    vertices, faces = compact(np.asarray(vertices, np.float64), np.asarray(faces, np.int64))
    num_faces = len(faces)
    areas = face_areas(vertices, faces)
    total_area = float(areas.sum())
    requested = default_texels_per_unit(total_area) if texels_per_unit is None else float(texels_per_unit)
    if not (math.isfinite(requested) and requested > 0):
        raise ValueError(f"texels_per_unit must be finite and > 0, got {requested!r}")
    folder = _cache_folder(cache_dir)
    path = None
    if folder is not None:
        path = folder / f"{_object_key(vertices, faces, requested, padding, max_page_size, chunk_faces)}.npz"
        result = _read_cache(path, num_faces)
        if result is not None:
            log.info("uv unwrap %s: %d faces from the cache (%s) in %.2f s", name, num_faces, path.name[:12],
                     time.perf_counter() - start)
            return result
    why = refusal(name, num_faces, num_faces * SECONDS_PER_FACE, max_faces=max_faces, time_limit_s=time_limit_s)
    if why:
        raise InputError.single(mesh_file, f"object {name!r}", why)

    # Keep the atlas within max_page_size: start from the area estimate, then redo with the measured size.
    tpu, note = requested, ""
    centroids = vertices[faces].mean(axis=1)
    chunks = split_chunks(centroids, max(1, int(chunk_faces))) if num_faces > chunk_faces else [np.arange(num_faces)]
    fill = EXPECTED_FILL * (CHUNK_PACKING if len(chunks) > 1 else 1.0)
    estimate = math.sqrt(total_area / fill) * tpu
    if estimate > max_page_size:
        tpu = requested * max_page_size / estimate
    pieces = [compact(vertices, faces[idx]) for idx in chunks]
    for attempt in range(CAP_RETRIES + 1):
        uv_texel, side = _unwrap_chunks(pieces, chunks, tpu, padding, name=name, progress=progress,
                                        time_limit_s=time_limit_s, mesh_file=mesh_file, num_faces=num_faces,
                                        elapsed=time.perf_counter() - start)
        if side <= max_page_size or attempt == CAP_RETRIES:
            break
        tpu *= 0.97 * max_page_size / side
    if side > max_page_size:       # still too large after the retries: scale down (padding shrinks with it)
        uv_texel *= max_page_size / side
        tpu *= max_page_size / side
        side = max_page_size
    if tpu < requested * (1 - 1e-9):
        note = f"capped at page {max_page_size}: {requested:.4g} -> {tpu:.4g} texels/unit"
    page_size = min(max(_next_power_of_two(side), MIN_PAGE_SIZE), max_page_size)
    uv = np.clip(uv_texel / page_size, 0.0, 1.0)
    result = UnwrapResult(uv=uv, page_size=page_size, texels_per_unit=tpu, chunks=len(chunks), cached=False,
                          note=note)
    if path is not None:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(path.name + f".{os.getpid()}.tmp.npz")
        np.savez(tmp, uv=uv, page_size=page_size, texels_per_unit=tpu, chunks=len(chunks), note=note)
        os.replace(tmp, path)
    log.info("uv unwrap %s: %d faces, %d chunk(s), page %d, %.4g texels/unit%s in %.1f s", name, num_faces,
             len(chunks), page_size, tpu, f" ({note})" if note else "", time.perf_counter() - start)
    return result


def _unwrap_chunks(pieces, chunks, tpu: float, padding: int, *, name: str, progress: bool, time_limit_s: float,
                   mesh_file: str, num_faces: int, elapsed: float) -> tuple[np.ndarray, int]:
    """xatlas per chunk at `tpu`, then merged: (texel coords (F, 3, 2) in [0, w] x [0, h], v up, max(w, h))."""
    parts = []
    done, t0 = 0, time.perf_counter()
    with tqdm(total=num_faces, desc=f"uv unwrap {name}", unit="face", unit_scale=True, disable=not progress,
              dynamic_ncols=True) as bar:
        for i, (v, f) in enumerate(pieces):
            parts.append(xatlas_chunk(v, f, tpu, padding))
            done += len(f)
            bar.update(len(f))
            if i == 0 and len(pieces) > 1:                      # refine the estimate with the measured rate
                spent = time.perf_counter() - t0
                estimate = elapsed + spent * num_faces / max(done, 1)
                why = refusal(name, num_faces, estimate, max_faces=num_faces, time_limit_s=time_limit_s)
                if why:
                    raise InputError.single(mesh_file, f"object {name!r}", why + f" (measured on the first "
                                            f"chunk: {spent / max(done, 1) * 1e6:.0f} us/face)")
        if len(parts) == 1:
            texel, width, height = parts[0].texels[parts[0].faces], parts[0].width, parts[0].height
        else:
            bar.set_postfix_str("packing chunks")
            merged, width, height = merge_atlases(parts, padding)
            texel = np.empty((num_faces, 3, 2))
            texel[np.concatenate(chunks)] = merged
    texel[..., 1] = height - texel[..., 1]                      # xatlas v down -> ours v up
    return texel, max(width, height)


# ----------------------------------------------------------------------------- entry point


def ensure_uvs(mesh: Mesh, cameras: Sequence[Camera] = (), *, policy: str = "auto", max_page_size: int = 4096,
               cache_dir=None, progress: bool = True, max_faces: int = MAX_FACES,
               time_limit_s: float = TIME_LIMIT_S, mesh_file: str = "mesh",
               chunk_faces: int = CHUNK_FACES) -> tuple[Mesh, list[UVDecision]]:
    """The mesh with usable UVs for every object, and one UVDecision per object.

    policy "auto": keep objects whose UVs are usable, unwrap the others; "unwrap": unwrap every
    object; "keep": raise InputError (naming mesh_file, object and reason) for any unusable
    object. The returned Mesh shares vertices, faces, face_object and object_names; only uv is new.
    Limits (max_faces, time_limit_s) are checked for every object before any is unwrapped.
    """
    if max_page_size < MIN_PAGE_SIZE or max_page_size & (max_page_size - 1):
        raise InputError.single("arguments", "max_page_size", f"must be a power of two >= {MIN_PAGE_SIZE}, got "
                                f"{max_page_size!r}")
    if policy not in POLICIES:
        raise InputError.single("arguments", "uv policy", f"unknown policy {policy!r}; use one of "
                                f"{', '.join(POLICIES)}")
    cameras = list(cameras)
    num_objects = len(mesh.object_names)
    order = np.argsort(mesh.face_object, kind="stable")
    bounds = np.searchsorted(mesh.face_object[order], np.arange(num_objects + 1))
    object_faces = [order[bounds[o]:bounds[o + 1]] for o in range(num_objects)]
    reasons: list[str | None] = []
    problems = ProblemList()
    for o, idx in enumerate(object_faces):
        start = time.perf_counter()
        reason = uv_problem(mesh.uv[idx], mesh.vertices[mesh.faces[idx]]) if len(idx) else None
        if policy == "unwrap" and len(idx):
            reason = reason or "unwrap requested"
        if policy == "keep" and reason is not None:
            problems.add(mesh_file, f"object {mesh.object_names[o]!r} uv", f"{reason}: cannot be kept (uv policy "
                         "'keep'); use policy 'auto' to re-unwrap it with xatlas")
        reasons.append(reason)
        log.debug("uv check %s: %s in %.2f s", mesh.object_names[o], reason or "usable", time.perf_counter() - start)
    problems.raise_if_any()

    todo = [o for o in range(num_objects) if reasons[o] is not None]
    density = np.full(num_objects, np.nan)
    if todo and cameras:
        observed = observed_texels_per_unit(mesh, cameras)
        seen = observed[np.isfinite(observed) & (observed > 0)]
        fallback = float(np.median(seen)) if len(seen) else np.nan
        density = np.where(np.isfinite(observed) & (observed > 0), observed, fallback)
        density = np.array([quantise_density(d) if np.isfinite(d) else np.nan for d in density])
    for o in todo:                                            # refuse before unwrapping anything
        n = len(object_faces[o])
        why = refusal(mesh.object_names[o], n, n * SECONDS_PER_FACE, max_faces=max_faces, time_limit_s=time_limit_s)
        if why and not _is_cached(mesh, object_faces[o], density[o], max_page_size, chunk_faces, cache_dir):
            problems.add(mesh_file, f"object {mesh.object_names[o]!r}", why)
    problems.raise_if_any()

    uv = mesh.uv.copy()
    decisions = []
    for o, idx in enumerate(object_faces):
        name = mesh.object_names[o]
        if reasons[o] is None:
            decisions.append(UVDecision(name, False, "kept" if len(idx) else "no faces", 0.0, faces=len(idx)))
            continue
        start = time.perf_counter()
        result = unwrap_object(mesh.vertices, mesh.faces[idx], texels_per_unit=_or_none(density[o]), name=name,
                               max_page_size=max_page_size, chunk_faces=chunk_faces, cache_dir=cache_dir,
                               progress=progress, max_faces=max_faces, time_limit_s=time_limit_s,
                               mesh_file=mesh_file)
        uv[idx] = result.uv
        reason = reasons[o] + (f"; {result.note}" if result.note else "")
        decisions.append(UVDecision(name, True, reason, time.perf_counter() - start, page_size=result.page_size,
                                    texels_per_unit=result.texels_per_unit, cached=result.cached, faces=len(idx)))
    out = Mesh(vertices=mesh.vertices, faces=mesh.faces, uv=uv, face_object=mesh.face_object,
               object_names=mesh.object_names)
    return out, decisions


def _or_none(x: float) -> float | None:
    return float(x) if np.isfinite(x) else None


def _is_cached(mesh: Mesh, idx: np.ndarray, density: float, max_page_size: int, chunk_faces: int, cache_dir) -> bool:
    folder = _cache_folder(cache_dir)
    if folder is None:
        return False
    vertices, faces = compact(mesh.vertices, mesh.faces[idx])
    tpu = density if np.isfinite(density) else default_texels_per_unit(float(face_areas(vertices, faces).sum()))
    return (folder / f"{_object_key(vertices, faces, tpu, XATLAS_PADDING, max_page_size, chunk_faces)}.npz").is_file()


def format_decisions(decisions: Sequence[UVDecision]) -> str:
    """A plain-text table: object, faces, kept/unwrapped, reason, page, seconds, cached."""
    rows = [("object", "faces", "uv", "reason", "page", "seconds", "cached")]
    for d in decisions:
        rows.append((d.name, "" if d.faces is None else str(d.faces), "unwrapped" if d.reunwrapped else "kept",
                     d.reason if d.reunwrapped else "", "" if d.page_size is None else str(d.page_size),
                     f"{d.seconds:.2f}", "yes" if d.cached else ""))
    widths = [max(len(r[i]) for r in rows) for i in range(len(rows[0]))]
    lines = ["  ".join(c.ljust(w) if i in (0, 2, 3, 6) else c.rjust(w) for i, (c, w) in enumerate(zip(r, widths)))
             for r in rows]
    return "\n".join(line.rstrip() for line in lines)
