"""Shared fixtures: small synthetic scenes with analytic geometry."""

from __future__ import annotations

import os

os.environ.setdefault("JAX_PLATFORMS", "cpu")

import numpy as np
import pytest

from jaxdistill import cameras


def intrinsics(width: int, height: int, fx: float, fy: float | None = None, cx: float | None = None,
               cy: float | None = None) -> np.ndarray:
    """K with the principal point at the image centre unless given."""
    return np.array([[fx, 0.0, width / 2 if cx is None else cx],
                     [0.0, fy or fx, height / 2 if cy is None else cy],
                     [0.0, 0.0, 1.0]])


def look_at_camera(eye, target, width=32, height=24, fx=30.0, up=(0.0, 1.0, 0.0), **kw) -> cameras.Camera:
    """A canonical camera at `eye` looking at `target`."""
    return cameras.look_at(np.asarray(eye, float), np.asarray(target, float), np.asarray(up, float),
                           intrinsics(width, height, fx, **kw), width, height)


@pytest.fixture
def cache_dir(tmp_path):
    return tmp_path / "cache"


@pytest.fixture(scope="session")
def rgbx_dir(tmp_path_factory):
    """A tiny random RGB↔X folder (diffusers/transformers save_pretrained, safetensors)."""
    pytest.importorskip("torch")
    from tiny_rgbx import write_tiny_rgbx

    return write_tiny_rgbx(tmp_path_factory.mktemp("rgbx") / "rgb-to-x")


@pytest.fixture(scope="session")
def loaded(rgbx_dir):
    """The tiny folder loaded by our converter (float32)."""
    from jaxdistill.models import convert

    return convert.load_rgbx(rgbx_dir)


@pytest.fixture(scope="session")
def torch_models(rgbx_dir):
    """(unet, vae, text_encoder) PyTorch references read from the same folder."""
    from diffusers import AutoencoderKL, UNet2DConditionModel
    from transformers import CLIPTextModel

    return (UNet2DConditionModel.from_pretrained(rgbx_dir / "unet").eval(),
            AutoencoderKL.from_pretrained(rgbx_dir / "vae").eval(),
            CLIPTextModel.from_pretrained(rgbx_dir / "text_encoder").eval())
