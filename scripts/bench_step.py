"""Seconds per distillation step with the rgbx prior, at the real RGB↔X size (random weights).

    python scripts/make_random_rgbx.py --size=full --out=/tmp/fullrgbx/rgb-to-x     # once, ~1 min, 4.8 GB
    python scripts/bench_step.py --rgbx_dir=/tmp/fullrgbx/rgb-to-x [--render_size=256] [--maps=albedo]
        [--views_per_step=1] [--prior_dtype=float32] [--steps=3] [--json]

Runs the real step (`distill.make_step` + `jit_step`, the same code `python -m jaxdistill.main`
runs) on the embedded bedroom with the rgbx prior: gather-render, VAE encode, one guided UNet pass
(w_t = w_i = 1), VAE decode, image-space loss, texel gradient, AdamW. Reports setup (weight
conversion, photo latents), compile, and the median of `--steps` timed steps after the compiled
warm-up step. `--size=tiny` uses a tiny random folder made on the fly (a quick check of this
script). The weights are random: the figures are timings, the images are meaningless.
"""

from __future__ import annotations

import argparse
import json
import platform
import resource
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--rgbx_dir", help="RGB<->X folder (diffusers format); required unless --size=tiny")
    p.add_argument("--size", choices=("given", "tiny"), default="given", help="tiny: make a tiny random folder")
    p.add_argument("--render_size", type=int, default=256, help="longer side of the renders (multiple of 8)")
    p.add_argument("--maps", default="albedo", help="comma-separated maps distilled per step")
    p.add_argument("--views_per_step", type=int, default=1)
    p.add_argument("--prior_dtype", choices=("float32", "bfloat16"), default="float32")
    p.add_argument("--max_texture_size", type=int, default=1024)
    p.add_argument("--steps", type=int, default=3, help="timed steps after the warm-up step")
    p.add_argument("--json", action="store_true")
    args = p.parse_args(argv)
    if args.size == "given" and not args.rgbx_dir:
        p.error("--rgbx_dir is required (or --size=tiny)")
    if args.render_size % 8:
        p.error("--render_size must be a multiple of 8")
    return args


def main(argv=None) -> int:
    args = parse_args(argv)
    import jax

    from jaxdistill import config as config_lib
    from jaxdistill.distill import StepSettings, data_mesh, init_state, jit_step, make_optimizer, make_step
    from jaxdistill.problem import build_problem

    folder = args.rgbx_dir
    if args.size == "tiny":
        import tiny_rgbx

        folder = str(tiny_rgbx.write_tiny_rgbx(Path(tempfile.mkdtemp()) / "rgb-to-x"))
    config = config_lib.validate(config_lib.DistillConfig(
        scene="bedroom", out_dir="unused", maps=tuple(args.maps.split(",")), prior="rgbx", rgbx_dir=folder,
        prior_dtype=args.prior_dtype, render_size=args.render_size, views_per_step=args.views_per_step,
        max_texture_size=args.max_texture_size, steps=1000))
    t0 = time.perf_counter()
    problem = build_problem(config)
    setup_s = time.perf_counter() - t0
    optimizer = make_optimizer(config.lr, config.weight_decay)
    settings = StepSettings(channels=problem.channels, height=problem.height, width=problem.width,
                            total_steps=config.steps, num_train_timesteps=problem.prior.scheduler.num_train_timesteps)
    mesh = data_mesh()
    replicated = jax.sharding.NamedSharding(mesh, jax.sharding.PartitionSpec())
    by_view = jax.sharding.NamedSharding(mesh, jax.sharding.PartitionSpec("data"))
    state = init_state(problem.initial_texels(), optimizer, config.seed)
    first = problem.batch(problem.view_ids(0, config.views_per_step, config.seed))
    step, traces = jit_step(make_step(problem.prior, settings, optimizer), mesh, first, state, problem.frozen)
    state = jax.device_put(state, replicated)
    frozen = jax.device_put(problem.frozen, replicated)
    times = []
    for i in range(args.steps + 1):
        batch = jax.device_put(problem.batch(problem.view_ids(i, config.views_per_step, config.seed)), by_view)
        t0 = time.perf_counter()
        state, metrics = step(state, batch, frozen)
        jax.block_until_ready(metrics["loss"])
        times.append(time.perf_counter() - t0)
        print(f"step {i}: {times[-1]:.2f} s, loss {float(metrics['loss']):.4g}, finite {int(metrics['finite'])}",
              file=sys.stderr)
    traces.check(1)
    median = float(np.median(times[1:])) if len(times) > 1 else float("nan")
    result = {
        "folder": folder, "render": [problem.height, problem.width], "maps": list(problem.channels.maps),
        "views_per_step": config.views_per_step, "prior_dtype": config.prior_dtype,
        "unet_passes_per_step": config.views_per_step * len(problem.channels.maps),
        "texels": problem.space.num_texels, "setup_s": setup_s, "setup_timings": problem.timings,
        "first_step_s_with_compile": times[0], "median_step_s": median, "steps_timed": len(times) - 1,
        "peak_rss_gb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2 ** 20,
        "backend": jax.default_backend(), "device": jax.devices()[0].device_kind, "cpus": platform.processor() or None,
    }
    if args.json:
        print(json.dumps(result, indent=1))
    else:
        for key in ("render", "maps", "views_per_step", "prior_dtype", "unet_passes_per_step", "texels", "setup_s",
                    "first_step_s_with_compile", "median_step_s", "peak_rss_gb", "backend"):
            value = result[key]
            print(f"{key:28s} {value:.2f}" if isinstance(value, float) else f"{key:28s} {value}")
    print(f"median seconds per step: {median:.2f} ({result['unet_passes_per_step']} UNet passes per step, "
          f"{problem.height}x{problem.width} renders, {config.prior_dtype}, {jax.default_backend()})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
