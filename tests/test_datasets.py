"""Dataset loaders on tiny self-written fixtures: the pose check per convention, images, masks,
exposure, ground truth, the import script, and bad input naming file and field."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import dataset_fixtures as fx
from dataset_fixtures import cache, cams  # noqa: F401  (fixtures)
from jaxdistill import datasets
from jaxdistill.io import images as imageio
from jaxdistill.datasets.common import ImportOptions
from jaxdistill.errors import InputError
from jaxdistill.io.exposure import HYPERSIM_TARGET
from jaxdistill.scene.model import read_scene

REPO = Path(__file__).resolve().parents[1]


def options(tmp_path, **kw) -> ImportOptions:
    return ImportOptions(work_dir=str(tmp_path / "work"), progress=False, **kw)


def loaded_scenes(tmp_path, cams) -> dict:
    """Every format written from the same cameras, loaded."""
    mesh = fx.write_mesh(tmp_path / "room.glb")
    return {
        "fipt": datasets.load("fipt", fx.write_fipt(tmp_path / "fipt", cams), options(tmp_path / "a")),
        "iris": datasets.load("iris", fx.write_fipt(tmp_path / "iris", cams, ldr=True), options(tmp_path / "b")),
        "nerfstudio": datasets.load("nerfstudio", fx.write_nerfstudio(tmp_path / "ns", cams),
                                    options(tmp_path / "c", mesh=str(mesh))),
        "scannetpp": datasets.load("scannetpp", fx.write_scannetpp(tmp_path / "spp", cams), options(tmp_path / "d")),
        "colmap": datasets.load("colmap", fx.write_colmap(tmp_path / "colmap", cams),
                                options(tmp_path / "e", mesh=str(mesh))),
    }


def test_the_same_point_lands_on_the_same_pixel_through_every_loader(tmp_path, cams):
    points = fx.known_points(cams)
    scenes = loaded_scenes(tmp_path, cams)
    for fmt, scene in scenes.items():
        assert len(scene.views) == len(cams), fmt
        for view, cam in zip(scene.views, cams):
            pixels, depth = view.camera.project(points)
            expected = fx.reference_pixels(cam, points)
            front = depth > 0
            assert front.sum() >= 4, fmt
            np.testing.assert_allclose(pixels[front], expected[front], atol=2e-3, err_msg=fmt)
            assert (view.camera.width, view.camera.height) == (fx.WIDTH, fx.HEIGHT)


def test_fipt_cameras_follow_fipts_own_ray_generation(tmp_path, cams):
    """A pixel's ray by FIPT's formula passes through the point our camera projects there."""
    root = fx.write_fipt(tmp_path / "fipt", cams)
    meta = json.loads((root / "train" / "transforms.json").read_text())
    scene = datasets.load("fipt", root, options(tmp_path))
    points = fx.known_points(cams, seed=5)
    for view, frame in zip(scene.views, meta["frames"]):
        pixels, depth = view.camera.project(points)
        for p, (col, row) in zip(points[depth > 0], pixels[depth > 0]):
            origin, d = fx.fipt_ray(frame["transform_matrix"], meta["camera_angle_x"], col, row)
            off_ray = (p - origin) - ((p - origin) @ d) * d
            assert np.linalg.norm(off_ray) < 1e-9


def test_fipt_ground_truth_emitter_masks_and_hdr_exposure(tmp_path, cams):
    root = fx.write_fipt(tmp_path / "fipt", cams)
    scene = datasets.load("fipt", root, options(tmp_path))
    view = scene.views[0]
    assert set(view.ground_truth) == {"albedo", "roughness"} and view.ground_truth["albedo"].parent.name == "DiffCol"
    mask = imageio.read_image(view.mask, linear=False)[..., 0]
    assert (mask[:4, :5] == 0).all() and (mask[4:] == 1).all()      # the emitter corner is masked
    # one scene-wide exposure by Hypersim's rule over the unmasked HDR pixels
    values = []
    for v in scene.views:
        photo = imageio.read_image(v.photo)
        keep = imageio.read_image(v.mask, linear=False)[..., 0] >= 0.5
        values.append((photo[..., :3] @ np.array([0.3, 0.59, 0.11], np.float32))[keep])
    expected = math.log2(HYPERSIM_TARGET / np.percentile(np.concatenate(values), 90))
    assert len({v.exposure for v in scene.views}) == 1
    assert scene.views[0].exposure == pytest.approx(expected, abs=1e-3)
    # LDR photos (IRIS) keep their camera's exposure; a given number wins
    iris = datasets.load("iris", fx.write_fipt(tmp_path / "iris", cams, ldr=True), options(tmp_path / "i"))
    assert all(v.exposure == 0.0 and v.photo.suffix == ".png" for v in iris.views)
    fixed = datasets.load("fipt", root, options(tmp_path / "f", exposure="-1.5"))
    assert {v.exposure for v in fixed.views} == {-1.5}


def test_exposure_scales_the_photo_rgbx_sees(tmp_path):
    photo = np.full((4, 4, 3), 0.1, np.float32)
    imageio.write_image(tmp_path / "p.exr", photo)
    got = imageio.read_photo_srgb(tmp_path / "p.exr", exposure=2.0)
    np.testing.assert_allclose(got, imageio.linear_to_srgb(np.full((4, 4, 3), 0.4)), atol=1e-6)
    assert imageio.read_photo_srgb(tmp_path / "p.exr", exposure=5.0).max() == pytest.approx(1.0)   # clipped


def test_scannetpp_skips_bad_frames_reads_masks_and_reorthogonalises(tmp_path, cams):
    root = fx.write_scannetpp(tmp_path / "spp", cams, bad_frame=1)
    scene = datasets.load("scannetpp", root, options(tmp_path))
    assert [v.name for v in scene.views] == ["DSC00000", "DSC00002"]
    for view in scene.views:
        R = view.camera.c2w[:3, :3]
        np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-12)
        assert view.mask is not None and view.mask.parent.name == "undistorted_anon_masks"
    # the laser scan has no UVs: unwrapped, every object in [0, 1]
    uv = scene.mesh.uv
    assert np.isfinite(uv).all() and uv.min() >= 0 and uv.max() <= 1


def test_scannetpp_marker_vertex_lands_on_its_pixel_in_train_and_test_frames(tmp_path, cams):
    """Poses written by ScanNet++'s own formula (world x<->y swapped, z negated) land in the mesh's
    world: a vertex of the released mesh, found in the loaded mesh, projects where the true camera
    puts it, in a train and in a test frame."""
    root = fx.write_scannetpp(tmp_path / "spp", cams, test_frame=2)
    train = datasets.load("scannetpp", root, options(tmp_path / "a"))
    test = datasets.load("scannetpp", root, options(tmp_path / "b"), split="test")
    assert [v.name for v in train.views] == ["DSC00000", "DSC00001"] and [v.name for v in test.views] == ["DSC00002"]
    released = fx.room_mesh().vertices
    for view, cam in zip(train.views + test.views, cams):
        depth = (released - cam["c2w"][:3, 3]) @ cam["c2w"][:3, 2]
        pixel = fx.reference_pixels(cam, released)
        inside = (depth > 0) & (pixel >= 0).all(1) & (pixel < [fx.WIDTH, fx.HEIGHT]).all(1)
        marker = released[np.argmax(np.where(inside, depth, -np.inf))]     # the farthest visible vertex
        assert np.linalg.norm(train.mesh.vertices - marker, axis=1).min() < 1e-9      # the mesh is not moved
        got, got_depth = view.camera.project(marker[None])
        assert got_depth[0] > 0
        assert np.abs(got[0] - fx.reference_pixels(cam, marker[None])[0]).max() < 1e-3


def test_scannetpp_with_only_the_distorted_transforms_gives_the_undistortion_command(tmp_path, cams):
    root = fx.write_scannetpp(tmp_path / "spp", cams, undistorted=False)
    with pytest.raises(InputError) as err:
        datasets.load("scannetpp", root, options(tmp_path))
    text = str(err.value)
    assert "transforms_undistorted.json: (file): not found; only the distorted (fisheye) " \
           "dslr/nerfstudio/transforms.json is there" in text
    assert "python -m dslr.undistort dslr/configs/undistort.yml" in text


def test_distorted_nerfstudio_photos_are_undistorted_and_their_gaps_masked(tmp_path, cams):
    mesh = fx.write_mesh(tmp_path / "room.glb")
    path = fx.write_nerfstudio(tmp_path / "ns", cams, distortion={"k1": 0.25, "k2": 0.05, "p1": 0.001, "p2": -0.002})
    scene = datasets.load("nerfstudio", path, options(tmp_path, mesh=str(mesh)))
    for view in scene.views:
        assert view.photo.parent == tmp_path / "work" / "undistorted"
        mask = imageio.read_image(view.mask, linear=False)[..., 0]
        assert 0 < (mask < 0.5).sum() < mask.size / 2       # pincushion: the corners lie outside the photo
    # the pose check is unaffected by undistortion (same K, same pose)
    points = fx.known_points(cams)
    pixels, depth = scene.views[0].camera.project(points)
    np.testing.assert_allclose(pixels[depth > 0], fx.reference_pixels(cams[0], points)[depth > 0], atol=2e-3)


def test_open_scene_reads_format_prefixed_paths(tmp_path, cams):
    root = fx.write_fipt(tmp_path / "fipt", cams)
    scene = datasets.open_scene(f"fipt:{root}")
    assert len(scene.views) == 3 and scene.texture_layout == "pages"
    assert datasets.split_spec("C:/scenes/x") == ("scene", "C:/scenes/x")      # no format: a scene path


def test_import_script_writes_a_scene_that_reads_back(tmp_path, cams):
    root = fx.write_scannetpp(tmp_path / "spp", cams)
    out = tmp_path / "imported"
    proc = subprocess.run([sys.executable, str(REPO / "scripts" / "import_scene.py"), "--format=scannetpp",
                           f"--path={root}", f"--out={out}", "--quiet", "--link=none"], capture_output=True, text=True,
                          env={**__import__("os").environ})
    assert proc.returncode == 0, proc.stderr
    # --link=none: the photos stay in the dataset, outside `out`: refused by default, read with the opt-in
    with pytest.raises(InputError, match=r"views\[0\]\.photo: '\.\./spp/dslr/undistorted_images/DSC00000\.JPG' "
                       r"resolves outside the scene folder"):
        read_scene(out)
    assert f"--scene={out} --out_dir=runs/spp --allow_outside_paths" in proc.stdout
    scene = read_scene(out, allow_outside_paths=True)
    assert len(scene.views) == 3 and np.isfinite(scene.mesh.uv).all()
    report = json.loads((out / "import.json").read_text())
    assert report["views"] == 3 and report["uv_decisions"] and "uv_s" in report["timings"]
    assert "unwrap" in proc.stdout.lower() and "exposure" in proc.stdout


def test_main_job_reads_a_scene_naming_outside_files_only_with_its_flag(tmp_path, cams):
    """An imported scene names the dataset's photos (../): the main job's --allow_outside_paths
    reaches the scene reader; without it the run stops before anything is read."""
    from absl import flags

    from jaxdistill.engine import config as config_lib
    from jaxdistill.engine.problem import build_problem
    from jaxdistill.scene.model import write_scene

    out = tmp_path / "imported"
    write_scene(datasets.load("scannetpp", fx.write_scannetpp(tmp_path / "spp", cams), options(tmp_path)), out)
    fv = flags.FlagValues()
    config_lib.define_flags(fv)
    fv(["main", f"--scene={out}", f"--out_dir={tmp_path / 'run'}", "--prior=views", "--maps=albedo"])
    config = config_lib.config_from_flags(fv)
    assert config.allow_outside_paths is False
    with pytest.raises(InputError, match=r"scene\.json: views\[0\]\.photo: .*resolves outside the scene folder"
                       r".*pass --allow_outside_paths"):
        build_problem(config)
    fv(["main", "--allow_outside_paths"])
    config = config_lib.config_from_flags(fv)
    assert config.allow_outside_paths is True
    with pytest.raises(InputError, match=r"views\[0\]\.targets\.albedo: view DSC00000 has no albedo target"):
        build_problem(config)        # the scene was read: the views prior then asks for its targets


# ----------------------------------------------------------------------------- bad input


def test_missing_photo_and_inconsistent_counts_name_the_frame(tmp_path, cams):
    root = fx.write_fipt(tmp_path / "fipt", cams, missing_photo=2)
    with pytest.raises(InputError, match=r"transforms\.json: frames\[2\]: photo not found.*2 photos in"):
        datasets.load("fipt", root, options(tmp_path))


def test_unsupported_camera_model_is_named(tmp_path, cams):
    path = fx.write_nerfstudio(tmp_path / "ns", cams, model="OPENCV_FISHEYE")
    with pytest.raises(InputError, match=r"frames\[0\]\.camera_model: OPENCV_FISHEYE is not supported"):
        datasets.load("nerfstudio", path, options(tmp_path, mesh=str(fx.write_mesh(tmp_path / "m.glb"))))


def test_formats_without_a_mesh_ask_for_one(tmp_path, cams):
    path = fx.write_nerfstudio(tmp_path / "ns", cams)
    with pytest.raises(InputError, match=r"mesh: .*--mesh"):
        datasets.load("nerfstudio", path, options(tmp_path))


def test_wrong_image_size_and_missing_files_are_all_reported(tmp_path, cams):
    root = fx.write_scannetpp(tmp_path / "spp", cams)
    imageio.write_image(root / "dslr" / "undistorted_images" / "DSC00001.JPG", np.zeros((10, 10, 3)))
    (root / "dslr" / "undistorted_images" / "DSC00002.JPG").unlink()
    with pytest.raises(InputError) as err:
        datasets.load("scannetpp", root, options(tmp_path))
    text = str(err.value)
    assert "view DSC00001.photo" in text and "10x10 but the view is 32x24" in text
    assert "view DSC00002.photo: file not found" in text
    (tmp_path / "empty").mkdir()
    with pytest.raises(InputError, match=r"transforms_undistorted\.json.*not found"):
        datasets.load("scannetpp", tmp_path / "empty", options(tmp_path))


def test_import_script_exits_2_with_the_problem(tmp_path, cams):
    path = fx.write_nerfstudio(tmp_path / "ns", cams, model="EQUIRECTANGULAR")
    proc = subprocess.run([sys.executable, str(REPO / "scripts" / "import_scene.py"), "--format=nerfstudio",
                           f"--path={path}", f"--mesh={fx.write_mesh(tmp_path / 'm.glb')}", f"--out={tmp_path / 'o'}",
                           "--quiet"], capture_output=True, text=True)
    assert proc.returncode == 2 and "EQUIRECTANGULAR is not supported" in proc.stderr


def test_main_job_runs_on_a_fipt_dataset_directly_and_scores_its_image_ground_truth(tmp_path, cams, run_rgbx_dir):
    """--scene=fipt:PATH: exposure, emitter masks in the loss, metrics against DiffCol/Roughness."""
    from jaxdistill import pipeline
    from jaxdistill.engine import config as config_lib, loop
    from jaxdistill.engine.config import DistillConfig
    from jaxdistill.engine.problem import build_problem

    root = fx.write_fipt(tmp_path / "fipt", cams)
    config = config_lib.validate(DistillConfig(scene=f"fipt:{root}", out_dir=str(tmp_path / "run"), steps=2,
                                               views_per_step=1, prior="rgbx", rgbx_dir=str(run_rgbx_dir),
                                               maps=("albedo", "roughness"), renders=False, eval_every=0,
                                               contact_views=1, estimate_steps=4))
    problem = build_problem(config)
    assert (problem.pixel_weight[:, :4, :5] == 0).all()              # the emitter corner is out of the loss
    pipeline.run(config, progress=False)
    doc = json.loads((tmp_path / "run" / "metrics.json").read_text())
    assert doc["ours"]["num_views"] == 3
    assert np.isfinite(doc["ours"]["albedo_psnr"]) and np.isfinite(doc["ours"]["roughness_mse"])


def test_max_views_keeps_that_many_views_of_a_jaxdistill_scene_evenly_spread(tmp_path):
    from tiny_scene import write_tiny_scene
    path = write_tiny_scene(tmp_path / "scene", views=7)
    full = datasets.open_scene(str(path))
    assert [v.name for v in full.views] == [f"v{i}" for i in range(7)]
    for n, names in ((3, ["v0", "v3", "v6"]), (2, ["v0", "v6"]), (7, None), (9, None), (0, None)):
        kept = datasets.open_scene(str(path), ImportOptions(max_views=n))
        assert [v.name for v in kept.views] == (names or [v.name for v in full.views])
        assert kept.mesh is full.mesh or np.array_equal(kept.mesh.faces, full.mesh.faces)
