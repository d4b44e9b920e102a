"""`scripts/bench_step.py`'s own arithmetic: the FLOP count it reports (against the analytic count
of a convolution and a matrix product), the device's bf16 peak by name, and the summary table's
speed-ups and projected thesis run (17 000 steps of every map)."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import pytest

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def bench():
    spec = importlib.util.spec_from_file_location("bench_step", REPO / "scripts" / "bench_step.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules["bench_step"] = module
    spec.loader.exec_module(module)
    return module


def test_flops_are_counted_before_optimisation_and_match_the_analytic_count(bench):
    n, h, w, c, k, kh = 2, 12, 10, 8, 16, 3

    def f(x, kernel, m):
        y = jax.lax.conv_general_dilated(x, kernel, (1, 1), "VALID", dimension_numbers=("NHWC", "HWIO", "NHWC"))
        return y @ m

    args = (jnp.ones((n, h, w, c)), jnp.ones((kh, kh, c, k)), jnp.ones((k, 5)))
    ho, wo = h - kh + 1, w - kh + 1
    conv = 2 * n * ho * wo * k * kh * kh * c
    matmul = 2 * n * ho * wo * k * 5
    assert bench.cost_flops(jax.jit(f).lower(*args)) == pytest.approx(conv + matmul, rel=0.02)


def test_bf16_peak_by_device_name(bench):
    assert bench.bf16_peak_tflops("NVIDIA H200", None) == bench.BF16_PEAK_TFLOPS["H200"]
    assert bench.bf16_peak_tflops("NVIDIA H100 80GB HBM3", None) == bench.BF16_PEAK_TFLOPS["H100"]
    assert bench.bf16_peak_tflops("cpu", None) is None
    assert bench.bf16_peak_tflops("NVIDIA H200", 500.0) == 500.0


def row(framework, dtype, maps, step_s, **extra):
    return {"framework": framework, "dtype": dtype, "render": [384, 512], "maps": list(bench_maps(maps)),
            "step_s": step_s, **extra}


def bench_maps(count):
    return ("albedo", "normal", "roughness", "metallic", "irradiance")[:count]


def test_summary_gives_speedups_and_the_projected_thesis_run(bench):
    rows = [row("jax", "float32", 1, 0.02, device_peak_gb=4.0), row("jax", "bfloat16", 1, 0.01),
            row("torch", "float32", 1, 0.09), row("jax", "float32", 5, 0.08), row("torch", "float32", 5, 0.44)]
    table = {e["maps"]: e for e in bench.summarise(rows)["table"]}
    assert table[1]["speedup_jax_float32"] == pytest.approx(0.09 / 0.02)
    assert table[1]["speedup_jax_bfloat16"] == pytest.approx(0.09 / 0.01)
    assert table[1]["jax_float32_device_peak_gb"] == 4.0
    # 5 maps x 17 000 steps: one map a step costs five runs; five maps a step, one run
    assert table[1]["jax_float32_thesis_run_min"] == pytest.approx(0.02 * 17_000 * 5 / 60)
    assert table[5]["torch_float32_thesis_run_min"] == pytest.approx(0.44 * 17_000 / 60)
    assert "float32 5.50x" in bench.headline(bench.summarise(rows))


def test_a_step_with_x0_reuse_is_a_row_of_its_own_against_the_same_recipe(bench):
    """--reuse_steps=1,2: our step with the prior every step and with x̂0 reused over 2 steps, each
    against the recipe; the every-step row keeps its name, so earlier JSON reads the same."""
    rows = [row("jax", "float32", 1, 0.02, reuse_steps=1), row("jax", "float32", 1, 0.012, reuse_steps=2),
            row("torch", "float32", 1, 0.09)]
    (entry,) = bench.summarise(rows)["table"]
    assert entry["speedup_jax_float32"] == pytest.approx(0.09 / 0.02)
    assert entry["speedup_jax_float32_reuse2"] == pytest.approx(0.09 / 0.012)
    assert entry["jax_float32_reuse2_s"] == 0.012
    assert bench.headline(bench.summarise(rows)).endswith("1 map(s): float32 4.50x, float32_reuse2 7.50x")


def test_both_workers_start_with_the_huge_page_tunable_the_package_adds_to_itself(bench, monkeypatch):
    """--huge_pages (default): the workers' environment gets glibc's tunable exactly where the package's
    commands would add it to themselves (`huge_pages.tunables_to_add`); a value given is kept; false: as started."""
    from jaxdistill import huge_pages

    monkeypatch.setattr(huge_pages, "glibc_version", lambda: (2, 36))
    monkeypatch.setattr(huge_pages, "thp_mode", lambda: "madvise")
    for name in ("GLIBC_TUNABLES", huge_pages.RAN_AGAIN, huge_pages.OFF):
        monkeypatch.delenv(name, raising=False)
    assert bench.worker_environment(True)["GLIBC_TUNABLES"] == "glibc.malloc.hugetlb=1"
    assert "GLIBC_TUNABLES" not in bench.worker_environment(False)
    monkeypatch.setenv("GLIBC_TUNABLES", "glibc.malloc.arena_max=2")
    assert bench.worker_environment(True)["GLIBC_TUNABLES"] == "glibc.malloc.arena_max=2:glibc.malloc.hugetlb=1"
    monkeypatch.setenv("GLIBC_TUNABLES", "glibc.malloc.hugetlb=0")        # the user's value wins
    assert bench.worker_environment(True)["GLIBC_TUNABLES"] == "glibc.malloc.hugetlb=0"
    monkeypatch.delenv("GLIBC_TUNABLES")
    monkeypatch.setattr(huge_pages, "thp_mode", lambda: "always")         # nothing to add where it does nothing
    assert "GLIBC_TUNABLES" not in bench.worker_environment(True)
