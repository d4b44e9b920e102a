"""Checkpoint store: bit-exact round trips, completeness, config compatibility, stop signals."""

from __future__ import annotations

import json
import logging
import os
import signal
import time

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

from jaxdistill.io.checkpoint import CheckpointStore, StopSignals, check_compatible, compatible
from jaxdistill.errors import InputError

CONFIG = {"lr": 0.01, "tex_res": [64, 64], "scene": "bedroom", "steps": 100, "out_dir": "out/x"}


def _tx():
    return optax.adamw(learning_rate=0.05, weight_decay=0.01)


def _state(n=64, c=5, seed=0):
    texels = jnp.asarray(np.random.default_rng(seed).standard_normal((n, c)), jnp.float32)
    return {"texels": texels, "opt_state": _tx().init(texels), "step": jnp.int32(0),
            "key": jax.random.PRNGKey(seed)}


@jax.jit
def _update(state):
    """One deterministic update that uses (and advances) the PRNG key."""
    key, sub = jax.random.split(state["key"])
    target = jax.random.normal(sub, state["texels"].shape, state["texels"].dtype)
    grads = jax.grad(lambda t: jnp.mean((t - target) ** 2))(state["texels"])
    updates, opt_state = _tx().update(grads, state["opt_state"], state["texels"])
    return {"texels": optax.apply_updates(state["texels"], updates), "opt_state": opt_state,
            "step": state["step"] + 1, "key": key}


def _run(state, n):
    for _ in range(n):
        state = _update(state)
    return state


def _assert_bit_identical(a, b):
    la, ta = jax.tree_util.tree_flatten(a)
    lb, tb = jax.tree_util.tree_flatten(b)
    assert ta == tb
    for x, y in zip(la, lb):
        x, y = np.asarray(x), np.asarray(y)
        assert x.dtype == y.dtype and x.shape == y.shape
        assert x.tobytes() == y.tobytes()


def _abstract(state):
    return jax.tree.map(lambda x: jax.ShapeDtypeStruct(x.shape, x.dtype), state)


def test_adamw_round_trip_is_bit_exact_and_resumes_identically(tmp_path):
    state = _run(_state(), 3)
    with CheckpointStore(tmp_path / "checkpoints") as store:
        assert store.save(3, state, CONFIG)
        assert store.latest_step() == 3
    with CheckpointStore(tmp_path / "checkpoints") as store:  # a new process resuming
        restored, config = store.restore(None, _abstract(state))
    _assert_bit_identical(restored, state)
    assert isinstance(restored["opt_state"][0], optax.ScaleByAdamState)
    assert restored["step"].dtype == jnp.int32 and int(restored["step"]) == 3
    assert config == json.loads(json.dumps(CONFIG))
    # the restored key continues the same random stream, and training continues identically
    np.testing.assert_array_equal(jax.random.uniform(restored["key"], (8,)), jax.random.uniform(state["key"], (8,)))
    _assert_bit_identical(_run(restored, 3), _run(state, 3))


def test_restore_into_concrete_like_and_typed_keys(tmp_path):
    state = {"texels": jnp.arange(12, dtype=jnp.float32).reshape(4, 3), "key": jax.random.key(7)}
    with CheckpointStore(tmp_path) as store:
        store.save(1, state, {})
        restored, config = store.restore(1, state)  # concrete example
        restored2, _ = store.restore(1, _abstract(state))  # abstract, typed key
    assert config == {}
    for r in (restored, restored2):
        assert jax.dtypes.issubdtype(r["key"].dtype, jax.dtypes.prng_key)
        np.testing.assert_array_equal(jax.random.key_data(r["key"]), jax.random.key_data(state["key"]))
        np.testing.assert_array_equal(jax.random.normal(r["key"], (4,)), jax.random.normal(state["key"], (4,)))
        _assert_bit_identical(r["texels"], state["texels"])
        assert list(r["texels"].devices()) == [jax.local_devices()[0]]


