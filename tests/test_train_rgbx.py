"""The prior's training (scripts/train_rgbx.py, `jaxdistill.models.training.train_prior`): its
export is a diffusers folder that diffusers, transformers and our loader read to the same
networks; training stages resume bit-identically (tiny sizes)."""

from __future__ import annotations

import json
import os
from functools import partial
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

torch = pytest.importorskip("torch")
diffusers = pytest.importorskip("diffusers")
transformers = pytest.importorskip("transformers")

from jaxdistill.io import checkpoint  # noqa: E402
from jaxdistill.models.clip import CLIPTextConfig, CLIPTextTransformer  # noqa: E402
from jaxdistill.models.convert import load_rgbx  # noqa: E402
from jaxdistill.models.tokenizer import load_tokenizer  # noqa: E402
from jaxdistill.models.training import export_model, recipe, shards, train_prior  # noqa: E402
from jaxdistill.models.training.stages import Budget  # noqa: E402
from jaxdistill.models.training.vocabulary import write_prior_tokenizer  # noqa: E402
from jaxdistill.models.unet import UNet2DCondition, UNetConfig  # noqa: E402
from jaxdistill.models.vae import AutoencoderKL, VAEConfig  # noqa: E402
from tiny_rgbx import nchw, nhwc, rel_err  # noqa: E402

# two blocks each (a VAE of factor 2; one UNet level with cross-attention, one without), one text
# layer: every kind of block the recipe has, at a fraction of its compile time. The recipe's own four
# blocks go through the same export in tests/test_shipped_model.py (diffusers and transformers
# read the shipped folder to our networks).
TINY_VAE = dict(recipe.VAE, block_out_channels=(8, 16), down_block_types=("DownEncoderBlock2D",) * 2,
                up_block_types=("UpDecoderBlock2D",) * 2, norm_num_groups=8)
TINY_UNET = dict(recipe.UNET, block_out_channels=(8, 16), norm_num_groups=8, attention_head_dim=(2, 2),
                 cross_attention_dim=16, down_block_types=("CrossAttnDownBlock2D", "DownBlock2D"),
                 up_block_types=("UpBlock2D", "CrossAttnUpBlock2D"))
TINY_TEXT = dict(recipe.TEXT, hidden_size=16, intermediate_size=32, num_attention_heads=2, projection_dim=16,
                 num_hidden_layers=1)


def random_params(module, key, *inputs):
    """Flax's parameter tree (its shapes only: `eval_shape`, no init computed, a minute saved),
    every leaf seeded noise (norm scales around 1), so no transposition or naming error can hide
    behind zeros and ones."""
    params = jax.eval_shape(module.init, key, *inputs)
    leaves, tree = jax.tree.flatten_with_path(params)
    rng = np.random.default_rng(0)
    out = []
    for path, x in leaves:
        name = str(path[-1])
        fan_in = np.prod(x.shape[:-1]) if x.ndim > 1 else 1
        noise = rng.standard_normal(x.shape).astype(np.float32)
        out.append(jnp.asarray(1 + 0.2 * noise if "scale" in name else noise / np.sqrt(max(fan_in, 1)) * (0.1 if x.ndim == 1 else 1)))
    return jax.tree.unflatten(tree, out)


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    root = tmp_path_factory.mktemp("export")
    tok_dir = write_prior_tokenizer(root / "tok")
    tok = load_tokenizer(tok_dir)
    key = jax.random.key(3)
    unet = UNet2DCondition(UNetConfig.from_dict(TINY_UNET))
    vae = AutoencoderKL(VAEConfig.from_dict(TINY_VAE))
    text = CLIPTextTransformer(CLIPTextConfig.from_dict(dict(TINY_TEXT, vocab_size=len(tok.backend.get_vocab()))))
    unet_p = random_params(unet, key, jnp.zeros((1, 12, 16, 8)), jnp.zeros((1,)), jnp.zeros((1, 77, 16)))
    vae_p = random_params(vae, key, jnp.zeros((1, 32, 32, 3)))
    text_p = random_params(text, key, jnp.zeros((1, 77), jnp.int32))
    folder = root / "model"
    export_model.export(folder, tok_dir, unet_p, vae_p, text_p, scaling=0.37, unet=TINY_UNET, vae=TINY_VAE, text=TINY_TEXT)
    return folder, (unet, unet_p), (vae, vae_p), (text, text_p), tok


