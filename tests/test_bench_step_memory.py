"""`scripts/bench_step_memory.py` as a user runs it: the step's three forms on a tiny scene with a
tiny RGB↔X model, x̂0 reused every second step (as configs/bedroom.cfg) and the re-rendering term
on: XLA's memory of each, steps of each side by side (the state donated, run after run), and the
same texels."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

from tiny_scene import write_tiny_scene

REPO = Path(__file__).resolve().parents[1]


def test_the_benchmark_gives_each_forms_memory_and_steps_with_the_same_texels(run_rgbx_dir, tmp_path):
    scene = write_tiny_scene(tmp_path / "scene", views=3)
    out = tmp_path / "bench.json"
    done = subprocess.run([sys.executable, "scripts/bench_step_memory.py", f"--scene={scene}", "--prior=rgbx",
                           f"--rgbx_dir={run_rgbx_dir}", "--maps=albedo,irradiance", "--render_size=32", "--reuse_steps=2",
                           "--views_per_step=2", "--sampler=trilinear", "--photo_weight=1", "--steps=4", "--log_every=2",
                           f"--out_dir={tmp_path / 'out'}", "--bench_steps=4", "--bench_repeats=2", "--bench_loop",
                           f"--bench_json={out}"],
                          cwd=REPO, capture_output=True, text=True, timeout=600,
                          env={**os.environ, "JAXDISTILL_CACHE": str(tmp_path / "cache")})
    assert done.returncode == 0, done.stderr[-3000:]
    doc = json.loads(out.read_text())
    forms = doc["forms"]
    assert list(forms) == ["optax_where_concat", "gated_concat", "gated_split"]
    assert all(f["temp"]["gb"] > 0 and f["argument"]["arrays"] >= 3 for f in forms.values())   # texels, mu, nu
    assert all(f["prior_s"] > 0 and f["reused_s"] > 0 for f in forms.values())     # both kinds of step ran
    assert forms["gated_concat"]["texels_max_rel_diff"] <= 1e-6                    # optax's arithmetic
    # the same gather, split: the same sums in float32, their order as XLA fuses each form (the renders'
    # and photos' taps in one gather, sampler.sample_many, leave 5e-6 after these 8 steps); a wrong
    # tap or weight would be off by the texels' own scale
    assert forms["gated_split"]["texels_max_rel_diff"] <= 2e-5
    assert "gated_split" in done.stdout and "temporaries" in done.stdout
    main_job = doc["main_job"]                           # --bench_loop: the main job's set-up and loop first
    assert main_job["loop_peak_gb"] >= main_job["setup_peak_gb"] > 0 and main_job["loop_s"] > 0
    assert main_job["loss"] > 0
    # the step compiled apart, and two windows of two steps: their median is their mean, so the steps'
    # seconds fit in the loop's beside the compilation (and the evaluation, left out of the windows)
    assert main_job["compile_s"] > 0 and main_job["s_per_step"] > 0
    assert main_job["s_per_step"] * 4 + main_job["compile_s"] <= main_job["loop_s"]
    bad = subprocess.run([sys.executable, "scripts/bench_step_memory.py", f"--scene={scene}", "--bench_repeats=0"],
                         cwd=REPO, capture_output=True, text=True, timeout=300)
    assert bad.returncode != 0 and "--bench_repeats" in bad.stderr
