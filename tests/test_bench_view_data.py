"""`scripts/bench_view_data.py` as a user runs it: both settings on a tiny scene, side by side,
and their ratio; the per-view arrays really were in files for the disk cases."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

from tiny_scene import write_tiny_scene

REPO = Path(__file__).resolve().parents[1]


def test_the_benchmark_runs_both_settings_and_gives_their_ratio(tmp_path):
    scene = write_tiny_scene(tmp_path / "scene", views=3)
    out = tmp_path / "bench.json"
    done = subprocess.run([sys.executable, "scripts/bench_view_data.py", f"--scene={scene}", "--steps=2", "--log_every=1",
                           "--repeats=1", "--views_per_step=2", f"--cache={tmp_path / 'cache'}", f"--json={out}"],
                          cwd=REPO, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-2000:]
    assert "disk / memory: s/step" in done.stdout
    doc = json.loads(out.read_text())
    assert [(r["view_data"], r["on_disk"]) for r in doc["rows"]] == [("memory", False), ("disk", True)]
    assert all(r["s_per_step"] > 0 and r["batch_s"] > 0 and r["peak_rss_gb"] > 0 for r in doc["rows"])
    assert doc["disk_over_memory"]["s_per_step"] > 0
