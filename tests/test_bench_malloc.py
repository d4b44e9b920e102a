"""`scripts/bench_malloc.py` as a user runs it: the three malloc forms in their own processes on a
tiny scene (the huge-page tunable in the `huge` child's environment only), their steps timed with
their page faults, and the same texels."""

from __future__ import annotations

import json
import os
import platform
import subprocess
import sys
from pathlib import Path

import pytest

from tiny_scene import write_tiny_scene

REPO = Path(__file__).resolve().parents[1]


def test_the_benchmark_times_each_form_with_the_same_texels(tmp_path):
    if platform.libc_ver()[0] != "glibc":
        pytest.skip("not glibc: there is no second form to compare")
    scene = write_tiny_scene(tmp_path / "scene", views=3)
    flagfile = tmp_path / "tiny.cfg"
    flagfile.write_text("\n".join([f"--scene={scene}", "--prior=views", "--maps=albedo,irradiance", "--render_size=16",
                                   "--views_per_step=2", "--steps=4", "--sampler=trilinear", ""]))
    out = tmp_path / "bench.json"
    done = subprocess.run([sys.executable, "scripts/bench_malloc.py", f"--flagfile={flagfile}", "--steps=2",
                           "--repeats=1", "--set=lr=0.1", f"--json={out}"],
                          cwd=REPO, capture_output=True, text=True, timeout=600,
                          env={**os.environ, "JAXDISTILL_CACHE": str(tmp_path / "cache")})
    assert done.returncode == 0, done.stderr[-3000:]
    doc = json.loads(out.read_text())
    assert [r["form"] for r in doc["runs"]] == ["system", "keep", "huge"] and doc["texels_identical"]
    tunables = {r["form"]: r["glibc_tunables"] for r in doc["runs"]}
    assert tunables["huge"] == "glibc.malloc.hugetlb=1" and "hugetlb" not in tunables["system"] + tunables["keep"]
    assert all(r["wall_s"] > 0 and isinstance(r["minor_faults"], int) and r["peak_rss_gb"] > 0 for r in doc["runs"])
    assert doc["keep_settings"]["M_ARENA_MAX"] == 1 and doc["set"] == ["lr=0.1"]
    assert set(doc["ratio_to_first"]) == {"keep", "huge"} and doc["ratio_to_first"]["huge"]["wall_s"] > 0
    assert "keep / system" in done.stdout and "huge / system" in done.stdout and "identical" in done.stdout
    bad = subprocess.run([sys.executable, "scripts/bench_malloc.py", "--forms=system,tiny"], cwd=REPO,
                         capture_output=True, text=True, timeout=60)
    assert bad.returncode == 2 and "--forms=system,tiny" in bad.stderr
