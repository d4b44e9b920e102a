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
