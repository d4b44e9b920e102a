"""Scores an RGB<->X-family model's per-image estimates on held-out rendered rooms.

    python scripts/eval_rgbx_model.py --data=data/rgbx/heldout [--rgbx_dir=DIR] [--out=eval.json]

For every image of `make_rgbx_data.py` shards (by default the held-out split, rooms the model
never saw), the model's estimate of each map (the demo's 50 DDIM steps, noise per image and map
from --seed, as `jaxdistill.estimate` draws it; `--steps=50,1` adds a row per step count, 1 step
being the model's conditional mean: one UNet pass at t = 999 under zero terminal SNR) against
the exact ground truth, with the main
job's metrics (`jaxdistill.evaluate.metrics.evaluate_view`, valid pixels: not emitters, no misses), next
to the trivial baseline: the photo as albedo (linear), the mean material, normals facing the
camera, the photo's luminance as irradiance. Prints a table, writes JSON.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import jax
import numpy as np
from tqdm import tqdm

from jaxdistill.evaluate import metrics
from jaxdistill.models import convert
from jaxdistill.models import prior as rgbx
from jaxdistill.models.shipped import model_info, shipped_folder
from jaxdistill.models.training.heldout import shard_ground_truth, to_file_space, trivial
from jaxdistill.models.training.shards import shard_paths

MAPS = ("albedo", "normal", "roughness", "metallic", "irradiance")


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--data", type=Path, required=True, help="folder of make_rgbx_data.py shards")
    parser.add_argument("--rgbx_dir", type=Path, default=None, help="model folder (default: the shipped model)")
    parser.add_argument("--out", type=Path, default=None, help="JSON with per-image and mean metrics")
    parser.add_argument("--steps", default="50", help="DDIM steps, or a comma-separated list: one row each (the first is "
                        "'estimates' in the JSON)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--limit", type=int, default=0, help="score at most this many images (0: all)")
    args = parser.parse_args(argv)
    try:
        steps = [int(s) for s in args.steps.split(",")]
        assert steps and all(s >= 1 for s in steps)
    except (ValueError, AssertionError):
        raise SystemExit(f"--steps={args.steps}: give DDIM step counts ≥ 1, comma-separated (e.g. 50 or 50,1)")
    folder = args.rgbx_dir or shipped_folder()
    if folder is None:
        raise SystemExit("--rgbx_dir: no model given and none shipped in this installation")
    shards = shard_paths(args.data)
    if not shards:
        raise SystemExit(f"{args.data}: no room_*.npz shards; make them with scripts/make_rgbx_data.py --split=heldout")
    model = rgbx.load_prior(convert.load_rgbx(folder))
    key = jax.random.key(args.seed)
    ours, base, names = {s: [] for s in steps}, [], []
    start = time.perf_counter()
    images = []
    for path in shards:
        with np.load(path) as z:
            for i in range(len(z["photo"])):
                images.append((f"{path.stem}/{i}", z["photo"][i].astype(np.float32) / 255.0, shard_ground_truth(z, i),
                               z["valid"][i][..., 0] > 0))
    images = images[:args.limit or None]
    for j in tqdm(range(0, len(images), 16), desc="estimates", unit="batch"):
        chunk = images[j:j + 16]
        latents = np.concatenate([np.asarray(rgbx.encode_photo(model, photo)) for _, photo, _, _ in chunk])
        for s in steps:
            pred = [{} for _ in chunk]
            for m in MAPS:
                noise = np.concatenate([np.asarray(jax.random.normal(rgbx.view_map_key(key, n, m), (1,) + latents.shape[1:]))
                                        for n, _, _, _ in chunk])
                for p, image in zip(pred, rgbx.estimate_batch(model, latents, m, noise, s, gamma=False)):
                    p[m] = to_file_space(m, image)
            ours[s] += [metrics.evaluate_view(p, gt, valid) for (_, _, gt, valid), p in zip(chunk, pred)]
        for name, photo, gt, valid in chunk:
            names.append(name)
            base.append(metrics.evaluate_view(trivial(photo), gt, valid))
    result = {"model": model_info(folder), "data": str(args.data), "images": len(names), "steps": steps[0],
              "seconds": time.perf_counter() - start, "estimates": metrics.aggregate(ours[steps[0]]),
              "trivial": metrics.aggregate(base), "per_image": dict(zip(names, ours[steps[0]])),
              "estimates_by_steps": {str(s): metrics.aggregate(ours[s]) for s in steps}}
    keys = ("albedo_psnr", "albedo_si_psnr", "albedo_ssim", "normal_angular_deg", "roughness_mse", "metallic_mse",
            "irradiance_si_psnr")
    print(f"{len(names)} held-out images, {result['seconds']:.0f} s")
    print("| | " + " | ".join(keys) + " |\n|---|" + "---|" * len(keys))
    rows = [(f"estimates, {s} DDIM step{'s' * (s > 1)}", result["estimates_by_steps"][str(s)]) for s in steps]
    for row, values in rows + [("trivial", result["trivial"])]:
        print(f"| {row} | " + " | ".join(f"{values[k]:.4g}" for k in keys) + " |")
    for row, values in rows:
        print(f"{row}: albedo PSNR {values['albedo_psnr'] - result['trivial']['albedo_psnr']:+.2f} dB over the photo")
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(result, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
