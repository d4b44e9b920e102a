"""`scripts/bench_scale.py`'s own parts: its size arguments are parsed or refused by name, a
flagfile's settings come before its own, and a child's accounting (exit status, wall, peak RSS, last log line) comes from the child itself."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def bench():
    spec = importlib.util.spec_from_file_location("bench_scale", REPO / "scripts" / "bench_scale.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules["bench_scale"] = module
    spec.loader.exec_module(module)
    return module


def test_sizes_and_views_are_parsed_or_refused(bench, capsys):
    args = bench.parse_args(["--views=50,600", "--sizes=876x584,1752X1168"])
    assert args.views == [50, 600] and args.sizes == [(876, 584), (1752, 1168)]
    for bad in ("--sizes=876by584", "--views=0", "--sizes=4x4"):
        with pytest.raises(SystemExit):
            bench.parse_args([bad])
        assert "--views" in capsys.readouterr().err


def test_a_flagfile_comes_first_so_the_scale_settings_win(bench, tmp_path, capsys):
    with pytest.raises(SystemExit):
        bench.parse_args([f"--flagfile={tmp_path / 'missing.cfg'}"])
    assert "--flagfile: " in capsys.readouterr().err
    args = bench.parse_args([f"--flagfile={REPO / 'configs' / 'bedroom.cfg'}", "--steps=20"])
    cmd = bench.main_command(args, Path("scene"), Path("out"), 50)
    assert cmd[3] == f"--flagfile={(REPO / 'configs' / 'bedroom.cfg').resolve()}"
    assert cmd.index("--steps=20") > 3 and "--scene=scene" in cmd
    assert not any(c.startswith("--prior") for c in cmd)                  # the flagfile's prior (auto)
    assert "--prior=views" in bench.main_command(bench.parse_args([]), Path("s"), Path("o"), 5)
    given = bench.parse_args([f"--flagfile={REPO / 'configs' / 'bedroom.cfg'}", "--prior=views"])
    assert "--prior=views" in bench.main_command(given, Path("s"), Path("o"), 5)         # given: it wins


def test_a_childs_accounting_is_its_own(bench, tmp_path):
    code = "import sys; b = bytearray(200 * 2**20); print('first'); print('last line'); sys.exit(3)"
    got = bench.run_child([sys.executable, "-c", code], tmp_path / "child.log")
    assert got["exit"] == 3 and got["last_line"] == "last line"
    assert got["peak_rss_gb"] > 0.19 and got["wall_s"] > 0


def test_several_processes_each_get_their_flags_and_their_own_accounting(bench, tmp_path, capsys):
    with pytest.raises(SystemExit):
        bench.parse_args(["--processes=0"])
    assert "--processes must be >= 1" in capsys.readouterr().err
    args = bench.parse_args(["--processes=2"])
    cmd = bench.main_command(args, Path("s"), Path("o"), 5, (1, "localhost:1234"))
    assert cmd[-3:] == ["--coordinator_address=localhost:1234", "--num_processes=2", "--process_id=1"]
    assert not any("coordinator" in c for c in bench.main_command(bench.parse_args([]), Path("s"), Path("o"), 5))
    big = "import sys, time; b = bytearray(300 * 2**20); time.sleep(0.3); print('big done'); sys.exit(2)"
    small = "print('small done')"
    got = bench.run_children([[sys.executable, "-c", big], [sys.executable, "-c", small]],
                             [tmp_path / "p0.log", tmp_path / "p1.log"])
    assert [g["exit"] for g in got] == [2, 0] and [g["last_line"] for g in got] == ["big done", "small done"]
    # each child's own wall time (the small one ends first) and peak RSS (a forked child's includes
    # its parent's memory at the fork, so only the big one's lower bound says it is the child's)
    assert got[0]["peak_rss_gb"] > 0.29 and got[1]["peak_rss_gb"] > 0
    assert got[0]["wall_s"] >= 0.3 and got[1]["wall_s"] < got[0]["wall_s"]
