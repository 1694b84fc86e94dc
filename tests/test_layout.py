"""The package's layout: imports inside bdpt_drjit run one way.

Every ``import`` and ``from ... import`` of every module of the package is read with
``ast``, those inside functions too (a lazy import is still a dependency), and the
graph of modules importing modules must have no cycle.  ``from . import name`` is an
edge to the submodule ``name`` where there is one, else to the package's
``__init__``; importing a submodule is not counted as importing its parent package
(Python runs the parent's ``__init__`` first, but that is the package's entry point,
not a dependency of the module)."""
from __future__ import annotations

import ast
from pathlib import Path

import bdpt_drjit

PACKAGE = Path(bdpt_drjit.__file__).resolve().parent


def modules(package: Path = PACKAGE) -> dict:
    """Dotted name -> (path, is a package's __init__) of every module of the package."""
    out = {}
    for path in sorted(package.rglob("*.py")):
        parts = list(path.relative_to(package.parent).with_suffix("").parts)
        is_init = parts[-1] == "__init__"
        out[".".join(parts[:-1] if is_init else parts)] = (path, is_init)
    return out


def imported(name: str, is_init: bool, node) -> list:
    """The dotted names an import statement of module ``name`` asks for."""
    if isinstance(node, ast.Import):
        return [a.name for a in node.names]
    if node.level:
        base = name.split(".") if is_init else name.split(".")[:-1]
        base = base[:len(base) - (node.level - 1)]
        module = ".".join(base + ([node.module] if node.module else []))
    else:
        module = node.module
    return [module + "." + a.name for a in node.names] + [module]


def import_graph(package: Path = PACKAGE) -> dict:
    """Module -> the set of the package's modules it imports (anywhere in its code)."""
    mods = modules(package)
    graph = {m: set() for m in mods}
    for name, (path, is_init) in mods.items():
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if not isinstance(node, (ast.Import, ast.ImportFrom)):
                continue
            wanted = imported(name, is_init, node)
            if isinstance(node, ast.ImportFrom):
                # "from M import x": the submodule M.x if there is one, else M itself.
                subs = [w for w in wanted[:-1] if w in mods]
                wanted = subs if len(subs) == len(wanted) - 1 else subs + [wanted[-1]]
            for w in wanted:
                while w not in mods and "." in w:      # "import a.b.c" of a module a.b
                    w = w.rsplit(".", 1)[0]
                if w in mods and w != name:
                    graph[name].add(w)
    return graph


def find_cycle(graph: dict) -> list | None:
    """One cycle of the graph as a list of nodes (first == last), or None."""
    state = {}                         # 1: on the current path, 2: done
    path = []

    def visit(v):
        state[v] = 1
        path.append(v)
        for w in sorted(graph[v]):
            if state.get(w) == 1:
                return path[path.index(w):] + [w]
            if w not in state:
                found = visit(w)
                if found:
                    return found
        path.pop()
        state[v] = 2
        return None

    for v in sorted(graph):
        if v not in state:
            found = visit(v)
            if found:
                return found
    return None


def test_the_graph_reads_lazy_and_relative_imports():
    graph = import_graph()
    assert "bdpt_drjit.render" in graph["bdpt_drjit"]                 # from .render import
    assert "bdpt_drjit.render" in graph["bdpt_drjit.api"]
    assert "bdpt_drjit.cluster" in graph["bdpt_drjit.api"]            # inside render()
    assert "bdpt_drjit.settings" in graph["bdpt_drjit.cli.args"]      # from ..settings
    assert "bdpt_drjit.cluster" in graph["bdpt_drjit.cli.render"]     # inside a function
    assert find_cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == ["a", "b", "c", "a"]
    assert find_cycle({"a": {"b"}, "b": set()}) is None


def test_the_package_imports_have_no_cycle():
    cycle = find_cycle(import_graph())
    assert cycle is None, "bdpt_drjit's modules import each other: " + " -> ".join(cycle)


def test_render_is_the_api_function():
    from bdpt_drjit import api
    assert bdpt_drjit.render is api.render
    assert bdpt_drjit.Renderer.__module__ == "bdpt_drjit.render"
