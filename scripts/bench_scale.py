"""How the main job's cost grows with a capture's size: views, resolution, faces.

    python scripts/bench_scale.py [--views=50,150] [--sizes=876x584] [--faces_per_side=300] \\
        [--steps=5] [--prior=views] [--max_texture_size=4096] [--view_data=auto] [--work=out/bench_scale] \
        [--flagfile=configs/bedroom.cfg] [--processes=1] [--json=FILE]

For every resolution × view count, one after the other:
1. the capture-sized synthetic room (`scripts/make_capture_scene.py`'s scene, reused when it is
   already in the work folder), its generation timed;
2. the main job on it, cold (a new, empty `JAXDISTILL_CACHE` in the work folder), for `--steps`
   steps. The script records the child's wall seconds and peak RSS (the operating system's
   accounting), the set-up phases from `metrics.json` (scene read, fragments, gather plans,
   prior), the loop (compilation + steps), the peak RSS by the end of set-up and of the loop
   (`metrics.json` `peak_host_memory_gb`), the size of the cache on disk, and that of the
   per-view arrays' files (`--view_data`, `metrics.json` `view_data`; unlinked, so not in the cache's size).
With `--processes=N` the main job runs as N processes on this machine, joined by
`jax.distributed` on localhost (gloo): process 0 holds every view and writes the outputs, each
other its share of the views (`jaxdistill/engine/distributed.py`); every process's wall seconds
and peak RSS are recorded, the table's row being process 0's and the other processes' peaks
printed under it.
A run that fails (out of memory, say) is recorded with its exit status and the log's last line,
and the next size still runs. The table prints as the runs finish; `--json` writes it.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import socket
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--views", default="50,150", help="view counts, comma-separated")
    p.add_argument("--sizes", default="876x584", help="WxH resolutions, comma-separated")
    p.add_argument("--faces_per_side", type=int, default=300, help="wall subdivisions; 300 gives 1.13M faces")
    p.add_argument("--steps", type=int, default=5, help="distillation steps per run (the first compiles)")
    p.add_argument("--prior", default=None, choices=("views", "auto"),
                   help="views: the targets; auto: SDS (default: views, or --flagfile's prior)")
    p.add_argument("--views_per_step", type=int, default=8)
    p.add_argument("--view_data", default="auto", choices=("auto", "memory", "disk"),
                   help="the main job's --view_data: per-view arrays in memory or in files")
    p.add_argument("--max_texture_size", type=int, default=4096)
    p.add_argument("--work", default="out/bench_scale", help="scenes, caches, runs and logs")
    p.add_argument("--flagfile", default=None,
                   help="the main job's settings (e.g. configs/bedroom.cfg for SDS as the default run does it); "
                        "the scene, steps, views per step, page cap, --view_data and a --prior given above override it")
    p.add_argument("--processes", type=int, default=1, help="processes of the main job on this machine, joined on "
                   "localhost; each but process 0 holds its share of the views")
    p.add_argument("--json", default=None)
    args = p.parse_args(argv)
    if args.flagfile and not Path(args.flagfile).is_file():
        p.error(f"--flagfile: {args.flagfile} is not a file")
    try:
        args.views = [int(v) for v in args.views.split(",")]
        args.sizes = [tuple(int(x) for x in s.lower().split("x")) for s in args.sizes.split(",")]
    except ValueError:
        p.error("--views takes integers (50,150) and --sizes WxH pairs (876x584,1752x1168)")
    if any(v < 1 for v in args.views) or any(len(s) != 2 or min(s) < 8 for s in args.sizes):
        p.error("--views must be >= 1 and --sizes WxH with sides >= 8")
    if args.processes < 1:
        p.error(f"--processes must be >= 1, got {args.processes}")
    return args


def run_child(cmd: list[str], log: Path, env: dict | None = None) -> dict:
    """Runs `cmd` with its output in `log`; its wall seconds, peak RSS and exit status."""
    return run_children([cmd], [log], env)[0]


def run_children(cmds: list[list[str]], logs: list[Path], env: dict | None = None) -> list[dict]:
    """Runs the commands at once, each with its output in its log; each one's wall seconds (from
    the common start), peak RSS and exit status, and its log's last line."""
    outs = [open(log, "w") for log in logs]
    try:
        t0 = time.monotonic()
        procs = {subprocess.Popen(cmd, cwd=REPO, env=env, stdout=out, stderr=subprocess.STDOUT).pid: i
                 for i, (cmd, out) in enumerate(zip(cmds, outs))}
        got = [None] * len(cmds)
        while procs:
            pid, status, usage = os.wait4(-1, 0)
            if pid in procs:
                got[procs.pop(pid)] = (os.waitstatus_to_exitcode(status), time.monotonic() - t0, usage.ru_maxrss)
    finally:
        for out in outs:
            out.close()
    rows = []
    for (code, wall, rss), log in zip(got, logs):
        lines = log.read_text(errors="replace").replace("\r", "\n").strip().splitlines()
        rows.append({"exit": code, "wall_s": wall, "peak_rss_gb": rss / 2 ** 20, "last_line": lines[-1] if lines else ""})
    return rows


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("localhost", 0))
        return s.getsockname()[1]


def folder_bytes(folder: Path) -> int:
    return sum(p.stat().st_size for p in folder.rglob("*") if p.is_file())


