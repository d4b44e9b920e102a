"""Trains our small RGB<->X-family prior on `make_rgbx_data.py` shards and exports it.

    python scripts/train_rgbx.py --data=data/rgbx/train --work=data/rgbx_model            # all stages
    python scripts/train_rgbx.py --data=... --work=... --stage=unet --unet_steps=8000     # one stage

The model has RGB<->X's families and interface (shared/DESIGN.md section 3), only smaller:
AutoencoderKL (4 blocks, factor 8), UNet2DConditionModel with 8 input channels (noisy latent ||
photo latent), cross-attention on CLIP text embeddings of the five RGB<->X prompts,
v-prediction on scaled-linear betas rescaled to zero terminal SNR. All in JAX with the
project's own Flax modules (`jaxdistill.models`) and optax:

1. `vae`: the autoencoder on photos and all five maps ([-1, 1], grey maps as 3 channels):
   L1 + L2 reconstruction plus a small KL term; AdamW.
2. `latents`: every photo and map encoded once (the posterior mean); the latent scaling
   factor is 1 / std of the map latents (Stable Diffusion's rule), written to the VAE config.
3. `unet`: v-prediction MSE at t ~ U{0..999}; the photo latent is zeroed and the prompt
   emptied each with probability `--p_drop` (independently), so eq. 4.2's guidance means
   something; AdamW with warm-up and cosine decay; an EMA of the weights is what ships.
   The text encoder is a tiny CLIP transformer with seeded random weights, frozen (RGB<->X's
   CLIP is frozen too): it only has to give the five prompts and "" distinct embeddings.
4. `export`: a diffusers folder (model_index.json, unet/, vae/, text_encoder/, tokenizer/,
   scheduler/, safetensors), written by diffusers/transformers themselves from our weights
   (needs the test extras: torch 2.13.0 CPU, diffusers, transformers), read back by
   `jaxdistill.models.convert.load_rgbx` and checked equal.

Every stage is deterministic from `--seed`, shows a progress bar with ETA, saves orbax
checkpoints in `--work` every `--ckpt_every` steps and on SIGINT/SIGTERM, and resumes from the
newest one when run again (a finished stage is skipped).
"""

from __future__ import annotations

import argparse
import json
import math
import shutil
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import optax
from tqdm import tqdm

from jaxdistill.io import images as imageio
from jaxdistill.io.checkpoint import CheckpointStore, StopSignals
from jaxdistill.models import scheduler as sched
from jaxdistill.models.clip import CLIPTextConfig, CLIPTextTransformer
from jaxdistill.models.prior import MAP_PROMPTS, photo_to_model_space
from jaxdistill.models.tokenizer import load_tokenizer
from jaxdistill.models.unet import UNet2DCondition, UNetConfig
from jaxdistill.models.vae import AutoencoderKL, VAEConfig

REPO = Path(__file__).resolve().parents[1]
MAPS = ("albedo", "normal", "roughness", "metallic", "irradiance")

# diffusers / transformers configs (what export writes); our Flax configs are read from them
VAE = dict(in_channels=3, out_channels=3, block_out_channels=(16, 32, 64, 64), layers_per_block=1,
           down_block_types=("DownEncoderBlock2D",) * 4, up_block_types=("UpDecoderBlock2D",) * 4,
           latent_channels=4, norm_num_groups=16, sample_size=128, scaling_factor=1.0)
UNET = dict(sample_size=16, in_channels=8, out_channels=4, block_out_channels=(32, 64, 64, 64), layers_per_block=1,
            norm_num_groups=16, attention_head_dim=(2, 4, 4, 4), cross_attention_dim=64, use_linear_projection=True,
            upcast_attention=True, down_block_types=("CrossAttnDownBlock2D",) * 3 + ("DownBlock2D",),
            up_block_types=("UpBlock2D",) + ("CrossAttnUpBlock2D",) * 3)
TEXT = dict(hidden_size=64, intermediate_size=128, num_hidden_layers=2, num_attention_heads=4,
            max_position_embeddings=77, hidden_act="gelu", layer_norm_eps=1e-5, projection_dim=64)
