"""The main job's step, stage by stage, as it runs: a profile of the compiled step itself.

    python scripts/bench_profile.py --flagfile=configs/bedroom.cfg [main-job flags] [--profile_steps=5]
        [--profile_json=FILE] [--profile_trace=DIR]

Builds the main job's problem (`build_problem`) and its step compiled ahead (`loop.prepare_step`,
as `python -m jaxdistill.main` does), runs two cycles of --reuse_steps steps to warm up, then
--profile_steps cycles (with --reuse_steps=2: a step with the prior's pass, then one reusing its
x-hat-0), timing each kind of step apart (medians). Then the first two steps of one more cycle (one
of each kind; with --reuse_steps=1, two with the prior) under `jax.profiler`: every XLA operation's
time on the host's threads, each given to a stage by the name JAX recorded for its source in the
compiled program (`op_name`: the networks' modules, and the named scopes of `render.sampler` and
`engine.step`):

  taps (gathers)                 the pyramid's rows each pixel's taps read (`sampler` "taps")
  taps' transpose (scatter-adds)  their gradient: scatter-adds into the texels and the pyramid
  taps weighted                  the taps' weighting into pixels, and its transpose
  pyramid                        the mip pyramid, and its transpose (its pull-back to the texels)
  photo term                     the photos re-rendered and compared, with its gradient
  rest of the forward / backward  what is left of the differentiated part (the renders' rotation,
                                 the SDS loss, the smoothness terms)
  VAE encode / UNet / VAE decode  the prior's networks (only in the steps that run them)
  prior's pass (other)           the rest of the prior's branch (its noise, the schedule); with
                                 --reuse_steps=1 there is no branch and these go to "other"
  AdamW and the finite gate      the update and the gate that keeps a non-finite step out
  metrics (gradient norm)        the step's metrics, the gradient's norm most of it
  other / unlabelled             anything else, by JAX's name or, with none, XLA's kind of op

An operation XLA made without a name (a tree reduction's first pass) takes its operand's; a fusion
holding a gather outside the named scopes counts as taps. The stage times are thread times: two
threads at once count twice, and the time between operations (the runtime's own) counts nowhere,
so their sum is not the step's wall time (on the default bedroom step with 2 threads it fell below
it). One step of each kind is traced, so a stage swings between runs (by up to 3x for a small
stage); the medians of whole steps are the figures to compare. XLA's cost analysis gives the
step's FLOPs (both kinds in one program: the prior's branch counted once). Prints the table;
--profile_json writes it, with each traced step's longest operations; --profile_trace keeps the
profiler's trace (TensorBoard's or Perfetto's viewer reads it).
"""

from __future__ import annotations

import collections
import glob
import gzip
import json
import re
import statistics
import sys
import tempfile
import time
from pathlib import Path

from absl import app, flags

import jaxdistill  # noqa: F401  (the package's XLA flags, as the main job)
from jaxdistill.engine import config as config_lib

config_lib.define_flags(flags.FLAGS, main_module=True)
flags.DEFINE_integer("profile_steps", 5, "timed cycles of --reuse_steps steps")
flags.DEFINE_string("profile_json", None, "write the table as JSON here")
flags.DEFINE_string("profile_trace", None, "keep the profiler's trace in this folder (default: a temporary one)")

STAGES = ("taps (gathers)", "taps' transpose (scatter-adds)", "taps weighted", "pyramid", "photo term",
          "rest of the forward", "rest of the backward", "VAE encode", "UNet", "VAE decode", "prior's pass (other)",
          "AdamW and the finite gate", "metrics (gradient norm)", "other")
TOP_OPS = 15


def _scope(op_name: str, name: str) -> bool:
    """`name` is a named scope on the way to the operation (`jax.named_scope`: .../name/... or
    jvp(name), transpose(jvp(name)))."""
    return re.search(rf"[(/]{re.escape(name)}[)/]", op_name) is not None


