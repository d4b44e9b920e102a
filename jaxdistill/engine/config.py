"""The distillation run's settings: absl flags, parsed once into a frozen `DistillConfig`.

Flags are declared by `define_flags(flag_values)` (the command calls it on the global FLAGS;
tests use their own `flags.FlagValues`), read by `config_from_flags`, which reports every bad
value at once, naming the flag, before any compute.
"""

from __future__ import annotations

import dataclasses
import os
import sys
from pathlib import Path
from typing import Any, Mapping

from absl import flags

from jaxdistill import MAP_NAMES
from jaxdistill.datasets.common import UV_POLICIES, ImportOptions
from jaxdistill.engine.distributed import address_problem
from jaxdistill.engine.photo import PHOTO_LOSSES, PHOTO_SCALES, PHOTO_SPACES
from jaxdistill.errors import InputError, ProblemList
from jaxdistill.render.gather_plan import SAMPLERS
from jaxdistill.io.view_rows import VIEW_DATA

PRIORS = ("auto", "rgbx", "views")
LOSS_SPACES = ("image", "latent")
ALIGN_MODES = ("none", "gain")
ANCHOR_MODES = ("auto", "estimates", "traced", "none")
ANNEALING = ("none", "linear", "sqrt")
T_WEIGHTINGS = ("none", "sds")
LATENT_MODES = ("mode", "sample")
LR_SCHEDULES = ("constant", "cosine")
PRIOR_DTYPES = ("float32", "bfloat16")
PRIOR_ATTENTION = ("chunked", "cudnn")
RGBX_DIR_ENV = "JAXDISTILL_RGBX_DIR"

# Flags that may change when a run is resumed; every other flag must match the checkpoint.
# (--max_unwrap_faces and --unwrap_time_limit only decide whether an unwrap is attempted, never its result.)
RESUMABLE_FLAGS = ("steps", "resume", "ckpt_every", "keep_checkpoints", "out_dir", "log_every", "eval_every", "renders",
                   "contact_views", "rgbx_dir", "convert_cache", "allow_outside_paths", "anchor", "estimate_steps",
                   "max_unwrap_faces", "unwrap_time_limit", "coordinator_address", "num_processes", "process_id",
                   "view_data", "prior_attention")      # the attention only changes bf16 rounding
# Flags handed to the dataset loaders for --scene=FORMAT:PATH (`ImportOptions` fields, the import
# command's flags of the same names).
IMPORT_FLAGS = ("mesh", "exposure", "uv", "max_views", "max_page_size", "max_unwrap_faces", "unwrap_time_limit")
_IMPORT = ImportOptions()


