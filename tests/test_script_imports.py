"""Library code lives in the package: no file of scripts/ or jaxdistill/ imports from tests/, no
script imports another script, and tests reach scripts only as command lines, but for the
tests listed below that test a script's own code (not library code) by loading the script."""

from __future__ import annotations

import ast
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
SCRIPTS = {p.stem for p in (REPO / "scripts").glob("*.py")}
TEST_MODULES = {p.stem for p in (REPO / "tests").glob("*.py")}
# tests that load a script to test that script's own code (its objects, generation, checks)
LOADS_ITS_SCRIPT = {"test_bedroom.py": "make_bedroom", "test_room_scene.py": "make_room_scene",
                    "test_photo_light_scale.py": "photo_light_scale", "test_bench_step.py": "bench_step",
                    "test_bench_main.py": "bench_main", "test_bench_scale.py": "bench_scale",
                    "test_bench_layers.py": "bench_layers"}


def imported_names(path: Path) -> set[str]:
    """Top-level module names `path` imports anywhere (module level and inside functions)."""
    names = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Import):
            names.update(alias.name.split(".")[0] for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and not node.level and node.module:
            names.add(node.module.split(".")[0])
    return names


def path_changes(path: Path) -> list[str]:
    """Source of every sys.path.insert/append and spec_from_file_location call in `path`."""
    text = path.read_text(encoding="utf-8")
    calls = []
    for node in ast.walk(ast.parse(text)):
        if isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) and (
                node.func.attr in ("insert", "append") and ast.unparse(node.func.value) == "sys.path"
                or node.func.attr == "spec_from_file_location"):
            calls.append(ast.get_source_segment(text, node))
    return calls


def problems_of(path: Path, *, scripts_allowed=frozenset()) -> list[str]:
    """What `path` does that the rules forbid: imports of tests/ modules or of scripts, and sys.path
    entries or file loads that reach tests/ or scripts/ (the repository root is allowed)."""
    out = [f"imports {name} from tests/" for name in sorted(imported_names(path) & TEST_MODULES - {"conftest"})
           if path.parent.name != "tests"]
    out += [f"imports the script {name}" for name in sorted(imported_names(path) & SCRIPTS - scripts_allowed)]
    for call in path_changes(path):
        reaches_root = "parents[1]" in call and '"tests"' not in call and '"scripts"' not in call
        loads_allowed = scripts_allowed and ('"scripts"' in call or any(f"{n}.py" in call for n in scripts_allowed))
        if not (reaches_root or loads_allowed):      # (the imports above say which scripts it may then import)
            out.append(f"reaches another folder: {call}")
    return out


def test_the_checker_sees_each_kind_of_import(tmp_path):
    bad = tmp_path / "bad.py"
    bad.write_text('import sys\nsys.path.insert(0, str(ROOT / "tests"))\nfrom tiny_rgbx import nchw\n'
                   "def f():\n    import make_bedroom\n")
    assert problems_of(bad) == ["imports tiny_rgbx from tests/", "imports the script make_bedroom",
                                'reaches another folder: sys.path.insert(0, str(ROOT / "tests"))']
    good = tmp_path / "good.py"
    good.write_text("import sys\nsys.path.insert(0, str(Path(__file__).resolve().parents[1]))\nimport jaxdistill\n")
    assert problems_of(good) == []


def test_scripts_and_the_package_import_neither_tests_nor_scripts():
    files = sorted((REPO / "scripts").glob("*.py")) + sorted((REPO / "jaxdistill").rglob("*.py"))
    found = {str(p.relative_to(REPO)): problems_of(p) for p in files}
    assert {k: v for k, v in found.items() if v} == {}


def test_tests_reach_scripts_only_as_command_lines():
    found = {p.name: problems_of(p, scripts_allowed=frozenset({LOADS_ITS_SCRIPT[p.name]}) if p.name in LOADS_ITS_SCRIPT
                                 else frozenset())
             for p in sorted((REPO / "tests").glob("*.py")) if p.name != Path(__file__).name}
    assert {k: v for k, v in found.items() if v} == {}
