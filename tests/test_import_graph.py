"""The project's own import graph, built from the source: every import statement, including those inside
functions, so a cycle closed by a lazy import is still a cycle.

A module imports only modules below it (docs/design.md §2, "Layout"); a cycle would mean two modules each
need the other. Imports sit at the top of modules: the command line (the `gsbench.cli` package) alone imports
each subcommand's stage lazily, so that ``gsbench list`` and ``--help`` start without torch.
"""

from __future__ import annotations

import ast
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
# source folder -> the package it installs as (pyproject.toml, [tool.setuptools] package-dir)
ROOTS = {"gsbench": REPO / "gsbench", "gsbench.methods": REPO / "methods", "gsbench.evaluators": REPO / "evaluators"}
LAZY_PROJECT_IMPORTS_ALLOWED = "gsbench.cli"  # the package and its modules


def project_modules() -> dict[str, Path]:
    """Dotted name -> file of every module of the installed package."""
    modules = {}
    for package, root in ROOTS.items():
        for path in root.rglob("*.py"):
            parts = list(path.relative_to(root).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts = parts[:-1]
            modules[".".join([package, *parts])] = path
    return modules


def _known(name: str, modules) -> str | None:
    """The longest prefix of ``name`` that is a project module (``gsbench.x.y.func`` -> ``gsbench.x.y``)."""
    while name and name not in modules:
        name = name.rpartition(".")[0]
    return name or None


def imported_modules(module: str, node, modules) -> list[str]:
    """The project modules an import statement of ``module`` loads: for ``from P import a, b`` the submodules
    P.a, P.b where they are modules, else P itself."""
    if isinstance(node, ast.Import):
        targets = [alias.name for alias in node.names]
    else:
        base = node.module or ""
        if node.level:
            package = module.split(".")
            if modules[module].name != "__init__.py":
                package = package[:-1]
            package = package[: len(package) - node.level + 1]
            base = ".".join(package + ([node.module] if node.module else []))
        subs = [f"{base}.{alias.name}" for alias in node.names if f"{base}.{alias.name}" in modules]
        targets = subs + ([base] if len(subs) < len(node.names) else [])
    found = (_known(t, modules) for t in targets)
    return [t for t in found if t and t != module]


def import_graph() -> tuple[dict[str, set[str]], dict[str, list[str]]]:
    """(module -> project modules it imports anywhere, module -> 'line: target' of its imports inside a
    function or class)."""
    modules = project_modules()
    graph, nested = {m: set() for m in modules}, {m: [] for m in modules}
    for module, path in modules.items():
        tree = ast.parse(path.read_text(), str(path))
        top_level = set()
        for statement in tree.body:  # module level, including try/if blocks there
            top_level.update(id(n) for n in ast.walk(statement) if not isinstance(statement, (ast.FunctionDef,
                                                                                            ast.AsyncFunctionDef,
                                                                                            ast.ClassDef)))
        for node in ast.walk(tree):
            if isinstance(node, (ast.Import, ast.ImportFrom)):
                targets = imported_modules(module, node, modules)
                graph[module].update(targets)
                if id(node) not in top_level:
                    nested[module] += [f"{node.lineno}: {t}" for t in targets]
    return graph, nested


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components with more than one module (Tarjan), each sorted."""
    index, low, stack, on_stack, found = {}, {}, [], set(), []

    def visit(v):
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph[v]):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return found


def test_the_graph_sees_the_whole_package():
    graph, _ = import_graph()
    assert "gsbench.runs.runner" in graph and "gsbench.methods.base" in graph and "gsbench.evaluators.api" in graph
    assert "gsbench.training.trainer" in graph["gsbench.runs.runner"]
    assert "gsbench.raster.render" in graph["gsbench.raster"]


def test_a_cycle_is_found_even_through_a_function_level_import():
    graph = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}
    assert cycles(graph) == [["a", "b", "c"]]
    assert cycles({"a": {"b"}, "b": set()}) == []


def test_no_import_cycle_among_the_projects_modules():
    found = cycles(import_graph()[0])
    assert not found, "import cycles: " + "; ".join(" <-> ".join(c) for c in found)


def test_imports_of_project_modules_sit_at_the_top():
    _, nested = import_graph()
    offenders = {m: lines for m, lines in nested.items()
                 if lines and m != LAZY_PROJECT_IMPORTS_ALLOWED and not m.startswith(LAZY_PROJECT_IMPORTS_ALLOWED + ".")}
    assert not offenders, f"project imports inside functions: {offenders}"
