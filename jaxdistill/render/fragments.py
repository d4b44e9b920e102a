"""Fragment buffers: one primary ray per pixel centre, cast once per view with Embree.

The ray cast (triangle id, barycentrics, distance) is the only expensive part and is cached
on disk under a key that hashes the mesh geometry, the camera and the resolution. Everything
else (UV, depth, UV derivatives) is derived exactly from it in float64 NumPy.

Geometry is translated and scaled to a unit box before it reaches Embree (float32), so scenes
in millimetres or kilometres get the same relative precision. Back faces are hit (cameras
inside rooms see the inside of walls); zero-area triangles are never hit; misses get id -1.
"""

from __future__ import annotations

import dataclasses
import hashlib
import os
import shutil
from pathlib import Path
from typing import Callable, Sequence

import numpy as np
from tqdm.auto import tqdm

from jaxdistill.errors import InputError
from jaxdistill.io.cache import default_cache_dir  # noqa: F401  (fr.default_cache_dir: callers read it from here)
from jaxdistill.scene.cameras import Camera
from jaxdistill.scene.model import Mesh
from jaxdistill.threads import ordered_map

CACHE_VERSION = 1
RAYS_PER_CALL = 1 << 20
NEAR_TRIANGLE = 1e-2  # how far (barycentric units) the exact hit may lie outside Embree's triangle


@dataclasses.dataclass(frozen=True, eq=False)
class Fragments:
    """Per-pixel ray hits for one view (pixel centres, row-major).

    triangle (H, W) int32 face id, -1 where the ray misses; barycentric (H, W, 2) float32
    weights of corners 1 and 2 (corner 0 gets 1 - b1 - b2); depth (H, W) float32 camera z
    in world units (inf on miss); uv (H, W, 2) float32 in [0, 1], v up; uv_grad (H, W, 2, 2)
    float32 with uv_grad[..., 0, :] = d(u, v)/dx and uv_grad[..., 1, :] = d(u, v)/dy per
    pixel (0 on miss); object_id (H, W) int32, -1 on miss. Fragments read back from per-view
    files (`FragmentRows`) have no barycentric or depth (None): nothing after the ray casts reads
    them in a run; nor uv_grad where the rows were made without it (only the trilinear sampler's
    plans read it after the page sizes are chosen).
    """

    triangle: np.ndarray
    barycentric: np.ndarray | None
    depth: np.ndarray | None
    uv: np.ndarray
    uv_grad: np.ndarray | None
    object_id: np.ndarray

    @property
    def hit(self) -> np.ndarray:
        """(H, W) bool: the pixel's ray hit a triangle."""
        return self.triangle >= 0

    @property
    def shape(self) -> tuple[int, int]:
        return self.triangle.shape


FRAGMENT_FIELDS = {"triangle": ((), np.int32), "barycentric": ((2,), np.float32), "depth": ((), np.float32),
                   "uv": ((2,), np.float32), "uv_grad": ((2, 2), np.float32), "object_id": ((), np.int32)}
BYTES_PER_PIXEL = sum(4 * int(np.prod(shape)) for shape, _ in FRAGMENT_FIELDS.values())     # 44
# what `FragmentRows` keeps of them: what a run reads after the ray casts (texel needs, gather plans and the
# evaluation: the triangle, whose object is the mesh's, and uv; uv_grad for the trilinear sampler's levels),
# not barycentric and depth; the page sizes' footprints are kept per view and page instead (`footprints`)
ROW_FIELDS = ("triangle", "uv")
UV_GRAD_FIELDS = ROW_FIELDS + ("uv_grad",)


def row_bytes_per_pixel(uv_grad: bool = False) -> int:
    """Bytes a pixel of `FragmentRows`' files: 12 (triangle, uv), 28 with uv_grad."""
    return sum(4 * int(np.prod(FRAGMENT_FIELDS[name][0])) for name in (UV_GRAD_FIELDS if uv_grad else ROW_FIELDS))