def test_latest_step_max_to_keep_and_config_round_trip(tmp_path):
    state = _state(8, 2)
    with CheckpointStore(tmp_path, max_to_keep=2) as store:
        assert store.latest_step() is None
        for step in (10, 20, 30):
            cfg = dict(CONFIG, steps=step, tex_res=(32, step))
            assert store.save(step, dict(state, step=jnp.int32(step)), cfg)
            assert store.latest_step() == step
        assert store.all_steps() == [20, 30]
        assert not store.save(30, state, CONFIG)  # already complete: a no-op (loop end == ckpt_every)
        assert store.read_config(20)["tex_res"] == [32, 20]
        restored, config = store.restore(20, state)
        assert int(restored["step"]) == 20 and config["steps"] == 20
    assert sorted(p.name for p in tmp_path.iterdir()) == ["20", "30"]


def test_async_save_finalises_and_copies_state(tmp_path):
    state = _state(16, 3)
    with CheckpointStore(tmp_path) as store:
        store.save(1, state, CONFIG, wait=False)
        later = _run(state, 1)  # the loop goes on while the write finishes
        store.wait()
        assert store.latest_step() == 1
        restored, _ = store.restore(1, state)
    _assert_bit_identical(restored, state)
    assert not np.array_equal(later["texels"], state["texels"])


def _fake_interrupted(directory):
    """An in-progress orbax temp dir and a step dir missing the commit marker, at later steps."""
    tmp = directory / "7.orbax-checkpoint-tmp"
    (tmp / "state").mkdir(parents=True)
    (directory / "8.orbax-checkpoint-tmp-1700000000").mkdir()
    partial = directory / "9"
    (partial / "state").mkdir(parents=True)
    (partial / "state" / "_METADATA").write_text("{}")
    (partial / "_CHECKPOINT_METADATA").write_text(json.dumps({"init_timestamp_nsecs": 1}))


def test_interrupted_writes_are_never_listed_or_restored(tmp_path, caplog):
    state = _state(8, 2)
    with CheckpointStore(tmp_path) as store:
        store.save(5, state, CONFIG)
        # a complete checkpoint carries orbax's commit marker and commit timestamp
        assert (tmp_path / "5" / "commit_success.txt").is_file()
        assert json.loads((tmp_path / "5" / "_CHECKPOINT_METADATA").read_text())["commit_timestamp_nsecs"] > 0
    _fake_interrupted(tmp_path)
    with CheckpointStore(tmp_path) as store:
        assert store.latest_step() == 5 and store.all_steps() == [5]
        restored, _ = store.restore(None, state)
        _assert_bit_identical(restored, state)
        for step in (7, 9):
            with pytest.raises(InputError, match=f"no complete checkpoint for step {step}"):
                store.restore(step, state)
        # the partial step 9 is replaced by a real save of step 9
        assert store.save(9, dict(state, step=jnp.int32(9)), CONFIG)
        assert store.latest_step() == 9
        assert int(store.restore(9, state)[0]["step"]) == 9
    # saving also cleared the temp dirs of the interrupted writes
    assert sorted(p.name for p in tmp_path.iterdir()) == ["5", "9"]
    assert not [r for r in caplog.records if r.levelno >= logging.ERROR]


def test_only_interrupted_writes_is_no_checkpoint(tmp_path, caplog):
    _fake_interrupted(tmp_path)
    with CheckpointStore(tmp_path) as store:
        assert store.latest_step() is None
        with pytest.raises(InputError, match="no complete checkpoint") as err:
            store.restore(None, _state(8, 2))
    assert str(tmp_path) in str(err.value) and "--resume" in str(err.value)
    assert len(list(tmp_path.iterdir())) == 3  # reading deletes nothing
    assert not [r for r in caplog.records if r.levelno >= logging.ERROR]


def test_missing_directory_is_an_input_error_and_not_created(tmp_path):
    missing = tmp_path / "nope" / "checkpoints"
    with CheckpointStore(missing) as store:
        assert store.latest_step() is None
        with pytest.raises(InputError) as err:
            store.restore(None, _state(8, 2))
    msg = str(err.value)
    assert str(missing) in msg and "no complete checkpoint" in msg and "--resume needs one" in msg
    assert not missing.exists()


