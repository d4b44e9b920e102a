"""`scripts/bench_main.py`'s own parts: it finds the estimates' time in a log line written with the
package's own format string, reads the pinned revision's config through git (and names what is
missing when it cannot), and takes ratios only of figures both runs have."""

from __future__ import annotations

import ast
import importlib.util
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def bench():
    spec = importlib.util.spec_from_file_location("bench_main", REPO / "scripts" / "bench_main.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules["bench_main"] = module
    spec.loader.exec_module(module)
    return module


def estimates_log_format() -> str:
    """The format string of the log line `models.estimates` writes when it has made the estimates."""
    tree = ast.parse((REPO / "jaxdistill" / "models" / "estimates.py").read_text(encoding="utf-8"))
    for node in ast.walk(tree):
        if (isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) and node.func.attr == "info"
                and node.args and isinstance(node.args[0], ast.Constant)
                and "per-view estimates" in node.args[0].value):
            return node.args[0].value
    raise AssertionError("models/estimates.py no longer logs the estimates' time")


def test_the_estimates_time_is_read_from_the_packages_own_log_line(bench):
    line = "I1126 15:26:55 estimates.py:111] " + estimates_log_format() % (48, 5, 113.4, "/cache/estimates/ab12")
    found = bench.ESTIMATES_LINE.findall(line)
    assert found and float(found[-1][2]) == pytest.approx(113.0)


def test_the_pinned_config_comes_from_git_or_the_error_names_it(bench, tmp_path):
    if subprocess.run(["git", "-C", str(REPO), "rev-parse", "HEAD"], capture_output=True).returncode:
        pytest.skip("not a git checkout")
    got = bench.pinned_config("HEAD", "configs/bedroom.cfg", tmp_path / "pinned.cfg")
    shown = subprocess.run(["git", "-C", str(REPO), "show", "HEAD:configs/bedroom.cfg"], capture_output=True, text=True)
    assert got.read_text() == shown.stdout
    with pytest.raises(SystemExit, match="--pinned=no-such-rev"):
        bench.pinned_config("no-such-rev", "configs/bedroom.cfg", tmp_path / "x.cfg")


def test_ratios_only_of_figures_both_runs_have(bench):
    now = {"wall_s": 300.0, "cpu_s": 500.0, "estimates_s": None, "seconds_per_step": 2.0}
    pinned = {"wall_s": 600.0, "cpu_s": 0.0, "estimates_s": 100.0, "seconds_per_step": 4.0}
    assert bench.ratios(now, pinned) == {"wall_s": 0.5, "seconds_per_step": 0.5}
