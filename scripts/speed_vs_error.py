r"""Speed vs error: the curve users choose a configuration from (docs/benchmarks.md §2, §3).

    python scripts/speed_vs_error.py                      # the full sweep: about 45 min on 2 idle cores
    python scripts/speed_vs_error.py --quick              # smoke version: 3 points, 4 steps (~2 min)
    python scripts/speed_vs_error.py --rgbx_only --rgbx_dir=data/random-rgbx/rgb-to-x   # part B, into the same JSON
    options: [--out_dir=out/speed_vs_error] [--factors=steps,texture,render,sampler,views] [--<factor>_values=...]
             [--maps=albedo] [--config=configs/bedroom.cfg] [--scene=...] [--max_gb=...] [--json]
             [--rgbx_dir=DIR [--convert_cache=DIR] [--rgbx_render_size=256] [--rgbx_t=20,200,500,800,980]]

A. The sweep (embedded bedroom, `views` prior). Around the baseline of `configs/bedroom.cfg`
   (trilinear, pages auto up to 512, 32 views per step, 100 steps, lr 0.05 cosine), one factor
   at a time is changed:

     steps    25, 50, 100, 200                   (the cosine schedule always decays over the run)
     texture  fixed pages 512, 1024, 2048, 4096; auto up to 4096   (baseline: auto up to 512)
     render   160, 240, 320 (native)             (--render_size: longer side of the renders)
     sampler  bilinear, trilinear
     views    8, 16, 32, 48 per step

   A value that computes the same as the baseline (steps 100, render 320, trilinear, 32 views)
   is the baseline point, run once. A point whose texels and AdamW state would not fit in memory
   (an estimate: 8 float32 copies of the texels + 2 GB, against MemAvailable or --max_gb) is
   skipped and listed as such: fixed 4096 pages with trilinear sampling are 388M texels, about
   37 GB, more than a 24 GB machine has (fixed 2048: 97M texels, 9.3 GB peak RSS measured).

   Each point is one fresh Python process running the main job's own code: `build_problem`, then
   `jaxdistill.engine.loop.run_loop` (the step set up as the main job sets it up, the step loop
   fetching the metrics every --log_every steps, NaN check), with `LoopHooks` that compile the
   step ahead of time and note the time of every fetch, and no checkpoints. Its albedo PSNR
   against ground truth is measured at the photos' native size (`scoring.evaluation_context` /
   `scoring.quick_psnr`, what --eval_every reports). Per point:

     setup_s    build_problem (scene, cached fragments, layout, gather plans, visibility, targets)
                + optimizer, initial state and placing state and constants on the device
     compile_s  tracing, lowering and XLA-compiling the step (ahead of time, then run compiled)
     steps_s    all --steps steps, batches assembled on the host as in the main job, to the last result
     wall_s     setup_s + compile_s + steps_s: what the distillation costs a user. Not included:
                importing Python/JAX (import_s), evaluation against GT (eval_s: native-size plans,
                GT renders, the PSNR), the periodic --eval_every PSNRs (switched off here),
                checkpoints and the outputs the main job writes (maps, glb, renders, contact
                sheets: about 40 s for the bedroom's five maps)
     s_per_step the median over windows of --log_every steps of (window time / steps)
     peak_rss_gb the point's process high-water mark (ru_maxrss)

   Ray casts are cached on disk by the library (`$JAXDISTILL_CACHE`); they are computed before
   the sweep for every render size (reported as fragments_cold_s, what the first run of a scene
   at that size pays once), so setup_s holds the cached read, as on every later run.

   --maps defaults to albedo: the loss is a sum of independent per-map terms on separate texel
   channels (AdamW is element-wise, the views prior ignores t, the views of a step depend only on
   (seed, step)), so the albedo texels and PSNR of an albedo-only run equal those of a five-map
   run (measured: 10 baseline steps, 17.6211316 dB both), and the sweep measures only albedo.
   The five-map job is slower, as it gathers 11 channels instead of 3: measured back to back,
   1.66x the seconds per step (4.58 against 2.77 on a loaded machine), setup +14 s, peak RSS
   4.8 against 2.9 GB. Give --maps=albedo,normal,roughness,metallic,irradiance to time the full
   job; its PSNR axis is unchanged.

   The timings are wall-clock: other jobs on the machine inflate them (each row records the
   1-minute load average before and after the point; 2-3x slower steps were seen at load 5-7 on
   2 cores). Run the sweep on an otherwise idle machine.

   Figure speed_vs_error.png: albedo PSNR (dB, vs GT, sRGB) against wall_s. Each factor has its
   own colour and marker, its points joined in order of wall time through the baseline (black star)
   and labelled with their value; the dashed step line is the Pareto front (points no other is
   both faster and better than); the grey horizontal line is the PSNR of the per-view estimates
   (the scene's targets), which the distillation must beat.

B. The prior's activation dtype (with --rgbx_dir=DIR; RGB<->X in diffusers format, e.g.
   the random-weight folder of `scripts/make_random_rgbx.py --size=full`). The folder is
   converted once (`convert.load_rgbx`, float32 parameters whatever the dtype); the bfloat16
   networks (`convert.build_networks(dtype=bfloat16)`) share those parameters, which is what
   `load_rgbx(dtype=bfloat16)` returns. On one bedroom view at --rgbx_render_size (photo via
   `problem.resize`), z0 = VAE encoding of the view's GT albedo, a fixed noise, for each t:

     latent  x̂0 = predict_x0(...) (jitted, one guided UNet pass, w_t = w_i = 1) on identical
             fp32 inputs (z_t, photo latent, prompt embedding): the UNet's bf16 error alone
     image   x_pred = RgbxPrior.targets(...) as the distillation step computes it (VAE encode →
             noise → guided x̂0 → VAE decode → clamp), every network in that dtype, each dtype
             with its own photo latent and prompt embedding: the error the step sees

   and reports the relative L2 error ||bf16 − fp32|| / ||fp32|| and, in image space, the PSNR of
   bf16 against fp32, with the median time of each jitted function after compilation for both
   dtypes and their ratio. Figure rgbx_dtype.png: relative error against t (log scale), both
   measures, times in the legend. With random weights (a tokenizer smaller than CLIP's, as the
   random folders have) the output says so: the errors are those of random networks.
   Part B runs in its own process after the sweep, or alone with --rgbx_only; either way the
   results merge into the out_dir's JSON. At real size on 2 CPU cores expect roughly 6-10 min
   (mostly XLA compiles of 2 functions x 2 dtypes, and bf16 calls, which are slower than fp32 on
   CPU) and about 10 GB peak RSS; the weights are held once, in float32.

Outputs in --out_dir: speed_vs_error.json (meta, the sweep table, the Pareto front, the
baseline, the rgbx rows), speed_vs_error.png, rgbx_dtype.png, logs/<point>.log (each point's
stderr). The table and the Pareto front are printed; --json prints the JSON as the last line.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
FACTORS = ("steps", "texture", "render", "sampler", "views")
DEFAULT_VALUES = {"steps": "25,50,100,200", "texture": "512,1024,2048,4096,auto:4096", "render": "160,240,320",
                  "sampler": "bilinear,trilinear", "views": "8,16,32,48"}
# --quick: a smoke version of the sweep (two factors, a few steps, 8 views)
QUICK_BASE = {"steps": 4, "views_per_step": 8}
QUICK_VALUES = {"steps": "2,4", "texture": "auto:512,1024", "render": "160", "sampler": "bilinear", "views": "4,8"}
QUICK_FACTORS = "steps,sampler"
RESULT_MARK = "@@SPEED_VS_ERROR "
REAL_CLIP_VOCAB = 49408
COLOURS = {"steps": "tab:blue", "texture": "tab:orange", "render": "tab:green", "sampler": "tab:red",
           "views": "tab:purple"}
MARKERS = {"steps": "o", "texture": "s", "render": "^", "sampler": "D", "views": "v"}


# ----------------------------------------------------------------------------- arguments

def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter, epilog=__doc__)
    p.add_argument("--config", default=str(ROOT / "configs" / "bedroom.cfg"), help="flagfile of the baseline")
    p.add_argument("--scene", help="override the baseline's --scene (default: the config's, the bedroom)")
    p.add_argument("--out_dir", default="out/speed_vs_error")
    p.add_argument("--maps", default="albedo", help="maps distilled at every point (albedo must be one)")
    p.add_argument("--factors", default=None, help=f"comma-separated subset of {','.join(FACTORS)} (default all; "
                   f"--quick: {QUICK_FACTORS}); 'none' runs only the baseline")
    for f in FACTORS:
        p.add_argument(f"--{f}_values", default=None, help=f"values of {f} (default {DEFAULT_VALUES[f]})")
    p.add_argument("--quick", action="store_true", help="smoke version: baseline at "
                   f"{QUICK_BASE}, factors {QUICK_FACTORS} with {QUICK_VALUES}")
    p.add_argument("--rgbx_dir", help="RGB<->X folder: also run part B (bf16 vs fp32 prior)")
    p.add_argument("--rgbx_only", action="store_true", help="run part B only (skip the sweep)")
    p.add_argument("--convert_cache", help="cache of converted RGB<->X weights (convert.load_rgbx cache_dir)")
    p.add_argument("--rgbx_render_size", type=int, default=256,
                   help="longer side of the view in part B (multiple of 8)")
    p.add_argument("--rgbx_t", default="20,200,500,800,980", help="timesteps of part B")
    p.add_argument("--rgbx_view", type=int, default=0, help="index of the view of part B")
    p.add_argument("--rgbx_repeats", type=int, default=0, help="extra timed calls per t and dtype in part B")
    p.add_argument("--max_gb", type=float, default=None, help="skip points whose texels and AdamW state would need "
                   "more memory than this (default: MemAvailable when the point starts)")
    p.add_argument("--json", action="store_true", help="print the JSON table as the last line of stdout")
    p.add_argument("--_point", help=argparse.SUPPRESS)     # internal: run one point in this process
    p.add_argument("--_rgbx", help=argparse.SUPPRESS)      # internal: run part B in this process
    args = p.parse_args(argv)
    if args.rgbx_render_size % 8 or args.rgbx_render_size < 8:
        p.error("--rgbx_render_size must be a positive multiple of 8 (the VAE's downsampling)")
    if args.rgbx_only and not args.rgbx_dir:
        p.error("--rgbx_only needs --rgbx_dir")
    factors = args.factors if args.factors is not None else (QUICK_FACTORS if args.quick else ",".join(FACTORS))
    args.factor_list = [] if factors == "none" else [f for f in factors.split(",") if f]
    unknown = [f for f in args.factor_list if f not in FACTORS]
    if unknown:
        p.error(f"--factors: unknown {unknown}; choose from {','.join(FACTORS)}")
    if "albedo" not in args.maps.split(","):
        p.error("--maps must include albedo (the sweep measures albedo PSNR against GT)")
    return args


def base_config(args, out_dir: str):
    """The baseline DistillConfig: --config parsed by the library's own flags, then the sweep's
    fixed settings (views prior, --maps, no checkpoints, no periodic evaluation, no outputs)."""
    from absl import flags

    from jaxdistill.engine import config as config_lib

    fv = flags.FlagValues()
    config_lib.define_flags(fv)
    fv(["speed_vs_error", f"--flagfile={Path(args.config).resolve()}"])
    config = config_lib.config_from_flags(fv)
    # the views prior at the photos' size and 32 views per step, as this sweep was measured (bedroom.cfg
    # now renders at 128 with 8 views per step, the shipped rgbx model's setting)
    # and without the re-rendering term (bedroom.cfg now has it; this sweep measured the distillation alone);
    # x̂0 reuse is the rgbx prior's (bedroom.cfg's --reuse_steps=2), the views prior refuses it
    changes = dict(out_dir=out_dir, maps=tuple(args.maps.split(",")), prior="views", eval_every=0, ckpt_every=0,
                   renders=False, contact_views=0, resume=False, render_size=0, views_per_step=32,
                   photo_weight=0.0, irradiance_smoothness=0.0, albedo_smoothness=0.0, reuse_steps=1)
    if args.scene:
        changes["scene"] = args.scene
    if args.quick:
        changes.update(QUICK_BASE)
    return config_lib.validate(dataclasses.replace(config, **changes))


# ----------------------------------------------------------------------------- the points

def factor_values(args, factor: str) -> list[str]:
    given = getattr(args, f"{factor}_values")
    text = given if given is not None else (QUICK_VALUES if args.quick else DEFAULT_VALUES)[factor]
    return [v.strip() for v in text.split(",") if v.strip()]


def overrides(factor: str, value: str) -> dict:
    """DistillConfig fields a factor's value sets."""
    if factor == "steps":
        return {"steps": int(value)}
    if factor == "views":
        return {"views_per_step": int(value)}
    if factor == "render":
        return {"render_size": int(value)}
    if factor == "sampler":
        return {"sampler": value}
    if factor == "texture":
        if value.startswith("auto"):
            cap = value.partition(":")[2]
            return {"texture_size": "auto", **({"max_texture_size": int(cap)} if cap else {})}
        return {"texture_size": value}
    raise ValueError(factor)


