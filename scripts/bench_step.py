"""Where the time of a distillation step goes, against the thesis's PyTorch recipe, at real size.

    python scripts/make_random_rgbx.py --size=full --out=data/random-rgbx/rgb-to-x    # once, ~1 min, 4.8 GB
    python scripts/bench_step.py --rgbx_dir=data/random-rgbx/rgb-to-x \\
        [--render_sizes=256,512] [--map_counts=1,5] [--dtypes=float32,bfloat16] [--frameworks=jax,torch]
        [--views_per_step=1] [--reuse_steps=1,2] [--repeats=3] [--threads=N] [--json]
        [--torch_device=cuda] [--last_stage=unet] [--stage_cases=last] [--peak_tflops=989.4]
    python scripts/bench_step.py --size=tiny          # a tiny random folder: a quick check of this script

One run measures, side by side, for every render size (longer side; the bedroom is 4:3) and
number of maps per step:

- **jax** (ours, one child process per prior dtype): the real step (`engine.loop.setup_step`,
  what `python -m jaxdistill.main` runs; rgbx prior, w_t = w_i = 1 so one UNet branch,
  photo latents encoded once at setup, all maps of a view in one network call), and its stages
  jitted one by one on the same inputs: gather-render, VAE encode, UNet (noise + guided x̂0),
  VAE decode, loss + gradient (the transpose of the gather), AdamW. FLOPs per step from XLA's
  cost analysis and the achieved FLOP/s. With `--reuse_steps=1,2` the real step is also timed
  as the main job runs it with `--reuse_steps=2` (the default config's: the prior's x̂0 of one
  step reused by the next, Instruct-NeRF2NeRF's iterative dataset update): seconds per step
  averaged over whole cycles (one step with the prior pass, K - 1 without), a row of its own
  (`jax_float32_reuse2`) beside the every-step row.
- **torch** (the thesis's recipe on diffusers, one child process): fp32, the photo re-encoded
  every step, all three classifier-free-guidance branches every step (one UNet call of batch 3),
  one map per pass (the thesis distils each map in its own run, so M maps cost M passes), loss
  backward through the same gather-render (torch autograd), torch.optim.AdamW. Networks run
  under `torch.inference_mode()`. The thesis rasterised with nvdiffrast every step; here both
  sides use the precomputed gather plan, so the ratio measures the prior recipe and framework.

Fairness: both sides use the same weights (one diffusers folder), scene, views, plans and thread
count (`--threads`, default all cores: each child is pinned to that many cores, XLA sizes its
pool by them and torch.set_num_threads gets the count); each does a warm-up (compilation for JAX) before `--repeats` timed runs; figures
are medians. Each framework runs in a fresh child process so peak RSS is its own. Both children
start with glibc's huge-page tunable (`--huge_pages`, default true), as the package's commands
start themselves (jaxdistill/huge_pages.py): a user's run of ours has it, and the recipe gets it
too; each row records its worker's `huge_pages` status.
On a GPU (`scripts/bench_gpu.sh` runs the thesis's setting there): `--torch_device=cuda` puts the
recipe on the card (its clocks read after a synchronise), each row reports the device's peak
memory, and the UNet's FLOP/s is given as a share of the card's dense bf16 peak. FLOPs are XLA's
count of each program before optimisation: after it, a GPU program's convolutions and matrix
products are cuDNN/cuBLAS calls that the count leaves out (and a `bfloat16_cudnn` row's fused
attention is a custom call it never counts: take the UNet's FLOPs from the chunked row, or from
the program lowered for the CPU, as docs/benchmarks.md §9b does). A failed worker is reported and the
others still run; every row is also logged as it is measured (`ROW {...}` on stderr).
The weights are random: the figures are timings; the images are meaningless.
The last line with --json is a JSON object whose "headline" states the ratio.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import platform
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from jaxdistill import huge_pages

ALL_MAPS = ("albedo", "normal", "roughness", "metallic", "irradiance")
THESIS_STEPS = 17_000          # the thesis's steps per map (§5.2)
STAGES = ("render", "vae_encode", "unet", "vae_decode", "loss_grad", "optimizer")
TORCH_STAGES = ("render", "photo_encode", "vae_encode", "unet", "vae_decode", "loss_grad", "optimizer")


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--rgbx_dir", help="RGB<->X folder (diffusers format); required unless --size=tiny")
    p.add_argument("--size", choices=("given", "tiny"), default="given", help="tiny: make a tiny random folder")
    p.add_argument("--render_sizes", default="256,512", help="longer sides of the renders (multiples of 8)")
    p.add_argument("--map_counts", default="1,5", help="maps per step: 1 = albedo, 5 = all five")
    p.add_argument("--dtypes", default="float32,bfloat16",
                   help="activation dtypes of our prior; bfloat16_cudnn: bfloat16 with cuDNN's fused attention "
                        "(NVIDIA GPUs only) instead of the chunked XLA attention")
    p.add_argument("--frameworks", default="jax,torch")
    p.add_argument("--views_per_step", type=int, default=1, help="views per step (the thesis: 1)")
    p.add_argument("--reuse_steps", default="1",
                   help="comma-separated K: our step timed with the prior's x̂0 reused over K steps (1: a prior "
                        "pass every step, as the recipe; 2: the default config's), seconds per step over whole cycles")
    p.add_argument("--max_texture_size", type=int, default=1024)
    p.add_argument("--repeats", type=int, default=3, help="timed runs after the warm-up")
    p.add_argument("--threads", type=int, default=os.cpu_count(), help="CPU threads for both frameworks")
    p.add_argument("--convert_cache", default=None, help="cache of converted weights (faster JAX loading)")
    p.add_argument("--torch_device", default="cpu", choices=("cpu", "cuda"),
                   help="where the PyTorch recipe runs (JAX runs on its default backend)")
    p.add_argument("--last_stage", default=STAGES[-1], choices=STAGES,
                   help="time the stages alone up to this one (each is compiled on its own; on a GPU the "
                        "UNet's compile dominates, so `unet` saves the decode's and the optimizer's)")
    p.add_argument("--stage_cases", default="all", choices=("all", "last"),
                   help="time the stages alone in every case, or only in the last (largest) one")
    p.add_argument("--fragment_cache", default=None,
                   help="folder of the rasterised fragments' cache, shared by the workers (default: the "
                        "package's, $JAXDISTILL_CACHE or ~/.cache/jaxdistill)")
    p.add_argument("--peak_tflops", type=float, default=None,
                   help="the card's dense bf16 peak for the utilisation figure (default: from the device name)")
    p.add_argument("--huge_pages", default="true", choices=("true", "false"),
                   help="start both workers with glibc's huge-page tunable, as the package's commands run "
                        "(jaxdistill/huge_pages.py; nothing where the system cannot use it); false: as started")
    p.add_argument("--json", action="store_true")
    p.add_argument("--worker", help=argparse.SUPPRESS)     # jax:<dtype> or torch: a child process
    args = p.parse_args(argv)
    if args.size == "given" and not args.rgbx_dir:
        p.error("--rgbx_dir is required (or --size=tiny)")
    args.render_sizes = [int(s) for s in args.render_sizes.split(",")]
    args.map_counts = [int(s) for s in args.map_counts.split(",")]
    args.dtypes = args.dtypes.split(",")
    args.frameworks = args.frameworks.split(",")
    args.reuse_steps = [int(k) for k in args.reuse_steps.split(",")]
    if any(k < 1 for k in args.reuse_steps):
        p.error(f"--reuse_steps: every K must be >= 1, got {args.reuse_steps}")
    for s in args.render_sizes:
        if s % 8:
            p.error(f"--render_sizes: {s} is not a multiple of 8")
    for m in args.map_counts:
        if not 1 <= m <= len(ALL_MAPS):
            p.error(f"--map_counts: {m} is not in 1..{len(ALL_MAPS)}")
    return args


def median_of(fn, repeats: int) -> float:
    """Median wall seconds of fn() (which must block until its work is done)."""
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return float(np.median(times))


def peak_rss_gb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2 ** 20


# dense bf16 tensor-core peaks from the vendors' datasheets (TFLOP/s, no sparsity), by device name
BF16_PEAK_TFLOPS = {"H100": 989.4, "H200": 989.4, "A100": 312.0, "L40S": 362.1, "RTX 3090": 71.0, "RTX 4090": 165.2}


def bf16_peak_tflops(device_name: str, given: float | None) -> float | None:
    if given:
        return given
    for key, value in BF16_PEAK_TFLOPS.items():
        if key.lower() in device_name.lower():
            return value
    return None


def jax_device_peak_gb() -> float | None:
    """Peak bytes the first device's allocator held so far (GPU/TPU); None on the CPU backend."""
    import jax

    stats = jax.local_devices()[0].memory_stats() or {}
    peak = stats.get("peak_bytes_in_use")
    return peak / 2 ** 30 if peak else None


