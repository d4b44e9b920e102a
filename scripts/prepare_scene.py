"""Turns a Mitsuba 3 scene into a jaxdistill scene with exact per-view ground truth.

    python scripts/prepare_scene.py --mitsuba=PATH/scene.xml --out=DIR [--views=24] [--width=384]
        [--height=288] [--spp=64] [--seed=0] [--up=auto|x,y,z]

Writes into DIR: scene.json + mesh.glb (the reconstruction mesh: the scene's triangles, one
object per Mitsuba shape, UVs kept or re-unwrapped with xatlas so they lie in [0, 1] without
overlap), photos/<view>.exr|png (Mitsuba path traced), targets/{albedo,normal,roughness,
metallic}/<view>.exr (ground truth evaluated at the original UVs), irradiance (E / pi rendered
by Mitsuba: ground_truth/irradiance/<view>.exr, and scaled into [0, 1] as
targets/irradiance/<view>.exr), masks/<view>.png (valid = hit, not emitter, not glass), each
referenced by its view in scene.json (targets, ground_truth, mask: a complete scene for the
main job and its evaluation), import.json (conventions, materials, UV decisions, statistics,
timings) and README.md. How each step works: `jaxdistill/datasets/mitsuba/prepare.py`. Then:

    python -m jaxdistill.main --flagfile=configs/bedroom.cfg --scene=DIR --out_dir=RUN --views_per_step=8

Needs the `scenes` extra (Mitsuba 3; the irradiance needs its llvm_ad_rgb variant, i.e. libLLVM). Bad input (missing XML or texture files, not a
scene, unsupported plugins, bad flags) is reported as a list of problems, exit status 2.

The real scene this was written for, `../shared/scenes/staircase2`, is "Modern Hall" by
NewSee2l035 (Blend Swap), converted to Mitsuba by Benedikt Bitterli for his Rendering
Resources (https://benedikt-bitterli.me/resources/), released under CC-BY 3.0
(https://creativecommons.org/licenses/by/3.0/). The README.md written beside an imported scene
quotes the source's licence file.
"""

from __future__ import annotations

import argparse
import json
import logging
import shlex
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from jaxdistill.errors import InputError  # noqa: E402


def parse_up(text: str):
    if text == "auto":
        return None
    try:
        values = [float(x) for x in text.split(",")]
    except ValueError:
        values = []
    if len(values) != 3 or not any(values):
        raise InputError.single("command line", "--up", f"expected 'auto' or three numbers x,y,z, got {text!r}")
    return values


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--mitsuba", required=True, help="Mitsuba 3 scene XML (Mitsuba 0.5/0.6 files are upgraded first)")
    parser.add_argument("--out", required=True, help="output folder")
    parser.add_argument("--views", type=int, default=24)
    parser.add_argument("--width", type=int, default=384)
    parser.add_argument("--height", type=int, default=288)
    parser.add_argument("--spp", type=int, default=64)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--up", default="auto", help="world up vector x,y,z, or auto (the scene sensor's up, else +y)")
    parser.add_argument("--quiet", action="store_true", help="no progress bars")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(message)s")
    command = "python scripts/prepare_scene.py " + " ".join(
        shlex.quote(a) for a in (sys.argv[1:] if argv is None else argv))
    try:
        from jaxdistill.datasets.mitsuba.prepare import prepare_scene
        summary = prepare_scene(args.mitsuba, args.out, num_views=args.views, width=args.width, height=args.height,
                                spp=args.spp, seed=args.seed, up=parse_up(args.up), command=command,
                                progress=not args.quiet)
    except InputError as err:
        print(err, file=sys.stderr)
        return 2
    brief = {k: summary[k] for k in ("reunwrapped", "statistics", "timings")}
    print(json.dumps(brief, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
