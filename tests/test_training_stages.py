"""The training stages' checkpoints (`jaxdistill.models.training.stages`): a stage's state is saved
packed, one flat array per dtype, and resumes to the same arrays; a checkpoint written leaf by
leaf (before packing) still resumes; one of another layout is refused, naming the leaf."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

from jaxdistill.errors import InputError
from jaxdistill.io.checkpoint import CheckpointStore
from jaxdistill.models.training import stages
from jaxdistill.models.training.stages import Budget, run_stage


def toy_state(width: int = 3, empty: bool = True):
    """A network-like state: nested params, AdamW moments, an int32 step count, a scalar and
    (with `empty`) an empty array, values unlike their neighbours (a misplaced slice shows)."""
    rng = np.random.default_rng(0)
    params = {"dense": {"kernel": jnp.asarray(rng.normal(size=(4, width)), jnp.float32),
                        "bias": jnp.asarray(rng.normal(size=(width,)), jnp.float32)},
              "norm": {"scale": jnp.asarray(rng.normal(size=()), jnp.float32)}}
    if empty:
        params["empty"] = jnp.zeros((0, 2), jnp.float32)
    return {"params": params, "opt": optax.adamw(0.1).init(params), "ids": jnp.arange(5, dtype=jnp.int32)}


def toy_step(state, batch):
    grads = jax.tree.map(lambda p: p * batch, state["params"])
    updates, opt = optax.adamw(0.1).update(grads, state["opt"], state["params"])
    return {"params": optax.apply_updates(state["params"], updates), "opt": opt, "ids": state["ids"] + 1}, jnp.float32(batch)


def run(work, steps, budget=0, init=toy_state):
    return run_stage("toy", work, init, jax.jit(toy_step), lambda step: jnp.float32(step + 1), steps, ckpt_every=2,
                     config={"stage": "toy"}, budget=Budget(steps=budget))


def assert_trees_equal(a, b):
    assert jax.tree.structure(a) == jax.tree.structure(b)
    for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b)):
        assert np.dtype(x.dtype) == np.dtype(y.dtype) and np.shape(x) == np.shape(y)
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))


def test_pack_is_one_array_per_dtype_and_unpack_gives_the_state_back():
    state = toy_state()
    packed = stages.pack(state)
    leaves = jax.tree.leaves(state)
    assert sorted(packed) == ["float32", "int32"]
    for name, flat in packed.items():                            # the leaves in tree order, nothing else
        expected = np.concatenate([np.ravel(np.asarray(x)) for x in leaves if np.dtype(x.dtype).name == name])
        np.testing.assert_array_equal(flat, expected)
    assert_trees_equal(stages.unpack(packed, jax.eval_shape(lambda: state)), state)
    assert stages.layout(state)[0] == ["['ids']", [5], "int32"]


def test_a_stage_stopped_on_its_budget_resumes_from_a_packed_checkpoint_to_the_same_state(tmp_path):
    whole = run(tmp_path / "a", 5)
    with pytest.raises(SystemExit) as stop:
        run(tmp_path / "b", 5, budget=3)
    assert stop.value.code == Budget.EXIT_UNFINISHED
    with CheckpointStore(tmp_path / "b" / "ckpt_toy") as store:
        assert store.latest_step() == 3
        assert sorted(store.saved_shapes()) == ["float32", "int32"]           # packed: two arrays, not one per leaf
        assert store.read_config()[stages.LAYOUT] == stages.layout(toy_state())
    assert_trees_equal(run(tmp_path / "b", 5), whole)


def test_a_checkpoint_written_leaf_by_leaf_still_resumes(tmp_path):
    def init():                         # orbax saves no empty array leaf by leaf: a state without one
        return toy_state(empty=False)

    whole = run(tmp_path / "a", 5, init=init)
    with pytest.raises(SystemExit):
        run(tmp_path / "b", 5, budget=3, init=init)
    with CheckpointStore(tmp_path / "b" / "ckpt_toy") as store:       # rewritten as before packing
        state = stages.restore_packed(store, 3, jax.eval_shape(init))
        old = CheckpointStore(tmp_path / "old" / "ckpt_toy")
        old.save(3, state, {"stage": "toy"})
        old.close()
        assert len(old.saved_shapes()) == len(jax.tree.leaves(state))
    assert_trees_equal(run(tmp_path / "old", 5, init=init), whole)


def test_a_checkpoint_of_another_layout_is_refused_naming_the_leaf(tmp_path):
    with pytest.raises(SystemExit):
        run(tmp_path / "w", 5, budget=3)
    with pytest.raises(InputError) as err:
        run(tmp_path / "w", 5, init=lambda: toy_state(width=4))      # same dtypes, other shapes
    message = str(err.value)
    assert str(tmp_path / "w" / "ckpt_toy" / "3") in message and stages.LAYOUT in message
    assert "['opt'][0].mu['dense']['bias'] (3,) float32 there" in message, message       # the first leaf that differs
    assert "['opt'][0].mu['dense']['bias'] (4,) float32 here" in message and "another --work" in message


def test_a_typed_prng_key_is_refused_naming_its_leaf():
    with pytest.raises(ValueError, match=r"\['params'\]\['key'\]: a typed PRNG key cannot be packed"):
        stages.pack({"params": {"key": jax.random.key(0), "w": jnp.ones(2)}})
