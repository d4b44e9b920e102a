"""The XLA flags `import jaxdistill` sets (jaxdistill/xla_flags.py): appended to XLA_FLAGS unless
the user named the flag, in effect in the programs JAX then compiles, and a warning instead of a
silent no-op when JAX already runs."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

from jaxdistill import xla_flags

FLAG = "--xla_cpu_experimental_ynn_fusion_type"

# a dot with an element-wise consumer: what jaxlib's YNNPACK fusions take when they are on
COMPILED_TEXT = """
import jax, jax.numpy as jnp
text = jax.jit(lambda a, b: jnp.tanh(a @ b)).lower(jnp.ones((64, 64)), jnp.ones((64, 64))).compile().as_text()
print("YNN" if "ynn_fusion" in text else "NO-YNN")
"""


def run_python(code: str, xla: str | None, opt_out: bool = False) -> subprocess.CompletedProcess:
    env = dict(os.environ, JAX_PLATFORMS="cpu")
    env.pop("XLA_FLAGS", None)
    env.pop("JAXDISTILL_XLA_FLAGS", None)           # the suite's own setting (tests/conftest.py)
    if opt_out:
        env["JAXDISTILL_XLA_FLAGS"] = "0"
    if xla is not None:
        env["XLA_FLAGS"] = xla
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, check=True)


def test_flags_are_appended_unless_the_user_named_them():
    assert xla_flags.with_flags("") == f"{FLAG}="
    assert xla_flags.with_flags(" --xla_backend_optimization_level=0 ") == \
        f"--xla_backend_optimization_level=0 {FLAG}="
    assert xla_flags.with_flags(f"{FLAG}=dot") == f"{FLAG}=dot"                 # the user's value wins
    once = xla_flags.with_flags("--a=1")
    assert xla_flags.with_flags(once) == once                                     # idempotent
    env = {"XLA_FLAGS": "--xla_force_host_platform_device_count=2"}
    assert xla_flags.apply(env) is True
    assert env["XLA_FLAGS"] == f"--xla_force_host_platform_device_count=2 {FLAG}="
    env = {"JAXDISTILL_XLA_FLAGS": "0", "XLA_FLAGS": "--a=1"}
    assert xla_flags.apply(env) is False and env["XLA_FLAGS"] == "--a=1"          # jaxlib's own defaults


def test_a_jaxlib_older_than_the_flag_or_unknown_is_left_alone():
    """XLA aborts on a flag its build does not know: older jaxlibs get nothing."""
    for version in ((0, 4, 35), (0, 9, 9), None):
        env = {"XLA_FLAGS": "--a=1"}
        assert xla_flags.apply(env, version=version) is False and env == {"XLA_FLAGS": "--a=1"}
    env = {}
    assert xla_flags.apply(env, version=xla_flags.MIN_JAXLIB) is True and env["XLA_FLAGS"] == f"{FLAG}="
    assert xla_flags.jaxlib_version()[:2] >= (0, 4)                # read from the installed jaxlib's metadata


def test_importing_the_package_turns_the_library_fusions_off_and_a_users_value_wins():
    if xla_flags.jaxlib_version() < xla_flags.MIN_JAXLIB:
        pytest.skip("this jaxlib predates the flag: the package sets nothing")
    # the control: jaxlib's defaults (the package's flags opted out) fuse this program
    if run_python("import jaxdistill\n" + COMPILED_TEXT, None, opt_out=True).stdout.split()[-1] == "NO-YNN":
        pytest.skip("this jaxlib's CPU backend makes no YNNPACK fusions here: the flag has nothing to turn off")
    assert run_python("import jaxdistill\n" + COMPILED_TEXT, f"{FLAG}=dot,eltwise").stdout.split()[-1] == "YNN"
    assert run_python("import jaxdistill\n" + COMPILED_TEXT, None).stdout.split()[-1] == "NO-YNN"
    assert run_python("import jaxdistill\n" + COMPILED_TEXT, "").stdout.split()[-1] == "NO-YNN"
    # jax imported first is fine: XLA reads the flags when its first backend starts
    assert run_python("import jax\nimport jaxdistill\n" + COMPILED_TEXT, None).stdout.split()[-1] == "NO-YNN"


def test_importing_after_jax_computed_warns_and_changes_nothing():
    if xla_flags.jaxlib_version() < xla_flags.MIN_JAXLIB:
        pytest.skip("this jaxlib predates the flag: the package sets nothing")
    code = ("import os, warnings, jax.numpy as jnp\n"
            "jnp.ones(2).block_until_ready()\n"
            "with warnings.catch_warnings(record=True) as caught:\n"
            "    warnings.simplefilter('always')\n"
            "    import jaxdistill\n"
            "print(repr(os.environ.get('XLA_FLAGS')))\n"
            "print([str(w.message) for w in caught])\n")
    out = run_python(code, None).stdout.splitlines()
    assert out[-2] == "None"
    assert "was not applied" in out[-1] and FLAG in out[-1]
    # a flag already there (given, or inherited from a parent that imported the package) needs no warning
    out = run_python(code, f"{FLAG}=").stdout.splitlines()
    assert out[-2] == repr(f"{FLAG}=") and out[-1] == "[]"
