"""The resumable training stage: a step function run to a step count with checkpoints.

`run_stage` runs `state = step_fn(state, batch_fn(step))` from the newest orbax checkpoint of a
stage, with a progress bar (loss, ETA), a loss log, checkpoints every `ckpt_every` steps and on
SIGINT/SIGTERM, and a `Budget` of steps and minutes shared by the stages of one run (spent: a
checkpoint, then exit 75, so running the same command again continues). `adamw` is the
optimizer every stage uses. The VAE and UNet stages are `train_prior`'s.

A stage's checkpoint holds its state packed (`pack`): one flat array per dtype, the leaves
concatenated in tree order, and the leaves' paths, shapes and dtypes in the saved config
("layout"), checked on resume. Orbax spends a few milliseconds on each array it writes or reads
on top of its size, so a network's state of hundreds of small arrays (params, EMA, AdamW
moments) took seconds a checkpoint leaf by leaf. Checkpoints written leaf by leaf still resume.
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path
from typing import Any, Callable

import jax
import numpy as np
import optax
from tqdm import tqdm

from jaxdistill.errors import InputError
from jaxdistill.io.checkpoint import CheckpointStore, StopSignals, is_typed_key

LAYOUT = "layout"           # the saved config's key for the packed state's leaves


class Budget:
    """This run's limits across stages: at most `steps` steps (0: none) and `minutes` (0: none)."""

    EXIT_UNFINISHED = 75          # EX_TEMPFAIL: checkpoint saved, run again to continue

    def __init__(self, steps: int = 0, minutes: float = 0.0):
        self.steps, self.deadline, self.done = steps, time.monotonic() + 60 * minutes if minutes else None, 0

    def spent(self) -> bool:
        return bool(self.steps and self.done >= self.steps) or bool(self.deadline and time.monotonic() > self.deadline)


def run_stage(name: str, work: Path, init_state: Callable[[], Any], step_fn, batch_fn, steps: int, ckpt_every: int,
              config: dict, budget: Budget, on_save: Callable[[int, Any], None] | None = None):
    """Runs `state = step_fn(state, batch_fn(step))` from the newest checkpoint of stage `name`
    to `steps`, with a progress bar (loss, ETA) and orbax checkpoints; returns the final state.
    `init_state()` gives the state of step 0 and is computed only when the stage has no
    checkpoint: a resumed stage restores into its shapes (`jax.eval_shape`, no initialisation run,
    which for a network's Flax init is most of a short run's time).
    SIGINT/SIGTERM save and exit with 130/143; a spent `budget` saves and exits with 75.
    `on_save(step, state)`, if given, runs after each checkpoint is written."""
    with CheckpointStore(work / f"ckpt_{name}", max_to_keep=2) as store:
        start = store.latest_step() or 0
        if not start:
            state = init_state()
        else:
            state = restore_packed(store, start, jax.eval_shape(init_state))
            print(f"{name}: resumed at step {start} of {steps}")
        if start >= steps:
            return state
        losses = []
        with StopSignals() as stop, tqdm(total=steps, initial=start, desc=name, unit="step") as bar:
            for step in range(start, steps):
                state, loss = step_fn(state, batch_fn(step))
                losses.append(loss)
                budget.done += 1
                if (step + 1) % 25 == 0 or step + 1 == steps:
                    bar.set_postfix(loss=f"{float(np.mean(jax.device_get(losses[-25:]))):.4f}")
                bar.update(1)
                halt = stop.requested or budget.spent()
                if (step + 1) % ckpt_every == 0 or step + 1 == steps or halt:
                    store.save(step + 1, pack(state), {**config, LAYOUT: layout(state)})
                    if on_save is not None:
                        on_save(step + 1, state)
                    with open(work / f"{name}_loss.jsonl", "a") as f:
                        f.write(json.dumps({"step": step + 1, "loss": float(np.mean(jax.device_get(losses)))}) + "\n")
                    losses = []
                if halt and step + 1 < steps:
                    why = stop.signal_name or "this run's step/time budget spent"
                    status = stop.exit_status if stop.requested else Budget.EXIT_UNFINISHED
                    print(f"{name}: {why} at step {step + 1} of {steps}; checkpoint saved, run the same command "
                          f"again to resume (exit status {status})")
                    sys.exit(status)
    return state