def test_export_is_read_back_by_our_loader_exactly(exported):
    folder, (_, unet_p), (_, vae_p), (_, text_p), _ = exported
    loaded = load_rgbx(folder)
    assert loaded.networks.vae.config.scaling_factor == pytest.approx(0.37)
    for part, params in (("unet", unet_p), ("vae", vae_p), ("text_encoder", text_p)):
        ours, back = jax.tree.leaves(params), jax.tree.leaves(loaded.params[part])
        assert len(ours) == len(back)
        assert all(np.array_equal(np.asarray(a), np.asarray(b)) for a, b in zip(ours, back)), part


def test_diffusers_and_transformers_load_the_export_and_agree_with_ours(exported):
    folder, (unet, unet_p), (vae, vae_p), (text, text_p), tok = exported
    rng = np.random.default_rng(1)
    sample = rng.standard_normal((2, 12, 16, 8)).astype(np.float32)
    t = np.array([10.0, 900.0], np.float32)
    context = rng.standard_normal((2, 77, 16)).astype(np.float32)
    t_unet = diffusers.UNet2DConditionModel.from_pretrained(folder / "unet").eval()
    with torch.no_grad():
        ref = t_unet(torch.from_numpy(nchw(sample)), torch.from_numpy(t), torch.from_numpy(context)).sample.numpy()
    assert rel_err(jax.jit(unet.apply)(unet_p, sample, t, context), nhwc(ref)) < 1e-5

    images = rng.uniform(-1, 1, (1, 32, 48, 3)).astype(np.float32)
    t_vae = diffusers.AutoencoderKL.from_pretrained(folder / "vae").eval()
    assert t_vae.config.scaling_factor == pytest.approx(0.37)
    with torch.no_grad():
        posterior = t_vae.encode(torch.from_numpy(nchw(images))).latent_dist
        decoded = t_vae.decode(posterior.mean).sample.numpy()
    mean, _ = jax.jit(partial(vae.apply, method="encode"))(vae_p, images)
    assert rel_err(mean, nhwc(posterior.mean.numpy())) < 1e-5
    assert rel_err(jax.jit(partial(vae.apply, method="decode"))(vae_p, mean), nhwc(decoded)) < 1e-5

    ids = tok.encode(["Albedo (diffuse basecolor)", ""])
    t_text = transformers.CLIPTextModel.from_pretrained(folder / "text_encoder").eval()
    t_tok = transformers.CLIPTokenizer.from_pretrained(folder / "tokenizer")
    assert t_tok(["Albedo (diffuse basecolor)", ""], padding="max_length", max_length=77).input_ids == ids.tolist()
    with torch.no_grad():
        hidden = t_text(torch.from_numpy(np.asarray(ids, np.int64))).last_hidden_state.numpy()
    assert rel_err(jax.jit(text.apply)(text_p, jnp.asarray(ids)), hidden) < 1e-5


def tiny_shards(folder: Path, rooms: int = 2, views: int = 3) -> None:
    rng = np.random.default_rng(0)
    for seed in range(rooms):
        arrays = {k: rng.integers(0, 256, (views, 16, 32, c), dtype=np.uint8)
                  for k, c in (("photo", 3), ("albedo", 3), ("normal", 3), ("roughness", 1), ("metallic", 1), ("irradiance", 3))}
        arrays["valid"] = np.ones((views, 16, 32, 1), np.uint8)
        shards.write_shard(folder / f"room_{seed:07d}.npz", arrays, {"seed": seed})


@pytest.fixture
def request_restore():
    """Config values to restore after the test: [(jax config name, previous value)]."""
    saved = []
    yield saved
    for name, value in saved:
        jax.config.update(name, value)


