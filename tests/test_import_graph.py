"""The package's module import graph has no cycle, counting imports inside functions too."""

from __future__ import annotations

import ast
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[1] / "jaxdistill"


def module_files() -> dict[str, Path]:
    """{dotted module name: file} of every module of the package (a package is its __init__)."""
    out = {}
    for path in sorted(PACKAGE.rglob("*.py")):
        parts = list(path.relative_to(PACKAGE.parent).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
        out[".".join(parts)] = path
    return out


def imported_modules(name: str, path: Path, modules) -> set[str]:
    """The package modules `name` imports anywhere in its file (module level, functions, classes)."""
    package = name.split(".") if path.name == "__init__.py" else name.split(".")[:-1]
    found = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = package[:len(package) - node.level + 1]
                base = ".".join(anchor + ([base] if base else []))
            for alias in node.names:       # `from pkg import module` imports the module itself
                found.add(f"{base}.{alias.name}" if f"{base}.{alias.name}" in modules else base)
    return {m for m in found if m in modules and m != name}


def import_graph() -> dict[str, set[str]]:
    modules = module_files()
    return {name: imported_modules(name, path, modules) for name, path in modules.items()}


def find_cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """One cycle [a, b, ..., a] of `graph`, or None (iterative depth-first search)."""
    state = {}                             # 1: on the current path, 2: finished
    for start in sorted(graph):
        if start in state:
            continue
        path, stack = [start], [iter(sorted(graph[start]))]
        state[start] = 1
        while stack:
            nxt = next(stack[-1], None)
            if nxt is None:
                state[path.pop()] = 2
                stack.pop()
            elif state.get(nxt) == 1:
                return path[path.index(nxt):] + [nxt]
            elif nxt not in state:
                state[nxt] = 1
                path.append(nxt)
                stack.append(iter(sorted(graph[nxt])))
    return None


def test_the_cycle_finder_finds_a_cycle_hidden_in_a_function(tmp_path):
    """The checker itself: a function-level import closing a loop is found, a chain is not."""
    assert find_cycle({"a": {"b"}, "b": {"c"}, "c": set()}) is None
    assert find_cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == ["a", "b", "c", "a"]
    pkg = tmp_path / "p"
    pkg.mkdir()
    (pkg / "__init__.py").write_text("")
    (pkg / "low.py").write_text("def f():\n    from p.high import g\n")
    (pkg / "high.py").write_text("from p import low\n")
    modules = {"p": pkg / "__init__.py", "p.low": pkg / "low.py", "p.high": pkg / "high.py"}
    graph = {n: imported_modules(n, f, modules) for n, f in modules.items()}
    assert graph == {"p": set(), "p.low": {"p.high"}, "p.high": {"p.low"}}
    assert find_cycle(graph) == ["p.high", "p.low", "p.high"]


def test_no_import_cycle_in_the_package():
    graph = import_graph()
    assert len(graph) > 40 and "jaxdistill.datasets.common" in graph       # really read the package
    assert "jaxdistill.scene.objects" in graph["jaxdistill.scene.model"]          # reads real edges
    cycle = find_cycle(graph)
    assert cycle is None, "import cycle: " + " -> ".join(cycle)


# The stages, lowest first (docs/design.md "Layers"). A module may import its own stage and the
# stages below it, never one above: data flows scene → fragments → gather plans → step → outputs.
LAYERS = (
    ("jaxdistill", "jaxdistill.scenes", "jaxdistill.errors", "jaxdistill.xla_flags", "jaxdistill.threads",
     "jaxdistill.huge_pages"),
    # constants, the embedded scene's data, errors, the XLA flags set on import, the per-view thread map,
    # glibc's huge-page tunable
    ("jaxdistill.io",),            # images, checkpoints, per-view image files, exposure
    ("jaxdistill.scene",),         # cameras, mesh, scene objects and paths, the scene model, the maps
    ("jaxdistill.render",),        # ray casts into fragments, texel layout, gather plans, sampler, visibility, unwrap
    ("jaxdistill.datasets",),      # format loaders and the Mitsuba importer
    ("jaxdistill.models",),        # the RGB<->X networks, conversion, sampling, the shipped model, training
    ("jaxdistill.engine",),        # config, priors, the pure step, the problem, the loop
    ("jaxdistill.evaluate",),      # metrics, ground truth, scoring a run
    ("jaxdistill.export",),        # map pages, glTF, plots, the anchor, a run's folder and outputs
    ("jaxdistill.viewer",),        # the browser viewer
    ("jaxdistill.pipeline", "jaxdistill.main", "jaxdistill.cli", "jaxdistill.__main__", "jaxdistill.estimate",
     "jaxdistill.precompute", "jaxdistill.import_scene", "jaxdistill.view"),   # the main job and entry points
)


def layer_of(module: str) -> int:
    """Index in LAYERS of the stage holding `module` (its longest matching prefix)."""
    best, depth = None, -1
    for i, stage in enumerate(LAYERS):
        for prefix in stage:
            matches = module == prefix or (prefix != "jaxdistill" and module.startswith(prefix + "."))
            if matches and prefix.count(".") > depth:
                best, depth = i, prefix.count(".")
    if best is None:
        raise AssertionError(f"{module} is in no stage of LAYERS: add its folder to the layering (and docs/design.md)")
    return best


def upward_imports(graph: dict[str, set[str]]) -> list[str]:
    """'a -> b' for every import of a module from a higher stage than the importer's."""
    return [f"{a} (stage {layer_of(a)}) imports {b} (stage {layer_of(b)})"
            for a in sorted(graph) for b in sorted(graph[a]) if layer_of(b) > layer_of(a)]


def test_the_layering_check_finds_an_upward_import():
    graph = {"jaxdistill.scene.model": {"jaxdistill.io.images"}, "jaxdistill.render.sampler": {"jaxdistill.engine.step"},
             "jaxdistill.engine.step": set(), "jaxdistill.io.images": set()}
    assert upward_imports(graph) == ["jaxdistill.render.sampler (stage 3) imports jaxdistill.engine.step (stage 6)"]
    assert layer_of("jaxdistill.datasets.mitsuba.prepare") == 4 and layer_of("jaxdistill.scenes") == 0


def test_stages_import_only_downward():
    graph = import_graph()
    for module in graph:
        layer_of(module)                   # every module belongs to a stage
    assert upward_imports(graph) == []
