"""The main job's steps under three settings of glibc's malloc, side by side, each in its own
process (docs/benchmarks.md §7):

  system  glibc's defaults (`glibc.malloc.hugetlb` not set, `JAXDISTILL_HUGE_PAGES=0`; the
          kernel's own transparent huge page mode applies, recorded per child);
  keep    freed memory kept in the process (`mallopt`: one arena, blocks up to 1 GiB from the
          heap, the heap's free top kept up to 2 GiB): tried for the main job and not kept;
  huge    `GLIBC_TUNABLES=glibc.malloc.hugetlb=1`: glibc's mapped blocks marked for transparent
          huge pages, as the main job now runs itself (`jaxdistill/huge_pages.py`).

    python scripts/bench_malloc.py [--flagfile=configs/bedroom.cfg] [--steps=20] [--repeats=2]
        [--forms=system,keep,huge] [--set=flag=value ...] [--json=FILE]

Each child process (`--child=FORM`; the parent alternates the forms, `--repeats` times each)
builds the config's problem as the main job does, compiles its step ahead (`loop.prepare_step`),
runs 2 steps to warm up, then times `--steps` more steps: wall seconds, user and system CPU
seconds, minor page faults (`getrusage`), and the process's peak RSS. With `keep` the settings
are applied first thing, before XLA starts its threads; `huge` is set in the child's environment,
where glibc reads it at start-up. Every form computes the same arithmetic: the child reports a
checksum of its final texels, which must match. Prints each form's medians and their ratios to
the first form's; `--json` writes the runs.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
from pathlib import Path

from jaxdistill.huge_pages import OFF, TUNABLE       # light: the package's __init__ and this module

FORMS = ("system", "keep", "huge")
HUGE = f"{TUNABLE}=1"
M_TRIM_THRESHOLD, M_MMAP_THRESHOLD, M_ARENA_MAX = -1, -3, -8       # glibc's mallopt parameters (malloc.h)
KEEP = ((M_ARENA_MAX, 1), (M_MMAP_THRESHOLD, 1 << 30), (M_TRIM_THRESHOLD, (1 << 31) - 1))


def glibc():
    """The process's C library when it is glibc (it has `mallopt`), else None."""
    import ctypes
    import ctypes.util
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
    except OSError:
        return None
    if not (hasattr(libc, "gnu_get_libc_version") and hasattr(libc, "mallopt")):
        return None
    libc.mallopt.argtypes, libc.mallopt.restype = (ctypes.c_int, ctypes.c_int), ctypes.c_int
    return libc


def keep_freed_memory() -> bool:
    """`KEEP` applied with mallopt; True when glibc accepted every parameter."""
    libc = glibc()
    return libc is not None and all(libc.mallopt(name, value) == 1 for name, value in KEEP)


