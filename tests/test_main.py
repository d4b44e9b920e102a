"""The main job end to end on a tiny scene: outputs, resume, signals, NaN, bad input, the rgbx path."""

from __future__ import annotations

import dataclasses
import json
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import jax
import numpy as np
import pytest
import trimesh
from absl import flags

from jaxdistill.io import checkpoint, images as imageio
from jaxdistill import pipeline
from jaxdistill.engine import config as config_lib, loop
from jaxdistill.engine.config import DistillConfig
from jaxdistill.errors import InputError
from jaxdistill.engine.problem import Problem
from jaxdistill.export import run_dir
from jaxdistill.models import estimates as model_estimates
from tiny_scene import write_tiny_scene

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def tiny_scene(tmp_path_factory):
    return write_tiny_scene(tmp_path_factory.mktemp("tiny_main"))


@pytest.fixture(autouse=True)
def fragment_cache(tmp_path_factory, monkeypatch):
    monkeypatch.setenv("JAXDISTILL_CACHE", str(tmp_path_factory.getbasetemp() / "fragment_cache"))


def tiny_config(scene, out, **kw) -> DistillConfig:
    base = dict(scene=str(scene), out_dir=str(out), steps=6, views_per_step=2, prior="views", log_every=2,
                eval_every=3, renders=True, contact_views=2, lr=0.05)
    base.update(kw)
    return config_lib.validate(DistillConfig(**base))


def restored(out: Path, step: int):
    """(state, config) of the checkpoint at `step`, which must be the latest in out/checkpoints."""
    from jaxdistill.engine.step import init_state, make_optimizer

    with checkpoint.CheckpointStore(out / "checkpoints") as store:
        assert store.latest_step() == step
        shape, _ = store.saved_shapes(step)["texels"]
        like = init_state(np.zeros(shape, np.float32), make_optimizer(0.01, 0.0), 0)
        return store.restore(step, like)


def test_main_job_writes_every_output(tiny_scene, tmp_path, capsys):
    out = tmp_path / "run"
    summary = pipeline.run(tiny_config(tiny_scene, out), progress=False)
    doc = json.loads((out / "metrics.json").read_text())
    assert doc["prior"]["kind"] == "views" and "per-view target" in doc["prior"]["reason"]
    assert doc["traces"] == 1 and doc["steps"] == 6 and doc["wall_seconds"] > 0 and doc["peak_host_memory_mb"] > 0
    assert doc["huge_pages"].split(": ")[0] in ("on", "off", "as given")      # huge_pages.status()
    peaks = doc["peak_host_memory_gb"]                # the peak so far after set-up, loop and outputs: never falls
    assert list(peaks) == ["set-up", "loop", "outputs"] and 0 < peaks["set-up"] <= peaks["loop"] <= peaks["outputs"]
    for key in ("albedo_psnr", "albedo_ssim", "normal_angular_deg", "roughness_mse", "metallic_mse"):
        assert np.isfinite(doc["ours"][key]) and np.isfinite(doc["baseline_per_view_estimates"][key])
    assert doc["history"]["step"] == [1, 2, 3, 4, 5, 6] and doc["history"]["eval_step"] == [3, 6]
    assert doc["anchor"] is None                            # --anchor=auto: none with the views prior
    assert "anchored" not in capsys.readouterr().out
    anchored = pipeline.run(tiny_config(tiny_scene, tmp_path / "anchored", anchor="estimates", renders=False),
                         progress=False)
    assert "per-view target" in anchored["anchor"]["to"]
    assert sorted(anchored["anchor"]["gains"]) == ["albedo", "irradiance"]
    assert "overall scale anchored to the scene's per-view target images: gains albedo " in capsys.readouterr().out
    assert run_dir.json_safe(summary["ours"]) == doc["ours"]       # NaN (a seam ratio of a flat GT) is null
    objects = ["room_floor", "room_ceiling", "room_wall_z0", "room_wall_z1", "room_wall_x0", "room_wall_x1"]
    for m in ("albedo", "normal", "roughness", "metallic", "irradiance"):
        for o in objects:
            exr = imageio.read_image(out / "maps" / m / f"{o}.exr")
            assert exr.shape[-1] == (1 if m in ("roughness", "metallic") else 3) and np.isfinite(exr).all()
            assert (out / "maps" / m / f"{o}.png").is_file()
        assert sorted(p.stem for p in (out / "renders" / m).glob("*.png")) == ["v0", "v1", "v2", "v3"]
        assert (out / f"contact_{m}.png").is_file()
    assert (out / "loss.png").is_file()
    glb = trimesh.load(out / "scene.glb", force="scene")
    assert sorted(glb.geometry) == sorted(objects)
    material = glb.geometry["room_floor"].visual.material
    assert material.baseColorTexture is not None and material.metallicRoughnessTexture is not None
    assert material.normalTexture is not None


