"""A finished run's files: maps/, scene.glb and scene.usdc, renders/, evidence/, loss.png, contact sheets."""

from __future__ import annotations

import contextlib
import os
import resource
import time
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path

import numpy as np
from absl import logging

from jaxdistill import MAP_NAMES
from jaxdistill.engine.config import DistillConfig
from jaxdistill.engine.problem import Problem
from jaxdistill.evaluate import ground_truth as evaluation
from jaxdistill.evaluate import scoring
from jaxdistill.evaluate.rerender import rerender_scores
from jaxdistill.evaluate.scoring import Baseline, EvalContext, training_plan
from jaxdistill.export import gltf, pages as page_files, plots, run_dir as run_files, usd
from jaxdistill.io import images as imageio
from jaxdistill.io.view_images import resize
from jaxdistill.render import charts, visibility
from jaxdistill.render.sampler import expand
from jaxdistill.scene.cameras import rgbx_camera_rotation
from jaxdistill.scene.maps import CHANNELS


MAP_FILES_BESIDE_BYTES = 1 << 30     # `map_files_beside`: one map's full pages up to 1 GiB (30 pages of 2048²: 1.4 GiB)
# `evidence_passes`: about what one pass over the views holds, up to 512 MiB (the bedroom's 4.1M texels:
# albedo; normal, roughness and metallic; irradiance, 0.27, 0.43 and 0.27 GiB; a capture's 60M texels: a map
# a pass, as before). One pass of all five maps there held 0.36 GB more at the run's peak.
EVIDENCE_PASS_BYTES = 1 << 29


class OutputPhases:
    """Seconds and memory of each phase after the loop (estimates, anchor, maps, scores, ...):
    `with phases("name"):` logs the phase's wall time, the process's resident memory after it and
    its peak so far, and records them for metrics.json `output_timings` (a large capture's outputs
    take minutes, so the log says where)."""

    def __init__(self):
        self.record: dict[str, dict] = {}

    @contextlib.contextmanager
    def __call__(self, name: str):
        start = time.perf_counter()
        logging.info("outputs: %s ...", name)
        yield
        seconds = time.perf_counter() - start
        rss, peak = resident_gb(), resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2 ** 20
        self.record[name] = {"seconds": round(seconds, 2), "rss_gb": rss, "peak_rss_gb": round(peak, 3)}
        logging.info("outputs: %s took %.1f s (resident %s GB, peak so far %.2f GB)", name, seconds,
                     "?" if rss is None else f"{rss:.2f}", peak)


def resident_gb() -> float | None:
    """This process's resident memory now in GB (Linux /proc/self/statm), None elsewhere."""
    try:
        pages = int(Path("/proc/self/statm").read_text().split()[1])
    except (OSError, ValueError, IndexError):
        return None
    return round(pages * os.sysconf("SC_PAGE_SIZE") / 2 ** 30, 3)


def texel_trust(problem: Problem) -> np.ndarray:
    """(N,) float32 in [0, 1]: how far each texel's distilled value is kept in the exported pages
    (`charts.texel_trust`: its evidence, inside its object's UV charts)."""
    coverage = charts.chart_coverage(problem.scene.mesh, problem.space.layout.object_page,
                                     problem.space.layout.page_sizes)
    return charts.texel_trust(problem.evidence, coverage, problem.space)


def write_map_files(out: Path, problem: Problem, texels: np.ndarray, trust: np.ndarray) -> list[Path]:
    """maps/ (one map at a time: full float pages of all maps at once would be 20 GiB at 30 pages
    of 4096²), scene.glb with the views as cameras and scene.usdc (`write_usd_scene`); returns the
    map files written."""
    scene, channels, space = problem.scene, problem.channels, problem.space
    written, layers = [], {}
    for m in [m for m in MAP_NAMES if m in channels.maps]:
        pages = run_files.map_pages(m, texels, channels, space, trust)
        written += page_files.write_maps(out, {m: pages}, scene.mesh.object_names, space.layout.object_page)
        layer = gltf.material_layers(m, pages, scene.mesh, space.layout.object_page)
        if layer is not None:
            layers[m] = layer
        del pages
    cameras = [(v.name, v.camera) for v in scene.views]
    gltf.write_gltf_images(out / "scene.glb", scene.mesh, space.layout.object_page,
                             gltf.combine_material_layers(layers, space.layout.num_pages), cameras)
    return written + write_usd_scene(out, scene.mesh, space.layout.object_page, layers, cameras)