class FragmentRows(Sequence):
    """Every view's fragments (one resolution) in per-view arrays, one per field of `ROW_FIELDS`
    (and uv_grad when asked for; NumPy, or files read a view at a time: `io.view_rows`): `rows[v]`
    is view v's `Fragments` (barycentric and depth None, uv_grad None without its array; object_id
    the mesh's `face_object` of the triangle), read when asked for, so a caller that goes through
    the views holds a few views' fragments at a time (the set-up's two threads,
    `threads.ordered_map`: at most three). `footprints`: (V, pages) float64, per view and page
    `layout.page_footprints` (what `layout.make_layout` sizes pages by), or None."""

    def __init__(self, arrays: dict, shape: tuple[int, int], face_object: np.ndarray,
                 footprints: np.ndarray | None = None):
        self.arrays, self.shape, self.footprints = arrays, shape, footprints
        self.face_object = np.asarray(face_object, np.int32)

    def __len__(self) -> int:
        return len(self.arrays["triangle"])

    def __getitem__(self, v):
        if isinstance(v, slice):
            return [self[i] for i in range(*v.indices(len(self)))]
        if not -len(self) <= v < len(self):
            raise IndexError(f"view {v} of {len(self)}")
        fields = {name: a[v] for name, a in self.arrays.items()}
        triangle = fields["triangle"]
        object_id = np.where(triangle >= 0, self.face_object[np.maximum(triangle, 0)], -1).astype(np.int32)
        return Fragments(triangle=triangle, uv=fields["uv"], uv_grad=fields.get("uv_grad"), object_id=object_id,
                         barycentric=None, depth=None)


class RayCaster:
    """Embree scene of a mesh, normalised to a unit box; `intersect` returns first hits."""

    def __init__(self, mesh: Mesh):
        from embreex import mesh_construction, rtcore_scene

        lo, hi = mesh.vertices.min(axis=0), mesh.vertices.max(axis=0)
        self.center = 0.5 * (lo + hi)
        self.scale = float(max(np.max(hi - lo), np.finfo(np.float64).tiny))
        triangles = ((mesh.triangles() - self.center) / self.scale).astype(np.float32)
        self._scene = rtcore_scene.EmbreeScene()
        self._mesh = mesh_construction.TriangleMesh(self._scene, triangles)

    def intersect(self, origins: np.ndarray, directions: np.ndarray):
        """(triangle (N,) int32, barycentric (N, 2) float32, distance (N,) float64) for unit rays."""
        n = len(origins)
        triangle = np.empty(n, np.int32)
        bary = np.empty((n, 2), np.float32)
        dist = np.empty(n, np.float64)
        for start in range(0, n, RAYS_PER_CALL):
            sl = slice(start, min(n, start + RAYS_PER_CALL))
            o = ((origins[sl] - self.center) / self.scale).astype(np.float32)
            d = np.ascontiguousarray(directions[sl], np.float32)
            res = self._scene.run(o, d, output=1)
            triangle[sl] = res["primID"]
            bary[sl, 0], bary[sl, 1] = res["u"], res["v"]
            dist[sl] = np.where(res["primID"] >= 0, res["tfar"].astype(np.float64) * self.scale, np.inf)
        return triangle, bary, dist


def mesh_key(mesh: Mesh) -> str:
    """Hex digest of the geometry that decides ray hits (vertices and faces)."""
    h = hashlib.sha256()
    for array in (mesh.vertices.astype(np.float64), mesh.faces.astype(np.int64)):
        h.update(str(array.shape).encode())
        h.update(np.ascontiguousarray(array).tobytes())
    return h.hexdigest()


def view_key(geometry_key: str, camera: Camera) -> str:
    """Cache key of one view's ray cast: mesh geometry, K, c2w, resolution and cache version."""
    h = hashlib.sha256(f"v{CACHE_VERSION}:{geometry_key}:{camera.width}x{camera.height}".encode())
    h.update(np.asarray(camera.K, np.float64).tobytes())
    h.update(np.asarray(camera.c2w, np.float64).tobytes())
    return h.hexdigest()[:32]


def cast_view(caster: RayCaster, camera: Camera):
    """Ray cast of all pixel centres: (triangle (H,W) int32, barycentric (H,W,2) f32, distance (H,W) f64)."""
    o, d = camera.pixel_rays()
    tri, bary, dist = caster.intersect(o, d)
    h, w = camera.height, camera.width
    return tri.reshape(h, w), bary.reshape(h, w, 2), dist.reshape(h, w)


@dataclasses.dataclass(frozen=True)
class _HitGeometry:
    """What `derive_fragments` and `derive_depth` compute first from a ray cast, per hit pixel."""

    hit: np.ndarray
    tri: np.ndarray
    d: np.ndarray
    corners: np.ndarray
    corner_uv: np.ndarray
    e1: np.ndarray
    e2: np.ndarray
    normal: np.ndarray
    n_dot_d: np.ndarray
    g11: np.ndarray
    g12: np.ndarray
    g22: np.ndarray
    det: np.ndarray
    t: np.ndarray               # hit point = origin + t d
    b: np.ndarray               # (N, 2) barycentric weights of corners 1 and 2


