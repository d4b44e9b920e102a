"""Can the photos themselves give albedo its absolute scale? A measurement of `--anchor=traced`
(README "Re-rendering against the photos", the overall scale) on scenes with ground truth.

The re-rendering term fixes only the product albedo ⊙ irradiance, and the prior decides the
split, including its overall scale (a · k, E / k explain the same photos). The photos hold the
missing unit where they show the light: the irradiance at a point is the radiance of everything
it sees, which the photos record (`jaxdistill.render.light_trace`, `jaxdistill.export.photo_light`).
Here the anchor's own estimator is given the GT albedo in place of a run's renders: its gain is
then the factor by which the traced light would misjudge the albedo's scale (1: exact; above 1:
light the photos do not show, such as a directional sun or a sky through windows no photo looks
out of). Per scene it prints that gain per channel, the per-point ratio photo / (E · GT albedo)
(quantiles, median per channel), and what decides whether the trace can be trusted: the
fraction of rays leaving the mesh where no photo shows what lies beyond (`escaped_unseen`).

    python scripts/photo_light_scale.py --scenes=data/val/room_0,data/val/room_1,data/val/room_2 \
        --json=docs/data/photo_light_scale.json
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from jaxdistill.evaluate import ground_truth as evaluation
from jaxdistill.export import photo_light
from jaxdistill.render.fragments import compute_fragments
from jaxdistill.scene.model import read_scene
from jaxdistill.scene.paths import resolve_scene_path


def scene_scale(path, *, points: int, rays: int, seed: int = 0) -> dict:
    """The trace's gain against GT albedo and the per-point ratios for one scene."""
    scene = read_scene(resolve_scene_path(path))
    frags = compute_fragments(scene.mesh, [v.camera for v in scene.views], progress=False)
    gt, gt_maps = evaluation.view_ground_truth(scene, frags)
    if not gt_maps or not all("albedo" in g for g in gt_maps):
        raise SystemExit(f"{path}: no albedo ground truth to compare with")
    hits = [np.asarray(m) > 0 for m in evaluation.evaluation_masks(gt, scene, frags)]
    start = time.perf_counter()
    t = photo_light.trace_points(scene, gt_maps, hits, seed=seed, points=points, rays=rays)
    gain, record = photo_light.gain_from_points(t)
    counted = photo_light.counted_points(t)
    ratio = t.radiance[counted] / np.maximum(t.irradiance[counted] * t.albedo[counted], 1e-12)
    return {**record, "seconds": round(time.perf_counter() - start, 1),
            "gain_vs_gt": None if gain is None else np.round(gain, 3).tolist(),
            "point_ratio_median_per_channel": np.median(ratio, 0).round(3).tolist() if len(ratio) else None,
            "point_ratio_quantiles_10_25_50_75_90": np.quantile(ratio.mean(1), [.1, .25, .5, .75, .9]).round(3).tolist()
            if len(ratio) else None}


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scenes", required=True, help="comma-separated scene folders (or names) with GT albedo")
    parser.add_argument("--points", type=int, default=photo_light.TRACE_POINTS, help="sampled pixels per view")
    parser.add_argument("--rays", type=int, default=photo_light.TRACE_RAYS, help="hemisphere rays (and emitter "
                        "samples) per point")
    parser.add_argument("--json", type=Path, help="write the results here")
    args = parser.parse_args()
    if args.points < 1 or args.rays < 1:
        parser.error(f"--points and --rays must be at least 1 (got {args.points}, {args.rays})")
    results = {}
    for path in args.scenes.split(","):
        results[Path(path).name] = scene_scale(path, points=args.points, rays=args.rays)
        print(Path(path).name, json.dumps(results[Path(path).name]), flush=True)
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps({"command": "python scripts/photo_light_scale.py --scenes=" + ",".join(
            Path(p).name for p in args.scenes.split(",")), "results": results}, indent=1) + "\n")


if __name__ == "__main__":
    main()
