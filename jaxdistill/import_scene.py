"""Imports a dataset in its own format as a jaxdistill scene folder (scene.json + mesh.glb).

    jaxdistill import --format=fipt --path=DATA/kitchen --out=scenes/kitchen
    jaxdistill import --format=scannetpp --path=DATA/scannetpp/data/<id> --out=OUT \\
        [--max_views=60]
    jaxdistill import --format=nerfstudio --path=capture/transforms.json --mesh=room.ply --out=OUT
    jaxdistill import --format=colmap --path=capture --mesh=objects.json --out=OUT

Formats: fipt (HDR .exr photos), iris (same layout, LDR .png), scannetpp, nerfstudio, colmap
(see `jaxdistill/datasets/`). `--mesh` replaces the dataset's mesh: a mesh file or a scene
config .json listing objects with transforms (`jaxdistill/scene/objects.py`). The photos, masks
and images the dataset keeps come into --out too (`--link`: hard links, copies where the file system
has none, by default; or copies, symlinks, or none: left in place, see `jaxdistill/scene/place.py`),
so the folder reads without --allow_outside_paths and can be moved whole; derived images (undistorted photos, masks) and
the unwrapped mesh are written into --out, with import.json (what was decided and how long
each step took, and per view the fraction of its rays that hit the mesh). The hit fractions are
printed (min / median / max and the views that see least): a wrong camera convention or units
show at once, and a mesh that no view sees stops the import. Objects whose UVs are missing, tiled, collapsed or overlapping are unwrapped
with xatlas at the density the cameras observe (cached by mesh hash).

The same loaders, with the same dataset flags (--mesh, --exposure, --uv, --max_views, ...), run when
the main job is given `--scene=FORMAT:PATH` directly. Bad input is
reported as a list of problems naming file and field, exit status 2.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import sys
import time
from pathlib import Path

from jaxdistill.scene.place import LINK_MODES
from jaxdistill.errors import InputError

IMPORT_FORMATS = ("fipt", "iris", "scannetpp", "nerfstudio", "colmap")


def build_parser() -> argparse.ArgumentParser:
    """The command's flags (the `ImportOptions` ones share their names with the main job's)."""
    parser = argparse.ArgumentParser(prog="jaxdistill import", description=__doc__.split("\n\n")[0])
    parser.add_argument("--format", required=True, choices=IMPORT_FORMATS)
    parser.add_argument("--path", required=True, help="the dataset (folder or file, per format)")
    parser.add_argument("--out", required=True, help="output folder for scene.json, mesh.glb, derived images")
    parser.add_argument("--mesh", default=None, help="mesh file or scene config .json replacing the dataset's")
    parser.add_argument("--split", default=None, help="fipt/iris: train or val; scannetpp: train, test or all")
    parser.add_argument("--exposure", default="auto", help="'auto' (HDR: Hypersim rule, LDR: 0) or stops")
    parser.add_argument("--uv", default="auto", choices=("auto", "keep", "unwrap"),
                        help="auto: unwrap objects whose UVs are unusable; keep: refuse them; unwrap: all")
    parser.add_argument("--max_page_size", type=int, default=4096)
    parser.add_argument("--max_views", type=int, default=0, help="0 = all, else that many evenly spread")
    parser.add_argument("--max_unwrap_faces", type=int, default=4_000_000)
    parser.add_argument("--unwrap_time_limit", type=float, default=1800.0, help="seconds")
    parser.add_argument("--allow_outside_paths", action="store_true",
                        help="a --mesh scene config may name object files outside its folder")
    parser.add_argument("--link", default="hardlink", choices=LINK_MODES,
                        help="how the dataset's photos, masks and images come into --out: hard links (copies where "
                             "the file system has none), symlinks (need --allow_outside_paths in the main job), "
                             "copies, or none (left in place: need --allow_outside_paths)")
    parser.add_argument("--quiet", action="store_true", help="no progress bars")
    return parser


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.WARNING if args.quiet else logging.INFO, format="%(message)s")

    from jaxdistill import datasets
    from jaxdistill.datasets.common import ImportOptions
    from jaxdistill.scene.place import place_files
    from jaxdistill.render.visibility import MIN_HIT_FRACTION
    from jaxdistill.scene.model import read_scene, write_scene
    from jaxdistill.scene.paths import ALLOW_FLAG, is_inside

    out = Path(args.out)
    start = time.perf_counter()
    try:
        options = ImportOptions(mesh=args.mesh, exposure=args.exposure, uv=args.uv, max_page_size=args.max_page_size,
                                max_views=args.max_views, work_dir=str(out), max_unwrap_faces=args.max_unwrap_faces,
                                unwrap_time_limit=args.unwrap_time_limit, progress=not args.quiet,
                                allow_outside_paths=args.allow_outside_paths)
        report: dict = {}
        scene = datasets.load(args.format, args.path, options, split=args.split, report=report)
        scene, placement = place_files(scene, out, args.link)
        scene_json = write_scene(scene, out)
        outside = args.link in ("none", "symlink")           # self-check: what we wrote reads back
        read_scene(scene_json, check_pixels=False, allow_outside_paths=outside)
    except InputError as err:
        print(err, file=sys.stderr)
        return 2
    report.update({"format": args.format, "path": str(Path(args.path).resolve()), "total_s": time.perf_counter() - start,
                   "command": " ".join(sys.argv), "files": dataclasses.asdict(placement)})
    (out / "import.json").write_text(json.dumps(report, indent=1))
    print(report["coverage"])
    if report["blind_views"]:
        print(f"views that see (almost) nothing (< {100 * MIN_HIT_FRACTION:g} % of rays hit the mesh): {', '.join(report['blind_views'])}")
    print(report["uv_table"])
    print(f"exposure: {report['exposure']}")
    print("timings: " + ", ".join(f"{k} {v:.1f} s" for k, v in report["timings"].items()) + f", total {report['total_s']:.1f} s")
    print(f"wrote {scene_json} ({report['views']} views, {report['faces']} faces, {len(report['objects'])} objects)")
    print(placement.summary(out))
    files = [p for v in scene.views for p in (v.photo, v.mask, *v.targets.values(), *v.ground_truth.values()) if p]
    outside = sum(not is_inside(p, out) for p in files)
    allow = ""
    if outside:
        allow = f" {ALLOW_FLAG}"
        where = "through symlinks that lead to" if args.link == "symlink" else "where the dataset keeps them,"
        print(f"note: scene.json names {outside} files {where} outside {out}; the main job reads them with "
              f"{ALLOW_FLAG} (or import again with --link=hardlink or --link=copy to place them in {out})")
    print(f"run:  jaxdistill distill --scene={out} --out_dir=runs/{scene.name}{allow}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
