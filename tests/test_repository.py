"""The repository stands on its own: no machine paths, no wording about how it was made, no
import of tests/ from the package or the scripts, one set of run configs. Fast: `git ls-files`
and a text scan of every file git tracks (or would track), each problem named by file and line.
"""

from __future__ import annotations

import ast
import re
import subprocess
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
THIS_FILE = "tests/test_repository.py"       # its examples hold what it looks for: left out of the scans
BINARY_SUFFIXES = {".png", ".jpg", ".jpeg", ".exr", ".hdr", ".safetensors", ".npz", ".npy", ".glb", ".pkl", ".whl",
                   ".gz", ".zip", ".pdf", ".ico"}

# An absolute path into a machine's own folders (home, scratch, mounts, this checkout's location).
MACHINE_PATH = re.compile(r"(?<![\w.:/~-])(/(?:work|root|tmp|home|Users|mnt|scratch|data|private/var)/"
                          r"|[A-Za-z]:\\(?:Users|Documents and Settings)\\)")

# Wording about the circumstances of the work rather than the work: sittings, stops, rounds,
# tickets, who asked. Written with \s+ so that these patterns do not match their own source.
CIRCUMSTANCES = re.compile(r"\b(?:this|last|previous|next|earlier|that)\s+sessions?\b|\bbetween\s+sessions\b"
                           r"|\b(?:this|last|previous|that)\s+stop(?:'s)?\b|\bissues?\s+#?\d+"
                           r"|\bthe\s+issue(?:'s)?\b|\b(?:this|last|earlier|next)\s+round\b|\bthe\s+lead(?:'s)?(?![\w-])"
                           r"|\bdevice\s+tool\b|\bGPU\s+(?:was\s+)?lent\b|\bthe\s+brief\b", re.IGNORECASE)

# Files that keep a machine path, and why. Each entry must still be needed (the test says when
# it is not), so the list only shrinks.
KEEPS_A_MACHINE_PATH: dict[str, str] = {}   # file: why it must name a machine path (none does today)


def repository_files() -> list[str]:
    """Relative paths of the files git tracks or would track (not ignored) that exist here."""
    out = subprocess.run(["git", "ls-files", "-z", "--cached", "--others", "--exclude-standard"], cwd=REPO,
                         capture_output=True, check=True).stdout.decode()
    return sorted({p for p in out.split("\0") if p and (REPO / p).is_file()})


def text_files() -> dict[str, list[str]]:
    """{path: lines} of the repository's text files (binary suffixes and files with NUL bytes left out)."""
    out = {}
    for name in repository_files():
        if Path(name).suffix.lower() in BINARY_SUFFIXES or name == THIS_FILE:
            continue
        data = (REPO / name).read_bytes()
        if b"\0" in data[:8192]:
            continue
        out[name] = data.decode("utf-8", errors="replace").splitlines()
    return out


def matches(pattern: re.Pattern, files: dict[str, list[str]]) -> dict[str, list[str]]:
    """{path: ['path:line: text', ...]} of the lines where `pattern` matches."""
    found = {}
    for name, lines in files.items():
        for number, line in enumerate(lines, 1):
            if pattern.search(line):
                found.setdefault(name, []).append(f"{name}:{number}: {line.strip()[:160]}")
    return found


def test_the_scan_reads_the_repository_and_its_patterns_find_what_they_should():
    files = text_files()
    assert "README.md" in files and "pyproject.toml" in files and "tests/test_wheel.py" in files
    assert not any(name.endswith(".png") for name in files)
    root = "/"                  # joined at run time, so this file holds no machine path itself
    for bad in (f"--out={root}tmp/x", f"data={root}work/data/rgbx", f"see {root}home/me/x", "C:" + "\\Users\\me",
                f"{root}Users/me/x"):
        assert MACHINE_PATH.search(bad), bad
    for fine in ("https://example.com/home/x", "~/models/rgb-to-x", "data/rgbx/train", "/usr/bin/time -v",
                 "tests/data/staircase2", "out/bed17_after"):
        assert not MACHINE_PATH.search(fine), fine
    for bad in ("measured in this session", "Issue 16 asks", "issue 6, part 2", "the issue's bar", "this stop's machine",
                "new this round", "before the lead's change", "no GPU lent"):
        assert CIRCUMSTANCES.search(bad), bad
    for fine in ("issues a warning", "this stops the run", "a viewer session", "the lead-in", "the round trip"):
        assert not CIRCUMSTANCES.search(fine), fine


