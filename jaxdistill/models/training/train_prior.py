"""Trains our small RGB<->X-family prior on `make_rgbx_data.py` shards and exports it.

`main(argv)` is `scripts/train_rgbx.py`; the networks are `recipe`'s, all in JAX with the
project's own Flax modules (`jaxdistill.models`) and optax:

1. `vae`: the autoencoder on photos and all five maps ([-1, 1], grey maps as 3 channels):
   L1 + L2 reconstruction plus a small KL term; AdamW.
2. `latents`: every photo and map encoded once (the posterior mean); the latent scaling
   factor is 1 / std of the map latents (Stable Diffusion's rule), written to the VAE config.
3. `unet`: v-prediction MSE at t ~ U{0..999}; the photo latent is zeroed and the prompt
   emptied each with probability `--p_drop` (independently), so eq. 4.2's guidance means
   something; AdamW with warm-up and cosine decay; an EMA of the weights is what ships.
   The text encoder is a tiny CLIP transformer with seeded random weights, frozen (RGB<->X's
   CLIP is frozen too): it only has to give the five prompts and "" distinct embeddings; the
   tokenizer is `vocabulary.write_prior_tokenizer`'s.
4. `export`: a diffusers folder (`export_model`), read back by our loader and checked equal.
   The UNet stage leaves its EMA weights in WORK/unet_ema.npz (with `--ema_snapshots`, those of
   every checkpoint too, in WORK/unet_ema_<step>.npz: a training length can then be chosen on
   validation rooms), and `--stage=export` reads them
   from there when that file exists: a UNet trained on another machine (a GPU without torch,
   `scripts/train_rgbx_gpu.sh`) is exported where torch is.

v2's options: `--unet_blocks`/`--unet_layers_per_block` (a wider or deeper UNet; `--fresh_unet`
keeps an `--init` model's VAE, text encoder and tokenizer but trains the UNet from random weights),
`--latent_bits=8` (the latents stored as 8-bit codes per channel, a quarter of the file, so they
can be carried to a GPU machine; the UNet trains on what is stored) and `--unet_minutes` (steps
chosen from the measured speed, kept in WORK/unet_steps.json).

Every stage is deterministic from `--seed` and resumable (`stages.run_stage`); `--init`
continues a model this script exported (its VAE, latent scaling, text encoder and tokenizer kept).
"""

from __future__ import annotations

import argparse
import functools
import json
import shutil
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import optax
from tqdm import tqdm

from jaxdistill.models import scheduler as sched
from jaxdistill.models.clip import CLIPTextConfig, CLIPTextTransformer
from jaxdistill.models.prior import MAP_PROMPTS, encode_text
from jaxdistill.models.tokenizer import load_tokenizer
from jaxdistill.models.training import recipe
from jaxdistill.models.training.export_model import check_export, export
from jaxdistill.models.training.recipe import MAPS
from jaxdistill.io.checkpoint import is_committed
from jaxdistill.models.training.stages import Budget, adamw, run_stage
from jaxdistill.models.training.vocabulary import write_prior_tokenizer
from jaxdistill.models.unet import UNet2DCondition, UNetConfig
from jaxdistill.models.vae import AutoencoderKL, VAEConfig

DESCRIPTION = "Trains our small RGB<->X-family prior on `make_rgbx_data.py` shards and exports it."


# ----------------------------------------------------------------------------- stage 1: VAE


@functools.lru_cache(maxsize=4)
def vae_program(vae_json: str, lr: float, steps: int, kl_weight: float):
    """(vae, init_state(key, sample), step(state, batch)) of the VAE stage, jitted once per process
    for a configuration (`recipe.VAE` as JSON and the flags the step reads): a run that resumes
    in the same process (the training tests') traces and compiles nothing again."""
    vae = AutoencoderKL(VAEConfig.from_dict(json.loads(vae_json)))
    tx = adamw(lr, steps)

    @jax.jit      # one program, not one eager dispatch (and compile) per initialiser
    def init_state(key, sample):
        params = vae.init(key, sample)
        return {"params": params, "opt": tx.init(params)}

    def loss_fn(params, images, key):
        mean, logvar = vae.apply(params, images, method="encode")
        z = mean + jnp.exp(0.5 * logvar) * jax.random.normal(key, mean.shape)
        recon = vae.apply(params, z, method="decode")
        kl = 0.5 * jnp.mean(jnp.sum(mean ** 2 + jnp.exp(logvar) - 1.0 - logvar, axis=-1))
        err = recon - images
        return jnp.mean(jnp.abs(err)) + jnp.mean(err ** 2) + kl_weight * kl

    @jax.jit
    def step(state, batch):
        images, key = batch
        loss, grads = jax.value_and_grad(loss_fn)(state["params"], images, key)
        updates, opt = tx.update(grads, state["opt"], state["params"])
        return {"params": optax.apply_updates(state["params"], updates), "opt": opt}, loss

    return vae, init_state, step


