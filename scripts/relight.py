"""Relights a scene under a new light with its ground-truth materials and with a run's, and scores the run.

    python scripts/relight.py --scene=bedroom --run=OUT_DIR --out=relight.json
        [--views=6 | --views=view_000,view_024 | --views=0,8,16] [--light=centre|offset|fx,fy,fz]
        [--spp=32] [--seed=0] [--max_depth=5] [--figures=DIR]

Every light of the scene is removed and one point light placed at --light (fractions of the
mesh's bounding box; `relight.LIGHTS`); the views are path traced by Mitsuba with principled
BSDFs on the GT pages (gt.json) and on the run's pages (OUT_DIR/maps), same seeds. The JSON has
the per-view and mean PSNR (sRGB, one exposure from the GT renders, evaluated pixels only),
the settings and timings; the figures folder (default: the JSON's name without .json) holds
each view's GT and run render and a sheet (GT | run | 4 x |difference|).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

from jaxdistill.errors import InputError
from jaxdistill.evaluate import relight as rl
from jaxdistill.scene.model import read_scene
from jaxdistill.scene.paths import resolve_scene_path


def pick_views(text: str, names: list[str]) -> list[int]:
    """--views: a count (evenly spaced), or a comma list of view names or indices."""
    if text.isdigit():
        return rl.default_views(int(text), len(names))
    out = []
    for part in text.split(","):
        part = part.strip()
        if part in names:
            out.append(names.index(part))
        elif part.lstrip("-").isdigit() and -len(names) <= int(part) < len(names):
            out.append(int(part) % len(names))
        else:
            raise ValueError(f"--views: {part!r} is neither a view name nor an index below {len(names)}")
    return out


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--scene", required=True, help="scene.json, its folder, or an embedded scene name ('bedroom')")
    parser.add_argument("--run", type=Path, required=True, help="a finished run's folder (holding maps/)")
    parser.add_argument("--out", type=Path, required=True, help="the JSON report")
    parser.add_argument("--views", default="6", help="a count (evenly spaced views; default 6) or names/indices, comma-separated")
    parser.add_argument("--light", default="centre", help=f"{' | '.join(rl.LIGHTS)} | fx,fy,fz (bounding-box fractions)")
    parser.add_argument("--spp", type=int, default=32)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--max_depth", type=int, default=5)
    parser.add_argument("--figures", type=Path, help="folder for the PNGs (default: --out without .json)")
    args = parser.parse_args(argv)
    if args.spp < 1 or args.max_depth < 1:
        parser.error("--spp and --max_depth must be >= 1")
    try:
        light = rl.parse_light(args.light)
        scene = read_scene(resolve_scene_path(args.scene))
        views = pick_views(args.views, [v.name for v in scene.views])
        pages, sources = rl.read_run_pages(args.run, scene.mesh.object_names)
        position = rl.light_position(scene.mesh, light)
        result = rl.relight(scene, pages, views=views, light=light, spp=args.spp, seed=args.seed,
                            max_depth=args.max_depth, progress=True)
    except (InputError, ValueError, FileNotFoundError) as err:
        print(err, file=sys.stderr)
        return 2
    report = rl.summary(result, scene_name=scene.name, run_dir=args.run, light=light, position=position, spp=args.spp,
                        seed=args.seed, max_depth=args.max_depth, sources=sources)
    figures = args.figures or args.out.with_suffix("")
    report["figures"] = str(figures)
    rl.write_figures(figures, result)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(report, indent=1, allow_nan=True))
    per_view = ", ".join(f"{n} {p:.2f}" for n, p in report["psnr_db"].items() if not math.isnan(p))
    print(f"relit PSNR (dB): mean {report['mean_psnr_db']:.2f}; {per_view}")
    print(f"light at {report['light_position']} ({args.light}), exposure {result.stops:+.2f} stops, "
          + ", ".join(f"{k} {v:.1f} s" for k, v in report["seconds"].items()) + f"; wrote {args.out} and {figures}/")
    return 0


if __name__ == "__main__":
    sys.exit(main())
