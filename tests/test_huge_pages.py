"""glibc's huge-page tunable (`jaxdistill/huge_pages.py`): when the commands that compute run
themselves again with it, with what, and what `metrics.json` says of it."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path


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
    assert huge_pages.status({**tunable, "JAXDISTILL_HUGE_PAGES": "0"}, *ON).startswith("on: ")   # the user's wins
    assert huge_pages.status({"GLIBC_TUNABLES": "glibc.malloc.hugetlb=0"}, (2, 36), "always").startswith("on: ")
    assert huge_pages.status(tunable, (2, 31), "madvise").startswith("off: glibc 2.31 has no")
    assert huge_pages.status(tunable, *ON).startswith("on: glibc.malloc.hugetlb=1")
    assert huge_pages.status({}, *ON).startswith("off: glibc.malloc.hugetlb is not set")
    assert huge_pages.status({}, (2, 36), "always").startswith("on: the kernel's transparent huge pages are 'always'")
    assert "'never'" in huge_pages.status(tunable, (2, 36), "never")
    assert "glibc 2.31 has no" in huge_pages.status({}, (2, 31), "madvise")
    assert huge_pages.status({"JAXDISTILL_HUGE_PAGES": "0"}, *ON) == "off: JAXDISTILL_HUGE_PAGES=0"
    assert huge_pages.status({"GLIBC_TUNABLES": "glibc.malloc.hugetlb=0"}, *ON) == \
        "off: GLIBC_TUNABLES has glibc.malloc.hugetlb=0"
    assert huge_pages.status({"GLIBC_TUNABLES": "glibc.malloc.hugetlb=2"}, *ON) == \
        "as given: GLIBC_TUNABLES has glibc.malloc.hugetlb=2"


def test_thp_mode_is_the_bracketed_word(tmp_path):
    path = tmp_path / "enabled"
    path.write_text("always [madvise] never\n")
    assert huge_pages.thp_mode(str(path)) == "madvise"
    path.write_text("[always] madvise never\n")
    assert huge_pages.thp_mode(str(path)) == "always"
    assert huge_pages.thp_mode(str(tmp_path / "missing")) is None


def test_only_the_packages_own_commands_run_again():
    yes = [["python", "-m", "jaxdistill.main", "--steps=3"], ["python", "-X", "utf8", "-u", "-m", "jaxdistill.estimate"],
           ["python", "-mjaxdistill.precompute"], ["python", "-m", "jaxdistill", "distill"],
           ["python", "/usr/local/bin/jaxdistill", "distill", "--config=bedroom"],
           ["python", str(Path(huge_pages.__file__).with_name("main.py")), "--steps=1"],
           ["python", "-Wdefault::DeprecationWarning", "-m", "jaxdistill.main"], ["python", "-Im", "jaxdistill.main"],
           ["python", "-W", "ignore", "-Xutf8", "--check-hash-based-pycs", "never", "-mjaxdistill.main"]]
    no = [["python", "-m", "cProfile", "-m", "jaxdistill.main"], ["python", "-m", "ipykernel_launcher", "-f", "k.json"],
          ["python", "-c", "import runpy"], ["python", "-Ic", "import runpy"], ["python", "-uc", "import runpy"],
          ["python", "-W", "ignore", "-c", "import runpy"], ["python", "-"], ["python", "run.py"],
          ["python", "-m", "jaxdistill.view"], ["python"], ["python", "-X"]]
    assert all(huge_pages.is_package_command(argv) for argv in yes), [a for a in yes if not huge_pages.is_package_command(a)]
    assert not any(huge_pages.is_package_command(argv) for argv in no), [a for a in no if huge_pages.is_package_command(a)]


def test_the_command_runs_again_once_with_its_own_interpreter_options_and_arguments(monkeypatch):
    calls = []
    monkeypatch.setattr(huge_pages, "glibc_version", lambda: (2, 36))
    monkeypatch.setattr(huge_pages, "thp_mode", lambda path=None: "madvise")
    monkeypatch.setattr(sys, "orig_argv", ["python3", "-X", "utf8", "-m", "jaxdistill.main", "--steps=3"])
    env = {"LANG": "C.UTF-8", "GLIBC_TUNABLES": "glibc.malloc.arena_max=2:"}
    assert huge_pages.run_again_with_huge_pages(env, execve=lambda *a: calls.append(a))
    (path, argv, new_env), = calls
    assert path == sys.executable and argv == [sys.executable, "-X", "utf8", "-m", "jaxdistill.main", "--steps=3"]
    assert new_env == {"LANG": "C.UTF-8", "GLIBC_TUNABLES": "glibc.malloc.arena_max=2:glibc.malloc.hugetlb=1",
                       huge_pages.RAN_AGAIN: "1"}
    calls.clear()
    assert not huge_pages.run_again_with_huge_pages(new_env, execve=lambda *a: calls.append(a))   # once only
    cleared = {k: v for k, v in new_env.items() if k != "GLIBC_TUNABLES"}      # a loader that drops the tunable
    assert not huge_pages.run_again_with_huge_pages(cleared, execve=lambda *a: calls.append(a))   # no loop
    assert "cleared at start-up" in huge_pages.status(cleared, (2, 36), "madvise")
    monkeypatch.setattr(sys, "orig_argv", ["python3", "-m", "cProfile", "-m", "jaxdistill.main"])
    assert not huge_pages.run_again_with_huge_pages(env, execve=lambda *a: calls.append(a))       # not our command
    assert not calls
    monkeypatch.setattr(sys, "orig_argv", ["python3", "-m", "jaxdistill.main"])
    for error in (PermissionError("no"), ValueError("illegal environment variable name")):
        def refused(*args, error=error):
            raise error

        assert not huge_pages.run_again_with_huge_pages(env, execve=refused)     # goes on without, saying so


SITECUSTOMIZE = """import os, sys
sys.stderr.write("TUNABLES=" + os.environ.get("GLIBC_TUNABLES", "") + "\\n")
sys.stderr.flush()
"""


def test_a_command_as_a_user_runs_it_starts_again_with_the_tunable_where_the_machine_has_them(tmp_path):
    """`python -m jaxdistill.precompute --helpshort` (the cheapest command that runs itself again),
    with a sitecustomize that prints GLIBC_TUNABLES at each interpreter start: a second start with
    the tunable exactly where this machine gives huge pages through it; one start for a module run
    by another command (`python -c` with runpy), and a user's own value kept."""
    (tmp_path / "sitecustomize.py").write_text(SITECUSTOMIZE)
    wanted = huge_pages.why_not({}, huge_pages.glibc_version(), huge_pages.thp_mode()) is None
    env = {k: v for k, v in os.environ.items() if k not in ("GLIBC_TUNABLES", huge_pages.OFF, huge_pages.RAN_AGAIN)}
    env["PYTHONPATH"] = os.pathsep.join([str(tmp_path), str(REPO)])

    def starts(command, **extra):
        done = subprocess.run([sys.executable, *command], cwd=REPO, env={**env, **extra}, capture_output=True,
                              text=True, timeout=300)
        assert "--helpfull" in done.stdout, done.stderr[-2000:]       # absl printed the help (and exited 1)
        return [line for line in done.stderr.splitlines() if line.startswith("TUNABLES=")]

    command = ["-m", "jaxdistill.precompute", "--helpshort"]
    assert starts(command) == (["TUNABLES=", "TUNABLES=glibc.malloc.hugetlb=1"] if wanted else ["TUNABLES="])
    runpy = ["-c", "import runpy, sys; sys.argv = ['precompute', '--helpshort']; "
             "runpy.run_module('jaxdistill.precompute', run_name='__main__')"]
    assert starts(runpy) == ["TUNABLES="]
    assert starts(command, GLIBC_TUNABLES="glibc.malloc.hugetlb=0") == ["TUNABLES=glibc.malloc.hugetlb=0"]
    assert starts(command, JAXDISTILL_HUGE_PAGES="0") == ["TUNABLES="]
