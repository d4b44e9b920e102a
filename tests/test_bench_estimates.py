"""`scripts/bench_estimates.py` as a user runs it: the estimates phase at two batch sizes (and two
step counts), side by side, on a tiny scene and model; the pairs are counted and the first case's
ratio is 1."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

from tiny_scene import write_tiny_scene

REPO = Path(__file__).resolve().parents[1]


def test_the_benchmark_times_each_batch_size_and_gives_their_ratio(run_rgbx_dir, tmp_path):
    scene = write_tiny_scene(tmp_path / "scene", views=3, width=32, height=24)
    out = tmp_path / "bench.json"
    done = subprocess.run([sys.executable, "scripts/bench_estimates.py", f"--scene={scene}", f"--rgbx_dir={run_rgbx_dir}",
                           "--batches=2,4", "--steps=1", "--maps=albedo,roughness", "--render_size=32", "--repeats=1",
                           f"--json={out}"], cwd=REPO, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-2000:]
    assert "3 views x 2 maps = 6 pairs at 32x24" in done.stdout
    assert "2 pairs a call at most (3 calls of 2, 0 padded), 1 steps" in done.stdout
    assert "4 pairs a call at most (2 calls of 3, 0 padded), 1 steps" in done.stdout
    doc = json.loads(out.read_text())
    assert doc["pairs"] == 6 and doc["size"] == [24, 32] and doc["ratio_to_first"]["2"] == 1.0
    assert all(len(s) == 1 and s[0] > 0 for s in doc["seconds"].values())
    steps = subprocess.run([sys.executable, "scripts/bench_estimates.py", f"--scene={scene}", f"--rgbx_dir={run_rgbx_dir}",
                            "--batches=4", "--steps=2,1", "--maps=albedo", "--render_size=32", "--repeats=1",
                            f"--json={out}"], cwd=REPO, capture_output=True, text=True, timeout=600)
    assert steps.returncode == 0, steps.stderr[-2000:]
    doc = json.loads(out.read_text())
    assert doc["steps"] == [2, 1] and list(doc["median_s"]) == ["4x2", "4x1"] and doc["ratio_to_first"]["4x2"] == 1.0
    bad = subprocess.run([sys.executable, "scripts/bench_estimates.py", "--batches=0"], cwd=REPO,
                         capture_output=True, text=True, timeout=120)
    assert bad.returncode == 2 and "must be positive" in bad.stderr
