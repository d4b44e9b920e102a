"""The `jaxdistill` command: dispatch to the modules, help listing our flags first, errors."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from jaxdistill import cli

REPO = Path(__file__).resolve().parents[1]


def jaxdistill(*args, **kw):
    return subprocess.run([sys.executable, "-m", "jaxdistill", *args], cwd=REPO, capture_output=True, text=True,
                          timeout=300, **kw)


def test_usage_unknown_command_and_missing_viewer(capsys, monkeypatch):
    assert cli.main(["jaxdistill"]) == 2
    assert "usage: jaxdistill COMMAND" in capsys.readouterr().err
    assert cli.main(["jaxdistill", "--help"]) == 0
    text = capsys.readouterr().out
    assert all(name in text for name in ("distill", "estimate", "precompute", "import", "view"))
    assert cli.main(["jaxdistill", "train"]) == 2
    assert "unknown command 'train'" in capsys.readouterr().err
    monkeypatch.setitem(sys.modules, "jaxdistill.view", None)      # an installation without the viewer
    assert cli.main(["jaxdistill", "view", "out/bedroom"]) == 2
    assert "has no viewer (jaxdistill.view is not installed)" in capsys.readouterr().err


def test_view_dispatches_to_the_viewers_main(monkeypatch):
    import types

    seen = {}
    viewer = types.ModuleType("jaxdistill.view")
    viewer.main = lambda: seen.setdefault("argv", list(sys.argv)) and 7
    monkeypatch.setitem(sys.modules, "jaxdistill.view", viewer)
    monkeypatch.setattr(sys, "argv", ["jaxdistill"])
    assert cli.main(["jaxdistill", "view", "out/x", "--port=1"]) == 7
    assert seen["argv"] == ["jaxdistill view", "out/x", "--port=1"]


def test_distill_help_lists_our_flags_first_and_short_help_has_them():
    short = jaxdistill("distill", "--helpshort")          # absl's help exits 1, as with python -m
    assert short.returncode == 1, short.stderr
    for flag in ("--scene", "--steps", "--prior", "--keep_checkpoints", "--eval_every"):
        assert flag in short.stdout
    full = jaxdistill("distill", "--helpfull").stdout
    assert full.index("  --scene:") < full.index("absl.app:") < full.index("--[no]logtostderr")


@pytest.mark.parametrize("command", ["precompute", "estimate", "import"])
def test_other_commands_reach_their_modules(command):
    result = jaxdistill(command, "--help")
    assert result.returncode == (0 if command == "import" else 1), result.stderr       # argparse 0, absl 1
    expected = {"precompute": "--texture_size", "estimate": "--steps", "import": "--format"}[command]
    assert expected in result.stdout


def test_bad_flag_exits_like_python_m():
    result = jaxdistill("distill", "--scene=bedroom", "--out_dir=out/x", "--steps=0")
    assert result.returncode == 1 and "--steps: must be >= 1" in result.stderr


def test_config_names_a_shipped_config_and_later_flags_override_it():
    from jaxdistill import main

    assert main.config_names() == ["bedroom", "smoke", "thesis"]
    smoke = main.CONFIGS_DIR / "smoke.cfg"
    assert main.expand_configs(["x", "--config=smoke", "--steps=3"]) == ["x", f"--flagfile={smoke}", "--steps=3"]
    assert main.expand_configs(["x", "--config", "smoke", "--view"]) == ["x", f"--flagfile={smoke}", "--view"]
    result = jaxdistill("distill", "--config=smoke", "--steps=0")       # scene and out_dir come from the config
    assert result.returncode == 1 and "--steps: must be >= 1" in result.stderr, result.stderr
    assert "--scene: is required" not in result.stderr and "--out_dir: is required" not in result.stderr
    result = jaxdistill("distill", "--config=nope")
    assert result.returncode == 1
    assert "--config=nope: no such config" in result.stderr and "bedroom, smoke, thesis" in result.stderr