def views_problem(args, size: int, maps):
    """The bedroom at `size` with the views prior: scene, plans, weights (no networks)."""
    from jaxdistill.engine import config as config_lib
    from jaxdistill.engine.problem import build_problem

    config = config_lib.validate(config_lib.DistillConfig(
        scene="bedroom", out_dir="unused", maps=tuple(maps), prior="views", render_size=size,
        views_per_step=args.views_per_step, max_texture_size=args.max_texture_size, sampler="bilinear", steps=1000))
    problem = build_problem(config, cache_dir=args.fragment_cache)
    if problem.height % 8 or problem.width % 8:
        raise SystemExit(f"render size {problem.width}x{problem.height}: sides must be multiples of 8")
    return config, problem


def cases(args):
    """(maps, config, problem, view ids) of every render size x map count, in order."""
    for size in args.render_sizes:
        for count in args.map_counts:
            maps = ALL_MAPS[:count]
            config, problem = views_problem(args, size, maps)
            yield maps, config, problem, np.arange(args.views_per_step) % problem.num_views


def batch_photos(problem, view_ids):
    """(B, H, W, 3) sRGB [0, 1] photos of the batch views at the render size."""
    from jaxdistill.io import images as imageio
    from jaxdistill.engine.problem import resize

    return [resize(imageio.read_photo_srgb(problem.scene.views[i].photo, problem.scene.views[i].exposure), problem.height, problem.width)
            for i in view_ids]


