"""Peak memory of the distillation: where host (and GPU) memory goes, phase by phase.

    python scripts/bench_memory.py [--cases=bedroom,bedroom_4096,bedroom_4096_bilinear_no_outputs,
        bedroom_auto_4096,room_1m] [--steps=3] [--faces_per_side=300] [--views=8] [--resolution=512]
        [--room_sampler=bilinear] [--room_max_texture_size=4096] [--max_gb=...] [--keep_work] [--json]

    # a quick check of the script (about 4 minutes on a busy 2-core machine):
    python scripts/bench_memory.py --cases=bedroom,room_1m --steps=2 --faces_per_side=40 --views=2 \
        --resolution=128

Every case runs the library's real job, `jaxdistill.engine.loop.run(config)` (what
`python -m jaxdistill.main` runs), in a fresh child process, so peaks never mix:

  bedroom                  configs/bedroom.cfg as it is: the default run (pages auto-sized, capped
                           at 512; trilinear; all five maps; 32 views of 320x240 per step).
  bedroom_4096             the same with --texture_size=4096 --max_texture_size=4096 (every one of
                           the 30 pages 4096^2), the case of docs/benchmarks.md §5.
  bedroom_4096_bilinear_no_outputs
                           4096^2 pages with --sampler=bilinear, and write_outputs replaced by a
                           stub (the outputs of 30 pages of 4096^2 write ~150 large image files).
  bedroom_auto_4096        bedroom.cfg with --max_texture_size=4096 (the flag's default cap):
                           auto-sized pages up to 2048 here.
  room_1m                  a >= 1M-triangle synthetic room (scripts/bench_render.py's geometry:
                           synthetic.box_room with furniture, one page per object) with --views
                           views of --resolution^2, written as a scene folder (mesh.glb, photos,
                           per-view targets of all five maps made from procedural textures seen
                           through Embree fragments) by a separate preparation child, then run
                           like the bedroom: read_scene (trimesh GLB load), Embree fragments,
                           layout, texel space, gather plans, visibility, views prior, compile,
                           steps, checkpoint, outputs. Library defaults for the texture flags
                           (pages auto-sized up to --room_max_texture_size, --room_sampler).

Common flags for every case: --steps, --views_per_step=min(32, views) for the room,
--ckpt_every=0 (one checkpoint at the end), --eval_every=0, --renders=false, --contact_views=0,
--log_every=steps: renders and contact sheets are the only outputs flags can turn off. The
rest of write_outputs (full pages of every map: maps/*.exr|png, scene.glb with tangent-space
normals, the final evaluation against GT and metrics.json) cannot be turned off by a flag and is
measured as the "outputs" phase, except in the *_no_outputs case. Each child gets a fresh,
empty fragment cache ($JAXDISTILL_CACHE), so fragments are ray cast, not reloaded
(--use_cache keeps yours).

Figures (per case; MB = 2^20 bytes):
  texels N, channels C       compact texel parameters (gather_plan.TexelSpace.num_texels) and
                             channels of the five maps (11); params = N x C.
  texels + AdamW             N x C x 4 bytes x 3 (texels, AdamW's two moments): the state.
  full pages                 the same for the layout's full level-0 pages (sum of S^2 x C), as
                             dense textures would need; compact / full is the saving.
  pyramid                    entries of the compact mip pyramid the trilinear gather reads.
  problem arrays             host arrays Problem keeps for the whole run: gather plans (index,
                             weight, hit), pixel weights, per-view targets, fragments.
  XLA step                   compiled.memory_analysis() of the step: arguments, outputs, temps
                             (temp = the step's intermediates: gathered taps, their cotangents...).
  RSS after <phase>          resident set size of the child when the phase ends (/proc/self/statm),
                             and in brackets the largest RSS sampled every 10 ms during the phase
                             (a sampled peak: a spike shorter than 10 ms can be missed).
  peak RSS                   the child's exact peak, getrusage(RUSAGE_SELF).ru_maxrss in the child
                             and os.wait4's rusage of that one child in this process (agree).
  GPU peak                   jax.devices()[0].memory_stats()["peak_bytes_in_use"]; None on CPU.
Phases, in order (each ends when the named code returns): imports (jax, jaxdistill), read scene
(scene.read_scene), fragments (fragments.compute_fragments, Embree BVH + casts + derivation),
texel space (gather_plan.build_texel_space), gather plans (build_gather_plans), visibility
(view_counts + pixel_weights), prior (per-view targets or RGB<->X latents), problem (the rest
of build_problem: host copies of the plans), init state (texels + AdamW), evaluation context
(GT maps of every view), compile (jit lower + XLA compile of the step; the script compiles it
ahead of time and calls the compiled step, identical to jit's own first call but timed apart),
first step, steps (the remaining steps), checkpoint (orbax, at the end), outputs.

Before the steps a guard estimates the memory a case needs at least, from the texel space it
has just built: state (texels + 2 moments) + gradient, + the trilinear pyramid and its
cotangent, and for the outputs + one map's full pages (write_outputs expands one map at a time).
A case whose estimate exceeds --max_gb (default 90% of MemAvailable when the script starts) is
stopped there and reported as "skipped" with its figures; this process also kills a child whose
RSS passes --max_gb. The machine (cores, RAM) and jax's backend and devices are printed first;
`--json` prints every figure as one JSON line last.
"""

