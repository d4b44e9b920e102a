"""scripts/speed_vs_error.py end to end on the tiny scene (sweep) and a tiny random RGB<->X folder (part B)."""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
from pathlib import Path

import pytest

from tiny_scene import write_tiny_scene

REPO = Path(__file__).resolve().parents[1]
SCRIPT = REPO / "scripts" / "speed_vs_error.py"


def run_script(tmp_path, *extra) -> dict:
    env = dict(os.environ, JAXDISTILL_CACHE=str(tmp_path / "cache"))
    env.pop("JAXDISTILL_RGBX_DIR", None)
    proc = subprocess.run([sys.executable, str(SCRIPT), "--out_dir", str(tmp_path / "out"), "--json", *extra],
                          capture_output=True, text=True, env=env, cwd=REPO, timeout=600)
    assert proc.returncode == 0, proc.stderr[-4000:]
    return json.loads(proc.stdout.strip().splitlines()[-1]), proc.stdout


def test_sweep_on_the_tiny_scene(tmp_path):
    scene = write_tiny_scene(tmp_path / "scene")
    doc, stdout = run_script(tmp_path, "--quick", f"--scene={scene}", "--factors=steps,render",
                             "--steps_values=2,4", "--render_values=16,32")
    rows = doc["sweep"]
    # baseline (4 steps, native 32x24 = render 32), steps=2, render=16: the duplicates run once
    assert [r["factor"] for r in rows] == ["baseline", "steps", "render"]
    assert ["steps", "4"] in rows[0]["labels"] and ["render", "32 (native)"] in rows[0]["labels"]
    assert rows[1]["changed"] == {"steps": 2} and rows[2]["changed"] == {"render_size": 16}
    assert rows[2]["render_hw"] == [12, 16]
    for r in rows:
        assert r["wall_s"] == pytest.approx(r["setup_s"] + r["compile_s"] + r["steps_s"])
        assert r["traces"] == 1 and r["peak_rss_gb"] > 0 and math.isfinite(r["albedo_psnr"])
    assert math.isfinite(doc["per_view_estimates"]["albedo_psnr"])
    assert doc["pareto"] and "Pareto front" in stdout
    assert (tmp_path / "out" / "speed_vs_error.png").stat().st_size > 0
    assert json.loads((tmp_path / "out" / "speed_vs_error.json").read_text())["sweep"][0]["factor"] == "baseline"


def test_memory_guard_skips_a_point(tmp_path):
    scene = write_tiny_scene(tmp_path / "scene")
    doc, stdout = run_script(tmp_path, "--quick", f"--scene={scene}", "--factors=none", "--max_gb=0.5")
    assert "skipped" in doc["sweep"][0] and "skipped" in stdout


@pytest.mark.skipif(os.environ.get("JAXDISTILL_SLOW_TESTS") != "1", reason="part B compiles the tiny RGB<->X "
                    "networks 4 times (1-3 min on 2 cores); set JAXDISTILL_SLOW_TESTS=1 to run it")
def test_rgbx_dtype_on_a_tiny_folder(tmp_path, rgbx_dir):
    scene = write_tiny_scene(tmp_path / "scene")
    doc, stdout = run_script(tmp_path, f"--scene={scene}", f"--rgbx_dir={rgbx_dir}", "--rgbx_only",
                             "--rgbx_render_size=32", "--rgbx_t=20,500,980")
    b = doc["rgbx"]
    assert b["random_weights"] and "RANDOM WEIGHTS" in stdout
    assert [r["t"] for r in b["rows"]] == [20, 500, 980] and b["render_hw"] == [24, 32]
    for r in b["rows"]:
        assert 0 < r["latent_rel_l2"] < 0.2 and 0 < r["image_rel_l2"] < 0.2, r
    for kind in ("latent", "image"):
        assert b["timing"][kind]["fp32_median_s"] > 0 and b["timing"][kind]["bf16_median_s"] > 0
    assert (tmp_path / "out" / "rgbx_dtype.png").stat().st_size > 0


def test_bf16_networks_share_the_fp32_parameters(rgbx_dir):
    """Part B builds the bf16 networks on the fp32 load's parameters: load_rgbx(dtype=bf16) gives the same ones."""
    import jax
    import jax.numpy as jnp
    import numpy as np

    from jaxdistill.models import convert

    a = convert.load_rgbx(rgbx_dir, dtype=jnp.float32).params
    b = convert.load_rgbx(rgbx_dir, dtype=jnp.bfloat16).params
    assert jax.tree.structure(a) == jax.tree.structure(b)
    assert all(x.dtype == np.float32 and np.array_equal(x, y) for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b)))
