"""Imports run one way (DESIGN.md, "Dependency direction"; STYLE.md, "The CLI only parses").

``services`` and ``dashboard`` import ``common``; ``common`` imports neither; no service
imports another; nothing below the command line imports ``recslam`` (the CLI) or ``lab`` (the
experiments); the dashboard reads the cloud through ``common.map_view`` and imports no
service; a service wires the dashboard in its runner only. Every import counts: module level,
inside functions, under ``TYPE_CHECKING``, relative, and ``importlib.import_module("...")``.
"""

from __future__ import annotations

import ast
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("common", "services", "dashboard")
CLI_AND_LAB = ("recslam", "lab")

# (importing module, imported module) pairs that break a rule today and are tolerated until
# they are fixed; each names its reason. Empty: a new violation cannot hide here.
KNOWN_EXCEPTIONS: frozenset[tuple[str, str]] = frozenset()


def _module_name(path: Path) -> str:
    parts = path.relative_to(ROOT).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _imported(path: Path) -> Iterator[str]:
    """Every module name ``path`` imports (absolute; relative imports resolved)."""
    name = _module_name(path)
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            yield from (alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[: len(base) - (node.level - 1)]
                yield ".".join([*base, *([node.module] if node.module else [])])
            elif node.module:
                yield node.module
        elif (
            isinstance(node, ast.Call)
            and isinstance(node.func, ast.Attribute | ast.Name)
            and getattr(node.func, "attr", getattr(node.func, "id", None)) == "import_module"
            and node.args
            and isinstance(node.args[0], ast.Constant)
            and isinstance(node.args[0].value, str)
        ):
            yield node.args[0].value


def _edges() -> list[tuple[str, str]]:
    edges = []
    for package in PACKAGES:
        for path in sorted((ROOT / package).rglob("*.py")):
            name = _module_name(path)
            edges.extend((name, target) for target in _imported(path))
    return edges


def _top(module: str) -> str:
    return module.split(".", 1)[0]


def _tier(module: str) -> str | None:
    """``services.edge.vio.x`` -> ``edge``; None outside ``services.<tier>``."""
    parts = module.split(".")
    return parts[1] if parts[0] == "services" and len(parts) > 1 else None


def _broken_rule(source: str, target: str) -> str | None:
    """The rule that ``source`` importing ``target`` breaks, or None."""
    top, target_top = _top(source), _top(target)
    if target_top in CLI_AND_LAB:
        return f"nothing below the CLI imports {target_top}"
    if top == "common" and target_top in ("services", "dashboard"):
        return f"common imports no {target_top}"
    if top == "dashboard" and target_top == "services":
        return "the dashboard reads common.map_view, no service"
    if top != "services":
        return None
    if _tier(target) is not None and _tier(target) != _tier(source):
        return "no service imports another"
    if target_top == "dashboard" and not source.endswith(".runner"):
        return "only a service's runner wires the dashboard"
    return None


def _violations(edges: list[tuple[str, str]]) -> list[str]:
    out = []
    for source, target in edges:
        rule = _broken_rule(source, target)
        if rule is not None and (source, target) not in KNOWN_EXCEPTIONS:
            out.append(f"{source} imports {target}: {rule}")
    return out


def test_imports_run_one_way() -> None:
    edges = _edges()
    assert len(edges) > 300, "the scan found too few imports: wrong root?"
    assert _violations(edges) == []


def test_known_exceptions_are_still_needed() -> None:
    edges = set(_edges())
    assert not KNOWN_EXCEPTIONS - edges, "a known exception is fixed: remove it from the list"


@pytest.mark.parametrize(
    ("source", "target", "broken"),
    [
        ("services.edge.__main__", "recslam.commands.edge", True),
        ("common.links", "services.cloud.uplink", True),
        ("services.edge.app", "services.cloud.config", True),
        ("services.edge.app", "lab.links", True),
        ("dashboard.viewer", "services.cloud.map_source", True),
        ("services.cloud.server", "dashboard.viewer", True),
        ("services.cloud.runner", "dashboard.viewer", False),
        ("services.edge.app", "services.edge.vio", False),
        ("services.edge.app", "services", False),
        ("dashboard.viewer", "common.map_view", False),
    ],
)
def test_rules_catch_what_they_name(source: str, target: str, broken: bool) -> None:
    assert bool(_violations([(source, target)])) is broken


def test_relative_and_dynamic_imports_are_resolved(tmp_path: Path, monkeypatch) -> None:
    pkg = tmp_path / "services" / "edge"
    pkg.mkdir(parents=True)
    (pkg / "x.py").write_text(
        "from ..cloud import app\nfrom . import y\nimport importlib\n"
        "def f():\n    importlib.import_module('recslam.cli')\n"
    )
    monkeypatch.setattr(sys.modules[__name__], "ROOT", tmp_path)
    assert sorted(_imported(pkg / "x.py")) == [
        "importlib",
        "recslam.cli",
        "services.cloud",
        "services.edge",
    ]


ROS_MODULES = ("rospy", "tf2_ros", "geometry_msgs", "nav_msgs", "sensor_msgs", "rclpy")
ROS_FENCE = "services.robot.ros1.bridge"
"""The one module that imports ROS (it runs under Debian's python3; see services/robot/ros1)."""


def test_ros_is_fenced_into_the_bridge() -> None:
    importers = set()
    for package in (*PACKAGES, *CLI_AND_LAB, "tests", "benchmarks"):
        for path in sorted((ROOT / package).rglob("*.py")):
            if any(m.split(".")[0] in ROS_MODULES for m in _imported(path)):
                importers.add(_module_name(path))
    assert importers == {ROS_FENCE}