from __future__ import annotations

import argparse
import functools
import json
import os
import platform
import resource
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
MB = float(1 << 20)
PAGE = os.sysconf("SC_PAGE_SIZE")

BEDROOM_CASES = {
    "bedroom": ("bedroom.cfg (auto pages <= 512, trilinear)", [], True),
    "bedroom_4096": ("bedroom.cfg, 4096^2 pages (trilinear)", ["--texture_size=4096", "--max_texture_size=4096"], True),
    "bedroom_4096_bilinear_no_outputs": ("4096^2 pages, bilinear, write_outputs stubbed",
                                         ["--texture_size=4096", "--max_texture_size=4096", "--sampler=bilinear"],
                                         False),
    "bedroom_auto_4096": ("bedroom.cfg, auto pages <= 4096 (trilinear)", ["--max_texture_size=4096"], True),
}
ALL_CASES = tuple(BEDROOM_CASES) + ("room_1m",)


# ----------------------------------------------------------------------------- /proc helpers

def rss_bytes(pid: str | int = "self") -> int:
    """Current resident set size (bytes) of a process, from /proc/<pid>/statm."""
    with open(f"/proc/{pid}/statm") as f:
        return int(f.read().split()[1]) * PAGE


def status_kb(field: str, pid: str | int = "self") -> int:
    """A kB figure of /proc/<pid>/status (VmHWM: peak RSS so far, VmRSS)."""
    with open(f"/proc/{pid}/status") as f:
        for line in f:
            if line.startswith(field + ":"):
                return int(line.split()[1])
    return 0


def meminfo_kb(field: str) -> int:
    with open("/proc/meminfo") as f:
        for line in f:
            if line.startswith(field + ":"):
                return int(line.split()[1])
    return 0


def machine() -> dict:
    cgroup_limit = None
    try:
        text = Path("/sys/fs/cgroup/memory.max").read_text().strip()
        cgroup_limit = None if text == "max" else int(text) / 2**30
    except OSError:
        pass
    return {"cores": os.cpu_count(), "cores_usable": len(os.sched_getaffinity(0)),
            "ram_gb": meminfo_kb("MemTotal") / 2**20, "ram_available_gb": meminfo_kb("MemAvailable") / 2**20,
            "cgroup_limit_gb": cgroup_limit, "cpu": platform.processor() or platform.machine(),
            "python": platform.python_version()}


# ----------------------------------------------------------------------------- child: recorder

class MemoryGuard(RuntimeError):
    """The case would need more memory than --max_gb: stopped before allocating it."""