def train_vae(args, photos, maps):
    vae, init_state, step = vae_program(json.dumps(recipe.VAE, sort_keys=True), args.vae_lr, args.vae_steps,
                                        args.kl_weight)
    pool = np.concatenate([photos] + [maps[m] for m in MAPS])        # (6N, H, W, 3)

    def batch(step):
        rng = np.random.default_rng([args.seed, 1, step])
        return jnp.asarray(pool[rng.integers(len(pool), size=args.vae_batch)]), jax.random.fold_in(jax.random.key(args.seed), step)

    init = functools.partial(init_state, jax.random.key(args.seed), jnp.zeros((1,) + pool.shape[1:]))
    state = run_stage("vae", args.work, init, step, batch, args.vae_steps, args.ckpt_every, {"stage": "vae", **recipe.VAE},
                      args.budget)
    return vae, state["params"]


# ----------------------------------------------------------------------------- stage 2: latents


LATENTS = "latents.npz"


def quantize(x: np.ndarray, bits: int) -> dict:
    """{"q": uint8 codes, "lo": (C,), "step": (C,)} of `x` (..., C): per channel, `2**bits` levels
    from its minimum to its maximum (bits = 8: the error is at most half a level, 1/510 of the range)."""
    axes = tuple(range(x.ndim - 1))
    lo, hi = x.min(axes), x.max(axes)
    step = np.maximum(hi - lo, 1e-12) / (2 ** bits - 1)
    return {"q": np.round((x - lo) / step).astype(np.uint8), "lo": lo.astype(np.float32), "step": step.astype(np.float32)}


def dequantize(q: np.ndarray, lo: np.ndarray, step: np.ndarray) -> np.ndarray:
    return (lo + q.astype(np.float32) * step).astype(np.float32)


def load_latents(path: Path, bits: int):
    """{photo, <map>: (N, h, w, 4) unscaled latents} of a latents file `encode_all` wrote, as float32
    (dequantized where it holds codes); None when there is none. SystemExit when it was written with
    another --latent_bits."""
    if not path.is_file():
        return None
    with np.load(path) as z:
        stored = 8 if z["photo"].dtype == np.uint8 else 32
        if stored != bits:
            raise SystemExit(f"{path}: its latents are stored in {stored} bits, but --latent_bits={bits}; pass "
                             f"--latent_bits={stored}, or another --work to encode them again")
        if bits == 32:
            return {k: z[k] for k in z.files}
        return {k: dequantize(z[k], z[k + "_lo"], z[k + "_step"]) for k in ("photo",) + MAPS}


def encode_all(args, vae, vae_params, photos, maps):
    """{photo, <map>: (N, h, w, 4) unscaled posterior means}, cached in work/latents.npz. With
    `--latent_bits=8` they are stored (and used) as 8-bit codes per channel, a quarter of the file:
    small enough to carry to another machine to train the UNet there."""
    cache = load_latents(args.work / LATENTS, args.latent_bits)
    if cache is not None:
        return cache
    encode = jax.jit(lambda x: vae.apply(vae_params, x, method="encode")[0])
    out = {}
    for name, images in tqdm([("photo", photos)] + [(m, maps[m]) for m in MAPS], desc="latents", unit="kind"):
        out[name] = np.concatenate([np.asarray(encode(jnp.asarray(images[i:i + 64]))) for i in range(0, len(images), 64)])
    if args.latent_bits == 8:
        stored = {}
        for name, x in out.items():
            q = quantize(x, 8)
            stored.update({name: q["q"], name + "_lo": q["lo"], name + "_step": q["step"]})
        np.savez(args.work / LATENTS, **stored)
        return load_latents(args.work / LATENTS, 8)
    np.savez(args.work / LATENTS, **out)
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
    return params, np.asarray(encode_text(init.networks.text_encoder, params, ids))


