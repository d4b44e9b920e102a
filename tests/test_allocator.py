"""`allocator.keep_freed_memory`: glibc's mallopt settings for the main job, the opt-out, a refusal."""

from __future__ import annotations

import subprocess
import sys

import pytest
from absl import app

from jaxdistill import allocator


def test_glibc_accepts_the_settings_in_a_fresh_process():
    """In its own process (the settings are process-wide): True where the C library is glibc."""
    if allocator._glibc() is None:
        pytest.skip("not glibc: keep_freed_memory does nothing here")
    done = subprocess.run([sys.executable, "-c", "from jaxdistill import allocator; "
                           "print(allocator.keep_freed_memory())"], capture_output=True, text=True, check=True)
    assert done.stdout.strip().splitlines()[-1] == "True"


def test_the_environment_opts_out_without_touching_malloc(monkeypatch):
    monkeypatch.setattr(allocator, "_glibc", lambda: pytest.fail("mallopt called despite JAXDISTILL_MALLOC=system"))
    assert allocator.keep_freed_memory({allocator.ENV: "System "}) is False


def test_a_refused_parameter_is_said_and_reported(monkeypatch):
    calls = []

    class Refusing:
        def mallopt(self, name, value):
            calls.append((name.value, value.value))
            return 0 if name.value == allocator.M_ARENA_MAX else 1

    warnings = []
    monkeypatch.setattr(allocator, "_glibc", lambda: Refusing())
    monkeypatch.setattr(allocator.logging, "warning", lambda msg, *args: warnings.append(msg % args))
    assert allocator.keep_freed_memory({}) is False
    assert calls == [(n, v) for n, v in allocator.SETTINGS]
    assert len(warnings) == 1 and str(allocator.M_ARENA_MAX) in warnings[0]


def test_the_main_job_sets_malloc_before_anything_else(monkeypatch):
    """`python -m jaxdistill.main` applies the settings first, before its arguments are even looked at."""
    from jaxdistill import main as main_module

    order = []
    monkeypatch.setattr(main_module.allocator, "keep_freed_memory", lambda: order.append("malloc"))
    with pytest.raises(app.UsageError, match="unexpected arguments"):
        main_module.main(["jaxdistill.main", "stray"])
    assert order == ["malloc"]