class Recorder:
    """Phase marks with RSS now, the largest RSS sampled during the phase, and GPU bytes."""

    def __init__(self, path: Path):
        self.path = path
        self.start = self.last = time.perf_counter()
        self.phases: list[dict] = []
        self.info: dict = {}
        self._max = rss_bytes()
        self._lock = threading.Lock()
        self._names: dict[str, int] = {}
        threading.Thread(target=self._sample, daemon=True).start()

    def _sample(self) -> None:
        while True:
            value = rss_bytes()
            with self._lock:
                self._max = max(self._max, value)
            time.sleep(0.01)

    def mark(self, name: str, **extra) -> dict:
        now_t = time.perf_counter()
        rss = rss_bytes()
        with self._lock:
            phase_max, self._max = max(self._max, rss), rss
        count = self._names.get(name, 0)
        self._names[name] = count + 1
        record = {"phase": name if not count else f"{name} #{count + 1}", "end_s": now_t - self.start,
                  "seconds": now_t - self.last, "rss_mb": rss / MB, "phase_max_rss_mb": phase_max / MB,
                  "peak_rss_so_far_mb": status_kb("VmHWM") / 1024.0, **device_memory(), **extra}
        self.last = now_t
        self.phases.append(record)
        with open(self.path, "a") as f:
            f.write(json.dumps(record) + "\n")
        return record


def device_memory() -> dict:
    """GPU bytes in use now and at peak (None on CPU, whose memory is the RSS)."""
    if "jax" not in sys.modules:
        return {"device_in_use_mb": None, "device_peak_mb": None}
    import jax

    stats = jax.devices()[0].memory_stats()
    if not stats:
        return {"device_in_use_mb": None, "device_peak_mb": None}
    get = lambda k: stats[k] / MB if stats.get(k) is not None else None  # noqa: E731
    return {"device_in_use_mb": get("bytes_in_use"), "device_peak_mb": get("peak_bytes_in_use")}


def after(module, name: str, fn) -> None:
    """Replaces module.name by a wrapper that calls fn(result, args, kwargs) after the original."""
    original = getattr(module, name)

    @functools.wraps(original)
    def wrapper(*args, **kwargs):
        result = original(*args, **kwargs)
        fn(result, args, kwargs)
        return result

    setattr(module, name, wrapper)


def nbytes(*arrays) -> int:
    """Bytes the arrays hold in memory (a --view_data=disk file, `ViewRows`, holds none)."""
    from jaxdistill.io.view_rows import ViewRows

    return int(sum(getattr(a, "nbytes", 0) for a in arrays if a is not None and not isinstance(a, ViewRows)))