def test_training_stops_on_its_budget_and_resumes_bit_identically(tmp_path, monkeypatch, request_restore):
    """4 VAE + 4 UNet steps in one run equal the same run cut after 2 and after 4 more steps
    (`--stop_after_steps`, exit 75 with a checkpoint, as a time limit or SIGTERM would) and resumed."""
    monkeypatch.setattr(recipe, "VAE", TINY_VAE)
    monkeypatch.setattr(recipe, "UNET", TINY_UNET)
    monkeypatch.setattr(recipe, "TEXT", TINY_TEXT)
    # each run jits its own closures: a persistent compilation cache compiles each program once
    for name, value in (("jax_compilation_cache_dir", str(tmp_path / "xla")),
                        ("jax_persistent_cache_min_compile_time_secs", 0.0),
                        ("jax_persistent_cache_min_entry_size_bytes", 0)):
        previous = getattr(jax.config, name)
        jax.config.update(name, value)
        request_restore.append((name, previous))
    tiny_shards(tmp_path / "data")
    common = ["--data", str(tmp_path / "data"), "--vae_batch=2", "--unet_batch=4", "--ckpt_every=3", "--stage=unet",
              "--vae_steps=4", "--unet_steps=4"]
    assert train_prior.main(common + ["--work", str(tmp_path / "a")]) == 0
    for budget, stage in ((2, "vae"), (4, "unet")):              # vae 0-2 | vae 2-4, unet 0-2 | unet 2-4
        with pytest.raises(SystemExit) as stop:
            train_prior.main(common + ["--work", str(tmp_path / "b"), f"--stop_after_steps={budget}"])
        assert stop.value.code == Budget.EXIT_UNFINISHED
        assert sorted(int(p.name) for p in (tmp_path / "b" / f"ckpt_{stage}").iterdir() if p.name.isdigit())[-1] == 2
    assert train_prior.main(common + ["--work", str(tmp_path / "b")]) == 0
    la, lb = (np.load(tmp_path / w / "latents.npz") for w in ("a", "b"))
    for k in la.files:
        np.testing.assert_array_equal(la[k], lb[k])
    final = [(tmp_path / w / "unet_loss.jsonl").read_text().splitlines()[-1] for w in ("a", "b")]
    assert final[0] == final[1] and '"step": 4' in final[0]


def test_float16_export_halves_the_weights_and_reads_back_rounded(exported, tmp_path):
    folder, (_, unet_p), (_, vae_p), (_, text_p), _ = exported
    half = tmp_path / "half"
    export_model.export(half, folder / "tokenizer", unet_p, vae_p, text_p, scaling=0.37, unet=TINY_UNET, vae=TINY_VAE,
                      text=TINY_TEXT, dtype="float16")
    export_model.check_export(half, unet_p, vae_p, text_p, "float16")     # raises unless equal to the rounded weights
    with pytest.raises(AssertionError):
        export_model.check_export(half, unet_p, vae_p, text_p, "float32")  # rounding did happen
    size = {f: sum(p.stat().st_size for p in (f / "unet").glob("*.safetensors")) for f in (folder, half)}
    assert size[half] < 0.6 * size[folder]          # half the bytes per weight, plus the same header


def test_init_continues_a_model_keeping_its_vae_scaling_and_text_encoder(exported, tmp_path, monkeypatch):
    """`--init`: no VAE training; the export keeps the init's VAE, latent scaling and text
    encoder exactly; with 0 UNet steps the UNet is the init's too (it was loaded into the right
    tree), with 2 steps it moved."""
    folder, (_, unet_p), (_, vae_p), (_, text_p), _ = exported
    monkeypatch.setattr(recipe, "VAE", TINY_VAE)
    monkeypatch.setattr(recipe, "UNET", TINY_UNET)
    monkeypatch.setattr(recipe, "TEXT", TINY_TEXT)
    tiny_shards(tmp_path / "data")
    for steps in (0, 2):
        work = tmp_path / f"work{steps}"
        assert train_prior.main(["--data", str(tmp_path / "data"), "--work", str(work), "--init", str(folder),
                                "--unet_batch=4", f"--unet_steps={steps}", "--export_dtype=float32"]) == 0
        assert not (work / "ckpt_vae").exists()
        out = load_rgbx(work / "model")
        assert out.networks.vae.config.scaling_factor == pytest.approx(0.37)
        for part, params in (("vae", vae_p), ("text_encoder", text_p)) + ((("unet", unet_p),) if steps == 0 else ()):
            assert all(np.array_equal(np.asarray(a), np.asarray(b))
                       for a, b in zip(jax.tree.leaves(params), jax.tree.leaves(out.params[part]))), (steps, part)
        moved = max(float(np.max(np.abs(np.asarray(a) - np.asarray(b))))
                    for a, b in zip(jax.tree.leaves(unet_p), jax.tree.leaves(out.params["unet"])))
        assert (moved > 0) == (steps > 0)


