"""Re-scores finished rgbx runs under other overall-scale anchors (README "Re-rendering against the
photos", the anchor), from each run's last checkpoint, without running the loop again.

`--anchor=estimates` (the default with the rgbx prior) scales albedo and irradiance each by their
own per-channel gains g_a, g_i (`export.anchor.anchor_gains`: the renders' sRGB mean over the
covered pixels set to the model's per-view estimates'). That changes the product albedo ⊙
irradiance, which the re-rendering term fitted to the photos. The variant measured here keeps the
product and takes only the split from the estimates:

    split:  albedo × s,  irradiance ÷ s,   s_c = (g_a,c / g_i,c)^½

(log s halves the disagreement between the two maps' gains, so an error of the model's overall
brightness, which moves g_a and g_i alike, cancels). Rows: none (the distilled scale), estimates,
split, `--anchor=traced` (albedo × g, irradiance ÷ g, g from the irradiance traced from
the photos: `export.photo_light.traced_albedo_gain`) and `--anchor=auto` (traced where the trace
is trusted, `export.anchor.trace_trusted`, else estimates), each scored against GT as the
main job scores (`evaluate.ground_truth.evaluate`):

    python scripts/rescore_anchor.py --runs=data/exp_val_budget/room_0/room_0/sds+p1sa_v8r2,... \
        --json=docs/data/anchor_split.json
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import tempfile
from pathlib import Path
from typing import Sequence

import numpy as np

from jaxdistill.engine.config import DistillConfig, validate
from jaxdistill.engine.problem import build_problem
from jaxdistill.evaluate import ground_truth as evaluation, scoring
from jaxdistill.export import anchor as anchor_lib
from jaxdistill.io.checkpoint import CheckpointStore

METRICS = ("albedo_psnr", "albedo_si_psnr", "albedo_ssim", "irradiance_si_psnr")
NAMES = ("none", "estimates", "split", "traced", "auto")


def anchor_rows(gains: dict, traced: dict, trusted: bool) -> tuple:
    """(name, gains) of each row: as distilled, `--anchor=estimates`, its product-keeping split,
    `--anchor=traced`, and `--anchor=auto` (traced where the trace is trusted, else estimates)."""
    return (("none", {}), ("estimates", gains), ("split", split_gains(gains)), ("traced", traced),
            ("auto", traced if trusted else gains))


def split_gains(gains: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """The product-keeping variant of `anchor_gains`' {albedo: g_a, irradiance: g_i}: albedo × s and
    irradiance ÷ s with s = (g_a / g_i)^½ per channel."""
    s = np.sqrt(np.asarray(gains["albedo"], np.float64) / np.asarray(gains["irradiance"], np.float64))
    return {"albedo": s, "irradiance": 1.0 / s}


def run_config(run: Path, out_dir: str) -> DistillConfig:
    """The run's own config (metrics.json `config`), writing nowhere that matters."""
    recorded = json.loads((run / "metrics.json").read_text())["config"]
    fields = {f.name for f in dataclasses.fields(DistillConfig)}
    values = {k: tuple(v) if isinstance(v, list) else v for k, v in recorded.items() if k in fields}
    return validate(DistillConfig(**{**values, "out_dir": out_dir, "resume": False}))


def rescore(run: Path) -> dict:
    with tempfile.TemporaryDirectory() as scratch:
        config = run_config(run, scratch)
        if config.prior == "views" or not {"albedo", "irradiance"} <= set(config.maps):
            raise SystemExit(f"{run}: needs an rgbx run distilling albedo and irradiance "
                             f"(prior {config.prior}, maps {', '.join(config.maps)})")
        problem = build_problem(config)
        if problem.rgbx_model is None:
            raise SystemExit(f"{run}: --prior={config.prior} resolved to {problem.choice.kind}, not rgbx")
        ctx = scoring.evaluation_context(config, problem)
        if ctx.gt_maps is None:
            raise SystemExit(f"{config.scene}: no ground truth to score against")
        texels = CheckpointStore(run / "checkpoints").read_texels()
        baseline = scoring.per_view_baseline(config, problem, ctx.shapes)
        renders = evaluation.render_views(np.clip(texels, -1.0, 1.0), ctx.plan, ctx.cameras, problem.channels,
                                          lazy=problem.views_on_disk)
        hits = ctx.plan.hit_images()
        gains = anchor_lib.anchor_gains(renders, baseline.views, hits, problem.channels.maps)
        traced, record = anchor_lib.traced_light(problem.scene, renders, hits, texels, problem.channels,
                                                 seed=config.seed)
        traced = {} if traced is None else anchor_lib.traced_gains(traced, problem.channels.maps)
        row = {"run": "/".join(run.parts[-4:]), "gains": {m: g.tolist() for m, g in gains.items()},
               "traced_gains": {m: g.tolist() for m, g in traced.items()}, "trace": record}
        trusted = bool(traced) and anchor_lib.trace_trusted(record)
        row["trusted"] = trusted
        for name, mode_gains in anchor_rows(gains, traced, trusted):
            scaled = anchor_lib.anchored_texels(texels, mode_gains, problem.channels)
            scores = evaluation.evaluate(evaluation.render_views(scaled, ctx.plan, ctx.cameras, problem.channels),
                                         ctx.gt_maps, ctx.masks, ctx.seams)
            row[name] = {k: scores[k] for k in METRICS if k in scores}
            print(row["run"], name, " ".join(f"{k} {v:.3f}" for k, v in row[name].items()), flush=True)
        return row


def main(argv: Sequence[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--runs", required=True, help="comma-separated finished run folders (metrics.json, checkpoints/)")
    parser.add_argument("--json", type=Path, help="write the rows and their means here")
    args = parser.parse_args(argv)
    rows = [rescore(Path(r)) for r in args.runs.split(",") if r]
    means = {name: {k: float(np.mean([r[name][k] for r in rows])) for k in METRICS if k in rows[0][name]}
             for name in NAMES}
    for name, m in means.items():
        print("mean", name, " ".join(f"{k} {v:.3f}" for k, v in m.items()))
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps({"rows": rows, "means": means}, indent=1))


if __name__ == "__main__":
    main()
