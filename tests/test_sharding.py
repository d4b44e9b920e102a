"""Data parallelism: the batch of views sharded over a "data" mesh axis, texels and optimizer state
replicated, XLA reducing the gradients. With 2 simulated CPU devices the step gives the 1-device
result within float32 tolerance.

The device count is fixed when JAX starts, so the check runs in a fresh process
(tests/sharding_check.py) with XLA_FLAGS=--xla_force_host_platform_device_count=2.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

HERE = Path(__file__).resolve().parent


@pytest.fixture(scope="module")
def two_device_result(tmp_path_factory):
    work = tmp_path_factory.mktemp("sharding")
    env = dict(os.environ)
    env["XLA_FLAGS"] = (env.get("XLA_FLAGS", "") + " --xla_force_host_platform_device_count=2").strip()
    env["JAX_PLATFORMS"] = "cpu"
    env["JAXDISTILL_CACHE"] = str(work / "jaxdistill_cache")
    env.pop("JAXDISTILL_RGBX_DIR", None)             # prior="views" regardless
    proc = subprocess.run([sys.executable, str(HERE / "sharding_check.py"), str(work)], env=env, cwd=HERE.parent,
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, f"sharding_check.py failed:\n{proc.stdout[-4000:]}\n{proc.stderr[-4000:]}"
    lines = [line for line in proc.stdout.splitlines() if line.startswith("RESULT ")]
    assert lines, f"no RESULT line:\n{proc.stdout[-4000:]}\n{proc.stderr[-4000:]}"
    return json.loads(lines[-1][len("RESULT "):])


def test_two_devices_give_the_one_device_result(two_device_result):
    r = two_device_result
    assert r["devices"] == 2
    assert r["texels_moved"] > 1e-3                           # the steps did change the texels
    assert max(abs(v) for v in r["texel_range"]) <= 1.5         # model-space values, about [-1, 1]
    assert r["max_abs_diff"] <= 1e-5, r["max_abs_diff"]
    np.testing.assert_allclose(r["losses_2"], r["losses_1"], rtol=1e-5)
    np.testing.assert_allclose(r["grad_norms_2"], r["grad_norms_1"], rtol=1e-5)
    assert len(set(r["losses_1"])) == len(r["losses_1"])        # the steps differ (views, dropout masks)
    assert r["traces_1"] == 1 and r["traces_2"] == 1


def test_batch_is_sharded_by_view_and_state_replicated(two_device_result):
    c = two_device_result["checks"]
    assert c["batch_devices"] == [2]                            # every batch leaf spans both devices
    assert c["batch_shard_count"] == [2] and c["batch_shard_rows"] == [2]    # 4 views: 2 per device
    assert c["index_rows_per_device"] == [[0, 2], [2, 4]]
    assert c["index_device_ids"] == [0, 1]
    assert c["texels_replicated"] and c["texels_devices"] == 2 and c["texels_shards_identical"]
    assert c["all_reduce_in_hlo"]


def test_views_per_step_must_split_over_the_devices(two_device_result):
    message = two_device_result["rejected"]
    assert message is not None, "train.run accepted --views_per_step=3 on 2 devices"
    assert "--views_per_step" in message and "2 devices" in message
    assert not two_device_result["bad_run_wrote_outputs"]
