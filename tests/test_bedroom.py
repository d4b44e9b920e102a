"""The procedural bedroom: packing, UVs, normals, estimates, and the committed scene folder.

The room kit (`room_geometry`), the stand-in estimates (`standins`) and the normals are library
code, tested here through the package; the bedroom's own objects and generation are
scripts/make_bedroom.py's, loaded from the script."""

from __future__ import annotations

import hashlib
import importlib.util
import json
import sys
from pathlib import Path

import numpy as np
import pytest

from jaxdistill.models.training import room_geometry, standins
from jaxdistill.scene.cameras import camera_normals
from jaxdistill.scene.mesh import face_normals
from jaxdistill.scene.model import read_scene
from jaxdistill.scenes import scene_path

REPO = Path(__file__).resolve().parents[1]


def load_script():
    spec = importlib.util.spec_from_file_location("make_bedroom", REPO / "scripts" / "make_bedroom.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules["make_bedroom"] = module                 # dataclasses look their module up
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="module")
def mb():
    pytest.importorskip("mitsuba")
    return load_script()


@pytest.fixture(scope="module")
def geometry(mb):
    objs = mb.bedroom_objects()
    mesh, sizes = room_geometry.build_scene_geometry(objs)
    return objs, mesh, sizes


def test_pack_rects_fits_without_overlap_at_one_scale():
    sizes = np.array([[2.0, 1.0], [1.0, 1.0], [0.5, 2.0], [0.3, 0.2], [1.5, 0.4]])
    gutter = 0.01
    corners, scale = room_geometry.pack_rects(sizes, gutter)
    lo, hi = corners, corners + sizes * scale
    assert np.all(lo >= gutter - 1e-12) and np.all(hi <= 1 - gutter + 1e-12)
    for i in range(len(sizes)):
        for j in range(i + 1, len(sizes)):
            apart = np.any((hi[i] + gutter <= lo[j] + 1e-12) | (hi[j] + gutter <= lo[i] + 1e-12))
            assert apart, (i, j)
    assert room_geometry.pack_rects(sizes, gutter)[1] == scale
    total = (sizes * scale).prod(axis=1).sum()
    assert total > 0.3                                   # a shelf packer should use a fair share


def test_every_object_has_non_overlapping_uvs_in_the_unit_square(geometry):
    objs, mesh, sizes = geometry
    assert np.all(mesh.uv >= 0) and np.all(mesh.uv <= 1)
    res = 256
    centres = (np.arange(res) + 0.5) / res
    px, py = np.meshgrid(centres, centres)
    for k, (name, _, _) in enumerate(objs):
        uv = mesh.uv[mesh.face_object == k]
        cover = np.zeros((res, res), np.int32)
        for a, b, c in uv:
            d = (b[1] - c[1]) * (a[0] - c[0]) + (c[0] - b[0]) * (a[1] - c[1])
            assert abs(d) > 0, f"{name}: degenerate UV triangle"
            l1 = ((b[1] - c[1]) * (px - c[0]) + (c[0] - b[0]) * (py - c[1])) / d
            l2 = ((c[1] - a[1]) * (px - c[0]) + (a[0] - c[0]) * (py - c[1])) / d
            inside = (l1 > 1e-9) & (l2 > 1e-9) & (1 - l1 - l2 > 1e-9)
            cover += inside
        assert cover.max() <= 1, f"{name}: UV charts overlap"
        assert cover.sum() > 0, f"{name}: no UV area"


def test_normals_face_into_the_room_and_out_of_furniture(mb, geometry):
    objs, mesh, _ = geometry
    normals = face_normals(mesh)
    centres = mesh.triangles().mean(axis=1)
    room_centre = mb.ROOM / 2
    for k, name in enumerate(mesh.object_names):
        sel = mesh.face_object == k
        towards_room = np.einsum("fi,fi->f", normals[sel], room_centre - centres[sel])
        if name in ("floor", "ceiling") or name.startswith("wall_"):
            assert np.all(towards_room > 0), name
    bed = mesh.object_names.index("mattress")
    sel = mesh.face_object == bed
    box_centre = mesh.triangles()[sel].reshape(-1, 3).mean(axis=0)
    assert np.all(np.einsum("fi,fi->f", normals[sel], centres[sel] - box_centre) > 0)


def test_camera_normals_of_a_wall_facing_the_camera_point_at_it():
    from jaxdistill.scene import cameras
    K = np.array([[20.0, 0, 8], [0, 20.0, 6], [0, 0, 1]])
    cam = cameras.look_at(np.array([0.0, 0.0, 5.0]), np.zeros(3), np.array([0.0, 1.0, 0.0]), K, 16, 12)
    normals = np.array([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0]])             # facing the camera; facing up
    triangle = np.zeros((12, 16), np.int64)
    triangle[:, 8:] = 1
    triangle[0, 0] = -1
    n = camera_normals(normals, triangle, cam)
    np.testing.assert_allclose(n[1, 1], [0, 0, 1], atol=1e-12)          # z towards the camera
    np.testing.assert_allclose(n[1, 9], [0, 1, 0], atol=1e-12)          # y up
    assert np.all(n[0, 0] == 0)


