"""glibc's huge-page tunable (`jaxdistill/huge_pages.py`): when the commands that compute run
themselves again with it, with what, and what `metrics.json` says of it."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from jaxdistill import huge_pages

REPO = Path(__file__).resolve().parents[1]
ON = (2, 36), "madvise"


def test_the_tunable_is_added_only_where_it_does_something_and_a_users_value_wins():
    assert huge_pages.tunables_to_add({}, *ON) == "glibc.malloc.hugetlb=1"
    assert (huge_pages.tunables_to_add({"GLIBC_TUNABLES": "glibc.malloc.arena_max=2"}, *ON)
            == "glibc.malloc.arena_max=2:glibc.malloc.hugetlb=1")                      # the user's others kept
    assert huge_pages.tunables_to_add({"GLIBC_TUNABLES": "glibc.malloc.hugetlb=0"}, *ON) is None   # the user's wins
    assert huge_pages.tunables_to_add({"GLIBC_TUNABLES": "glibc.malloc.hugetlb=1"}, *ON) is None   # run again already
    assert huge_pages.tunables_to_add({"JAXDISTILL_HUGE_PAGES": "0"}, *ON) is None
    assert huge_pages.tunables_to_add({"JAXDISTILL_HUGE_PAGES": "1"}, *ON) == "glibc.malloc.hugetlb=1"
    for glibc, mode in [((2, 34), "madvise"), (None, "madvise"), ((2, 36), "always"), ((2, 36), "never"),
                        ((2, 36), None)]:
        assert huge_pages.tunables_to_add({}, glibc, mode) is None, (glibc, mode)


def test_status_names_what_applies():
    tunable = {"GLIBC_TUNABLES": "glibc.malloc.hugetlb=1"}
    assert huge_pages.status(tunable, *ON).startswith("on: glibc.malloc.hugetlb=1")
    assert huge_pages.status({}, *ON).startswith("off: glibc.malloc.hugetlb is not set")
    assert huge_pages.status({}, (2, 36), "always").startswith("on: the kernel's transparent huge pages are 'always'")
    assert "'never'" in huge_pages.status(tunable, (2, 36), "never")
    assert "glibc 2.31 has no" in huge_pages.status({}, (2, 31), "madvise")
    assert huge_pages.status({"JAXDISTILL_HUGE_PAGES": "0"}, *ON) == "off: JAXDISTILL_HUGE_PAGES=0"
    assert huge_pages.status({"GLIBC_TUNABLES": "glibc.malloc.hugetlb=0"}, *ON) == \
        "off: GLIBC_TUNABLES has glibc.malloc.hugetlb=0"


def test_thp_mode_is_the_bracketed_word(tmp_path):
    path = tmp_path / "enabled"
    path.write_text("always [madvise] never\n")
    assert huge_pages.thp_mode(str(path)) == "madvise"
    path.write_text("[always] madvise never\n")
    assert huge_pages.thp_mode(str(path)) == "always"
    assert huge_pages.thp_mode(str(tmp_path / "missing")) is None


def test_the_command_runs_again_with_its_own_interpreter_options_and_arguments(monkeypatch):
    calls = []
    monkeypatch.setattr(huge_pages, "glibc_version", lambda: (2, 36))
    monkeypatch.setattr(huge_pages, "thp_mode", lambda path=None: "madvise")
    monkeypatch.setattr(sys, "orig_argv", ["python3", "-X", "utf8", "-m", "jaxdistill.main", "--steps=3"])
    env = {"LANG": "C.UTF-8", "GLIBC_TUNABLES": "glibc.malloc.arena_max=2"}
    assert huge_pages.run_again_with_huge_pages(env, execve=lambda *a: calls.append(a))
    (path, argv, new_env), = calls
    assert path == sys.executable and argv == [sys.executable, "-X", "utf8", "-m", "jaxdistill.main", "--steps=3"]
    assert new_env == {"LANG": "C.UTF-8", "GLIBC_TUNABLES": "glibc.malloc.arena_max=2:glibc.malloc.hugetlb=1"}
    calls.clear()
    assert not huge_pages.run_again_with_huge_pages(new_env, execve=lambda *a: calls.append(a))   # once only
    assert not calls

    def refused(*args):
        raise PermissionError("no")

    assert not huge_pages.run_again_with_huge_pages(env, execve=refused)      # goes on without, saying so


def test_a_command_run_as_a_user_runs_it_runs_with_the_tunable_where_the_machine_has_them(tmp_path):
    """`python -m jaxdistill.precompute --help` (the cheapest command that runs itself again): the
    process that prints the help has the tunable exactly when this machine gives huge pages
    through it, and a user's own value is kept."""
    probe = ("import os, runpy, sys; sys.argv = ['jaxdistill.precompute', '--helpshort']; "
             "print('TUNABLES=' + os.environ.get('GLIBC_TUNABLES', ''), flush=True); "
             "runpy.run_module('jaxdistill.precompute', run_name='__main__')")
    wanted = huge_pages.why_not({}, huge_pages.glibc_version(), huge_pages.thp_mode()) is None
    env = {k: v for k, v in os.environ.items() if k not in ("GLIBC_TUNABLES", "JAXDISTILL_HUGE_PAGES")}
    done = subprocess.run([sys.executable, "-c", probe], cwd=REPO, env=env, capture_output=True, text=True,
                          timeout=300)
    lines = [line for line in done.stdout.splitlines() if line.startswith("TUNABLES=")]
    assert "--helpfull" in done.stdout, done.stderr[-2000:]              # absl printed the help (and exited 1)
    assert lines == (["TUNABLES=", "TUNABLES=glibc.malloc.hugetlb=1"] if wanted else ["TUNABLES="]), done.stdout
    if not wanted:
        pytest.skip(f"this machine gives no huge pages through the tunable: "
                    f"{huge_pages.why_not({}, huge_pages.glibc_version(), huge_pages.thp_mode())}")
    kept = subprocess.run([sys.executable, "-c", probe], cwd=REPO, capture_output=True, text=True, timeout=300,
                          env={**env, "GLIBC_TUNABLES": "glibc.malloc.hugetlb=0"})
    assert [line for line in kept.stdout.splitlines() if line.startswith("TUNABLES=")] == \
        ["TUNABLES=glibc.malloc.hugetlb=0"], kept.stdout