def test_no_machine_paths_in_the_repository():
    found = matches(MACHINE_PATH, text_files())
    problems = [line for name, lines in found.items() if name not in KEEPS_A_MACHINE_PATH for line in lines]
    assert not problems, ("absolute machine paths (use paths relative to the repository, or a placeholder such "
                          "as DIR):\n" + "\n".join(problems))
    stale = sorted(set(KEEPS_A_MACHINE_PATH) - set(found))
    assert not stale, f"no machine path left in {stale}: remove them from KEEPS_A_MACHINE_PATH"


def test_no_wording_about_how_the_work_was_done():
    found = matches(CIRCUMSTANCES, text_files())
    problems = [line for lines in found.values() for line in lines]
    assert not problems, ("say what the code does and what was measured (with the commit or config), not the "
                          "circumstances of the work:\n" + "\n".join(problems))


def test_design_notes_are_cited_from_the_repository():
    upper = re.compile("DESIGN" + r"\.md")             # docs/design.md is the design; nothing outside the repository
    problems = [line for lines in matches(upper, text_files()).values() for line in lines]
    assert not problems, "cite docs/design.md (and its section) instead:\n" + "\n".join(problems)


def imported_names(path: Path) -> list[tuple[int, str]]:
    """(line, top-level module name) of every import in a Python file, function-level ones included."""
    found = []
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"), str(path))):
        if isinstance(node, ast.Import):
            found += [(node.lineno, alias.name.split(".")[0]) for alias in node.names]
        elif isinstance(node, ast.ImportFrom) and not node.level and node.module:
            found.append((node.lineno, node.module.split(".")[0]))
    return found


def test_the_package_and_the_scripts_never_import_the_tests():
    files = repository_files()
    test_modules = {Path(n).stem for n in files if n.startswith("tests/") and n.endswith(".py")} | {"tests"}
    script_modules = {Path(n).stem for n in files if n.startswith("scripts/") and n.endswith(".py")}
    forbidden = test_modules - script_modules - {"__init__"}
    problems = []
    for name in files:
        if name.endswith(".py") and name.startswith(("jaxdistill/", "scripts/")):
            problems += [f"{name}:{line}: imports {module} from tests/"
                         for line, module in imported_names(REPO / name) if module in forbidden]
            source = (REPO / name).read_text(encoding="utf-8").splitlines()
            problems += [f"{name}:{i}: puts tests/ on sys.path" for i, text in enumerate(source, 1)
                         if "sys.path" in text and re.search(r"""["']tests["'/]""", text)]
    assert not problems, "the package and scripts must stand without tests/:\n" + "\n".join(problems)


def test_the_packaged_configs_are_the_top_level_configs():
    """configs/*.cfg (what commands in a checkout name) and jaxdistill/configs/*.cfg (what the wheel
    ships, `--config=NAME`) are the same files; edit configs/ and copy: cp configs/*.cfg jaxdistill/configs/."""
    top = {p.name: p.read_bytes() for p in (REPO / "configs").glob("*.cfg")}
    packaged = {p.name: p.read_bytes() for p in (REPO / "jaxdistill" / "configs").glob("*.cfg")}
    assert {"bedroom.cfg", "smoke.cfg", "thesis.cfg"} <= set(top)
    assert sorted(top) == sorted(packaged), (sorted(top), sorted(packaged))
    differ = [name for name in top if top[name] != packaged[name]]
    assert not differ, f"configs/ and jaxdistill/configs/ differ in {differ}: cp configs/*.cfg jaxdistill/configs/"