SCHEDULER = {"_class_name": "DDIMScheduler", "_diffusers_version": "0.20.0", "beta_end": 0.012,
             "beta_schedule": "scaled_linear", "beta_start": 0.00085, "clip_sample": False,
             "num_train_timesteps": 1000, "prediction_type": "v_prediction", "set_alpha_to_one": False,
             "skip_prk_steps": True, "steps_offset": 1, "trained_betas": None,
             "rescale_betas_zero_snr": True, "timestep_spacing": "trailing"}


# ----------------------------------------------------------------------------- data


def load_images(folder: Path):
    """(photos (N, H, W, 3) in model space, {map: (N, H, W, 3) in model space}, valid (N, H, W)):
    every shard of `folder`, in seed order; model space as `jaxdistill.scene.maps` defines it (albedo
    and irradiance linear, normals unit vectors, grey maps replicated to 3 channels)."""
    shards = sorted(p for p in folder.glob("room_*.npz") if ".tmp" not in p.name)
    if not shards:
        raise SystemExit(f"{folder}: no room_*.npz shards; generate them with scripts/make_rgbx_data.py")
    parts = {k: [] for k in ("photo", "valid") + MAPS}
    for path in shards:
        with np.load(path) as z:
            for k in parts:
                parts[k].append(z[k])
    u8 = {k: np.concatenate(v) for k, v in parts.items()}
    photos = np.asarray(photo_to_model_space(u8["photo"].astype(np.float32) / 255))
    maps = {}
    for name in MAPS:
        x = u8[name].astype(np.float32) / 255
        if name in ("albedo", "irradiance"):
            x = imageio.srgb_to_linear(x)
        if x.shape[-1] == 1:
            x = np.repeat(x, 3, -1)
        maps[name] = (2.0 * x - 1.0).astype(np.float32)
    return photos.astype(np.float32), maps, u8["valid"][..., 0] > 0


# ----------------------------------------------------------------------------- training loop


class Budget:
    """This run's limits across stages: at most `steps` steps (0: none) and `minutes` (0: none)."""

    EXIT_UNFINISHED = 75          # EX_TEMPFAIL: checkpoint saved, run again to continue

    def __init__(self, steps: int = 0, minutes: float = 0.0):
        self.steps, self.deadline, self.done = steps, time.monotonic() + 60 * minutes if minutes else None, 0

    def spent(self) -> bool:
        return bool(self.steps and self.done >= self.steps) or bool(self.deadline and time.monotonic() > self.deadline)


def run_stage(name: str, work: Path, state, step_fn, batch_fn, steps: int, ckpt_every: int, config: dict,
              budget: Budget):
    """Runs `state = step_fn(state, batch_fn(step))` from the newest checkpoint of stage `name`
    to `steps`, with a progress bar (loss, ETA) and orbax checkpoints; returns the final state.
    SIGINT/SIGTERM save and exit with 130/143; a spent `budget` saves and exits with 75."""
    with CheckpointStore(work / f"ckpt_{name}", max_to_keep=2) as store:
        start = store.latest_step() or 0
        if start:
            state, _ = store.restore(start, state)
            print(f"{name}: resumed at step {start} of {steps}")
        if start >= steps:
            return state
        losses = []
        with StopSignals() as stop, tqdm(total=steps, initial=start, desc=name, unit="step") as bar:
            for step in range(start, steps):
                state, loss = step_fn(state, batch_fn(step))
                losses.append(loss)
                budget.done += 1
                if (step + 1) % 25 == 0 or step + 1 == steps:
                    bar.set_postfix(loss=f"{float(np.mean(jax.device_get(losses[-25:]))):.4f}")
                bar.update(1)
                halt = stop.requested or budget.spent()
                if (step + 1) % ckpt_every == 0 or step + 1 == steps or halt:
                    store.save(step + 1, state, config)
                    with open(work / f"{name}_loss.jsonl", "a") as f:
                        f.write(json.dumps({"step": step + 1, "loss": float(np.mean(jax.device_get(losses)))}) + "\n")
                    losses = []
                if halt and step + 1 < steps:
                    why = stop.signal_name or "this run's step/time budget spent"
                    status = stop.exit_status if stop.requested else Budget.EXIT_UNFINISHED
                    print(f"{name}: {why} at step {step + 1} of {steps}; checkpoint saved, run the same command "
                          f"again to resume (exit status {status})")
                    sys.exit(status)
    return state


