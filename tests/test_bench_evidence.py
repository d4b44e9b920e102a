"""`scripts/bench_evidence.py` as a user runs it: the evidence's statistics of this checkout against
a git revision's, on a tiny scene; against HEAD~0 of an unchanged file the two sides agree exactly."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
from tiny_scene import write_tiny_scene

REPO = Path(__file__).resolve().parents[1]


def test_the_benchmark_times_both_sides_and_compares_their_statistics(tmp_path):
    if subprocess.run(["git", "-C", str(REPO), "rev-parse", "HEAD"], capture_output=True).returncode:
        pytest.skip("not a git checkout")
    scene = write_tiny_scene(tmp_path / "scene", views=3)
    out = tmp_path / "bench.json"
    done = subprocess.run([sys.executable, "scripts/bench_evidence.py", f"--scene={scene}", "--prior=views",
                           "--steps=1", "--views_per_step=2", "--against=HEAD", "--bench_repeats=2",
                           f"--out_dir={tmp_path / 'out'}", f"--bench_json={out}"],
                          cwd=REPO, capture_output=True, text=True, timeout=600,
                          env={**os.environ, "JAXDISTILL_CACHE": str(tmp_path / "cache")})
    assert done.returncode == 0, done.stderr[-2000:]
    assert "now / then" in done.stdout
    doc = json.loads(out.read_text())
    assert doc["views"] == 3 and doc["maps"] and doc["num_texels"] > 0
    assert all(len(s) == 2 and min(s) > 0 for s in doc["seconds"].values())
    assert doc["now_over_then"] > 0
    assert doc["apart"]["counts_equal"] and doc["apart"]["nan_equal"]
    # HEAD's file against this checkout's: equal, or (with the file changed but not committed) within rounding
    assert doc["apart"]["mean"] < 1e-5 and doc["apart"]["variance"] < 1e-4


def test_an_unknown_revision_is_named():
    done = subprocess.run([sys.executable, "scripts/bench_evidence.py", "--against=no-such-revision"],
                          cwd=REPO, capture_output=True, text=True, timeout=120)
    assert done.returncode != 0
    assert "--against=no-such-revision" in done.stderr + done.stdout
