"""The precompute command end to end on a small scene written by the test."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np

from jaxdistill.io import images as imageio
from jaxdistill.precompute import PrecomputeConfig, run
from test_scene import make_scene_folder


def test_precompute_writes_visibility_and_summary(tmp_path):
    _, path = make_scene_folder(tmp_path / "scene")
    summary = run(PrecomputeConfig(scene=str(path), out_dir=str(tmp_path / "out"), texture_size="32",
                                   cache_dir=str(tmp_path / "cache")))
    assert summary["views"] == 2 and summary["parameters"] < summary["full_page_texels"]
    assert summary["observed_texels"] == summary["parameters"]  # bilinear, tile 1: every parameter is seen
    assert json.loads((tmp_path / "out" / "precompute.json").read_text())["parameters"] == summary["parameters"]
    pngs = sorted((tmp_path / "out" / "visibility").glob("*.png"))
    assert len(pngs) == 24  # one page per object of the furnished room
    counts = np.concatenate([imageio.read_image(p.with_suffix(".exr")).ravel() for p in pngs])
    assert counts.max() == 2 and counts.sum() > 0
    weights = imageio.read_image(tmp_path / "out" / "weights" / "a.png", linear=False)
    assert weights.shape == (24, 32, 1) and 0.19 < weights.max() <= 1.0


def test_precompute_cli_reports_bad_flags(tmp_path):
    result = subprocess.run([sys.executable, "-m", "jaxdistill.precompute", f"--scene={tmp_path}/nope",
                             f"--out_dir={tmp_path}/out", "--texture_size=300"], capture_output=True, text=True)
    assert result.returncode != 0 and "--texture_size: must be 'auto' or a power of two" in result.stderr
    result = subprocess.run([sys.executable, "-m", "jaxdistill.precompute", f"--scene={tmp_path}/nope",
                             f"--out_dir={tmp_path}/out"], capture_output=True, text=True)
    assert result.returncode != 0 and "nope not found (give scene.json, its folder" in result.stderr
