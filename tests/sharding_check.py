"""Run by tests/test_sharding.py in a fresh process with 2 simulated CPU devices
(XLA_FLAGS=--xla_force_host_platform_device_count=2): the data-parallel step on a 2-device mesh
against the same steps on a 1-device mesh. Prints one JSON line (prefixed RESULT) for the test.

Usage: python tests/sharding_check.py WORK_DIR
"""

from __future__ import annotations

import json
import sys
import tempfile
from pathlib import Path

import jax
import numpy as np

from jaxdistill.engine import config as config_lib
from jaxdistill import pipeline
from jaxdistill.engine import loop
from jaxdistill.engine.config import DistillConfig
from jaxdistill.engine.step import StepSettings, data_mesh, init_state, jit_step, make_optimizer, make_step
from jaxdistill.errors import InputError
from jaxdistill.engine.problem import build_problem
from tiny_scene import write_tiny_scene

STEPS = 5
VIEWS = 4
SEED = 7


def run_on(mesh, problem, settings, optimizer, checks: dict | None = None):
    """STEPS steps of the jitted step on `mesh` (as train.run places state, batch and frozen)."""
    state = init_state(problem.initial_texels(), optimizer, SEED)
    first = problem.batch(problem.view_ids(0, VIEWS, SEED))
    step_fn, traces = jit_step(make_step(problem.prior, settings, optimizer), mesh, first, state, problem.frozen)
    replicated = jax.sharding.NamedSharding(mesh, jax.sharding.PartitionSpec())
    by_view = jax.sharding.NamedSharding(mesh, jax.sharding.PartitionSpec("data"))
    state = jax.device_put(state, replicated)
    frozen = jax.device_put(problem.frozen, replicated)
    losses, grad_norms = [], []
    batch = None
    for step in range(STEPS):
        batch = jax.device_put(problem.batch(problem.view_ids(step, VIEWS, SEED)), by_view)
        state, metrics = step_fn(state, batch, frozen)
        metrics = jax.device_get(metrics)
        assert metrics["finite"] == 1, metrics
        losses.append(float(metrics["loss"]))
        grad_norms.append(float(metrics["grad_norm"]))
    num_traces = traces.traces
    if checks is not None:
        n = len(mesh.devices.flat)
        for name, leaf in jax.tree_util.tree_leaves_with_path(batch):
            shards = leaf.addressable_shards
            checks.setdefault("batch_devices", set()).add(len(leaf.sharding.device_set))
            checks.setdefault("batch_shard_rows", set()).update(s.data.shape[0] for s in shards)
            checks.setdefault("batch_shard_count", set()).add(len(shards))
            assert not leaf.sharding.is_fully_replicated, jax.tree_util.keystr(name)
        # the views each device holds: disjoint halves of the step's views
        index = batch["index"]
        rows = sorted(tuple(s.index[0].indices(VIEWS)[:2]) for s in index.addressable_shards)
        checks["index_rows_per_device"] = rows
        checks["index_device_ids"] = sorted(s.device.id for s in index.addressable_shards)
        for leaf in jax.tree.leaves(state):
            assert leaf.sharding.is_fully_replicated and len(leaf.sharding.device_set) == n
        checks["texels_replicated"] = bool(state.texels.sharding.is_fully_replicated)
        checks["texels_devices"] = len(state.texels.sharding.device_set)
        shard_texels = [np.asarray(s.data) for s in state.texels.addressable_shards]
        checks["texels_shards_identical"] = all(np.array_equal(shard_texels[0], t) for t in shard_texels)
        # XLA reduces the gradient (and loss) across the data axis: the program has an all-reduce
        hlo = step_fn.lower(state, batch, frozen).compile().as_text()
        checks["all_reduce_in_hlo"] = "all-reduce" in hlo
        checks = {k: sorted(v) if isinstance(v, set) else v for k, v in checks.items()}
    return np.asarray(jax.device_get(state.texels)), losses, grad_norms, num_traces, checks


def main(work: Path) -> None:
    assert len(jax.devices()) == 2, jax.devices()
    scene = write_tiny_scene(work / "scene", views=4)
    config = DistillConfig(scene=str(scene), out_dir="unused", prior="views", views_per_step=VIEWS, p_keep=0.8,
                           seed=SEED)
    problem = build_problem(config, cache_dir=work / "cache")
    settings = StepSettings(channels=problem.channels, height=problem.height, width=problem.width,
                            total_steps=STEPS, p_keep=0.8)
    optimizer = make_optimizer(0.01, 0.01)

    one_device = data_mesh(jax.devices()[:1])
    one_texels, one_losses, one_grads, one_traces, _ = run_on(one_device, problem, settings, optimizer)
    checks: dict = {}
    two_texels, two_losses, two_grads, two_traces, checks = run_on(data_mesh(), problem, settings, optimizer, checks)
    start = problem.initial_texels()

    # views_per_step not divisible by the device count is refused by train.run before any compute
    bad = config_lib.validate(DistillConfig(scene=str(scene), out_dir=str(work / "run_bad"), prior="views",
                                            views_per_step=3, steps=1))
    try:
        pipeline.run(bad, progress=False)
        rejected = None
    except InputError as e:
        rejected = str(e)

    result = {
        "devices": len(jax.devices()),
        "max_abs_diff": float(np.max(np.abs(one_texels - two_texels))),
        "texels_moved": float(np.max(np.abs(two_texels - start))),
        "texel_range": [float(two_texels.min()), float(two_texels.max())],
        "losses_1": one_losses, "losses_2": two_losses,
        "grad_norms_1": one_grads, "grad_norms_2": two_grads,
        "traces_1": one_traces, "traces_2": two_traces,
        "checks": checks, "rejected": rejected,
        "bad_run_wrote_outputs": (work / "run_bad" / "checkpoints").exists(),
    }
    print("RESULT " + json.dumps(result))


if __name__ == "__main__":
    if len(sys.argv) > 1:
        main(Path(sys.argv[1]))
    else:
        with tempfile.TemporaryDirectory() as d:
            main(Path(d))
