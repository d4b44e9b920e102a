"""Benchmark of the geometry half: fragments, render + gradient, compact-texel memory.

    python scripts/bench_render.py [--faces_per_side=320] [--views=8] [--repeats=7] [--json]

Prints, side by side in one run:
  1. fragment precompute on a >= 1M-triangle room at 512x512: BVH build, Embree ray cast and
     derivation (UV, depth, UV derivatives) in rays/s, and a cached reload;
  2. render + gradient per 512^2 view of a 4096^2 atlas texture, bilinear and trilinear, for
     several tile sizes (medians over repeats, after compilation);
  3. parameter memory of compact texels vs full pages (albedo, fp32, plus AdamW's two moments).
Figures from a shared 2-core machine are noisy: medians and ratios are what to compare.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time

import jax
import jax.numpy as jnp
import numpy as np

from jaxdistill.scene import shapes as synthetic
from jaxdistill.render import fragments as fr
from jaxdistill.render.gather_plan import build_gather_plans, build_texel_space
from jaxdistill.render.layout import make_layout
from jaxdistill.render.sampler import render


def median_time(fn, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        jax.block_until_ready(fn())
        times.append(time.perf_counter() - start)
    return float(np.median(times))


def bench_fragments(mesh, cams):
    out = {}
    start = time.perf_counter()
    caster = fr.RayCaster(mesh)
    caster.intersect(np.zeros((1, 3)) + mesh.vertices.mean(0), np.array([[0.0, 0.0, 1.0]]))  # forces the BVH build
    out["bvh_build_s"] = time.perf_counter() - start
    rays = cams[0].width * cams[0].height
    cast_times, derive_times, casts = [], [], []
    for cam in cams:
        start = time.perf_counter()
        cast = fr.cast_view(caster, cam)
        cast_times.append(time.perf_counter() - start)
        casts.append(cast)
        start = time.perf_counter()
        fr.derive_fragments(mesh, cam, *cast)
        derive_times.append(time.perf_counter() - start)
    out["cast_mrays_per_s"] = rays / np.median(cast_times) / 1e6
    out["derive_mrays_per_s"] = rays / np.median(derive_times) / 1e6
    out["total_mrays_per_s"] = rays / (np.median(cast_times) + np.median(derive_times)) / 1e6
    out["casts"] = casts
    with tempfile.TemporaryDirectory() as cache:
        fr.compute_fragments(mesh, cams, cache_dir=cache, progress=False)
        start = time.perf_counter()
        frags = fr.compute_fragments(mesh, cams, cache_dir=cache, progress=False)
        out["cached_reload_mrays_per_s"] = rays * len(cams) / (time.perf_counter() - start) / 1e6
    return out, frags


def bench_render(mesh, frags, texture_size, sampler, tile_size, repeats):
    start = time.perf_counter()
    layout = make_layout(len(mesh.object_names), "atlas", texture_size, frags,
                         mipmaps=sampler == "trilinear", tile_size=tile_size)
    space = build_texel_space(frags, layout, sampler)
    plan = build_gather_plans(frags, space, sampler)
    build_s = time.perf_counter() - start
    view = plan.select(jnp.array([0]))
    texels = jnp.zeros((space.num_texels, 3), jnp.float32)
    target = jnp.ones((1, plan.height, plan.width, 3), jnp.float32)
    forward = jax.jit(lambda t: render(t, view))
    value_and_grad = jax.jit(jax.value_and_grad(lambda t: jnp.sum((render(t, view) - target) ** 2)))
    jax.block_until_ready(forward(texels))
    jax.block_until_ready(value_and_grad(texels))
    return {
        "sampler": sampler, "tile": layout.tile, "plan_build_s": build_s,
        "params": space.num_texels, "full_texels": layout.full_size(),
        "forward_ms": 1e3 * median_time(lambda: forward(texels), repeats),
        "forward_grad_ms": 1e3 * median_time(lambda: value_and_grad(texels), repeats),
    }


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--faces_per_side", type=int, default=300, help="room wall subdivisions (2*n^2 faces per wall)")
    parser.add_argument("--views", type=int, default=8)
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--texture_size", type=int, default=4096)
    parser.add_argument("--json", action="store_true", help="also print one JSON line with every figure")
    args = parser.parse_args(argv)

    print(f"jax {jax.__version__} on {jax.devices()[0].device_kind}, {os.cpu_count()} cores")
    mesh = synthetic.box_room((6.0, 3.0, 5.0), subdivisions=args.faces_per_side, furniture=True,
                              furniture_subdivisions=args.faces_per_side // 8, atlas=True)
    cams = synthetic.room_cameras(args.views)
    print(f"\n[1] fragments: {mesh.num_faces / 1e6:.2f}M triangles, {args.views} views of 512x512")
    frag_stats, frags = bench_fragments(mesh, cams)
    casts = frag_stats.pop("casts")
    print(f"  BVH build {frag_stats['bvh_build_s']:.2f} s (once per mesh)")
    print(f"  Embree cast {frag_stats['cast_mrays_per_s']:.2f} Mrays/s | derive {frag_stats['derive_mrays_per_s']:.2f} "
          f"Mrays/s | together {frag_stats['total_mrays_per_s']:.2f} Mrays/s | cached reload "
          f"{frag_stats['cached_reload_mrays_per_s']:.2f} Mrays/s ({frag_stats['cached_reload_mrays_per_s'] / frag_stats['total_mrays_per_s']:.1f}x)")

    print(f"\n[2] render + gradient, one 512^2 view, {args.texture_size}^2 atlas, compact texels ({args.views} views plan the set)")
    header = f"  {'sampler':10s} {'tile':>4s} {'params':>12s} {'plan build':>10s} {'forward':>10s} {'fwd+grad':>10s}"
    print(header)
    rows = []
    for sampler, tile in (("bilinear", 1), ("bilinear", 16), ("trilinear", 1), ("trilinear", 8), ("trilinear", 16)):
        row = bench_render(mesh, frags, args.texture_size, sampler, tile, args.repeats)
        rows.append(row)
        print(f"  {sampler:10s} {row['tile']:4d} {row['params'] / 1e6:10.2f} M {row['plan_build_s']:9.2f}s "
              f"{row['forward_ms']:8.1f}ms {row['forward_grad_ms']:8.1f}ms")
    base = rows[0]["forward_grad_ms"]
    print("  fwd+grad relative to bilinear/tile 1: " + ", ".join(f"{r['sampler']}/{r['tile']} {r['forward_grad_ms'] / base:.1f}x" for r in rows))

    print("\n[3] parameter memory, albedo (3 x fp32) + AdamW moments (2 x), room with furniture:")
    # Same geometry (so the same ray casts), but every object's UVs span its own page.
    mesh = synthetic.box_room((6.0, 3.0, 5.0), subdivisions=args.faces_per_side, furniture=True,
                              furniture_subdivisions=args.faces_per_side // 8, atlas=False)
    frags = [fr.derive_fragments(mesh, cam, *cast) for cam, cast in zip(cams, casts)]
    mem = []
    for texture_size in ("auto", 1024, 4096):
        for sampler, tile in (("bilinear", 1), ("trilinear", 8)):
            layout = make_layout(len(mesh.object_names), "pages", texture_size, frags,
                                 mipmaps=sampler == "trilinear", tile_size=tile)
            space = build_texel_space(frags, layout, sampler)
            compact_mb = space.num_texels * 3 * 4 * 3 / 2**20
            full_mb = layout.full_size() * 3 * 4 * 3 / 2**20
            mem.append({"texture_size": texture_size, "sampler": sampler, "tile": tile, "params": space.num_texels,
                        "full_texels": layout.full_size(), "compact_mb": compact_mb, "full_mb": full_mb})
            print(f"  one page per object, size {str(texture_size):>5s}, {sampler:9s} tile {tile:2d}: compact "
                  f"{compact_mb:9.1f} MB vs full pages {full_mb:9.1f} MB ({full_mb / max(compact_mb, 1e-9):.1f}x smaller)")
    if args.json:
        print(json.dumps({"fragments": frag_stats, "render": rows, "memory": mem}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
