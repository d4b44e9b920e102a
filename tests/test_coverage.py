"""Coverage: the fraction of each view's pixels that hit the mesh, against an analytic plane;
a scene no view sees stops before compute (main job and import), a blind view is named."""

from __future__ import annotations

import json
import logging
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

import dataset_fixtures as fx
from jaxdistill.scene import cameras
from jaxdistill.engine.config import DistillConfig
from jaxdistill.errors import InputError
from jaxdistill.engine.problem import build_problem
from jaxdistill.render import fragments as fr
from jaxdistill.render.visibility import cast_hit_fractions, check_coverage, coverage_summary, hit_fractions
from jaxdistill.scene.model import Mesh, read_scene
from tiny_scene import write_tiny_scene

REPO = Path(__file__).resolve().parents[1]
AWAY = [[1.0, 0.0, 0.0, 2.0], [0.0, -1.0, 0.0, 1.25], [0.0, 0.0, -1.0, -10.0], [0.0, 0.0, 0.0, 1.0]]
"""An OpenCV c2w 10 m in front of the tiny room (which spans z in [0, 3]), looking away from it (-z)."""


@pytest.fixture(autouse=True)
def fragment_cache(tmp_path_factory, monkeypatch):
    monkeypatch.setenv("JAXDISTILL_CACHE", str(tmp_path_factory.getbasetemp() / "coverage_cache"))


def rectangle_in_view(K, c2w, depth, cols, rows) -> Mesh:
    """Two triangles at camera depth `depth` whose image is exactly pixel columns [c0, c1) x rows
    [r0, r1) of the pinhole K (u = fx X / Z + cx), placed in the world by c2w."""
    (c0, c1), (r0, r1) = cols, rows
    xs = [(c - K[0, 2]) * depth / K[0, 0] for c in (c0, c1)]
    ys = [(r - K[1, 2]) * depth / K[1, 1] for r in (r0, r1)]
    local = np.array([[xs[0], ys[0], depth], [xs[1], ys[0], depth], [xs[1], ys[1], depth], [xs[0], ys[1], depth]])
    world = local @ c2w[:3, :3].T + c2w[:3, 3]
    uv = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], np.float64)
    faces = np.array([[0, 1, 2], [0, 2, 3]])
    return Mesh(vertices=world, faces=faces, uv=uv[faces], face_object=np.zeros(2, np.int32), object_names=("quad",))