def layout(state) -> list:
    """[[leaf path, shape, dtype], ...] of `state` (arrays or shapes) in tree order; ValueError
    for a typed PRNG key (a stage keeps its keys outside its state: store `key_data` if not)."""
    out = []
    for path, x in jax.tree_util.tree_flatten_with_path(state)[0]:
        if is_typed_key(x):
            raise ValueError(f"{jax.tree_util.keystr(path)}: a typed PRNG key cannot be packed into a checkpoint; "
                             "keep jax.random.key_data(key) in the state instead")
        out.append([jax.tree_util.keystr(path), list(np.shape(x)), np.dtype(x.dtype).name])
    return out


def pack(state) -> dict[str, np.ndarray]:
    """{dtype name: 1-D host array}: `state`'s leaves of that dtype ravelled and concatenated in
    tree order (`unpack` undoes it; empty leaves hold nothing and come back as zeros of their shape)."""
    layout(state)                       # refuses typed PRNG keys, naming the leaf
    leaves = [x for x in jax.device_get(jax.tree.leaves(state)) if np.size(x)]     # orbax saves no empty array
    names = sorted({np.dtype(x.dtype).name for x in leaves})
    return {n: np.concatenate([np.ravel(x) for x in leaves if np.dtype(x.dtype).name == n]) for n in names}


def unpack(packed: dict, like):
    """The state shaped as `like` (arrays or shapes) from `pack`'s arrays, as (uncommitted) device arrays."""
    leaves, treedef = jax.tree.flatten(like)
    offsets = {n: 0 for n in packed}
    out = []
    for x in leaves:
        n, size = np.dtype(x.dtype).name, int(np.prod(x.shape, dtype=np.int64))
        if not size:
            out.append(jax.numpy.zeros(x.shape, x.dtype))
            continue
        out.append(jax.numpy.asarray(packed[n][offsets[n]:offsets[n] + size].reshape(x.shape)))
        offsets[n] += size
    return jax.tree.unflatten(treedef, out)


def restore_packed(store: CheckpointStore, step: int, like):
    """The state of checkpoint `step`, shaped as `like` (shapes): a packed one (`pack`) after
    its saved layout is checked against `like`'s, one written leaf by leaf as it was saved.
    InputError naming the checkpoint and the first leaf that differs."""
    config = store.read_config(step)
    if LAYOUT not in config:             # written leaf by leaf (before packing)
        state, _ = store.restore(step, like)
        # restored arrays are committed to a device, a fresh state's are not: as host copies the
        # step sees the same arguments either way and compiles the same program (a persistent
        # compilation cache then serves a resumed run)
        return jax.tree.map(lambda x: jax.numpy.asarray(np.asarray(x)), state)
    saved, wanted = config[LAYOUT], layout(like)
    if saved != wanted:
        first = next((i for i, (a, b) in enumerate(zip(saved, wanted)) if a != b), min(len(saved), len(wanted)))
        have, want = (f"{x[first][0]} {tuple(x[first][1])} {x[first][2]}" if first < len(x) else "nothing"
                      for x in (saved, wanted))
        raise InputError.single(
            store.directory / str(step), LAYOUT,
            f"this checkpoint's state ({len(saved)} arrays) is not this stage's ({len(wanted)}): leaf {first} is "
            f"{have} there, {want} here (the recipe or its flags changed); use the flags it was saved with, "
            f"or another --work to start over")
    totals = {}
    for _, shape, dtype in wanted:
        totals[dtype] = totals.get(dtype, 0) + int(np.prod(shape, dtype=np.int64))
    packed, _ = store.restore(step, {n: jax.ShapeDtypeStruct((size,), np.dtype(n)) for n, size in totals.items() if size})
    return unpack({n: np.asarray(a) for n, a in packed.items()}, like)     # uncommitted, as a fresh state's


def adamw(lr: float, steps: int, weight_decay: float = 0.01):
    """AdamW with a linear warm-up (a tenth of `steps`, at most 500) and cosine decay to 5 % of
    `lr`, gradients clipped to global norm 1."""
    warmup = max(min(500, steps // 10), 1)
    schedule = optax.warmup_cosine_decay_schedule(0.0, lr, warmup, max(steps, warmup + 1), lr * 0.05)
    return optax.chain(optax.clip_by_global_norm(1.0), optax.adamw(schedule, weight_decay=weight_decay))
