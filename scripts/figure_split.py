"""Where the albedo/irradiance split fails: the views whose albedo carries the most light, side by side.

    python scripts/figure_split.py --scene=bedroom --run=SDS=out/bedroom --run="SDS + photo"=out/bedroom_photo \
        --out=docs/img/split_failures.jpg [--views=4 | --views=view_000,view_019] [--json=docs/data/split_failures.json]

Each --run is LABEL=OUT_DIR of a main-job run with renders (OUT_DIR/renders/albedo/<view>.png,
written by default). Per view and run, the albedo's shading leak β (`metrics.shading_leak`: the
slope of log(albedo / GT albedo) on log(GT irradiance); 0 none, 1 the photo) is measured against
the scene's ground truth at the photos' size; the figure shows the --views views where the last
run leaks most (sun patches, hard shadows, highlights on glossy floors), or the views named, with columns photo |
GT irradiance | GT albedo | each run's albedo, and every run's β in the row name. The JSON has
every view's β for every run and their means.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from jaxdistill.datasets import ImportOptions, open_scene
from jaxdistill.evaluate import ground_truth as evaluation, metrics
from jaxdistill.export import plots
from jaxdistill.io import images as imageio
from jaxdistill.render import fragments as fr


def parse_run(text: str) -> tuple[str, Path]:
    label, sep, folder = text.partition("=")
    if not sep or not label or not folder:
        raise SystemExit(f"--run: expected LABEL=OUT_DIR, got {text!r}")
    return label, Path(folder)


def run_albedo(folder: Path, view: str) -> np.ndarray:
    """A run's linear albedo render of one view (renders/albedo/<view>.png is sRGB)."""
    path = folder / "renders" / "albedo" / f"{view}.png"
    if not path.is_file():
        raise SystemExit(f"--run: {path} does not exist; run the main job with --renders (the default)")
    return imageio.read_image(path)[..., :3]          # decoded to linear


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--scene", required=True, help="scene folder or 'bedroom'")
    parser.add_argument("--run", action="append", required=True, help="LABEL=OUT_DIR (repeat; the last one picks the views)")
    parser.add_argument("--views", default="4", help="how many of the leakiest views, or a comma list of view names")
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args(argv)
    runs = [parse_run(r) for r in args.run]
    scene = open_scene(args.scene, ImportOptions(allow_outside_paths=True))
    frags = fr.compute_fragments(scene.mesh, [v.camera for v in scene.views])
    gt, gt_maps = evaluation.view_ground_truth(scene, frags)
    if gt_maps is None or not all("irradiance" in g and "albedo" in g for g in gt_maps):
        raise SystemExit(f"--scene: {args.scene} has no albedo and irradiance ground truth for every view")
    masks = evaluation.evaluation_masks(gt, scene, frags)
    names = [v.name for v in scene.views]
    leaks = {label: [] for label, _ in runs}
    albedo = {label: [] for label, _ in runs}
    for i, name in enumerate(names):
        for label, folder in runs:
            a = run_albedo(folder, name)
            albedo[label].append(a)
            leaks[label].append(metrics.shading_leak(a, gt_maps[i]["albedo"], gt_maps[i]["irradiance"], masks[i]))
    if args.views.isdigit():
        last = np.nan_to_num(np.asarray(leaks[runs[-1][0]]), nan=-np.inf)
        picks = [int(i) for i in np.argsort(-last)[:int(args.views)]]
    else:
        unknown = [v for v in args.views.split(",") if v not in names]
        if unknown:
            raise SystemExit(f"--views: no view named {', '.join(unknown)} in {args.scene}")
        picks = [names.index(v) for v in args.views.split(",")]
    rows, row_names = [], []
    for i in picks:
        photo = imageio.read_photo_srgb(scene.views[i].photo, scene.views[i].exposure)
        rows.append([photo, evaluation.display_image("irradiance", gt_maps[i]["irradiance"]),
                     evaluation.display_image("albedo", gt_maps[i]["albedo"])]
                    + [evaluation.display_image("albedo", albedo[label][i]) for label, _ in runs])
        row_names.append(names[i] + "\n" + "\n".join(f"β {leaks[label][i]:.2f}" for label, _ in runs))
    png = args.out.with_suffix(".png")
    plots.write_contact_sheet(png, rows, ["photo", "GT irradiance", "GT albedo"] + [label for label, _ in runs],
                              row_names)
    if args.out.suffix.lower() in (".jpg", ".jpeg"):
        from PIL import Image
        Image.open(png).convert("RGB").save(args.out, quality=88)
        png.unlink()
    doc = {"scene": args.scene, "runs": {label: folder.name for label, folder in runs}, "views": picks,
           "per_view": {label: dict(zip(names, v)) for label, v in leaks.items()},
           "mean": {label: float(np.nanmean(v)) for label, v in leaks.items()}}
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(doc, indent=1))
    print(json.dumps(doc["mean"]), "->", args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
