"""The texels' AdamW (`engine/optimizer.py`): its gated in-place update against optax's own
AdamW behind a `where`, and the texel-sized copy it exists to avoid."""

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

from jaxdistill.engine.optimizer import gated_step, make_optimizer
from tolerance import assert_close


def _reference(optimizer, grads, state, params, ok):
    """optax.adamw's update, applied, then kept only when ok: the step's form before the gate."""
    updates, new_state = optimizer.update(grads, state, params)
    keep = lambda new, old: jnp.where(ok, new, old)
    return jax.tree.map(keep, optax.apply_updates(params, updates), params), jax.tree.map(keep, new_state, state)


@pytest.mark.parametrize("schedule,weight_decay", [("constant", 0.0), ("cosine", 0.0), ("cosine", 0.01)])
def test_gated_update_is_optax_adamw_behind_the_gate(schedule, weight_decay):
    """Six steps with gradients of mixed scale, two of them gated off (ok false): parameters and
    every leaf of the state (moments, counts, the schedule's count) equal optax.adamw's update
    applied behind `where(ok, new, old)`, to float32 rounding."""
    rng = np.random.default_rng(0)
    optimizer = make_optimizer(0.05, weight_decay, schedule, total_steps=10)
    params = jnp.asarray(rng.normal(size=(257, 11)), jnp.float32)
    ours, ref = (params, optimizer.init(params)), (params, optimizer.init(params))
    gated = jax.jit(optimizer.gated_update)
    plain = jax.jit(lambda g, s, p, ok: _reference(optimizer, g, s, p, ok))
    for i, ok in enumerate([True, True, False, True, False, True]):
        grads = jnp.asarray(rng.normal(size=params.shape) * 10.0 ** rng.integers(-4, 2, size=params.shape),
                            jnp.float32)
        ours = gated(grads, ours[1], ours[0], jnp.bool_(ok))
        ref = plain(grads, ref[1], ref[0], jnp.bool_(ok))
        # float32 rounding of two programs: a texel that p - lr * u brings near 0 keeps the rounding of p's
        # magnitude, so the floor is relative to the leaf's largest value (tests/tolerance.py)
        for a, b in zip(jax.tree.leaves(ours), jax.tree.leaves(ref)):
            assert_close(a, b, rtol=2e-6, floor=1e-7, err_msg=f"step {i}")
    assert int(ours[1][0].count) == 4                 # the two gated steps did not count
    assert not np.array_equal(np.asarray(ours[0]), np.asarray(params))


def test_gated_off_returns_params_and_state_unchanged():
    optimizer = make_optimizer(0.05, 0.01, "cosine", total_steps=10)
    params = jnp.linspace(-1.0, 1.0, 66, dtype=jnp.float32).reshape(6, 11)
    state = optimizer.init(params)
    state = optimizer.update(jnp.ones_like(params), state, params)[1]            # non-zero moments
    new_params, new_state = jax.jit(optimizer.gated_update)(jnp.full_like(params, jnp.nan), state, params,
                                                            jnp.bool_(False))
    np.testing.assert_array_equal(np.asarray(new_params), np.asarray(params))
    for a, b in zip(jax.tree.leaves(new_state), jax.tree.leaves(state)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


def test_any_optax_transformation_takes_the_where_path():
    """A transformation without `gated_update` (a test's chain around AdamW) is updated and kept
    by `where`, with the same result as the gated form."""
    optimizer = make_optimizer(0.01, 0.0)
    chained = optax.chain(optimizer)
    params = jnp.arange(22, dtype=jnp.float32).reshape(2, 11) / 22
    grads = jnp.sin(params * 7.0)
    ours = gated_step(optimizer, grads, optimizer.init(params), params, jnp.bool_(True))
    theirs = gated_step(chained, grads, chained.init(params), params, jnp.bool_(True))
    np.testing.assert_allclose(np.asarray(ours[0]), np.asarray(theirs[0]), rtol=2e-6)


def test_gated_update_keeps_no_copy_of_a_moment():
    """Jitted with the state donated, as the step is: optax's update behind a `where` makes XLA
    keep a copy of the old first moment (temporaries of about one parameter array); the gated
    update's temporaries are the finite check's booleans, a quarter of one (XLA's own buffer
    assignment, `compiled.memory_analysis()`)."""
    n = 1 << 18
    params = jnp.ones((n, 11), jnp.float32)
    size = params.size * 4
    gated = make_optimizer(0.05, 0.0, "cosine", 100)
    plain = optax.chain(gated)

    def temporaries(optimizer):
        def step(params, state, grads, halted):
            ok = jnp.all(jnp.isfinite(grads)) & ~halted
            return gated_step(optimizer, grads, state, params, ok)
        compiled = jax.jit(step, donate_argnums=(0, 1)).lower(
            params, optimizer.init(params), params, jnp.bool_(False)).compile()
        return compiled.memory_analysis().temp_size_in_bytes / size

    ours, theirs = temporaries(gated), temporaries(plain)
    assert theirs > 0.9, theirs                  # the copy this form avoids is there in the plain one
    assert ours < theirs - 0.7 and ours < 0.3, (ours, theirs)
