"""The step loop: the state set up (or restored), steps run with checkpoints, stopped cleanly.

`run_loop` is the middle of the main job (`jaxdistill.pipeline.run`). The loop is thin: view ids
for a step are a function of (seed, step); the host assembles that batch while the device runs
the previous step (JAX dispatch is asynchronous); metrics are fetched every --log_every steps,
before an evaluation and before a checkpoint. `setup_step` is what it steps with (settings,
optimizers, the step-0 state, the jitted step), for benchmarks that time the step alone;
`prepare_step` sets it up and compiles the step ahead (the main job does so in a thread beside
the evaluation's set-up); `LoopHooks` lets a benchmark time the loop itself (scripts/speed_vs_error.py) without a copy of it.
"""

from __future__ import annotations

import collections
import dataclasses
import json
import math
import time
from pathlib import Path
from typing import Callable

import jax
import numpy as np
import optax
from absl import logging
from tqdm.auto import tqdm

from jaxdistill.engine import distributed
from jaxdistill.engine.config import DistillConfig, resumable_flags
from jaxdistill.engine.problem import Problem
from jaxdistill.engine.step import (DistillState, StepSettings, TraceCounter, data_mesh, init_state, initial_align,
                                    initial_reused, jit_step, make_optimizer, make_step)
from jaxdistill.errors import InputError
from jaxdistill.io import checkpoint


class NonFiniteLoss(RuntimeError):
    """The loss or gradient became NaN/inf; the last good state was checkpointed."""


def step_settings(config: DistillConfig, problem: Problem) -> StepSettings:
    """The step's static settings for this problem (`StepSettings.from_config`). The mip pyramid is
    split on the CPU only: there it saves a texel-sized array and is no slower; on an H200 the split
    step took 2.2-2.7x the time, and with XLA's deterministic GPU scatter more memory, not less
    (docs/benchmarks.md §10)."""
    settings = StepSettings.from_config(config, problem.channels, problem.height, problem.width,
                                        problem.prior.num_train_timesteps, problem.photo_shape,
                                        problem.photos.scale if problem.photos is not None else None)
    return dataclasses.replace(settings, split_pyramid=jax.default_backend() == "cpu")


def batch_views(problem: Problem, config: DistillConfig, step: int) -> np.ndarray:
    """The views of `step`: a function of (seed, step // reuse_steps, the view shares), so the steps
    that reuse one x_pred see the views it was computed for, and a resumed run samples the same."""
    return problem.view_ids(step // config.reuse_steps, config.views_per_step, config.seed,
                            distributed.shares_of_run(config.view_shares))


def first_batch(problem: Problem, config: DistillConfig) -> dict:
    """A host batch of the run's shapes, which the step is traced for: step 0's, or in a process
    holding its share of the views alone (`Problem.held`), its own rows of step 0 repeated to the
    batch's size (nothing but their shapes is read)."""
    views = batch_views(problem, config, 0)
    if problem.held is not None:
        views = np.resize(views[np.isin(views, problem.held)], len(views))
    return problem.batch(views)


@dataclasses.dataclass
class Stepper:
    """What the loop steps with, set up once for a problem: the step's static settings, the
    optimizers (texels; per-view gains with --align=gain, else None), the step-0 state (on the
    host), the jitted step with its trace counter, and the shardings (state and constants
    replicated, batches split over the devices by view)."""

    settings: StepSettings
    optimizer: optax.GradientTransformation
    align_optimizer: optax.GradientTransformation | None
    state: DistillState
    step_fn: Callable
    traces: TraceCounter
    replicated: jax.sharding.NamedSharding
    by_view: jax.sharding.NamedSharding