def child_run(args, flag_argv) -> int:
    """One case: pipeline.run(config) with phase marks; writes the result JSON to args.result."""
    rec = Recorder(Path(args.phases))
    from absl import flags

    from jaxdistill.engine import config as config_lib

    fv = flags.FlagValues()
    config_lib.define_flags(fv)
    fv(["bench_memory"] + list(flag_argv))
    config = config_lib.config_from_flags(fv)

    import jax
    import numpy as np

    from jaxdistill import datasets as datasets_mod
    from jaxdistill.engine import problem as problem_mod
    from jaxdistill import pipeline
    from jaxdistill.engine import loop
    from jaxdistill.evaluate import scoring
    from jaxdistill.errors import InputError
    from jaxdistill.scene.maps import MapChannels
    from jaxdistill.render import fragments as fragments_mod

    rec.mark("imports")
    channels = MapChannels(tuple(config.maps)).num_channels
    limit = args.max_gb * 2**30

    after(datasets_mod, "open_scene", lambda r, a, k: rec.mark("read scene", faces=r.mesh.num_faces,
                                                                  views=len(r.views)))
    after(fragments_mod, "compute_fragments", lambda r, a, k: rec.mark("fragments"))

    def on_space(space, a, k):
        layout = space.layout
        n, full, pyramid = space.num_texels, layout.full_size(), space.pyramid_size
        word = 4 * channels
        state = 3 * n * word
        step_need = state + n * word + (2 * pyramid * word if layout.mipmaps else 0)
        slices = [MapChannels(tuple(config.maps)).slice(m) for m in config.maps]
        widest = max(sl.stop - sl.start for sl in slices)
        # write_outputs holds one map's full pages at a time
        out_need = state + n * word + full * 4 * widest if args.outputs else 0
        tile_maps = sum(m.nbytes for m in space.tile_map) + sum(m.nbytes for ms in space.coarse_maps for m in ms)
        rec.info.update({
            "texels": n, "channels": channels, "params": n * channels, "full_texels": full,
            "full_params": full * channels, "pyramid": pyramid, "tile": space.tile,
            "page_sizes": list(layout.page_sizes), "sampler": config.sampler,
            "texels_adamw_mb": state / MB, "full_pages_adamw_mb": 3 * full * word / MB,
            "texel_space_maps_mb": tile_maps / MB,
            "estimated_min_step_mb": step_need / MB, "estimated_min_outputs_mb": out_need / MB})
        rss = rss_bytes()
        rec.mark("texel space", texels=n)
        need = rss + max(step_need, out_need)
        if need > limit and not args.force:
            raise MemoryGuard(f"needs at least {need / 2**30:.1f} GiB (RSS now {rss / 2**30:.1f} + state "
                              f"{state / 2**30:.1f} + gradient/pyramid {(step_need - state) / 2**30:.1f}"
                              + (f", outputs: full pages {full * word / 2**30:.1f}" if args.outputs else "")
                              + f" GiB) > --max_gb={args.max_gb:.1f}")

    after(problem_mod, "space_from_needs", on_space)
    after(problem_mod, "build_gather_plans", lambda r, a, k: rec.mark("gather plans"))
    after(problem_mod, "pixel_weights", lambda r, a, k: rec.mark("visibility"))
    after(problem_mod, "_views_prior", lambda r, a, k: rec.mark("prior (views targets)"))
    after(problem_mod, "_rgbx_prior", lambda r, a, k: rec.mark("prior (rgbx)"))

    def on_problem(p, a, k):
        def held(fragments):              # FragmentRows (--view_data): its arrays; a list: every view's
            if hasattr(fragments, "arrays"):
                return nbytes(*fragments.arrays.values())
            return sum(nbytes(f.triangle, f.barycentric, f.depth, f.uv, f.uv_grad, f.object_id) for f in fragments)

        frag_bytes = held(p.fragments) + (0 if p.native_fragments is p.fragments else held(p.native_fragments))
        prior_bytes = nbytes(getattr(p.prior, "target_images", None), getattr(p.prior, "photo_latents", None))
        rec.info["problem_arrays_mb"] = {
            "plans": nbytes(p.plan_index, p.plan_weight, p.plan_hit) / MB,
            "pixel_weights": nbytes(p.pixel_weight) / MB, "prior_view_data": prior_bytes / MB,
            "fragments": frag_bytes / MB, "counts": nbytes(p.counts) / MB}
        rec.info.update({"views": p.num_views, "height": p.height, "width": p.width})
        rec.mark("problem")

    after(pipeline, "build_problem", on_problem)
    after(loop, "init_state", lambda r, a, k: rec.mark("init state"))
    after(scoring, "evaluation_context", lambda r, a, k: rec.mark("evaluation context"))

    original_jit_step = loop.jit_step

    def jit_step(*a, **k):
        jitted, counter = original_jit_step(*a, **k)
        compiled = None

        def call(state, batch, frozen):
            nonlocal compiled
            if compiled is not None:
                return compiled(state, batch, frozen)
            compiled = jitted.lower(state, batch, frozen).compile()
            analysis = compiled.memory_analysis()
            xla = None
            if analysis is not None:
                xla = {key: getattr(analysis, key + "_size_in_bytes") / MB
                       for key in ("argument", "output", "alias", "temp", "generated_code")}
            rec.info["xla_step_mb"] = xla
            rec.mark("compile")
            out = jax.block_until_ready(compiled(state, batch, frozen))
            rec.mark("first step")
            return out

        return call, counter

    loop.jit_step = jit_step
    original_save = loop._save

    def save(store, state, *a, **k):
        jax.block_until_ready(state)
        rec.mark("steps")
        original_save(store, state, *a, **k)
        rec.mark("checkpoint")

    loop._save = save
    if args.outputs:
        after(pipeline, "write_outputs", lambda r, a, k: rec.mark("outputs"))
    else:
        pipeline.write_outputs = lambda *a, **k: {"outputs": "skipped by bench_memory (write_outputs stubbed)"}

    status, reason, summary = "ok", None, {}
    try:
        summary = pipeline.run(config, progress=False)
    except MemoryGuard as err:
        status, reason = "skipped", str(err)
    except InputError as err:          # the library's own refusal (problem.check_state_fits)
        status, reason = "refused", str(err)
    rec.mark("end")
    steps_phase = next((p for p in rec.phases if p["phase"] == "steps"), None)
    result = {
        "status": status, "reason": reason, "phases": rec.phases, **rec.info,
        "ru_maxrss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
        "backend": jax.default_backend(), "devices": [str(d) for d in jax.devices()],
        "device_kind": jax.devices()[0].device_kind, "jax": jax.__version__,
        "seconds_per_step_after_first": (steps_phase["seconds"] / (config.steps - 1)
                                         if steps_phase and config.steps > 1 else None),
        "setup_timings": summary.get("setup_timings"),
        "steps": config.steps, "views_per_step": config.views_per_step,
        "config": {k: v for k, v in config.as_dict().items()
                   if k in ("maps", "sampler", "texture_size", "max_texture_size", "render_size", "prior")},
        "prior_kind": summary.get("prior", {}).get("kind")}
    Path(args.result).write_text(json.dumps(result, default=lambda o: o.tolist() if hasattr(o, "tolist") else str(o)))
    return 0