def text_encoder_and_prompts(seed: int, tokenizer, text: dict = recipe.TEXT):
    """(frozen CLIP params, (6, 77, D) last hidden states of the five prompts then "")."""
    encoder = CLIPTextTransformer(CLIPTextConfig.from_dict(dict(text, vocab_size=len(tokenizer.backend.get_vocab()))))
    ids = prompt_ids(tokenizer)
    params = jax.jit(encoder.init)(jax.random.key(seed + 7), ids)       # jitted: one program, not op by op
    return params, np.asarray(encode_text(encoder, params, ids))


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


@functools.lru_cache(maxsize=4)
def unet_program(unet_json: str, scheduler_json: str, lr: float, steps: int, ema: float, p_drop: float,
                 t_high_fraction: float, t_high_from: int):
    """(unet, init_params(key, sample, t, context), init_opt(params), step(state, batch, contexts))
    of the UNet stage, jitted once per process for a configuration (`recipe.UNET` and
    `recipe.SCHEDULER` as JSON and the flags the step reads), as `vae_program`."""
    unet = UNet2DCondition(UNetConfig.from_dict(json.loads(unet_json)))
    scheduler = json.loads(scheduler_json)
    config = sched.SchedulerConfig(**{k: scheduler[k] for k in ("beta_start", "beta_end", "beta_schedule",
                                                                "num_train_timesteps", "prediction_type",
                                                                "rescale_betas_zero_snr")})
    alpha_bar = sched.alphas_cumprod(config)
    tx = adamw(lr, steps)

    def loss_fn(params, x0, cond, which, key, ctx):
        k_t, k_eps, k_img, k_txt = jax.random.split(key, 4)
        b = x0.shape[0]
        t = timesteps(k_t, b, config.num_train_timesteps, t_high_fraction, t_high_from)
        eps = jax.random.normal(k_eps, x0.shape)
        ab = alpha_bar[t]
        z_t = sched.add_noise(x0, eps, ab)
        v = sched.v_from_x0_eps(x0, eps, ab)
        cond = jnp.where((jax.random.uniform(k_img, (b,)) < p_drop)[:, None, None, None], 0.0, cond)
        which = jnp.where(jax.random.uniform(k_txt, (b,)) < p_drop, len(MAPS), which)
        pred = unet.apply(params, jnp.concatenate([z_t, cond], -1), t, ctx[which])
        return jnp.mean((pred - v) ** 2)

    @jax.jit
    def step(state, batch, ctx):
        x0, cond, which, key = batch
        loss, grads = jax.value_and_grad(loss_fn)(state["params"], x0, cond, which, key, ctx)
        updates, opt = tx.update(grads, state["opt"], state["params"])
        params = optax.apply_updates(state["params"], updates)
        ema_params = jax.tree.map(lambda e, p: ema * e + (1 - ema) * p, state["ema"], params)
        return {"params": params, "ema": ema_params, "opt": opt}, loss

    # jitted: one program, not one eager dispatch (and compile) per initialiser
    return unet, jax.jit(unet.init), jax.jit(tx.init), step


def unet_recipe(args) -> dict:
    """The diffusers config of the UNet the flags ask for (`recipe.unet_config`)."""
    return recipe.unet_config(args.unet_blocks, args.unet_layers_per_block)