def test_shape_mismatch_names_leaf_and_shapes(tmp_path):
    with CheckpointStore(tmp_path) as store:
        store.save(2, _state(8, 2), CONFIG)
        with pytest.raises(InputError) as err:
            store.restore(2, _abstract(_state(16, 2)))
    msg = str(err.value)
    assert "texels" in msg and "(8, 2)" in msg and "(16, 2)" in msg
    assert "opt_state/0/mu" in msg  # the AdamW moments follow the texels
    assert str(tmp_path / "2") in msg


def test_structure_and_dtype_mismatch(tmp_path):
    state = _state(8, 2)
    with CheckpointStore(tmp_path) as store:
        store.save(2, state, CONFIG)
        like = dict(state, texels=state["texels"].astype(jnp.float16), extra=jnp.zeros(3))
        del like["step"]
        with pytest.raises(InputError) as err:
            store.restore(2, like)
    msg = str(err.value)
    assert "texels: the checkpoint has shape (8, 2) float32" in msg and "float16" in msg
    assert "extra: missing from the checkpoint" in msg
    assert "step: in the checkpoint but not in the current state" in msg


def test_compatible():
    saved = dict(CONFIG, tex_res=[64, 64])
    current = dict(CONFIG, tex_res=(64, 64), steps=500, out_dir="/elsewhere")
    assert compatible(saved, current) == []  # tuple == list after JSON; steps/out_dir ignored
    current = dict(current, lr=0.02, new_flag=True)
    assert compatible(saved, current) == ["lr", "new_flag"]
    assert compatible(saved, current, ignore=("lr",)) == ["new_flag", "out_dir", "steps"]
    check_compatible(saved, dict(saved, resume=True), "/ckpt")  # no error


def test_check_compatible_message():
    saved = dict(CONFIG)
    current = dict(CONFIG, lr=0.02, scene="kitchen")
    del current["tex_res"]
    with pytest.raises(InputError) as err:
        check_compatible(saved, current, "/runs/a/checkpoints")
    msg = str(err.value)
    assert "/runs/a/checkpoints: --lr: checkpoint has 0.01, current run has 0.02" in msg
    assert '--scene: checkpoint has "bedroom", current run has "kitchen"' in msg
    assert "--tex_res: checkpoint has [64, 64], current run has (not set)" in msg
    assert "use the same flags, or a new --out_dir, or drop --resume to start over" in msg
    assert [p[1] for p in err.value.problems] == ["--lr", "--scene", "--tex_res", "--resume"]


def test_config_must_be_jsonable(tmp_path):
    with CheckpointStore(tmp_path) as store:
        with pytest.raises(TypeError, match="'bad'"):
            store.save(1, _state(4, 1), {"bad": object()})
        assert store.latest_step() is None


def _wait_for(predicate, timeout=2.0):
    end = time.monotonic() + timeout
    while not predicate() and time.monotonic() < end:
        time.sleep(0.005)
    return predicate()


def test_stop_signals_sets_flag_and_restores_handlers():
    before = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
    with StopSignals() as stop:
        assert not stop.requested and stop.signal_name is None and stop.exit_status is None
        os.kill(os.getpid(), signal.SIGTERM)
        assert _wait_for(lambda: stop.requested)
        assert stop.signal_name == "SIGTERM" and stop.exit_status == 143      # what a shell reports: 128 + 15
    # still alive, handlers back
    assert {s: signal.getsignal(s) for s in before} == before


def test_stop_signals_second_signal_goes_to_previous_handler():
    calls = []
    previous = signal.signal(signal.SIGINT, lambda signum, frame: calls.append(signum))
    try:
        with StopSignals() as stop:
            os.kill(os.getpid(), signal.SIGINT)
            assert _wait_for(lambda: stop.requested) and stop.signal_name == "SIGINT" and stop.exit_status == 130
            assert calls == []
            os.kill(os.getpid(), signal.SIGINT)
            assert _wait_for(lambda: calls == [signal.SIGINT])
        os.kill(os.getpid(), signal.SIGINT)  # restored: goes straight to the previous handler
        assert _wait_for(lambda: len(calls) == 2)
    finally:
        signal.signal(signal.SIGINT, previous)