def test_resumed_run_is_bit_identical_to_an_uninterrupted_one(tiny_scene, tmp_path, monkeypatch):
    full = tmp_path / "full"
    pipeline.run(tiny_config(tiny_scene, full, steps=8, p_keep=0.7, renders=False), progress=False)
    part = tmp_path / "part"
    pipeline.run(tiny_config(tiny_scene, part, steps=4, p_keep=0.7, renders=False), progress=False)
    pipeline.run(tiny_config(tiny_scene, part, steps=8, p_keep=0.7, renders=False, resume=True), progress=False)
    a, config_a = restored(full, 8)
    b, _ = restored(part, 8)
    assert config_a["p_keep"] == 0.7 and config_a["prior_kind"] == "views"
    for leaf_a, leaf_b in zip(*(jax_leaves(s) for s in (a, b))):
        np.testing.assert_array_equal(leaf_a, leaf_b)
    resumed = json.loads((part / "metrics.json").read_text())
    uninterrupted = json.loads((full / "metrics.json").read_text())
    assert resumed["resumed_from"] == 4 and resumed["steps_this_run"] == 4
    assert resumed["history"]["step"] == uninterrupted["history"]["step"] == list(range(1, 9))
    assert resumed["history"]["loss"] == uninterrupted["history"]["loss"]

    # a crash between metric fetches: the checkpoint's history still has every step up to it
    crashed = tmp_path / "crashed"
    original = Problem.batch
    calls = {"n": 0}

    def batch_then_crash(self, ids):
        calls["n"] += 1
        if calls["n"] == 6:                     # call 1 is the jit example: this is step 4, after the checkpoint at 3
            raise RuntimeError("simulated crash")
        return original(self, ids)

    monkeypatch.setattr(Problem, "batch", batch_then_crash)
    with pytest.raises(RuntimeError, match="simulated crash"):
        pipeline.run(tiny_config(tiny_scene, crashed, steps=8, p_keep=0.7, renders=False, ckpt_every=3, log_every=2),
                  progress=False)
    monkeypatch.setattr(Problem, "batch", original)
    pipeline.run(tiny_config(tiny_scene, crashed, steps=8, p_keep=0.7, renders=False, resume=True), progress=False)
    again = json.loads((crashed / "metrics.json").read_text())
    assert again["resumed_from"] == 3
    assert again["history"]["step"] == list(range(1, 9))
    assert again["history"]["loss"] == uninterrupted["history"]["loss"]


def jax_leaves(tree):
    import jax

    return [np.asarray(x) for x in jax.tree.leaves(tree)]


def test_resume_refuses_a_different_config_and_needs_a_checkpoint(tiny_scene, tmp_path):
    out = tmp_path / "run"
    pipeline.run(tiny_config(tiny_scene, out, steps=2, renders=False), progress=False)
    with pytest.raises(InputError, match=r"--lr.*0\.05.*0\.2"):
        pipeline.run(tiny_config(tiny_scene, out, steps=4, lr=0.2, resume=True), progress=False)
    with pytest.raises(InputError, match="already holds a run.*--resume"):
        pipeline.run(tiny_config(tiny_scene, out, steps=4), progress=False)
    with pytest.raises(InputError, match="no complete checkpoint"):
        pipeline.run(tiny_config(tiny_scene, tmp_path / "empty", resume=True), progress=False)
    with pytest.raises(InputError, match=r"--steps: 1 is below the checkpoint's step 2"):
        pipeline.run(tiny_config(tiny_scene, out, steps=1, resume=True), progress=False)
    from jaxdistill.models import shipped

    with pytest.MonkeyPatch.context() as mp, pytest.raises(InputError, match=r"--loss_space.*views prior"):
        mp.setattr(shipped, "SHIPPED_DIR", tmp_path / "no_shipped_model")     # auto resolves to views
        pipeline.run(tiny_config(tiny_scene, tmp_path / "latent", prior="auto", loss_space="latent"), progress=False)
    cosine = tmp_path / "cosine"
    pipeline.run(tiny_config(tiny_scene, cosine, steps=2, lr_schedule="cosine", renders=False), progress=False)
    with pytest.raises(InputError, match="--steps"):       # the cosine schedule depends on the run's length
        pipeline.run(tiny_config(tiny_scene, cosine, steps=4, lr_schedule="cosine", resume=True), progress=False)