def value_label(factor: str, config) -> str:
    """The value of `factor` in `config`, as the plot labels it."""
    if factor == "steps":
        return str(config.steps)
    if factor == "views":
        return str(config.views_per_step)
    if factor == "render":
        return str(config.render_size)
    if factor == "sampler":
        return config.sampler
    if config.texture_size == "auto":
        return f"auto≤{config.max_texture_size}"
    return config.texture_size


def effective(config, native_long_side: int | None):
    """The config with what does not change the computation normalised: --render_size equal to
    the photos' longer side is the photos' size (0); the cap of fixed page sizes is unused."""
    changes = {}
    if native_long_side and config.render_size == native_long_side:
        changes["render_size"] = 0
    if config.texture_size != "auto":
        changes["max_texture_size"] = 4096
    return dataclasses.replace(config, **changes)


def make_points(args, base, native_long_side):
    """[(key config, [(factor, label), ...])]: the baseline first, then each factor's other values;
    points whose computation equals another's are run once and carry every label."""
    from jaxdistill.engine import config as config_lib

    points = [(base, [("baseline", "baseline")])]
    index = {effective(base, native_long_side): 0}
    for factor in args.factor_list:
        for value in factor_values(args, factor):
            config = config_lib.validate(dataclasses.replace(base, **overrides(factor, value)))
            if factor == "render" and native_long_side and config.render_size == native_long_side:
                label = f"{value} (native)"
            else:
                label = value_label(factor, config)
            key = effective(config, native_long_side)
            if key in index:
                points[index[key]][1].append((factor, label))
            else:
                index[key] = len(points)
                points.append((config, [(factor, label)]))
    return points


