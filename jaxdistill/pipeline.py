"""The main job, read top to bottom: check the inputs → build the problem → run the step loop →
score against the per-view estimates and ground truth → anchor → write the outputs.

`run(config)` is what `python -m jaxdistill.main` (and `jaxdistill distill`) calls; each stage is
a function of a lower layer (`engine`, `evaluate`, `export`), so experiments and benchmarks call
the same pieces instead of copying the loop.
"""

from __future__ import annotations

import dataclasses
import json
import resource
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import jax
import numpy as np
from absl import logging

from jaxdistill import huge_pages
from jaxdistill.engine import distributed, gains as align_lib
from jaxdistill.engine.config import DistillConfig, check_views_per_step
from jaxdistill.engine import loop as loop_lib
from jaxdistill.engine.problem import build_problem, choose_prior
from jaxdistill.evaluate import ground_truth as evaluation, scoring
from jaxdistill.evaluate.summary import summary_table
from jaxdistill.export import anchor as anchor_lib, run_dir as run_files
from jaxdistill.export.outputs import OutputPhases, texel_trust, write_outputs
from jaxdistill.export.run_dir import json_safe
from jaxdistill.models.shipped import model_info


def run(config: DistillConfig, *, progress: bool = True) -> dict:
    """Runs the distillation described by `config`; returns the metrics written to metrics.json
    (or, when a signal stopped the loop, where it stopped)."""
    wall_start = time.perf_counter()
    out = Path(config.out_dir)
    latest = loop_lib.check_before_compute(config, out, choose_prior(config))
    problem = build_problem(config, check_scene=lambda scene: (
        check_views_per_step(config, len(scene.views), config.scene), anchor_lib.check_anchor(config, scene),
        evaluation.read_ground_truth(scene)))
    recorded = loop_lib.recorded_config(config, problem.choice.kind)
    banner = f"PRIOR: {problem.choice.kind.upper()} -- {problem.choice.reason}"
    logging.warning("%s\n%s\n%s", "=" * len(banner), banner, "=" * len(banner))

    out.mkdir(parents=True, exist_ok=True)
    if not distributed.is_primary():               # another process of a multi-process run: the loop only
        problem = problem.without_fragments()
        loop = loop_lib.run_loop(config, problem, recorded, latest, progress=False)
        if not loop.stopped_by:
            distributed.barrier("outputs")     # process 0 writes them: JAX's shutdown waits only 300 s for it
        return {"process_id": jax.process_index(), "step": int(jax.device_get(loop.state.step)),
                "stopped_by": loop.stopped_by, "exit_status": loop.exit_status}
    steps_left = latest is None or latest < config.steps
    # one thread compiles beside the evaluation's set-up: the step, then the model's per-view
    # estimates' programs (used after the loop), which go on while the loop runs (XLA compiles on
    # one core, which the steps leave partly idle); only the step is waited for here
    pool = ThreadPoolExecutor(max_workers=1)
    try:
        preparing = pool.submit(loop_lib.prepare_step, config, problem) if steps_left else None
        estimates_compiled = (pool.submit(scoring.compile_baseline_ahead, config,    # (the fragments not held)
                                          dataclasses.replace(problem, fragments=None, native_fragments=None))
                              if steps_left else None)
        trust = texel_trust(problem)               # once: the texel space file and the exported pages
        run_files.write_texel_space(out, problem.space, trust, problem.channels.maps, json_safe(recorded))
        ctx = scoring.evaluation_context(config, problem)
        waited = time.perf_counter()
        prepared = preparing.result() if preparing is not None else None
        waited = time.perf_counter() - waited
        preparing = None
    except BaseException:
        pool.shutdown(wait=False, cancel_futures=True)          # the estimates' programs are not needed
        raise
    pool.shutdown(wait=False)
    problem = problem.without_fragments()         # read by nothing after the evaluation context
    if prepared is not None:
        problem.timings.update(step_compiled_s=round(prepared.seconds, 2), step_compile_waited_s=round(waited, 2))
    peaks = {"set-up": peak_host_memory_gb()}
    evaluate = (lambda state: scoring.quick_psnr(state, problem, ctx)) if ctx.gt_maps is not None else None
    loop = loop_lib.run_loop(config, problem, recorded, latest, evaluate=evaluate, progress=progress,
                             prepared=prepared)
    prepared = None                               # its step-0 state (a resumed run's, never donated) goes now
    if loop.stopped_by:
        if estimates_compiled is not None and not estimates_compiled.done():
            logging.warning("the process ends once the per-view estimates' programs, compiling since the set-up, "
                            "are compiled (XLA's compilation cannot be stopped)")
        return {"stopped_by": loop.stopped_by, "step": int(jax.device_get(loop.state.step)),
                "exit_status": loop.exit_status}

    texels = np.asarray(jax.device_get(loop.state.texels))
    peaks["loop"] = peak_host_memory_gb()
    gains = None
    if loop.state.align is not None:          # the learned per-view gains (geometric mean 1 per channel)
        gains = np.exp(np.asarray(jax.device_get(align_lib.centred(loop.state.align["log_gains"]))))
    # the state holds AdamW's two moments, each as large as the texels: nothing after the loop reads them
    loop = dataclasses.replace(loop, state=None)
    if estimates_compiled is not None:
        try:
            seconds = estimates_compiled.result()
        except Exception as err:         # noqa: BLE001 -- only a head start: the estimates compile them anyway
            logging.warning("compiling the per-view estimates' programs ahead failed (%s: %s); they are compiled "
                            "when they run", type(err).__name__, err)
            seconds = None
        problem.timings["estimates_compiled_s"] = None if seconds is None else round(seconds, 2)
    phases = OutputPhases()
    with phases("per-view estimates"):
        baseline = scoring.per_view_baseline(config, problem, ctx.shapes)
    with phases("anchor"):
        texels, anchor = anchor_lib.anchor_to_baseline(config, problem, texels, ctx, baseline)
    summary = write_outputs(config, problem, texels, loop.history, ctx, trust, baseline, phases)
    if problem.photos is not None and problem.photos.noise is not None:     # each photo's noise and term weight
        names = [v.name for v in problem.scene.views]
        summary["photo_noise"] = {"ref": config.photo_noise_ref,
                                  "sigma": dict(zip(names, np.round(problem.photos.noise, 4).tolist())),
                                  "weight": dict(zip(names, np.round(problem.photos.noise_weight, 4).tolist()))}
    summary.update(run_record(config, problem, loop, wall_start))
    summary["anchor"] = anchor
    summary["peak_host_memory_gb"] = {**peaks, "outputs": peak_host_memory_gb()}    # the peak so far after each stage
    summary["output_timings"] = phases.record
    if gains is not None:
        summary["align"] = {"maps": list(align_lib.aligned_maps(problem.channels)),
                            "gains": {v.name: g.round(4).tolist() for v, g in zip(problem.scene.views, gains)}}
    (out / "metrics.json").write_text(json.dumps(json_safe(summary), indent=1))
    logging.info("wrote %s", out / "metrics.json")
    print(summary_table(json_safe(summary), out), flush=True)
    distributed.barrier("outputs")
    return summary