def fit_steps(work: Path, minutes: float, step_fn, init_state, batch_fn, probe: int = 100) -> int:
    """--unet_steps for a UNet stage of about `minutes` on this machine, all of it counted: two
    steps compile the program (and settle its first arguments), `probe` more are timed (their
    batches included), and what is left after these and one more compilation (the real schedule's
    program) goes to steps at that rate, rounded down to thousands. The choice is kept in
    work/unet_steps.json, so a resumed run keeps its schedule."""
    record = work / "unet_steps.json"
    if record.is_file():
        kept = read_steps(record)
        if kept["minutes"] != minutes:
            raise SystemExit(f"{record}: this stage's steps were fitted to --unet_minutes={kept['minutes']}, not "
                             f"{minutes}; resume with that flag (its learning-rate schedule is that of "
                             f"{kept['steps']} steps), or use another --work")
        return int(kept["steps"])
    if newest_checkpoint(work / "ckpt_unet") is not None:
        raise SystemExit(f"{work / 'ckpt_unet'}: this stage was started with --unet_steps, not --unet_minutes; "
                         f"resume with the same --unet_steps, or use another --work")
    start = time.perf_counter()
    state = init_state()
    for i in range(2):
        state, loss = step_fn(state, batch_fn(i))
    jax.block_until_ready(loss)
    compile_s = time.perf_counter() - start
    start = time.perf_counter()
    for i in range(2, probe + 2):
        state, loss = step_fn(state, batch_fn(i))
    jax.block_until_ready(loss)
    probe_s = time.perf_counter() - start
    per_step = probe_s / probe
    steps = int((60 * minutes - 2 * compile_s - probe_s) / per_step) // 1000 * 1000
    if steps < 1000:
        raise SystemExit(f"--unet_minutes={minutes}: at {per_step * 1e3:.1f} ms a step after {compile_s:.0f} s of "
                         f"compilation, fewer than 1000 steps fit; give more minutes or --unet_steps")
    record.write_text(json.dumps({"minutes": minutes, "steps": steps, "ms_per_step": round(per_step * 1e3, 3),
                                  "compile_s": round(compile_s, 1), "device": str(jax.devices()[0])}))
    print(f"--unet_minutes={minutes}: {per_step * 1e3:.2f} ms a step after {compile_s:.0f} s of compilation on "
          f"{jax.devices()[0]}: {steps} steps")
    return steps


def read_steps(record: Path) -> dict:
    """{"minutes", "steps", ...} of a work folder's unet_steps.json (`fit_steps`); SystemExit naming
    the file when it is not such a record."""
    try:
        kept = json.loads(record.read_text())
        int(kept["steps"]), float(kept["minutes"])
    except (ValueError, TypeError, KeyError) as e:
        raise SystemExit(f"{record}: not a record of --unet_minutes' choice ({e!r}); it holds "
                         f"{{\"minutes\": M, \"steps\": N, ...}}: delete it, or pass --unet_steps") from None
    return kept


def train_unet(args, latents, contexts, scaling, init_params=None):
    config = unet_recipe(args)

    def program(steps):
        return unet_program(json.dumps(config, sort_keys=True), json.dumps(recipe.SCHEDULER, sort_keys=True),
                            args.unet_lr, steps, args.ema, args.p_drop, args.t_high_fraction, args.t_high_from)
    unet, init_unet, init_opt, unet_step = program(args.unet_steps)
    photo = latents["photo"] * scaling
    targets = np.stack([latents[m] * scaling for m in MAPS], 1)   # (N, 5, h, w, 4)
    n, h, w = photo.shape[:3]
    init_args = (jax.random.key(args.seed + 1), jnp.zeros((1, h, w, 8)), jnp.zeros((1,)), jnp.asarray(contexts[:1]))
    if init_params is not None:
        shapes = jax.eval_shape(unet.init, *init_args)
        if jax.tree.structure(init_params) != jax.tree.structure(shapes) or any(
                a.shape != b.shape for a, b in zip(jax.tree.leaves(init_params), jax.tree.leaves(shapes))):
            raise SystemExit(f"--init: its UNet is not the one asked for ({config['block_out_channels']} blocks, "
                             f"{config['layers_per_block']} layers each, {h}x{w} latents); give a folder this script "
                             f"exported with the same --unet_blocks/--unet_layers_per_block, or --fresh_unet")

    def init_state():
        params = init_unet(*init_args) if init_params is None else jax.tree.map(jnp.asarray, init_params)
        return {"params": params, "ema": params, "opt": init_opt(params)}
    ctx = jnp.asarray(contexts)

    def batch(step):
        rng = np.random.default_rng([args.seed, 3, step])
        i, m = rng.integers(n, size=args.unet_batch), rng.integers(len(MAPS), size=args.unet_batch)
        return (jnp.asarray(targets[i, m]), jnp.asarray(photo[i]), jnp.asarray(m),
                jax.random.fold_in(jax.random.key(args.seed + 3), step))

    steps = args.unet_steps
    if args.unet_minutes:
        steps = fit_steps(args.work, args.unet_minutes, lambda state, b: unet_step(state, b, ctx), init_state, batch)
        args.unet_steps = steps                      # what the model record reports
        unet_step = program(steps)[3]

    def step(state, batch):
        return unet_step(state, batch, ctx)

    def snapshot(at, state):          # the EMA weights at every checkpoint: the training length can be chosen later
        save_unet(args.work / f"unet_ema_{at}.npz", state["ema"])

    state = run_stage("unet", args.work, init_state, step, batch, steps, args.ckpt_every, {"stage": "unet", **config},
                      args.budget, on_save=snapshot if args.ema_snapshots else None)
    return unet, state["ema"]