def adamw(lr: float, steps: int, weight_decay: float = 0.01):
    warmup = max(min(500, steps // 10), 1)
    schedule = optax.warmup_cosine_decay_schedule(0.0, lr, warmup, max(steps, warmup + 1), lr * 0.05)
    return optax.chain(optax.clip_by_global_norm(1.0), optax.adamw(schedule, weight_decay=weight_decay))


# ----------------------------------------------------------------------------- stage 1: VAE


def train_vae(args, photos, maps):
    vae = AutoencoderKL(VAEConfig.from_dict(VAE))
    pool = np.concatenate([photos] + [maps[m] for m in MAPS])        # (6N, H, W, 3)
    params = vae.init(jax.random.key(args.seed), jnp.zeros((1,) + pool.shape[1:]))
    tx = adamw(args.vae_lr, args.vae_steps)
    state = {"params": params, "opt": tx.init(params)}

    def loss_fn(params, images, key):
        mean, logvar = vae.apply(params, images, method="encode")
        z = mean + jnp.exp(0.5 * logvar) * jax.random.normal(key, mean.shape)
        recon = vae.apply(params, z, method="decode")
        kl = 0.5 * jnp.mean(jnp.sum(mean ** 2 + jnp.exp(logvar) - 1.0 - logvar, axis=-1))
        err = recon - images
        return jnp.mean(jnp.abs(err)) + jnp.mean(err ** 2) + args.kl_weight * kl

    @jax.jit
    def step(state, batch):
        images, key = batch
        loss, grads = jax.value_and_grad(loss_fn)(state["params"], images, key)
        updates, opt = tx.update(grads, state["opt"], state["params"])
        return {"params": optax.apply_updates(state["params"], updates), "opt": opt}, loss

    def batch(step):
        rng = np.random.default_rng([args.seed, 1, step])
        return jnp.asarray(pool[rng.integers(len(pool), size=args.vae_batch)]), jax.random.fold_in(jax.random.key(args.seed), step)

    state = run_stage("vae", args.work, state, step, batch, args.vae_steps, args.ckpt_every, {"stage": "vae", **VAE},
                      args.budget)
    return vae, state["params"]


# ----------------------------------------------------------------------------- stage 2: latents


def encode_all(args, vae, vae_params, photos, maps):
    """{photo, <map>: (N, h, w, 4) unscaled posterior means}, cached in work/latents.npz."""
    cache = args.work / "latents.npz"
    if cache.exists():
        with np.load(cache) as z:
            return {k: z[k] for k in z.files}
    encode = jax.jit(lambda x: vae.apply(vae_params, x, method="encode")[0])
    out = {}
    for name, images in tqdm([("photo", photos)] + [(m, maps[m]) for m in MAPS], desc="latents", unit="kind"):
        out[name] = np.concatenate([np.asarray(encode(jnp.asarray(images[i:i + 64]))) for i in range(0, len(images), 64)])
    np.savez(cache, **out)
    return out


# ----------------------------------------------------------------------------- stage 3: UNet


def prompt_ids(tokenizer):
    """(6, 77) token ids of the five map prompts, then the empty prompt."""
    return jnp.asarray(tokenizer.encode([MAP_PROMPTS[m] for m in MAPS] + [""]))


def load_init(folder: Path):
    """The networks and float32 params of a diffusers folder to continue from (`--init`)."""
    from jaxdistill.models.convert import load_rgbx

    if not (folder / "model_index.json").is_file():
        raise SystemExit(f"--init: {folder} has no model_index.json; give a diffusers folder this script exported")
    return load_rgbx(folder, flag="--init")


def init_prompts(init, tokenizer):
    """(text params, (6, 77, D) last hidden states of the five prompts then "") of an `--init` model."""
    ids = prompt_ids(tokenizer)
    params = init.params["text_encoder"]
    return params, np.asarray(init.networks.text_encoder.apply(params, ids))


def text_encoder_and_prompts(seed: int, tokenizer, text: dict = TEXT):
    """(frozen CLIP params, (6, 77, D) last hidden states of the five prompts then "")."""
    encoder = CLIPTextTransformer(CLIPTextConfig.from_dict(dict(text, vocab_size=len(tokenizer.backend.get_vocab()))))
    ids = prompt_ids(tokenizer)
    params = encoder.init(jax.random.key(seed + 7), ids)
    return params, np.asarray(encoder.apply(params, ids))


def timesteps(key, batch: int, num_train_timesteps: int, high_fraction: float = 0.0, high_from: int = 900):
    """(batch,) int32 training timesteps: U{0..T-1}, except that a fraction `high_fraction` of
    the batch (rounded down) draws from U{high_from..T-1}. The x̂0 a single pass at t = T-1 gives
    (the model's conditional mean under zero terminal SNR) is learned only from the high-t
    samples, a tenth of a uniform batch above t = 900."""
    t = jax.random.randint(key, (batch,), 0, num_train_timesteps)      # as before the option: same stream at 0
    high = int(batch * high_fraction)
    if high:
        t = t.at[:high].set(jax.random.randint(jax.random.fold_in(key, 1), (high,), high_from, num_train_timesteps))
    return t


def train_unet(args, latents, contexts, scaling, init_params=None):
    unet = UNet2DCondition(UNetConfig.from_dict(UNET))
    config = sched.SchedulerConfig(**{k: SCHEDULER[k] for k in ("beta_start", "beta_end", "beta_schedule",
                                                                "num_train_timesteps", "prediction_type",
                                                                "rescale_betas_zero_snr")})
    alpha_bar = sched.alphas_cumprod(config)
    photo = latents["photo"] * scaling
    targets = np.stack([latents[m] * scaling for m in MAPS], 1)   # (N, 5, h, w, 4)
    n, h, w = photo.shape[:3]
    params = unet.init(jax.random.key(args.seed + 1), jnp.zeros((1, h, w, 8)), jnp.zeros((1,)), jnp.asarray(contexts[:1]))
    if init_params is not None:
        if jax.tree.structure(init_params) != jax.tree.structure(params) or any(
                a.shape != b.shape for a, b in zip(jax.tree.leaves(init_params), jax.tree.leaves(params))):
            raise SystemExit(f"--init: its UNet is not this script's UNet ({UNET['block_out_channels']} blocks, "
                             f"{h}x{w} latents); give a folder this script exported")
        params = jax.tree.map(jnp.asarray, init_params)
    tx = adamw(args.unet_lr, args.unet_steps)
    state = {"params": params, "ema": params, "opt": tx.init(params)}
    ctx = jnp.asarray(contexts)

    def loss_fn(params, x0, cond, which, key):
        k_t, k_eps, k_img, k_txt = jax.random.split(key, 4)
        b = x0.shape[0]
        t = timesteps(k_t, b, config.num_train_timesteps, args.t_high_fraction, args.t_high_from)
        eps = jax.random.normal(k_eps, x0.shape)
        ab = alpha_bar[t]
        z_t = sched.add_noise(x0, eps, ab)
        v = sched.v_from_x0_eps(x0, eps, ab)
        cond = jnp.where((jax.random.uniform(k_img, (b,)) < args.p_drop)[:, None, None, None], 0.0, cond)
        which = jnp.where(jax.random.uniform(k_txt, (b,)) < args.p_drop, len(MAPS), which)
        pred = unet.apply(params, jnp.concatenate([z_t, cond], -1), t, ctx[which])
        return jnp.mean((pred - v) ** 2)

    @jax.jit
    def step(state, batch):
        x0, cond, which, key = batch
        loss, grads = jax.value_and_grad(loss_fn)(state["params"], x0, cond, which, key)
        updates, opt = tx.update(grads, state["opt"], state["params"])
        params = optax.apply_updates(state["params"], updates)
        ema = jax.tree.map(lambda e, p: args.ema * e + (1 - args.ema) * p, state["ema"], params)
        return {"params": params, "ema": ema, "opt": opt}, loss

    def batch(step):
        rng = np.random.default_rng([args.seed, 3, step])
        i, m = rng.integers(n, size=args.unet_batch), rng.integers(len(MAPS), size=args.unet_batch)
        return (jnp.asarray(targets[i, m]), jnp.asarray(photo[i]), jnp.asarray(m),
                jax.random.fold_in(jax.random.key(args.seed + 3), step))

    state = run_stage("unet", args.work, state, step, batch, args.unet_steps, args.ckpt_every, {"stage": "unet", **UNET},
                      args.budget)
    return unet, state["ema"]


# ----------------------------------------------------------------------------- stage 4: export


def torch_state(flax_params: dict, torch_shapes: dict[str, tuple]) -> dict:
    """The PyTorch state dict (name -> float32 array) of our Flax params, by the inverse of
    `convert.convert_state_dict`'s rules: conv kernel HWIO -> OIHW, linear kernel transposed,
    scale/embedding -> weight. Keys come from the PyTorch model itself."""
    from flax import traverse_util

    from jaxdistill.models.convert import _IGNORED_KEYS, _normalise_key, flax_path

    flat = traverse_util.flatten_dict(flax_params)
    out = {}
    for key, shape in torch_shapes.items():
        norm = _normalise_key(key)
        if norm in _IGNORED_KEYS:
            continue
        path = flax_path(norm)
        module, leaf = path[:-1], path[-1]
        if leaf == "weight":
            leaf = next(n for n in ("kernel", "scale", "embedding") if module + (n,) in flat)
        array = np.asarray(flat[module + (leaf,)], np.float32)
        if leaf == "kernel":
            array = array.transpose(3, 2, 0, 1) if array.ndim == 4 else array.T
        assert tuple(array.shape) == tuple(shape), (key, array.shape, shape)
        out[key] = np.ascontiguousarray(array)
    return out


def export(folder: Path, tokenizer_dir: Path, unet_params, vae_params, text_params, *, scaling: float,
           unet: dict = UNET, vae: dict = VAE, text: dict = TEXT, dtype: str = "float32") -> None:
    """Writes the diffusers folder with diffusers/transformers' own save_pretrained (configs are
    the diffusers/transformers dicts; `scaling` becomes the VAE's scaling_factor); weights
    stored as `dtype` (float16 halves the folder; loaders compute in float32 either way)."""
    import shutil

    import torch
    from diffusers import AutoencoderKL as TorchVAE
    from diffusers import UNet2DConditionModel
    from transformers import CLIPTextConfig as TorchTextConfig
    from transformers import CLIPTextModel

    from jaxdistill.models.convert import _IGNORED_KEYS, MODEL_INDEX, _normalise_key

    folder.mkdir(parents=True, exist_ok=True)
    tok = load_tokenizer(tokenizer_dir)
    text_config = TorchTextConfig(**text, vocab_size=len(tok.backend.get_vocab()), bos_token_id=tok.bos_id,
                                  eos_token_id=tok.eos_id, pad_token_id=tok.pad_id)
    for name, model, params in (("unet", UNet2DConditionModel(**unet), unet_params),
                                ("vae", TorchVAE(**dict(vae, scaling_factor=scaling)), vae_params),
                                ("text_encoder", CLIPTextModel(text_config), text_params)):
        shapes = {k: tuple(v.shape) for k, v in model.state_dict().items()}
        state = {k: torch.tensor(v) for k, v in torch_state(params["params"], shapes).items()}
        missing, unexpected = model.load_state_dict(state, strict=False)
        missing = [k for k in missing if _normalise_key(k) not in _IGNORED_KEYS]
        if missing or unexpected:
            raise RuntimeError(f"{name}: missing {missing[:5]}, unexpected {unexpected[:5]}")
        model = model.eval().to(getattr(torch, dtype))
        model.save_pretrained(folder / name, safe_serialization=True)
    shutil.copytree(tokenizer_dir, folder / "tokenizer", dirs_exist_ok=True)
    (folder / "scheduler").mkdir(exist_ok=True)
    (folder / "scheduler" / "scheduler_config.json").write_text(json.dumps(SCHEDULER, indent=2))
    (folder / "model_index.json").write_text(json.dumps(MODEL_INDEX, indent=2))


def check_export(folder: Path, unet_params, vae_params, text_params, dtype: str = "float32") -> None:
    """Our loader reads the exported folder back to exactly the trained parameters (rounded to
    the export dtype)."""
    from jaxdistill.models.convert import load_rgbx

    loaded = load_rgbx(folder)
    for part, params in (("unet", unet_params), ("vae", vae_params), ("text_encoder", text_params)):
        a, b = jax.tree.leaves(loaded.params[part]), jax.tree.leaves(params)
        assert len(a) == len(b) and all(np.array_equal(np.asarray(x), np.asarray(y).astype(dtype).astype(np.float32))
                                        for x, y in zip(a, b)), part


# ----------------------------------------------------------------------------- main


def model_record(args, images: int, scaling: float) -> dict:
    """jaxdistill_model.json: what `models/shipped.py` reports as the model (name, version) and
    how it was made (data, recipe, final losses), for the model card and metrics.json."""
    def last_loss(stage):
        path = args.work / f"{stage}_loss.jsonl"
        return json.loads(path.read_text().splitlines()[-1])["loss"] if path.is_file() else None

    return {"name": args.name, "version": args.version, "images": images, "data": str(args.data),
            "init": str(args.init) if args.init else None,
            "seed": args.seed, "latent_scaling_factor": scaling, "export_dtype": args.export_dtype,
            "vae": ({"from": str(args.init)} if args.init else
                    {"steps": args.vae_steps, "batch": args.vae_batch, "lr": args.vae_lr, "final_loss": last_loss("vae")}),
            "unet": {"steps": args.unet_steps, "batch": args.unet_batch, "lr": args.unet_lr, "ema": args.ema,
                     "p_drop": args.p_drop, "t_high_fraction": args.t_high_fraction, "t_high_from": args.t_high_from,
                     "final_loss": last_loss("unet")},
            "command": "python scripts/train_rgbx.py " + " ".join(sys.argv[1:])}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--data", type=Path, required=True, help="folder of make_rgbx_data.py shards")
    parser.add_argument("--work", type=Path, required=True, help="checkpoints, latents, logs")
    parser.add_argument("--out", type=Path, default=None, help="diffusers folder to export (default WORK/model)")
    parser.add_argument("--stage", choices=("all", "vae", "latents", "unet", "export"), default="all")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--vae_steps", type=int, default=3000)
    parser.add_argument("--vae_batch", type=int, default=16)
    parser.add_argument("--vae_lr", type=float, default=1e-3)
    parser.add_argument("--kl_weight", type=float, default=1e-6)
    parser.add_argument("--unet_steps", type=int, default=6000)
    parser.add_argument("--unet_batch", type=int, default=64)
    parser.add_argument("--unet_lr", type=float, default=1e-3)
    parser.add_argument("--ema", type=float, default=0.999)
    parser.add_argument("--t_high_fraction", type=float, default=0.0,
                        help="fraction in [0, 1] of each UNet batch whose t is drawn from U{t_high_from..T-1} instead "
                        "of U{0..T-1} (T = 1000 training timesteps)")
    parser.add_argument("--t_high_from", type=int, default=900,
                        help="first timestep of the high draw (--t_high_fraction), in [0, T-1]")
    parser.add_argument("--p_drop", type=float, default=0.1, help="photo and prompt dropout, each")
    parser.add_argument("--name", default="jaxdistill-rgbx-rooms", help="model name in jaxdistill_model.json")
    parser.add_argument("--version", default="1")
    parser.add_argument("--export_dtype", choices=("float32", "float16"), default="float16",
                        help="weights dtype of the exported folder (float16: half the size)")
    parser.add_argument("--init", type=Path, default=None,
                        help="continue from this diffusers folder (e.g. the shipped model): its VAE, latent scaling, "
                             "text encoder and tokenizer are kept, the VAE stage is skipped, and the UNet starts "
                             "from its weights (fine-tuning on --data)")
    parser.add_argument("--ckpt_every", type=int, default=250)
    parser.add_argument("--stop_after_steps", type=int, default=0, help="train at most this many steps in this run")
    parser.add_argument("--time_limit", type=float, default=0.0, help="minutes; then checkpoint and exit 75")
    args = parser.parse_args(argv)
    if not 0.0 <= args.t_high_fraction <= 1.0:
        parser.error(f"--t_high_fraction: must be in [0, 1], got {args.t_high_fraction}")
    if not 0 <= args.t_high_from < SCHEDULER["num_train_timesteps"]:
        parser.error(f"--t_high_from: must be in [0, {SCHEDULER['num_train_timesteps'] - 1}], got {args.t_high_from}")
    args.budget = Budget(args.stop_after_steps, args.time_limit)
    args.work.mkdir(parents=True, exist_ok=True)
    out = args.out or args.work / "model"
    sys.path.insert(0, str(REPO / "tests"))
    from tiny_clip_vocab import write_tiny_clip_tokenizer

    init = load_init(args.init) if args.init else None
    if init is not None:
        shutil.copytree(args.init / "tokenizer", args.work / "tokenizer", dirs_exist_ok=True)
    elif not (args.work / "tokenizer" / "vocab.json").exists():
        write_tiny_clip_tokenizer(args.work / "tokenizer", pad_token="!", style="modern")
    tokenizer = load_tokenizer(args.work / "tokenizer")
    start = time.perf_counter()
    photos, maps, _ = load_images(args.data)
    print(f"{len(photos)} images of {photos.shape[2]}x{photos.shape[1]} from {args.data} ({time.perf_counter() - start:.0f} s)")
    if init is None:
        vae, vae_params = train_vae(args, photos, maps)
    else:
        vae, vae_params = init.networks.vae, init.params["vae"]
        print(f"VAE, latent scaling and text encoder of {args.init}; the UNet starts from its weights")
    if args.stage == "vae":
        return 0
    latents = encode_all(args, vae, vae_params, photos, maps)
    if init is None:
        scaling = float(1.0 / np.std(np.concatenate([latents[m] for m in MAPS])))
    else:
        scaling = float(init.networks.vae.config.scaling_factor)
    print(f"latent scaling factor {scaling:.5f}")
    if args.stage == "latents":
        return 0
    if init is None:
        text_params, contexts = text_encoder_and_prompts(args.seed, tokenizer, TEXT)
    else:
        text_params, contexts = init_prompts(init, tokenizer)
    _, unet_params = train_unet(args, latents, contexts, scaling, init.params["unet"] if init else None)
    if args.stage == "unet":
        return 0
    export(out, args.work / "tokenizer", unet_params, vae_params, text_params, scaling=scaling, unet=UNET, vae=VAE, text=TEXT,
           dtype=args.export_dtype)
    check_export(out, unet_params, vae_params, text_params, args.export_dtype)
    (out / "jaxdistill_model.json").write_text(json.dumps(model_record(args, len(photos), scaling), indent=1))
    size = sum(p.stat().st_size for p in out.rglob("*") if p.is_file())
    print(f"exported {out} ({size / 2**20:.1f} MiB), read back identical; total {(time.perf_counter() - start) / 60:.1f} min")
    return 0


if __name__ == "__main__":
    sys.exit(main())
