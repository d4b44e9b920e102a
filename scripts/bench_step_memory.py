"""The step's memory in three forms, and their seconds per step, side by side on one problem.

    python scripts/bench_step_memory.py --flagfile=configs/bedroom.cfg [main-job flags, e.g.
        --max_texture_size=2048 or --scene=DIR] [--bench_steps=8] [--bench_repeats=3] [--bench_loop]
        [--bench_json=FILE]

Builds the main job's problem once (`build_problem` with the given flags), then the jitted step
(`loop.setup_step`) in three forms:

  optax_where_concat   optax's AdamW, applied and kept by `where(ok, new, old)` per leaf, and
                       the mip pyramid concatenated (the step before commit 7037c6b);
  gated_concat         `optimizer.GatedAdamW.gated_update` (AdamW in place behind the finite
                       gate), the pyramid concatenated (7037c6b);
  gated_split          the same with the pyramid split (`sampler.SplitPyramid`): the main job.

With --bench_loop it first runs the main job's set-up and loop as `pipeline.run` does (the
evaluation context built, the fragments let go, --steps steps with the evaluation every
--eval_every, no checkpoint), with the step as the main job builds it, and reports the peak RSS by
the loop's end (the operating system's accounting) and the loop's seconds: the figure
`metrics.json` records as `peak_host_memory_gb["loop"]`, without the outputs after it. The step is
compiled before the first step (timed apart), and the seconds a step are the median over the
windows between the loop's metric fetches (--log_every steps each), evaluations left out.

For each form: XLA's own buffer assignment of the compiled step (`memory_analysis`: arguments, i.e.
texels, AdamW's two moments and the batch, and temporaries), in GB and in arrays of the texels'
size (N x C float32). With --bench_steps > 0 the forms then alternate --bench_repeats times, each
running --bench_steps steps from the same initial state (the first repeat's first two steps not
timed: compilation); with --reuse_steps=2 even steps run the prior's pass and odd ones reuse its
x-hat-0, timed apart (medians). The last repeat's texels are compared with the first form's
(largest difference relative to their largest magnitude). Prints a table; --bench_json writes it.
"""

from __future__ import annotations

import dataclasses
import json
import resource
import statistics
import sys
import time

from absl import app, flags

import jaxdistill  # noqa: F401  (the package's XLA flags, as the main job)
from jaxdistill.engine import config as config_lib

FORMS = (("optax_where_concat", True, False), ("gated_concat", False, False), ("gated_split", False, True))

config_lib.define_flags(flags.FLAGS, main_module=True)
flags.DEFINE_integer("bench_steps", 8, "steps per form and repeat (0: memory analysis only)")
flags.DEFINE_integer("bench_repeats", 3, "times the forms alternate")
flags.DEFINE_boolean("bench_loop", False, "first run the main job's set-up and loop; report their peak RSS")
flags.DEFINE_string("bench_json", None, "write the table as JSON here")