UNET_EMA = "unet_ema.npz"


def save_unet(path: Path, params) -> None:
    """The UNet's weights as one float32 .npz of '/'-joined parameter paths (what the export reads,
    so a UNet trained on another machine exports where torch is)."""
    from flax import traverse_util

    flat = traverse_util.flatten_dict(jax.device_get(params), sep="/")
    tmp = path.with_suffix(".tmp.npz")
    np.savez(tmp, **{k: np.asarray(v, np.float32) for k, v in flat.items()})
    tmp.replace(path)


def newest_checkpoint(folder: Path) -> Path | None:
    """The newest complete step folder of a stage's checkpoints (orbax's partial writes are not), or None."""
    steps = [p for p in folder.iterdir() if p.name.isdigit() and is_committed(p)] if folder.is_dir() else []
    return max(steps, key=lambda p: int(p.name)) if steps else None


def load_unet(path: Path, args, latents, contexts):
    """`save_unet`'s weights, checked against the UNet the flags ask for (SystemExit naming the file)."""
    from flax import traverse_util

    config = unet_recipe(args)
    unet = UNet2DCondition(UNetConfig.from_dict(config))
    h, w = latents["photo"].shape[1:3]
    like = traverse_util.flatten_dict(jax.eval_shape(unet.init, jax.random.key(0), jnp.zeros((1, h, w, 8)),
                                                     jnp.zeros((1,)), jnp.asarray(contexts[:1])), sep="/")
    with np.load(path) as z:
        got = {k: z[k].astype(np.float32) for k in z.files}
    if set(got) != set(like) or any(got[k].shape != like[k].shape for k in like):
        raise SystemExit(f"{path}: its UNet is not the one asked for ({config['block_out_channels']} blocks, "
                         f"{config['layers_per_block']} layers each); pass the --unet_blocks/--unet_layers_per_block "
                         f"it was trained with")
    return traverse_util.unflatten_dict(got, sep="/")


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
            "latent_bits": args.latent_bits,
            "unet": {"blocks": list(args.unet_blocks), "layers_per_block": args.unet_layers_per_block,
                     "fresh": bool(args.fresh_unet or not args.init), "minutes": args.unet_minutes or None,
                     "steps": args.unet_steps, "batch": args.unet_batch, "lr": args.unet_lr, "ema": args.ema,
                     "p_drop": args.p_drop, "t_high_fraction": args.t_high_fraction, "t_high_from": args.t_high_from,
                     "final_loss": last_loss("unet")},
            "command": "python scripts/train_rgbx.py " + " ".join(sys.argv[1:])}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=DESCRIPTION)
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
    parser.add_argument("--unet_blocks", default=None,
                        help="the UNet's four block widths, comma-separated multiples of 16 (default: the "
                             "recipe's, 32,64,64,64)")
    parser.add_argument("--unet_layers_per_block", type=int, default=None, help="default: the recipe's, 1")
    parser.add_argument("--fresh_unet", action="store_true",
                        help="with --init: keep its VAE, latent scaling, text encoder and tokenizer, but train the "
                             "UNet from random weights (needed when --unet_blocks or --unet_layers_per_block differ)")
    parser.add_argument("--unet_minutes", type=float, default=0.0,
                        help="choose --unet_steps to train about this long on this machine (timed after compiling; "
                             "kept in WORK/unet_steps.json and the model record)")
    parser.add_argument("--ema_snapshots", action="store_true",
                        help="also write the UNet's EMA weights at every checkpoint (WORK/unet_ema_<step>.npz)")
    parser.add_argument("--latent_bits", type=int, choices=(32, 8), default=32,
                        help="store the encoded latents as float32, or as 8-bit codes per channel (a quarter of the "
                             "file, to carry to another machine); the UNet trains on what is stored")
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
    if not 0 <= args.t_high_from < recipe.SCHEDULER["num_train_timesteps"]:
        parser.error(f"--t_high_from: must be in [0, {recipe.SCHEDULER['num_train_timesteps'] - 1}], got {args.t_high_from}")
    try:
        if args.unet_blocks is not None:
            args.unet_blocks = tuple(int(b) for b in str(args.unet_blocks).split(","))
        config = recipe.unet_config(args.unet_blocks, args.unet_layers_per_block)
        args.unet_blocks, args.unet_layers_per_block = config["block_out_channels"], config["layers_per_block"]
    except ValueError as e:
        parser.error(f"--unet_blocks/--unet_layers_per_block: {e}")
    if args.fresh_unet and not args.init:
        parser.error("--fresh_unet: only with --init (without it the UNet always starts from random weights)")
    if args.unet_minutes < 0:
        parser.error(f"--unet_minutes: must be >= 0, got {args.unet_minutes}")
    args.budget = Budget(args.stop_after_steps, args.time_limit)
    args.work.mkdir(parents=True, exist_ok=True)
    out = args.out or args.work / "model"
    init = load_init(args.init) if args.init else None
    if init is not None:
        shutil.copytree(args.init / "tokenizer", args.work / "tokenizer", dirs_exist_ok=True)
    elif not (args.work / "tokenizer" / "vocab.json").exists():
        write_prior_tokenizer(args.work / "tokenizer")
    tokenizer = load_tokenizer(args.work / "tokenizer")
    start = time.perf_counter()
    # with --init the VAE is the init's, so latents already encoded are all the UNet needs: the
    # shards are not read (a machine that trains only the UNet gets WORK/latents.npz alone)
    latents = load_latents(args.work / LATENTS, args.latent_bits) if init is not None else None
    if latents is None:
        # imported here: the shards' reader needs the image library, a UNet trained from latents does not
        from jaxdistill.models.training.shards import load_images

        photos, maps, _ = load_images(args.data)
        print(f"{len(photos)} images of {photos.shape[2]}x{photos.shape[1]} from {args.data} "
              f"({time.perf_counter() - start:.0f} s)")
    else:
        print(f"{len(latents['photo'])} images' latents from {args.work / LATENTS}; the shards are not read")
    if init is None:
        vae, vae_params = train_vae(args, photos, maps)
    else:
        vae, vae_params = init.networks.vae, init.params["vae"]
        print(f"VAE, latent scaling and text encoder of {args.init}; the UNet starts from "
              + ("random weights (--fresh_unet)" if args.fresh_unet else "its weights"))
    if args.stage == "vae":
        return 0
    if latents is None:
        latents = encode_all(args, vae, vae_params, photos, maps)
    if init is None:
        scaling = float(1.0 / np.std(np.concatenate([latents[m] for m in MAPS])))
    else:
        scaling = float(init.networks.vae.config.scaling_factor)
    print(f"latent scaling factor {scaling:.5f}")
    if args.stage == "latents":
        return 0
    if init is None:
        text_params, contexts = text_encoder_and_prompts(args.seed, tokenizer, recipe.TEXT)
    else:
        text_params, contexts = init_prompts(init, tokenizer)
    if args.stage == "export" and (args.work / UNET_EMA).is_file():
        newest = newest_checkpoint(args.work / "ckpt_unet")
        if newest is not None and newest.stat().st_mtime > (args.work / UNET_EMA).stat().st_mtime:
            raise SystemExit(f"{args.work / UNET_EMA}: older than the UNet stage's checkpoint {newest}; finish or "
                             f"rerun the stage (--stage=unet), which writes the weights again, then export")
        unet_params = load_unet(args.work / UNET_EMA, args, latents, contexts)
        if (args.work / "unet_steps.json").is_file():             # the steps --unet_minutes chose there
            kept = read_steps(args.work / "unet_steps.json")
            args.unet_steps, args.unet_minutes = int(kept["steps"]), float(kept["minutes"])
    else:
        _, unet_params = train_unet(args, latents, contexts, scaling,
                                    init.params["unet"] if init and not args.fresh_unet else None)
        save_unet(args.work / UNET_EMA, unet_params)
    if args.stage == "unet":
        return 0
    export(out, args.work / "tokenizer", unet_params, vae_params, text_params, scaling=scaling, unet=unet_recipe(args),
           vae=recipe.VAE,
           text=recipe.TEXT,
           dtype=args.export_dtype)
    check_export(out, unet_params, vae_params, text_params, args.export_dtype)
    (out / "jaxdistill_model.json").write_text(json.dumps(model_record(args, len(latents["photo"]), scaling), indent=1))
    size = sum(p.stat().st_size for p in out.rglob("*") if p.is_file())
    print(f"exported {out} ({size / 2**20:.1f} MiB), read back identical; total {(time.perf_counter() - start) / 60:.1f} min")
    return 0