def differing_fields(config, base) -> dict:
    a, b = config.as_dict(), base.as_dict()
    return {k: a[k] for k in a if a[k] != b[k]}


def cost_guess(config, native_hw) -> float:
    """Relative cost of a point for the progress bar's ETA (seconds-ish, calibrated on the baseline)."""
    h, w = native_hw
    if config.render_size:
        scale = config.render_size / max(h, w)
        pixels = scale * scale
    else:
        pixels = 1.0
    # measured relative to the baseline (s/step, setup); fixed 4096 pages are skipped on a 24 GB machine
    step_x = {"512": 1.3, "1024": 2.5, "2048": 6.0, "4096": 0.0}.get(config.texture_size,
                                                                     1.0 if config.max_texture_size <= 512 else 1.5)
    setup_x = {"2048": 1.7, "4096": 0.6}.get(config.texture_size, 1.0)
    per_step = 1.0 * config.views_per_step / 32 * pixels * step_x * (1.0 if config.sampler == "trilinear" else 0.6)
    return 45.0 * setup_x + config.steps * per_step


# ----------------------------------------------------------------------------- one point (child process)

STATE_COPIES = 8     # texels, AdamW mu and nu, gradient, updates, step temporaries, host copy (estimate)


def state_gb(num_texels: int, channels: int) -> float:
    """Estimated peak memory of a point beyond the fixed problem: STATE_COPIES float32 texel arrays + 2 GB."""
    return num_texels * channels * 4 * STATE_COPIES / 2 ** 30 + 2.0


def skip_reason(need_gb, texels, channels, limit_gb) -> str:
    return (f"the texels and AdamW state need about {need_gb:.1f} GB ({STATE_COPIES} copies of {texels} x {channels} "
            f"float32, + 2 GB), more than the {limit_gb:.1f} GB available (--max_gb)")


