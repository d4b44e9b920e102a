"""What the re-rendering term costs per step, against the same step without it, at real size.

    python scripts/bench_photo.py [--config=configs/bedroom.cfg] [--photo_sizes=0,240,160]
        [--samplers=trilinear,bilinear] [--repeats=5] [--json]

For each setting one child process builds the main job's problem (`engine.problem.build_problem`)
and jitted step (`engine.loop.step_settings`, `engine.step.make_step`, `jit_step`) exactly as
`python -m jaxdistill.main --flagfile=CONFIG` does, runs a warm-up step (compilation) and then
`--repeats` steps on the batches the run would draw, and reports the median seconds per step
(blocking on each step's texels). Rows: the config as it is (--photo_weight=0), then the term on
at each photo size (0 = the photos' own size) and sampler; the ratio to the first row is printed
beside each. The machine is shared: compare ratios of one run, not absolute times across runs.
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import time


def child(args) -> dict:
    """One row, in this process: build, compile, time."""
    import jax
    from absl import flags

    from jaxdistill.engine import config as config_lib
    from jaxdistill.engine.loop import batch_views, step_settings
    from jaxdistill.engine.problem import build_problem
    from jaxdistill.engine.step import data_mesh, init_state, jit_step, make_optimizer, make_step

    fv = flags.FlagValues()
    config_lib.define_flags(fv)
    # without the term its smoothness flags go too (the config's are part of the term)
    off = ["--irradiance_smoothness=0", "--albedo_smoothness=0"] if args.photo_weight == 0 else []
    fv(["bench", f"--flagfile={args.config}", "--out_dir=out/bench_photo", f"--photo_weight={args.photo_weight}",
        f"--photo_size={args.photo_size}", f"--sampler={args.sampler}", *off])
    config = config_lib.config_from_flags(fv)
    t0 = time.perf_counter()
    problem = build_problem(config)
    setup_s = time.perf_counter() - t0
    optimizer = make_optimizer(config.lr, config.weight_decay, config.lr_schedule, config.steps)
    first = problem.batch(batch_views(problem, config, 0))
    state = init_state(problem.initial_texels(), optimizer, config.seed)
    step, _ = jit_step(make_step(problem.prior, step_settings(config, problem), optimizer), data_mesh(), first,
                       state, problem.frozen)
    frozen = jax.device_put(problem.frozen)
    t0 = time.perf_counter()
    state, _ = step(state, first, frozen)
    jax.block_until_ready(state.texels)
    compile_s = time.perf_counter() - t0
    times = []
    for i in range(1, args.repeats + 1):
        batch = problem.batch(batch_views(problem, config, i))
        t0 = time.perf_counter()
        state, _ = step(state, batch, frozen)
        jax.block_until_ready(state.texels)
        times.append(time.perf_counter() - t0)
    return {"photo_weight": args.photo_weight, "photo_size": args.photo_size, "sampler": args.sampler,
            "photo_shape": list(problem.photo_shape), "texels": problem.space.num_texels,
            "setup_s": setup_s, "compile_s": compile_s, "step_s_median": statistics.median(times), "step_s": times}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--config", default="configs/bedroom.cfg")
    parser.add_argument("--photo_sizes", default="0,240,160")
    parser.add_argument("--samplers", default="trilinear")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--json", action="store_true")
    parser.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--photo_weight", type=float, default=0.0, help=argparse.SUPPRESS)
    parser.add_argument("--photo_size", type=int, default=0, help=argparse.SUPPRESS)
    parser.add_argument("--sampler", default="trilinear", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.child:
        print("ROW " + json.dumps(child(args)), flush=True)
        return 0
    settings = [(0.0, 0, "trilinear")] + [(1.0, int(size), sampler) for sampler in args.samplers.split(",")
                                           for size in args.photo_sizes.split(",")]
    rows = []
    for weight, size, sampler in settings:
        cmd = [sys.executable, __file__, "--child", f"--config={args.config}", f"--repeats={args.repeats}",
               f"--photo_weight={weight}", f"--photo_size={size}", f"--sampler={sampler}"]
        out = subprocess.run(cmd, capture_output=True, text=True, check=True).stdout
        rows.append(json.loads(next(line for line in out.splitlines() if line.startswith("ROW "))[4:]))
        base = rows[0]["step_s_median"]
        r = rows[-1]
        print(f"photo_weight={r['photo_weight']:g} photo {r['photo_shape'][1]}x{r['photo_shape'][0]} {r['sampler']:9s} "
              f"texels {r['texels']:>9,}  step {r['step_s_median']:.2f} s (x{r['step_s_median'] / base:.2f})  "
              f"compile {r['compile_s']:.0f} s", flush=True)
    if args.json:
        print(json.dumps({"rows": rows}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
