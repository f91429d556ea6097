"""The protocol package's modules import each other without cycles, and only at the top."""

from __future__ import annotations

import ast
from pathlib import Path

import common.protocol

PACKAGE = Path(common.protocol.__file__).parent


def _imports(tree: ast.AST) -> list[tuple[str, bool]]:
    """``(imported module, at module level)`` for every ``from common.protocol.x import``."""
    top = {id(n) for n in ast.iter_child_nodes(tree)}
    return [
        (n.module, id(n) in top)
        for n in ast.walk(tree)
        if isinstance(n, ast.ImportFrom) and (n.module or "").startswith("common.protocol.")
    ]


def _graph() -> tuple[dict[str, set[str]], list[str]]:
    graph: dict[str, set[str]] = {}
    nested: list[str] = []
    for path in sorted(PACKAGE.glob("*.py")):
        if path.name == "__init__.py":
            continue
        name = f"common.protocol.{path.stem}"
        deps = graph.setdefault(name, set())
        tree = ast.parse(path.read_text())
        for module, at_top in _imports(tree):
            deps.add(module)
            if not at_top:
                nested.append(f"{name} imports {module} inside a function or block")
    return graph, nested


def test_protocol_modules_form_no_import_cycle_and_import_at_module_level() -> None:
    graph, nested = _graph()
    assert "common.protocol.link" not in graph["common.protocol.store"]
    assert "common.protocol.link_state" in graph["common.protocol.store"]
    assert "common.protocol.link_state" in graph["common.protocol.link"]
    assert nested == []
    done: set[str] = set()

    def visit(node: str, path: tuple[str, ...]) -> None:
        assert node not in path, " -> ".join((*path, node))
        if node in done:
            return
        for dep in graph.get(node, ()):
            visit(dep, (*path, node))
        done.add(node)

    for node in graph:
        visit(node, ())
