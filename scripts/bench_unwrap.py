"""Unwrap time of scan-like meshes without UVs: xatlas through `unwrap.ensure_uvs`, cold and cached.

    python scripts/bench_unwrap.py [--faces=50000,200000,1000000] [--views=8] [--json]

Each mesh is a closed box room (4 x 2.5 x 3 m) whose walls are finely triangulated grids with
millimetre noise, like a laser scan, split into 6 objects (walls) or kept as one object
(--one_object, the ScanNet++ case). Cameras stand inside looking at the walls. Prints, per
size: faces, objects, cold unwrap seconds, faces per second, cached seconds, chosen page
sizes, UV overlap fraction of the result, and the ratio cold / cached.
"""

from __future__ import annotations

import argparse
import json
import math
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from jaxdistill.scene import cameras
from jaxdistill.scene.model import Mesh  # noqa: E402


def scan_room(faces: int, one_object: bool, seed: int = 0) -> Mesh:
    """A noisy, finely triangulated box room of about `faces` triangles, NaN UVs (no texture coordinates)."""
    rng = np.random.default_rng(seed)
    size = np.array([4.0, 2.5, 3.0])
    walls = [(0, 1, 2, 0.0), (0, 1, 2, size[2]), (0, 2, 1, 0.0), (0, 2, 1, size[1]), (1, 2, 0, 0.0), (1, 2, 0, size[0])]
    areas = [size[a] * size[b] for a, b, _, _ in walls]
    vertices, tris, face_object = [], [], []
    offset = 0
    for w, ((a, b, c, level), area) in enumerate(zip(walls, areas)):
        n = max(2, int(round(math.sqrt(faces * area / sum(areas) / 2))))
        s, t = np.meshgrid(np.linspace(0, size[a], n + 1), np.linspace(0, size[b], n + 1))
        v = np.zeros((s.size, 3))
        v[:, a], v[:, b] = s.ravel(), t.ravel()
        v[:, c] = level + 0.002 * rng.standard_normal(s.size)
        i = (np.arange(n)[None, :] + (n + 1) * np.arange(n)[:, None]).ravel()
        f = np.concatenate([np.stack([i, i + 1, i + n + 2], 1), np.stack([i, i + n + 2, i + n + 1], 1)])
        vertices.append(v)
        tris.append(f + offset)
        face_object.append(np.full(len(f), 0 if one_object else w, np.int32))
        offset += len(v)
    f = np.concatenate(tris)
    names = ("scan",) if one_object else tuple(f"wall{w}" for w in range(6))
    return Mesh(vertices=np.concatenate(vertices), faces=f, uv=np.full((len(f), 3, 2), np.nan),
                face_object=np.concatenate(face_object), object_names=names)


def room_cameras(views: int, width: int = 320, height: int = 240) -> list:
    K = cameras.intrinsics_from_fov(70.0, width, height)
    centre = np.array([2.0, 1.25, 1.5])
    out = []
    for i in range(views):
        angle = 2 * math.pi * i / views
        target = centre + np.array([math.cos(angle), -0.1, math.sin(angle)])
        out.append(cameras.look_at(centre, target, [0.0, 1.0, 0.0], K, width, height))
    return out


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--faces", default="50000,200000,1000000")
    parser.add_argument("--views", type=int, default=8)
    parser.add_argument("--one_object", action="store_true", help="one object (a scan) instead of six walls")
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args(argv)
    from jaxdistill.render import unwrap, uv_checks

    rows = []
    cams = room_cameras(args.views)
    for target in [int(x) for x in args.faces.split(",")]:
        mesh = scan_room(target, args.one_object)
        cache = Path(tempfile.mkdtemp(prefix="bench_unwrap_"))
        try:
            t0 = time.perf_counter()
            out, decisions = unwrap.ensure_uvs(mesh, cams, cache_dir=cache, progress=False)
            cold = time.perf_counter() - t0
            t0 = time.perf_counter()
            again, cached = unwrap.ensure_uvs(mesh, cams, cache_dir=cache, progress=False)
            warm = time.perf_counter() - t0
        finally:
            shutil.rmtree(cache, ignore_errors=True)
        assert np.array_equal(out.uv, again.uv) and all(d.cached for d in cached)
        overlap = max(uv_checks.uv_overlap_fraction(out.uv[out.face_object == o], 1024) for o in range(len(out.object_names)))
        row = {"faces": mesh.num_faces, "objects": len(mesh.object_names), "cold_s": round(cold, 2),
               "faces_per_s": round(mesh.num_faces / cold), "cached_s": round(warm, 3),
               "cold_over_cached": round(cold / max(warm, 1e-9), 1),
               "page_sizes": sorted({d.page_size for d in decisions}), "max_overlap": round(overlap, 4)}
        rows.append(row)
        print(f"{row['faces']:>9} faces  {row['objects']} objects  cold {cold:7.1f} s  ({row['faces_per_s']:>6} faces/s)  "
              f"cached {warm:6.3f} s  ({row['cold_over_cached']}x)  pages {row['page_sizes']}  overlap {overlap:.4f}",
              flush=True)
    if args.json:
        print(json.dumps({"rows": rows, "views": args.views, "one_object": args.one_object}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