@dataclasses.dataclass(frozen=True)
class DistillConfig:
    """Every setting of one run (hashable; fields mirror the flags one to one)."""

    scene: str
    out_dir: str
    maps: tuple[str, ...] = MAP_NAMES
    prior: str = "auto"
    rgbx_dir: str | None = None
    convert_cache: str | None = None
    prior_dtype: str = "float32"
    prior_attention: str = "chunked"
    steps: int = 300
    lr: float = 0.01
    lr_schedule: str = "constant"
    weight_decay: float = 0.0
    t_min: float = 0.2
    t_max: float = 0.98
    anneal: str = "none"
    t_weighting: str = "none"
    w_t: float = 1.0
    w_i: float = 1.0
    loss_space: str = "image"
    latent: str = "mode"
    visibility_weighting: bool = True
    p_keep: float = 1.0
    reuse_steps: int = 1
    align: str = "none"
    align_strength: float = 0.01
    anchor: str = "auto"
    estimate_steps: int = 0                  # 0: auto, models.estimates.default_steps (10 shipped model, 50 otherwise)
    photo_weight: float = 0.0
    photo_size: int = 0
    photo_space: str = "log"
    photo_loss: str = "charbonnier"
    photo_scale: str = "auto"
    irradiance_smoothness: float = 0.0
    irradiance_sds_weight: float = 1.0
    albedo_smoothness: float = 0.0
    photo_noise_ref: float = 0.0
    render_size: int = 0
    texture_size: str = "auto"
    max_texture_size: int = 4096
    sampler: str = "bilinear"
    view_data: str = "auto"
    views_per_step: int = 8
    seed: int = 0
    ckpt_every: int = 0
    keep_checkpoints: int = 2
    resume: bool = False
    log_every: int = 10
    eval_every: int = 0
    renders: bool = True
    contact_views: int = 4
    allow_outside_paths: bool = False
    coordinator_address: str = ""           # engine/distributed.py: "" one process, HOST:PORT or auto several
    num_processes: int = 1
    process_id: int = -1
    view_shares: int = 0                    # steps' views drawn from this many shares (0: one per process)
    mesh: str | None = _IMPORT.mesh
    exposure: str = _IMPORT.exposure
    uv: str = _IMPORT.uv
    max_views: int = _IMPORT.max_views
    max_page_size: int = _IMPORT.max_page_size
    max_unwrap_faces: int = _IMPORT.max_unwrap_faces
    unwrap_time_limit: float = _IMPORT.unwrap_time_limit

    def as_dict(self) -> dict[str, Any]:
        """JSON-able {flag: value}, as recorded in checkpoints and metrics.json."""
        return {k: (list(v) if isinstance(v, tuple) else v) for k, v in dataclasses.asdict(self).items()}


_DEFAULTS = DistillConfig(scene="", out_dir="")