def test_a_unet_trained_from_8_bit_latents_elsewhere_exports_from_its_weights_file(exported, tmp_path, monkeypatch):
    """v2's route: latents encoded in 8 bits by the init's VAE; the UNet trained from random
    weights (`--fresh_unet`) from them alone, the shards not read (another machine); its EMA weights
    carried back as float16 (`scripts/train_rgbx_gpu.sh`) and exported by `--stage=export` from
    that file: the exported UNet is those weights, the VAE and text encoder the init's."""
    folder, (_, unet_p), (_, vae_p), (_, text_p), _ = exported
    monkeypatch.setattr(recipe, "VAE", TINY_VAE)
    monkeypatch.setattr(recipe, "UNET", TINY_UNET)
    monkeypatch.setattr(recipe, "TEXT", TINY_TEXT)
    tiny_shards(tmp_path / "data")
    here, there = tmp_path / "here", tmp_path / "there"
    common = ["--init", str(folder), "--latent_bits=8", "--fresh_unet", "--unet_batch=4", "--unet_steps=2"]
    assert train_prior.main(["--data", str(tmp_path / "data"), "--work", str(here), "--stage=latents"] + common) == 0
    there.mkdir()
    (there / "latents.npz").write_bytes((here / "latents.npz").read_bytes())
    with np.load(here / "latents.npz") as z:
        assert z["albedo"].dtype == np.uint8 and z["albedo_lo"].shape == (4,)
    assert train_prior.main(["--data", str(tmp_path / "no_shards_here"), "--work", str(there), "--stage=unet",
                             "--ema_snapshots", "--ckpt_every=1"] + common) == 0
    with np.load(there / "unet_ema.npz") as z:
        carried = {k: z[k].astype(np.float16) for k in z.files}
        with np.load(there / "unet_ema_2.npz") as last, np.load(there / "unet_ema_1.npz") as first:
            assert all(np.array_equal(z[k], last[k]) for k in z.files)            # the final snapshot is the weights
            assert not all(np.array_equal(z[k], first[k]) for k in z.files)       # the first is a step earlier
    np.savez(here / "unet_ema.npz", **carried)
    assert train_prior.main(["--data", str(tmp_path / "data"), "--work", str(here), "--stage=export"] + common) == 0
    out = load_rgbx(here / "model")
    from flax import traverse_util
    exported_unet = traverse_util.flatten_dict(jax.device_get(out.params["unet"]), sep="/")
    assert set(exported_unet) == set(carried)
    for k, v in carried.items():
        np.testing.assert_array_equal(np.asarray(exported_unet[k], np.float16), v)
    moved = max(float(np.max(np.abs(np.asarray(a, np.float32) - np.asarray(b, np.float32))))
                for a, b in zip(jax.tree.leaves(unet_p), jax.tree.leaves(out.params["unet"])))
    assert moved > 0.01                                     # not the init's UNet: trained from random weights
    for part, params in (("vae", vae_p), ("text_encoder", text_p)):
        for a, b in zip(jax.tree.leaves(params), jax.tree.leaves(out.params[part])):
            np.testing.assert_array_equal(np.asarray(a, np.float16), np.asarray(b, np.float16))
    record = json.loads((here / "model" / "jaxdistill_model.json").read_text())
    assert record["latent_bits"] == 8 and record["unet"]["fresh"] and record["unet"]["layers_per_block"] == 1
    with pytest.raises(SystemExit, match=r"unet_ema\.npz: its UNet is not the one asked for"):
        train_prior.main(["--data", str(tmp_path / "data"), "--work", str(here), "--stage=export",
                          "--unet_layers_per_block=2"] + common)
    future = (there / "unet_ema.npz").stat().st_mtime + 60          # a checkpoint newer than the weights file
    os.utime(there / "ckpt_unet" / "2", (future, future))
    with pytest.raises(SystemExit, match=r"unet_ema\.npz: older than the UNet stage's checkpoint .*ckpt_unet/2"):
        train_prior.main(["--data", str(tmp_path / "data"), "--work", str(there), "--stage=export"] + common)
    with pytest.raises(SystemExit, match=r"latents\.npz: its latents are stored in 8 bits, but --latent_bits=32"):
        train_prior.main(["--data", str(tmp_path / "data"), "--work", str(here), "--stage=export", "--init",
                          str(folder), "--fresh_unet"])


def test_8_bit_latents_are_within_half_a_level_per_channel():
    rng = np.random.default_rng(1)
    x = (rng.standard_normal((6, 3, 5, 4)) * np.array([1.0, 5.0, 0.1, 30.0]) + np.array([0, 3, -2, 9])).astype(np.float32)
    q = train_prior.quantize(x, 8)
    assert q["q"].dtype == np.uint8 and q["q"].min() == 0 and q["q"].max() == 255
    back = train_prior.dequantize(q["q"], q["lo"], q["step"])
    span = x.max((0, 1, 2)) - x.min((0, 1, 2))
    assert np.all(np.abs(back - x).max((0, 1, 2)) <= span / 510 * (1 + 1e-5))