def test_a_checkpoint_from_before_added_flags_resumes_when_they_keep_their_old_behaviour(tiny_scene, tmp_path,
                                                                                         monkeypatch):
    """A run checkpointed by a jaxdistill without --reuse_steps/--align (its recorded flags lack
    them) resumes with those flags at the values that reproduce it, and is refused otherwise."""
    original = loop.recorded_config
    monkeypatch.setattr(loop, "recorded_config", lambda config, kind: {
        k: v for k, v in original(config, kind).items() if k not in loop.ADDED_FLAG_DEFAULTS})
    out = tmp_path / "old"
    pipeline.run(tiny_config(tiny_scene, out, steps=2, renders=False), progress=False)
    monkeypatch.setattr(loop, "recorded_config", original)
    with pytest.raises(InputError, match=r"--align: checkpoint has \(not set\), current run has \"gain\""):
        pipeline.run(tiny_config(tiny_scene, out, steps=3, renders=False, resume=True, align="gain"), progress=False)
    done = pipeline.run(tiny_config(tiny_scene, out, steps=3, renders=False, resume=True), progress=False)
    assert done["resumed_from"] == 2 and done["steps"] == 3


# The flags a resume compares as they are, with no default for checkpoints that lack them. A flag
# added to DistillConfig must be resumable (config.RESUMABLE_FLAGS) or have the value that
# reproduces older runs in loop.ADDED_FLAG_DEFAULTS, or every checkpoint written before it would
# refuse to resume (as --prior_attention nearly did).
FIRST_RECORDED_FLAGS = frozenset((
    "scene", "maps", "prior", "prior_dtype", "lr", "lr_schedule", "weight_decay", "t_min", "t_max", "anneal",
    "t_weighting", "w_t", "w_i", "loss_space", "latent", "visibility_weighting", "p_keep", "render_size",
    "texture_size", "max_texture_size", "sampler", "views_per_step", "seed"))


def test_every_flag_added_since_the_first_checkpoints_keeps_them_resumable():
    fields = {f.name for f in dataclasses.fields(DistillConfig)}
    unplaced = fields - FIRST_RECORDED_FLAGS - set(config_lib.RESUMABLE_FLAGS) - set(loop.ADDED_FLAG_DEFAULTS)
    assert not unplaced, (f"{sorted(unplaced)}: add each to config.RESUMABLE_FLAGS, or to loop.ADDED_FLAG_DEFAULTS "
                          "with the value older checkpoints ran with")
    assert FIRST_RECORDED_FLAGS <= fields


def test_sigterm_saves_a_checkpoint_and_the_run_resumes_to_the_same_result(tiny_scene, tmp_path, monkeypatch):
    reference = tmp_path / "reference"
    pipeline.run(tiny_config(tiny_scene, reference, steps=6, renders=False), progress=False)
    original = Problem.batch
    calls = {"n": 0}

    def batch_then_signal(self, ids):
        calls["n"] += 1
        if calls["n"] == 4:                      # the batch of step 3
            os.kill(os.getpid(), signal.SIGTERM)
        return original(self, ids)

    monkeypatch.setattr(Problem, "batch", batch_then_signal)
    out = tmp_path / "interrupted"
    result = pipeline.run(tiny_config(tiny_scene, out, steps=6, renders=False), progress=False)
    monkeypatch.setattr(Problem, "batch", original)
    assert result == {"stopped_by": "SIGTERM", "step": 3, "exit_status": 128 + signal.SIGTERM}
    assert not (out / "metrics.json").exists()
    pipeline.run(tiny_config(tiny_scene, out, steps=6, renders=False, resume=True), progress=False)
    a, _ = restored(reference, 6)
    b, _ = restored(out, 6)
    np.testing.assert_array_equal(np.asarray(a.texels), np.asarray(b.texels))


def test_a_nan_loss_stops_the_run_and_keeps_the_last_good_state(tiny_scene, tmp_path, monkeypatch):
    from jaxdistill.engine import problem as problem_lib

    build = problem_lib.build_problem
    seed, poisoned_view = 0, {}

    def poisoned(config, **kw):
        p = build(config, **kw)
        # poison the one view that first appears at step >= 2, so steps before it are good
        first_seen = {}
        for step in range(config.steps):
            for v in p.view_ids(step, config.views_per_step, seed):
                first_seen.setdefault(int(v), step)
        view, step = max(first_seen.items(), key=lambda kv: kv[1])
        poisoned_view.update(view=view, step=step)
        targets = p.prior.target_images.copy()
        targets[view] = np.nan
        return dataclasses.replace(p, prior=dataclasses.replace(p.prior, target_images=targets))

    monkeypatch.setattr(pipeline, "build_problem", poisoned)
    out = tmp_path / "nan"
    with pytest.raises(loop.NonFiniteLoss, match=r"NaN/inf at step (\d+).*--lr") as err:
        pipeline.run(tiny_config(tiny_scene, out, steps=8, log_every=4, renders=False), progress=False)
    bad = poisoned_view["step"]
    assert bad >= 1 and f"at step {bad};" in str(err.value)
    state, _ = restored(out, bad)          # the checkpoint is the state before the bad step, not after
    assert int(state.step) == bad and bool(state.halted)
    assert np.isfinite(np.asarray(state.texels)).all()