def define_flags(fv: flags.FlagValues = flags.FLAGS, *, main_module: bool = False) -> None:
    """Declares the run's flags on `fv` (defaults are DistillConfig's). With `main_module` they are
    declared as the running program's own (key) flags, so `--helpshort`/`--help` list them and
    `--helpfull` lists them before absl's."""
    d = _DEFAULTS
    where = {"flag_values": fv, "module_name": sys.argv[0]} if main_module else {"flag_values": fv}
    flags.DEFINE_string("scene", None, "scene.json or its folder ('bedroom' = the embedded bedroom), or a dataset "
                        "read directly as FORMAT:PATH with FORMAT fipt, iris, scannetpp, nerfstudio or colmap "
                        "(scripts/import_scene.py for its options)", **where)
    flags.DEFINE_string("out_dir", None, "output folder (maps, scene.glb, renders, metrics.json, checkpoints)",
                        **where)
    flags.DEFINE_list("maps", list(d.maps), f"maps to distil, any of {','.join(MAP_NAMES)}", **where)
    flags.DEFINE_enum("prior", d.prior, PRIORS, "rgbx: the RGB<->X model; views: the scene's per-view target "
                      "images; auto: rgbx when weights are found, else views", **where)
    flags.DEFINE_string("rgbx_dir", None, f"RGB<->X folder (diffusers format); default ${RGBX_DIR_ENV}",
                        **where)
    flags.DEFINE_string("convert_cache", None, "cache folder for converted RGB<->X weights", **where)
    flags.DEFINE_enum("prior_dtype", d.prior_dtype, PRIOR_DTYPES, "activation dtype of the frozen networks "
                      "(texels, loss and optimizer are always float32)", **where)
    flags.DEFINE_enum("prior_attention", d.prior_attention, PRIOR_ATTENTION, "the UNet's attention: chunked "
                      "(XLA, any device) or cudnn (cuDNN's fused kernel: an NVIDIA GPU and --prior_dtype=bfloat16; "
                      "1.09-1.12x a step on an H200, docs/benchmarks.md section 9b)", **where)
    flags.DEFINE_integer("steps", d.steps, "optimisation steps", **where)
    flags.DEFINE_float("lr", d.lr, "AdamW learning rate", **where)
    flags.DEFINE_enum("lr_schedule", d.lr_schedule, LR_SCHEDULES, "constant (thesis) or cosine decay to 0 over "
                      "--steps", **where)
    flags.DEFINE_float("weight_decay", d.weight_decay, "AdamW weight decay", **where)
    flags.DEFINE_float("t_min", d.t_min, "smallest diffusion time, fraction of 1000 steps", **where)
    flags.DEFINE_float("t_max", d.t_max, "largest diffusion time, fraction of 1000 steps", **where)
    flags.DEFINE_enum("anneal", d.anneal, ANNEALING, "shrink the upper end of the t range from t_max to t_min "
                      "over the run (linear or sqrt in the step)", **where)
    flags.DEFINE_enum("t_weighting", d.t_weighting, T_WEIGHTINGS, "w(t) per sample: none (1) or sds (1 - alpha_bar_t)",
                      **where)
    flags.DEFINE_float("w_t", d.w_t, "text guidance weight (eq. 4.2)", **where)
    flags.DEFINE_float("w_i", d.w_i, "image guidance weight (eq. 4.2)", **where)
    flags.DEFINE_enum("loss_space", d.loss_space, LOSS_SPACES, "image: MSE of renders (thesis default); latent: "
                      "MSE of VAE latents (the thesis's ablation; backpropagates through the encoder)", **where)
    flags.DEFINE_enum("latent", d.latent, LATENT_MODES, "VAE encoding of renders: the mode or a sample",
                      **where)
    flags.DEFINE_bool("visibility_weighting", d.visibility_weighting, "weight pixels by 1 / (2 clip(V, 1, 6))",
                      **where)
    flags.DEFINE_float("p_keep", d.p_keep, "image-space dropout: probability a pixel counts in a step", **where)
    flags.DEFINE_enum("align", d.align, ALIGN_MODES, "photometric alignment across views: none, or gain (a "
                      "per-view, per-channel gain on the albedo and irradiance targets, learned with the texels, "
                      "geometric mean 1)", **where)
    flags.DEFINE_float("align_strength", d.align_strength, "ridge on the per-view log-gains, per unit of pixel "
                       "weight (--align=gain)", **where)
    flags.DEFINE_integer("estimate_steps", d.estimate_steps, "rgbx prior: DDIM steps of the model's own per-view "
                         "estimates after the loop, the baseline the run is scored against and (--anchor=auto, "
                         "unless the photos' traced light is used) the overall scale it is anchored to; 0 (auto): 10 with the shipped model (chosen on the validation "
                         "rooms), 50 (RGB<->X's demo) with weights you give", **where)
    flags.DEFINE_enum("anchor", d.anchor, ANCHOR_MODES, "overall scale of the distilled albedo and irradiance: "
                      "estimates (after the loop, one gain per channel sets the renders' sRGB mean over the views to "
                      "the per-view estimates': the model's own with the rgbx prior, the scene's targets with views), "
                      "traced (albedo x g, irradiance / g: g from the irradiance traced through the mesh from the HDR "
                      "photos' own radiance), none (as distilled), or auto: with the rgbx prior traced where the HDR "
                      "photos show what the trace's escaping rays meet (a background, or a closed room) and its gain "
                      "puts at most a tenth of the albedo above 1, else estimates; none with views (a fusion "
                      "already has its targets' scale)", **where)
    flags.DEFINE_float("photo_weight", d.photo_weight, "weight of the re-rendering term: every view's photo rendered "
                       "back from the texels as albedo x irradiance and compared with the photo (0: off, the "
                       "prior alone)", **where)
    flags.DEFINE_integer("photo_size", d.photo_size, "longer side in pixels at which the photos are re-rendered; "
                         "0 = the photos' own size", **where)
    flags.DEFINE_enum("photo_space", d.photo_space, PHOTO_SPACES, "where photo and re-rendering are compared: log "
                      "(relative errors) or linear", **where)
    flags.DEFINE_enum("photo_loss", d.photo_loss, PHOTO_LOSSES, "penalty of the re-rendering residual: charbonnier "
                      "(robust to highlights and noise) or l2", **where)
    flags.DEFINE_enum("photo_scale", d.photo_scale, PHOTO_SCALES, "the photos' scale against albedo x irradiance: "
                      "fitted per batch, per view (auto-exposure), per view and colour channel (view_rgb: "
                      "auto-exposure and white balance) or none (irradiance in the exposed photo's units); auto: "
                      "view_rgb for LDR photos (PNG/JPG), batch for HDR", **where)
    flags.DEFINE_float("irradiance_smoothness", d.irradiance_smoothness, "weight of a penalty on log-irradiance "
                       "differences between neighbouring pixels of the re-rendered photos (with --photo_weight > 0)",
                       **where)
    flags.DEFINE_float("irradiance_sds_weight", d.irradiance_sds_weight, "weight of the irradiance map's SDS term "
                       "(1: as every map; lower leaves more of the albedo/irradiance split to the photos and "
                       "--irradiance_smoothness)", **where)
    flags.DEFINE_float("albedo_smoothness", d.albedo_smoothness, "weight of a penalty on log-albedo differences "
                       "between neighbouring pixels of the re-rendered photos, weighted by how little the photo's "
                       "colour (chromaticity) changes there: shadow and sun-patch edges are pushed out of the "
                       "albedo (colour Retinex); part of the re-rendering term", **where)
    flags.DEFINE_float("photo_noise_ref", d.photo_noise_ref, "noise (in log units) above which a view's photo "
                       "weighs less in the re-rendering term: weight min(1, (ref / sigma)^2), sigma the photo's own "
                       "noise estimated from neighbouring pixels; 0: every photo weighs 1", **where)
    flags.DEFINE_integer("reuse_steps", d.reuse_steps, "rgbx prior: take K AdamW steps on the same views towards "
                         "one x_pred before the prior runs again (1 = a new x_pred every step, the thesis; K > 1 costs "
                         "1/K of the prior per step, like Instruct-NeRF2NeRF's iterative dataset update)", **where)
    flags.DEFINE_integer("render_size", d.render_size, "longer side of the renders in pixels; 0 = the photos' size",
                         **where)
    flags.DEFINE_string("texture_size", d.texture_size, "page side (power of two) or 'auto'", **where)
    flags.DEFINE_integer("max_texture_size", d.max_texture_size, "cap for --texture_size=auto", **where)
    flags.DEFINE_enum("sampler", d.sampler, SAMPLERS, "texture sampler", **where)
    flags.DEFINE_enum("view_data", d.view_data, VIEW_DATA, "where the per-view arrays are held (fragments, gather "
                      "plans, pixel weights, the views prior's targets, the re-rendering term's photos; about 20-35 "
                      "values a pixel): memory, or disk (files under the cache read a view or a batch at a time, so "
                      "memory does not grow with the view count); auto: disk when they would take more than 1 GiB "
                      "(about 10 views of 1752x1168). Never changes a result", **where)
    flags.DEFINE_integer("views_per_step", d.views_per_step, "views per step (split over devices)", **where)
    flags.DEFINE_integer("seed", d.seed, "seed of everything random in the run", **where)
    flags.DEFINE_integer("ckpt_every", d.ckpt_every, "checkpoint every N steps (0: only at the end)", **where)
    flags.DEFINE_integer("keep_checkpoints", d.keep_checkpoints, "keep the newest N checkpoints (0: keep all); "
                         "a damaged newest one falls back to the one before, so keep >= 2 to resume safely", **where)
    flags.DEFINE_bool("resume", d.resume, "continue from the latest complete checkpoint in out_dir", **where)
    flags.DEFINE_integer("log_every", d.log_every, "fetch the step metrics (loss history, progress bar, NaN check) every N steps", **where)
    flags.DEFINE_integer("eval_every", d.eval_every, "evaluate against GT every N steps (0: only at the end)",
                         **where)
    flags.DEFINE_bool("renders", d.renders, "write renders of every view for every map", **where)
    flags.DEFINE_integer("contact_views", d.contact_views, "views in the contact sheet", **where)
    flags.DEFINE_bool("allow_outside_paths", d.allow_outside_paths, "let scene files (scene.json, gt.json, "
                      "scene configs) name files outside their folder (../, absolute paths); off: refused, for "
                      "scenes from elsewhere", **where)
    flags.DEFINE_string("coordinator_address", d.coordinator_address, "more than one process (hosts or GPUs): "
                        "HOST:PORT of process 0, which every process of the run is given, or auto (SLURM, Open MPI, "
                        "Kubernetes: JAX reads the rest from the environment); empty: one process", **where)
    flags.DEFINE_integer("num_processes", d.num_processes, "processes of the run, with --coordinator_address=HOST:PORT",
                         **where)
    flags.DEFINE_integer("process_id", d.process_id, "this process's rank in [0, --num_processes), with "
                         "--coordinator_address=HOST:PORT; process 0 writes the outputs", **where)
    flags.DEFINE_integer("view_shares", d.view_shares, "split the views into this many shares (view i in share "
                         "i mod N) and draw each step's views evenly from them; with several processes each process "
                         "holds one share (0: one share per process). A one-process run with --view_shares=N steps "
                         "through the views an N-process run does (and resumes its checkpoint)", **where)
    define_dataset_flags(fv, main_module=main_module)


