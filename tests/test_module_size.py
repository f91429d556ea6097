"""No module outgrows the size guide (issue 50: "modules <= ~600 lines").

A module past ~600 lines holds more than one idea: split it along a real seam (a base class
for one half, as ``services.cloud.app_optimization`` is ``CloudApp``'s; plain data into a
sibling module) without an import cycle (``tests/test_import_direction.py``). The limit here
leaves a little room above the guide so that a small fix does not force a split at once.
"""

from __future__ import annotations

from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("common", "services", "dashboard", "lab", "sim", "recslam", "benchmarks")
MAX_LINES = 650


def _lines(path: Path) -> int:
    return len(path.read_text().splitlines())


def test_no_module_is_over_the_limit() -> None:
    paths = [p for package in PACKAGES for p in sorted((ROOT / package).rglob("*.py"))]
    assert len(paths) > 200, "the scan found too few modules: wrong root?"
    too_long = {str(p.relative_to(ROOT)): n for p in paths if (n := _lines(p)) > MAX_LINES}
    assert too_long == {}, f"modules over {MAX_LINES} lines: split them along a real seam"


def test_the_count_is_of_lines(tmp_path: Path) -> None:
    module = tmp_path / "m.py"
    module.write_text("x = 1\n" * (MAX_LINES + 1))
    assert _lines(module) == MAX_LINES + 1