def run_record(config: DistillConfig, problem, loop, wall_start: float) -> dict:
    """metrics.json's account of the run: steps, times, prior, device, memory, size, the flags."""
    devices = jax.devices()
    steps_run = config.steps - loop.start_step
    return {
        "steps": config.steps, "steps_this_run": steps_run,
        "resumed_from": loop.start_step if config.resume else None,
        "wall_seconds": time.perf_counter() - wall_start, "loop_seconds": loop.seconds,
        "seconds_per_step": loop.seconds / max(steps_run, 1), "setup_timings": problem.timings,
        "prior": {"kind": problem.choice.kind, "reason": problem.choice.reason, "folder": problem.choice.folder,
                  "model": model_info(problem.choice.folder) if problem.choice.folder else None},
        "device": {"backend": jax.default_backend(), "devices": [str(d) for d in devices],
                   "kind": devices[0].device_kind, "processes": jax.process_count()},
        "peak_host_memory_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
        "huge_pages": huge_pages.status(),       # how large host arrays are faulted in (huge_pages.py)
        "view_data": {"flag": config.view_data, "where": "disk" if problem.views_on_disk else "memory",
                      "disk_bytes": problem.view_folder.nbytes if problem.view_folder else 0},
        "peak_device_memory_mb": _peak_device_memory_mb(jax.local_devices()),     # this process's
        "parameters": {"texels": problem.space.num_texels, "channels": problem.channels.num_channels,
                       "page_sizes": list(problem.space.layout.page_sizes)},
        "traces": loop.traces, "config": loop_lib.recorded_config(config, problem.choice.kind),
    }


def peak_host_memory_gb() -> float:
    """This process's peak resident memory so far, GB (the operating system's accounting)."""
    return round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2 ** 20, 3)


def _peak_device_memory_mb(devices) -> float | None:
    stats = [d.memory_stats() for d in devices if hasattr(d, "memory_stats")]
    peaks = [s.get("peak_bytes_in_use") for s in stats if s]
    return max(peaks) / 2 ** 20 if peaks and all(p is not None for p in peaks) else None