def cost_flops(lowered) -> float | None:
    """FLOPs of a program from XLA's cost analysis of its HLO before optimisation (None when the
    backend gives none). Not the compiled program's: on a GPU, convolutions and matrix products
    compile to cuDNN/cuBLAS custom calls, whose FLOPs the compiled analysis leaves out (measured on
    an H200: the same UNet counted 71 GFLOP in float32 and 172 in bfloat16)."""
    analysis = lowered.cost_analysis()
    if isinstance(analysis, (list, tuple)):
        analysis = analysis[0] if analysis else {}
    flops = (analysis or {}).get("flops")
    return float(flops) if flops is not None and flops > 0 else None


# ----------------------------------------------------------------------------- ours (JAX)

def jax_worker(args, folder: str, dtype_name: str) -> list[dict]:
    import jax
    import jax.numpy as jnp
    import optax

    from jaxdistill.engine import loop
    from jaxdistill.engine.step import render_maps, sample_timesteps, weighted_square_error
    from jaxdistill.models import convert, layers
    from jaxdistill.models import prior as rgbx
    from jaxdistill.engine.priors import make_rgbx_prior
    from jaxdistill.render.gather_plan import GatherPlan

    device_name = jax.devices()[0].device_kind
    peak_tflops = bf16_peak_tflops(device_name, args.peak_tflops) if jax.default_backend() == "gpu" else None
    t0 = time.perf_counter()
    base_dtype, _, attention = dtype_name.partition("_")
    dtype = {"float32": jnp.float32, "bfloat16": jnp.bfloat16}[base_dtype]
    chunk = {"": None, "cudnn": layers.FUSED_CUDNN}[attention]
    model = rgbx.load_prior(convert.load_rgbx(folder, dtype=dtype, cache_dir=args.convert_cache, chunk_size=chunk))
    load_s = time.perf_counter() - t0
    rows = []
    num_cases = len(args.render_sizes) * len(args.map_counts)
    for case, (maps, config, problem, ids) in enumerate(cases(args)):
        count = len(maps)
        t0 = time.perf_counter()
        prior, prior_frozen = make_rgbx_prior(model, problem.channels, batch_photos(problem, ids),
                                              guidance=rgbx.Guidance(1.0, 1.0), sample_latent=False,
                                              latent_space=False)
        photo_s = time.perf_counter() - t0
        frozen = {"chain": problem.frozen["chain"], "prior": prior_frozen,
                  "alphas_cumprod": np.asarray(rgbx.sched.alphas_cumprod(model.scheduler))}
        # the batch's photo latents are rows 0..B-1 of the prior; the plans are the views `ids`
        batch_host = problem.batch(ids)
        batch_host["prior"] = prior.view_data(np.arange(len(ids)))
        problem = dataclasses.replace(problem, prior=prior, frozen=frozen)

        # --- the whole step, set up by the main job's own `setup_step` and run as its loop runs it;
        # with x̂0 reuse (K > 1) timed over whole cycles of K steps, the first of each with the prior
        whole = {}
        for reuse in args.reuse_steps:
            stepper = loop.setup_step(dataclasses.replace(config, reuse_steps=reuse), problem, batch_host)
            settings, optimizer, step, traces = stepper.settings, stepper.optimizer, stepper.step_fn, stepper.traces
            placed_frozen = jax.device_put(frozen, stepper.replicated)
            batch = jax.device_put(batch_host, stepper.by_view)
            state = jax.device_put(stepper.state, stepper.replicated)
            t0 = time.perf_counter()
            lowered = step.lower(state, batch, placed_frozen)
            compiled = lowered.compile()
            compile_s = time.perf_counter() - t0
            for _ in range(reuse):                               # warm-up: one whole cycle
                state, metrics = compiled(state, batch, placed_frozen)
            jax.block_until_ready(metrics["loss"])
            step_times = []
            for _ in range(args.repeats):
                t0 = time.perf_counter()
                for _ in range(reuse):
                    state, metrics = compiled(state, batch, placed_frozen)
                jax.block_until_ready(metrics["loss"])
                step_times.append((time.perf_counter() - t0) / reuse)
            traces.check(1)
            if int(state.step) != reuse * (args.repeats + 1):
                # a non-finite loss halts the state (the step counter stays): the cycles would not
                # alternate prior and reused steps, so the figure would mean something else
                raise SystemExit(f"--reuse_steps={reuse}: the state stopped at step {int(state.step)} of "
                                 f"{reuse * (args.repeats + 1)} (a non-finite loss); no row")
            whole[reuse] = {"step_times": step_times, "compile_s": compile_s, "finite": int(metrics["finite"]),
                            "flops": cost_flops(lowered)}
            del state, compiled, lowered
        frozen = placed_frozen
        settings = loop.step_settings(config, problem)

        # --- the same work, stage by stage (each jitted alone, fed the previous stage's output)
        texels = jnp.asarray(problem.initial_texels())
        key = jax.random.PRNGKey(0)
        t = sample_timesteps(key, jnp.int32(0), (len(ids), count), settings)
        fp = frozen["prior"]

        def plan_of(b):
            return GatherPlan(index=b["index"], weight=b["weight"], hit=b["hit"], chain=frozen["chain"],
                              height=settings.height, width=settings.width)

        def render_stage(texels, b):
            return render_maps(texels, plan_of(b), b["normal_rotation"], settings.channels)

        def loss_grad_stage(texels, b, images, targets):
            (loss, _), g_images = jax.value_and_grad(weighted_square_error, has_aux=True)(
                images, targets, b["pixel_weight"], jnp.ones(t.shape, jnp.float32), settings.channels.maps)
            (grad,) = jax.linear_transpose(lambda x: render_stage(x, b), texels)(g_images)
            return loss, grad

        def optimizer_stage(grad, opt_state, texels):
            updates, opt_state = optimizer.update(grad, opt_state, texels)
            return optax.apply_updates(texels, updates), opt_state

        # each stage: (function, its inputs from the earlier stages' outputs `out`)
        stages = {
            "render": (render_stage, lambda out: (texels, batch)),
            "vae_encode": (lambda fp, images: prior.encode(fp, images, key), lambda out: (fp, out["render"])),
            "unet": (lambda fp, z0, d: prior.denoise(fp, z0, d, t, key),
                     lambda out: (fp, out["vae_encode"], batch["prior"])),
            "vae_decode": (prior.decode, lambda out: (fp, out["unet"])),
            "loss_grad": (loss_grad_stage, lambda out: (texels, batch, out["render"], out["vae_decode"])),
            "optimizer": (optimizer_stage, lambda out: (out["loss_grad"][1], optimizer.init(texels), texels)),
        }
        outputs, stage_s, stage_flops = {}, {}, {}
        for name, (fn, inputs_of) in stages.items():
            if args.stage_cases == "last" and case < num_cases - 1:
                break
            inputs = inputs_of(outputs)
            lowered_stage = jax.jit(fn).lower(*inputs)
            compiled_stage = lowered_stage.compile()
            stage_flops[name] = cost_flops(lowered_stage)
            outputs[name] = jax.block_until_ready(compiled_stage(*inputs))
            stage_s[name] = median_of(lambda: jax.block_until_ready(compiled_stage(*inputs)), args.repeats)
            if name == args.last_stage:
                break
        unet_tflops = (stage_flops["unet"] / stage_s["unet"] / 1e12
                       if stage_flops.get("unet") and stage_s.get("unet") else None)
        for reuse, timed in whole.items():
            first = reuse == min(whole)          # the stages (timed once a case) go with the first row
            median = float(np.median(timed["step_times"]))
            # XLA counts the program's prior branch, which the cond runs once a cycle: no per-step
            # FLOP figure for a row with reuse
            step_flops = timed["flops"] if reuse == 1 else None
            rows.append({
                "framework": "jax", "dtype": dtype_name, "reuse_steps": reuse, "render": [problem.height, problem.width],
                "maps": list(maps), "views_per_step": len(ids), "unet_batch_per_step": len(ids) * count,
                "step_s": median, "step_s_all": timed["step_times"], "stages_s": stage_s if first else {},
                "stages_sum_s": float(sum(stage_s.values())) if first else None, "compile_s": timed["compile_s"],
                "finite": timed["finite"], "flops_per_step": step_flops, "stage_flops": stage_flops,
                "achieved_gflops_per_s": step_flops / median / 1e9 if step_flops else None,
                "texels": problem.space.num_texels, "load_s": load_s, "photo_latents_s": photo_s,
                "device": device_name, "device_peak_gb": jax_device_peak_gb(),
                "unet_tflops_per_s": unet_tflops, "bf16_peak_tflops": peak_tflops,
                "unet_fraction_of_bf16_peak": unet_tflops / peak_tflops if unet_tflops and peak_tflops else None,
            })
            print("ROW " + json.dumps(rows[-1]), file=sys.stderr)          # survives a later case's failure
            print(f"[jax {dtype_name}, reuse {reuse}] {problem.width}x{problem.height} {count} map(s): {median:.2f} s/step "
                  f"(stages {', '.join(f'{k} {v:.2f}' for k, v in stage_s.items())})", file=sys.stderr)
        del step, outputs
    for row in rows:
        row["peak_rss_gb"] = peak_rss_gb()
        row["huge_pages"] = huge_pages.status()
    return rows