def test_estimates_are_seeded_and_corrupt_every_map():
    rng = np.random.default_rng(3)
    h, w = 24, 32
    n = rng.normal(size=(h, w, 3))
    gt = {"albedo": rng.uniform(0.1, 0.8, (h, w, 3)).astype(np.float32),
          "roughness": rng.uniform(0, 1, (h, w, 1)).astype(np.float32),
          "metallic": (rng.uniform(0, 1, (h, w, 1)) > 0.7).astype(np.float32),
          "normal": (n / np.linalg.norm(n, axis=-1, keepdims=True)).astype(np.float32)}
    photo = (gt["albedo"] * rng.uniform(0.2, 2.0, (h, w, 1))).astype(np.float32)
    hit = np.ones((h, w), bool)
    hit[0, 0] = False
    a, pa = standins.estimate_view(np.random.default_rng([0, 1]), gt, photo, hit)
    b, pb = standins.estimate_view(np.random.default_rng([0, 1]), gt, photo, hit)
    c, _ = standins.estimate_view(np.random.default_rng([0, 2]), gt, photo, hit)
    assert pa == pb
    for key in gt:
        np.testing.assert_array_equal(a[key], b[key])
        assert not np.array_equal(a[key], c[key])
        assert np.all(a[key][0, 0] == 0)                                # misses stay empty
    assert set(a) == {"albedo", "roughness", "metallic", "normal", "irradiance"}
    assert np.abs(a["albedo"] - gt["albedo"])[hit].mean() > 0.01
    np.testing.assert_allclose(np.linalg.norm(a["normal"][hit], axis=-1), 1.0, atol=1e-5)
    assert a["irradiance"].min() >= 0 and a["irradiance"].max() <= 1


def test_tiny_generation_agrees_with_mitsuba(mb, tmp_path):
    summary = mb.generate(tmp_path, seed=1, views=1, width=48, height=36, spp=1)
    agreement = summary["agreement"][0]
    assert agreement["hit_agreement"] > 0.99
    assert agreement["match_fraction"] > 0.9
    assert agreement["psnr_db"] > 30
    scene = read_scene(tmp_path)
    assert len(scene.views) == 1 and set(scene.views[0].targets) == {"albedo", "roughness", "metallic", "normal",
                                                                       "irradiance"}


def test_committed_bedroom_is_complete_and_untouched():
    folder = scene_path("bedroom")
    scene = read_scene(folder)
    assert 48 <= len(scene.views) <= 64
    assert all(set(v.targets) == {"albedo", "roughness", "metallic", "normal", "irradiance"} for v in scene.views)
    lines = [line.split("  ", 1) for line in (folder / "manifest.sha256").read_text().splitlines() if line]
    files = {p.relative_to(folder).as_posix() for p in folder.rglob("*") if p.is_file()}
    assert {name for _, name in lines} == files - {"README.md", "manifest.sha256"}
    for digest, name in lines:
        assert hashlib.sha256((folder / name).read_bytes()).hexdigest() == digest, name
    size = sum((folder / name).stat().st_size for name in files)
    assert size < 30 * 2**20                  # photos, targets and irradiance GT about 5 MiB each
    gt = json.loads((folder / "gt.json").read_text())
    for textures in gt["textures"].values():
        assert list(textures) == list(scene.mesh.object_names)


def test_committed_bedroom_photos_carry_hypersims_exposure():
    """The prior must see the bedroom's HDR photos as it was trained (and as imports are shown):
    one scene-wide exposure that brings the 90th-percentile brightness 0.3 R + 0.59 G + 0.11 B
    to 0.8 after a 1/2.2 gamma, written out here in NumPy."""
    from jaxdistill.io import images as imageio

    scene = read_scene(scene_path("bedroom"))
    photos = [imageio.read_image(v.photo)[..., :3] for v in scene.views]
    brightness = np.concatenate([(p @ np.array([0.3, 0.59, 0.11])).ravel() for p in photos])
    stops = np.log2(0.8 ** 2.2 / np.percentile(brightness, 90))
    assert {v.exposure for v in scene.views} == {scene.views[0].exposure}
    assert abs(scene.views[0].exposure - stops) < 0.01
    exposed = np.concatenate([(p * 2.0 ** scene.views[0].exposure @ np.array([0.3, 0.59, 0.11])).ravel()
                              for p in photos])
    assert abs(np.percentile(exposed, 90) ** (1 / 2.2) - 0.8) < 0.005
