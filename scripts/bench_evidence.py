"""The evidence's per-texel statistics (`render.visibility.texel_view_statistics`), this
checkout's against another revision's, side by side on one problem (docs/benchmarks.md section 7):

    python scripts/bench_evidence.py --flagfile=configs/bedroom.cfg [main-job flags, e.g. --scene=DIR]
        [--against=HEAD~1] [--bench_repeats=3] [--bench_json=FILE]

Builds the main job's problem, evaluation context and per-view estimates once (`build_problem`,
`scoring.evaluation_context`, `scoring.per_view_baseline`: the estimates from the cache when they
are there), then takes the statistics of every map as `outputs.write_evidence` does (the estimates
through `outputs.evidence_images`; in the passes of `outputs.evidence_passes`, or one map at a time
with a `render/visibility.py` that has no `texel_view_statistics_of`) with `render/visibility.py` as
it is here and as it was at `--against` (loaded from git as its own module), alternated
`--bench_repeats` times. The first repeat of each side includes its compilation and is reported apart. Prints the
median seconds of each side over the other repeats (or the first, with one repeat), their ratio,
and how far the two sides' statistics are apart (counts equal; mean and variance: the largest
difference relative to each array's largest magnitude).
"""

from __future__ import annotations

import json
import statistics
import subprocess
import sys
import time
import types
from pathlib import Path

from absl import app, flags

import jaxdistill  # noqa: F401  (the package's XLA flags, as the main job)
from jaxdistill.engine import config as config_lib

REPO = Path(__file__).resolve().parents[1]
MODULE = "jaxdistill/render/visibility.py"

config_lib.define_flags(flags.FLAGS, main_module=True)
flags.DEFINE_string("against", "HEAD~1", "the git revision whose statistics to compare with")
flags.DEFINE_integer("bench_repeats", 3, "times the two sides alternate")
flags.DEFINE_string("bench_json", None, "write the figures as JSON here")


def module_at(revision: str):
    """`render/visibility.py` as it was at `revision`, loaded as its own module. Only that file comes
    from the revision: what it imports (the sampler's `render`, the gather plans) is this checkout's."""
    done = subprocess.run(["git", "show", f"{revision}:{MODULE}"], cwd=REPO, capture_output=True, text=True)
    if done.returncode != 0:
        sys.exit(f"--against={revision}: git cannot show {MODULE} there ({done.stderr.strip()})")
    module = types.ModuleType("visibility_then")
    exec(compile(done.stdout, f"{revision}:{MODULE}", "exec"), module.__dict__)
    return module


def statistics_of(module, plan, images_of, passes, num_texels) -> tuple[float, dict]:
    """(seconds, {map: (count, mean, variance)}) of `module`'s statistics as the export takes them:
    `texel_view_statistics_of` a pass of maps at a time, or without it `texel_view_statistics` a map
    at a time. images_of(maps): per view a tuple of those maps' images."""
    out = {}
    start = time.perf_counter()
    for maps in passes:
        if hasattr(module, "texel_view_statistics_of"):
            out.update(zip(maps, module.texel_view_statistics_of(plan, images_of(maps), num_texels)))
        else:
            for m in maps:
                out[m] = module.texel_view_statistics(plan, (t[0] for t in images_of((m,))), num_texels)
    return time.perf_counter() - start, out


def apart(a: dict, b: dict) -> dict:
    """How far two sides' statistics are apart, over all maps: counts equal, NaN in the same places,
    and the largest difference of mean and variance where both are finite, relative to the largest
    finite magnitude."""
    import numpy as np

    worst = {"counts_equal": True, "nan_equal": True, "mean": 0.0, "variance": 0.0}
    for m in a:
        worst["counts_equal"] &= bool(np.array_equal(a[m][0], b[m][0]))
        for i, name in ((1, "mean"), (2, "variance")):
            x, y = np.asarray(a[m][i], np.float64), np.asarray(b[m][i], np.float64)
            worst["nan_equal"] &= bool(np.array_equal(np.isnan(x), np.isnan(y)))
            both = np.isfinite(x) & np.isfinite(y)
            if both.any():
                scale = max(float(np.abs(x[both]).max()), 1e-30)
                worst[name] = max(worst[name], float(np.abs(x[both] - y[both]).max()) / scale)
    return worst


def main(argv) -> int:
    del argv
    from jaxdistill.engine.problem import build_problem
    from jaxdistill.evaluate import scoring
    from jaxdistill.export import outputs
    from jaxdistill.render import visibility

    fv = flags.FLAGS
    if fv.bench_repeats < 1:
        sys.exit("--bench_repeats must be >= 1")
    then = module_at(fv.against)
    config = config_lib.config_from_flags(fv)
    problem = build_problem(config)
    ctx = scoring.evaluation_context(config, problem)
    problem = problem.without_fragments()
    baseline = scoring.per_view_baseline(config, problem, ctx.shapes)
    if not baseline.views:
        sys.exit("the problem has no per-view estimates or targets: the evidence has no statistics to take")
    plan = outputs.training_plan(problem)
    maps = problem.channels.maps
    images_of = lambda ms: outputs.evidence_images(problem, ctx, baseline.views, ms)   # noqa: E731
    passes = outputs.evidence_passes(maps, problem.space.num_texels)
    sides = {"now": visibility, "then": then}
    seconds = {side: [] for side in sides}
    results = {}
    for repeat in range(fv.bench_repeats):
        for side, module in sides.items():
            s, results[side] = statistics_of(module, plan, images_of, passes, problem.space.num_texels)
            seconds[side].append(s)
            print(f"repeat {repeat}: {side} {s:.2f} s", flush=True)
    timed = {side: (s[1:] if len(s) > 1 else s) for side, s in seconds.items()}
    median = {side: statistics.median(s) for side, s in timed.items()}
    doc = {"what": "texel_view_statistics of every map, as the evidence export takes them",
           "scene": config.scene, "against": fv.against, "num_texels": problem.space.num_texels,
           "views": problem.num_views, "render": [problem.height, problem.width], "maps": list(maps),
           "passes": [list(p) for p in passes],
           "seconds": seconds, "first_repeat_s": {side: s[0] for side, s in seconds.items()},
           "median_s": median, "now_over_then": median["now"] / median["then"],
           "apart": apart(results["now"], results["then"])}
    print(f"{problem.space.num_texels} texels, {problem.num_views} views of {problem.width}x{problem.height}, "
          f"{len(maps)} maps: now {median['now']:.2f} s, then ({fv.against}) {median['then']:.2f} s, "
          f"now / then {doc['now_over_then']:.3f}; first repeat (compiling) now {seconds['now'][0]:.2f} s, "
          f"then {seconds['then'][0]:.2f} s; apart: {doc['apart']}")
    if fv.bench_json:
        Path(fv.bench_json).write_text(json.dumps(doc, indent=1))
    return 0


if __name__ == "__main__":
    app.run(main)