def define_dataset_flags(fv: flags.FlagValues = flags.FLAGS, *, main_module: bool = False) -> None:
    """Declares the dataset flags (IMPORT_FLAGS: the loaders' options for --scene=FORMAT:PATH, as
    `jaxdistill import` spells them) on `fv`, defaults ImportOptions'. The main job, estimate and
    precompute declare them with this; `dataset_options` reads them back. `main_module` as in
    `define_flags`."""
    d = _IMPORT
    where = {"flag_values": fv, "module_name": sys.argv[0]} if main_module else {"flag_values": fv}
    dataset = "--scene=FORMAT:PATH (a dataset read directly): "
    flags.DEFINE_string("mesh", d.mesh, dataset + "mesh file or scene config .json replacing the dataset's (nerfstudio "
                        "and colmap have none of their own)", **where)
    flags.DEFINE_string("exposure", d.exposure, dataset + "'auto' (HDR: Hypersim rule, LDR: 0) or stops", **where)
    flags.DEFINE_enum("uv", d.uv, UV_POLICIES, dataset + "auto: unwrap objects whose UVs are unusable; keep: refuse "
                      "them; unwrap: all", **where)
    flags.DEFINE_integer("max_views", d.max_views, "0 = all views, else that many evenly spread (any --scene, "
                         "a jaxdistill scene too: a quick run on a subset)", **where)
    flags.DEFINE_integer("max_page_size", d.max_page_size, dataset + "largest texture page an unwrap is packed for",
                         **where)
    flags.DEFINE_integer("max_unwrap_faces", d.max_unwrap_faces, dataset + "objects with more faces are refused, not "
                         "unwrapped", **where)
    flags.DEFINE_float("unwrap_time_limit", d.unwrap_time_limit, dataset + "seconds; objects whose unwrap would take "
                       "longer are refused", **where)


