"""Evaluation's ground truth: gt.json textures, per-view images, both, neither, and a bad gt.json."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest

from jaxdistill import pipeline

from jaxdistill.engine import config as config_lib, loop
from jaxdistill.evaluate import ground_truth as evaluation
from jaxdistill.io import images as imageio
from jaxdistill.engine.config import DistillConfig
from jaxdistill.errors import InputError
from jaxdistill.render import fragments as fr
from jaxdistill.scene.model import read_scene, write_scene
from tiny_scene import write_tiny_scene


@pytest.fixture(scope="module")
def tiny(tmp_path_factory) -> Path:
    return write_tiny_scene(tmp_path_factory.mktemp("tiny_eval"), views=2).parent


def with_view_ground_truth(folder: Path, maps=("albedo", "irradiance")) -> dict:
    """Adds per-view ground_truth images (constant per view and map) to the scene; returns the values."""
    scene = read_scene(folder)
    values, views = {}, []
    for i, view in enumerate(scene.views):
        h, w = view.camera.height, view.camera.width
        paths = {}
        for k, m in enumerate(maps):
            values[view.name, m] = np.full((h, w, 3), 0.1 + 0.2 * i + 0.05 * k, np.float32)
            paths[m] = folder / "gt_images" / m / f"{view.name}.exr"
            imageio.write_image(paths[m], values[view.name, m])
        views.append(dataclasses.replace(view, ground_truth=paths))
    write_scene(dataclasses.replace(scene, views=tuple(views)), folder)
    return values


def frags_of(scene):
    return fr.compute_fragments(scene.mesh, [v.camera for v in scene.views], cache_dir=False, progress=False)


def test_gt_json_maps_and_per_view_ground_truth_combine(tiny, tmp_path):
    """gt.json gives albedo (its textures win), roughness, metallic and geometry normals; the views'
    images give irradiance, which gt.json lacks."""
    import shutil
    folder = tmp_path / "scene"
    shutil.copytree(tiny, folder)
    values = with_view_ground_truth(folder)
    scene = read_scene(folder)
    frags = frags_of(scene)
    gt, maps = evaluation.view_ground_truth(scene, frags)
    textured = evaluation.gt_view_maps(gt, scene, frags)
    for view, per_view, tex in zip(scene.views, maps, textured):
        assert set(per_view) == {"albedo", "roughness", "metallic", "normal", "irradiance"}
        np.testing.assert_array_equal(per_view["albedo"], tex["albedo"])            # gt.json's, not the image's
        assert not np.allclose(per_view["albedo"], values[view.name, "albedo"])
        np.testing.assert_allclose(per_view["irradiance"], values[view.name, "irradiance"], rtol=1e-6)
    (folder / "gt.json").unlink()
    _, maps = evaluation.view_ground_truth(read_scene(folder), frags)
    assert set(maps[0]) == {"albedo", "irradiance"}
    np.testing.assert_allclose(maps[1]["albedo"], values[scene.views[1].name, "albedo"], rtol=1e-6)


def test_gt_json_with_only_geometry_normals_gives_normals(tiny, tmp_path):
    import shutil
    folder = tmp_path / "scene"
    shutil.copytree(tiny, folder)
    (folder / "gt.json").write_text(json.dumps({"format": "jaxdistill-gt", "version": 1, "normal": "geometry"}))
    scene = read_scene(folder)
    frags = frags_of(scene)
    _, maps = evaluation.view_ground_truth(scene, frags)
    hit = frags[0].hit
    assert set(maps[0]) == {"normal"}
    np.testing.assert_allclose(np.linalg.norm(maps[0]["normal"][hit], axis=-1), 1.0, rtol=1e-5)


def refusal_before_compute(folder, tmp_path, monkeypatch) -> str:
    """The InputError message of the main job on the scene `folder`, which must come before any ray is cast."""
    def poisoned(*args, **kwargs):
        raise AssertionError("rays were cast: the bad gt.json was not caught before compute")

    monkeypatch.setattr(fr, "compute_fragments", poisoned)
    config = config_lib.validate(DistillConfig(scene=str(folder), out_dir=str(tmp_path / "run"), steps=2,
                                               views_per_step=2, prior="views"))
    with pytest.raises(InputError) as err:
        pipeline.run(config, progress=False)
    print(err.value)
    return str(err.value)


def test_gt_json_without_any_map_is_refused_before_compute(tiny, tmp_path, monkeypatch):
    """What an earlier prepare_scene.py wrote: our format, no textures. The run stops before any
    setup, naming the file and the field, instead of crashing in evaluation after the run."""
    import shutil
    folder = tmp_path / "scene"
    shutil.copytree(tiny, folder)
    (folder / "gt.json").write_text(json.dumps({"format": "jaxdistill-gt", "version": 1, "source": {}}))
    message = refusal_before_compute(folder, tmp_path, monkeypatch)
    assert f"{folder / 'gt.json'}: textures: no ground-truth texture for any map" in message
    assert "delete gt.json" in message
    (folder / "gt.json").write_text(json.dumps({"format": "jaxdistill-gt", "textures": {"normal": {}}}))
    with pytest.raises(InputError, match=r"textures\.normal: GT textures can be"):
        evaluation.read_gt_document(folder)


def test_gt_textures_missing_or_of_unusable_channels_are_refused_before_compute_and_grey_is_rgb(tiny, tmp_path,
                                                                                                  monkeypatch):
    """gt.json's textures are checked with the scene, before any ray is cast: a missing file and a
    grey + alpha roughness are named by file and field; a grey albedo texture is used as R = G = B
    (it had crashed the scores after the whole run)."""
    import shutil
    folder = tmp_path / "scene"
    shutil.copytree(tiny, folder)
    doc = json.loads((folder / "gt.json").read_text())
    first, second = list(doc["textures"]["albedo"])[:2]
    grey = imageio.read_image(folder / doc["textures"]["albedo"][first], linear=False)[..., :1]
    imageio.write_image(folder / "gt" / "grey.png", grey, encode_srgb=False)
    doc["textures"]["albedo"][first] = "gt/grey.png"
    (folder / "gt.json").write_text(json.dumps(doc))
    gt = evaluation.read_ground_truth(read_scene(folder))
    page = gt.pages["albedo"][0]
    assert page.shape[-1] == 3
    assert np.array_equal(page[..., 0], page[..., 2]) and np.array_equal(page[..., 0], page[..., 1])
    np.testing.assert_allclose(page[..., 0], imageio.read_image(folder / "gt" / "grey.png")[..., 0], rtol=1e-6)
    two = np.concatenate([grey, np.ones_like(grey)], -1)
    imageio.write_image(folder / "gt" / "grey_alpha.png", two, encode_srgb=False)
    doc["textures"]["roughness"][second] = "gt/grey_alpha.png"
    doc["textures"]["metallic"][first] = "gt/nowhere.png"
    (folder / "gt.json").write_text(json.dumps(doc))
    message = refusal_before_compute(folder, tmp_path, monkeypatch)
    assert f"{folder / 'gt.json'}: textures.roughness.{second}:" in message and "2 channels" in message
    assert f"{folder / 'gt.json'}: textures.metallic.{first}: file not found" in message
    assert "textures.albedo" not in message                                 # grey albedo: accepted


def test_scene_without_ground_truth_has_none(tiny, tmp_path):
    import shutil
    folder = tmp_path / "scene"
    shutil.copytree(tiny, folder)
    (folder / "gt.json").unlink()
    scene = read_scene(folder)
    assert evaluation.view_ground_truth(scene, frags_of(scene)) == (None, None)


def test_the_run_lets_the_fragments_go_once_the_evaluation_context_is_built(tiny, tmp_path, monkeypatch):
    """The fragments (44 bytes a pixel per view) serve only to build the evaluation context: from
    the loop on, nothing holds them (weak references to every one of them are dead)."""
    import gc
    import weakref

    from jaxdistill.evaluate import scoring

    refs, checked = [], []
    build, run_loop = scoring.evaluation_context, loop.run_loop

    def context(config, problem):
        refs.extend(weakref.ref(f) for f in list(problem.fragments) + list(problem.native_fragments))
        return build(config, problem)

    def loop_after_the_context(config, problem, *args, **kwargs):
        gc.collect()
        checked.append([r() is None for r in refs])
        assert problem.fragments is None and problem.native_fragments is None
        return run_loop(config, problem, *args, **kwargs)

    monkeypatch.setattr(scoring, "evaluation_context", context)
    monkeypatch.setattr(loop, "run_loop", loop_after_the_context)
    config = config_lib.validate(DistillConfig(scene=str(tiny), out_dir=str(tmp_path / "run"), steps=2,
                                               views_per_step=2, prior="views", render_size=16))
    metrics = pipeline.run(config, progress=False)
    assert len(refs) == 4 and checked == [[True] * 4], checked       # 2 views at render size, 2 at native size
    assert metrics["steps"] == 2 and "rerender" in metrics      # scored and re-rendered without them


def test_quick_psnr_renders_only_the_albedo_and_gives_the_full_renders_figure(tiny, tmp_path, monkeypatch):
    """The loop's --eval_every figure renders the albedo's channels alone: the same PSNR as the
    albedo of a render of every map (the render is per channel), from a 3-channel render."""
    import types

    from jaxdistill.engine.problem import build_problem
    from jaxdistill.evaluate import scoring

    config = config_lib.validate(DistillConfig(scene=str(tiny), out_dir=str(tmp_path / "run"), steps=2,
                                               views_per_step=2, prior="views", render_size=16))
    problem = build_problem(config, cache_dir=tmp_path / "cache")
    ctx = scoring.evaluation_context(config, problem)
    texels = np.random.default_rng(0).uniform(-1, 1, (problem.space.num_texels, problem.channels.num_channels))
    state = types.SimpleNamespace(texels=texels.astype(np.float32))
    full = evaluation.render_views(state.texels, ctx.plan, ctx.cameras, problem.channels)
    expected = evaluation.albedo_psnr(full, ctx.gt_maps, ctx.masks)
    assert problem.channels.num_channels > 3 and np.isfinite(expected)
    widths, render = [], evaluation.render_views
    monkeypatch.setattr(evaluation, "render_views",
                        lambda texels, *a, **k: (widths.append(np.shape(texels)[1]), render(texels, *a, **k))[1])
    np.testing.assert_allclose(scoring.quick_psnr(state, problem, ctx), expected, rtol=1e-6)
    assert widths == [3]


def test_a_step_compiled_ahead_runs_the_loop_as_the_jitted_step_does(tiny, tmp_path):
    """`loop.prepare_step` (what the main job compiles beside the evaluation's set-up) traces the
    step once and gives, step for step, the texels and losses of the loop's own jitted step."""
    import jax

    from jaxdistill.engine.problem import build_problem

    results = {}
    for name in ("jitted", "prepared"):
        config = config_lib.validate(DistillConfig(scene=str(tiny), out_dir=str(tmp_path / name), steps=3,
                                                   views_per_step=2, prior="views", render_size=16))
        problem = build_problem(config, cache_dir=tmp_path / "cache")
        prepared = loop.prepare_step(config, problem) if name == "prepared" else None
        if prepared is not None:
            assert prepared.stepper.traces.traces == 1 and prepared.seconds > 0
        result = loop.run_loop(config, problem, loop.recorded_config(config, "views"), None, progress=False,
                               prepared=prepared)
        results[name] = (np.asarray(jax.device_get(result.state.texels)), result.history["loss"], result.traces)
    (texels_a, loss_a, traces_a), (texels_b, loss_b, traces_b) = results["jitted"], results["prepared"]
    np.testing.assert_array_equal(texels_a, texels_b)
    assert loss_a == loss_b and len(loss_a) == 3 and traces_a == traces_b == 1
    with pytest.raises(ValueError, match="a prepared step and a before_steps hook"):
        loop.run_loop(config, problem, loop.recorded_config(config, "views"), None, progress=False,
                      prepared=prepared, hooks=loop.LoopHooks(before_steps=lambda *a: a[0]))


def test_the_outputs_made_in_two_threads_equal_those_made_in_one(tiny, tmp_path, monkeypatch):
    """The map files and scores beside the renders, evidence and plots (`outputs.map_files_beside`)
    give the files and metrics of the same outputs made one after the other."""
    from jaxdistill.export import outputs

    runs = {}
    for beside in (True, False):
        monkeypatch.setattr(outputs, "map_files_beside", lambda problem, beside=beside: beside)
        out = tmp_path / f"beside_{beside}"
        config = config_lib.validate(DistillConfig(scene=str(tiny), out_dir=str(out), steps=2, views_per_step=2,
                                                   prior="views", render_size=16))
        metrics = pipeline.run(config, progress=False)
        files = sorted(p.relative_to(out) for p in out.rglob("*") if p.is_file() and p.suffix in (".exr", ".png"))
        runs[beside] = metrics, files, out
    (m2, files2, out2), (m1, files1, out1) = runs[True], runs[False]
    assert files1 == files2 and any(f.parts[0] == "maps" for f in files1) and any(f.parts[0] == "evidence" for f in files1)
    assert m1["ours"] == m2["ours"] and m1["maps_written"] == m2["maps_written"]
    assert "beside" in m2["output_timings"]["maps, glTF, USD"] and "beside" not in m1["output_timings"]["scores"]
    for f in files1:
        if f.suffix == ".exr":
            np.testing.assert_array_equal(imageio.read_image(out1 / f), imageio.read_image(out2 / f))
