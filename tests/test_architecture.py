"""The package's structure, read from its source with ``ast`` (nothing is imported or run; fast lane):

* no import circle between hyqjax's modules, counting every import statement: at module level, inside functions
  and under ``TYPE_CHECKING`` (a circle hidden by a function-level import is still a circle);
* no module above ``hyqjax/sim/`` compares implementation names (``impl == "warp"``, ``impl != "auto"``,
  ``"c" in supported``, ``impl in ("jax", "warp")``): a task asks the backend object of
  :func:`hyqjax.sim.backend.get` and :mod:`hyqjax.sim.backend`'s functions instead, so it never knows which
  simulator runs it;
* no module above ``hyqjax/sim/`` imports a backend implementation (``sim.mjx_backend``, ``sim.cpu_backend``)
  directly: they are reached through :func:`hyqjax.sim.backend.get`.
"""
from __future__ import annotations

import ast
import os
import re

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
PACKAGE = os.path.join(ROOT, "hyqjax")
#: The implementation names (:data:`hyqjax.sim.impls.IMPLS`).
IMPL_NAMES = {"auto", "jax", "warp", "c"}
#: A string constant that can only be an implementation name (``"jax"`` alone also names the library:
#: ``"jax" in sys.modules``; a comparison of it with an ``impl`` expression is still caught).
IMPL_ONLY = {"auto", "warp", "c"}
#: An expression naming an implementation: ``impl``, ``st.impl``, ``args.impl``, ``SUPPORTED_IMPLS``, ...
IMPL_IDENT = re.compile(r"(^|_)impls?(_|$)", re.IGNORECASE)
#: The backend implementations and the modules of the C MuJoCo backend's parts (its models, runner, host programs).
BACKEND_IMPLEMENTATIONS = ("hyqjax.sim.mjx_backend", "hyqjax.sim.cpu_backend", "hyqjax.sim.cpu_models",
                           "hyqjax.sim.cpu_runner", "hyqjax.sim.host_jit")


def modules() -> dict[str, tuple[str, bool]]:
    """``{dotted name: (path, is a package)}`` of every module of hyqjax."""
    out = {}
    for d, _, files in os.walk(PACKAGE):
        for f in files:
            if not f.endswith(".py"):
                continue
            path = os.path.join(d, f)
            parts = os.path.relpath(path, ROOT)[:-3].split(os.sep)
            is_pkg = parts[-1] == "__init__"
            out[".".join(parts[:-1] if is_pkg else parts)] = (path, is_pkg)
    return out


MODULES = modules()
TREES = {name: ast.parse(open(path, encoding="utf-8").read(), path) for name, (path, _) in MODULES.items()}


def _module_of(name: str) -> str | None:
    """The hyqjax module a dotted name lies in (the longest prefix that is a module)."""
    while name and name not in MODULES:
        name = name.rpartition(".")[0]
    return name or None


def imports(name: str) -> dict[str, int]:
    """``{imported hyqjax module: line}`` of every import statement of module ``name``, wherever it stands.
    ``from P import x`` imports ``P.x`` when that is a module, else ``P``."""
    _, is_pkg = MODULES[name]
    base = name if is_pkg else name.rpartition(".")[0]
    out: dict[str, int] = {}
    for node in ast.walk(TREES[name]):
        if isinstance(node, ast.Import):
            targets = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            mod = node.module or ""
            if node.level:
                pkg = base
                for _ in range(node.level - 1):
                    pkg = pkg.rpartition(".")[0]
                mod = f"{pkg}.{mod}" if mod else pkg
            targets = [f"{mod}.{a.name}" if f"{mod}.{a.name}" in MODULES else mod for a in node.names]
        else:
            continue
        for t in targets:
            m = _module_of(t) if t == "hyqjax" or t.startswith("hyqjax.") else None
            if m is not None and m != name:
                out.setdefault(m, node.lineno)
    return out


GRAPH = {name: imports(name) for name in MODULES}


def cycles(graph: dict[str, dict[str, int]]) -> list[list[str]]:
    """The strongly connected components with more than one module (Tarjan), each as a list of modules."""
    index, low, stack, on, found = {}, {}, [], set(), []

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
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                found.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return found


def above_sim(name: str) -> bool:
    return name != "hyqjax.sim" and not name.startswith("hyqjax.sim.")


def _names_impl(node: ast.AST) -> bool:
    if isinstance(node, ast.Name):
        return bool(IMPL_IDENT.search(node.id))
    if isinstance(node, ast.Attribute):
        return bool(IMPL_IDENT.search(node.attr))
    return False


def _impl_constant(node: ast.AST) -> bool:
    if isinstance(node, ast.Constant) and isinstance(node.value, str):
        return node.value in IMPL_ONLY
    if isinstance(node, (ast.Tuple, ast.List, ast.Set)) and node.elts:
        return all(isinstance(e, ast.Constant) and e.value in IMPL_NAMES for e in node.elts)
    return False


def impl_comparisons(name: str) -> list[str]:
    """``"path:line: source"`` of every comparison in module ``name`` that compares implementation names."""
    path, _ = MODULES[name]
    src = open(path, encoding="utf-8").read()
    out = []
    for node in ast.walk(TREES[name]):
        if not isinstance(node, ast.Compare):
            continue
        operands = [node.left, *node.comparators]
        if any(_names_impl(o) or _impl_constant(o) for o in operands):
            out.append(f"{os.path.relpath(path, ROOT)}:{node.lineno}: {ast.get_source_segment(src, node)}")
    return out


def test_the_graph_sees_function_level_imports():
    """The reader counts an import inside a function (sim.backend.get imports the backends only when called)."""
    assert "hyqjax.sim.mjx_backend" in GRAPH["hyqjax.sim.backend"]
    assert "hyqjax.sim.cpu_backend" in GRAPH["hyqjax.sim.backend"]
    assert cycles({"a": {"b": 1}, "b": {"c": 1}, "c": {"a": 1}, "d": {"a": 1}}) == [["a", "b", "c"]]


def test_no_import_circle():
    found = cycles(GRAPH)
    lines = [f"{a} imports {b} (line {GRAPH[a][b]})" for comp in found for a in comp for b in GRAPH[a] if b in comp]
    assert not found, "import circles (every import statement counts, function-level too):\n" + "\n".join(lines)


def test_the_comparison_reader_finds_impl_comparisons():
    tree = ast.parse('if st.impl == "warp": pass\nok = "c" in supported\nx = impl in ("jax", "warp")\n'
                     'if "jax" not in sys.modules: pass\nif mode == "fast": pass\n')
    found = [n.lineno for n in ast.walk(tree) if isinstance(n, ast.Compare)
             and any(_names_impl(o) or _impl_constant(o) for o in [n.left, *n.comparators])]
    assert sorted(found) == [1, 2, 3]


def test_no_impl_comparison_above_sim():
    found = [c for name in sorted(MODULES) if above_sim(name) for c in impl_comparisons(name)]
    assert not found, ("implementation names compared above hyqjax/sim/ (ask the backend object of "
                       "hyqjax.sim.backend.get, or hyqjax.sim.backend's functions):\n" + "\n".join(found))


def test_backends_are_reached_through_backend_get():
    direct = [f"{a} imports {b} (line {line})" for a, deps in GRAPH.items() if above_sim(a)
              for b, line in deps.items() if b in BACKEND_IMPLEMENTATIONS]
    assert not direct, "use hyqjax.sim.backend.get(impl) instead:\n" + "\n".join(direct)