def config_from_flags(fv: flags.FlagValues = flags.FLAGS) -> DistillConfig:
    """The frozen config; InputError listing every invalid flag (by name) at once."""
    values = {f.name: fv[f.name].value for f in dataclasses.fields(DistillConfig)}
    values["maps"] = tuple(values["maps"] or ())
    return validate(DistillConfig(**values))


def validate(config: DistillConfig) -> DistillConfig:
    """`config` if every value is usable; InputError naming each bad flag otherwise."""
    p = ProblemList()
    c = config

    def bad(flag: str, message: str) -> None:
        p.add("flags", f"--{flag}", message)

    for name in ("scene", "out_dir"):
        if not getattr(c, name):
            bad(name, "is required")
    out_problem = out_dir_problem(c.out_dir) if c.out_dir else None
    if out_problem:
        bad("out_dir", out_problem)
    unknown = [m for m in c.maps if m not in MAP_NAMES]
    if unknown or not c.maps:
        bad("maps", f"unknown {unknown}; choose from {','.join(MAP_NAMES)}" if unknown else "names no map")
    if len(set(c.maps)) != len(c.maps):
        bad("maps", f"lists a map twice: {','.join(c.maps)}")
    if c.steps < 1:
        bad("steps", f"must be >= 1, got {c.steps}")
    if not c.lr > 0:
        bad("lr", f"must be > 0, got {c.lr}")
    if c.weight_decay < 0:
        bad("weight_decay", f"must be >= 0, got {c.weight_decay}")
    if not 0.0 <= c.t_min <= c.t_max <= 1.0:
        bad("t_min/--t_max", f"need 0 <= t_min <= t_max <= 1, got {c.t_min} and {c.t_max}")
    if not 0.0 < c.p_keep <= 1.0:
        bad("p_keep", f"must be in (0, 1], got {c.p_keep}")
    if c.render_size < 0 or (c.render_size and c.render_size < 8):
        bad("render_size", f"must be 0 (photo size) or >= 8, got {c.render_size}")
    size = c.texture_size
    if size != "auto" and not (size.isdigit() and int(size) > 0 and int(size) & (int(size) - 1) == 0):
        bad("texture_size", f"must be 'auto' or a power of two, got {size!r}")
    if c.max_texture_size < 8 or c.max_texture_size & (c.max_texture_size - 1):
        bad("max_texture_size", f"must be a power of two >= 8, got {c.max_texture_size}")
    if c.views_per_step < 1:
        bad("views_per_step", f"must be >= 1, got {c.views_per_step}")
    if c.view_shares < 0:
        bad("view_shares", f"must be >= 0 (0: one share per process), got {c.view_shares}")
    elif c.view_shares and c.views_per_step % c.view_shares:
        bad("view_shares", f"{c.view_shares} shares do not split --views_per_step={c.views_per_step} evenly; use a "
            f"divisor of {c.views_per_step}")
    elif c.view_shares and c.coordinator_address and c.coordinator_address != "auto" and \
            c.view_shares != c.num_processes:
        bad("view_shares", f"is {c.view_shares}, but each of the --num_processes={c.num_processes} processes holds "
            "one share; leave it at 0")
    for name in ("ckpt_every", "keep_checkpoints", "log_every", "eval_every", "contact_views"):
        if getattr(c, name) < 0:
            bad(name, f"must be >= 0, got {getattr(c, name)}")
    if c.log_every == 0:
        bad("log_every", "must be >= 1")
    if c.estimate_steps < 0:
        bad("estimate_steps", f"must be >= 1, or 0 for auto, got {c.estimate_steps}")
    if c.anchor not in ANCHOR_MODES:
        bad("anchor", f"must be one of {', '.join(ANCHOR_MODES)}, got {c.anchor!r}")
    if c.view_data not in VIEW_DATA:
        bad("view_data", f"must be one of {', '.join(VIEW_DATA)}, got {c.view_data!r}")
    if c.align_strength < 0:
        bad("align_strength", f"must be >= 0, got {c.align_strength}")
    if c.align != "none" and c.loss_space == "latent":
        bad("align", "per-view gains scale images, but --loss_space=latent compares latents; use --loss_space=image")
    if c.align != "none" and not {"albedo", "irradiance"} & set(c.maps):
        bad("align", "aligns the albedo and irradiance maps, and --maps has neither; use --align=none")
    if not c.photo_weight >= 0:
        bad("photo_weight", f"must be >= 0, got {c.photo_weight}")
    elif c.photo_weight > 0 and not {"albedo", "irradiance"} <= set(c.maps):
        missing = " and ".join(m for m in ("albedo", "irradiance") if m not in c.maps)
        bad("photo_weight", f"re-renders the photos as albedo x irradiance, and --maps lacks {missing}; add it, or "
            "use --photo_weight=0")
    elif c.photo_weight > 0 and c.loss_space == "latent":
        bad("photo_weight", "the re-rendering term is an image-space loss; use --loss_space=image")
    if c.photo_size < 0 or (c.photo_size and c.photo_size < 8):
        bad("photo_size", f"must be 0 (the photos' size) or >= 8, got {c.photo_size}")
    if not c.irradiance_smoothness >= 0:
        bad("irradiance_smoothness", f"must be >= 0, got {c.irradiance_smoothness}")
    for flag, message in address_problem(c.coordinator_address, c.num_processes, c.process_id):
        bad(flag, message)
    if not c.photo_noise_ref >= 0:
        bad("photo_noise_ref", f"must be >= 0, got {c.photo_noise_ref}")
    # the smoothness terms are terms of their own, refused without the re-rendering term; --photo_noise_ref,
    # like --photo_loss, only shapes that term (moot without it: --photo_weight=0 turns a config's term off)
    for name in ("irradiance_smoothness", "albedo_smoothness"):
        if getattr(c, name) > 0 and c.photo_weight == 0:
            bad(name, "is part of the re-rendering term, which --photo_weight=0 turns off; give --photo_weight > 0 "
                f"or --{name}=0")
    if not c.albedo_smoothness >= 0:
        bad("albedo_smoothness", f"must be >= 0, got {c.albedo_smoothness}")
    if not c.irradiance_sds_weight >= 0:
        bad("irradiance_sds_weight", f"must be >= 0, got {c.irradiance_sds_weight}")
    if c.reuse_steps < 1:
        bad("reuse_steps", f"must be >= 1, got {c.reuse_steps}")
    elif c.reuse_steps > 1 and c.prior == "views":
        bad("reuse_steps", "the views prior's targets never change, so there is nothing to reuse; use --reuse_steps=1 "
            "(or --prior=rgbx)")
    if c.loss_space == "latent" and c.prior == "views":
        bad("loss_space", "latent needs the rgbx prior (the views prior has no VAE); use --loss_space=image")
    if c.prior == "rgbx" and c.render_size and c.render_size % 8:
        bad("render_size", f"must be a multiple of 8 for the rgbx prior's VAE, got {c.render_size}")
    if c.prior_attention == "cudnn" and c.prior_dtype != "bfloat16":
        bad("prior_attention", f"cudnn needs --prior_dtype=bfloat16 (cuDNN's fused attention has no float32 kernel), "
            f"got --prior_dtype={c.prior_dtype}")
    if c.prior_attention == "cudnn" and c.prior == "views":
        bad("prior_attention", "the views prior runs no network, so cudnn would change nothing; use "
            "--prior_attention=chunked (or --prior=rgbx)")
    # the backend is checked in loop.check_before_compute: asking JAX for it here would start its
    # backends before jax.distributed.initialize, which then refuses to run
    if c.w_t < 0 or c.w_i < 0:
        bad("w_t/--w_i", f"guidance weights must be >= 0, got {c.w_t} and {c.w_i}")
    import_option_problems(c, p)
    p.raise_if_any()
    return config