def test_the_loop_runs_one_step_ahead_of_the_running_one_and_no_further(tiny_scene, tmp_path):
    """JAX returns from a step before it has run, on the CPU too: the loop places the next step's batch
    while a step runs, and no further ahead (each step dispatched ahead holds its batch in memory until
    it runs: up to --log_every of them between the metric fetches otherwise). Each step's metrics are
    made slow to finish here; when a step is dispatched, every step before the last has finished."""
    import jax.numpy as jnp

    from jaxdistill.engine.problem import build_problem

    @jax.jit
    def slow(metrics):
        x = jax.lax.fori_loop(0, 40, lambda _, x: jnp.tanh(x @ x), jnp.full((512, 512), 0.01, jnp.float32))
        return jax.tree.map(lambda a: a + (0 * x[0, 0]).astype(a.dtype) if jnp.issubdtype(a.dtype, jnp.floating)
                            else a, metrics)

    outputs, unfinished = [], []

    def before_steps(step_fn, state, batch, frozen):
        def step(state, batch, frozen):
            unfinished.append(sum(not a.is_ready() for m in outputs[:-1] for a in jax.tree.leaves(m)))
            state, metrics = step_fn(state, batch, frozen)
            outputs.append(slow(metrics))
            return state, outputs[-1]
        return step

    config = tiny_config(tiny_scene, tmp_path / "out", steps=6, log_every=6, eval_every=0, renders=False)
    problem = build_problem(config, cache_dir=tmp_path / "cache")
    result = loop.run_loop(config, problem, loop.recorded_config(config, "views"), None, progress=False,
                           hooks=loop.LoopHooks(before_steps=before_steps, checkpoints=False))
    assert unfinished == [0] * 6
    assert len(result.history["loss"]) == 6 and loop.PREFETCH_STEPS == 1


def test_configs_parse_into_valid_configs():
    for cfg in sorted((REPO / "configs").glob("*.cfg")):
        fv = flags.FlagValues()
        config_lib.define_flags(fv)
        fv([sys.argv[0], f"--flagfile={cfg}"])
        config = config_lib.config_from_flags(fv)
        assert config.scene and config.out_dir, cfg
    names = {p.stem for p in (REPO / "configs").glob("*.cfg")}
    assert {"bedroom", "smoke", "thesis"} <= names


def test_bad_flags_are_named_before_any_compute():
    fv = flags.FlagValues()
    config_lib.define_flags(fv)
    fv([sys.argv[0], "--scene=x", "--out_dir=y", "--p_keep=0", "--maps=albedo,shiny", "--t_min=0.9", "--t_max=0.5",
        "--texture_size=300", "--views_per_step=0"])
    with pytest.raises(InputError) as err:
        config_lib.config_from_flags(fv)
    text = str(err.value)
    for flag in ("--p_keep", "--maps", "--t_min/--t_max", "--texture_size", "--views_per_step"):
        assert flag in text
    for args, message in ((["--reuse_steps=0"], "--reuse_steps: must be >= 1, got 0"),
                          (["--reuse_steps=2", "--prior=views"], "--reuse_steps: the views prior's targets never change"),
                          (["--estimate_steps=-1"], "--estimate_steps: must be >= 1, or 0 for auto, got -1"),
                          (["--prior_attention=cudnn"], "--prior_attention: cudnn needs --prior_dtype=bfloat16"),
                          (["--prior_attention=cudnn", "--prior_dtype=bfloat16", "--prior=views"],
                           "--prior_attention: the views prior runs no network")):
        fv = flags.FlagValues()
        config_lib.define_flags(fv)
        fv([sys.argv[0], "--scene=x", "--out_dir=y", *args])
        with pytest.raises(InputError, match=message):
            config_lib.config_from_flags(fv)


