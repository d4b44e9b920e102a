"""scripts/bench_xla_flags.py on the smallest case (the UNet alone at batch 1, one repeat): both
settings run in processes of their own, the children's XLA_FLAGS show which is which, and the
ratios are theirs. The VAE's rows are the same code path (`time_calls`) with another network."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def test_the_benchmark_runs_both_settings_in_their_own_processes(tmp_path):
    out = tmp_path / "flags.json"
    env = dict(os.environ)
    env.pop("JAXDISTILL_XLA_FLAGS", None)        # as in a user's shell: the script's own import sets the flags
    proc = subprocess.run([sys.executable, "scripts/bench_xla_flags.py", "--batches=1", "--networks=unet", "--repeats=1",
                           f"--json={out}"],
                          cwd=REPO, capture_output=True, text=True, env=env, timeout=600)
    assert proc.returncode == 0, proc.stderr[-2000:]
    data = json.loads(out.read_text())
    (flags,), (defaults,) = data["rows"]["flags"], data["rows"]["defaults"]
    assert "--xla_cpu_experimental_ynn_fusion_type=" in flags["xla_flags"].split()
    assert "ynn_fusion_type" not in defaults["xla_flags"]
    keys = {"unet_b1_s"}
    assert {k for k in flags if k.endswith("_s")} == keys == {k for k in defaults if k.endswith("_s")}
    for k in keys:
        assert data["ratios_flags_over_defaults"][k] == flags[k] / defaults[k] > 0
    assert "unet_b1_s" in proc.stdout and "ratio" in proc.stdout


def test_the_benchmark_refuses_xla_flags_that_name_its_flag_already():
    env = dict(os.environ, XLA_FLAGS="--xla_cpu_experimental_ynn_fusion_type=dot")
    env.pop("JAXDISTILL_XLA_FLAGS", None)
    proc = subprocess.run([sys.executable, "scripts/bench_xla_flags.py", "--batches=1", "--repeats=1"], cwd=REPO,
                          capture_output=True, text=True, env=env, timeout=600)
    assert proc.returncode == 2 and "names --xla_cpu_experimental_ynn_fusion_type=" in proc.stderr
    env.pop("XLA_FLAGS")
    proc = subprocess.run([sys.executable, "scripts/bench_xla_flags.py", "--networks=unet,vae"], cwd=REPO,
                          capture_output=True, text=True, env=env, timeout=600)
    assert proc.returncode == 2 and "--networks: unknown vae" in proc.stderr
