"""The package's modules import one another without circles (STYLE.md §1: imports run one
way), read from the source with `ast`: every import counts, at module level, inside a
function or under `TYPE_CHECKING`, because each one is an arrow a reader must follow."""

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1] / "thermojax"

# No known exception: the command line's shared argument helpers live in
# `cli/_arguments.py`, so `cli/_main.py` imports its subcommands and none imports it.
KNOWN_CIRCLES: tuple[str, ...] = ()


def _modules() -> dict[str, Path]:
    out = {}
    for path in ROOT.rglob("*.py"):
        parts = path.relative_to(ROOT.parent).with_suffix("").parts
        name = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
        out[name] = path
    return out


def _package(name: str, path: Path) -> str:
    """The package a module's relative imports start from."""
    return name if path.name == "__init__.py" else name.rpartition(".")[0]


def _edges(name: str, path: Path, modules: dict) -> set[str]:
    """The thermojax modules that `name` imports: `from a import b` goes to `a.b` where
    that is a module, else to `a`."""
    out = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            targets = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = _package(name, path).split(".")
                base = base[:len(base) - (node.level - 1)]
                source = ".".join(base + ([node.module] if node.module else []))
            else:
                source = node.module or ""
            targets = [f"{source}.{a.name}" if f"{source}.{a.name}" in modules else source
                       for a in node.names]
        else:
            continue
        out.update(t for t in targets if t in modules and t != name)
    return out


def import_graph() -> dict[str, set[str]]:
    modules = _modules()
    return {name: _edges(name, path, modules) for name, path in modules.items()}


def circles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan), each sorted."""
    index, low, stack, on_stack, out = {}, {}, [], set(), []

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
                out.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return out


def _known(component: list[str]) -> bool:
    return any(all(m == p or m.startswith(p + ".") for m in component) for p in KNOWN_CIRCLES)


def test_the_graph_sees_relative_and_absolute_imports():
    graph = import_graph()
    assert "thermojax.fitting._summary" in graph["thermojax.fitting._fit"]
    assert "thermojax.model._model" in graph["thermojax.observer._schedule"]  # in a function


def test_the_finder_finds_a_circle():
    graph = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}, "e": set()}
    assert circles(graph) == [["a", "b", "c"]]


def test_no_import_circle():
    found = [c for c in circles(import_graph()) if not _known(c)]
    assert not found, "import circles (each a set of modules that reach one another): " + \
        "; ".join(" <-> ".join(c) for c in found)