def _hit_geometry(mesh: Mesh, camera: Camera, triangle: np.ndarray, barycentric: np.ndarray,
                  distance: np.ndarray) -> _HitGeometry:
    """The hit points recomputed in float64 (`derive_fragments` says how), per hit pixel."""
    h, w = triangle.shape
    hit = triangle >= 0
    tri = triangle[hit]
    d = camera.pixel_directions().reshape(h, w, 3)[hit]
    origin = camera.c2w[:3, 3]
    corners = mesh.vertices[mesh.faces[tri]]                       # (N, 3, 3)
    corner_uv = mesh.uv[tri]                                       # (N, 3, 2)
    e1, e2 = corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]
    normal = np.cross(e1, e2)
    g11, g12, g22 = (np.einsum("nc,nc->n", a, b_) for a, b_ in ((e1, e1), (e1, e2), (e2, e2)))
    det = np.einsum("nc,nc->n", normal, normal)                    # g11 g22 - g12², without cancellation
    n_dot_d = np.einsum("nc,nc->n", normal, d)

    def barycentrics(t):
        """(N, 2) weights of corners 1 and 2 of the point origin + t d, projected onto the triangle."""
        rel = origin + t[:, None] * d - corners[:, 0]
        r1, r2 = np.einsum("nc,nc->n", e1, rel), np.einsum("nc,nc->n", e2, rel)
        return np.stack([(g22 * r1 - g12 * r2) / det, (g11 * r2 - g12 * r1) / det], axis=1)

    with np.errstate(divide="ignore", invalid="ignore"):
        t_embree = distance[hit] / np.linalg.norm(d, axis=1)       # hit = origin + t * d
        t_plane = np.einsum("nc,nc->n", normal, corners[:, 0] - origin) / n_dot_d
        b_plane, b_embree = barycentrics(t_plane), barycentrics(t_embree)
        inside = (np.isfinite(b_plane).all(axis=1) & (b_plane.min(axis=1) >= -NEAR_TRIANGLE)
                  & (b_plane.sum(axis=1) <= 1 + NEAR_TRIANGLE))
        t = np.where(inside, t_plane, t_embree)
        b = np.where(inside[:, None], b_plane, b_embree)
        b = np.where(np.isfinite(b), b, barycentric[hit])
    return _HitGeometry(hit, tri, d, corners, corner_uv, e1, e2, normal, n_dot_d, g11, g12, g22, det, t, b)


def _depth(g: _HitGeometry, camera: Camera, shape: tuple[int, int]) -> np.ndarray:
    depth = np.full(shape, np.inf, np.float32)
    depth[g.hit] = g.t * (g.d @ camera.c2w[:3, 2])
    return depth


def derive_depth(mesh: Mesh, camera: Camera, triangle: np.ndarray, barycentric: np.ndarray,
                 distance: np.ndarray) -> np.ndarray:
    """(H, W) float32 camera depth of a ray cast (inf on misses): `derive_fragments`' depth, bit for
    bit, without its UVs and derivatives."""
    return _depth(_hit_geometry(mesh, camera, triangle, barycentric, distance), camera, triangle.shape)