def test_commit_timestamp_alone_counts_as_complete(tmp_path):
    """Checkpoints finalised by rename + commit timestamp only (older orbax) still resume."""
    state = _state(8, 2)
    with CheckpointStore(tmp_path) as store:
        store.save(4, state, CONFIG)
    (tmp_path / "4" / "commit_success.txt").unlink()
    with CheckpointStore(tmp_path) as store:
        assert store.latest_step() == 4
        _assert_bit_identical(store.restore(4, state)[0], state)


def test_damage_finds_unreadable_arrays_and_config_and_set_aside_frees_the_step(tmp_path):
    state = _state()
    with CheckpointStore(tmp_path / "checkpoints") as store:
        for step in (1, 2, 3):
            store.save(step, _run(state, step), CONFIG)
        assert [store.damage(s) for s in (1, 2, 3)] == [None, None, None]
        (tmp_path / "checkpoints" / "2" / "config" / "metadata").write_text("{ not json")
        for f in (tmp_path / "checkpoints" / "3" / "state").glob("ocdbt.process_*/d/*"):
            f.write_bytes(f.read_bytes()[:10])
        assert store.damage(1) is None and store.damage(2) and store.damage(3)
        assert store.damage(2).startswith("its saved flags (config/) do not read: Expecting property name")
        assert "Error reading" in store.damage(3)                   # tensorstore's words, naming the array
        moved = store.set_aside(3)
        assert moved == tmp_path / "checkpoints.damaged" / "3" and moved.is_dir()
        assert store.all_steps() == [1, 2] and store.latest_step() == 2
        assert store.save(3, _run(state, 3), CONFIG)                 # the step can be written again
        restored, _ = store.restore(3, _abstract(state))
    _assert_bit_identical(restored, _run(state, 3))


def test_abandoned_reads_of_a_damaged_step_print_no_traceback(monkeypatch):
    """A failed orbax read leaves coroutines that raise when collected; Python prints those as
    'Exception ignored in ...' tracebacks (through sys.unraisablehook). While a damaged step is
    checked they go to the debug log instead (the damage itself is reported once, by the caller)."""
    import gc
    import sys

    from jaxdistill.io.checkpoint import _quiet_abandoned_reads

    reported = []
    monkeypatch.setattr(sys, "unraisablehook", lambda u: reported.append(str(u.exc_value)))

    class Raises:
        def __del__(self):
            raise OSError("read of a damaged chunk")

    with _quiet_abandoned_reads():
        a = Raises()
        a.cycle = a          # collected by the gc.collect() on the way out, as abandoned coroutines are
        del a
    assert reported == []
    b = Raises()
    del b                    # outside, the hook that was installed before reports again
    gc.collect()
    assert reported == ["read of a damaged chunk"]


def test_fields_stored_as_none_by_older_versions_restore(tmp_path, monkeypatch):
    """A checkpoint that stored an unused optional field as None (jaxdistill before
    `stored_tree`) restores into a dataclass state whose field is None, with the other leaves
    bit-identical."""
    import dataclasses

    from jaxdistill.io import checkpoint

    @jax.tree_util.register_dataclass
    @dataclasses.dataclass(frozen=True)
    class State:
        texels: jax.Array
        step: jax.Array
        reused: jax.Array | None = None

        def replace(self, **kw):
            return dataclasses.replace(self, **kw)

    state = State(jnp.arange(6, dtype=jnp.float32).reshape(3, 2), jnp.int32(4))
    monkeypatch.setattr(checkpoint, "stored_tree", lambda s: dataclasses.asdict(s) if dataclasses.is_dataclass(s) else s)
    with CheckpointStore(tmp_path) as store:                  # the older layout: {"reused": None} on disk
        store.save(4, state, {})
    monkeypatch.undo()
    with CheckpointStore(tmp_path) as store:
        assert store._mngr.metadata(4).item_metadata["state"].tree["reused"] is None
        restored, _ = store.restore(4, State(jnp.zeros((3, 2)), jnp.int32(0)))
    assert restored.reused is None
    _assert_bit_identical((restored.texels, restored.step), (state.texels, state.step))
