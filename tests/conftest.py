"""Shared fixtures: small synthetic scenes with analytic geometry."""

from __future__ import annotations

import os
import shutil
import tempfile
from pathlib import Path

os.environ.setdefault("JAX_PLATFORMS", "cpu")
# One persistent XLA compilation cache for the whole run, its workers and the main jobs they start
# as subprocesses: the tests compile the same small programs many times over (every pipeline.run
# jits its own closures; every subprocess starts cold). Set here, before jax is imported; the
# controller's folder is inherited by the xdist workers, and removed when the run ends. A cache of
# one's own (JAX_COMPILATION_CACHE_DIR set) is used as it is and left alone.
_OWN_XLA_CACHE = "JAX_COMPILATION_CACHE_DIR" not in os.environ
if _OWN_XLA_CACHE:
    os.environ["JAX_COMPILATION_CACHE_DIR"] = tempfile.mkdtemp(prefix="jaxdistill-tests-xla-")
    os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", "0.2")
# The suite's programs are small and run a few times each, so most of its time is XLA compiling
# them: LLVM's back end at optimisation level 0 compiles them 2-3.5x faster (a tiny VAE's random
# init 45 -> 13 s, its training step 10 -> 5.6 s) and runs them slower, which only the few large
# ones notice. Set for the workers and the main jobs they start; a level given in XLA_FLAGS wins.
# Results agree within the tests' tolerances at either level (no fast-math at either).
if "xla_backend_optimization_level" not in os.environ.get("XLA_FLAGS", ""):
    os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "") + " --xla_backend_optimization_level=0").strip()
# At level 0 XLA's own code is unoptimised and jaxlib's YNNPACK library fusions, which
# `import jaxdistill` turns off for real runs (jaxdistill/xla_flags.py), are the faster ones: the
# suite keeps jaxlib's defaults (test_unet_matches_diffusers 16.5 -> 11.4 s). tests/test_xla_flags.py
# checks the package's flags in processes of its own. A value given in the environment wins.
os.environ.setdefault("JAXDISTILL_XLA_FLAGS", "0")
# XLA's older loop emitters compile the suite's small programs faster than its MLIR fusion emitters (jaxlib
# 0.10's default): test_main.py's auto-prior run 36.8-37.7 -> 29.1-33.3 s alone, the summed test times 0.87x
# (docs/benchmarks.md §8). Not for real runs: at the main job's level they compile and run its step slower.
# Results differ from the default emitters' in float32 rounding only (the tests' tolerances, tests/tolerance.py).
# Only from the jaxlib it was measured with (XLA aborts on a flag it does not know): xla_flags.py's check, read
# once JAXDISTILL_XLA_FLAGS is set, so importing the package applies none of its own flags here.
from jaxdistill.xla_flags import MIN_JAXLIB, jaxlib_version  # noqa: E402

if "xla_cpu_use_fusion_emitters" not in os.environ.get("XLA_FLAGS", "") and (jaxlib_version() or (0, 0)) >= MIN_JAXLIB:
    os.environ["XLA_FLAGS"] = (os.environ["XLA_FLAGS"] + " --xla_cpu_use_fusion_emitters=false").strip()

import numpy as np
import pytest

from jaxdistill.scene import cameras


# The modules whose tests take minutes (an end-to-end run or a training in a fixture or a test;
# `pytest --durations=30` lists them), slowest first. They are collected first, so that `pytest -n 2 --dist
# loadfile` (the README's test command) starts them at once and the quick modules fill in around
# them, instead of one of them running alone at the end.
SLOW_MODULES = ("test_train_rgbx.py", "test_view.py", "test_main.py", "test_prepare_scene.py", "test_walkthrough.py",
                "test_prior.py", "test_models.py", "test_shipped_model.py", "test_speed_vs_error.py", "test_distill.py")


def pytest_configure(config):
    # pytest-xdist's loadfile keeps the order collected only with --no-loadscope-reorder (3.8; by
    # default, and always before 3.8, it puts the files with more tests first, which had put modules
    # of a few slow tests, such as the training tests, in the second half of the queue). Off here
    # unless --loadscope-reorder is given.
    if hasattr(config.option, "loadscopereorder") and "--loadscope-reorder" not in config.invocation_params.args:
        config.option.loadscopereorder = False


def pytest_sessionfinish(session, exitstatus):
    if _OWN_XLA_CACHE and not hasattr(session.config, "workerinput"):         # the controller, or a run without -n
        shutil.rmtree(Path(os.environ["JAX_COMPILATION_CACHE_DIR"]), ignore_errors=True)


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
def run_rgbx_dir(tmp_path_factory):
    """A tiny random RGB↔X folder for end-to-end runs: `rgbx_dir`'s blocks and widths with one
    layer per block and one text layer, so a run traces and compiles about half the graph. Runs
    prove what the pipeline does with a prior (resume, reuse, scoring against its estimates, dataset
    scenes), not the networks' structure, which `rgbx_dir` proves against diffusers and transformers."""
    pytest.importorskip("torch")
    from tiny_rgbx import TINY_TEXT, TINY_UNET, TINY_VAE, write_tiny_rgbx

    return write_tiny_rgbx(tmp_path_factory.mktemp("rgbx_run") / "rgb-to-x", unet=dict(TINY_UNET, layers_per_block=1),
                           vae=dict(TINY_VAE, layers_per_block=1), text=dict(TINY_TEXT, num_hidden_layers=1))


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
