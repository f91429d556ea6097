"""Every tier's ``core.py`` is sans-I/O (docs/architecture.md; like h11 and aioquic).

A core never touches a socket, a clock, a thread, a process or a file: time enters as ``now``
and work leaves as actions that the tier's server runs. This checks the core module's own
imports (module level, in functions, under ``TYPE_CHECKING``); what the modules it imports
import in turn is out of scope (the cloud core drives ``CloudApp``, which owns SQLite and a
lock, through its methods only).
"""

from __future__ import annotations

import ast
from collections.abc import Iterator
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
CORES = ("services/robot/core.py", "services/cloud/core.py", "services/edge/core.py")
KNOWN_GAPS: set[str] = set()
IO_MODULES = ("asyncio", "threading", "sqlite3", "socket", "concurrent.futures", "time", "os")


def _imports(source: str) -> Iterator[str]:
    """Every absolute module name ``source`` imports, with ``from a import b`` also as
    ``a.b`` (``from concurrent import futures`` imports ``concurrent.futures``)."""
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            yield from (alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and not node.level and node.module:
            yield node.module
            yield from (f"{node.module}.{alias.name}" for alias in node.names)


def _io_imports(source: str) -> set[str]:
    return {
        name
        for name in _imports(source)
        for io in IO_MODULES
        if name == io or name.startswith(f"{io}.")
    }


@pytest.mark.parametrize("core", CORES)
def test_core_imports_no_io(core: str) -> None:
    assert _io_imports((ROOT / core).read_text()) == set()


def test_known_gaps_are_still_gaps() -> None:
    assert not [gap for gap in KNOWN_GAPS if (ROOT / gap).exists()], (
        "a tier has a core now: move it from KNOWN_GAPS to CORES"
    )


def test_the_check_sees_io() -> None:
    source = (
        "import os.path\nfrom concurrent import futures\nimport asyncio as aio\n"
        "def f():\n    from time import monotonic\n"
        "import timeit\nfrom osgeo import gdal\nfrom collections import deque\n"
    )
    assert _io_imports(source) == {
        "os.path",
        "concurrent.futures",
        "asyncio",
        "time",
        "time.monotonic",
    }