def peak_rss_gb() -> float:
    """This process's peak resident memory so far, in units of 2^30 bytes (as metrics.json)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2 ** 20


def main(argv) -> int:
    del argv
    import jax
    import numpy as np
    import optax

    from jaxdistill.engine import distributed, loop
    from jaxdistill.engine.problem import build_problem
    from jaxdistill.engine.step import init_state
    from jaxdistill.evaluate import scoring

    fv = flags.FLAGS
    if fv.bench_steps < 0 or fv.bench_repeats < 1:
        raise app.UsageError("--bench_steps must be >= 0 and --bench_repeats >= 1")
    config = config_lib.config_from_flags(fv)
    start = time.perf_counter()
    problem = build_problem(config)
    loop_run = {"setup_s": time.perf_counter() - start, "setup_peak_gb": peak_rss_gb()}
    if fv.bench_loop:
        context = scoring.evaluation_context(config, problem)
        problem = problem.without_fragments()
        clock = loop.StepClock()
        evaluate = None
        if context.gt_maps is not None:
            def evaluate(state):
                psnr = scoring.quick_psnr(state, problem, context)
                clock.exclude_since_mark()                     # the evaluation is not a step's time
                return psnr

        start = time.perf_counter()
        result = loop.run_loop(config, problem, loop.recorded_config(config, problem.choice.kind), None,
                               evaluate=evaluate, progress=False, hooks=clock.hooks())
        # seconds a step between fetches (--log_every), the compilation and evaluations left out
        loop_run.update(loop_s=time.perf_counter() - start, loop_peak_gb=peak_rss_gb(), compile_s=clock.compile_s,
                        s_per_step=statistics.median(clock.seconds_per_step()), loss=result.history["loss"][-1],
                        albedo_psnr=result.history["albedo_psnr"])
        result = None
        print(f"set-up {loop_run['setup_s']:.1f} s (peak RSS {loop_run['setup_peak_gb']:.2f} GB), loop of "
              f"{config.steps} steps {loop_run['loop_s']:.1f} s (compilation {loop_run['compile_s']:.1f} s, "
              f"{loop_run['s_per_step']:.3f} s a step, median over --log_every windows): "
              f"peak RSS {loop_run['loop_peak_gb']:.2f} GB", flush=True)
    n, c = problem.space.num_texels, problem.channels.num_channels
    array = n * c * 4
    first = problem.batch(loop.batch_views(problem, config, 0))
    base = loop.step_settings(config, problem)
    forms = {}
    rows = {}
    for name, plain, split in FORMS:
        optimizer = loop.make_optimizer(config.lr, config.weight_decay, config.lr_schedule, config.steps)
        stepper = loop.setup_step(config, problem, first, optimizer=optax.chain(optimizer) if plain else optimizer,
                                  settings=dataclasses.replace(base, split_pyramid=split))
        frozen = jax.device_put(problem.frozen, stepper.replicated)
        batch = distributed.place_batch(problem.batch, loop.batch_views(problem, config, 0), stepper.by_view)
        compiled = stepper.step_fn.lower(jax.device_put(stepper.state, stepper.replicated), batch, frozen).compile()
        analysis = compiled.memory_analysis()
        rows[name] = {key: {"gb": getattr(analysis, f"{key}_size_in_bytes") / 2 ** 30,
                            "arrays": getattr(analysis, f"{key}_size_in_bytes") / array}
                      for key in ("argument", "temp")}

        def initial(optimizer=stepper.optimizer, placed=stepper.replicated, reused=jax.device_get(stepper.state.reused),
                    align=jax.device_get(stepper.state.align)):          # on the host: each run donates its copy
            """A fresh step-0 state (each run donates its own), not one held for every form."""
            return jax.device_put(init_state(problem.initial_texels(), optimizer, config.seed, reused, align), placed)

        forms[name] = (stepper.by_view, initial, compiled, frozen)
        stepper = None                                 # its state: three texel-sized arrays
    seconds = {name: {"prior": [], "reused": []} for name in forms}
    texels = {}
    for repeat in range(fv.bench_repeats if fv.bench_steps else 0):
        for name, (by_view, initial, compiled, frozen) in forms.items():
            state = initial()
            for step in range(fv.bench_steps):
                batch = distributed.place_batch(problem.batch, loop.batch_views(problem, config, step), by_view)
                jax.block_until_ready(batch)
                start = time.perf_counter()
                state, _ = compiled(state, batch, frozen)
                jax.block_until_ready(state)
                if repeat or step >= 2:
                    kind = "prior" if config.reuse_steps == 1 or step % config.reuse_steps == 0 else "reused"
                    seconds[name][kind].append(time.perf_counter() - start)
            texels[name] = np.asarray(state.texels)
    reference = texels.get(FORMS[0][0])
    print(f"{n} texels x {c} channels: one array {array / 2 ** 30:.3f} GB; {problem.num_views} views, "
          f"{config.views_per_step} a step, {jax.default_backend()}")
    print(f"{'form':20s} {'arguments':>18s} {'temporaries':>18s} {'prior step':>11s} {'reused':>9s} {'texels vs first':>16s}")
    for name in forms:
        row = rows[name]
        for kind, values in seconds[name].items():
            row[f"{kind}_s"] = statistics.median(values) if values else None
        if reference is not None:
            scale = np.abs(reference).max()
            row["texels_max_rel_diff"] = float(np.abs(texels[name] - reference).max() / scale)
            row["texels_p999_rel_diff"] = float(np.quantile(np.abs(texels[name] - reference), 0.999) / scale)
            row["texels_changed_share"] = float(np.mean(texels[name] != reference))
        fmt = lambda v: f"{v:9.3f}" if v is not None else f"{'-':>9s}"
        print(f"{name:20s} {row['argument']['gb']:7.2f} GB {row['argument']['arrays']:5.2f} arr "
              f"{row['temp']['gb']:7.2f} GB {row['temp']['arrays']:5.2f} arr  {fmt(row.get('prior_s'))}  "
              f"{fmt(row.get('reused_s'))}  {row.get('texels_max_rel_diff', float('nan')):14.2e}")
    if fv.bench_json:
        with open(fv.bench_json, "w") as f:
            json.dump({"texels": n, "channels": c, "array_gb": array / 2 ** 30, "views": problem.num_views,
                       "command": " ".join(sys.argv), "main_job": loop_run, "forms": rows}, f, indent=1)
    return 0


if __name__ == "__main__":
    app.run(main)