def main_command(args, scene: Path, out: Path, views: int, process: tuple[int, str] | None = None) -> list[str]:
    """The main job's command for one case: `--flagfile`'s settings first, so the flags after it win;
    `process` (id, coordinator HOST:PORT) with --processes > 1."""
    settings = [f"--flagfile={Path(args.flagfile).resolve()}"] if args.flagfile else []
    prior = [f"--prior={args.prior}"] if args.prior else [] if args.flagfile else ["--prior=views"]
    return [sys.executable, "-m", "jaxdistill.main", *settings, f"--scene={scene}", *prior,
            f"--steps={args.steps}", f"--views_per_step={min(args.views_per_step, views)}",
            f"--max_texture_size={args.max_texture_size}", f"--out_dir={out}", "--renders=false",
            f"--view_data={args.view_data}"] + ([] if process is None else [
            f"--coordinator_address={process[1]}", f"--num_processes={args.processes}", f"--process_id={process[0]}"])


def one_case(args, work: Path, width: int, height: int, views: int) -> dict:
    tag = f"{width}x{height}_{views}v_{args.faces_per_side}f"
    scene = work / f"scene_{tag}"
    row = {"width": width, "height": height, "views": views, "faces_per_side": args.faces_per_side}
    if not (scene / "scene.json").is_file():
        gen = run_child([sys.executable, str(REPO / "scripts" / "make_capture_scene.py"), f"--out={scene}",
                         f"--faces_per_side={args.faces_per_side}", f"--views={views}", f"--width={width}",
                         f"--height={height}"], work / f"generate_{tag}.log")
        row["generate"] = gen
        if gen["exit"]:
            return {**row, "status": "generation failed"}
    cache, out = work / f"cache_{tag}", work / f"run_{tag}"
    for folder in (cache, out):
        shutil.rmtree(folder, ignore_errors=True)
    several = args.processes > 1
    address = f"localhost:{free_port()}" if several else ""
    runs = run_children([main_command(args, scene, out, views, (i, address) if several else None)
                         for i in range(args.processes)],
                        [work / (f"run_{tag}_p{i}.log" if several else f"run_{tag}.log") for i in range(args.processes)],
                        env={**os.environ, "JAXDISTILL_CACHE": str(cache)})
    # the row is process 0's, failed when any process failed
    run = {**runs[0], "exit": next((r["exit"] for r in runs if r["exit"]), 0)}
    if several:
        row["processes"] = runs
    row.update(run=run, cache_gb=folder_bytes(cache) / 2 ** 30 if cache.exists() else 0.0)
    if run["exit"]:
        return {**row, "status": f"main job failed (exit {run['exit']})"}
    metrics = json.loads((out / "metrics.json").read_text())
    row.update(status="ok", setup=metrics.get("setup_timings", {}), loop_s=metrics["loop_seconds"],
               outputs=metrics.get("output_timings", {}), steps=metrics["steps"],
               texels=(metrics.get("parameters") or {}).get("texels"),
               peaks=metrics.get("peak_host_memory_gb", {}), view_data=metrics.get("view_data", {}))
    return row


def print_row(r: dict, file=sys.stdout) -> None:
    run = r.get("run") or {}
    setup = r.get("setup") or {}
    peaks = r.get("peaks") or {}
    gen = (r.get("generate") or {}).get("wall_s")
    print(f"{r['width']}x{r['height']:<5d} {r['views']:5d} {r['status']:>24s} "
          f"{'-' if gen is None else f'{gen:.0f}':>6s} {setup.get('fragments_s', 0):8.0f} {setup.get('plans_s', 0):7.0f} "
          f"{r.get('loop_s', 0):7.0f} {sum(p['seconds'] for p in (r.get('outputs') or {}).values()):6.0f} "
          f"{run.get('wall_s', 0):7.0f} {run.get('peak_rss_gb', 0):7.1f} {peaks.get('set-up', 0):7.1f} "
          f"{peaks.get('loop', 0):7.1f} {r.get('cache_gb', 0):8.2f} {(r.get('view_data') or {}).get('disk_bytes', 0) / 2 ** 30:7.2f}",
          file=file, flush=True)
    for i, p in enumerate((r.get("processes") or [])[1:], start=1):
        print(f"{'':11s} process {i}: exit {p['exit']}, wall {p['wall_s']:.0f} s, peak RSS {p['peak_rss_gb']:.1f} GB",
              file=file, flush=True)


def main(argv=None) -> int:
    args = parse_args(argv)
    work = (REPO / args.work) if not Path(args.work).is_absolute() else Path(args.work)
    work.mkdir(parents=True, exist_ok=True)
    print(f"{'render':11s} {'views':>5s} {'status':>24s} {'gen s':>6s} {'frags s':>8s} {'plans s':>7s} "
          f"{'loop s':>7s} {'out s':>6s} {'wall s':>7s} {'RSS GB':>7s} {'set-up':>7s} {'loop':>7s} {'cache GB':>8s} "
          f"{'rows GB':>7s}   (loop: compile + {args.steps} steps; RSS: peak, and the peak by the end of set-up and "
          "loop; rows: --view_data files)",
          flush=True)
    rows = []
    for width, height in args.sizes:
        for views in args.views:
            rows.append(one_case(args, work, width, height, views))
            print_row(rows[-1])
    if args.json:
        Path(args.json).write_text(json.dumps({"rows": rows, "args": {k: v for k, v in vars(args).items()},
                                               "cpu_count": os.cpu_count()}, indent=1, default=str))
    return 0 if all(r["status"] == "ok" for r in rows) else 1


if __name__ == "__main__":
    sys.exit(main())
