"""Shared fixtures: small synthetic scenes with analytic geometry."""

from __future__ import annotations

import os

os.environ.setdefault("JAX_PLATFORMS", "cpu")

import numpy as np
import pytest

from jaxdistill.scene import cameras


# The modules whose tests take minutes (an end-to-end run or a training in a fixture or a test;
# `pytest --durations=30` lists them), slowest first. They are collected first, so that `pytest -n 2 --dist
# loadfile` (the README's test command) starts them at once and the quick modules fill in around
# them, instead of one of them running alone at the end.
SLOW_MODULES = ("test_train_rgbx.py", "test_view.py", "test_prepare_scene.py", "test_smoke_outputs.py", "test_main.py",
                "test_photo.py", "test_walkthrough.py")


def pytest_collection_modifyitems(config, items):
    rank = {name: i for i, name in enumerate(SLOW_MODULES)}
    items.sort(key=lambda item: rank.get(item.path.name, len(rank)))      # stable: order kept within a module


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