def run_main(*args, env=None):
    return subprocess.run([sys.executable, "-m", "jaxdistill.main", *args], capture_output=True, text=True,
                          env={**os.environ, **(env or {})}, cwd=REPO)


def test_cli_explains_how_to_get_the_rgbx_weights(tiny_scene, tmp_path):
    env = {"JAXDISTILL_RGBX_DIR": ""}
    result = run_main(f"--scene={tiny_scene}", f"--out_dir={tmp_path}/o", f"--rgbx_dir={tmp_path}/nowhere", env=env)
    assert result.returncode != 0
    assert "huggingface-cli download zheng95z/rgb-to-x" in result.stderr and "Adobe Research License" in result.stderr
    partial = tmp_path / "rgbx"
    (partial / "unet").mkdir(parents=True)
    (partial / "model_index.json").write_text("{}")
    result = run_main(f"--scene={tiny_scene}", f"--out_dir={tmp_path}/o", f"--rgbx_dir={partial}", env=env)
    assert result.returncode != 0 and "vae/" in result.stderr and "missing" in result.stderr
    result = run_main(f"--scene={tmp_path}/nowhere", f"--out_dir={tmp_path}/o", env=env)
    assert result.returncode != 0 and "--scene" in result.stderr


def test_views_prior_names_a_missing_target(tmp_path):
    scene = write_tiny_scene(tmp_path / "scene", views=2)
    doc = json.loads(scene.read_text())
    del doc["views"][1]["targets"]["roughness"]
    scene.write_text(json.dumps(doc))
    with pytest.raises(InputError, match=r"views\[1\]\.targets\.roughness.*v1 has no roughness target"):
        pipeline.run(tiny_config(scene, tmp_path / "o", prior="views"), progress=False)


def test_auto_prior_uses_rgbx_weights_end_to_end(tiny_scene, run_rgbx_dir, tmp_path, monkeypatch):
    from jaxdistill.models import shipped

    monkeypatch.setattr(shipped, "SHIPPED_DIR", tmp_path / "no_shipped_model")   # auto: views when no weights at all
    monkeypatch.setenv("JAXDISTILL_RGBX_DIR", str(run_rgbx_dir))
    views_run = tmp_path / "views_run"
    monkeypatch.delenv("JAXDISTILL_RGBX_DIR")
    pipeline.run(tiny_config(tiny_scene, views_run, prior="auto", steps=1, maps=("albedo", "roughness"), renders=False,
                          eval_every=0), progress=False)
    monkeypatch.setenv("JAXDISTILL_RGBX_DIR", str(run_rgbx_dir))
    with pytest.raises(InputError, match=r"--prior_kind.*views.*rgbx"):     # auto resolved differently now
        pipeline.run(tiny_config(tiny_scene, views_run, prior="auto", steps=2, maps=("albedo", "roughness"),
                              resume=True), progress=False)
    out = tmp_path / "rgbx"
    # --estimate_steps=0 (auto, the default) asks models.estimates.default_steps for the model's count: for weights
    # a user brings that is the demo's 50 (below), for the shipped model its 10 (chosen on the validation rooms);
    # here it answers 4, since what is sampled is not the point
    asked = []
    monkeypatch.setattr(model_estimates, "default_steps", lambda folder: asked.append(folder) or 4)
    assert DistillConfig.estimate_steps == 0
    pipeline.run(tiny_config(tiny_scene, out, prior="auto", steps=2, maps=("albedo", "roughness"), renders=False,
                          eval_every=0, estimate_steps=0), progress=False)
    monkeypatch.undo()
    doc = json.loads((out / "metrics.json").read_text())
    assert doc["prior"]["kind"] == "rgbx" and "JAXDISTILL_RGBX_DIR" in doc["prior"]["reason"]
    assert doc["prior"]["model"] == {"name": "rgb-to-x", "source": "user", "folder": str(run_rgbx_dir)}
    # scored against the model's own per-view estimates, not the scene's targets, in the count auto resolved to
    assert asked and {str(f) for f in asked} == {str(run_rgbx_dir)}      # (also asked to compile them ahead)
    assert doc["baseline_source"].startswith("the model's own per-view estimates (4 DDIM steps")
    assert doc["baseline_estimate_steps"] == 4 and doc["config"]["estimate_steps"] == 0
    assert model_estimates.default_steps(run_rgbx_dir) == model_estimates.default_steps(None) == 50
    assert doc["anchor"]["to"] == doc["baseline_source"] and list(doc["anchor"]["gains"]) == ["albedo"]  # auto
    assert doc["baseline_per_view_estimates"]["albedo_psnr"] != json.loads(
        (views_run / "metrics.json").read_text())["baseline_per_view_estimates"]["albedo_psnr"]
    assert doc["traces"] == 1 and all(np.isfinite(doc["history"]["loss"]))
    assert (out / "maps" / "albedo" / "room_wall_x0.exr").is_file()


