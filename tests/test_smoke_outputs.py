"""The smoke run end to end through the `jaxdistill` command (configs/smoke.cfg, views prior): the
Khronos glTF-Validator on its scene.glb, its cameras against scene.json, the console summary."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from jaxdistill.scene.cameras import from_opencv
from jaxdistill.scenes import scene_path
from test_export import gltf_projection, read_glb
from tolerance import assert_close

REPO = Path(__file__).resolve().parents[1]
SMOKE_VIEWS = 16
VALIDATOR = Path(os.environ.get("JAXDISTILL_TOOLS", REPO / ".tools")) / "node" / "node_modules"


@pytest.fixture(scope="module")
def smoke(tmp_path_factory):
    """(out_dir, console output) of `python -m jaxdistill distill --flagfile=configs/smoke.cfg --prior=views
    --max_views=16`: 16 of the bedroom's 48 views, evenly spread (a third of the set-up and outputs;
    the glTF, its cameras and the console are made the same way for any number of views)."""
    out = tmp_path_factory.mktemp("smoke") / "out"
    env = {**os.environ, "JAXDISTILL_CACHE": str(tmp_path_factory.getbasetemp() / "fragment_cache")}
    run = subprocess.run([sys.executable, "-m", "jaxdistill", "distill", "--flagfile=configs/smoke.cfg",
                          "--prior=views", f"--max_views={SMOKE_VIEWS}", f"--out_dir={out}"], cwd=REPO, env=env,
                         capture_output=True, text=True, timeout=900)
    assert run.returncode == 0, run.stderr[-4000:]
    return out, run.stdout + run.stderr


def test_gltf_validator_reports_no_error_and_no_warning(smoke):
    if shutil.which("node") is None:
        pytest.skip("node is not installed: the Khronos glTF-Validator (npm gltf-validator) needs Node.js")
    assert (VALIDATOR / "gltf-validator").is_dir(), (
        f"gltf-validator is not installed in {VALIDATOR}: run `bash scripts/install_test_tools.sh` "
        "(the README's test command does)")
    out, _ = smoke
    run = subprocess.run(["node", str(REPO / "scripts" / "validate_gltf.js"), str(VALIDATOR), str(out / "scene.glb")],
                         capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr
    report = json.loads(run.stdout)
    issues = [m for m in report["issues"]["messages"] if m["severity"] <= 1]
    assert report["issues"]["numErrors"] == 0 and report["issues"]["numWarnings"] == 0, issues[:10]
    assert report["info"]["totalTriangleCount"] == 498


def test_gltf_cameras_are_the_views_of_scene_json(smoke):
    out, _ = smoke
    doc, _ = read_glb(out / "scene.glb")
    scene = json.loads((scene_path("bedroom") / "scene.json").read_text())
    nodes = {n["name"]: n for n in doc["nodes"] if "camera" in n}
    picks = np.linspace(0, len(scene["views"]) - 1, SMOKE_VIEWS).round().astype(int)     # --max_views' choice
    used = [scene["views"][i] for i in picks]
    assert len(nodes) == SMOKE_VIEWS and sorted(nodes) == sorted(v["name"] for v in used)
    points = np.random.default_rng(1).uniform([0.5, 0.2, 0.5], [3.5, 2.3, 3.0], (50, 3))   # inside the room
    for view in used:
        camera = from_opencv(view["K"], view["c2w"], width=view["width"], height=view["height"])
        expected, depth = camera.project(points)
        front = depth > 0
        pixels, cam = gltf_projection(doc, nodes[view["name"]])
        assert cam["name"] == view["name"]
        assert_close(pixels(points[front]), expected[front], rtol=1e-6)


def test_console_ends_with_a_summary_and_shows_eval_psnr_while_running(smoke):
    out, console = smoke
    metrics = json.loads((out / "metrics.json").read_text())
    assert "albedo_psnr=" in console                                     # the progress bar, --eval_every=10
    table = console[console.index("metric "):]
    row = next(line for line in table.splitlines() if line.startswith("albedo PSNR (dB)"))
    ours, estimates = (float(x) for x in row.split()[3:5])
    assert ours == pytest.approx(metrics["ours"]["albedo_psnr"], rel=1e-3)
    assert estimates == pytest.approx(metrics["baseline_per_view_estimates"]["albedo_psnr"], rel=1e-3)
    assert f"outputs in {out}" in table and "wall time" in table


def test_metrics_report_seams_for_ours_and_the_estimates(smoke):
    out, _ = smoke
    metrics = json.loads((out / "metrics.json").read_text())
    for block in ("ours", "baseline_per_view_estimates"):
        for m in ("albedo", "normal", "roughness", "metallic"):
            values = metrics[block]
            assert values[f"{m}_seam_energy"] >= 0 and values[f"{m}_seam_energy_gt"] > 0
            assert values[f"{m}_seam_excess"] == pytest.approx(
                values[f"{m}_seam_energy"] - values[f"{m}_seam_energy_gt"], rel=1e-9, abs=1e-12)
            if values[f"{m}_seam_ratio"] is not None:
                assert values[f"{m}_seam_ratio"] == pytest.approx(
                    values[f"{m}_seam_energy"] / values[f"{m}_seam_energy_gt"], rel=1e-9)
    checkpoints = [p for p in (out / "checkpoints").iterdir() if p.name.isdigit()]
    assert len(checkpoints) == 1                                          # smoke saves only at the end
