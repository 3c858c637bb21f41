"""The package's import graph: no module imports one that imports it back, directly or round a circle, counting
the imports inside functions too (they run as soon as the function does)."""

import ast
from pathlib import Path

import fcnpose_tf

PACKAGE = Path(fcnpose_tf.__file__).parent


def _modules() -> dict[str, Path]:
    modules = {}
    for path in PACKAGE.rglob("*.py"):
        parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
        modules[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = path
    return modules


def import_graph() -> dict[str, set[str]]:
    """Module -> the package's modules it imports (`from pkg import submodule` counts as the submodule only)."""
    modules = _modules()
    graph: dict[str, set[str]] = {name: set() for name in modules}
    for name, path in modules.items():
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                submodules = {f"{node.module}.{alias.name}" for alias in node.names} & modules.keys()
                targets = submodules or {node.module}
            elif isinstance(node, ast.Import):
                targets = {alias.name for alias in node.names}
            else:
                continue
            graph[name] |= {t for t in targets if t in modules and t != name}
    return graph


def circles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan's algorithm)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    found: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        for w in graph[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return found


def test_no_import_circle():
    graph = import_graph()
    assert "fcnpose_tf.progress" in graph["fcnpose_tf.data.online"]  # the graph sees what modules import
    assert circles(graph) == []


def test_the_circle_check_finds_one():
    assert circles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]


def test_the_pi_runtime_imports_nothing_of_the_training_side_or_the_correction_loop():
    graph = import_graph()
    runtime = {name for name in graph if name.startswith("fcnpose_tf.runtime")}
    reached = {target for name in runtime for target in graph[name]}
    assert not {t for t in reached if t.startswith(("fcnpose_tf.data", "fcnpose_tf.correction", "fcnpose_tf.training",
                                                    "fcnpose_tf.compression", "fcnpose_tf.sweep"))}


COMPRESSION_MODULE_MAX_LINES = 500
"""No module of compression/ longer: each holds one concern a reader takes in at once (issue 51's layout)."""


def test_no_compression_module_is_over_500_lines():
    lengths = {path.name: len(path.read_text().splitlines()) for path in (PACKAGE / "compression").glob("*.py")}
    assert lengths and max(lengths.values()) <= COMPRESSION_MODULE_MAX_LINES, {
        name: n for name, n in lengths.items() if n > COMPRESSION_MODULE_MAX_LINES}
