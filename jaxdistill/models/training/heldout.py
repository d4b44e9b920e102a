"""What scoring the prior's per-image estimates on held-out shards compares, in file space.

`shard_ground_truth` decodes one image's exact maps from a shard, `to_file_space` turns an
estimate (`prior.estimate_batch(gamma=False)`) into the same space, and `trivial` /
`trivial_linear` are the baseline every estimate must beat: the photo as albedo (linear), the
mean material, normals facing the camera, the photo's luminance as irradiance. Used by
`scripts/eval_rgbx_model.py` (the model card's figures) and `scripts/experiment_rgbx.py`.
"""

from __future__ import annotations

import numpy as np

from jaxdistill.io import images as imageio
from jaxdistill.models import prior as rgbx

TRIVIAL_ROUGHNESS, TRIVIAL_METALLIC = 0.6, 0.05


def shard_ground_truth(z, i: int) -> dict:
    """File-space GT maps of image i of a shard (uint8 arrays as make_rgbx_data writes them)."""
    f = lambda k: z[k][i].astype(np.float32) / 255.0          # noqa: E731
    return {"albedo": imageio.srgb_to_linear(f("albedo")), "normal": 2.0 * f("normal") - 1.0,
            "roughness": f("roughness")[..., :1], "metallic": f("metallic")[..., :1],
            "irradiance": imageio.srgb_to_linear(f("irradiance"))}


def trivial(photo_srgb: np.ndarray) -> dict:
    """The trivial baseline of an sRGB photo in [0, 1] (see `trivial_linear`)."""
    return trivial_linear(imageio.srgb_to_linear(photo_srgb))


def trivial_linear(linear: np.ndarray) -> dict:
    """The trivial baseline of a linear photo in [0, 1]: the photo as albedo, the mean material,
    normals facing the camera, the photo's luminance as irradiance."""
    h, w = linear.shape[:2]
    grey = linear @ np.array([0.2126, 0.7152, 0.0722], np.float32)
    return {"albedo": linear, "normal": np.broadcast_to(np.float32([0, 0, 1]), (h, w, 3)),
            "roughness": np.full((h, w, 1), TRIVIAL_ROUGHNESS, np.float32),
            "metallic": np.full((h, w, 1), TRIVIAL_METALLIC, np.float32), "irradiance": np.repeat(grey[..., None], 3, -1)}


def to_file_space(name: str, image: np.ndarray) -> np.ndarray:
    """`estimate_batch(gamma=False)` output of one map → the file space metrics compare."""
    if name == "normal":
        return 2.0 * image - 1.0
    return image[..., :1] if name in rgbx.GREY_MAPS else image