# ----------------------------------------------------------------------------- the thesis recipe (PyTorch)

def torch_worker(args, folder: str) -> list[dict]:
    # the scene and plans are built with JAX on the host: keep it off the GPU the recipe is timed on
    os.environ["JAX_PLATFORMS"] = "cpu"
    import torch
    from diffusers import AutoencoderKL, DDIMScheduler, UNet2DConditionModel
    from transformers import CLIPTextModel, CLIPTokenizer

    from jaxdistill.scene.maps import GREY_MAPS
    from jaxdistill.models.prior import DEMO_SCHEDULER_OVERRIDES, photo_to_model_space
    from jaxdistill.models.tokenizer import MAP_PROMPTS

    torch.set_num_threads(args.threads)
    dev = torch.device(args.torch_device)
    cuda = dev.type == "cuda"
    device_name = torch.cuda.get_device_name(dev) if cuda else platform.processor() or "cpu"

    def now():
        """A host clock read after the device's queued work is done (CUDA runs asynchronously)."""
        if cuda:
            torch.cuda.synchronize(dev)
        return time.perf_counter()

    folder = Path(folder)
    t0 = time.perf_counter()
    unet = UNet2DConditionModel.from_pretrained(folder / "unet").eval().to(dev)
    vae = AutoencoderKL.from_pretrained(folder / "vae").eval().to(dev)
    tokenizer = CLIPTokenizer.from_pretrained(folder / "tokenizer")
    text_encoder = CLIPTextModel.from_pretrained(folder / "text_encoder").eval()
    with torch.inference_mode():
        ids = tokenizer([MAP_PROMPTS[m] for m in ALL_MAPS] + [""], padding="max_length",
                        max_length=tokenizer.model_max_length, truncation=True, return_tensors="pt").input_ids
        hidden = text_encoder(ids)[0]
    hidden = hidden.to(dev)
    prompt_of = {m: hidden[i:i + 1] for i, m in enumerate(ALL_MAPS)}
    empty = hidden[-1:]
    del text_encoder
    scheduler = DDIMScheduler.from_pretrained(folder / "scheduler", **DEMO_SCHEDULER_OVERRIDES)
    alphas = scheduler.alphas_cumprod.float().to(dev)
    sf = vae.config.scaling_factor
    load_s = time.perf_counter() - t0
    gen = torch.Generator(device=dev).manual_seed(0)
    rows = []
    for maps, config, problem, view_ids in cases(args):
        count = len(maps)
        b = problem.batch(view_ids)
        if cuda:
            torch.cuda.reset_peak_memory_stats(dev)
        index = torch.from_numpy(b["index"]).long().to(dev)         # (B, P, T)
        weight = torch.from_numpy(b["weight"]).to(dev)              # (B, P, T)
        pixel_weight = torch.from_numpy(b["pixel_weight"]).to(dev)  # (B, H, W)
        rotation = torch.from_numpy(b["normal_rotation"]).to(dev)   # (B, 3, 3)
        photos = torch.from_numpy(np.asarray(photo_to_model_space(np.stack(batch_photos(problem, view_ids)))))
        photos = photos.permute(0, 3, 1, 2).contiguous().to(dev)    # (B, 3, H, W) in [-1, 1]
        texels = torch.tensor(problem.initial_texels(), requires_grad=True, device=dev)
        opt = torch.optim.AdamW([texels], lr=config.lr, weight_decay=config.weight_decay)
        h, w, nb = problem.height, problem.width, len(view_ids)
        lo, hi = config.t_min * 1000, config.t_max * 1000

        def step():
            times = {}
            t0 = now()
            image = (texels[index] * weight[..., None]).sum(-2).reshape(nb, h, w, -1)
            images = {m: image[..., problem.channels.slice(m)] for m in maps}
            if "normal" in images:
                images["normal"] = torch.einsum("bhwi,bij->bhwj", images["normal"], rotation)
            times["render"] = now() - t0
            targets = {}
            for k in ("photo_encode", "vae_encode", "unet", "vae_decode"):
                times[k] = 0.0
            for m in maps:                     # the thesis: one map per run, so one pass per map
                with torch.inference_mode():
                    t0 = now()
                    photo_latent = vae.encode(photos).latent_dist.mode() * sf        # re-encoded every step
                    times["photo_encode"] += now() - t0
                    t0 = now()
                    x = images[m].detach()
                    x = x.repeat(1, 1, 1, 3) if x.shape[-1] == 1 else x
                    z0 = vae.encode(x.permute(0, 3, 1, 2)).latent_dist.mode() * sf
                    times["vae_encode"] += now() - t0
                    t0 = now()
                    t = torch.randint(int(lo), int(hi) + 1, (nb,), generator=gen, device=dev)
                    a = alphas[t].view(-1, 1, 1, 1)
                    z_t = a.sqrt() * z0 + (1 - a).sqrt() * torch.randn(z0.shape, generator=gen, device=dev)
                    sample = torch.cat([torch.cat([z_t, photo_latent], 1), torch.cat([z_t, photo_latent], 1),
                                        torch.cat([z_t, torch.zeros_like(photo_latent)], 1)])
                    context = torch.cat([prompt_of[m].expand(nb, -1, -1), empty.expand(2 * nb, -1, -1)])
                    v_full, v_image, v_uncond = unet(sample, t.repeat(3), context).sample.chunk(3)
                    v = v_uncond + 1.0 * (v_full - v_image) + 1.0 * (v_image - v_uncond)
                    x0 = a.sqrt() * z_t - (1 - a).sqrt() * v
                    times["unet"] += now() - t0
                    t0 = now()
                    decoded = vae.decode(x0 / sf).sample.clamp(-1, 1).permute(0, 2, 3, 1)
                    targets[m] = decoded[..., :1] if m in GREY_MAPS else decoded
                    times["vae_decode"] += now() - t0
            t0 = now()
            loss = sum(((images[m] - targets[m].clone()) ** 2).sum(-1).mul(pixel_weight).sum() for m in maps) / nb
            loss.backward()
            times["loss_grad"] = now() - t0
            t0 = now()
            opt.step()
            opt.zero_grad(set_to_none=True)
            times["optimizer"] = now() - t0
            return times, float(loss.detach())

        step()                                                       # warm-up
        runs = []
        for _ in range(args.repeats):
            t0 = now()
            times, loss = step()
            runs.append((now() - t0, times))
        step_times = [r[0] for r in runs]
        stage_s = {k: float(np.median([r[1][k] for r in runs])) for k in TORCH_STAGES}
        rows.append({
            "framework": "torch", "dtype": "float32", "render": [h, w], "maps": list(maps),
            "views_per_step": nb, "unet_batch_per_step": 3 * nb * count,
            "step_s": float(np.median(step_times)), "step_s_all": step_times, "stages_s": stage_s,
            "stages_sum_s": float(sum(stage_s.values())), "finite": int(np.isfinite(loss)),
            "load_s": load_s, "torch_threads": torch.get_num_threads(), "device": device_name,
            "device_peak_gb": torch.cuda.max_memory_allocated(dev) / 2 ** 30 if cuda else None,
        })
        print("ROW " + json.dumps(rows[-1]), file=sys.stderr)
        print(f"[torch] {w}x{h} {count} map(s): {rows[-1]['step_s']:.2f} s/step "
              f"(stages {', '.join(f'{k} {v:.2f}' for k, v in stage_s.items())})", file=sys.stderr)
    for row in rows:
        row["peak_rss_gb"] = peak_rss_gb()
        row["huge_pages"] = huge_pages.status()
    return rows