def import_option_problems(c: DistillConfig, p: ProblemList) -> None:
    """`dataset_option_problems` of a run's config."""
    dataset_option_problems(c.scene, c.as_dict(), p)


def dataset_option_problems(scene: str | None, values: Mapping[str, Any], p: ProblemList) -> None:
    """Adds a problem for each bad dataset flag (IMPORT_FLAGS) in `values` ({flag: value}), and for
    any of them set while `scene` (--scene) is a scene folder, which names its own mesh and images
    (the flag would do nothing); --max_views applies to every scene (`datasets.open_scene`)."""
    from jaxdistill.datasets import split_spec

    try:
        import_options(values)
    except InputError as err:
        p.problems.extend(err.problems)
    given = [f"--{name}" for name in IMPORT_FLAGS
             if name != "max_views" and values.get(name, getattr(_IMPORT, name)) != getattr(_IMPORT, name)]
    if given and scene and split_spec(scene)[0] == "scene":
        p.add("flags", given[0], f"{', '.join(given)} {'applies' if len(given) == 1 else 'apply'} to --scene=FORMAT:PATH (a dataset read directly), and "
              f"--scene={scene} is a scene folder, which names its own mesh and images; leave them out here, or "
              "import the dataset again with them (jaxdistill import)")


def dataset_options(scene: str | None, fv: flags.FlagValues) -> ImportOptions:
    """The loader options of a command's dataset flags (`define_dataset_flags`) and its
    --allow_outside_paths on `fv`, for `scene` (--scene); InputError naming each bad flag."""
    values = {name: fv[name].value for name in (*IMPORT_FLAGS, "allow_outside_paths")}
    p = ProblemList()
    dataset_option_problems(scene, values, p)
    p.raise_if_any()
    return import_options(values)