def derive_fragments(mesh: Mesh, camera: Camera, triangle: np.ndarray, barycentric: np.ndarray,
                     distance: np.ndarray) -> Fragments:
    """Fragments from a ray cast: UV, camera depth and exact analytic UV derivatives per pixel.

    Embree only decides which triangle a ray hits. The hit point is recomputed in float64 as the
    ray's intersection with that triangle's plane: Embree's float32 barycentrics lose about
    eps32 x the aspect ratio on sliver triangles (7e-4 in UV at aspect 1e4) and its distance
    about eps32 / sin(angle) at grazing angles. Where that point lies outside the triangle by more
    than NEAR_TRIANGLE (barycentric units: a float32 near miss of a ray almost parallel to it, or
    Embree chose a neighbouring sliver), Embree's hit point o + t d is projected onto it instead.
    """
    h, w = triangle.shape
    g = _hit_geometry(mesh, camera, triangle, barycentric, distance)
    hit, tri, d, corner_uv, t, b = g.hit, g.tri, g.d, g.corner_uv, g.t, g.b
    e1, e2, normal, n_dot_d, g11, g12, g22, det = g.e1, g.e2, g.normal, g.n_dot_d, g.g11, g.g12, g.g22, g.det
    weights = np.stack([1.0 - b[:, 0] - b[:, 1], b[:, 0], b[:, 1]], axis=1)
    uv = np.zeros((h, w, 2), np.float32)
    uv[hit] = np.clip(np.einsum("nk,nkc->nc", weights, corner_uv), 0.0, 1.0)
    bary = barycentric.astype(np.float32)
    bary[hit] = b

    depth = _depth(g, camera, (h, w))

    # d(hit point)/d(pixel) on the triangle's plane, then barycentric and UV derivatives.
    step = camera.c2w[:3, :3] @ np.linalg.inv(camera.K)            # columns: d(d)/dx, d(d)/dy
    uv_grad = np.zeros((h, w, 2, 2), np.float32)
    grads = []
    with np.errstate(divide="ignore", invalid="ignore"):
        for axis in range(2):
            dd = step[:, axis][None, :]
            dp = t[:, None] * (dd - d * (normal @ step[:, axis])[:, None] / n_dot_d[:, None])
            r1, r2 = np.einsum("nc,nc->n", e1, dp), np.einsum("nc,nc->n", e2, dp)
            db1 = (g22 * r1 - g12 * r2) / det
            db2 = (g11 * r2 - g12 * r1) / det
            duv = db1[:, None] * (corner_uv[:, 1] - corner_uv[:, 0]) + db2[:, None] * (corner_uv[:, 2] - corner_uv[:, 0])
            grads.append(np.where(np.isfinite(duv), duv, 0.0))
    uv_grad[hit] = np.stack(grads, axis=1)

    object_id = np.full((h, w), -1, np.int32)
    object_id[hit] = mesh.face_object[tri]
    return Fragments(triangle=triangle.astype(np.int32), barycentric=bary, depth=depth, uv=uv, uv_grad=uv_grad,
                     object_id=object_id)


def _cache_paths(mesh: Mesh, cameras: Sequence[Camera], cache_dir: Path | None | bool) -> list[Path | None]:
    """Each camera's ray-cast file in the cache (None without one), the disk space of those not
    cached yet checked first (`check_cache_space`)."""
    cache = None if cache_dir is False else Path(cache_dir or default_cache_dir()) / "fragments"
    geometry_key = mesh_key(mesh)
    paths = [cache / f"{view_key(geometry_key, c)}.npz" if cache else None for c in cameras]
    if cache is not None:
        check_cache_space(cache, [c for c, p in zip(cameras, paths) if not p.is_file()])
    return paths


class _Casts:
    """A view's ray cast (triangle, barycentric, distance): read from its cache file `path` when
    there, else cast (the caster built on first need) and written there (None: no cache)."""

    def __init__(self, mesh: Mesh):
        self.mesh, self.caster = mesh, None

    def __call__(self, camera: Camera, path: Path | None):
        if path is not None and path.is_file():
            with np.load(path) as data:
                return data["triangle"], data["barycentric"], data["distance"]
        if self.caster is None:
            self.caster = RayCaster(self.mesh)
        hits = cast_view(self.caster, camera)
        if path is not None:
            path.parent.mkdir(parents=True, exist_ok=True)
            tmp = path.with_name(path.name + f".{os.getpid()}.tmp.npz")
            np.savez(tmp, triangle=hits[0], barycentric=hits[1], distance=hits[2])
            os.replace(tmp, path)
        return hits


def compute_depths(mesh: Mesh, cameras: Sequence[Camera], *, cache_dir: Path | None | bool = None
                   ) -> list[tuple[np.ndarray, np.ndarray]]:
    """Per camera, (triangle (H, W) int32, -1 on misses; depth (H, W) float32, inf on misses): the
    fields of `compute_fragments`' fragments, bit for bit, from the same cached ray casts, without
    their UVs and derivatives (about half the time of the fragments where the casts are cached)."""
    paths = _cache_paths(mesh, cameras, cache_dir)
    casting = _Casts(mesh)
    casts = ((c, casting(c, p)) for c, p in zip(cameras, paths))
    return list(ordered_map(lambda c: (c[1][0].astype(np.int32), derive_depth(mesh, c[0], *c[1])), casts))


CACHE_BYTES_PER_PIXEL = 4 + 2 * 4 + 8    # a cached ray cast: triangle int32, barycentric 2 x float32, distance float64
CACHE_BYTES_PER_VIEW = 1024              # the .npz's headers
CACHE_HEADROOM = 1 << 28                 # 256 MiB left free on the cache's disk after the ray casts are written


