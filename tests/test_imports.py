"""The package's imports: no circle among npbrs's modules (deferred imports inside functions
included), and the layers in one direction: inference imports models, models imports domains,
never the other way."""

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = {"models": "npbrs.models", "inference": "npbrs.inference", "domains": "npbrs.domains"}


def modules() -> dict:
    """{module name: source path} of every library module."""
    out = {}
    for folder, package in PACKAGES.items():
        for path in (ROOT / folder).rglob("*.py"):
            parts = path.relative_to(ROOT / folder).with_suffix("").parts
            out[".".join([package] + [p for p in parts if p != "__init__"])] = path
    return out


def import_graph(files: dict) -> dict:
    """{module: the library modules it imports anywhere in its source}; a package's
    ``__init__`` (which only re-exports) is not an edge target."""
    graph = {}
    for name, path in files.items():
        package = name.split(".") if path.name == "__init__.py" else name.split(".")[:-1]
        targets = set()
        for node in ast.walk(ast.parse(path.read_text())):
            found = []
            if isinstance(node, ast.Import):
                found = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:
                    base = ".".join(package[:len(package) - node.level + 1] + ([base] if base else []))
                found = [base] + [f"{base}.{a.name}" for a in node.names]
            targets.update(t for t in found if t in files and t != name and files[t].name != "__init__.py")
        graph[name] = targets
    return graph


def circles(graph: dict) -> list:
    """The strongly connected components of more than one module (Tarjan)."""
    index, low, stack, on, out = {}, {}, [], set(), []

    def visit(v):
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in graph[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                out.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return out


def test_no_module_imports_itself_through_others():
    graph = import_graph(modules())
    assert len(graph) > 50  # (the walk found the library)
    assert circles(graph) == []


def test_the_circle_finder_finds_a_circle():
    assert circles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert circles({"a": {"b"}, "b": set()}) == []


def test_the_layers_import_in_one_direction():
    below = {"npbrs.domains": ("npbrs.models", "npbrs.inference"), "npbrs.models": ("npbrs.inference",)}
    wrong = [(name, target) for name, targets in import_graph(modules()).items() for target in targets
             for layer, above in below.items() if name.startswith(layer + ".") and target.startswith(above)]
    assert wrong == []