# ----------------------------------------------------------------------------- the parent

def worker_environment(huge: bool) -> dict:
    """The workers' environment: this process's, with glibc's huge-page tunable added (`huge`) as the
    package's commands add it to themselves (`huge_pages.tunables_to_add`: nothing where it would do
    nothing, and a value already given is kept)."""
    env = dict(os.environ)
    value = huge_pages.tunables_to_add(env, huge_pages.glibc_version(), huge_pages.thp_mode()) if huge else None
    if value is not None:
        env["GLIBC_TUNABLES"] = value
    return env


def run_child(args, folder: str, worker: str) -> list[dict]:
    """Runs one worker in a fresh process; its rows are the last line of its stdout."""
    cmd = [sys.executable, __file__, f"--worker={worker}", f"--rgbx_dir={folder}",
           f"--render_sizes={','.join(map(str, args.render_sizes))}",
           f"--map_counts={','.join(map(str, args.map_counts))}", f"--views_per_step={args.views_per_step}",
           f"--reuse_steps={','.join(map(str, args.reuse_steps))}",
           f"--max_texture_size={args.max_texture_size}", f"--repeats={args.repeats}", f"--threads={args.threads}",
           f"--torch_device={args.torch_device}", f"--last_stage={args.last_stage}",
           f"--stage_cases={args.stage_cases}"]
    if args.fragment_cache:
        cmd.append(f"--fragment_cache={args.fragment_cache}")
    if args.peak_tflops:
        cmd.append(f"--peak_tflops={args.peak_tflops}")
    if args.convert_cache:
        cmd.append(f"--convert_cache={args.convert_cache}")
    cores = sorted(os.sched_getaffinity(0))[:args.threads]
    env = worker_environment(args.huge_pages == "true")
    print(f"--- {worker} on cores {cores}, huge pages {huge_pages.status(env)}: {' '.join(cmd[1:])}",
          file=sys.stderr)
    # both frameworks see the same cores (XLA sizes its pool by them; torch also gets the count), and the
    # same allocator settings: with --huge_pages, glibc's tunable that the package's commands run with
    proc = subprocess.run(cmd, stdout=subprocess.PIPE, text=True, env=env,
                          preexec_fn=lambda: os.sched_setaffinity(0, cores))
    if proc.returncode:
        print(f"the {worker} worker failed (exit {proc.returncode}); its log is above; the others still run",
              file=sys.stderr)
        return None
    return json.loads(proc.stdout.strip().splitlines()[-1])


