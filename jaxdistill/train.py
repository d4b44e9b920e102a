"""The distillation run: setup, the step loop with checkpoints, and the outputs.

`run(config)` is what `python -m jaxdistill.main` calls. The loop is thin: view ids for a step
are a function of (seed, step); the host assembles that batch while the device runs the
previous step (JAX dispatch is asynchronous); metrics are fetched every --log_every steps.
"""

from __future__ import annotations

import dataclasses
import json
import math
from concurrent.futures import ThreadPoolExecutor
import resource
import time
from pathlib import Path

import jax
import numpy as np
from absl import logging
from tqdm.auto import tqdm

from jaxdistill import (MAP_NAMES, align as align_lib, checkpoint, evaluation, export, imageio, metrics,
                        model_estimates, run_files)
from jaxdistill.config import DistillConfig, check_views_per_step, resumable_flags
from jaxdistill.distill import (StepSettings, data_mesh, init_state, initial_align, initial_reused, jit_step,
                                make_optimizer, make_step)
from jaxdistill.errors import InputError
from jaxdistill.models.shipped import model_info
from jaxdistill.problem import Problem, build_problem, choose_prior
from jaxdistill.render.gather_plan import GatherPlan, build_gather_plans
from jaxdistill.cameras import rgbx_camera_rotation
from jaxdistill.render.sampler import expand
from jaxdistill.render.visibility import texel_view_statistics
from jaxdistill.summary import summary_table
from jaxdistill.view_images import resize


class NonFiniteLoss(RuntimeError):
    """The loss or gradient became NaN/inf; the last good state was checkpointed."""


def step_settings(config: DistillConfig, problem: Problem) -> StepSettings:
    num_train = 1000
    if problem.choice.kind == "rgbx":
        num_train = problem.prior.scheduler.num_train_timesteps
    return StepSettings(channels=problem.channels, height=problem.height, width=problem.width,
                        total_steps=config.steps, t_min=config.t_min, t_max=config.t_max, anneal=config.anneal,
                        t_weighting=config.t_weighting, p_keep=config.p_keep, num_train_timesteps=num_train,
                        reuse_steps=config.reuse_steps, align=config.align, align_strength=config.align_strength)