def memory_precheck(config, limit_gb: float) -> dict | None:
    """A skipped row when the point's texels cannot fit in `limit_gb`, found without the gather plans
    (minutes at 4096-texel pages). Only when full pages would not fit does it count the compact
    texels, with the layout and texel space build_problem makes from the same fragments."""
    from jaxdistill.scene.maps import MapChannels
    from jaxdistill.engine.problem import render_shape, resolve_scene_path, scaled_camera
    from jaxdistill.render import fragments as fr
    from jaxdistill.render.gather_plan import build_texel_space
    from jaxdistill.render.layout import make_layout
    from jaxdistill.scene.model import read_scene

    scene = read_scene(resolve_scene_path(config.scene))
    channels = MapChannels(tuple(config.maps)).num_channels
    side = config.max_texture_size if config.texture_size == "auto" else int(config.texture_size)
    pages = scene.num_objects if scene.texture_layout == "pages" else 1
    if state_gb(pages * side * side, channels) <= limit_gb:
        return None
    height, width = render_shape(scene, config.render_size, 1)
    frags = fr.compute_fragments(scene.mesh, [scaled_camera(v.camera, height, width) for v in scene.views])
    if any((v.camera.height, v.camera.width) != (height, width) for v in scene.views):
        frags = list(frags) + fr.compute_fragments(scene.mesh, [v.camera for v in scene.views])
    size = config.texture_size if config.texture_size == "auto" else int(config.texture_size)
    layout = make_layout(scene.num_objects, scene.texture_layout, size, frags, max_size=config.max_texture_size,
                         mipmaps=config.sampler == "trilinear")
    texels = build_texel_space(frags, layout, config.sampler).num_texels
    need = state_gb(texels, channels)
    if need <= limit_gb:
        return None
    return {"skipped": skip_reason(need, texels, channels, limit_gb), "texels": int(texels), "need_gb": need,
            "render_hw": [height, width]}


def available_gb() -> float:
    """MemAvailable of /proc/meminfo in GB (inf where unknown)."""
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemAvailable:"):
                return int(line.split()[1]) / 2 ** 20
    except OSError:
        pass
    return math.inf