def fmt(x, spec=".2f") -> str:
    return "-" if x is None else format(x, spec)


def row_name(r: dict) -> str:
    """"torch_float32", "jax_float32", or "jax_float32_reuse2" for our step with x̂0 reused over 2 steps."""
    reuse = r.get("reuse_steps", 1)
    return f"{r['framework']}_{r['dtype']}" + (f"_reuse{reuse}" if reuse > 1 else "")


def summarise(rows: list[dict]) -> dict:
    """Per (render, maps): JAX steps per dtype, the torch step, and torch / JAX ratios."""
    groups = {}
    for r in rows:
        groups.setdefault((tuple(r["render"]), len(r["maps"])), {})[row_name(r)] = r
    table = []
    for (render, count), g in groups.items():
        entry = {"render": list(render), "maps": count}
        for name, r in g.items():
            entry[f"{name}_s"] = r["step_s"]
        ref = g.get("torch_float32")
        ours = g.get("jax_float32")
        if ref and ours and all(ours.get("stage_flops", {}).get(k) for k in ("vae_encode", "unet", "vae_decode")):
            # the recipe's work in our XLA counts: the photo encoded as often as the renders, three
            # UNet branches, one decode (the same images in total, one map per pass)
            f = ours["stage_flops"]
            ref["flops_per_step"] = 2 * f["vae_encode"] + 3 * f["unet"] + f["vae_decode"]
            ref["flops_estimated_from"] = "jax stage cost analysis (2 encodes, 3 UNet branches, 1 decode)"
            ref["achieved_gflops_per_s"] = ref["flops_per_step"] / ref["step_s"] / 1e9
            entry["work_ratio_torch_over_jax"] = ref["flops_per_step"] / ours["flops_per_step"]
        for name in g:
            if ref and name.startswith("jax_"):
                entry[f"speedup_{name}"] = ref["step_s"] / g[name]["step_s"]
        for name, r in g.items():
            # the thesis's run: 17 000 steps of every map (the recipe: 5 runs of one map each, which its
            # 5-map row already does as 5 passes a step)
            entry[f"{name}_thesis_run_min"] = THESIS_STEPS * r["step_s"] / 60 * len(ALL_MAPS) / count
            for key in ("device_peak_gb", "compile_s", "unet_tflops_per_s", "unet_fraction_of_bf16_peak"):
                if r.get(key) is not None:
                    entry[f"{name}_{key}"] = r[key]
        table.append(entry)
    return {"table": table}