def stage_of(op_name: str, instruction: str, gathers: bool = False) -> str:
    """The stage of an XLA operation from JAX's name for its source (`op_name`: the networks'
    modules and the step's named scopes, `sampler` and `engine.step`), else its kind. `gathers`:
    the operation reads rows by index (a gather, or a fusion holding one) where no scope says more."""
    backward = "transpose(" in op_name
    if "AutoencoderKL.encode" in op_name:
        return "VAE encode"
    if "AutoencoderKL.decode" in op_name:
        return "VAE decode"
    if "UNet" in op_name:
        return "UNet"
    if "/cond/" in op_name:                  # the prior's branch outside its networks: noise, schedule
        return "prior's pass (other)"
    if _scope(op_name, "taps"):
        return "taps' transpose (scatter-adds)" if backward else "taps (gathers)"
    for scope, stage in (("weighting", "taps weighted"), ("pyramid", "pyramid"), ("photo_term", "photo term"),
                         ("update", "AdamW and the finite gate"), ("metrics", "metrics (gradient norm)")):
        if _scope(op_name, scope):
            return stage
    if gathers and "jvp(" in op_name and not backward:
        return "taps (gathers)"
    if backward:
        return "rest of the backward"
    if "jvp(" in op_name:
        return "rest of the forward"
    if op_name:
        return "other"
    return "unlabelled: " + re.sub(r"^(wrapped_|bitcast_)*|(\.\d+)+$", "", instruction)


def gathering(hlo_text: str) -> set[str]:
    """The instructions that gather: a gather itself, or a fusion whose computation holds one."""
    bodies, current = {}, None
    for line in hlo_text.splitlines():
        head = re.match(r"^(?:ENTRY )?%?([\w.\-]+) .*\{$", line)
        if head:
            current = head.group(1)
            bodies[current] = []
        elif line.startswith("}"):
            current = None
        elif current is not None:
            bodies[current].append(line)
    holds = {name for name, lines in bodies.items() if any(re.search(r"\bgather\(", x) for x in lines)}
    out = set()
    for lines in bodies.values():
        for line in lines:
            found = re.match(r"^\s*(?:ROOT )?%?([\w.\-]+) = ", line)
            called = re.search(r"calls=%?([\w.\-]+)", line)
            if found and (re.search(r"\bgather\(", line) or (called and called.group(1) in holds)):
                out.add(found.group(1))
    return out


def op_names(hlo_text: str) -> dict[str, str]:
    """Instruction name -> JAX's op_name, from the compiled program's text. An instruction XLA made
    without one (a tree reduction's first pass, a fusion of such) takes that of its first operand
    that has one from the step's code (`jit(...)/...`; a parameter's is its argument's name)."""
    lines = {m.group(1): m.group(2) for m in re.finditer(r"^\s*(?:ROOT )?%?([\w.\-]+) = ([^\n]*)$", hlo_text, re.M)}
    named = {}
    for name, line in lines.items():
        found = re.search(r"metadata=\{[^}]*?op_name=\"([^\"]*)\"", line)
        if found:
            named[name] = found.group(1)
    for _ in range(3):                         # operands of operands, a few levels
        for name, line in lines.items():
            if name not in named:
                operands = re.findall(r"%([\w.\-]+)", line)
                source = next((named[o] for o in operands if named.get(o, "").startswith("jit(")), None)
                if source is not None:
                    named[name] = source
    return named


def stage_seconds(trace_file: Path, names: dict[str, str], gathers: set[str], module: str) -> list[dict]:
    """Per execution of the program `module` in the trace (XLA's run id), in the order they ran:
    ({stage: thread seconds} of its operations, its TOP_OPS longest operations)."""
    with gzip.open(trace_file) as f:
        events = [e for e in json.load(f)["traceEvents"] if e.get("ph") == "X" and "dur" in e
                  and e.get("args", {}).get("hlo_module") == module]
    runs = collections.defaultdict(list)
    for e in events:
        runs[e["args"].get("run_id")].append(e)
    out = []
    for run in sorted(runs.values(), key=lambda es: min(e["ts"] for e in es)):
        totals, ops = collections.Counter(), collections.Counter()
        for e in run:
            op = e["args"].get("hlo_op", e["name"])
            totals[stage_of(names.get(op, ""), op, op in gathers)] += e["dur"] / 1e6
            ops[op] += e["dur"] / 1e6
        top = [{"op": op, "s": s, "op_name": names.get(op, ""), "stage": stage_of(names.get(op, ""), op, op in gathers)}
               for op, s in ops.most_common(TOP_OPS)]
        out.append((dict(totals), top))
    return out


