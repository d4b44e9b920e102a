"""`scripts/bench_view_data.py` as a user runs it: its three cases on a tiny scene, side by side,
and their ratios; the per-view arrays really were in files for the disk cases, the targets read
again from the scene's files in one (forced) and copied into a file in the other."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

from tiny_scene import write_tiny_scene

REPO = Path(__file__).resolve().parents[1]


def test_the_benchmark_runs_its_cases_and_gives_their_ratios(tmp_path):
    scene = write_tiny_scene(tmp_path / "scene", views=3)
    out = tmp_path / "bench.json"
    done = subprocess.run([sys.executable, "scripts/bench_view_data.py", f"--scene={scene}", "--steps=2", "--log_every=1",
                           "--repeats=1", "--views_per_step=2", f"--cache={tmp_path / 'cache'}", f"--json={out}"],
                          cwd=REPO, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-2000:]
    assert "disk / memory: s/step" in done.stdout and "disk_sources / memory: s/step" in done.stdout
    doc = json.loads(out.read_text())
    rows = {r["view_data"]: r for r in doc["rows"]}
    assert [(r["view_data"], r["on_disk"], r["targets_in"]) for r in doc["rows"]] == [
        ("memory", False, "ndarray"), ("disk", True, "ViewRows"), ("disk_sources", True, "SourceRows")]
    assert all(r["s_per_step"] > 0 and r["batch_s"] > 0 and r["peak_rss_gb"] > 0 for r in doc["rows"])
    # the targets' float32 copies (4 bytes x 11 channels a pixel) are what the disk case no longer writes
    height, width = rows["disk"]["render_hw"]
    copies = rows["disk"]["files_gb"] - rows["disk_sources"]["files_gb"]
    assert abs(copies * 2 ** 30 - 3 * height * width * 44) <= 1e-9 * 2 ** 30
    assert doc["ratios"]["disk_over_memory"]["s_per_step"] > 0
