"""Renders the embedded bedroom's per-view irradiance ground truth into its folder.

    python scripts/make_bedroom_irradiance.py [--scene=jaxdistill/scenes/bedroom] [--seed=0]
        [--spp=make_bedroom.IRRADIANCE_SPP]

The bedroom's photos were path traced by `scripts/make_bedroom.py`; this renders, for every
view, the irradiance E/pi at each pixel's first hit in the photos' units from the same Mitsuba
scene (`jaxdistill.datasets.mitsuba.bedroom.mitsuba_scene` on the same geometry, the folder's
GT pages and cameras), exactly as `make_bedroom.generate` does (`make_bedroom.write_irradiance`),
so that a regeneration of the whole folder writes the same files:

- ground_truth/irradiance/<view>.exr (half float, linear, not exposed);
- each view's `ground_truth.irradiance` in scene.json (nothing else in it changes);
- manifest.sha256, and the README's irradiance section with the check photo / (albedo x
  irradiance) on diffuse pixels (`jaxdistill.evaluate.consistency.scene_consistency`).
"""

from __future__ import annotations

import argparse
import json
import os
import re
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from jaxdistill.evaluate.ground_truth import read_ground_truth  # noqa: E402
from jaxdistill.scene.model import read_scene  # noqa: E402

import make_bedroom  # noqa: E402

GEOMETRY_TOLERANCE = 1e-5     # metres / uv units: the folder's mesh.glb (float32) against the rebuilt one


def rebuilt_mesh(scene):
    """The generator's own mesh (float64, as make_bedroom renders it), checked against the folder's."""
    objs = make_bedroom.bedroom_objects()
    mesh, _ = make_bedroom.build_scene_geometry(objs)
    if tuple(mesh.object_names) != tuple(scene.mesh.object_names) or mesh.faces.shape != scene.mesh.faces.shape:
        raise ValueError(f"{scene.root}: its objects or faces differ from make_bedroom.py's bedroom")
    corners = [(np.asarray(m.vertices)[np.asarray(m.faces)], np.asarray(m.uv), np.asarray(m.face_object))
               for m in (mesh, scene.mesh)]
    (a, ua, oa), (b, ub, ob) = corners
    if not (np.array_equal(oa, ob) and np.abs(a - b).max() < GEOMETRY_TOLERANCE and np.abs(ua - ub).max() < GEOMETRY_TOLERANCE):
        raise ValueError(f"{scene.root}: its mesh differs from make_bedroom.py's bedroom")
    return mesh


def add_ground_truth(folder: Path, paths: dict[str, Path]) -> None:
    """Adds `ground_truth.irradiance` to every view of folder/scene.json, as write_scene writes it
    (after `targets`, relative paths), every other byte unchanged."""
    file = folder / "scene.json"
    text = file.read_text()
    doc = json.loads(text)
    if json.dumps(doc, indent=1) != text:
        raise ValueError(f"{file}: not in write_scene's layout (json indent 1); refusing to rewrite it")
    for entry in doc["views"]:
        ground_truth = {k: v for k, v in entry.get("ground_truth", {}).items() if k != "irradiance"}
        ground_truth["irradiance"] = os.path.relpath(paths[entry["name"]], folder).replace(os.sep, "/")
        entry.pop("ground_truth", None)
        entry["ground_truth"] = ground_truth
    tmp = file.with_suffix(".json.tmp")
    tmp.write_text(json.dumps(doc, indent=1))
    os.replace(tmp, file)


def update_readme(folder: Path, section: str) -> None:
    """Replaces (or inserts before '## Our sampler against Mitsuba') the README's irradiance section."""
    path = folder / "README.md"
    text = path.read_text() if path.is_file() else ""
    pattern = re.compile(r"## Irradiance ground truth\n.*?(?=\n## |\Z)", re.S)
    if pattern.search(text):
        text = pattern.sub(lambda _: section, text)
    elif "## Our sampler against Mitsuba" in text:
        text = text.replace("## Our sampler against Mitsuba", section + "\n## Our sampler against Mitsuba")
    else:
        text += "\n" + section
    if "- `ground_truth/irradiance/<view>.exr`" not in text:
        text = text.replace("- `estimates.json`: the corruption parameters of every view.\n",
                            "- `estimates.json`: the corruption parameters of every view.\n"
                            "- `ground_truth/irradiance/<view>.exr`: per-view irradiance E/pi (see below).\n")
    path.write_text(text)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--scene", type=Path, default=make_bedroom.DEFAULT_OUT, help="the bedroom's folder")
    parser.add_argument("--seed", type=int, default=0, help="the seed make_bedroom.py made the folder with")
    parser.add_argument("--spp", type=int, default=make_bedroom.IRRADIANCE_SPP)
    args = parser.parse_args(argv)
    if args.spp < 1:
        parser.error("--spp must be >= 1")
    folder = args.scene
    scene = read_scene(folder)
    mesh = rebuilt_mesh(scene)
    pages = read_ground_truth(scene).pages            # what make_bedroom's write_textures returned
    names = [v.name for v in scene.views]
    start = time.perf_counter()
    paths = make_bedroom.write_irradiance(folder, names, [v.camera for v in scene.views], mesh, pages,
                                          spp=args.spp, seed=args.seed)
    seconds = time.perf_counter() - start
    add_ground_truth(folder, dict(zip(names, paths)))
    check = make_bedroom.irradiance_check(folder)
    manifest = make_bedroom.manifest(folder)
    (folder / "manifest.sha256").write_text("".join(f"{h}  {p}\n" for p, h in manifest.items()))
    update_readme(folder, make_bedroom.irradiance_section({"spp": args.spp, "seconds": seconds, "consistency": check}))
    d = check["diffuse"]
    size = sum(p.stat().st_size for p in paths)
    print(f"{len(paths)} views, {args.spp} spp in {seconds:.0f} s ({size / 2**20:.2f} MiB); photo / (albedo x irradiance) "
          f"on {d['pixels']} diffuse pixels: median {d['median_ratio']:.3f} (p10 {d['p10']:.3f}, p90 {d['p90']:.3f}), "
          f"ratio of sums {d['sum_ratio']:.3f}; dielectric median {check['dielectric']['median_ratio']:.3f}, "
          f"all {check['all_valid']['median_ratio']:.3f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