# ----------------------------------------------------------------------------- child: room scene

def child_prep(args) -> int:
    """Writes the synthetic >= 1M-triangle room as a scene folder (mesh.glb, photos, targets): the
    package's capture room (`datasets.synthetic_capture`) seen by this benchmark's own square views."""
    from jaxdistill.datasets import synthetic_capture
    from jaxdistill.scene import shapes as synthetic

    mesh = synthetic_capture.capture_room_mesh(args.faces_per_side)
    cams = synthetic.room_cameras(args.views, resolution=args.resolution)
    summary = synthetic_capture.write_capture_room(args.scene_dir, mesh=mesh, cameras=cams, seed=0,
                                                   progress=False)
    print(json.dumps({k: summary[k] for k in ("faces", "objects", "views")}))
    return 0


# ----------------------------------------------------------------------------- parent

def run_child(cmd: list[str], log: Path, env: dict, limit_bytes: float, timeout_s: float) -> dict:
    """Runs one child; returns its exit, wall time and peak RSS (wait4 of that child alone)."""
    start = time.perf_counter()
    with open(log, "w") as out:
        proc = subprocess.Popen(cmd, cwd=ROOT, stdout=out, stderr=subprocess.STDOUT, env=env)
    polled, killed = 0, None
    while True:
        pid, status, usage = os.wait4(proc.pid, os.WNOHANG)
        if pid:
            break
        try:
            polled = max(polled, rss_bytes(proc.pid))
        except (OSError, IndexError):
            pass
        if killed is None and polled > limit_bytes:
            killed = f"RSS {polled / 2**30:.1f} GiB passed --max_gb"
            os.kill(proc.pid, signal.SIGKILL)
        elif killed is None and time.perf_counter() - start > timeout_s:
            killed = f"ran past --timeout_s={timeout_s:.0f}"
            os.kill(proc.pid, signal.SIGKILL)
        time.sleep(0.1)
    proc.returncode = os.waitstatus_to_exitcode(status)
    return {"exit": proc.returncode, "wall_s": time.perf_counter() - start, "killed": killed,
            "wait4_maxrss_mb": usage.ru_maxrss / 1024.0, "polled_max_rss_mb": polled / MB}


def read_phases(path: Path) -> list[dict]:
    if not path.is_file():
        return []
    return [json.loads(line) for line in path.read_text().splitlines() if line.strip()]


def log_tail(path: Path, lines: int = 15) -> str:
    try:
        return "\n".join(path.read_text(errors="replace").splitlines()[-lines:])
    except OSError:
        return ""


def prepare_room(args, work: Path, env: dict, limit: float) -> tuple[Path | None, dict]:
    scene_dir = Path(args.room_dir) if args.room_dir else work / "room_scene"
    stamp = scene_dir / "bench_memory.json"
    key = {"faces_per_side": args.faces_per_side, "views": args.views, "resolution": args.resolution}
    if stamp.is_file() and json.loads(stamp.read_text()) == key:
        return scene_dir, {"reused": True}
    shutil.rmtree(scene_dir, ignore_errors=True)
    scene_dir.mkdir(parents=True)
    cmd = [sys.executable, __file__, "--child=prep", f"--scene_dir={scene_dir}",
           f"--faces_per_side={args.faces_per_side}", f"--views={args.views}", f"--resolution={args.resolution}"]
    print(f"preparing the synthetic room scene in {scene_dir} ...", file=sys.stderr, flush=True)
    info = run_child(cmd, work / "room_prep.log", env, limit, args.timeout_s)
    if info["exit"] != 0:
        print(f"room preparation failed ({info}):\n{log_tail(work / 'room_prep.log')}", file=sys.stderr)
        return None, info
    stamp.write_text(json.dumps(key))
    return scene_dir, info


