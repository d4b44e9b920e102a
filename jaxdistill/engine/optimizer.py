"""The texels' optimizer: optax's AdamW, with an update that the step applies in place.

`make_optimizer` returns a `GatedAdamW`: an optax `GradientTransformation` whose `init` and
`update` are `optax.adamw`'s own (same state tree, so checkpoints and optax's combinators work as
before), plus `gated_update(grads, state, params, ok)`, the step's whole AdamW step behind its
finite gate (`ok` false: params and state come back unchanged). Wrapped in a combinator (e.g.
`optax.chain`) it loses `gated_update`, and the step falls back to the `where` form below.

Why a second form of the same update: written as `optimizer.update`, `apply_updates` and a
`where(ok, new, old)` per leaf, XLA recomputes the new first moment inside the texels' update
while writing it over the old one in place, so it keeps a copy of the old moment: one more array
of the texels' size in the step's temporaries (XLA's buffer assignment of the default step at
19.3M texels: 0.79 GB; at the capture room's 32.5M texels the temporaries fell by 0.58 of an array,
docs/benchmarks.md §10). `gated_update` gates the two moments
first, makes XLA materialise them (`lax.optimization_barrier`) in their own donated buffers, and
only then derives the texels' update from them: the same arithmetic as optax's AdamW (tested
against it, `tests/test_optimizer.py`), with no copy.
"""

from __future__ import annotations

import functools
from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp
import optax

B1, B2, EPS = 0.9, 0.999, 1e-8                     # optax.adamw's defaults (and the thesis's)


class GatedAdamW(NamedTuple):
    """optax AdamW (`init`, `update`: `optax.adamw`'s) and `gated_update` (module docstring)."""

    init: Callable
    update: Callable
    gated_update: Callable


def learning_rate(lr: float, schedule: str = "constant", total_steps: int = 1):
    """The thesis's constant rate, or a cosine decay from lr to 0 over the run."""
    if schedule == "constant":
        return lr
    if schedule == "cosine":
        return optax.cosine_decay_schedule(lr, max(total_steps, 1))
    raise ValueError(f"unknown learning-rate schedule {schedule!r}")


def make_optimizer(lr: float, weight_decay: float, schedule: str = "constant",
                   total_steps: int = 1) -> GatedAdamW:
    """optax AdamW (thesis: lr 0.01, constant), with `gated_update`."""
    return adamw(learning_rate(lr, schedule, total_steps), weight_decay)


def adamw(rate, weight_decay: float) -> GatedAdamW:
    """`optax.adamw(rate, weight_decay=weight_decay)` as a `GatedAdamW`."""
    reference = optax.adamw(learning_rate=rate, b1=B1, b2=B2, eps=EPS, weight_decay=weight_decay)
    decay = optax.add_decayed_weights(weight_decay)
    scale = optax.scale_by_learning_rate(rate)

    def gated_update(grads: Any, state: tuple, params: Any, ok: jax.Array) -> tuple[Any, tuple]:
        adam, decay_state, scale_state = state
        keep = functools.partial(jax.tree.map, functools.partial(jnp.where, ok))
        mu = keep(optax.tree.update_moment(grads, adam.mu, B1, 1), adam.mu)
        nu = keep(optax.tree.update_moment_per_elem_norm(grads, adam.nu, B2, 2), adam.nu)
        mu, nu = jax.lax.optimization_barrier((mu, nu))     # written in place before anything reads them
        count = optax.safe_increment(adam.count)
        mu_hat = optax.tree.bias_correction(mu, B1, count)
        nu_hat = optax.tree.bias_correction(nu, B2, count)
        updates = jax.tree.map(lambda m, v: m / (jnp.sqrt(v) + EPS), mu_hat, nu_hat)
        updates, decay_state_new = decay.update(updates, decay_state, params)
        updates, scale_state_new = scale.update(updates, scale_state, params)
        new_params = keep(optax.apply_updates(params, updates), params)
        new_adam = optax.ScaleByAdamState(count=jnp.where(ok, count, adam.count), mu=mu, nu=nu)
        return new_params, (new_adam, decay_state_new, keep(scale_state_new, scale_state))

    return GatedAdamW(init=reference.init, update=reference.update, gated_update=gated_update)


def gated_step(optimizer: optax.GradientTransformation, grads: Any, state: Any, params: Any,
               ok: jax.Array) -> tuple[Any, Any]:
    """(params, state) after one step of `optimizer` when `ok`, else as they were: the optimizer's
    `gated_update` when it has one, else its `update` with `where(ok, new, old)` on every leaf
    (any optax transformation, e.g. a test's chain around AdamW)."""
    if hasattr(optimizer, "gated_update"):
        return optimizer.gated_update(grads, state, params, ok)
    keep = functools.partial(jnp.where, ok)
    updates, new_state = optimizer.update(grads, state, params)
    return (jax.tree.map(keep, optax.apply_updates(params, updates), params),
            jax.tree.map(keep, new_state, state))