def write_usd_scene(out: Path, mesh, object_page, layers: dict, cameras) -> list[Path]:
    """scene.usdc (`usd.write_usd`) when usd-core is installed, else one log line saying how to get
    it. Its materials read maps/' albedo, roughness and metallic PNGs and maps/normal_tangent
    (.png, or /<page>.png), the tangent-space normal pages of scene.glb (`layers`, from
    `gltf.material_layers`), written here; returns those."""
    if not usd.usd_available():
        logging.warning("scene.usdc not written: usd-core is not installed (%s writes it beside scene.glb)",
                        usd.USD_INSTALL)
        return []
    stems = page_files.page_names(mesh.object_names, object_page)
    png = lambda name: [page_files.page_file(out / "maps", name, stems, p, ".png") for p in range(len(stems))]
    textures = {m: png(m) for m in layers if m != "normal"}
    if "normal" in layers:
        textures["normal"] = png("normal_tangent")
        for path, page in zip(textures["normal"], layers["normal"]):
            imageio.write_image(path, page.astype(np.float32) / 255.0, encode_srgb=False)
    usd.write_usd(out / "scene.usdc", mesh, object_page, textures, cameras)
    return list(textures.get("normal", []))


def write_evidence(out: Path, problem: Problem, ctx: EvalContext, baseline: list[dict] | None) -> list[Path]:
    """evidence/: per texel the view count V of the training plans (`visibility`) and, for each
    map with per-view estimates, how much they disagree (`disagreement_<map>`: RMS deviation of
    the views' values from their mean, in file space, normals in world space; NaN where fewer
    than two views see the texel), both as the fusion sees them: through the training plans, the
    estimates at the render size. Where the fusion had little or conflicting evidence. The maps'
    statistics are taken in as few passes over the views as `evidence_passes` allows."""
    space, channels = problem.space, problem.channels
    pages = {"visibility": expand(problem.counts.astype(np.float32)[:, None], space, 0.0, dilation=0)}
    if baseline:
        plan = training_plan(problem)
        for maps in evidence_passes(channels.maps, space.num_texels):
            stats = visibility.texel_view_statistics_of(plan, evidence_images(problem, ctx, baseline, maps),
                                                        space.num_texels)
            for m, (count, _, variance) in zip(maps, stats):
                spread = np.where(count >= 2, np.sqrt(variance.sum(axis=1)), np.nan).astype(np.float32)
                pages[f"disagreement_{m}"] = expand(spread[:, None], space, np.nan, dilation=0)
            del stats, variance
    return page_files.write_evidence(out, pages, problem.scene.mesh.object_names, space.layout.object_page)


def evidence_passes(maps, num_texels: int, budget: int = EVIDENCE_PASS_BYTES) -> list[tuple[str, ...]]:
    """`maps` in order, grouped into passes of `visibility.texel_view_statistics_of` that hold about
    `budget` bytes at most (`visibility.EVIDENCE_BYTES_*`): each pass computes the views' read weights
    once for its maps. A map over the budget alone gets a pass of its own (as every map had before)."""
    def nbytes(group):
        return num_texels * (visibility.EVIDENCE_BYTES_PER_TEXEL +
                             visibility.EVIDENCE_BYTES_PER_CHANNEL * sum(CHANNELS[m] for m in group))

    passes: list[tuple[str, ...]] = []
    for m in maps:
        if passes and nbytes(passes[-1] + (m,)) <= budget:
            passes[-1] += (m,)
        else:
            passes.append((m,))
    return passes


def evidence_images(problem: Problem, ctx: EvalContext, baseline: list[dict], maps):
    """Per view, a tuple of the estimates of `maps` as the evidence reads them: at the render size,
    normals turned from RGB<->X camera space into world space (the texels'), one view at a time."""
    for camera, per_view in zip(ctx.cameras, baseline):
        images = []
        for m in maps:
            image = resize(per_view[m], problem.height, problem.width)
            if m == "normal":
                image = image @ rgbx_camera_rotation(camera.c2w).T.astype(np.float32)
            images.append(image)
        yield tuple(images)


def write_contact_sheets(out: Path, config: DistillConfig, problem: Problem, pred: list[dict], ctx: EvalContext,
                         baseline: list[dict] | None) -> None:
    """contact_<map>.png: photo, per-view estimate, ours and GT for --contact_views evenly spaced views."""
    scene = problem.scene
    names = [v.name for v in scene.views]
    picks = np.linspace(0, len(names) - 1, min(config.contact_views, len(names))).round().astype(int)
    if not len(picks):
        return
    photos = [imageio.read_photo_srgb(scene.views[i].photo, scene.views[i].exposure) for i in picks]
    pred = {i: pred[i] for i in picks}           # each picked view once (lazy views render or read a chunk)
    baseline = {i: baseline[i] for i in picks} if baseline else None
    for m in problem.channels.maps:
        rows = []
        for j, i in enumerate(picks):
            gt = ctx.gt_maps[i][m] if ctx.gt_maps is not None and m in ctx.gt_maps[i] else None
            rows.append([photos[j], evaluation.display_image(m, baseline[i][m]) if baseline else None,
                         evaluation.display_image(m, pred[i][m]),
                         evaluation.display_image(m, gt) if gt is not None else None])
        plots.write_contact_sheet(out / f"contact_{m}.png", rows, ["photo", "per-view estimate", "ours", "GT"],
                                   [names[i] for i in picks])


