"""The model's per-view estimates (`jaxdistill/models/estimates.py`) at several sampling batch sizes
(and DDIM step counts), side by side.

    python scripts/bench_estimates.py [--scene=bedroom] [--rgbx_dir=DIR] [--batches=16,48] [--steps=50[,10]]
        [--maps=albedo,normal,roughness,metallic,irradiance] [--repeats=2] [--json=FILE]

What the main job's "per-view estimates" phase does, in one process: every view's photo encoded,
then every (map, view) pair sampled (`--steps` DDIM steps) and decoded in calls of at most
each size of `--batches` (shared evenly over the calls, the last one padded), and written as PNGs into a fresh folder. Each case
(a batch size of `--batches` at a step count of `--steps`) runs once to compile, then the cases
alternate `--repeats` times. Default: the shipped model on the embedded bedroom at
`configs/bedroom.cfg`'s render size (128x96; 48 views x 5 maps = 240 pairs). Prints the median
seconds per case, the seconds per pair, and each case's ratio to the first. The JSON's cases are
keyed by batch size, or, with several step counts, "BATCHxSTEPS".
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
    parser.add_argument("--steps", default="50", help="comma-separated DDIM steps (the main job's --estimate_steps)")
    parser.add_argument("--maps", default="albedo,normal,roughness,metallic,irradiance")
    parser.add_argument("--render_size", type=int, default=128, help="longer side of the images sampled")
    parser.add_argument("--repeats", type=int, default=2)
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args(argv)
    try:
        batches = [int(b) for b in args.batches.split(",")]
        step_counts = [int(s) for s in args.steps.split(",")]
    except ValueError:
        parser.error("--batches and --steps are comma-separated integers")
    if not batches or min(batches) < 1 or args.repeats < 1 or min(step_counts) < 1:
        parser.error("--batches, --repeats and --steps must be positive")
    if len(set(batches)) < len(batches) or len(set(step_counts)) < len(step_counts):
        parser.error("--batches and --steps must not repeat a value")
    cases = [(b, s) for s in step_counts for b in batches]
    label = {c: str(c[0]) if len(step_counts) == 1 else f"{c[0]}x{c[1]}" for c in cases}

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

    def run(case: tuple[int, int]) -> float:
        batch, steps = case
        with tempfile.TemporaryDirectory() as folder:
            start = time.perf_counter()
            estimates.estimate_views(model, photos, maps, height, width, Path(folder), steps=steps,
                                     progress=False, max_batch=batch)
            return time.perf_counter() - start

    first = {c: run(c) for c in cases}                                    # compiles each case's programs
    seconds = {c: [] for c in cases}
    for _ in range(args.repeats):
        for c in cases:
            seconds[c].append(run(c))
    medians = {c: statistics.median(s) for c, s in seconds.items()}
    print(f"{scene.name}: {len(photos)} views x {len(maps)} maps = {pairs} pairs at {width}x{height}, "
          f"DDIM steps {args.steps}, {jax.device_count()} {jax.default_backend()} device(s)")
    for c in cases:
        b, steps = c
        size = estimates.batch_size(0, pairs, b)
        calls = -(-pairs // size)
        print(f"  {b:4d} pairs a call at most ({calls} calls of {size}, {calls * size - pairs} padded), {steps} steps: "
              f"first {first[c]:7.2f} s, median {medians[c]:7.2f} s, {medians[c] / pairs * 1e3:6.1f} ms a pair, "
              f"ratio to the first: {medians[c] / medians[cases[0]]:.3f}")
    if args.json:
        args.json.write_text(json.dumps({
            "scene": scene.name, "pairs": pairs, "size": [height, width], "steps": step_counts,
            "backend": jax.default_backend(), "first_s": {label[c]: v for c, v in first.items()},
            "seconds": {label[c]: v for c, v in seconds.items()}, "median_s": {label[c]: v for c, v in medians.items()},
            "ratio_to_first": {label[c]: medians[c] / medians[cases[0]] for c in cases}}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
