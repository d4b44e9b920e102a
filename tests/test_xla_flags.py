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


def run_python(code: str, xla: str | None) -> subprocess.CompletedProcess:
    env = dict(os.environ, JAX_PLATFORMS="cpu")
    env.pop("XLA_FLAGS", None)
    env.pop("JAXDISTILL_XLA_FLAGS", None)           # the suite's own setting (tests/conftest.py)
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


def test_importing_the_package_turns_the_library_fusions_off_and_a_users_value_wins():
    users = run_python("import jaxdistill\n" + COMPILED_TEXT, f"{FLAG}=dot,eltwise").stdout.split()[-1]
    if users == "NO-YNN":
        pytest.skip("this jaxlib's CPU backend makes no YNNPACK fusions: the flag has nothing to turn off")
    assert run_python("import jaxdistill\n" + COMPILED_TEXT, None).stdout.split()[-1] == "NO-YNN"
    assert run_python("import jaxdistill\n" + COMPILED_TEXT, "").stdout.split()[-1] == "NO-YNN"


def test_importing_after_jax_computed_warns_and_changes_nothing():
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