def test_hit_fractions_of_a_plane_covering_a_known_part_of_the_image():
    width, height = 64, 48
    K = np.array([[50.0, 0, 31.0], [0, 55.0, 25.0], [0, 0, 1]])
    c2w = np.eye(4)
    c2w[:3, :3] = Rotation.from_euler("xyz", [20, -35, 50], degrees=True).as_matrix()
    c2w[:3, 3] = [1.5, -2.0, 0.7]
    cols, rows = (8, 48), (6, 30)                       # even bounds: a 2x coarser grid sees the same
    expected = (cols[1] - cols[0]) * (rows[1] - rows[0]) / (width * height)
    mesh = rectangle_in_view(K, c2w, 3.0, cols, rows)
    cam = cameras.Camera(K=K, c2w=c2w, width=width, height=height)
    behind = cameras.Camera(K=K, c2w=c2w @ np.diag([-1.0, 1.0, -1.0, 1.0]), width=width, height=height)
    frags = fr.compute_fragments(mesh, [cam, behind], cache_dir=False, progress=False)
    np.testing.assert_allclose(hit_fractions(frags), [expected, 0.0], rtol=1e-12, atol=0)
    np.testing.assert_allclose(cast_hit_fractions(mesh, [cam, behind], max_width=width), [expected, 0.0], rtol=1e-12)
    np.testing.assert_allclose(cast_hit_fractions(mesh, [cam], max_width=width // 2), [expected], rtol=1e-12)
    assert expected == pytest.approx(0.3125)


def test_summary_names_the_views_that_see_least(caplog):
    names = ["a", "b", "c", "d"]
    fractions = np.array([0.5, 0.004, 0.9, 0.0])
    text = coverage_summary(names, fractions)
    assert "min 0.0 %, median 25.2 %, max 90.0 %" in text and "fewest: d 0.0 %, b 0.4 %, a 50.0 %" in text
    with caplog.at_level(logging.INFO):
        blind = check_coverage(names, fractions, [], None, "scene.json")
    assert blind == ["b", "d"]
    warning = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warning) == 1 and "2 of 4 views see (almost) nothing" in warning[0] and "b 0.4 %" in warning[0]


def scene_with_cameras_away(folder, which) -> Path:
    path = write_tiny_scene(folder, views=3, gt=False)
    doc = json.loads(path.read_text())
    for i in which:
        doc["views"][i]["c2w"] = AWAY
    path.write_text(json.dumps(doc))
    return path


def test_a_scene_no_view_sees_stops_before_compute_naming_the_scene_file(tmp_path):
    path = scene_with_cameras_away(tmp_path / "away", [0, 1, 2])
    with pytest.raises(InputError) as err:
        build_problem(DistillConfig(scene=str(path.parent), out_dir="unused", prior="views"), cache_dir=tmp_path)
    text = str(err.value)
    assert f"{path}: views: no view sees the mesh" in text and "check the camera convention" in text
    assert "0 of 3 camera centres lie inside the mesh's bounding box (0, 0, 0)..(4, 2.5, 3)" in text
    proc = subprocess.run([sys.executable, "-m", "jaxdistill.main", f"--scene={path.parent}",
                           f"--out_dir={tmp_path / 'run'}", "--prior=views", "--steps=1", "--views_per_step=3"],
                          capture_output=True, text=True, cwd=REPO, env={**os.environ, "JAX_PLATFORMS": "cpu"})
    assert proc.returncode != 0 and "no view sees the mesh" in proc.stderr
    # no traceback, and nothing from the gather plans' code (the flags' help that absl prints may name them)
    assert "Traceback" not in proc.stderr and "gather_plan.py" not in proc.stderr


def test_a_view_that_misses_is_named_in_a_warning_and_the_run_goes_on(tmp_path, caplog):
    path = scene_with_cameras_away(tmp_path / "one", [1])
    with caplog.at_level(logging.INFO):
        problem = build_problem(DistillConfig(scene=str(path.parent), out_dir="unused", prior="views"),
                                cache_dir=tmp_path)
    warning = [r.getMessage() for r in caplog.records if "see (almost) nothing" in r.getMessage()]
    assert len(warning) == 1 and "1 of 3 views" in warning[0] and "v1 0.0 %" in warning[0]
    summary = [r.getMessage() for r in caplog.records if r.getMessage().startswith("pixels that hit the mesh")]
    assert summary and "fewest: v1 0.0 %" in summary[0]
    assert problem.pixel_weight[1].max() == 0 and problem.pixel_weight[0].max() > 0


def test_all_degenerate_faces_are_refused_when_the_scene_is_read(tmp_path):
    path = write_tiny_scene(tmp_path / "flat", views=1, targets=False, gt=False)
    import trimesh

    loaded = trimesh.load(path.parent / "mesh.glb", force="scene", process=False)
    for geom in loaded.geometry.values():
        geom.vertices[:] = geom.vertices[0]                 # every corner at one point
    loaded.export(path.parent / "mesh.glb")
    with pytest.raises(InputError, match=r"mesh\.glb: faces: all \d+ faces have zero area"):
        read_scene(path)


def import_scene(tmp_path, cams):
    path = fx.write_nerfstudio(tmp_path / "ns", cams)
    return subprocess.run([sys.executable, str(REPO / "scripts" / "import_scene.py"), "--format=nerfstudio",
                           f"--path={path}", f"--mesh={fx.write_mesh(tmp_path / 'm.glb')}", f"--out={tmp_path / 'o'}",
                           "--quiet"], capture_output=True, text=True)


def test_import_prints_the_hit_fractions_and_stops_when_no_view_sees_the_mesh(tmp_path):
    cams = fx.ground_truth_cameras(3)
    cams[1] = {"K": cams[1]["K"], "c2w": np.array(AWAY)}
    proc = import_scene(tmp_path / "one", cams)
    assert proc.returncode == 0, proc.stderr
    assert "pixels that hit the mesh per view (3 views): min 0.0 %, median 100.0 %, max 100.0 %" in proc.stdout
    assert "views that see (almost) nothing (< 1 % of rays hit the mesh): frame_00002" in proc.stdout
    report = json.loads((tmp_path / "one" / "o" / "import.json").read_text())
    assert report["hit_fractions"] == {"frame_00001": 1.0, "frame_00002": 0.0, "frame_00003": 1.0}
    proc = import_scene(tmp_path / "all", [{"K": c["K"], "c2w": np.array(AWAY)} for c in cams])
    assert proc.returncode == 2 and "transforms.json: views: no view sees the mesh" in proc.stderr
    assert "check that the cameras follow the format's convention (README: Real datasets)" in proc.stderr
    assert "Traceback" not in proc.stderr