@pytest.mark.skipif(jax.default_backend() == "gpu", reason="checks the refusal on a machine without a GPU")
def test_fused_attention_is_refused_before_compute_without_an_nvidia_gpu(tiny_scene, run_rgbx_dir, tmp_path,
                                                                        monkeypatch):
    """--prior_attention=cudnn is checked against the run's device with the other flag problems,
    after jax.distributed would have joined (so not in `validate`), and before any set-up."""
    config = tiny_config(tiny_scene, tmp_path / "out", prior="rgbx", rgbx_dir=str(run_rgbx_dir), steps=1,
                         prior_dtype="bfloat16", prior_attention="cudnn")
    monkeypatch.setattr(pipeline, "build_problem", lambda *a, **k: pytest.fail("set-up ran before the refusal"))
    with pytest.raises(InputError, match="--prior_attention: cudnn needs an NVIDIA GPU .* this run's device is cpu"):
        pipeline.run(config, progress=False)
    assert not (tmp_path / "out").exists()


def test_a_run_that_reuses_x_pred_resumes_mid_cycle_to_the_same_losses(tiny_scene, run_rgbx_dir, tmp_path):
    """--reuse_steps=3 with the rgbx prior: 7 steps in one run, and 4 + 3 resumed (step 4 reuses
    the x_pred of step 3, which only the checkpointed state holds) give the same loss history, bit
    for bit; and the reused steps cost no prior pass (one trace, finite losses)."""
    kw = dict(prior="rgbx", rgbx_dir=str(run_rgbx_dir), maps=("albedo", "roughness"), reuse_steps=3, renders=False,
              eval_every=0, log_every=1)
    full, part = tmp_path / "full", tmp_path / "part"
    pipeline.run(tiny_config(tiny_scene, full, steps=7, **kw), progress=False)
    pipeline.run(tiny_config(tiny_scene, part, steps=4, **kw), progress=False)
    pipeline.run(tiny_config(tiny_scene, part, steps=7, resume=True, **kw), progress=False)
    a, b = (json.loads((o / "metrics.json").read_text()) for o in (full, part))
    assert b["resumed_from"] == 4 and a["traces"] == 1 and all(np.isfinite(a["history"]["loss"]))
    assert a["history"]["loss"] == b["history"]["loss"] and len(a["history"]["loss"]) == 7
    assert a["ours"] == b["ours"]
    with pytest.raises(InputError, match="--reuse_steps"):
        pipeline.run(tiny_config(tiny_scene, part, steps=8, resume=True, **dict(kw, reuse_steps=2)), progress=False)


def test_smaller_renders_train_at_their_size_and_evaluate_at_the_photos_size(tiny_scene, tmp_path):
    out = tmp_path / "small"
    pipeline.run(tiny_config(tiny_scene, out, render_size=16, steps=2, eval_every=0), progress=False)
    doc = json.loads((out / "metrics.json").read_text())
    assert doc["config"]["render_size"] == 16 and np.isfinite(doc["ours"]["albedo_psnr"])
    assert imageio.read_image(out / "renders" / "albedo" / "v0.png").shape == (24, 32, 3)


def test_state_that_cannot_fit_in_memory_is_refused_before_any_allocation(tiny_scene, tmp_path, monkeypatch):
    """A run whose texels + AdamW moments exceed the memory budget stops in build_problem with an
    InputError naming the sizing flags (the budget is shrunk to make the tiny scene 'too big')."""
    from jaxdistill.engine import problem as problem_lib

    config = tiny_config(tiny_scene, tmp_path / "big", texture_size="64", sampler="trilinear")
    fits = problem_lib.build_problem(config)
    need = fits.space.num_texels * fits.channels.num_channels * 4 * problem_lib.STATE_COPIES
    monkeypatch.setattr(problem_lib, "memory_budget", lambda: (need - 1, "test RAM"))
    with pytest.raises(InputError) as err:
        problem_lib.build_problem(config)
    message = str(err.value)
    assert "--texture_size/--max_texture_size" in message and "test RAM" in message
    assert f"{fits.space.num_texels:,} texels x {fits.channels.num_channels} channels" in message
    assert "--texture_size=auto" in message and "--sampler=bilinear" in message
    monkeypatch.setattr(problem_lib, "memory_budget", lambda: (need, "test RAM"))
    assert problem_lib.build_problem(config).space.num_texels == fits.space.num_texels   # exactly fits: runs