def child(form: str, flagfile: str, steps: int, sets: list[str]) -> dict:
    if form == "keep":
        if not keep_freed_memory():
            raise SystemExit("bench_malloc: glibc's mallopt is not available here: nothing to compare")
    import hashlib
    import resource
    import tempfile
    import time

    import jax
    import numpy as np
    from absl import flags

    from jaxdistill import huge_pages
    from jaxdistill.engine import config as config_lib, distributed, loop
    from jaxdistill.engine.problem import build_problem

    fv = flags.FlagValues()
    config_lib.define_flags(fv)
    with tempfile.TemporaryDirectory() as out:
        fv(["bench_malloc", f"--flagfile={flagfile}", f"--out_dir={out}", *[f"--{s}" for s in sets]])
        config = config_lib.config_from_flags(fv)
        problem = build_problem(config)
        prepared = loop.prepare_step(config, problem)
        stepper = prepared.stepper
        state = jax.device_put(stepper.state, stepper.replicated)
        frozen = jax.device_put(problem.frozen, stepper.replicated)

        def run(first: int, count: int):
            nonlocal state
            for step in range(first, first + count):
                batch = distributed.place_batch(problem.batch, loop.batch_views(problem, config, step), stepper.by_view)
                state, _ = prepared.compiled(state, batch, frozen)
            jax.block_until_ready(state)

        run(0, 2)
        before, start = resource.getrusage(resource.RUSAGE_SELF), time.perf_counter()
        run(2, steps)
        after, wall = resource.getrusage(resource.RUSAGE_SELF), time.perf_counter() - start
        texels = np.asarray(jax.device_get(state.texels))
    return {"form": form, "steps": steps, "wall_s": wall, "user_s": after.ru_utime - before.ru_utime,
            "system_s": after.ru_stime - before.ru_stime, "minor_faults": after.ru_minflt - before.ru_minflt,
            "peak_rss_gb": after.ru_maxrss / 2 ** 20, "texels_sha1": hashlib.sha1(texels.tobytes()).hexdigest(),
            "glibc_tunables": os.environ.get("GLIBC_TUNABLES", ""), "thp_mode": huge_pages.thp_mode()}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--flagfile", default="configs/bedroom.cfg", help="the main job's flags")
    parser.add_argument("--set", action="append", default=[], metavar="FLAG=VALUE",
                        help="a flag on top of --flagfile (repeatable), e.g. --set=views_per_step=4")
    parser.add_argument("--steps", type=int, default=20, help="steps timed after 2 warm-up steps")
    parser.add_argument("--repeats", type=int, default=2, help="runs of each form, alternated")
    parser.add_argument("--forms", default=",".join(FORMS), help=f"comma-separated, of {', '.join(FORMS)}; "
                        "ratios are to the first")
    parser.add_argument("--json", type=Path, default=None)
    parser.add_argument("--child", choices=FORMS, default=None, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.steps < 1 or args.repeats < 1:
        parser.error("--steps and --repeats must be positive")
    forms = [f for f in args.forms.split(",") if f]
    if not forms or any(f not in FORMS for f in forms) or len(set(forms)) != len(forms):
        parser.error(f"--forms={args.forms}: give distinct forms of {', '.join(FORMS)}")
    if args.child:
        print(json.dumps(child(args.child, args.flagfile, args.steps, args.set)))
        return 0
    runs = []
    base_env = {k: v for k, v in os.environ.items() if k != "GLIBC_TUNABLES"}
    others = ":".join(t for t in os.environ.get("GLIBC_TUNABLES", "").split(":") if t and not t.strip().startswith(TUNABLE))
    for _ in range(args.repeats):
        for form in forms:
            env = {**base_env, OFF: "0"}
            tunables = ":".join(t for t in (others, HUGE if form == "huge" else "") if t)
            if tunables:
                env["GLIBC_TUNABLES"] = tunables
            command = [sys.executable, os.path.abspath(__file__), f"--child={form}", f"--flagfile={args.flagfile}",
                       f"--steps={args.steps}", *[f"--set={s}" for s in args.set]]
            done = subprocess.run(command, capture_output=True, text=True, env=env)
            if done.returncode:
                sys.stderr.write(done.stderr[-4000:])
                raise SystemExit(f"bench_malloc: the {form} child failed (exit {done.returncode})")
            runs.append(json.loads(done.stdout.strip().splitlines()[-1]))
            print(f"  {form:6s}: {runs[-1]['wall_s']:.2f} s wall, {runs[-1]['system_s']:.2f} s system, "
                  f"{runs[-1]['minor_faults']} minor faults", flush=True)
    keys = ("wall_s", "user_s", "system_s", "minor_faults", "peak_rss_gb")
    medians = {f: {k: statistics.median(r[k] for r in runs if r["form"] == f) for k in keys} for f in forms}
    same = len({r["texels_sha1"] for r in runs}) == 1
    print(f"{args.flagfile}, {args.steps} steps timed, medians of {args.repeats} runs each:")
    for f in forms:
        m = medians[f]
        print(f"  {f:6s}: wall {m['wall_s']:7.2f} s ({m['wall_s'] / args.steps:.3f} s/step), user {m['user_s']:7.2f} s, "
              f"system {m['system_s']:6.2f} s, minor faults {m['minor_faults']:9.0f}, peak RSS {m['peak_rss_gb']:.2f} GB")
    ratios = {f: {k: medians[f][k] / medians[forms[0]][k] if medians[forms[0]][k] else None for k in keys}
              for f in forms[1:]}
    for f, ratio in ratios.items():
        shown = {k: "n/a" if v is None else f"{v:.3f}" for k, v in ratio.items()}
        print(f"  {f} / {forms[0]}: wall {shown['wall_s']}, system time {shown['system_s']}, "
              f"minor faults {shown['minor_faults']}, peak RSS {shown['peak_rss_gb']}")
    print(f"  final texels {'identical' if same else 'DIFFER'}")
    if args.json:
        args.json.write_text(json.dumps({"flagfile": args.flagfile, "set": args.set, "steps": args.steps,
                                         "forms": forms, "huge_tunable": HUGE,
                                         "keep_settings": {"M_ARENA_MAX": KEEP[0][1], "M_MMAP_THRESHOLD": KEEP[1][1],
                                                           "M_TRIM_THRESHOLD": KEEP[2][1]},
                                         "runs": runs, "median": medians,
                                         "ratio_to_first": ratios, "texels_identical": same}, indent=1))
    return 0 if same else 1


if __name__ == "__main__":
    raise SystemExit(main())