def uncached_cameras(mesh: Mesh, cameras: Sequence[Camera], cache_dir: Path | None | bool = None) -> list[Camera]:
    """The cameras of `cameras` whose ray casts are not in the cache yet, each distinct view once
    (none without a cache)."""
    if cache_dir is False:
        return []
    cache = Path(cache_dir or default_cache_dir()) / "fragments"
    geometry_key = mesh_key(mesh)
    missing = {}
    for c in cameras:
        path = cache / f"{view_key(geometry_key, c)}.npz"
        if path not in missing and not path.is_file():
            missing[path] = c
    return list(missing.values())


def uncached_bytes(mesh: Mesh, cameras: Sequence[Camera], cache_dir: Path | None | bool = None) -> int:
    """Bytes the ray casts of `cameras` not in the cache yet will take there (each distinct view
    once; 0 without a cache)."""
    return cast_bytes(uncached_cameras(mesh, cameras, cache_dir))


def cast_bytes(cameras: Sequence[Camera]) -> int:
    """Bytes the ray casts of `cameras` take in the cache (each one counted)."""
    return sum(c.height * c.width * CACHE_BYTES_PER_PIXEL + CACHE_BYTES_PER_VIEW for c in cameras)


def check_cache_space(cache: Path, cameras: Sequence[Camera]) -> None:
    """InputError naming `cache`, before any ray casting, when the ray casts of `cameras` (the views
    not cached yet) would not fit on its disk with CACHE_HEADROOM to spare: how much they need, how
    much is free, and where else to put them."""
    if not cameras:
        return
    needed = cast_bytes(cameras)
    existing = next((p for p in (cache, *cache.parents) if p.exists()), None)
    if existing is None:
        return
    free = shutil.disk_usage(existing).free
    if needed + CACHE_HEADROOM > free:
        gb = 2 ** 30
        raise InputError.single(str(cache), "disk space", (
            f"the ray casts of {len(cameras)} views need {needed / gb:.2f} GB here (plus {CACHE_HEADROOM / gb:.2f} GB "
            f"kept free), and its disk has {free / gb:.2f} GB free; free space there, or point $JAXDISTILL_CACHE at a "
            "folder on a larger disk"))


def compute_fragments(mesh: Mesh, cameras: Sequence[Camera], *, cache_dir: Path | None | bool = None,
                      progress: bool = True, empty: Callable | None = None, uv_grad: bool = True,
                      footprints: Callable | None = None) -> Sequence[Fragments]:
    """Fragments for every camera; ray casts are read from / written to the cache (`check_cache_space`
    first: InputError when the views not cached yet would not fit on its disk).

    cache_dir: a folder, None for `default_cache_dir()`, or False to disable caching.
    empty: None returns a list; else `empty(name, shape, dtype)` allocates a (V, H, W, ...) array
    per field of `ROW_FIELDS` (and uv_grad with `uv_grad`; all cameras of one resolution), filled a
    view at a time, and a `FragmentRows` over them is returned (with file-backed arrays, a few views
    are in memory at once: the one being cast and at most three being derived), with
    `footprints(fragments)` of each view (`layout.page_footprints`) when given.
    """
    paths = _cache_paths(mesh, cameras, cache_dir)
    out = []
    if empty is not None:
        sizes = {(c.height, c.width) for c in cameras}
        if len(sizes) != 1:
            raise ValueError(f"fragments in per-view arrays need one resolution, got {sorted(sizes)}")
        shape = sizes.pop()
        fields = UV_GRAD_FIELDS if uv_grad else ROW_FIELDS
        out = FragmentRows({name: empty(f"fragments_{name}", (len(cameras),) + shape + extra, dtype)
                            for name, (extra, dtype) in FRAGMENT_FIELDS.items() if name in fields}, shape,
                           mesh.face_object)
        summaries = []
    casting = _Casts(mesh)

    def cast(camera, path):
        return camera, casting(camera, path)

    # the casts (and cache reads) in this thread, a view at a time; the fragments derived from them
    # in two threads (NumPy), taken in view order
    bar = tqdm(cameras, desc="fragments", unit="view", disable=not progress, dynamic_ncols=True)
    casts = (cast(camera, path) for camera, path in zip(bar, paths))
    for v, frag in enumerate(ordered_map(lambda c: derive_fragments(mesh, c[0], *c[1]), casts)):
        if empty is None:
            out.append(frag)
        else:
            for name, array in out.arrays.items():
                array[v] = getattr(frag, name)
            if footprints is not None:
                summaries.append(footprints(frag))
    if empty is not None and footprints is not None:
        out.footprints = np.stack(summaries) if summaries else None
    return out