def setup_step(config: DistillConfig, problem: Problem, first_batch: dict, *,
               optimizer: optax.GradientTransformation | None = None,
               settings: StepSettings | None = None) -> Stepper:
    """The `Stepper` of `config` and `problem`; `first_batch` (a host batch, e.g. of step 0) gives
    the shapes the step is traced for and the state's reused x_pred (--reuse_steps) is shaped by.
    `optimizer` and `settings` replace the config's (a benchmark comparing forms of the step)."""
    mesh = data_mesh(jax.devices())
    if optimizer is None:
        optimizer = make_optimizer(config.lr, config.weight_decay, config.lr_schedule, config.steps)
    align_optimizer = (make_optimizer(config.lr, 0.0, config.lr_schedule, config.steps) if config.align == "gain"
                       else None)
    if settings is None:
        settings = step_settings(config, problem)
    texels = problem.initial_texels()
    state = init_state(texels, optimizer, config.seed,
                       initial_reused(problem.prior, settings, texels, first_batch, problem.frozen),
                       initial_align(problem.num_views, problem.channels, align_optimizer))
    step_fn, traces = jit_step(make_step(problem.prior, settings, optimizer, align_optimizer), mesh, first_batch, state,
                               problem.frozen)
    return Stepper(settings, optimizer, align_optimizer, state, step_fn, traces,
                   jax.sharding.NamedSharding(mesh, jax.sharding.PartitionSpec()),
                   jax.sharding.NamedSharding(mesh, jax.sharding.PartitionSpec("data")))


@dataclasses.dataclass
class PreparedStep:
    """A run's `Stepper` and its step compiled ahead for the run's shapes (`prepare_step`)."""

    stepper: Stepper
    compiled: Callable
    seconds: float               # what setting up, tracing and compiling took


def prepare_step(config: DistillConfig, problem: Problem) -> PreparedStep:
    """What `run_loop` does before its first step (`setup_step`, which makes the step-0 state), and
    the step traced and compiled for the shardings and shapes of the run's state, batches and
    constants (`lower().compile()` on their abstract values). The main job calls it in a
    thread while the evaluation context is built: XLA's compilation (most of the first step's
    time with the rgbx prior) holds no Python lock, so it runs beside that NumPy work."""
    start = time.perf_counter()
    first = first_batch(problem, config)
    stepper = setup_step(config, problem, first)

    def abstract(value, sharding):
        return jax.ShapeDtypeStruct(np.shape(value), value.dtype, sharding=sharding,
                                    weak_type=bool(getattr(value, "weak_type", False)))

    lowered = stepper.step_fn.lower(jax.tree.map(lambda x: abstract(x, stepper.replicated), stepper.state),
                                    jax.tree.map(lambda x: abstract(x, stepper.by_view), first),
                                    jax.tree.map(lambda x: abstract(x, stepper.replicated), problem.frozen))
    compiled = lowered.compile()
    return PreparedStep(stepper, compiled, time.perf_counter() - start)


@dataclasses.dataclass(frozen=True)
class LoopHooks:
    """Ways into `run_loop` for measuring it; the main job passes none, and the defaults change
    nothing.

    before_steps(step_fn, state, batch, frozen) -> step function: called once, when the state is
      restored and placed on the devices with the constants, before the first step, with the
      jitted step and a placed batch of the run's shapes; the loop then calls what it returns as
      it would the jitted step, e.g. `step_fn.lower(state, batch, frozen).compile()` so that the
      compilation is timed apart from the steps.
    after_fetch(steps_done, metrics): called whenever step metrics come back from the device
      (every --log_every steps and at the end), with the number of steps done and the fetched
      metrics of each step since the last fetch (dicts of host values).
    checkpoints: False saves no checkpoint at all (periodic, final, or on a non-finite loss): a
      throw-away run that cannot be resumed and writes nothing to --out_dir.
    """

    before_steps: Callable[..., Callable] | None = None
    after_fetch: Callable[[int, list], None] | None = None
    checkpoints: bool = True