def test_sigterm_exits_143_after_the_checkpoint_and_says_so(tiny_scene, tmp_path):
    """The command, not just train.run: a scheduler's SIGTERM leaves a checkpoint and status 143
    (128 + 15, what a shell reports for a process the signal ended), never 0."""
    out = tmp_path / "run"
    log = tmp_path / "stderr.txt"
    with open(log, "w") as stderr:
        proc = subprocess.Popen([sys.executable, "-m", "jaxdistill.main", f"--scene={tiny_scene}", f"--out_dir={out}",
                                 "--prior=views", "--steps=1000000", "--views_per_step=2", "--log_every=1",
                                 "--renders=false"], stderr=stderr, stdout=subprocess.DEVNULL, cwd=REPO,
                                env={**os.environ, "JAX_PLATFORMS": "cpu"})
        try:
            deadline = time.monotonic() + 300
            while "distil:" not in log.read_text() and proc.poll() is None and time.monotonic() < deadline:
                time.sleep(0.2)          # the progress bar is up: the loop (and its signal handler) runs
            assert proc.poll() is None, log.read_text()[-3000:]
            proc.send_signal(signal.SIGTERM)
            status = proc.wait(timeout=300)
        finally:
            if proc.poll() is None:
                proc.kill()
    text = log.read_text()
    assert status == 143, text[-3000:]
    assert "stopped by SIGTERM at step" in text and "Exiting with status 143" in text
    assert "Traceback" not in text
    with checkpoint.CheckpointStore(out / "checkpoints") as store:
        assert store.latest_step() is not None and store.latest_step() >= 1


