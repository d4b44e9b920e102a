"""Test helpers for the RGB↔X networks: `rel_err`, and the package's random-weight folders
(`jaxdistill.models.training.random_model`) under the names the tests import from here."""

from __future__ import annotations

import numpy as np

from jaxdistill.models.training.random_model import (TINY_TEXT, TINY_UNET, TINY_VAE, nchw, nhwc,  # noqa: F401
                                                     write_tiny_rgbx)


def rel_err(ours, ref) -> float:
    """max |ours − ref| / max |ref| (float64), after checking the shapes agree."""
    ours, ref = np.asarray(ours, np.float64), np.asarray(ref, np.float64)
    assert ours.shape == ref.shape, (ours.shape, ref.shape)
    return float(np.abs(ours - ref).max() / np.abs(ref).max())