def run_point(spec: dict) -> dict:
    """Runs one sweep point in this process (the child); returns its row."""
    t0 = time.perf_counter()
    import numpy as np
    from absl import logging

    from jaxdistill.engine import config as config_lib, loop
    from jaxdistill.engine.problem import build_problem, choose_prior
    from jaxdistill.evaluate import ground_truth as evaluation, scoring
    import_s = time.perf_counter() - t0
    logging.set_verbosity(logging.INFO)

    cfg = spec["config"]
    cfg["maps"] = tuple(cfg["maps"])
    config = config_lib.validate(config_lib.DistillConfig(**cfg))
    loop.check_before_compute(config, Path(config.out_dir), choose_prior(config))   # as the main job, before compute

    # setup: what the main job does before its loop (less the evaluation context, timed in eval_s)
    load_before = os.getloadavg()[0]
    limit_gb = spec.get("max_gb") or available_gb()
    too_big = memory_precheck(config, limit_gb)      # only when full pages could not fit: not a timed part
    if too_big:
        return {**too_big, "import_s": import_s,
                "peak_rss_gb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2 ** 20}
    t0 = time.perf_counter()
    problem = build_problem(config)
    need_gb = state_gb(problem.space.num_texels, problem.channels.num_channels)
    if need_gb > limit_gb:
        return {"skipped": skip_reason(need_gb, problem.space.num_texels, problem.channels.num_channels, limit_gb),
                "texels": int(problem.space.num_texels), "render_hw": [problem.height, problem.width],
                "import_s": import_s, "setup_s": time.perf_counter() - t0, "setup_timings": problem.timings,
                "need_gb": need_gb, "peak_rss_gb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2 ** 20}

    # the main job's loop; the clock marks the end of the setup, compiles the step ahead of time (so
    # that the steps are timed apart) and notes when each --log_every window's metrics come back
    clock = loop.StepClock()
    result = loop.run_loop(config, problem, loop.recorded_config(config, problem.choice.kind), None, progress=False,
                           hooks=clock.hooks())
    setup_s = clock.start - t0
    compile_s = clock.compile_s
    steps_s = clock.marks[-1][1] - clock.marks[0][1]
    windows = clock.seconds_per_step()

    # evaluation at the photos' native size, as --eval_every does
    t0 = time.perf_counter()
    ctx = scoring.evaluation_context(config, problem)
    psnr = scoring.quick_psnr(result.state, problem, ctx) if ctx.gt is not None else math.nan
    eval_s = time.perf_counter() - t0
    losses = result.history["loss"]
    row = {
        "render_hw": [problem.height, problem.width], "texels": int(problem.space.num_texels),
        "page_sizes": sorted(set(int(s) for s in problem.space.layout.page_sizes)),
        "import_s": import_s, "setup_s": setup_s, "compile_s": compile_s, "steps_s": steps_s,
        "wall_s": setup_s + compile_s + steps_s, "s_per_step": float(np.median(windows)),
        "eval_s": eval_s, "albedo_psnr": psnr, "final_loss": losses[-1] if losses else math.nan,
        "setup_timings": problem.timings, "traces": result.traces, "need_gb": need_gb,
        "load_avg_1min": [load_before, os.getloadavg()[0]],
    }
    if spec.get("baseline") and ctx.gt is not None:
        base = evaluation.read_baseline(problem.scene, ["albedo"], ctx.shapes)
        row["per_view_estimates_psnr"] = (evaluation.albedo_psnr(base, ctx.gt_maps, ctx.masks)
                                          if base is not None else math.nan)
    row["peak_rss_gb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2 ** 20
    return row


# ----------------------------------------------------------------------------- part B (child process)

def run_rgbx(spec: dict) -> dict:
    """bf16 against fp32 activations of the RGB<->X prior on one view; returns part B's result."""
    import functools

    import jax
    import jax.numpy as jnp
    import numpy as np
    from absl import logging

    from jaxdistill.evaluate import ground_truth as evaluation
    from jaxdistill.io import images as imageio
    from jaxdistill.scene.maps import MapChannels, file_to_model
    from jaxdistill.models import convert, prior as rgbx, scheduler as sched
    from jaxdistill.engine.priors import make_rgbx_prior
    from jaxdistill.engine.problem import read_target, render_shape, resize, resolve_scene_path
    from jaxdistill.render import fragments as fr
    from jaxdistill.scene.model import read_scene
    logging.set_verbosity(logging.INFO)

    folder = Path(spec["folder"]).expanduser()
    scene = read_scene(resolve_scene_path(spec["scene"]))
    view = scene.views[spec["view"]]
    height, width = render_shape(scene, spec["render_size"], 8)
    photo = resize(imageio.read_photo_srgb(view.photo, view.exposure), height, width)
    gt = evaluation.read_ground_truth(scene)
    if gt is not None and "albedo" in gt.pages:
        one = dataclasses.replace(scene, views=(view,))
        frags = fr.compute_fragments(scene.mesh, [view.camera], progress=False)
        albedo, source = evaluation.gt_view_maps(gt, one, frags)[0]["albedo"], f"GT albedo of {view.name}"
    elif "albedo" in view.targets:
        albedo, source = read_target("albedo", view.targets["albedo"]), f"albedo target of {view.name}"
    else:
        albedo, source = imageio.srgb_to_linear(imageio.read_photo_srgb(view.photo, view.exposure)), f"linear photo of {view.name}"
    image = file_to_model("albedo", resize(np.asarray(albedo, np.float32)[..., :3], height, width))[None]

    vocab_file = folder / "tokenizer" / "vocab.json"
    vocab = len(json.loads(vocab_file.read_text())) if vocab_file.is_file() else None
    random_weights = vocab is not None and vocab < REAL_CLIP_VOCAB

    t0 = time.perf_counter()
    loaded = convert.load_rgbx(folder, dtype=jnp.float32, cache_dir=spec.get("convert_cache"))
    load_s = time.perf_counter() - t0
    loaded.params = jax.device_put(loaded.params)           # once: both dtypes share the device copy
    nets16 = convert.build_networks(folder, jnp.bfloat16)
    loaded16 = convert.LoadedRgbx(loaded.folder, nets16, loaded.params, dict(loaded.seconds))
    models = {"float32": rgbx.load_prior(loaded), "bfloat16": rgbx.load_prior(loaded16)}
    guidance = rgbx.Guidance()
    channels = MapChannels(("albedo",))

    m32 = models["float32"]
    photo_latent32 = rgbx.encode_photo(m32, photo)
    z0 = rgbx.encode_images(m32.networks.vae, m32.params["vae"], jnp.asarray(image))
    noise = jax.random.normal(jax.random.PRNGKey(spec["seed"]), z0.shape, jnp.float32)
    alphas = sched.alphas_cumprod(m32.scheduler)
    key = jax.random.PRNGKey(spec["seed"] + 1)

    fns = {}
    for name, model in models.items():
        unet_fn = jax.jit(functools.partial(rgbx.predict_x0, model.networks.unet, model.scheduler,
                                            guidance=guidance))
        prior, frozen = make_rgbx_prior(model, channels, [photo], guidance=guidance, sample_latent=False,
                                        latent_space=False)
        frozen = jax.device_put(frozen)

        def targets(frozen, image, photo_latent, t, key, prior=prior):
            return prior.targets(frozen, {"albedo": image}, {"photo_latent": photo_latent}, t, key)["albedo"]

        fns[name] = (unet_fn, jax.jit(targets), frozen, jnp.asarray(prior.photo_latents[:1]))

    def timed(fn, *a):
        t0 = time.perf_counter()
        out = jax.block_until_ready(fn(*a))
        return out, time.perf_counter() - t0

    def latent_call(name, t):
        unet_fn = fns[name][0]
        z_t = sched.add_noise(z0, noise, alphas[t])
        return timed(unet_fn, loaded.params["unet"], z_t, jnp.full((1,), t, jnp.int32), photo_latent32,
                     m32.text["albedo"])

    def image_call(name, t):
        _, target_fn, frozen, photo_latent = fns[name]
        return timed(target_fn, frozen, jnp.asarray(image), photo_latent, jnp.full((1, 1), t, jnp.int32), key)

    ts = spec["t"]
    compile_s = {}
    for name in models:                                    # first calls: compile (and run once)
        compile_s[name] = {"latent": latent_call(name, ts[0])[1], "image": image_call(name, ts[0])[1]}
    times = {n: {"latent": [], "image": []} for n in models}
    rows = []
    for t in ts:                                           # the two dtypes interleaved: same machine load
        out = {}
        for name in models:
            for kind, call in (("latent", latent_call), ("image", image_call)):
                for r in range(1 + spec["repeats"]):
                    value, seconds = call(name, t)
                    times[name][kind].append(seconds)
                out[name, "latent" if call is latent_call else "image"] = np.asarray(value, np.float64)
        row = {"t": int(t), "alpha_bar": float(alphas[t])}
        for kind in ("latent", "image"):
            ref, low = out["float32", kind], out["bfloat16", kind]
            row[f"{kind}_rel_l2"] = float(np.linalg.norm(low - ref) / max(np.linalg.norm(ref), 1e-30))
            row[f"{kind}_max_abs"] = float(np.abs(low - ref).max())
        a, b = ((out[n, "image"] + 1.0) / 2.0 for n in ("float32", "bfloat16"))
        mse = float(np.mean((a - b) ** 2))
        row["image_psnr_bf16_vs_fp32_db"] = 10 * math.log10(1.0 / mse) if mse > 0 else math.inf
        rows.append(row)
    timing = {}
    for kind in ("latent", "image"):
        med = {n: float(np.median(times[n][kind])) for n in models}
        timing[kind] = {"fp32_median_s": med["float32"], "bf16_median_s": med["bfloat16"],
                        "bf16_over_fp32": med["bfloat16"] / med["float32"],
                        "saved_s": med["float32"] - med["bfloat16"],
                        "fp32_compile_s": compile_s["float32"][kind], "bf16_compile_s": compile_s["bfloat16"][kind],
                        "calls_timed": len(times["float32"][kind])}
    note = ("RANDOM WEIGHTS (the tokenizer has %d entries, CLIP has %d: a folder written by "
            "scripts/make_random_rgbx.py or jaxdistill.models.training.random_model): the errors are those of random networks, "
            "the timings are real" % (vocab, REAL_CLIP_VOCAB)) if random_weights else \
        "weights as supplied (tokenizer vocabulary of CLIP's size)"
    return {"folder": str(folder), "random_weights": random_weights, "note": note, "view": view.name,
            "render_hw": [height, width], "z0": f"VAE mode x scaling_factor of the {source}",
            "load_s": load_s, "load_seconds": loaded.seconds, "rows": rows, "timing": timing,
            "measures": {"latent": "predict_x0 (one guided UNet pass) on identical fp32 inputs",
                         "image": "RgbxPrior.targets: VAE encode, noise, guided x0, VAE decode, clamp; "
                                  "all networks in the dtype"},
            "backend": jax.default_backend(), "device": jax.devices()[0].device_kind,
            "peak_rss_gb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2 ** 20}


# ----------------------------------------------------------------------------- the parent

def run_child(kind: str, spec: dict, log: Path) -> dict:
    """Runs `spec` in a fresh Python process (clean timing and peak RSS); its stderr goes to `log`."""
    log.parent.mkdir(parents=True, exist_ok=True)
    with open(log, "w") as err:
        proc = subprocess.run([sys.executable, str(Path(__file__).resolve()), f"--{kind}", json.dumps(spec)],
                              stdout=subprocess.PIPE, stderr=err, text=True, cwd=os.getcwd())
    lines = [l for l in proc.stdout.splitlines() if l.startswith(RESULT_MARK)]
    if proc.returncode or not lines:
        tail = log.read_text()[-3000:]
        raise RuntimeError(f"{kind} failed (exit {proc.returncode}); see {log}:\n{tail}")
    return json.loads(lines[-1][len(RESULT_MARK):])


def warm_fragments(base, render_sizes) -> dict:
    """Ray casts every render size of the sweep into the library's disk cache (timed)."""
    from jaxdistill.engine.problem import render_shape, resolve_scene_path, scaled_camera
    from jaxdistill.render import fragments as fr
    from jaxdistill.scene.model import read_scene

    scene = read_scene(resolve_scene_path(base.scene))
    out = {}
    for size in sorted(set(render_sizes) | {0}):
        h, w = render_shape(scene, size, 1)
        t0 = time.perf_counter()
        fr.compute_fragments(scene.mesh, [scaled_camera(v.camera, h, w) for v in scene.views], progress=False)
        out[f"{w}x{h}"] = time.perf_counter() - t0
    return out


def pareto(rows: list[dict]) -> list[dict]:
    """Rows no other row beats on both counts (lower wall_s and higher albedo PSNR), by wall time."""
    ok = sorted((r for r in measured(rows) if r.get("albedo_psnr") is not None and math.isfinite(r["albedo_psnr"])),
                key=lambda r: (r["wall_s"], -r["albedo_psnr"]))
    front, best = [], -math.inf
    for r in ok:
        if r["albedo_psnr"] > best:
            front.append(r)
            best = r["albedo_psnr"]
    return front


def measured(rows: list[dict]) -> list[dict]:
    return [r for r in rows if "skipped" not in r]


def row_name(row) -> str:
    return ", ".join(f"{f}={v}" if f != "baseline" else "baseline" for f, v in row["labels"])


def format_table(rows, baseline_psnr) -> str:
    head = (f"{'point':34s} {'wall_s':>7s} {'setup':>6s} {'compile':>7s} {'steps':>7s} {'s/step':>6s} "
            f"{'eval':>5s} {'PSNR':>6s} {'gain':>6s} {'texels':>10s} {'RSS GB':>6s}")
    lines = [head, "-" * len(head)]
    for r in rows:
        if "skipped" in r:
            lines.append(f"{row_name(r)[:34]:34s} skipped: {r['skipped']}")
            continue
        gain = r["albedo_psnr"] - baseline_psnr if baseline_psnr is not None else math.nan
        lines.append(f"{row_name(r)[:34]:34s} {r['wall_s']:7.1f} {r['setup_s']:6.1f} {r['compile_s']:7.1f} "
                     f"{r['steps_s']:7.1f} {r['s_per_step']:6.3f} {r['eval_s']:5.1f} {r['albedo_psnr']:6.2f} "
                     f"{gain:+6.2f} {r['texels']:10d} {r['peak_rss_gb']:6.2f}")
    return "\n".join(lines)


def baseline_label(config) -> str:
    texture = f"auto≤{config.max_texture_size}" if config.texture_size == "auto" else config.texture_size
    render = f"render {config.render_size}" if config.render_size else "native render"
    return (f"{config.steps} steps, {texture}, {render}, {config.sampler}, {config.views_per_step} views, "
            f"lr {config.lr:g} {config.lr_schedule}")


def plot_sweep(path: Path, rows, front, baseline_psnr, title: str, base_text: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    skipped = [row_name(r) for r in rows if "skipped" in r]
    rows = measured(rows)
    base = next((r for r in rows if r["factor"] == "baseline"), None)
    if base is None:
        print(f"no plot: the baseline point was not measured", file=sys.stderr)
        return
    fig, ax = plt.subplots(figsize=(11, 6))
    factors = [f for f in FACTORS if any(l[0] == f for r in rows for l in r["labels"])]
    for f in factors:
        series = [(r, l[1]) for r in rows for l in r["labels"] if l[0] == f]
        if not any(r is base for r, _ in series):
            series.append((base, None))
        series.sort(key=lambda s: s[0]["wall_s"])
        xs, ys = [r["wall_s"] for r, _ in series], [r["albedo_psnr"] for r, _ in series]
        ax.plot(xs, ys, color=COLOURS[f], alpha=0.35, lw=1)
        pts = [(r, lab) for r, lab in series if r is not base]
        ax.scatter([r["wall_s"] for r, _ in pts], [r["albedo_psnr"] for r, _ in pts], color=COLOURS[f],
                   marker=MARKERS[f], s=45, label=f, zorder=3)
        for r, lab in pts:
            ax.annotate(lab, (r["wall_s"], r["albedo_psnr"]), textcoords="offset points", xytext=(5, 4),
                        fontsize=8, color=COLOURS[f])
    ax.scatter([base["wall_s"]], [base["albedo_psnr"]], marker="*", s=220, color="k", zorder=4,
               label="baseline:\n" + base_text.replace(", lr", ",\nlr"))
    if front:
        xs = [r["wall_s"] for r in front]
        ys = [r["albedo_psnr"] for r in front]
        right = max(r["wall_s"] for r in rows) * 1.05
        ax.step(xs + [right], ys + [ys[-1]], where="post", color="k", ls="--", lw=1, label="Pareto front", zorder=2)
    if baseline_psnr is not None and math.isfinite(baseline_psnr):
        ax.axhline(baseline_psnr, color="0.5", lw=1.2, label=f"per-view estimates {baseline_psnr:.2f} dB")
    walls = [r["wall_s"] for r in rows]
    if max(walls) / max(min(walls), 1e-9) > 6:
        from matplotlib.ticker import FixedLocator, NullFormatter, ScalarFormatter

        ax.set_xscale("log")
        nice = [v * 10 ** e for e in range(-1, 6) for v in (1, 2, 3, 5)]
        lo, hi = ax.get_xlim()
        ax.xaxis.set_major_locator(FixedLocator([v for v in nice if lo <= v <= hi]))
        ax.xaxis.set_major_formatter(ScalarFormatter())
        ax.xaxis.set_minor_formatter(NullFormatter())
    if skipped:
        fig.text(0.01, 0.01, "not run (memory): " + "; ".join(skipped), fontsize=8, color="0.4")
    ax.set_xlabel("wall time, s (setup + compile + steps)")
    ax.set_ylabel("albedo PSNR vs GT, dB (native size, sRGB)")
    ax.set_title(title, fontsize=10)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8, loc="upper left", bbox_to_anchor=(1.01, 1.0), borderaxespad=0)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def plot_rgbx(path: Path, result: dict) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows, timing = result["rows"], result["timing"]
    fig, ax = plt.subplots(figsize=(7, 4.5))
    ts = [r["t"] for r in rows]
    for kind, style, what in (("latent", "o-", "x̂0 latent (UNet)"), ("image", "s-", "x_pred image (VAE+UNet+VAE)")):
        tm = timing[kind]
        ax.plot(ts, [max(r[f"{kind}_rel_l2"], 1e-12) for r in rows], style,
                label=f"{what}: fp32 {tm['fp32_median_s']:.3g} s, bf16 {tm['bf16_median_s']:.3g} s "
                      f"(x{tm['bf16_over_fp32']:.2f})")
    ax.set_yscale("log")
    ax.set_xlabel("t")
    ax.set_ylabel("||bf16 − fp32|| / ||fp32||")
    h, w = result["render_hw"]
    title = f"RGB<->X bf16 vs fp32 activations, {w}x{h}, {result['backend']}"
    if result["random_weights"]:
        title += "\nRANDOM WEIGHTS: errors of random networks, real timings"
    ax.set_title(title, fontsize=10)
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def json_safe(value):
    if isinstance(value, dict):
        return {str(k): json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [json_safe(v) for v in value]
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def main(argv=None) -> int:
    args = parse_args(argv)
    if args._point:
        print(RESULT_MARK + json.dumps(json_safe(run_point(json.loads(args._point)))), flush=True)
        return 0
    if args._rgbx:
        print(RESULT_MARK + json.dumps(json_safe(run_rgbx(json.loads(args._rgbx)))), flush=True)
        return 0

    from tqdm.auto import tqdm

    start = time.perf_counter()
    out = Path(args.out_dir)
    out.mkdir(parents=True, exist_ok=True)
    scratch = tempfile.mkdtemp(prefix="speed_vs_error_")     # the points write nothing there
    base = base_config(args, scratch)
    doc = {"meta": {"command": " ".join([Path(sys.argv[0]).name] + sys.argv[1:]), "config": args.config,
                    "baseline_config": base.as_dict(), "maps": list(base.maps), "quick": args.quick,
                    "cpus": os.cpu_count(),
                    "wall_s_includes": "setup_s (build_problem with cached fragments, optimizer, init_state, device "
                                       "placement) + compile_s (trace, lower, XLA compile of the step) + steps_s "
                                       "(every step, host batches included, to the last result)",
                    "wall_s_excludes": "import_s, eval_s, periodic --eval_every PSNRs, checkpoints, output files"}}
    rows, front, baseline_psnr = [], [], None
    if not args.rgbx_only:
        from jaxdistill.engine.problem import resolve_scene_path
        from jaxdistill.scene.model import read_scene

        scene = read_scene(resolve_scene_path(base.scene))
        sizes = {(v.camera.height, v.camera.width) for v in scene.views}
        native_hw = max(sizes, key=lambda s: s[0] * s[1])
        native_long = max(native_hw) if len(sizes) == 1 else None
        points = make_points(args, base, native_long)
        render_sizes = {c.render_size for c, _ in points}
        print(f"{len(points)} points ({', '.join(args.factor_list) or 'baseline only'}), maps {','.join(base.maps)}, "
              f"each in a fresh process; ray casts into the disk cache first", file=sys.stderr)
        doc["meta"]["fragments_cold_s"] = warm_fragments(base, render_sizes)
        doc["meta"]["fragments_note"] = ("seconds to ray cast (or read from $JAXDISTILL_CACHE when already cached) "
                                         "every view at each render size, before the sweep")
        weights = [cost_guess(c, native_hw) for c, _ in points]
        bar = tqdm(total=round(sum(weights)), unit="", desc="speed vs error", dynamic_ncols=True, smoothing=0,
                   bar_format="{l_bar}{bar}| [{elapsed}<{remaining}{postfix}]")
        for i, ((config, labels), weight) in enumerate(zip(points, weights)):
            name = "baseline" if i == 0 else "_".join(f"{f}-{v}" for f, v in labels)
            name = name.replace("≤", "le").replace(" ", "")
            bar.set_postfix_str(f"point {i + 1}/{len(points)} {name}")
            spec = {"config": config.as_dict(), "baseline": i == 0, "max_gb": args.max_gb}
            row = run_child("_point", spec, out / "logs" / f"{name}.log")
            row = {"labels": labels, "factor": labels[0][0], "value": labels[0][1],
                   "changed": differing_fields(config, base), **row}
            if i == 0:
                baseline_psnr = row.pop("per_view_estimates_psnr", None)
            rows.append(row)
            if "skipped" in row:
                print(f"\n{name}: skipped: {row['skipped']}", file=sys.stderr)
            bar.update(round(weight))
        bar.close()
        front = pareto(rows)
        doc["sweep"] = rows
        doc["pareto"] = [row_name(r) for r in front]
        doc["per_view_estimates"] = {"albedo_psnr": baseline_psnr,
                                     "what": "the scene's per-view albedo targets against GT (evaluation.read_baseline"
                                             " + albedo_psnr, native size): the horizontal line"}
        title = (f"{scene.name}: albedo PSNR vs wall time ({','.join(base.maps)}, views prior, "
                 f"{os.cpu_count()} CPUs{', QUICK' if args.quick else ''})")
        plot_sweep(out / "speed_vs_error.png", rows, front, baseline_psnr, title, baseline_label(base))

    if args.rgbx_dir:
        cache = str(Path(args.convert_cache).expanduser()) if args.convert_cache else None
        spec = {"folder": str(Path(args.rgbx_dir).expanduser()), "convert_cache": cache, "scene": base.scene,
                "render_size": args.rgbx_render_size, "t": [int(t) for t in args.rgbx_t.split(",")],
                "view": args.rgbx_view, "repeats": args.rgbx_repeats, "seed": 0}
        print("part B: RGB<->X bf16 vs fp32 (load, compile, then every t for both dtypes) ...", file=sys.stderr)
        doc["rgbx"] = run_child("_rgbx", spec, out / "logs" / "rgbx.log")
        plot_rgbx(out / "rgbx_dtype.png", doc["rgbx"])
    doc["meta"]["total_s"] = time.perf_counter() - start
    path = out / "speed_vs_error.json"
    if path.is_file():       # a separate part-B run (--rgbx_only) keeps the sweep of the same out_dir, and back
        try:
            previous = json.loads(path.read_text())
        except json.JSONDecodeError:
            previous = {}
        kept = [k for k in ("sweep", "pareto", "per_view_estimates", "rgbx") if k not in doc and k in previous]
        for k in kept:
            doc[k] = previous[k]
        if kept:
            doc["meta"]["kept_from_previous_file"] = {"keys": kept, "previous_meta": previous.get("meta")}
    path.write_text(json.dumps(json_safe(doc), indent=1))

    if rows:
        print(format_table(rows, baseline_psnr))
        if baseline_psnr is not None:
            print(f"per-view estimates (baseline line): {baseline_psnr:.2f} dB")
        print("Pareto front (lower wall_s, higher albedo PSNR):")
        for r in front:
            print(f"  {r['wall_s']:7.1f} s  {r['albedo_psnr']:6.2f} dB  {row_name(r)}")
    if "rgbx" in doc:
        b = doc["rgbx"]
        print(f"RGB<->X bf16 vs fp32 on {b['view']} at {b['render_hw'][1]}x{b['render_hw'][0]} ({b['backend']}): "
              f"{b['note']}")
        print(f"{'t':>5s} {'latent rel L2':>14s} {'image rel L2':>13s} {'image PSNR dB':>14s}")
        for r in b["rows"]:
            print(f"{r['t']:5d} {r['latent_rel_l2']:14.3e} {r['image_rel_l2']:13.3e} "
                  f"{r['image_psnr_bf16_vs_fp32_db']:14.2f}")
        for kind, tm in b["timing"].items():
            print(f"{kind:6s}: fp32 {tm['fp32_median_s']:.3f} s, bf16 {tm['bf16_median_s']:.3f} s "
                  f"(bf16/fp32 {tm['bf16_over_fp32']:.2f}, saved {tm['saved_s']:+.3f} s per call; "
                  f"compile fp32 {tm['fp32_compile_s']:.1f} s, bf16 {tm['bf16_compile_s']:.1f} s)")
    print(f"wrote {out / 'speed_vs_error.json'} in {doc['meta']['total_s']:.0f} s", file=sys.stderr)
    if args.json:
        print(json.dumps(json_safe(doc)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
