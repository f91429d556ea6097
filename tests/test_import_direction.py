"""Imports run one way (docs/architecture.md: "the CLI only parses", experiments apart).

``services`` and ``dashboard`` import ``common``; ``common`` imports neither; no service
imports another; nothing below the command line imports ``recslam`` (the CLI) or ``lab`` (the
experiments); the dashboard reads the cloud through ``common.map_view`` and imports no
service; a service wires the dashboard in its runner only. ``sim`` (the simulators and link
tools, on the lab floor) imports ``common`` and ``services``, never ``lab`` or the CLI;
``common``, ``services`` and ``dashboard`` never import ``sim``; ``lab``, ``benchmarks``, the
CLI and the tests may. ``lab`` drives the services and never imports the CLI; ``benchmarks``
are scripts beside the CLI: they may import ``lab`` but not ``recslam`` (what a benchmark needs
of a command lives in ``lab`` or ``common``). Every import counts: module level, inside
functions, under ``TYPE_CHECKING``, relative, and ``importlib.import_module("...")``.

The cloud's rooms (``services/cloud/atlas``, ``optimization``, ``fusion``, ``store``) import
one way too: ``atlas`` <- ``optimization`` <- ``fusion``, ``atlas`` <- ``store``.

No module imports itself back through others: the modules of every package form no import
cycle (a cycle that a function-level import hides still is one; it is how splitting a file
to meet the size guide goes wrong).
"""

from __future__ import annotations

import ast
import sys
from collections.abc import Iterable, Iterator, Mapping
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("common", "services", "dashboard", "lab", "sim", "recslam", "benchmarks")
CLI_AND_LAB = ("recslam", "lab")
SIM = "sim"
"""The simulators: above ``common`` and ``services``, below ``lab``, the benchmarks and the CLI."""
SCRIPTS = ("benchmarks",)
"""Folders of scripts: run as ``python benchmarks/x.py``, they import their siblings by bare
name (``from bench_real_imu import run``)."""

# (importing module, imported module) pairs that break a rule today and are tolerated until
# they are fixed; each names its reason. Empty: a new violation cannot hide here.
KNOWN_EXCEPTIONS: frozenset[tuple[str, str]] = frozenset()

# Import cycles tolerated until they are fixed, each with its reason. Empty: a new cycle cannot
# hide here (the last one, the cloud app and its optimisation half sharing ``_Agent``, went
# with issue 50: both now import ``services.cloud.agents``).
KNOWN_CYCLES: frozenset[frozenset[str]] = frozenset()


def _module_name(path: Path) -> str:
    parts = path.relative_to(ROOT).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _is_import_module(node: ast.AST) -> bool:
    """``importlib.import_module("a.b")`` (or a bare ``import_module``) with a literal name."""
    return (
        isinstance(node, ast.Call)
        and isinstance(node.func, ast.Attribute | ast.Name)
        and getattr(node.func, "attr", getattr(node.func, "id", None)) == "import_module"
        and bool(node.args)
        and isinstance(node.args[0], ast.Constant)
        and isinstance(node.args[0].value, str)
    )


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
        elif _is_import_module(node):
            yield node.args[0].value  # type: ignore[attr-defined]


def _modules() -> dict[str, Path]:
    return {
        _module_name(path): path
        for package in PACKAGES
        for path in sorted((ROOT / package).rglob("*.py"))
    }