def test_fit_steps_fills_the_minutes_after_compiling_and_keeps_its_choice(tmp_path, monkeypatch):
    clock = [0.0]
    monkeypatch.setattr(train_prior.time, "perf_counter", lambda: clock[0])

    def step(state, batch, cost):
        clock[0] += 5.0 if state == 0 else cost          # the first call compiles
        return state + 1, jnp.zeros(())

    fit = partial(train_prior.fit_steps, tmp_path, 1.0, init_state=lambda: 0, batch_fn=lambda i: None, probe=10)
    # 60 s less 2 x 5.01 s of compiling (the probe's first two calls; the real program's) and the
    # probe's 0.1 s, at 10 ms a step: 4988, down to thousands
    assert fit(partial(step, cost=0.01)) == 4000
    assert json.loads((tmp_path / "unet_steps.json").read_text())["steps"] == 4000
    assert fit(partial(step, cost=1.0)) == 4000              # kept: a resumed run keeps its schedule
    with pytest.raises(SystemExit, match=r"unet_steps.json: this stage's steps were fitted to --unet_minutes=1.0, not 2.0"):
        train_prior.fit_steps(tmp_path, 2.0, partial(step, cost=0.01), lambda: 0, lambda i: None, probe=10)
    (tmp_path / "unet_steps.json").write_text("null")
    with pytest.raises(SystemExit, match=r"unet_steps.json: not a record of --unet_minutes' choice"):
        train_prior.fit_steps(tmp_path, 1.0, partial(step, cost=0.01), lambda: 0, lambda i: None, probe=10)
    begun = tmp_path / "steps_run" / "ckpt_unet" / "500"                    # a stage begun with --unet_steps
    begun.mkdir(parents=True)
    (begun / checkpoint._COMMIT_FILE).touch()                                 # a complete checkpoint, as orbax marks it
    with pytest.raises(SystemExit, match=r"ckpt_unet: this stage was started with --unet_steps"):
        train_prior.fit_steps(tmp_path / "steps_run", 1.0, partial(step, cost=0.01), lambda: 0, lambda i: None)
    with pytest.raises(SystemExit, match=r"--unet_minutes=1.0: .* fewer than 1000 steps fit"):
        train_prior.fit_steps(tmp_path / "slow", 1.0, partial(step, cost=0.1), lambda: 0, lambda i: None, probe=10)


def test_unet_config_keeps_the_recipe_and_names_widths_it_cannot_take():
    assert recipe.unet_config() == recipe.UNET
    wide = recipe.unet_config((48, 96, 96, 96), 2)
    assert wide["attention_head_dim"] == (3, 6, 6, 6) and wide["layers_per_block"] == 2
    with pytest.raises(ValueError, match="multiple of 16"):
        recipe.unet_config((40, 64, 64, 64))
    with pytest.raises(ValueError, match="1 or more"):
        recipe.unet_config(None, 0)


def test_init_names_the_flag_when_the_folder_is_not_a_model(tmp_path):
    tiny_shards(tmp_path / "data")
    with pytest.raises(SystemExit, match="--init: .*model_index.json"):
        train_prior.main(["--data", str(tmp_path / "data"), "--work", str(tmp_path / "w"), "--init", str(tmp_path)])


def test_timesteps_draw_the_high_fraction_from_the_top_of_the_schedule():
    key = jax.random.key(0)
    uniform = np.asarray(train_prior.timesteps(key, 4000, 1000))
    assert uniform.min() >= 0 and uniform.max() <= 999 and abs((uniform >= 900).mean() - 0.1) < 0.02
    mixed = np.asarray(train_prior.timesteps(key, 4000, 1000, high_fraction=0.25, high_from=900))
    assert (mixed[:1000] >= 900).all() and mixed.max() <= 999            # the first quarter: U{900..999}
    assert abs((mixed[1000:] >= 900).mean() - 0.1) < 0.02                # the rest stays uniform
    assert len(np.unique(mixed[:1000])) > 90


def test_uniform_timesteps_are_the_stream_of_one_randint_and_bad_high_flags_are_named(tmp_path, capsys):
    key = jax.random.key(3)
    np.testing.assert_array_equal(np.asarray(train_prior.timesteps(key, 64, 1000)),
                                  np.asarray(jax.random.randint(key, (64,), 0, 1000)))   # recipes stay reproducible
    for flag, value in (("--t_high_fraction", "1.5"), ("--t_high_from", "1000"), ("--t_high_from", "-1")):
        with pytest.raises(SystemExit):
            train_prior.main([f"--data={tmp_path}", f"--work={tmp_path / 'w'}", f"{flag}={value}"])
        assert f"{flag}: must be in" in capsys.readouterr().err
