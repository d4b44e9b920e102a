"""The model's per-view estimates (`jaxdistill/models/estimates.py`) at several sampling batch sizes, side by side.

    python scripts/bench_estimates.py [--scene=bedroom] [--rgbx_dir=DIR] [--batches=16,48] [--steps=50]
        [--maps=albedo,normal,roughness,metallic,irradiance] [--repeats=2] [--json=FILE]

What the main job's "per-view estimates" phase does, in one process: every view's photo encoded,
then every (map, view) pair sampled (`--steps` DDIM steps) and decoded in calls of at most
each size of `--batches` (shared evenly over the calls, the last one padded), and written as PNGs into a fresh folder. Each batch size
of `--batches` runs once to compile, then the sizes alternate `--repeats` times. Default: the
shipped model on the embedded bedroom at `configs/bedroom.cfg`'s render size (128x96; 48 views x
5 maps = 240 pairs). Prints the median seconds per size, the seconds per pair, and each size's
ratio to the first.
"""

from __future__ import annotations

import argparse
import json
import statistics
import tempfile
import time
from pathlib import Path


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--scene", default="bedroom", help="scene folder ('bedroom' = embedded)")
    parser.add_argument("--rgbx_dir", default=None, help="model folder (default: the shipped model)")
    parser.add_argument("--batches", default="16,48", help="comma-separated (map, view) pairs per call")
    parser.add_argument("--steps", type=int, default=50, help="DDIM steps (the main job's --estimate_steps)")
    parser.add_argument("--maps", default="albedo,normal,roughness,metallic,irradiance")
    parser.add_argument("--render_size", type=int, default=128, help="longer side of the images sampled")
    parser.add_argument("--repeats", type=int, default=2)
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args(argv)
    batches = [int(b) for b in args.batches.split(",")]
    if not batches or min(batches) < 1 or args.repeats < 1 or args.steps < 1:
        parser.error("--batches, --repeats and --steps must be positive")

    import jax

    from jaxdistill.datasets import ImportOptions, open_scene
    from jaxdistill.engine.problem import render_shape
    from jaxdistill.models import convert, estimates
    from jaxdistill.models import prior as rgbx
    from jaxdistill.models.shipped import shipped_folder

    scene = open_scene(args.scene, ImportOptions())
    height, width = render_shape(scene, args.render_size, 8)
    model = rgbx.load_prior(convert.load_rgbx(args.rgbx_dir or shipped_folder()))
    photos = [(v.name, v.photo, v.exposure) for v in scene.views]
    maps = args.maps.split(",")
    pairs = len(photos) * len(maps)

    def run(batch: int) -> float:
        with tempfile.TemporaryDirectory() as folder:
            start = time.perf_counter()
            estimates.estimate_views(model, photos, maps, height, width, Path(folder), steps=args.steps,
                                     progress=False, max_batch=batch)
            return time.perf_counter() - start

    first = {b: run(b) for b in batches}                                  # compiles each size's programs
    seconds = {b: [] for b in batches}
    for _ in range(args.repeats):
        for b in batches:
            seconds[b].append(run(b))
    medians = {b: statistics.median(s) for b, s in seconds.items()}
    print(f"{scene.name}: {len(photos)} views x {len(maps)} maps = {pairs} pairs at {width}x{height}, "
          f"{args.steps} DDIM steps, {jax.device_count()} {jax.default_backend()} device(s)")
    for b in batches:
        size = estimates.batch_size(0, pairs, b)
        calls = -(-pairs // size)
        print(f"  {b:4d} pairs a call at most ({calls} calls of {size}, {calls * size - pairs} padded): first {first[b]:7.2f} s, "
              f"median {medians[b]:7.2f} s, {medians[b] / pairs * 1e3:6.1f} ms a pair, "
              f"ratio to {batches[0]}: {medians[b] / medians[batches[0]]:.3f}")
    if args.json:
        args.json.write_text(json.dumps({
            "scene": scene.name, "pairs": pairs, "size": [height, width], "steps": args.steps,
            "backend": jax.default_backend(), "first_s": first, "seconds": seconds, "median_s": medians,
            "ratio_to_first": {b: medians[b] / medians[batches[0]] for b in batches}}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
