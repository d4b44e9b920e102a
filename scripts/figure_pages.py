"""Before/after figure of exported pages seen by a renderer: a view of the bedroom rendered from
two runs' exported albedo pages (maps/albedo/*.exr) with trilinear mip sampling, as a game engine
samples them (`sampler.sample_pages`), side by side with the ground truth.

    python scripts/figure_pages.py --before=OUT_A --after=OUT_B --view=view_031 --out=docs/img/render.png
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from jaxdistill.evaluate import ground_truth as evaluation
from jaxdistill.io import images as imageio
from jaxdistill.render import fragments as fr  # noqa: E402
from jaxdistill.render.sampler import sample_pages  # noqa: E402
from jaxdistill.scene.model import read_scene  # noqa: E402
from jaxdistill.scenes import scene_path  # noqa: E402


def render(run: Path, scene, frag) -> np.ndarray:
    """(H, W, 3) display albedo of `run`'s exported pages through `frag`, trilinear."""
    pages = [imageio.read_image(run / "maps" / "albedo" / f"{name}.exr") for name in scene.mesh.object_names]
    image = sample_pages(pages, [frag], range(scene.num_objects), sampler="trilinear")[0]
    return evaluation.display_image("albedo", np.where(frag.hit[..., None], image, 0.0))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--before", required=True)
    parser.add_argument("--after", required=True)
    parser.add_argument("--view", default="view_031")
    parser.add_argument("--out", required=True)
    args = parser.parse_args()
    scene = read_scene(scene_path("bedroom"))
    view = next(v for v in scene.views if v.name == args.view)
    frag = fr.compute_fragments(scene.mesh, [view.camera])[0]
    _, gt = evaluation.view_ground_truth(scene, [frag])
    images = [render(Path(args.before), scene, frag), render(Path(args.after), scene, frag),
              evaluation.display_image("albedo", gt[0]["albedo"])]
    gap = np.ones((images[0].shape[0], 6, 3), np.float32)
    row = np.concatenate([images[0], gap, images[1], gap, images[2]], axis=1)
    imageio.write_image(args.out, row, encode_srgb=False)


if __name__ == "__main__":
    main()