def write_loss_plot(out: Path, problem: Problem, history: dict) -> None:
    """loss.png: the loss over the steps run (and the albedo PSNR of --eval_every)."""
    if not history["step"]:
        return
    extra = {"albedo PSNR (dB)": (history["eval_step"], history["albedo_psnr"])} if history["eval_step"] else None
    plots.write_loss_plot(out / "loss.png", history["step"], history["loss"], extra=extra,
                           title=f"{problem.scene.name}: {problem.choice.kind} prior, {len(problem.channels.maps)} maps")


def write_outputs(config: DistillConfig, problem: Problem, texels: np.ndarray, history: dict,
                  ctx: EvalContext, trust: np.ndarray, baseline: Baseline, phases: OutputPhases | None = None) -> dict:
    """maps/, scene.glb, scene.usdc, renders/, evidence/, loss.png, contact sheets; returns the metrics part
    of metrics.json. trust: (N,) each texel's weight in the exported pages (`texel_trust`);
    baseline: what the run is scored against (`scoring.per_view_baseline`); phases times each part."""
    out = Path(config.out_dir)
    phases = phases or OutputPhases()

    def map_files() -> list[Path]:
        with phases("maps, glTF, USD"):
            return write_map_files(out, problem, texels, trust)

    def scores(pred) -> dict:
        with phases("scores"):
            return scoring.score(pred, problem, ctx, baseline)

    # two lines of work: the map files, then the scores, in a thread (`map_files_beside`); the
    # renders, evidence, plots here. Without the thread, the same in this order.
    beside = map_files_beside(problem)
    if beside:      # pxr's first import, here: on the thread, beside the plots' imports, it can deadlock (`usd_available`)
        usd.usd_available()
    with ThreadPoolExecutor(max_workers=1) as pool:
        later = pool.submit if beside else _done
        maps_job = later(map_files)
        try:
            written, evidence, scored, rerender = _main_line(config, problem, texels, history, ctx, baseline, phases,
                                                             out, lambda pred: later(scores, pred), maps_job)
        except BaseException:                   # the queued scores are not started; the map files finish
            pool.shutdown(wait=False, cancel_futures=True)
            raise
    if beside:
        for name in ("maps, glTF, USD", "scores"):
            phases.record[name]["beside"] = "renders, evidence, plots"
    result = {"estimates_folder": str(baseline.folder)} if baseline.folder is not None else {}
    result.update(scored)
    result["rerender"] = rerender
    result["maps_written"] = [str(p.relative_to(out)) for p in written + evidence]
    result["history"] = history
    return result


def _main_line(config, problem, texels, history, ctx, baseline, phases, out, score_later, maps_job):
    """`write_outputs`' own line of work: renders, (the scores queued), evidence, plots, the photos
    re-rendered from the renders; then waits for the map files and the scores: (map files written,
    evidence files written, scores, the photos' re-rendering scores)."""
    with phases("renders of every view"):
        pred = evaluation.render_views(texels, ctx.plan, ctx.cameras, problem.channels,
                                       lazy=problem.views_on_disk)   # on disk: rendered when asked for
        if config.renders:
            evaluation.write_renders(out / "renders", [v.name for v in problem.scene.views], pred)
    scores_job = score_later(pred)
    with phases("evidence"):
        evidence = write_evidence(out, problem, ctx, baseline.views)
    with phases("plots and contact sheets"):
        write_loss_plot(out, problem, history)
        write_contact_sheets(out, config, problem, pred, ctx, baseline.views)
    if problem.views_on_disk:
        # lazy renders keep one chunk for every thread: walked here while the scores walk them on the
        # other thread, each would render the other's chunks again; so after the scores there
        scores_job.result()
    with phases("photos re-rendered"):
        rerender = rerender_scores(pred, problem, ctx.plan)
    return maps_job.result(), evidence, scores_job.result(), rerender


def _done(fn, *args) -> Future:
    """fn(*args) run now, as a finished Future (the outputs' work without the thread)."""
    future = Future()
    future.set_result(fn(*args))
    return future


def map_files_beside(problem: Problem) -> bool:
    """Whether the map files and then the scores are made in a thread beside the renders, evidence
    and plots: when one map's full float pages (3 channels, 4 bytes a value) stay under
    `MAP_FILES_BESIDE_BYTES`, so holding them beside the other outputs' arrays costs little
    memory. A capture of 4096² pages makes them one after the other, the map files first."""
    return problem.space.layout.full_size() * 3 * 4 <= MAP_FILES_BESIDE_BYTES