def import_options(values) -> ImportOptions:
    """The dataset loaders' options of a run's flags (a DistillConfig's `as_dict()`, or the config a
    checkpoint or metrics.json recorded: flags it lacks keep their defaults)."""
    kept = {name: values[name] for name in IMPORT_FLAGS if values.get(name) is not None}
    return ImportOptions(**kept, allow_outside_paths=bool(values.get("allow_outside_paths")))


def out_dir_problem(out_dir: str) -> str | None:
    """Why the run could not write `out_dir` (an existing file, under a file, not writable), or
    None. Checks the folder, or the nearest existing parent it would be created in; creates nothing."""
    path = Path(out_dir).expanduser().absolute()
    existing = path
    try:
        while not existing.exists():
            existing = existing.parent
    except OSError as err:                     # a parent that cannot be searched
        return f"{path} cannot be checked ({err.strerror}: {err.filename}); choose a folder you can write"
    if not existing.is_dir():
        if existing == path:
            return f"{path} is an existing file, not a folder; choose a folder (existing or new)"
        return f"{existing} is a file, so {path} cannot be created in it; choose another folder"
    if not os.access(existing, os.W_OK | os.X_OK):
        where = "is" if existing == path else f"would be created in {existing}, which is"
        return f"{path} {where} not writable (read-only folder or file system); choose a writable folder"
    return None


def check_views_per_step(config: DistillConfig, num_views: int, scene: str) -> None:
    """InputError when a step would draw more views than the scene has (it would repeat views):
    called as soon as the scene is read, before any ray casting. (With view shares, a step draws
    views_per_step / N from each; the smallest share holds num_views // N, never fewer.)"""
    if config.views_per_step > num_views:
        raise InputError.single("flags", "--views_per_step", (
            f"{config.views_per_step} is more than the {num_views} views of {scene}; a step never repeats a "
            f"view, so use --views_per_step <= {num_views}"))


def resumable_flags(config: DistillConfig) -> tuple[str, ...]:
    """Flags a resume may change. --steps only when nothing depends on the run's length (a cosine
    learning rate or t annealing does: changing --steps would change the steps already taken)."""
    if config.lr_schedule != "constant" or config.anneal != "none":
        return tuple(f for f in RESUMABLE_FLAGS if f != "steps")
    return RESUMABLE_FLAGS


def rgbx_dir(config: DistillConfig) -> str | None:
    """The RGB<->X folder to use: --rgbx_dir, else $JAXDISTILL_RGBX_DIR, else None."""
    return config.rgbx_dir or os.environ.get(RGBX_DIR_ENV) or None