def _dependencies(path: Path, modules: Mapping[str, Path]) -> set[str]:
    """The modules of ``modules`` that ``path`` imports, as precisely as the import says:
    ``from pkg import sub`` is ``pkg.sub`` when that is a module, ``pkg`` (its
    ``__init__``) otherwise; a script's bare ``import sibling`` is its sibling."""
    name = _module_name(path)
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found: set[str] = set()

    def add(module: str) -> None:
        if _top(name) in SCRIPTS and f"{_top(name)}.{module}" in modules:
            module = f"{_top(name)}.{module}"
        while module and module not in modules:
            module = module.rpartition(".")[0]
        if module and module != name:
            found.add(module)

    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[: len(base) - (node.level - 1)]
                module = ".".join([*base, *([node.module] if node.module else [])])
            else:
                module = node.module or ""
            for alias in node.names:
                sub = f"{module}.{alias.name}"
                add(sub if sub in modules else module)
        elif isinstance(node, ast.Import):
            for alias in node.names:
                add(alias.name)
        elif _is_import_module(node):
            add(node.args[0].value)  # type: ignore[attr-defined]
    return found


def _import_graph() -> dict[str, set[str]]:
    modules = _modules()
    return {name: _dependencies(path, modules) for name, path in modules.items()}


def _cycles(graph: Mapping[str, Iterable[str]]) -> list[frozenset[str]]:
    """The strongly connected components of ``graph`` with more than one module (Tarjan,
    iterative): each is a set of modules that import one another in a circle."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    out: list[frozenset[str]] = []
    for root in graph:
        if root in index:
            continue
        work = [(root, iter(graph.get(root, ())))]
        index[root] = low[root] = len(index)
        stack.append(root)
        on_stack.add(root)
        while work:
            node, targets = work[-1]
            for target in targets:
                if target not in index:
                    index[target] = low[target] = len(index)
                    stack.append(target)
                    on_stack.add(target)
                    work.append((target, iter(graph.get(target, ()))))
                    break
                if target in on_stack:
                    low[node] = min(low[node], index[target])
            else:
                work.pop()
                if work:
                    low[work[-1][0]] = min(low[work[-1][0]], low[node])
                if low[node] == index[node]:
                    component = set()
                    while True:
                        member = stack.pop()
                        on_stack.discard(member)
                        component.add(member)
                        if member == node:
                            break
                    if len(component) > 1:
                        out.append(frozenset(component))
    return out


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
    if target_top in SCRIPTS and top not in SCRIPTS:
        return f"nothing imports the {target_top} scripts"
    if top == "recslam":
        return None  # the command line sits on top
    if top in SCRIPTS or top == "lab":
        return f"{top} does not import the CLI" if target_top == "recslam" else None
    if target_top in CLI_AND_LAB:
        return f"nothing below the CLI imports {target_top}"
    if target_top == SIM and top != SIM:
        return f"{top} does not import the simulators"
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
        ("common.links", "services.cloud.fusion.uplink", True),
        ("services.edge.app", "services.cloud.config", True),
        ("services.edge.app", "lab.links", True),
        ("dashboard.viewer", "services.cloud.store.map_source", True),
        ("services.cloud.server", "dashboard.viewer", True),
        ("services.cloud.runner", "dashboard.viewer", False),
        ("services.edge.app", "services.edge.vio", False),
        ("services.edge.app", "services", False),
        ("dashboard.viewer", "common.map_view", False),
        ("lab.netns", "recslam.orchestration", True),
        ("lab.links", "lab.run.orchestration", False),
        ("lab.table3", "services.cloud.core", False),
        ("lab.seeds", "benchmarks.bench_real_imu", True),
        ("benchmarks.bench_vocabulary", "recslam.commands.vocab", True),
        ("benchmarks.bench_mbp_live", "lab.seeds", False),
        ("recslam.commands.demo", "lab.run.orchestration", False),
        ("recslam.commands.cloud", "services.cloud.runner", False),
        ("sim.cloud", "services.cloud.atlas.atlas", False),
        ("sim.robot", "services.robot.coding", False),
        ("sim.robot", "sim.vio", False),
        ("sim.netem", "common.errors", False),
        ("sim.cloud", "lab.table3", True),
        ("sim.vio", "recslam.cli", True),
        ("services.cloud.runner", "sim.cloud", True),
        ("common.data.synth.cameras", "sim.vio", True),
        ("dashboard.viewer", "sim.cloud", True),
        ("lab.bandwidth", "sim.faultproxy", False),
        ("benchmarks.bench_vio", "sim.vio", False),
        ("recslam.commands.experiment", "sim.netem", False),
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


def test_no_import_cycles() -> None:
    graph = _import_graph()
    assert len(graph) > 200, "the scan found too few modules: wrong root?"
    new = [sorted(c) for c in _cycles(graph) if c not in KNOWN_CYCLES]
    assert new == [], "modules that import one another in a circle"


def test_known_cycles_are_still_there() -> None:
    assert not KNOWN_CYCLES - set(_cycles(_import_graph())), "a known cycle is gone: remove it"


def test_cycles_hidden_in_functions_are_found(tmp_path: Path, monkeypatch) -> None:
    lab = tmp_path / "lab"
    lab.mkdir()
    (lab / "__init__.py").write_text("from lab import base\n")  # a package re-export
    (lab / "base.py").write_text("X = 1\n")
    (lab / "run.py").write_text("from lab import base\nfrom .report import write\n")
    (lab / "report.py").write_text("def write():\n    from lab.run import go\n")
    (lab / "table.py").write_text("import lab.base\nfrom lab import X\n")
    bench = tmp_path / "benchmarks"
    bench.mkdir()
    (bench / "bench_a.py").write_text("from bench_b import f\n")
    (bench / "bench_b.py").write_text("import bench_a\n")
    monkeypatch.setattr(sys.modules[__name__], "ROOT", tmp_path)
    monkeypatch.setattr(sys.modules[__name__], "PACKAGES", ("lab", "benchmarks"))
    graph = _import_graph()
    assert graph["lab.run"] == {"lab.base", "lab.report"}
    assert graph["lab.table"] == {"lab.base", "lab"}
    assert sorted(sorted(c) for c in _cycles(graph)) == [
        ["benchmarks.bench_a", "benchmarks.bench_b"],
        ["lab.report", "lab.run"],
    ]


CLOUD_ROOMS: dict[str, frozenset[str]] = {
    "atlas": frozenset(),
    "optimization": frozenset({"atlas"}),
    "fusion": frozenset({"atlas", "optimization"}),
    "store": frozenset({"atlas"}),
}
"""The cloud's rooms (``services/cloud/<room>/``) and the rooms each may import; a room imports
nothing else of the cloud but ``services.cloud.config`` (the service modules on top import the
rooms, never the other way)."""


def _cloud_room_violations(graph: Mapping[str, Iterable[str]]) -> list[str]:
    out = []
    for source, targets in graph.items():
        parts = source.split(".")
        if parts[:2] != ["services", "cloud"] or len(parts) < 4 or parts[2] not in CLOUD_ROOMS:
            continue
        for target in targets:
            tparts = target.split(".")
            if tparts[:2] != ["services", "cloud"] or target == "services.cloud.config":
                continue
            room = tparts[2] if len(tparts) > 2 else ""
            if room != parts[2] and room not in CLOUD_ROOMS[parts[2]]:
                out.append(f"{source} imports {target}")
    return out


def test_cloud_rooms_import_one_way() -> None:
    graph = _import_graph()
    assert any(m.startswith("services.cloud.atlas.") for m in graph), "no cloud rooms found"
    assert _cloud_room_violations(graph) == []


def test_cloud_room_rule_catches_what_it_names() -> None:
    graph = {
        "services.cloud.atlas.atlas": {"services.cloud.optimization.mbp"},
        "services.cloud.store.output": {"services.cloud.app", "services.cloud.atlas.atlas"},
        "services.cloud.fusion.merge": {"services.cloud.config", "services.cloud.fusion.uplink"},
        "services.cloud.core": {"services.cloud.store.persistence"},
    }
    assert _cloud_room_violations(graph) == [
        "services.cloud.atlas.atlas imports services.cloud.optimization.mbp",
        "services.cloud.store.output imports services.cloud.app",
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
