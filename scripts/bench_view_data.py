"""What holding the per-view arrays in files costs the loop: --view_data=memory against disk.

    python scripts/bench_view_data.py --scene=SCENE [--steps=20] [--log_every=5] [--repeats=2] \\
        [--views_per_step=8] [--max_texture_size=4096] [--prior=views] [--cache=DIR] [--json=FILE] \\
        [--cases=memory,disk,disk_sources]

Cases: `memory`, `disk` (--view_data=disk: targets and photos copied into float32 files, as the
package does where they fit), and `disk_sources` (--view_data=disk with targets and photos at their
files' size read again from those files for each batch, `view_rows.SourceRows`, as the package does
where the copies would not fit on the disk: forced in that child).

Each case is a child process (so that its peak RSS is its own): the main job's set-up and loop
(`build_problem`, `run_loop` with the step compiled ahead, no checkpoints, no outputs), the
two settings alternated `--repeats` times, with the ray casts read from `--cache` (or made first
by a warm-up case in a new cache). Per case: set-up seconds, seconds per step (median over the --log_every
windows), the host time to assemble one batch (`Problem.batch`: reads from the files on disk;
median), and peak RSS; then the medians per setting and their ratio, disk / memory.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
CASES = ("memory", "disk", "disk_sources")


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--scene", required=True)
    p.add_argument("--steps", type=int, default=20)
    p.add_argument("--log_every", type=int, default=5)
    p.add_argument("--repeats", type=int, default=2)
    p.add_argument("--views_per_step", type=int, default=8)
    p.add_argument("--max_texture_size", type=int, default=4096)
    p.add_argument("--prior", default="views", choices=("views", "auto"))
    p.add_argument("--cache", default=None, help="a ray-cast cache that holds the scene's casts already (default: a "
                   "new folder, filled by a warm-up case first)")
    p.add_argument("--json", default=None)
    p.add_argument("--cases", default="memory,disk,disk_sources", help="comma-separated, of " + ", ".join(CASES))
    p.add_argument("--one", default=None, choices=CASES, help=argparse.SUPPRESS)   # a child's case
    args = p.parse_args(argv)
    args.cases = [c for c in args.cases.split(",") if c]
    if not args.cases or set(args.cases) - set(CASES):
        p.error(f"--cases: some of {CASES}, got {args.cases}")
    if args.steps < 2 * args.log_every or args.log_every < 1 or args.repeats < 1:
        p.error("--steps must be at least 2 x --log_every (>= 1), --repeats >= 1")
    return args


def one_case(args) -> dict:
    """The child: one setting's set-up and loop, timed."""
    import numpy as np

    from jaxdistill.engine import config as config_lib, loop, problem as problem_lib
    from jaxdistill.engine.config import DistillConfig
    from jaxdistill.engine.problem import build_problem

    if args.one == "disk_sources":       # as the set-up decides where the copies would not fit
        decide = problem_lib._view_data_folder

        def sources(*a, **k):
            folder, _, casts = decide(*a, **k)
            return folder, True, casts

        problem_lib._view_data_folder = sources
    out = tempfile.TemporaryDirectory(prefix="bench_view_data_")       # the loop writes nothing there
    config = config_lib.validate(DistillConfig(
        scene=args.scene, out_dir=out.name, prior=args.prior, steps=args.steps, log_every=args.log_every,
        views_per_step=args.views_per_step, max_texture_size=args.max_texture_size,
        view_data="memory" if args.one == "memory" else "disk"))
    t0 = time.perf_counter()
    problem = build_problem(config)
    setup_s = time.perf_counter() - t0
    batch_s = []
    assemble = problem.batch

    def timed_batch(ids):
        start = time.perf_counter()
        batch = assemble(ids)
        batch_s.append(time.perf_counter() - start)
        return batch

    object.__setattr__(problem, "batch", timed_batch)        # a frozen dataclass: time its batches
    clock = loop.StepClock()
    loop.run_loop(config, problem, loop.recorded_config(config, problem.choice.kind), None, progress=False,
                  hooks=clock.hooks())
    windows = clock.seconds_per_step()
    return {"view_data": args.one, "on_disk": problem.view_folder is not None, "setup_s": setup_s,
            "s_per_step": float(np.median(windows)), "batch_s": float(np.median(batch_s[2:] or batch_s)),
            "views": problem.num_views, "render_hw": [problem.height, problem.width],
            "files_gb": problem.view_folder.nbytes / 2 ** 30 if problem.view_folder else 0.0,
            "targets_in": type(getattr(problem.prior, "target_images", None)).__name__,
            "peak_rss_gb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2 ** 20}


def run_child(args, view_data: str, cache: str) -> dict:
    cmd = [sys.executable, os.fspath(Path(__file__).resolve()), f"--scene={args.scene}", f"--steps={args.steps}",
           f"--cases={view_data}",
           f"--log_every={args.log_every}", f"--views_per_step={args.views_per_step}",
           f"--max_texture_size={args.max_texture_size}", f"--prior={args.prior}", f"--one={view_data}"]
    done = subprocess.run(cmd, cwd=REPO, env={**os.environ, "JAXDISTILL_CACHE": cache}, capture_output=True, text=True)
    if done.returncode:
        raise SystemExit(f"the {view_data} case failed (exit {done.returncode}):\n{done.stderr[-3000:]}")
    return json.loads(done.stdout.strip().splitlines()[-1])


def main(argv=None) -> int:
    args = parse_args(argv)
    if args.one:
        print(json.dumps(one_case(args)), flush=True)
        return 0
    import numpy as np

    cache = args.cache or tempfile.mkdtemp(prefix="bench_view_data_cache_")
    if not args.cache:
        run_child(args, "memory", cache)                       # warm-up: the ray casts into the new cache
    rows = []
    print(f"{'case':12s} {'set-up s':>9s} {'s/step':>8s} {'batch ms':>9s} {'peak RSS GB':>12s} {'files GiB':>10s} "
          "targets in", flush=True)
    for _ in range(args.repeats):
        for case in args.cases:
            rows.append(run_child(args, case, cache))
            r = rows[-1]
            print(f"{case:12s} {r['setup_s']:9.1f} {r['s_per_step']:8.3f} {1000 * r['batch_s']:9.1f} "
                  f"{r['peak_rss_gb']:12.2f} {r['files_gb']:10.3f} {r['targets_in']}", flush=True)
    summary = {}
    for case in args.cases:
        mine = [r for r in rows if r["view_data"] == case]
        summary[case] = {k: float(np.median([r[k] for r in mine]))
                         for k in ("setup_s", "s_per_step", "batch_s", "peak_rss_gb", "files_gb")}
    first = args.cases[0]
    ratios = {f"{case}_over_{first}": {k: summary[case][k] / summary[first][k] if summary[first][k] else None
                                       for k in summary[case]} for case in args.cases[1:]}
    print("medians: " + "; ".join(f"{v}: {s['s_per_step']:.3f} s/step, batch {1000 * s['batch_s']:.1f} ms, "
                                  f"peak {s['peak_rss_gb']:.2f} GB, files {s['files_gb']:.3f} GiB"
                                  for v, s in summary.items()))
    for name, ratio in ratios.items():
        print(f"{name.replace('_over_', ' / ')}: s/step {ratio['s_per_step']:.3f}x, set-up {ratio['setup_s']:.2f}x, "
              f"batch {ratio['batch_s']:.2f}x, peak RSS {ratio['peak_rss_gb']:.2f}x", flush=True)
    if args.json:
        Path(args.json).write_text(json.dumps({"args": {k: v for k, v in vars(args).items() if k != "one"},
                                               "rows": rows, "median": summary, "ratios": ratios}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
