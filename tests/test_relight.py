"""Relighting: a run whose maps are the GT pages relights exactly like GT; a grey albedo does not."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from jaxdistill.evaluate.ground_truth import read_ground_truth
from jaxdistill.scene.model import read_scene
from tiny_scene import write_tiny_scene

pytest.importorskip("mitsuba")


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    folder = tmp_path_factory.mktemp("tiny")
    write_tiny_scene(folder, views=4)
    return read_scene(folder)


def fake_run(folder, scene, albedo=None):
    """A run folder whose maps/ the exporter writes from the GT pages (albedo replaced if given)."""
    from jaxdistill.export.pages import write_maps

    pages = dict(read_ground_truth(scene).pages)
    if albedo is not None:
        pages["albedo"] = [np.full_like(p, albedo) for p in pages["albedo"]]
    write_maps(folder, pages, scene.mesh.object_names, list(range(scene.num_objects)))
    return folder


def test_identical_maps_relight_identically_and_grey_albedo_does_not(tiny, tmp_path):
    from jaxdistill.evaluate import relight as rl

    same, sources = rl.read_run_pages(fake_run(tmp_path / "same", tiny), tiny.mesh.object_names)
    assert sources == {"albedo": "exr", "roughness": "exr", "metallic": "exr"}
    grey, _ = rl.read_run_pages(fake_run(tmp_path / "grey", tiny, albedo=0.5), tiny.mesh.object_names)
    views = rl.default_views(6, len(tiny.views))
    assert views == [0, 1, 2, 3]
    a = rl.relight(tiny, same, views=views, spp=4, seed=3)
    b = rl.relight(tiny, grey, views=views, spp=4, seed=3)
    assert all(m.mean() > 0.9 for m in a.masks)
    for x in a.gt + a.run:
        assert np.isfinite(x).all() and x.max() > 0
    for x, y in zip(a.gt, a.run):
        np.testing.assert_allclose(x, y, rtol=1e-6, atol=1e-7)     # same pages, same samples
    assert min(a.psnr_db) >= 60
    assert a.stops == b.stops                                      # the exposure comes from the GT renders
    assert max(b.psnr_db) < 30 and np.mean(b.psnr_db) < np.mean(a.psnr_db) - 30
    report = rl.summary(b, scene_name="tiny", run_dir=tmp_path / "grey", light="centre",
                        position=rl.light_position(tiny.mesh, "centre"), spp=4, seed=3, max_depth=5, sources={})
    assert math.isclose(report["mean_psnr_db"], float(np.mean(b.psnr_db)))
    assert len(rl.write_figures(tmp_path / "figures", b)) == 2 * len(views) + 1


def test_light_positions_lie_inside_the_room(tiny):
    from jaxdistill.evaluate import relight as rl

    lo, hi = tiny.mesh.vertices.min(0), tiny.mesh.vertices.max(0)
    for name in rl.LIGHTS:
        p = rl.light_position(tiny.mesh, name)
        assert np.all(p > lo + 0.2 * (hi - lo)) and np.all(p < hi - 0.2 * (hi - lo))
    np.testing.assert_allclose(rl.light_position(tiny.mesh, rl.parse_light("0.5,0.5,0.5")), (lo + hi) / 2)
    with pytest.raises(ValueError):
        rl.parse_light("ceiling")
    with pytest.raises(ValueError):
        rl.light_position(tiny.mesh, (0.5, 1.2, 0.5))


def test_script_writes_the_report_and_figures(tiny, tmp_path):
    import subprocess
    import sys
    from pathlib import Path

    script = Path(__file__).resolve().parents[1] / "scripts" / "relight.py"
    run = fake_run(tmp_path / "run", tiny)
    out = tmp_path / "relight.json"
    done = subprocess.run([sys.executable, str(script), f"--scene={tiny.root}", f"--run={run}", f"--out={out}",
                           "--views=v1,3", "--spp=2", "--light=offset"], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr[-2000:]
    report = json.loads(out.read_text())
    assert list(report["psnr_db"]) == ["v1", "v3"] and report["mean_psnr_db"] >= 60
    assert (tmp_path / "relight" / "sheet.png").is_file()
