"""The shape of the house (docs/DESIGN.md): imports run downhill through the layers, and no
class or function grows past what one reader can hold.

The layers, lowest first. A module may import from its own layer and the ones below,
never from a higher one, and imports within a layer form no cycle.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "dyngs"

LAYERS: list[tuple[str, tuple[str, ...]]] = [
    (
        "foundation",
        (
            "dyngs.errors", "dyngs.types", "dyngs.ops", "dyngs.geometry", "dyngs.sh",
            "dyngs.io", "dyngs.neighbors", "dyngs.ply", "dyngs.registry", "dyngs.compiled",
        ),
    ),
    ("components", ("dyngs.renderers", "dyngs.fields", "dyngs.losses", "dyngs.datamanagers",
                    "dyngs.metrics", "dyngs.appearance")),
    ("model", ("dyngs.model",)),
    ("engine", ("dyngs.engine", "dyngs.config", "dyngs.configio")),
    ("runs", ("dyngs.methods", "dyngs.runs")),
    ("front", ("dyngs.cli", "dyngs.tools", "dyngs.viewer", "dyngs")),
]  # fmt: skip
"""`dyngs` itself (the package's __init__) is the front door: it may reach anything."""

MAX_CLASS_LINES = 250
MAX_FUNCTION_LINES = 60


def _module_name(path: Path) -> str:
    parts = path.relative_to(ROOT).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _layer(module: str) -> int:
    best, found = -1, -1
    for index, (_, prefixes) in enumerate(LAYERS):
        for prefix in prefixes:
            if (module == prefix or module.startswith(prefix + ".")) and len(prefix) > best:
                best, found = len(prefix), index
    if found < 0:
        raise AssertionError(f"{module} is in no layer: add it to LAYERS")
    return found


def _modules() -> dict[str, ast.Module]:
    return {_module_name(p): ast.parse(p.read_text()) for p in sorted(PACKAGE.rglob("*.py"))}


def _runtime_imports(tree: ast.Module) -> set[str]:
    """dyngs modules imported when the module runs (imports under `if TYPE_CHECKING:`
    are for the type checker only and are left out)."""
    found: set[str] = set()

    def visit(node: ast.AST) -> None:
        if isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test):
            for statement in node.orelse:
                visit(statement)
            return
        if isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("dyngs"):
            found.add(node.module)
        elif isinstance(node, ast.Import):
            found.update(a.name for a in node.names if a.name.startswith("dyngs"))
        for child in ast.iter_child_nodes(node):
            visit(child)

    visit(tree)
    return found


def test_every_import_runs_downhill() -> None:
    uphill = []
    for module, tree in _modules().items():
        for target in _runtime_imports(tree):
            if _layer(target) > _layer(module):
                uphill.append(f"{module} ({LAYERS[_layer(module)][0]}) imports {target} "
                              f"({LAYERS[_layer(target)][0]})")  # fmt: skip
    assert not uphill, "\n".join(uphill)


def test_no_import_cycle() -> None:
    modules = _modules()
    graph = {
        m: {t for t in _runtime_imports(tree) if t in modules and t != m}
        for m, tree in modules.items()
    }
    # A package's __init__ importing its own submodules is how packages are built; the
    # cycles that matter are between modules.
    for m in graph:
        graph[m] = {t for t in graph[m] if not m.startswith(t + ".")}
    state: dict[str, int] = {}
    cycle: list[str] = []

    def visit(node: str, path: list[str]) -> bool:
        state[node] = 1
        for nxt in graph[node]:
            if state.get(nxt) == 1:
                cycle.extend([*path[path.index(nxt) :], nxt])
                return True
            if state.get(nxt) is None and visit(nxt, [*path, nxt]):
                return True
        state[node] = 2
        return False

    for start in graph:
        if state.get(start) is None and visit(start, [start]):
            break
    assert not cycle, " → ".join(cycle)


def _sizes() -> list[tuple[str, str, int]]:
    sizes = []
    for path in sorted(PACKAGE.rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, (ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)):
                assert node.end_lineno is not None
                kind = "class" if isinstance(node, ast.ClassDef) else "function"
                where = f"{path.relative_to(ROOT)}:{node.lineno} {node.name}"
                sizes.append((kind, where, node.end_lineno - node.lineno + 1))
    return sizes


@pytest.mark.parametrize(("kind", "limit"), [("class", MAX_CLASS_LINES),
                                             ("function", MAX_FUNCTION_LINES)])  # fmt: skip
def test_no_class_or_function_is_too_long(kind: str, limit: int) -> None:
    long = [
        f"{where}: {lines} lines" for k, where, lines in _sizes() if k == kind and lines > limit
    ]
    assert not long, f"over {limit} lines:\n" + "\n".join(long)