def case_flags(name: str, args, room_dir: Path | None, out_dir: Path) -> tuple[list[str], bool, str]:
    common = [f"--out_dir={out_dir}", f"--steps={args.steps}", "--ckpt_every=0", "--eval_every=0",
              "--renders=false", "--contact_views=0", f"--log_every={args.steps}"]
    if name in BEDROOM_CASES:
        label, extra, outputs = BEDROOM_CASES[name]
        return [f"--flagfile={ROOT / 'configs/bedroom.cfg'}", *extra, *common, *args.extra_flags], outputs, label
    label = (f"room: {args.views} views {args.resolution}^2, auto pages <= {args.room_max_texture_size}, "
             f"{args.room_sampler}")
    flags_ = [f"--scene={room_dir}", "--prior=views", "--maps=albedo,normal,roughness,metallic,irradiance",
              f"--views_per_step={min(32, args.views)}", "--texture_size=auto",
              f"--max_texture_size={args.room_max_texture_size}", f"--sampler={args.room_sampler}",
              *common, *args.extra_flags]
    return flags_, True, label


def run_case(name: str, args, work: Path, env: dict, limit: float, room_dir: Path | None) -> dict:
    out_dir = work / name
    shutil.rmtree(out_dir, ignore_errors=True)
    flags_, outputs, label = case_flags(name, args, room_dir, out_dir)
    result_path, phases_path = work / f"{name}.result.json", work / f"{name}.phases.jsonl"
    for p in (result_path, phases_path):
        p.unlink(missing_ok=True)
    child_env = dict(env)
    if not args.use_cache:
        cache = work / f"cache_{name}"
        shutil.rmtree(cache, ignore_errors=True)
        child_env["JAXDISTILL_CACHE"] = str(cache)
    cmd = [sys.executable, __file__, "--child=run", f"--result={result_path}", f"--phases={phases_path}",
           f"--max_gb={args.max_gb}", f"--outputs={int(outputs)}"] + (["--force"] if args.force else []) + ["--"] + flags_
    print(f"[{name}] {label} ...", file=sys.stderr, flush=True)
    info = run_child(cmd, work / f"{name}.log", child_env, limit, args.timeout_s)
    if result_path.is_file():
        result = json.loads(result_path.read_text())
    else:
        result = {"status": "killed" if info["killed"] else "failed", "phases": read_phases(phases_path),
                  "reason": info["killed"] or log_tail(work / f"{name}.log")}
    result.update({"case": name, "label": label, "outputs": outputs, "flags": flags_, **info})
    if room_dir is not None and name == "room_1m":
        result["room"] = {"faces_per_side": args.faces_per_side, "views": args.views, "resolution": args.resolution}
    print(f"[{name}] {result['status']} in {info['wall_s']:.0f} s, peak RSS {info['wait4_maxrss_mb'] / 1024:.2f} GiB",
          file=sys.stderr, flush=True)
    return result


def fmt_mb(x) -> str:
    if x is None:
        return "-"
    return f"{x / 1024:.2f} GB" if x >= 1024 else f"{x:.0f} MB"


def fmt_count(x) -> str:
    if x is None:
        return "-"
    return f"{x / 1e6:.1f}M" if x >= 1e5 else str(x)


