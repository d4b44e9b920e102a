"""The resumable training stage: a step function run to a step count with checkpoints.

`run_stage` runs `state = step_fn(state, batch_fn(step))` from the newest orbax checkpoint of a
stage, with a progress bar (loss, ETA), a loss log, checkpoints every `ckpt_every` steps and on
SIGINT/SIGTERM, and a `Budget` of steps and minutes shared by the stages of one run (spent: a
checkpoint, then exit 75, so running the same command again continues). `adamw` is the
optimizer every stage uses. The VAE and UNet stages are `train_prior`'s.
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

from jaxdistill.io.checkpoint import CheckpointStore, StopSignals


class Budget:
    """This run's limits across stages: at most `steps` steps (0: none) and `minutes` (0: none)."""

    EXIT_UNFINISHED = 75          # EX_TEMPFAIL: checkpoint saved, run again to continue

    def __init__(self, steps: int = 0, minutes: float = 0.0):
        self.steps, self.deadline, self.done = steps, time.monotonic() + 60 * minutes if minutes else None, 0

    def spent(self) -> bool:
        return bool(self.steps and self.done >= self.steps) or bool(self.deadline and time.monotonic() > self.deadline)


def run_stage(name: str, work: Path, init_state: Callable[[], Any], step_fn, batch_fn, steps: int, ckpt_every: int,
              config: dict, budget: Budget):
    """Runs `state = step_fn(state, batch_fn(step))` from the newest checkpoint of stage `name`
    to `steps`, with a progress bar (loss, ETA) and orbax checkpoints; returns the final state.
    `init_state()` gives the state of step 0 and is computed only when the stage has no
    checkpoint: a resumed stage restores into its shapes (`jax.eval_shape`, no initialisation run,
    which for a network's Flax init is most of a short run's time).
    SIGINT/SIGTERM save and exit with 130/143; a spent `budget` saves and exits with 75."""
    with CheckpointStore(work / f"ckpt_{name}", max_to_keep=2) as store:
        start = store.latest_step() or 0
        if not start:
            state = init_state()
        else:
            state, _ = store.restore(start, jax.eval_shape(init_state))
            # restored arrays are committed to a device, a fresh state's are not: as host copies
            # the step sees the same arguments either way and compiles the same program (a
            # persistent compilation cache then serves a resumed run)
            state = jax.tree.map(lambda x: jax.numpy.asarray(np.asarray(x)), state)
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
                    store.save(step + 1, state, config)
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


def adamw(lr: float, steps: int, weight_decay: float = 0.01):
    """AdamW with a linear warm-up (a tenth of `steps`, at most 500) and cosine decay to 5 % of
    `lr`, gradients clipped to global norm 1."""
    warmup = max(min(500, steps // 10), 1)
    schedule = optax.warmup_cosine_decay_schedule(0.0, lr, warmup, max(steps, warmup + 1), lr * 0.05)
    return optax.chain(optax.clip_by_global_norm(1.0), optax.adamw(schedule, weight_decay=weight_decay))