def print_tables(rows: list[dict], summary: dict, file=sys.stdout) -> None:
    print("\nper-stage medians (seconds); sum of stages vs the whole step", file=file)
    names = list(dict.fromkeys(TORCH_STAGES))
    print(f"{'framework':10s} {'dtype':9s} {'render':9s} {'maps':>4s} " + " ".join(f"{n:>12s}" for n in names)
          + f" {'sum':>8s} {'step':>8s} {'GFLOP':>8s} {'GFLOP/s':>8s} {'RSS GB':>7s}", file=file)
    for r in rows:
        stages = " ".join(f"{fmt(r['stages_s'].get(n)):>12s}" for n in names)
        gflop = r["flops_per_step"] / 1e9 if r.get("flops_per_step") else None
        print(f"{r['framework']:10s} {row_name(r)[len(r['framework']) + 1:]:9s} {r['render'][1]}x{r['render'][0]:<5d} "
              f"{len(r['maps']):4d} {stages} {fmt(r['stages_sum_s']):>8s} {r['step_s']:8.2f} {fmt(gflop, '.0f'):>8s} "
              f"{fmt(r.get('achieved_gflops_per_s'), '.1f'):>8s} {r['peak_rss_gb']:7.1f}", file=file)
    print("(torch GFLOP: the recipe's work counted with our XLA stage costs: 2 encodes, 3 UNet branches, 1 decode)",
          file=file)
    print("\nseconds per step, side by side (torch = the thesis's recipe; speed-up = torch / jax)", file=file)
    print(f"{'render':9s} {'maps':>4s} {'jax fp32':>9s} {'jax bf16':>9s} {'torch':>9s} {'x fp32':>7s} {'x bf16':>7s}",
          file=file)
    for e in summary["table"]:
        print(f"{e['render'][1]}x{e['render'][0]:<5d} {e['maps']:4d} {fmt(e.get('jax_float32_s')):>9s} "
              f"{fmt(e.get('jax_bfloat16_s')):>9s} {fmt(e.get('torch_float32_s')):>9s} "
              f"{fmt(e.get('speedup_jax_float32')):>7s} {fmt(e.get('speedup_jax_bfloat16')):>7s}", file=file)
        for name in sorted(k[len("speedup_"):] for k in e if k.startswith("speedup_jax_") and "_reuse" in k):
            print(f"{'':14s} {name}: {e[f'{name}_s']:.2f} s/step over whole cycles, {e[f'speedup_{name}']:.2f}x",
                  file=file)


