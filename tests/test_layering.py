"""The package's layering: no import cycles, and the bottom layer imports no strategy.

Every import statement counts, including those inside functions and under
``TYPE_CHECKING``: a cycle hidden in a function still ties the modules together.
"""

import ast
import pathlib

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]
#: import name of each installed package -> its folder in the repository
PACKAGES = {"softbody": "softbody", "softbody.actuators": "actuators", "softbody.meshing": "meshing",
            "softbody.control": "control"}


def _modules() -> dict[str, pathlib.Path]:
    out = {}
    for package, folder in PACKAGES.items():
        for path in (ROOT / folder).rglob("*.py"):
            parts = [p for p in path.relative_to(ROOT / folder).with_suffix("").parts if p != "__init__"]
            if package == "softbody" and parts and parts[0] in ("actuators", "meshing", "control"):
                continue
            out[".".join([package, *parts])] = path
    return out


def _imports(name: str, path: pathlib.Path, modules) -> set[str]:
    """The project modules that ``name`` imports (resolved to the longest known module)."""

    def known(target: str) -> str | None:
        while target and target not in modules:
            target = target.rpartition(".")[0]
        return target or None

    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            targets = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = package.split(".")
                anchor = anchor[: len(anchor) - node.level + 1]
                base = ".".join(anchor + ([base] if base else []))
            # ``from pkg import mod`` imports the module; ``from mod import name`` the module.
            targets = [f"{base}.{alias.name}" if f"{base}.{alias.name}" in modules else base
                       for alias in node.names]
        else:
            continue
        for target in targets:
            resolved = known(target)
            if resolved and resolved != name:
                found.add(resolved)
    return found


def _graph():
    modules = _modules()
    return {name: _imports(name, path, modules) for name, path in modules.items()}


def _cycles(graph) -> list[list[str]]:
    """Strongly connected components of more than one module (Tarjan)."""
    index, low, stack, on_stack, out = {}, {}, [], set(), []

    def visit(v):
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in graph[v]:
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
                out.append(sorted(component))

    for v in graph:
        if v not in index:
            visit(v)
    return out


def test_cycle_finder_sees_a_cycle():
    """The checker itself can fail: a two-module and a three-module cycle are found."""
    graph = {"a": {"b"}, "b": {"a"}, "c": {"d"}, "d": {"e"}, "e": {"c"}, "f": {"a"}}
    assert sorted(_cycles(graph)) == [["a", "b"], ["c", "d", "e"]]


def test_relative_and_function_local_imports_count(tmp_path, monkeypatch):
    pkg = tmp_path / "pkg"
    pkg.mkdir()
    (pkg / "__init__.py").write_text("")
    (pkg / "a.py").write_text("def f():\n    from . import b\n")
    (pkg / "b.py").write_text("from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from pkg.a import f\n")
    modules = {"pkg": pkg / "__init__.py", "pkg.a": pkg / "a.py", "pkg.b": pkg / "b.py"}
    graph = {name: _imports(name, path, modules) for name, path in modules.items()}
    assert graph["pkg.a"] == {"pkg.b"} and graph["pkg.b"] == {"pkg.a"}
    assert _cycles(graph) == [["pkg.a", "pkg.b"]]


def test_no_import_cycles():
    graph = _graph()
    assert len(graph) > 40, "the module walk found too few modules"
    assert _cycles(graph) == []


@pytest.mark.parametrize("bottom", ["softbody._types", "softbody._interfaces"])
def test_bottom_layer_imports_no_strategy(bottom):
    """The data types and interfaces import no solver, adjoint, contact, skeleton or
    scene-building module (so every strategy can import them)."""
    strategies = {"softbody.solvers", "softbody.gradients", "softbody.contact", "softbody.skeleton",
                  "softbody.objective", "softbody.model", "softbody.simulate"}
    graph = _graph()
    reached, todo = set(), [bottom]
    while todo:
        for w in graph[todo.pop()]:
            if w not in reached:
                reached.add(w)
                todo.append(w)
    hit = {m for m in reached if any(m == s or m.startswith(s + ".") for s in strategies)}
    assert not hit, sorted(hit)