def batch_views(problem: Problem, config: DistillConfig, step: int) -> np.ndarray:
    """The views of `step`: a function of (seed, step // reuse_steps), so the steps that reuse one
    x_pred see the views it was computed for, and a resumed run samples the same."""
    return problem.view_ids(step // config.reuse_steps, config.views_per_step, config.seed)


def _history_path(out: Path) -> Path:
    return out / "checkpoints" / "history.json"


# flags added after checkpoints were first written, at the values that keep the earlier
# behaviour: a checkpoint that does not record them resumes when the run leaves them so
ADDED_FLAG_DEFAULTS = {"reuse_steps": 1, "align": "none", "align_strength": DistillConfig.align_strength}


def _recorded_config(config: DistillConfig, prior_kind: str) -> dict:
    """The flags saved with a checkpoint, plus the prior --prior=auto resolved to."""
    return {**config.as_dict(), "prior_kind": prior_kind}


def _save(store, state, recorded: dict, history: dict, out: Path) -> None:
    step = int(jax.device_get(state.step))
    store.save(step, state, recorded)
    _history_path(out).write_text(json.dumps(history))


def _check_before_compute(config: DistillConfig, out: Path, choice) -> int | None:
    """Flag problems found without any compute: the RGB<->X folder (layout, in_channels, every
    weights file's header), device split, --resume (the checkpoint must read back), an existing
    run. Returns the checkpoint step to resume from (None for a fresh run)."""
    if choice.kind == "rgbx":
        from jaxdistill.models import convert

        convert.check_rgbx_folder(choice.folder, "--rgbx_dir")
    devices = jax.devices()
    if config.views_per_step % len(devices):
        raise InputError.single("flags", "--views_per_step", f"{config.views_per_step} does not split over "
                                f"{len(devices)} devices; use a multiple of {len(devices)}")
    if choice.kind == "views" and config.loss_space == "latent":
        raise InputError.single("flags", "--loss_space", "latent needs the rgbx prior, but the views prior was "
                                f"chosen ({choice.reason}); use --loss_space=image or give --rgbx_dir")
    directory = out / "checkpoints"
    if not config.resume:
        if directory.exists():
            steps = checkpoint.CheckpointStore(directory).latest_step()
            if steps is not None:
                raise InputError.single("flags", "--out_dir", f"{out} already holds a run (checkpoint at step {steps})"
                                        "; pass --resume to continue it, or choose another --out_dir")
        return None
    with checkpoint.CheckpointStore(directory) as store:
        latest = _readable_checkpoint(store)
        if latest is None:
            raise InputError.single("flags", "--resume", f"no complete checkpoint in {directory}; "
                                    "run without --resume to start")
        checkpoint.check_compatible(store.read_config(latest), _recorded_config(config, choice.kind), directory,
                                    ignore=resumable_flags(config), defaults=ADDED_FLAG_DEFAULTS)
    if latest > config.steps:
        raise InputError.single("flags", "--steps", f"{config.steps} is below the checkpoint's step {latest} in "
                                f"{directory}; give --steps >= {latest}")
    return latest


def _readable_checkpoint(store: checkpoint.CheckpointStore) -> int | None:
    """The newest complete checkpoint whose files read back, or None when there is none. Newer
    ones that do not read (damaged after their commit) are moved aside with a warning; when
    none reads, InputError naming each step folder and how to start fresh."""
    steps = store.all_steps()
    damaged = []
    for step in reversed(steps):
        reason = store.damage(step)
        if reason is None:
            for bad, why in damaged:
                moved = store.set_aside(bad)
                logging.warning("%s: checkpoint of step %d is damaged (%s); moved it to %s and resuming from the "
                                "previous committed step %d", store.directory / str(bad), bad, why, moved, step)
            return step
        damaged.append((step, reason))
    if damaged:
        raise InputError([(str(store.directory / str(step)), f"step {step}", f"checkpoint is damaged ({why})")
                          for step, why in damaged] + [
            (str(store.directory), "--resume", "no committed checkpoint reads back, so there is nothing to resume; to "
             f"start fresh, move {store.directory} away (or choose another --out_dir) and run without --resume")])
    return None


def run(config: DistillConfig, *, progress: bool = True) -> dict:
    """Runs the distillation described by `config`; returns the metrics written to metrics.json."""
    wall_start = time.perf_counter()
    out = Path(config.out_dir)
    latest = _check_before_compute(config, out, choose_prior(config))
    problem = build_problem(config, check_scene=lambda scene: (
        check_views_per_step(config, len(scene.views), config.scene), evaluation.read_ground_truth(scene)))
    recorded = _recorded_config(config, problem.choice.kind)
    banner = f"PRIOR: {problem.choice.kind.upper()} -- {problem.choice.reason}"
    logging.warning("%s\n%s\n%s", "=" * len(banner), banner, "=" * len(banner))

    devices = jax.devices()
    mesh = data_mesh(devices)
    optimizer = make_optimizer(config.lr, config.weight_decay, config.lr_schedule, config.steps)
    settings = step_settings(config, problem)
    first = problem.batch(batch_views(problem, config, 0))
    texels = problem.initial_texels()
    align_optimizer = (make_optimizer(config.lr, 0.0, config.lr_schedule, config.steps) if config.align == "gain"
                       else None)
    state = init_state(texels, optimizer, config.seed,
                       initial_reused(problem.prior, settings, texels, first, problem.frozen),
                       initial_align(problem.num_views, problem.channels, align_optimizer))
    history = {"step": [], "loss": [], "eval_step": [], "albedo_psnr": []}

    out.mkdir(parents=True, exist_ok=True)
    trust = texel_trust(problem)                   # once: the texel space file and the exported pages
    run_files.write_texel_space(out, problem.space, trust, problem.channels.maps, _json_safe(recorded))
    store = checkpoint.CheckpointStore(out / "checkpoints", max_to_keep=config.keep_checkpoints or None)
    if latest is not None:
        state, _ = store.restore(latest, state)
        if _history_path(out).is_file():
            history = json.loads(_history_path(out).read_text())
            for key, at in (("loss", "step"), ("albedo_psnr", "eval_step")):
                keep = [i for i, s in enumerate(history[at]) if s <= latest]
                history[key] = [history[key][i] for i in keep]
                history[at] = [history[at][i] for i in keep]
        logging.info("resumed from step %d in %s", latest, out / "checkpoints")

    eval_context = evaluation_context(config, problem)
    step_fn, traces = jit_step(make_step(problem.prior, settings, optimizer, align_optimizer), mesh, first, state,
                               problem.frozen)
    replicated = jax.sharding.NamedSharding(mesh, jax.sharding.PartitionSpec())
    by_view = jax.sharding.NamedSharding(mesh, jax.sharding.PartitionSpec("data"))
    state = jax.device_put(state, replicated)
    frozen = jax.device_put(problem.frozen, replicated)

    start_step = int(jax.device_get(state.step))
    pending = []           # (step, metrics on device) not yet fetched
    stopped_by = None
    loop_start = time.perf_counter()
    with checkpoint.StopSignals() as stop, tqdm(total=config.steps, initial=start_step, unit="step", desc="distil",
                                                dynamic_ncols=True, disable=not progress,
                                                smoothing=0) as bar:   # steps run asynchronously: average rate
        for step in range(start_step, config.steps):
            batch = jax.device_put(problem.batch(batch_views(problem, config, step)), by_view)
            state, step_metrics = step_fn(state, batch, frozen)
            pending.append((step, step_metrics))
            done = step + 1
            if done % config.log_every == 0 or done == config.steps or stop.requested:
                _drain(pending, history, bar, state, store, recorded, out)
            traces.check(1)
            bar.update()
            if config.eval_every and done % config.eval_every == 0 and eval_context.gt_maps is not None:
                _drain(pending, history, bar, state, store, recorded, out)     # the bar shows this step's loss
                history["eval_step"].append(done)
                history["albedo_psnr"].append(quick_psnr(state, problem, eval_context))
                _show(bar, history)
            if config.ckpt_every and done % config.ckpt_every == 0 and done < config.steps:
                _drain(pending, history, bar, state, store, recorded, out)     # history matches the checkpoint
                _save(store, state, recorded, history, out)
            if stop.requested:
                stopped_by = stop.signal_name
                break
        _drain(pending, history, bar, state, store, recorded, out)
    loop_seconds = time.perf_counter() - loop_start
    _save(store, state, recorded, history, out)
    store.close()
    if stopped_by:
        logging.warning("stopped by %s at step %d; checkpoint saved. Continue with the same flags and --resume. "
                        "Exiting with status %d (128 + signal number): the run did not finish.",
                        stopped_by, int(jax.device_get(state.step)), stop.exit_status)
        return {"stopped_by": stopped_by, "step": int(jax.device_get(state.step)), "exit_status": stop.exit_status}

    texels = np.asarray(jax.device_get(state.texels))
    baseline = per_view_baseline(config, problem, [f.shape for f in eval_context.fragments])
    texels, anchor = anchor_to_baseline(config, problem, texels, eval_context, baseline)
    summary = write_outputs(config, problem, texels, history, eval_context, trust, baseline)
    steps_run = config.steps - start_step
    summary.update({
        "steps": config.steps, "steps_this_run": steps_run, "resumed_from": start_step if config.resume else None,
        "wall_seconds": time.perf_counter() - wall_start, "loop_seconds": loop_seconds,
        "seconds_per_step": loop_seconds / max(steps_run, 1), "setup_timings": problem.timings,
        "prior": {"kind": problem.choice.kind, "reason": problem.choice.reason, "folder": problem.choice.folder,
                  "model": model_info(problem.choice.folder) if problem.choice.folder else None},
        "device": {"backend": jax.default_backend(), "devices": [str(d) for d in devices],
                   "kind": devices[0].device_kind},
        "peak_host_memory_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
        "peak_device_memory_mb": _peak_device_memory_mb(devices),
        "parameters": {"texels": problem.space.num_texels, "channels": problem.channels.num_channels,
                       "page_sizes": list(problem.space.layout.page_sizes)},
        "traces": traces.traces, "config": recorded, "anchor": anchor,
    })
    if state.align is not None:          # the learned per-view gains (geometric mean 1 per channel)
        gains = np.exp(np.asarray(jax.device_get(align_lib.centred(state.align["log_gains"]))))
        summary["align"] = {"maps": list(align_lib.aligned_maps(problem.channels)),
                            "gains": {v.name: g.round(4).tolist() for v, g in zip(problem.scene.views, gains)}}
    (out / "metrics.json").write_text(json.dumps(_json_safe(summary), indent=1))
    logging.info("wrote %s", out / "metrics.json")
    print(summary_table(_json_safe(summary), out), flush=True)
    return summary


def _drain(pending: list, history: dict, bar, state, store, recorded: dict, out: Path) -> None:
    """Fetches pending step metrics into the history; stops the run on a non-finite step."""
    fetched = jax.device_get([m for _, m in pending])
    for (step, _), values in zip(pending, fetched):
        if not values["finite"]:
            _save(store, state, recorded, history, out)
            store.close()
            raise NonFiniteLoss(
                f"the loss or its gradient became NaN/inf at step {step}; the state before that step is saved in "
                f"{out / 'checkpoints'} (step {step}). Try a smaller --lr, --prior_dtype=float32, or check the "
                "photos and targets for NaN/inf; resume with --resume.")
        history["step"].append(step + 1)
        history["loss"].append(float(values["loss"]))
    pending.clear()
    if fetched:
        bar.t_mean = float(fetched[-1]["t_mean"])
        _show(bar, history)


def _show(bar, history: dict) -> None:
    """The progress bar's postfix: last loss and mean t, and the last eval's albedo PSNR (--eval_every)."""
    shown = {}
    if history["loss"]:
        shown["loss"] = f"{history['loss'][-1]:.4g}"
    if getattr(bar, "t_mean", None) is not None:
        shown["t"] = f"{bar.t_mean:.0f}"
    if history["albedo_psnr"] and math.isfinite(history["albedo_psnr"][-1]):
        shown["albedo_psnr"] = f"{history['albedo_psnr'][-1]:.2f}dB@{history['eval_step'][-1]}"
    bar.set_postfix(shown, refresh=False)


class EvalContext:
    """Native-resolution fragments, cameras, GT maps and masks, built once for evaluation."""

    def __init__(self, gt, fragments, cameras, gt_maps, masks, plan, seams):
        self.gt, self.fragments, self.cameras, self.gt_maps, self.masks = gt, fragments, cameras, gt_maps, masks
        self.plan, self.seams = plan, seams


def evaluation_context(config: DistillConfig, problem: Problem) -> EvalContext:
    """What evaluating at the photos' native size needs, built once: plans at native size (the
    training plans when the run renders at native size), GT maps and masks (None without GT)."""
    scene = problem.scene
    cameras = [v.camera for v in scene.views]
    native = all((c.height, c.width) == (problem.height, problem.width) for c in cameras)
    frags = problem.native_fragments
    if native:
        plan = training_plan(problem)
    else:
        plan = build_gather_plans(frags, problem.space, config.sampler)
    gt, gt_maps = evaluation.view_ground_truth(scene, frags)
    masks = evaluation.evaluation_masks(gt, scene, frags)
    owner = evaluation.dominant_views(problem.plan_index, problem.plan_weight, problem.space.pyramid_size)
    seams = [metrics.seam_pairs(region, f.object_id, m)
             for region, f, m in zip(evaluation.seam_regions(plan, frags, owner), frags, masks)]
    return EvalContext(gt, frags, cameras, gt_maps, masks, plan, seams)


def quick_psnr(state, problem: Problem, ctx: EvalContext) -> float:
    """Albedo PSNR (dB, sRGB, masked) of the state's renders against GT at native size; NaN
    when albedo is not distilled."""
    if "albedo" not in problem.channels.maps:
        return math.nan
    texels = np.asarray(jax.device_get(state.texels))
    pred = evaluation.render_views(texels, ctx.plan, ctx.cameras, problem.channels)
    return evaluation.albedo_psnr(pred, ctx.gt_maps, ctx.masks)


@dataclasses.dataclass(frozen=True)
class Baseline:
    """The per-view estimates a run is scored against (and anchored to): per view {map: (H, W, C)
    file-space image} at the evaluation size, where they come from, and the cache folder of the
    model's estimates (None for the views prior's targets)."""

    views: list[dict] | None
    source: str
    folder: Path | None = None


def per_view_baseline(config: DistillConfig, problem: Problem, shapes: list[tuple[int, int]]) -> Baseline:
    """The rgbx prior's baseline is the model's own per-view estimates (computed once, cached);
    the views prior's is the scene's per-view targets (None when the scene has none)."""
    scene, channels = problem.scene, problem.channels
    if problem.rgbx_model is None:
        return Baseline(evaluation.read_baseline(scene, channels.maps, shapes), "the scene's per-view target images")
    folder = model_estimates.cached_estimates(
        problem.rgbx_model, [(v.name, v.photo, v.exposure) for v in scene.views], channels.maps, problem.height,
        problem.width, dtype=config.prior_dtype, seed=config.seed)
    views = model_estimates.read_estimates(folder, [v.name for v in scene.views], channels.maps, shapes)
    return Baseline(views, f"the model's own per-view estimates ({model_estimates.ESTIMATE_STEPS} DDIM steps, "
                    f"{folder})", folder)


def anchor_mode(config: DistillConfig, problem: Problem) -> str:
    """--anchor resolved: auto is `estimates` with the rgbx prior (SDS follows the prior's x̂0 and
    drifts from the estimates' overall scale) and `none` with the views prior (a least-squares
    fusion of the targets has their scale already; docs/seams.md measures both)."""
    if config.anchor != "auto":
        return config.anchor
    return "estimates" if problem.rgbx_model is not None else "none"


def anchor_to_baseline(config: DistillConfig, problem: Problem, texels: np.ndarray, ctx: EvalContext,
                       baseline: Baseline) -> tuple[np.ndarray, dict | None]:
    """With `--anchor` resolving to estimates (`anchor_mode`): the texels with albedo and irradiance
    scaled per channel so that their renders' sRGB mean over the covered pixels of all views is
    the baseline's (`align.anchor_gains`), and what was done, for metrics.json; otherwise the
    texels unchanged and None."""
    if anchor_mode(config, problem) == "none":
        return texels, None
    gains = {}
    if baseline.views:
        # measured on the texels clipped to [-1, 1], as `anchored_texels` clips them before scaling
        renders = evaluation.render_views(np.clip(texels, -1.0, 1.0), ctx.plan, ctx.cameras, problem.channels)
        hits = np.asarray(ctx.plan.hit).reshape(-1, ctx.plan.height, ctx.plan.width)
        gains = align_lib.anchor_gains(renders, baseline.views, list(hits), problem.channels.maps)
    if not gains:
        if config.anchor == "estimates":     # asked for by name: say why nothing happened (auto: no colour map)
            logging.warning("--anchor=%s: nothing to anchor: %s has no %s for the distilled maps; the maps keep their "
                            "distilled scale", config.anchor, baseline.source, " or ".join(align_lib.ALIGNED_MAPS))
        return texels, None
    logging.info("anchored to %s: per-channel gains %s", baseline.source,
                 ", ".join(f"{m} {np.round(g, 3).tolist()}" for m, g in gains.items()))
    low, high = align_lib.ANCHOR_GAIN_RANGE
    extreme = [f"{m}[{c}] = {g:.3g}" for m, gs in gains.items() for c, g in enumerate(gs)
               if g <= low * 1.001 or g >= high * 0.999]
    if extreme:
        logging.warning("--anchor: %s reached the end of the gain range [%g, %g]: the renders and the per-view "
                        "estimates disagree about that channel's scale by more than the range (check the "
                        "estimates in %s, or run with --anchor=none)", ", ".join(extreme), low, high,
                        baseline.folder or "the scene's targets")
    return (align_lib.anchored_texels(texels, gains, problem.channels),
            {"to": baseline.source, "gains": {m: g.tolist() for m, g in gains.items()}})


def write_outputs(config: DistillConfig, problem: Problem, texels: np.ndarray, history: dict,
                  ctx: EvalContext, trust: np.ndarray, baseline: Baseline) -> dict:
    """maps/, scene.glb, renders/, contact sheets, loss.png; returns the metrics part of metrics.json.
    trust: (N,) each texel's weight in the exported pages (`texel_trust`); baseline: what the
    run is scored against (`per_view_baseline`)."""
    out = Path(config.out_dir)
    scene, channels, space = problem.scene, problem.channels, problem.space
    # one map at a time: full float pages of all maps at once would be 20 GiB at 30 pages of 4096²
    written, layers = [], {}
    for m in [m for m in MAP_NAMES if m in channels.maps]:
        pages = run_files.map_pages(m, texels, channels, space, trust)
        written += export.write_maps(out, {m: pages}, scene.mesh.object_names, space.layout.object_page)
        layer = export.material_layers(m, pages, scene.mesh, space.layout.object_page)
        if layer is not None:
            layers[m] = layer
        del pages
    export.write_gltf_images(out / "scene.glb", scene.mesh, space.layout.object_page,
                             export.combine_material_layers(layers, space.layout.num_pages),
                             [(v.name, v.camera) for v in scene.views])

    pred = evaluation.render_views(texels, ctx.plan, ctx.cameras, channels)
    names = [v.name for v in scene.views]
    if config.renders:
        evaluation.write_renders(out / "renders", names, pred)
    result = {}
    if baseline.folder is not None:
        result["estimates_folder"] = str(baseline.folder)
    baseline_source, baseline = baseline.source, baseline.views
    written += write_evidence(out, problem, ctx, baseline)
    result["maps_written"] = [str(p.relative_to(out)) for p in written]
    if ctx.gt_maps is not None:
        covered = sorted({m for per_view in ctx.gt_maps for m in per_view} & set(channels.maps))
        if not covered:
            result["note"] = (f"the scene's ground truth covers none of the distilled maps ({', '.join(channels.maps)})"
                              ": no metrics against GT")
        with ThreadPoolExecutor(2) as pool:          # the metrics are NumPy: two threads, two cores
            ours = pool.submit(evaluation.evaluate, pred, ctx.gt_maps, ctx.masks, ctx.seams)
            base = pool.submit(evaluation.evaluate, baseline, ctx.gt_maps, ctx.masks, ctx.seams) if baseline else None
            result["ours"] = ours.result()
            if base is not None:
                result["baseline_per_view_estimates"] = base.result()
                result["baseline_source"] = baseline_source
                result["improvement"] = _improvement(result["ours"], result["baseline_per_view_estimates"])
                same = [] if problem.rgbx_model is not None else evaluation.targets_are_ground_truth(scene, channels.maps)
                if same:
                    result["baseline_note"] = (f"the per-view targets of {', '.join(same)} are the ground truth "
                                               "files: their baseline is GT scored against itself")
    else:
        result["ours"] = None
        result["note"] = ("the scene has no ground truth (neither gt.json in jaxdistill-gt format nor views' "
                          "ground_truth images): no metrics against GT")

    if history["step"]:
        extra = {"albedo PSNR (dB)": (history["eval_step"], history["albedo_psnr"])} if history["eval_step"] else None
        export.write_loss_plot(out / "loss.png", history["step"], history["loss"], extra=extra,
                               title=f"{scene.name}: {problem.choice.kind} prior, {len(channels.maps)} maps")
    picks = np.linspace(0, len(names) - 1, min(config.contact_views, len(names))).round().astype(int)
    if len(picks):
        photos = [imageio.read_photo_srgb(scene.views[i].photo, scene.views[i].exposure) for i in picks]
        for m in channels.maps:
            rows = []
            for j, i in enumerate(picks):
                row = [photos[j], evaluation.display_image(m, baseline[i][m]) if baseline else None,
                       evaluation.display_image(m, pred[i][m])]
                if ctx.gt_maps is not None and m in ctx.gt_maps[i]:
                    row.append(evaluation.display_image(m, ctx.gt_maps[i][m]))
                else:
                    row.append(None)
                rows.append(row)
            export.write_contact_sheet(out / f"contact_{m}.png", rows, ["photo", "per-view estimate", "ours", "GT"],
                                       [names[i] for i in picks])
    result["history"] = history
    return result


def texel_trust(problem: Problem) -> np.ndarray:
    """(N,) float32 in [0, 1]: how far each texel's distilled value is kept in the exported pages
    (`export.texel_trust`: its evidence, inside its object's UV charts)."""
    coverage = export.chart_coverage(problem.scene.mesh, problem.space.layout.object_page,
                                     problem.space.layout.page_sizes)
    return export.texel_trust(problem.evidence, coverage, problem.space)


def training_plan(problem: Problem) -> GatherPlan:
    """The gather plans of all views at the render size the run trains at."""
    return GatherPlan(index=problem.plan_index, weight=problem.plan_weight, hit=problem.plan_hit,
                      chain=problem.frozen["chain"], height=problem.height, width=problem.width)


def write_evidence(out: Path, problem: Problem, ctx: EvalContext, baseline: list[dict] | None) -> list[Path]:
    """evidence/: per texel the view count V of the training plans (`visibility`) and, for each
    map with per-view estimates, how much they disagree (`disagreement_<map>`: RMS deviation of
    the views' values from their mean, in file space, normals in world space; NaN where fewer
    than two views see the texel), both as the fusion sees them: through the training plans, the
    estimates at the render size. Where the fusion had little or conflicting evidence."""
    space, channels = problem.space, problem.channels
    pages = {"visibility": expand(problem.counts.astype(np.float32)[:, None], space, 0.0, dilation=0)}
    if baseline:
        maps = list(channels.maps)
        images = []
        for camera, per_view in zip(ctx.cameras, baseline):
            parts = {m: resize(per_view[m], problem.height, problem.width) for m in maps}
            if "normal" in parts:           # estimates are in RGB<->X camera space; texels are world space
                parts["normal"] = parts["normal"] @ rgbx_camera_rotation(camera.c2w).T.astype(np.float32)
            images.append(np.concatenate([parts[m] for m in maps], axis=-1))
        count, _, variance = texel_view_statistics(training_plan(problem), images, space.num_texels)
        for m in maps:
            spread = np.sqrt(variance[:, channels.slice(m)].sum(axis=1))
            spread = np.where(count >= 2, spread, np.nan).astype(np.float32)
            pages[f"disagreement_{m}"] = expand(spread[:, None], space, np.nan, dilation=0)
    return export.write_evidence(out, pages, problem.scene.mesh.object_names, space.layout.object_page)


def _improvement(ours: dict, baseline: dict) -> dict:
    """ours - baseline for every metric both have (positive is better for PSNR/SSIM, worse for errors)."""
    return {k: ours[k] - baseline[k] for k in ours if k in baseline and k != "num_views" and not k.endswith("_gt")}


def _peak_device_memory_mb(devices) -> float | None:
    stats = [d.memory_stats() for d in devices if hasattr(d, "memory_stats")]
    peaks = [s.get("peak_bytes_in_use") for s in stats if s]
    return max(peaks) / 2 ** 20 if peaks and all(p is not None for p in peaks) else None


def _json_safe(value):
    if isinstance(value, dict):
        return {k: _json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_json_safe(v) for v in value]
    if isinstance(value, (np.floating, float)):
        return float(value) if math.isfinite(value) else None
    if isinstance(value, np.integer):
        return int(value)
    return value