class StepClock:
    """Times `run_loop` from outside, for benchmarks: `hooks()` compiles the step before the first step
    (`compile_s`, from `start`, when the state and constants are on the devices) and marks the time of
    every metrics fetch (`marks`: (steps done, time), the first (0, compiled)); `seconds_per_step()`
    gives each window between fetches per step; `exclude_since_mark()` moves the last mark to now, so
    that time spent after a fetch on something else (an evaluation) is in no window."""

    def __init__(self):
        self.start: float | None = None
        self.compile_s: float | None = None
        self.marks: list[tuple[int, float]] = []

    def _before_steps(self, step_fn, state, batch, frozen):
        jax.block_until_ready((state, frozen))
        self.start = time.perf_counter()
        compiled = step_fn.lower(state, batch, frozen).compile()
        self.compile_s = time.perf_counter() - self.start
        self.marks.append((0, time.perf_counter()))
        return compiled

    def _after_fetch(self, done: int, _) -> None:
        self.marks.append((done, time.perf_counter()))

    def hooks(self, checkpoints: bool = False) -> LoopHooks:
        return LoopHooks(before_steps=self._before_steps, after_fetch=self._after_fetch, checkpoints=checkpoints)

    def exclude_since_mark(self) -> None:
        self.marks[-1] = (self.marks[-1][0], time.perf_counter())

    def seconds_per_step(self) -> list[float]:
        return [(b - a) / (j - i) for (i, a), (j, b) in zip(self.marks, self.marks[1:]) if j > i]


# Steps dispatched ahead of the one running. JAX dispatches a step and returns before it has run (on
# the CPU too), so the loop would otherwise place batch after batch up to the next metrics fetch
# (--log_every steps), each held in memory until its step runs: about 0.3 GB a batch of 8 views of
# 876x584 and 1.2 GB at 1752x1168. One step ahead still reads the next batch while a step runs.
PREFETCH_STEPS = 1


def _history_path(out: Path) -> Path:
    return out / "checkpoints" / "history.json"


# flags added after checkpoints were first written, at the values that keep the earlier
# behaviour: a checkpoint that does not record them resumes when the run leaves them so
# (view_shares is recorded resolved: one share drew from every view, as every run did before shares)
ADDED_FLAG_DEFAULTS = {"view_shares": 1, "reuse_steps": 1, "align": "none",
                       "align_strength": DistillConfig.align_strength, "photo_weight": 0.0, "photo_size": 0,
                       "photo_space": DistillConfig.photo_space,
                       "photo_loss": DistillConfig.photo_loss, "photo_scale": DistillConfig.photo_scale,
                       "irradiance_smoothness": 0.0, "irradiance_sds_weight": 1.0, "albedo_smoothness": 0.0,
                       "photo_noise_ref": 0.0,
                       # --scene=FORMAT:PATH's loader options: like --scene they decide the mesh, its UVs, the
                       # views and their exposure, so a resume must keep them (None/defaults: the loader's own)
                       "mesh": None, "exposure": DistillConfig.exposure, "uv": DistillConfig.uv,
                       "max_views": DistillConfig.max_views, "max_page_size": DistillConfig.max_page_size}


def recorded_config(config: DistillConfig, prior_kind: str) -> dict:
    """The flags saved with a checkpoint, plus the prior --prior=auto resolved to; --view_shares
    as resolved (0: the process count), since the views a step draws depend on it."""
    return {**config.as_dict(), "prior_kind": prior_kind,
            "view_shares": distributed.shares_of_run(config.view_shares)}


def _save(store, state, recorded: dict, history: dict, out: Path) -> None:
    step = int(jax.device_get(state.step))
    store.save(step, state, recorded)          # every process (orbax's multi-process protocol)
    if distributed.is_primary():
        _history_path(out).write_text(json.dumps(history))