def main(argv) -> int:
    del argv
    import jax

    from jaxdistill.engine import distributed, loop
    from jaxdistill.engine.problem import build_problem

    fv = flags.FLAGS
    if fv.profile_steps < 1:
        raise app.UsageError("--profile_steps must be >= 1")
    config = config_lib.config_from_flags(fv)
    problem = build_problem(config)
    prepared = loop.prepare_step(config, problem)
    stepper, compiled = prepared.stepper, prepared.compiled
    cost = compiled.cost_analysis()
    cost = cost[0] if isinstance(cost, (list, tuple)) else cost
    flops = float(cost.get("flops", 0.0)) if cost else 0.0
    hlo = compiled.as_text()
    names = op_names(hlo)
    state = jax.device_put(stepper.state, stepper.replicated)
    frozen = jax.device_put(problem.frozen, stepper.replicated)
    cycle = config.reuse_steps

    def kind(step: int) -> str:
        return "prior" if cycle == 1 or step % cycle == 0 else "reused"

    def run(step: int):
        nonlocal state
        batch = distributed.place_batch(problem.batch, loop.batch_views(problem, config, step), stepper.by_view)
        jax.block_until_ready(batch)
        start = time.perf_counter()
        state, _ = compiled(state, batch, frozen)
        jax.block_until_ready(state)
        return start, time.perf_counter()

    seconds = collections.defaultdict(list)
    warm = 2 * cycle
    for step in range(warm + fv.profile_steps * cycle):
        start, end = run(step)
        if step >= warm:
            seconds[kind(step)].append(end - start)
    trace_dir = Path(fv.profile_trace or tempfile.mkdtemp(prefix="jaxdistill-profile-"))
    first = warm + fv.profile_steps * cycle
    jax.profiler.start_trace(str(trace_dir))
    clock = []                   # each traced step's kind
    for step in range(first, first + 2):
        run(step)
        clock.append(kind(step))
    jax.profiler.stop_trace()
    trace_file = Path(sorted(glob.glob(str(trace_dir / "**" / "*.trace.json.gz"), recursive=True))[-1])
    module = re.match(r"HloModule (\S+?),", hlo).group(1)
    traced = stage_seconds(trace_file, names, gathering(hlo), module)
    if len(traced) != len(clock):
        raise SystemExit(f"the trace in {trace_file} holds {len(traced)} runs of {module}, not the {len(clock)} "
                         "steps traced: nothing else should run the step while it is profiled")
    by_kind = {k: s for k, (s, _) in zip(clock, traced)}         # with --reuse_steps=1: the second prior step
    top_ops = {k: top for k, (_, top) in zip(clock, traced)}
    stages = list(STAGES) + sorted({s for v in by_kind.values() for s in v} - set(STAGES))
    table = {"config": {"reuse_steps": cycle, "views_per_step": config.views_per_step,
                        "render_size": config.render_size, "maps": list(config.maps),
                        "texels": int(problem.space.num_texels), "channels": int(problem.channels.num_channels),
                        "backend": jax.default_backend()},
             "compile_s": prepared.seconds, "step_gflop": flops / 1e9,
             "step_s": {k: statistics.median(v) for k, v in seconds.items()},
             "stages_s": {k: {s: v.get(s, 0.0) for s in stages} for k, v in by_kind.items()},
             "top_ops": top_ops,
             "command": " ".join(sys.argv)}
    kinds = list(by_kind)
    print(f"{problem.space.num_texels} texels x {problem.channels.num_channels} channels, {config.views_per_step} views "
          f"a step at render size {config.render_size}, --reuse_steps={cycle}, {jax.default_backend()}; "
          f"compile {prepared.seconds:.1f} s; {flops / 1e9:.1f} GFLOP per step (XLA, both branches' program)")
    print("seconds per step (median): " + ", ".join(f"{k} {v:.3f}" for k, v in table["step_s"].items()))
    print(f"{'stage (thread seconds of one traced step)':44s}" + "".join(f"{k:>10s}" for k in kinds))
    for s in stages:
        if s in STAGES or max(by_kind[k].get(s, 0.0) for k in kinds) >= 0.0005:     # the JSON has every one
            print(f"{s:44s}" + "".join(f"{by_kind[k].get(s, 0.0):10.3f}" for k in kinds))
    print(f"{'all operations':44s}" + "".join(f"{sum(by_kind[k].values()):10.3f}" for k in kinds))
    if fv.profile_json:
        Path(fv.profile_json).write_text(json.dumps(table, indent=1))
    return 0


if __name__ == "__main__":
    app.run(main)