def test_damaged_newest_checkpoint_falls_back_to_the_previous_one(tiny_scene, tmp_path, caplog):
    """The newest checkpoint's array files are damaged after its commit (truncated): --resume warns,
    names the step folder, sets it aside and resumes from the previous committed step, bit-identical
    to resuming from that step directly."""
    import shutil

    damaged, direct = tmp_path / "damaged", tmp_path / "direct"
    pipeline.run(tiny_config(tiny_scene, damaged, steps=4, ckpt_every=2, renders=False, eval_every=0), progress=False)
    shutil.copytree(damaged, direct)
    shutil.rmtree(direct / "checkpoints" / "4")                        # the reference: step 2 is the newest
    arrays = sorted((damaged / "checkpoints" / "4" / "state").glob("ocdbt.process_*/d/*"))
    assert arrays
    for f in arrays:
        f.write_bytes(f.read_bytes()[: f.stat().st_size // 2])
    with caplog.at_level("WARNING"):
        pipeline.run(tiny_config(tiny_scene, damaged, steps=6, resume=True, renders=False, eval_every=0), progress=False)
    pipeline.run(tiny_config(tiny_scene, direct, steps=6, resume=True, renders=False, eval_every=0), progress=False)
    warning = [r.getMessage() for r in caplog.records if "is damaged" in r.getMessage()]
    assert len(warning) == 1, warning
    assert warning[0].startswith(f"{damaged / 'checkpoints' / '4'}: checkpoint of step 4 is damaged (")
    assert "resuming from the previous committed step 2" in warning[0]
    assert (damaged / "checkpoints.damaged" / "4").is_dir()           # kept for inspection, out of the store
    a, _ = restored(damaged, 6)
    b, _ = restored(direct, 6)
    for leaf_a, leaf_b in zip(jax_leaves(a), jax_leaves(b)):
        np.testing.assert_array_equal(leaf_a, leaf_b)
    doc_a, doc_b = (json.loads((o / "metrics.json").read_text()) for o in (damaged, direct))
    assert doc_a["resumed_from"] == doc_b["resumed_from"] == 2
    assert doc_a["history"] == doc_b["history"]


def test_no_readable_checkpoint_says_how_to_start_fresh(tiny_scene, tmp_path, monkeypatch):
    out = tmp_path / "run"
    pipeline.run(tiny_config(tiny_scene, out, steps=2, renders=False, eval_every=0), progress=False)
    for f in (out / "checkpoints" / "2" / "state").glob("ocdbt.process_*/d/*"):
        f.write_bytes(b"\0" * 64)
    monkeypatch.setattr(pipeline, "build_problem", lambda *a, **k: pytest.fail("computed before refusing"))
    with pytest.raises(InputError) as err:
        pipeline.run(tiny_config(tiny_scene, out, steps=4, resume=True), progress=False)
    message = str(err.value)
    assert f"{out / 'checkpoints' / '2'}: step 2: checkpoint is damaged (" in message
    assert (f"{out / 'checkpoints'}: --resume: no committed checkpoint reads back, so there is nothing to resume; "
            f"to start fresh, move {out / 'checkpoints'} away (or choose another --out_dir) and run without "
            "--resume") in message
    assert (out / "checkpoints" / "2").is_dir()                      # nothing moved when nothing can resume


def test_out_dir_that_cannot_be_written_is_refused_with_the_flags(tmp_path):
    a_file = tmp_path / "a_file"
    a_file.write_text("x")
    for out, expected in ((a_file, f"--out_dir: {a_file} is an existing file, not a folder"),
                          (a_file / "run", f"--out_dir: {a_file} is a file, so {a_file / 'run'} cannot be created")):
        with pytest.raises(InputError) as err:
            tiny_config("scene", out)
        assert f"flags: {expected}" in str(err.value)
    assert config_lib.out_dir_problem(str(tmp_path / "new" / "deeper")) is None       # created by the run
    # a read-only folder, checked as an ordinary user (root may write into it, and then the run could)
    with tempfile.TemporaryDirectory(dir="/tmp") as shared:          # searchable by that user
        locked = Path(shared) / "locked"
        locked.mkdir()
        locked.chmod(0o555)
        Path(shared).chmod(0o755)
        below, itself = _as_ordinary_user(lambda: [config_lib.out_dir_problem(str(p)) for p in (locked / "run", locked)])
    assert below == (f"{locked / 'run'} would be created in {locked}, which is not writable (read-only folder or "
                     "file system); choose a writable folder")
    assert itself == f"{locked} is not writable (read-only folder or file system); choose a writable folder"


def _as_ordinary_user(fn):
    """fn() run in a forked child as user nobody when the tests run as root (else here); its
    JSON-able result."""
    if os.geteuid() != 0:
        return fn()
    read, write = os.pipe()
    pid = os.fork()
    if pid == 0:                                  # the child: plain os calls only, then _exit
        try:
            os.setgid(65534)
            os.setuid(65534)
            os.write(write, json.dumps(fn()).encode())
        finally:
            os._exit(0)
    os.close(write)
    with os.fdopen(read) as f:
        text = f.read()
    os.waitpid(pid, 0)
    return json.loads(text)


def test_views_per_step_above_the_view_count_is_refused_before_ray_casting(tiny_scene, tmp_path, monkeypatch):
    from jaxdistill.render import fragments

    monkeypatch.setattr(fragments, "compute_fragments", lambda *a, **k: pytest.fail("ray cast before refusing"))
    with pytest.raises(InputError, match=rf"flags: --views_per_step: 5 is more than the 4 views of {tiny_scene}; "
                       r".*use --views_per_step <= 4"):
        pipeline.run(tiny_config(tiny_scene, tmp_path / "o", views_per_step=5), progress=False)


def test_damaged_rgbx_weights_stop_the_main_job_before_any_compute(tiny_scene, rgbx_dir, tmp_path, monkeypatch):
    import shutil

    folder = shutil.copytree(rgbx_dir, tmp_path / "rgbx")
    vae = folder / "vae" / "diffusion_pytorch_model.safetensors"
    vae.write_bytes(vae.read_bytes()[:1000])
    monkeypatch.setattr(pipeline, "build_problem", lambda *a, **k: pytest.fail("computed before refusing"))
    with pytest.raises(InputError, match=rf"{vae}: vae weights: damaged or incomplete safetensors file "
                       r"\(1,000 bytes; safetensors: .*\); re-download it: `huggingface-cli download zheng95z/rgb-to-x "
                       rf"vae/diffusion_pytorch_model.safetensors --local-dir {folder}`"):
        pipeline.run(tiny_config(tiny_scene, tmp_path / "o", prior="rgbx", rgbx_dir=str(folder)), progress=False)


@pytest.mark.parametrize("keep, expected", [(None, [5, 6]), (0, [1, 2, 3, 4, 5, 6]), (3, [4, 5, 6])])
def test_checkpoints_are_kept_to_the_newest_two_by_default(tiny_scene, tmp_path, keep, expected):
    out = tmp_path / "run"
    extra = {} if keep is None else {"keep_checkpoints": keep}
    pipeline.run(tiny_config(tiny_scene, out, ckpt_every=1, renders=False, eval_every=0, **extra), progress=False)
    with checkpoint.CheckpointStore(out / "checkpoints") as store:
        assert store.all_steps() == expected
    assert sorted(int(p.name) for p in (out / "checkpoints").iterdir() if p.name.isdigit()) == expected
