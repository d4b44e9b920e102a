"""The main job, cold, with today's settings against a pinned earlier revision's, side by side.

    python scripts/bench_main.py [--config=configs/bedroom.cfg] [--pinned=d26f2b5] \\
        [--extra="--steps=2 --estimate_steps=1"] [--out=out/bench_main] [--json=docs/data/bench_main.json]

Runs `python -m jaxdistill.main` twice, one run after the other, each cold: a new, empty
`JAXDISTILL_CACHE`, so the fragments, the UVs and the model's per-view estimates are all
computed. The first run uses the config file as it is now. The second uses the same file as it
was at the pinned revision (`git show REV:PATH`, so a git checkout is needed). Flags that the old
file does not name take today's defaults. Both runs use today's code: the comparison is between
the settings.

For each run the script records:
- the child's wall seconds, its user + system CPU seconds and its peak RSS (the operating
  system's accounting);
- the phases: set-up (`metrics.json` `setup_timings`), the loop (compilation + steps), the
  model's per-view estimates (from the job's log), and the rest (anchor, scoring, outputs);
- albedo PSNR / SSIM and the anchor's gains.

It then gives the ratios, now / pinned. With `--extra`, both runs get the same flags appended
(a quick check of this script: `--extra="--steps=2 --estimate_steps=1 --render_size=64"`).
The default pinned revision, d26f2b5, is the default from before the re-rendering term: 16 views
per step with the prior on every step, and no photo term.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shlex
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
ESTIMATES_LINE = re.compile(r"the model's per-view estimates: (\d+) views x (\d+) maps in ([\d.]+) s")


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--config", default="configs/bedroom.cfg", help="the config file, relative to the repository")
    p.add_argument("--pinned", default="d26f2b5", help="the revision whose version of --config is the baseline")
    p.add_argument("--extra", default="", help="flags appended to both runs")
    p.add_argument("--out", default="out/bench_main", help="folder of the two runs' outputs and logs")
    p.add_argument("--json", default=None, help="write the rows and ratios here")
    return p.parse_args(argv)


def pinned_config(rev: str, path: str, dest: Path) -> Path:
    """The config file as it was at `rev`, written to `dest` (SystemExit naming what failed)."""
    proc = subprocess.run(["git", "-C", str(REPO), "show", f"{rev}:{path}"], capture_output=True, text=True)
    if proc.returncode:
        raise SystemExit(f"--pinned={rev}: cannot read {path} at that revision ({proc.stderr.strip()}); "
                         "this needs a git checkout that has the revision")
    dest.write_text(proc.stdout)
    return dest


def run_cold(name: str, flagfile: Path, out_dir: Path, extra: list[str]) -> dict:
    """One cold main job; its accounting, phases and scores."""
    out_dir.mkdir(parents=True, exist_ok=True)
    log_path = out_dir.parent / f"{name.replace(' ', '_')}.log"
    cmd = [sys.executable, "-m", "jaxdistill.main", f"--flagfile={flagfile}", f"--out_dir={out_dir}", *extra]
    print(f"--- {name}: {' '.join(cmd[1:])}", file=sys.stderr, flush=True)
    with tempfile.TemporaryDirectory(prefix="jaxdistill-cold-") as cache, open(log_path, "w") as log:
        env = {**os.environ, "JAXDISTILL_CACHE": cache}
        t0 = time.monotonic()
        proc = subprocess.Popen(cmd, cwd=REPO, env=env, stdout=log, stderr=subprocess.STDOUT)
        _, status, usage = os.wait4(proc.pid, 0)            # this child's own accounting
        wall = time.monotonic() - t0
        proc.returncode = os.waitstatus_to_exitcode(status)
    if proc.returncode:
        raise SystemExit(f"{name}: the main job failed (exit {proc.returncode}); its log: {log_path}")
    metrics = json.loads((out_dir / "metrics.json").read_text())
    found = ESTIMATES_LINE.findall(log_path.read_text(errors="replace"))
    estimates_s = float(found[-1][2]) if found else None
    setup_s = float(sum(metrics.get("setup_timings", {}).values()))
    loop_s = float(metrics["loop_seconds"])
    ours = metrics["ours"]
    return {
        "name": name, "flagfile": str(flagfile), "extra": extra, "log": str(log_path),
        "wall_s": wall, "cpu_s": usage.ru_utime + usage.ru_stime,
        "peak_rss_gb": usage.ru_maxrss / 2 ** 20,          # Linux reports kB
        "setup_s": setup_s, "loop_s": loop_s, "steps": metrics["steps"], "seconds_per_step": metrics["seconds_per_step"],
        "estimates_s": estimates_s,
        "rest_s": wall - setup_s - loop_s - (estimates_s or 0.0),
        "albedo_psnr": ours.get("albedo_psnr"), "albedo_ssim": ours.get("albedo_ssim"),
        "albedo_si_psnr": ours.get("albedo_si_psnr"), "anchor": metrics.get("anchor"),
        "settings": metrics.get("config"),
    }


def ratios(now: dict, pinned: dict) -> dict:
    keys = ("wall_s", "cpu_s", "setup_s", "loop_s", "seconds_per_step", "estimates_s", "rest_s", "peak_rss_gb")
    return {k: now[k] / pinned[k] for k in keys if now.get(k) and pinned.get(k)}


def fmt(x, spec=".1f") -> str:
    return "-" if x is None else format(x, spec)


def print_table(rows: list[dict], ratio: dict, file=sys.stdout) -> None:
    now, pinned = rows
    print(f"\n{'':22s} {now['name']:>14s} {pinned['name']:>14s} {'now / pinned':>13s}", file=file)
    for key, label, spec in (("wall_s", "wall s", ".0f"), ("cpu_s", "CPU s (user+sys)", ".0f"),
                             ("setup_s", "set-up s", ".0f"), ("loop_s", "compile + steps s", ".0f"),
                             ("seconds_per_step", "s per step", ".2f"), ("estimates_s", "estimates s", ".0f"),
                             ("rest_s", "anchor, scoring, out s", ".0f"), ("peak_rss_gb", "peak RSS GB", ".1f"),
                             ("albedo_psnr", "albedo PSNR dB", ".2f"), ("albedo_si_psnr", "albedo si-PSNR dB", ".2f"),
                             ("albedo_ssim", "albedo SSIM", ".3f")):
        r = ratio.get(key)
        print(f"{label:22s} {fmt(now.get(key), spec):>14s} {fmt(pinned.get(key), spec):>14s} "
              f"{fmt(r, '.2f') + 'x' if r else '':>13s}", file=file)


def main(argv=None) -> int:
    args = parse_args(argv)
    out = (REPO / args.out).resolve() if not Path(args.out).is_absolute() else Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    config = REPO / args.config
    if not config.is_file():
        raise SystemExit(f"--config={args.config}: no such file in the repository")
    old = pinned_config(args.pinned, args.config, out / f"pinned_{args.pinned}.cfg")
    extra = shlex.split(args.extra)
    rows = [run_cold("now", config, out / "now", extra), run_cold(f"pinned {args.pinned}", old, out / "pinned", extra)]
    ratio = ratios(*rows)
    print_table(rows, ratio)
    result = {"rows": rows, "ratios_now_over_pinned": ratio, "config": args.config, "pinned": args.pinned,
              "extra": extra, "cpu_count": os.cpu_count(),
              "headline": f"now / pinned {args.pinned}: wall {ratio.get('wall_s', float('nan')):.2f}x, "
                          f"albedo {rows[0]['albedo_psnr']:.2f} vs {rows[1]['albedo_psnr']:.2f} dB"}
    print("\n" + result["headline"])
    if args.json:
        Path(args.json).write_text(json.dumps(result, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