def print_device_table(summary: dict, file=sys.stdout) -> None:
    """Per case and framework/dtype: step, device memory, compile, UNet utilisation, thesis run."""
    print("\nper case: step s, device peak GiB, compile s, UNet TFLOP/s (share of the bf16 peak), "
          f"projected {THESIS_STEPS} steps x {len(ALL_MAPS)} maps (min)", file=file)
    for e in summary["table"]:
        for name in [k[:-len("_thesis_run_min")] for k in e if k.endswith("_thesis_run_min")]:
            share = e.get(f"{name}_unet_fraction_of_bf16_peak")
            print(f"{e['render'][1]}x{e['render'][0]:<5d} {e['maps']:4d} {name:14s} {e[f'{name}_s']:8.3f} "
                  f"{fmt(e.get(f'{name}_device_peak_gb'), '.1f'):>6s} {fmt(e.get(f'{name}_compile_s'), '.0f'):>5s} "
                  f"{fmt(e.get(f'{name}_unet_tflops_per_s'), '.0f'):>5s} ({fmt(share * 100 if share else None, '.0f')} %) "
                  f"{e[f'{name}_thesis_run_min']:8.1f}", file=file)


def headline(summary: dict) -> str:
    parts = [f"{e['render'][1]}x{e['render'][0]} {e['maps']} map(s): "
             + ", ".join(f"{k[len('speedup_jax_'):]} {v:.2f}x" for k, v in e.items() if k.startswith("speedup_jax_"))
             for e in summary["table"] if any(k.startswith("speedup_") for k in e)]
    if not parts:
        return "no torch/jax pair measured: no ratio"
    return "our step vs the thesis's PyTorch recipe (torch s / jax s): " + "; ".join(parts)


def main(argv=None) -> int:
    args = parse_args(argv)
    folder = args.rgbx_dir
    if args.worker:
        kind, _, dtype = args.worker.partition(":")
        rows = jax_worker(args, folder, dtype) if kind == "jax" else torch_worker(args, folder)
        print(json.dumps(rows))
        return 0
    if args.size == "tiny":
        from jaxdistill.models.training.random_model import write_tiny_rgbx

        folder = str(write_tiny_rgbx(Path(tempfile.mkdtemp()) / "rgb-to-x"))
    rows, failed = [], []
    for fw in args.frameworks:
        for dtype in (args.dtypes if fw == "jax" else ["float32"]):
            worker = f"{fw}:{dtype}" if fw == "jax" else "torch"
            got = run_child(args, folder, worker)
            if got is None:
                failed.append(worker)
            else:
                rows += got
    summary = summarise(rows)
    print_tables(rows, summary)
    print_device_table(summary)
    import jax

    result = {"rows": rows, **summary, "folder": folder, "threads": args.threads, "repeats": args.repeats,
              "machine": {"backend": jax.default_backend(), "device": jax.devices()[0].device_kind,
                          "cpu_count": os.cpu_count(), "platform": platform.platform()},
              "headline": headline(summary)}
    print("\n" + result["headline"])
    if failed:
        result["failed_workers"] = failed
        print(f"failed workers: {', '.join(failed)}")
    if args.json:
        print(json.dumps(result))
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
