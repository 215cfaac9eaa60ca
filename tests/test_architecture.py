"""The import graph of segmo, read from the source: every import statement counts, at
module level, inside a function or under TYPE_CHECKING.

Nodes of the package graph are the sub-packages (segmo.models, segmo.data, ...) and the
top-level modules (segmo.cli, segmo.demo, ...). Imports of the root package itself
(``from segmo import __version__``) are no edge: every import of a segmo module runs
segmo/__init__.py first anyway, and it imports nothing on import.
"""

from __future__ import annotations

import ast
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]

# What models/ may import besides itself: the layers below it.
BELOW_MODELS = ("segmo.errors", "segmo.files", "segmo.cpu", "segmo.network", "segmo.motion",
                "segmo.text")


def _module_of(path: Path) -> str:
    parts = path.relative_to(REPO).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


MODULES = {_module_of(p): p for p in sorted((REPO / "segmo").rglob("*.py"))}


def _resolve(name: str) -> str:
    """The module a dotted import name lives in (a name may end in a class or function)."""
    while name not in MODULES:
        name = name.rpartition(".")[0]
    return name


def imports(module: str) -> set[str]:
    """The segmo modules `module` imports, wherever the statement stands."""
    path = MODULES[module]
    package = module if path.name == "__init__.py" else module.rpartition(".")[0]
    names: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"), str(path))):
        if isinstance(node, ast.Import):
            names |= {alias.name for alias in node.names}
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                parent = package.split(".")[: len(package.split(".")) - node.level + 1]
                base = ".".join([*parent, base] if base else parent)
            # `from pkg import sub` imports the module pkg.sub when there is one.
            names |= {f"{base}.{a.name}" if f"{base}.{a.name}" in MODULES else base
                      for a in node.names}
    segmo = {_resolve(n) for n in names if n.startswith("segmo.")}
    return segmo - {module}


GRAPH = {module: imports(module) for module in MODULES}


def package_of(module: str) -> str:
    """segmo.models.tokenizer -> segmo.models; segmo.cli -> segmo.cli."""
    return ".".join(module.split(".")[:2])


def cycles(graph: dict[str, set[str]]) -> list[set[str]]:
    """The strongly connected components with more than one node."""
    reach: dict[str, set[str]] = {}
    for start in graph:
        seen, todo = set(), [start]
        while todo:
            for nxt in graph.get(todo.pop(), ()):
                if nxt not in seen:
                    seen.add(nxt)
                    todo.append(nxt)
        reach[start] = seen
    components: list[set[str]] = []
    for node in graph:
        component = {node} | {other for other in reach[node] if node in reach.get(other, ())}
        if len(component) > 1 and component not in components:
            components.append(component)
    return components


def _edges_between(component: set[str], graph: dict[str, set[str]], of=lambda m: m) -> list[str]:
    return sorted(f"{a} -> {b}" for a in MODULES for b in GRAPH[a]
                  if of(a) in component and of(b) in component and of(a) != of(b))


def test_the_graph_sees_every_kind_of_import() -> None:
    assert "segmo.text.vocabulary" in GRAPH["segmo.models.evaluator"]  # module level
    assert "segmo.tasks.action_classifier" in GRAPH["segmo.evaluation.sections"]  # in a function
    assert "segmo.pipeline.segmo" in GRAPH["segmo.evaluation.grounding"]  # under TYPE_CHECKING
    assert "segmo.models.registry" in GRAPH["segmo.models"]  # a package's __init__
    assert "segmo.pipeline.grounding" in GRAPH["segmo.pipeline.segmo"]  # from package import module


def test_no_cycle_between_packages() -> None:
    graph: dict[str, set[str]] = {}
    for module, targets in GRAPH.items():
        graph.setdefault(package_of(module), set()).update(
            package_of(t) for t in targets if package_of(t) != package_of(module))
    found = cycles(graph)
    assert not found, "; ".join(f"packages import each other: {sorted(c)}: "
                                f"{_edges_between(c, graph, package_of)}" for c in found)


def test_no_cycle_between_the_modules_of_a_package() -> None:
    graph = {m: {t for t in targets if package_of(t) == package_of(m)} for m, targets in GRAPH.items()}
    found = cycles(graph)
    assert not found, "; ".join(f"modules import each other: {sorted(c)}: "
                                f"{_edges_between(c, graph)}" for c in found)


def test_nothing_imports_evaluation() -> None:
    # Evaluation measures the pipeline; grounding and retrieval themselves live in pipeline/.
    users = {f"{m} -> {t}" for m in MODULES if package_of(m) != "segmo.evaluation"
             for t in GRAPH[m] if package_of(t) == "segmo.evaluation"}
    assert not users, sorted(users)


def test_models_import_nothing_above_them() -> None:
    above = {f"{m} -> {t}" for m in MODULES if package_of(m) == "segmo.models" for t in GRAPH[m]
             if package_of(t) != "segmo.models" and not t.startswith(BELOW_MODELS)}
    assert not above, sorted(above)

