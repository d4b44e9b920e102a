"""Writes an LDR copy of a scene: photos as an 8-bit sRGB capture gives them, all else unchanged.

    python scripts/make_ldr_scene.py --scene=bedroom --out=data/bedroom_ldr
    python scripts/make_ldr_scene.py --scene=bedroom --exposure_jitter=1 --white_balance_jitter=0.1 \
        --out=data/bedroom_ldr_phone

With --exposure_jitter / --white_balance_jitter each view also gets its own random exposure
(uniform in ± stops) and white balance (per-channel log-gains of that standard deviation, their
mean 0), as a phone's auto-exposure and auto white balance give them; ldr.json records each.

Each view's photo becomes sRGB(clip(linear photo x 2**exposure, 0, 1)) in an 8-bit PNG with
`exposure` 0 (`jaxdistill.datasets.ldr.write_ldr_scene`); the mesh, masks, targets,
ground_truth images, gt.json and its pages are copied, so the copy is scored like the source.
The copy is read back (`read_scene`, and gt.json's ground truth) before the script reports.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from jaxdistill.datasets.ldr import write_ldr_scene
from jaxdistill.errors import InputError
from jaxdistill.evaluate.ground_truth import read_ground_truth
from jaxdistill.scene.model import read_scene
from jaxdistill.scene.paths import resolve_scene_path


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--scene", required=True, help="scene.json, its folder, or an embedded scene name ('bedroom')")
    parser.add_argument("--out", type=Path, required=True, help="new or empty folder for the copy")
    parser.add_argument("--allow_outside_paths", action="store_true",
                        help="read a scene naming files outside its folder (they are copied under external/)")
    parser.add_argument("--exposure_jitter", type=float, default=0.0,
                        help="each view's exposure offset is uniform in +- this many stops (auto-exposure)")
    parser.add_argument("--white_balance_jitter", type=float, default=0.0,
                        help="standard deviation of each view's per-channel log-gains (auto white balance)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the per-view exposure and white balance")
    args = parser.parse_args(argv)
    try:
        source = resolve_scene_path(args.scene)
        path = write_ldr_scene(source, args.out, allow_outside_paths=args.allow_outside_paths,
                               exposure_jitter=args.exposure_jitter, white_balance_jitter=args.white_balance_jitter,
                               seed=args.seed)
        scene = read_scene(path)
        gt = read_ground_truth(scene)
    except (InputError, ValueError) as err:
        print(err, file=sys.stderr)
        return 2
    record = json.loads((args.out / "ldr.json").read_text())
    clipped = [v["clipped_fraction"] for v in record["views"].values()]
    print(f"wrote {path}: {len(scene.views)} views, exposure {sorted({v.exposure for v in scene.views})}, "
          f"clipped pixels {100 * min(clipped):.2f}-{100 * max(clipped):.2f} % per view "
          f"(mean {100 * sum(clipped) / len(clipped):.2f} %); gt.json maps: {sorted(gt.pages) if gt else 'none'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