def print_table(results: list[dict]) -> None:
    names = [r["case"] for r in results]
    width = max(14, *(len(n) for n in names))
    rows: list[tuple[str, list[str]]] = []

    def row(label, values):
        rows.append((label, [str(v) for v in values]))

    row("status", [r["status"] for r in results])
    row("wall", [f"{r['wall_s']:.0f} s" for r in results])
    row("views x size (per step)", [f"{r.get('views', '-')} x {r.get('width', '?')}x{r.get('height', '?')} "
                                    f"({r.get('views_per_step', '-')})" if r.get("views") else "-" for r in results])
    row("pages (side min-max)", [f"{len(r['page_sizes'])} ({min(r['page_sizes'])}-{max(r['page_sizes'])})"
                                 if r.get("page_sizes") else "-" for r in results])
    row("sampler / tile", [f"{r.get('sampler', '-')} / {r.get('tile', '-')}" for r in results])
    row("texels N", [fmt_count(r.get("texels")) for r in results])
    row("channels C", [r.get("channels", "-") for r in results])
    row("params N x C", [fmt_count(r.get("params")) for r in results])
    row("texels + AdamW (3x fp32)", [fmt_mb(r.get("texels_adamw_mb")) for r in results])
    row("full pages F x C", [fmt_count(r.get("full_params")) for r in results])
    row("full pages + AdamW", [fmt_mb(r.get("full_pages_adamw_mb")) for r in results])
    row("compact / full", [f"{r['texels'] / r['full_texels']:.3f}" if r.get("full_texels") else "-" for r in results])
    row("pyramid entries", [fmt_count(r.get("pyramid")) for r in results])
    row("texel-space tile maps", [fmt_mb(r.get("texel_space_maps_mb")) for r in results])
    for key in ("plans", "pixel_weights", "prior_view_data", "fragments"):
        row(f"problem: {key}", [fmt_mb((r.get("problem_arrays_mb") or {}).get(key)) for r in results])
    for key in ("argument", "output", "temp"):
        row(f"XLA step {key}", [fmt_mb((r.get("xla_step_mb") or {}).get(key)) for r in results])
    row("est. min need (step)", [fmt_mb(r.get("estimated_min_step_mb")) for r in results])
    row("est. min need (outputs)", [fmt_mb(r.get("estimated_min_outputs_mb")) if r.get("outputs") else "stubbed"
                                    for r in results])
    order: list[str] = []
    for r in results:
        for p in r.get("phases", []):
            if p["phase"] not in order:
                order.append(p["phase"])
    order = [p for p in order if p != "end"] + ["end"] * ("end" in order)   # a stubbed phase is never seen
    for phase in order:
        cells = []
        for r in results:
            p = next((p for p in r.get("phases", []) if p["phase"] == phase), None)
            cells.append("-" if p is None else f"{fmt_mb(p['rss_mb'])} ({fmt_mb(p['phase_max_rss_mb'])}) {p['seconds']:.0f}s")
        row(f"RSS after {phase}", cells)
    row("peak RSS (child, ru_maxrss)", [fmt_mb(r.get("ru_maxrss_mb")) for r in results])
    row("peak RSS (wait4 of child)", [fmt_mb(r.get("wait4_maxrss_mb")) for r in results])
    row("GPU peak", [fmt_mb(max([p["device_peak_mb"] for p in r.get("phases", []) if p.get("device_peak_mb")],
                                default=None)) for r in results])
    row("s / step (after the first)", [f"{r['seconds_per_step_after_first']:.2f}"
                                       if r.get("seconds_per_step_after_first") else "-" for r in results])
    label_w = max(len(label) for label, _ in rows)
    col_w = max(width, *(len(c) for _, cells in rows for c in cells))
    print(f"{'':{label_w}}  " + "  ".join(f"{n:>{col_w}}" for n in names))
    for label, cells in rows:
        print(f"{label:{label_w}}  " + "  ".join(f"{c:>{col_w}}" for c in cells))
    print("RSS cells: RSS when the phase ended (largest RSS sampled during it) and the phase's seconds.")
    for r in results:
        if r.get("reason"):
            print(f"{r['case']}: {r['status']}: {r['reason']}")


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--cases", default=",".join(ALL_CASES), help=f"comma-separated, of {','.join(ALL_CASES)}")
    p.add_argument("--steps", type=int, default=3, help="distillation steps per case (the first compiles)")
    p.add_argument("--faces_per_side", type=int, default=300, help="room wall subdivisions (2 n^2 faces per wall); "
                   "300 gives 1.13M triangles")
    p.add_argument("--views", type=int, default=8, help="views of the synthetic room")
    p.add_argument("--resolution", type=int, default=512, help="side of the synthetic room's square views")
    p.add_argument("--room_sampler", choices=("bilinear", "trilinear"), default="bilinear")
    p.add_argument("--room_max_texture_size", type=int, default=4096)
    p.add_argument("--room_dir", help="where to write (or reuse) the synthetic room scene; default: in the work dir")
    p.add_argument("--extra_flags", nargs="*", default=[], help="more jaxdistill.main flags for every case")
    p.add_argument("--max_gb", type=float, default=None,
                   help="memory a case may use (guard and kill); default 90%% of MemAvailable at start")
    p.add_argument("--force", action="store_true", help="run cases the guard would skip (the kill limit stays)")
    p.add_argument("--timeout_s", type=float, default=1800.0, help="per child")
    p.add_argument("--use_cache", action="store_true", help="use your fragment cache instead of a fresh one")
    p.add_argument("--work_dir", help="outputs, logs and the room scene; default: a temp dir removed at the end")
    p.add_argument("--keep_work", action="store_true", help="keep the temp work dir")
    p.add_argument("--json", action="store_true", help="print every figure as one JSON line last")
    # child modes
    p.add_argument("--child", choices=("run", "prep"), help=argparse.SUPPRESS)
    p.add_argument("--result", help=argparse.SUPPRESS)
    p.add_argument("--phases", help=argparse.SUPPRESS)
    p.add_argument("--outputs", type=int, default=1, help=argparse.SUPPRESS)
    p.add_argument("--scene_dir", help=argparse.SUPPRESS)
    return p.parse_known_args(argv)


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    own, flag_argv = (argv[:argv.index("--")], argv[argv.index("--") + 1:]) if "--" in argv else (argv, [])
    args, unknown = parse_args(own)
    if args.child == "run":
        return child_run(args, flag_argv + unknown)
    if unknown:
        print(f"unknown arguments {unknown}", file=sys.stderr)
        return 2
    if args.child == "prep":
        return child_prep(args)

    cases = [c.strip() for c in args.cases.split(",") if c.strip()]
    bad = [c for c in cases if c not in ALL_CASES]
    if bad:
        print(f"unknown cases {bad}; choose from {','.join(ALL_CASES)}", file=sys.stderr)
        return 2
    mach = machine()
    if args.max_gb is None:
        args.max_gb = 0.9 * mach["ram_available_gb"]
    limit = args.max_gb * 2**30
    work = Path(args.work_dir) if args.work_dir else Path(tempfile.mkdtemp(prefix="bench_memory_"))
    work.mkdir(parents=True, exist_ok=True)
    env = dict(os.environ)
    env.setdefault("TF_CPP_MIN_LOG_LEVEL", "1")
    started = time.perf_counter()
    results = []
    room_dir, prep = None, None
    try:
        if "room_1m" in cases:
            room_dir, prep = prepare_room(args, work, env, limit)
        for name in cases:
            if name == "room_1m" and room_dir is None:
                results.append({"case": name, "status": "failed", "reason": "room preparation failed",
                                "wall_s": 0.0, "phases": []})
                continue
            results.append(run_case(name, args, work, env, limit, room_dir))
    finally:
        if not args.work_dir and not args.keep_work:
            shutil.rmtree(work, ignore_errors=True)
        else:
            print(f"work dir kept: {work}", file=sys.stderr)
    backend = next((f"{r['backend']} ({', '.join(r['devices'])}; {r['device_kind']}), jax {r['jax']}"
                    for r in results if r.get("backend")), "unknown (no child reached the end)")
    print(f"machine: {mach['cores']} cores ({mach['cores_usable']} usable), RAM {mach['ram_gb']:.1f} GiB "
          f"({mach['ram_available_gb']:.1f} GiB available at start"
          + (f", cgroup limit {mach['cgroup_limit_gb']:.1f} GiB" if mach["cgroup_limit_gb"] else "")
          + f"), {mach['cpu']}, Python {mach['python']}")
    print(f"jax backend: {backend}")
    print(f"guard / kill limit per case: {args.max_gb:.1f} GiB; steps per case: {args.steps}; "
          f"total {time.perf_counter() - started:.0f} s"
          + (f"; room scene prepared in {prep['wall_s']:.0f} s" if prep and "wall_s" in prep else ""))
    print()
    print_table(results)
    if args.json:
        print(json.dumps({"machine": mach, "max_gb": args.max_gb, "steps": args.steps, "room_prep": prep,
                          "cases": results}))
    return 0 if all(r["status"] in ("ok", "skipped", "refused") for r in results) else 1


if __name__ == "__main__":
    sys.exit(main())
