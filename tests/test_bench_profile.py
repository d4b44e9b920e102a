"""`scripts/bench_profile.py` as a user runs it: the main job's compiled step profiled stage by
stage on a tiny scene with a tiny RGB↔X model, x̂0 reused every second step (as
configs/bedroom.cfg) and the re-rendering term on. The prior's networks show only in the step
that runs them; the texels' stages (found by the named scopes of `render.sampler` and
`engine.step`) in both, and the longest operations each in the stage of its scope."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

from tiny_scene import write_tiny_scene

REPO = Path(__file__).resolve().parents[1]


def test_the_profile_splits_each_kind_of_step_into_its_stages(run_rgbx_dir, tmp_path):
    scene = write_tiny_scene(tmp_path / "scene", views=3)
    out = tmp_path / "profile.json"
    done = subprocess.run([sys.executable, "scripts/bench_profile.py", f"--scene={scene}", "--prior=rgbx",
                           f"--rgbx_dir={run_rgbx_dir}", "--maps=albedo,irradiance", "--render_size=32", "--reuse_steps=2",
                           "--views_per_step=2", "--sampler=trilinear", "--photo_weight=1", "--steps=10",
                           f"--out_dir={tmp_path / 'out'}", "--profile_steps=1", f"--profile_json={out}",
                           f"--profile_trace={tmp_path / 'trace'}"],
                          cwd=REPO, capture_output=True, text=True, timeout=600,
                          env={**os.environ, "JAXDISTILL_CACHE": str(tmp_path / "cache")})
    assert done.returncode == 0, done.stderr[-3000:]
    doc = json.loads(out.read_text())
    assert set(doc["step_s"]) == {"prior", "reused"} and all(s > 0 for s in doc["step_s"].values())
    assert doc["step_gflop"] > 0 and doc["compile_s"] > 0
    prior, reused = doc["stages_s"]["prior"], doc["stages_s"]["reused"]
    for stage in ("VAE encode", "UNet", "VAE decode"):          # the prior's pass: only where it runs
        assert prior[stage] > 0 and reused[stage] == 0, stage
    # the texels' side in both, each stage found by the named scope of the code it came from
    for stage in ("taps (gathers)", "taps' transpose (scatter-adds)", "taps weighted", "pyramid", "photo term",
                  "AdamW and the finite gate"):
        assert prior[stage] > 0 and reused[stage] > 0, stage
    scoped = {"transpose(jvp(taps))": "taps' transpose (scatter-adds)", "jvp(taps)/": "taps (gathers)",
              "/update/": "AdamW and the finite gate", "UNet2DCondition": "UNet"}
    tops = [op for ops in doc["top_ops"].values() for op in ops]
    assert tops and all(op["stage"] for op in tops)
    for op in tops:                                   # the longest operations: each in the stage of its scope
        for marker, stage in scoped.items():
            if marker in op["op_name"]:
                assert op["stage"] == stage, op
                break
    assert "UNet" in done.stdout and "all operations" in done.stdout
    assert list((tmp_path / "trace").rglob("*.trace.json.gz"))             # the trace kept for a viewer
    bad = subprocess.run([sys.executable, "scripts/bench_profile.py", f"--scene={scene}", "--profile_steps=0"],
                         cwd=REPO, capture_output=True, text=True, timeout=300)
    assert bad.returncode != 0 and "--profile_steps" in bad.stderr