def check_before_compute(config: DistillConfig, out: Path, choice) -> int | None:
    """Flag problems found without any compute: the RGB<->X folder (layout, in_channels, every
    weights file's header), device split, --resume (the checkpoint must read back), an existing
    run. Returns the checkpoint step to resume from (None for a fresh run)."""
    if choice.kind == "rgbx":
        from jaxdistill.models import convert

        convert.check_rgbx_folder(choice.folder, "--rgbx_dir")
    devices = jax.devices()
    if jax.process_count() > 1 and config.view_shares not in (0, jax.process_count()):
        raise InputError.single("flags", "--view_shares", f"is {config.view_shares}, but each of the "
                                f"{jax.process_count()} processes holds one share of the views; leave it at 0")
    if jax.device_count() != jax.local_device_count() * jax.process_count():
        raise InputError.single("flags", "--num_processes", f"the {jax.process_count()} processes have "
                                f"{jax.device_count()} devices in all and this one {jax.local_device_count()}: each "
                                "process places its share's rows of a step on its own devices, so give every process "
                                "as many (e.g. one process per GPU, or every GPU of a host)")
    if config.views_per_step % len(devices):
        raise InputError.single("flags", "--views_per_step", f"{config.views_per_step} does not split over "
                                f"{len(devices)} devices; use a multiple of {len(devices)}")
    if jax.process_count() > 1:      # process q's devices must hold rows q*B/N.. of a step: its share's views
        q, n, b = jax.process_index(), jax.process_count(), config.views_per_step
        by_view = jax.sharding.NamedSharding(data_mesh(devices), jax.sharding.PartitionSpec("data"))
        rows = distributed.local_rows(by_view, b)
        if rows != (q * b // n, (q + 1) * b // n):
            raise InputError.single("flags", "--num_processes", f"process {q}'s devices hold rows {rows[0]}-{rows[1]} "
                                    f"of a step's {b} views, not its share's {q * b // n}-{(q + 1) * b // n}: the "
                                    "devices are not ordered by process; report this with `jax.devices()`")
    if config.prior_attention == "cudnn":
        if choice.kind != "rgbx":
            raise InputError.single("flags", "--prior_attention", "cudnn is the UNet's attention, but the views prior "
                                    f"was chosen ({choice.reason}); use --prior_attention=chunked or give --rgbx_dir")
        from jaxdistill.models import convert

        device = jax.local_devices()[0]
        kind, capability = getattr(device, "device_kind", device.platform), getattr(device, "compute_capability", None)
        if device.platform != "gpu" or "NVIDIA" not in kind.upper() or (capability and float(capability) < 8.0):
            raise InputError.single("flags", "--prior_attention", "cudnn needs an NVIDIA GPU of compute capability 8.0 "
                                    f"or newer (Ampere and later) and this run's device is {kind}"
                                    f"{f' ({capability})' if capability else ''}; use --prior_attention=chunked")
        heads = convert.fused_attention_problems(choice.folder)
        if heads:
            raise InputError.single("flags", "--prior_attention", f"cuDNN's fused attention takes heads of 8 to 128 "
                                    f"channels in steps of 8, and {choice.folder}'s UNet has {'; '.join(heads)}; "
                                    "use --prior_attention=chunked")
    if choice.kind == "views" and config.loss_space == "latent":
        raise InputError.single("flags", "--loss_space", "latent needs the rgbx prior, but the views prior was "
                                f"chosen ({choice.reason}); use --loss_space=image or give --rgbx_dir")
    directory = out / "checkpoints"
    if not config.resume:
        if directory.exists():
            steps = checkpoint.CheckpointStore(directory).latest_step()
            if steps is not None:
                raise InputError.single("flags", "--out_dir", f"{out} already holds a run (checkpoint at step {steps})"
                                        "; pass --resume to continue it, or choose another --out_dir")
        return None
    with checkpoint.CheckpointStore(directory) as store:
        latest = _readable_checkpoint(store)
        if latest is None:
            raise InputError.single("flags", "--resume", f"no complete checkpoint in {directory}; "
                                    "run without --resume to start")
        written = store.read_config(latest)
        shares, now = written.get("view_shares", ADDED_FLAG_DEFAULTS["view_shares"]), distributed.shares_of_run(
            config.view_shares)
        if shares != now:
            raise InputError.single(directory, "--view_shares", (
                f"the checkpoint's steps drew their views from {shares} share(s) (--view_shares, or one per "
                f"process) and this run would draw from {now}; resume in {shares} process(es) with --view_shares=0, "
                f"or in one process with --view_shares={shares}"))
        checkpoint.check_compatible(written, recorded_config(config, choice.kind), directory,
                                    ignore=resumable_flags(config), defaults=ADDED_FLAG_DEFAULTS)
    if latest > config.steps:
        raise InputError.single("flags", "--steps", f"{config.steps} is below the checkpoint's step {latest} in "
                                f"{directory}; give --steps >= {latest}")
    return latest


def _readable_checkpoint(store: checkpoint.CheckpointStore) -> int | None:
    """The newest complete checkpoint whose files read back, or None when there is none. Newer
    ones that do not read (damaged after their commit) are moved aside with a warning; when
    none reads, InputError naming each step folder and how to start fresh."""
    steps = store.all_steps()
    damaged = []
    for step in reversed(steps):
        reason = store.damage(step)
        if reason is None:
            for bad, why in damaged:
                moved = store.set_aside(bad)
                logging.warning("%s: checkpoint of step %d is damaged (%s); moved it to %s and resuming from the "
                                "previous committed step %d", store.directory / str(bad), bad, why, moved, step)
            return step
        damaged.append((step, reason))
    if damaged:
        raise InputError([(str(store.directory / str(step)), f"step {step}", f"checkpoint is damaged ({why})")
                          for step, why in damaged] + [
            (str(store.directory), "--resume", "no committed checkpoint reads back, so there is nothing to resume; to "
             f"start fresh, move {store.directory} away (or choose another --out_dir) and run without --resume")])
    return None


@dataclasses.dataclass
class LoopResult:
    """Where the loop ended: the state, the loss history, the step it started from, its time, how
    often the step was traced, and the signal that stopped it early (None when it finished). The
    main job drops the state (None) once it has taken the texels out."""

    state: DistillState | None
    history: dict
    start_step: int
    seconds: float
    traces: int
    stopped_by: str | None = None
    exit_status: int | None = None


class _Checkpoints:
    """The run's checkpoint store with what each save records beside the state."""

    def __init__(self, config: DistillConfig, out: Path, recorded: dict, enabled: bool = True):
        self.out, self.recorded = out, recorded
        self.store = (checkpoint.CheckpointStore(out / "checkpoints", max_to_keep=config.keep_checkpoints or None)
                      if enabled else None)

    def save(self, state, history: dict) -> None:
        if self.store is not None:
            _save(self.store, state, self.recorded, history, self.out)

    def close(self) -> None:
        if self.store is not None:
            self.store.close()

    def restore(self, step: int, state) -> tuple[DistillState, dict]:
        """The state of checkpoint `step` and the history up to it (empty history when none was saved)."""
        state, _ = self.store.restore(step, state)
        history = _empty_history()
        if _history_path(self.out).is_file():
            history = json.loads(_history_path(self.out).read_text())
            for key, at in (("loss", "step"), ("albedo_psnr", "eval_step")):
                keep = [i for i, s in enumerate(history[at]) if s <= step]
                history[key] = [history[key][i] for i in keep]
                history[at] = [history[at][i] for i in keep]
        logging.info("resumed from step %d in %s", step, self.out / "checkpoints")
        return state, history


def _empty_history() -> dict:
    return {"step": [], "loss": [], "eval_step": [], "albedo_psnr": []}


def run_loop(config: DistillConfig, problem: Problem, recorded: dict, latest: int | None, *,
             evaluate: Callable[[DistillState], float] | None = None, progress: bool = True,
             hooks: LoopHooks | None = None, prepared: PreparedStep | None = None) -> LoopResult:
    """Steps from `latest` (a checkpoint step, None for a fresh run) to --steps, checkpointing every
    --ckpt_every steps and at the end; `evaluate(state)` (albedo PSNR) every --eval_every steps.
    SIGINT/SIGTERM stop it after the current step with a checkpoint (`LoopResult.stopped_by`).
    `hooks` (`LoopHooks`) let a benchmark time it; None runs it as the main job does. `prepared`
    (`prepare_step` of the same config and problem): the step set up and compiled already."""
    hooks = hooks or LoopHooks()
    if prepared is not None and hooks.before_steps is not None:
        raise ValueError("run_loop: a prepared step and a before_steps hook: give one")
    stepper = (prepared.stepper if prepared is not None
               else setup_step(config, problem, first_batch(problem, config)))
    distributed.barrier("loop")      # process 0 also built the evaluation: meet before the first collective
    checkpoints = _Checkpoints(config, Path(config.out_dir), recorded, enabled=hooks.checkpoints)
    history = _empty_history()
    state = stepper.state
    if latest is not None:
        state, history = checkpoints.restore(latest, state)
    step_fn, traces, by_view = stepper.step_fn, stepper.traces, stepper.by_view
    if prepared is not None:
        step_fn = prepared.compiled
    state = jax.device_put(state, stepper.replicated)
    frozen = jax.device_put(problem.frozen, stepper.replicated)
    if hooks.before_steps is not None:
        step_fn = hooks.before_steps(step_fn, state, distributed.place_batch(
            problem.batch, batch_views(problem, config, 0), by_view), frozen)

    start_step = int(jax.device_get(state.step))
    pending = []           # (step, metrics on device) not yet fetched
    running = collections.deque()   # metrics of the steps dispatched and perhaps not finished
    stopped_by = None
    loop_start = time.perf_counter()
    with checkpoint.StopSignals() as stop, tqdm(total=config.steps, initial=start_step, unit="step", desc="distil",
                                                dynamic_ncols=True,
                                                disable=not (progress and distributed.is_primary()),
                                                smoothing=0) as bar:   # steps run asynchronously: average rate
        for step in range(start_step, config.steps):
            batch = distributed.place_batch(problem.batch, batch_views(problem, config, step), by_view)
            state, step_metrics = step_fn(state, batch, frozen)
            batch = None
            pending.append((step, step_metrics))
            running.append(step_metrics)
            if len(running) > PREFETCH_STEPS:     # dispatch is asynchronous: each step ahead holds its batch
                jax.block_until_ready(running.popleft())
            done = step + 1
            evaluating = bool(config.eval_every and done % config.eval_every == 0 and evaluate is not None)
            saving = bool(config.ckpt_every and done % config.ckpt_every == 0 and done < config.steps)
            if done % config.log_every == 0 or done == config.steps or stop.requested or evaluating or saving:
                _drain(pending, history, bar, state, checkpoints, hooks)   # the history matches an eval or a checkpoint
            traces.check(1)
            bar.update()
            if evaluating:
                history["eval_step"].append(done)
                history["albedo_psnr"].append(evaluate(state))
                _show(bar, history)
            if saving:
                checkpoints.save(state, history)
            if stop.requested:
                stopped_by = stop.signal_name
                break
        _drain(pending, history, bar, state, checkpoints, hooks)
    seconds = time.perf_counter() - loop_start
    checkpoints.save(state, history)
    checkpoints.close()
    result = LoopResult(state, history, start_step, seconds, traces.traces)
    if stopped_by:
        logging.warning("stopped by %s at step %d; checkpoint saved. Continue with the same flags and --resume. "
                        "Exiting with status %d (128 + signal number): the run did not finish.",
                        stopped_by, int(jax.device_get(state.step)), stop.exit_status)
        result = dataclasses.replace(result, stopped_by=stopped_by, exit_status=stop.exit_status)
    return result


def _drain(pending: list, history: dict, bar, state, checkpoints: _Checkpoints, hooks: LoopHooks) -> None:
    """Fetches pending step metrics into the history; stops the run on a non-finite step."""
    fetched = jax.device_get([m for _, m in pending])
    for (step, _), values in zip(pending, fetched):
        if not values["finite"]:
            checkpoints.save(state, history)
            checkpoints.close()
            raise NonFiniteLoss(
                f"the loss or its gradient became NaN/inf at step {step}; the state before that step is saved in "
                f"{checkpoints.out / 'checkpoints'} (step {step}). Try a smaller --lr, --prior_dtype=float32, or "
                "check the photos and targets for NaN/inf; resume with --resume.")
        history["step"].append(step + 1)
        history["loss"].append(float(values["loss"]))
    if fetched and hooks.after_fetch is not None:
        hooks.after_fetch(pending[-1][0] + 1, fetched)
    pending.clear()
    if fetched:
        bar.t_mean = float(fetched[-1]["t_mean"])
        _show(bar, history)


def _show(bar, history: dict) -> None:
    """The progress bar's postfix: last loss and mean t, and the last eval's albedo PSNR (--eval_every)."""
    shown = {}
    if history["loss"]:
        shown["loss"] = f"{history['loss'][-1]:.4g}"
    if getattr(bar, "t_mean", None) is not None:
        shown["t"] = f"{bar.t_mean:.0f}"
    if history["albedo_psnr"] and math.isfinite(history["albedo_psnr"][-1]):
        shown["albedo_psnr"] = f"{history['albedo_psnr'][-1]:.2f}dB@{history['eval_step'][-1]}"
    bar.set_postfix(shown, refresh=False)
