"""The README stays short, true and readable (issue 50).

CI proves the README: its first section has exactly two commands and ``.ci/run`` runs the
second. A newcomer reads the rest in five minutes: few lines, short table cells, a glossary,
one name for MBP, no history (sessions, commit hashes; that is what ``docs/results.md`` and
the results files are for), and every file it links to or names is in the repository.
"""

from __future__ import annotations

import re
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"

MAX_LINES = 150
MAX_CHARS = 10_000
MAX_LINE = 200
MAX_CELL = 120
GLOSSARY = ("agent", "atlas", "map", "mission", "keyframe", "MBP", "Table 3", "edge")
TOP_FOLDERS = ("benchmarks", "common", "dashboard", "deploy", "docker", "docs", "lab")
TOP_FOLDERS += ("recslam", "scripts", "services", "sim", "tests")
ALLOWED_MISSING: frozenset[str] = frozenset()
"""Paths the README may name before they exist: another change is writing them."""
OUTPUTS = ("out/", "data/")
"""Folders the commands write (``out/demo/report.md``): not in the repository."""


def readme() -> str:
    return README.read_text()


def section(title: str, text: str | None = None) -> str:
    text = readme() if text is None else text
    assert f"\n## {title}\n" in text, f"README has no '## {title}' section"
    return text.split(f"\n## {title}\n", 1)[1].split("\n## ", 1)[0]


def quick_start_commands() -> list[str]:
    block = re.search(r"```sh\n(.*?)```", section("Two commands"), re.S)
    assert block, "README's 'Two commands' section has no sh code block"
    lines = [ln.split("#", 1)[0].strip() for ln in block.group(1).splitlines()]
    return [ln for ln in lines if ln]


def table_cells(text: str) -> list[str]:
    rows = [ln for ln in text.splitlines() if ln.startswith("|")]
    rows = [row for row in rows if not re.fullmatch(r"[|:\- ]+", row.strip())]
    return [c.strip() for row in rows for c in row.strip().strip("|").split(" | ")]


def links(text: str) -> list[str]:
    """Markdown link and image targets, without anchors; external ones left out."""
    targets = re.findall(r"\]\(([^)\s]+)\)", text)
    return [t.split("#", 1)[0] for t in targets if not re.match(r"[a-z]+:", t) and t[0] != "#"]


def named_paths(text: str) -> list[str]:
    """Repository paths the README names in backticks (``lab/run/``, ``docs/x.md``): those
    starting with a top-level folder of the repository; outputs (``out/``, ``data/``) and
    placeholders (``<tier>``) left out."""
    out = []
    for code in re.findall(r"`([^`\n]+)`", text):
        for word in code.split():
            word = word.rstrip(",.;:)")
            if word.split("/", 1)[0] in TOP_FOLDERS and "/" in word and "<" not in word:
                out.append(word)
    return out


def mentioned_files(text: str) -> list[str]:
    """Every file name the README mentions, linked or not (``DESIGN.md``, ``docs/x.md``)."""
    return re.findall(r"(?<![\w/.-])[\w/.-]+\.(?:md|png|py|yml|toml|lock)\b", text)


def test_quick_start_has_two_commands() -> None:
    commands = quick_start_commands()
    assert commands == ["make demo", "make test"]


def test_ci_runs_the_readme_test_command() -> None:
    script = (ROOT / ".ci" / "run").read_text().splitlines()
    body = [ln.strip() for ln in script if ln.strip() and not ln.lstrip().startswith("#")]
    assert body[-1] == quick_start_commands()[1]


def test_make_targets_exist() -> None:
    for command in quick_start_commands():
        target = command.split()[1]
        out = subprocess.run(
            ["make", "-n", target], cwd=ROOT, capture_output=True, text=True, check=False
        )
        assert out.returncode == 0, out.stderr


def test_says_how_long_the_tests_take_and_how_to_run_fewer() -> None:
    text = section("Two commands")
    assert re.search(r"`make test` takes about \d+ min", text)
    assert 'pytest -m "not slow"' in text


def test_short() -> None:
    text = readme()
    assert len(text.splitlines()) <= MAX_LINES
    assert len(text) <= MAX_CHARS
    long = [n for n, ln in enumerate(text.splitlines(), 1) if len(ln) > MAX_LINE]
    assert long == [], f"lines over {MAX_LINE} characters"


def test_sections_in_order() -> None:
    titles = re.findall(r"^## (.+)$", readme(), re.M)
    assert titles == [
        "Two commands",
        "Status",
        "How it fits together",
        "Glossary",
        "Where to go next",
    ]


def test_status_cells_are_one_short_line_and_every_row_links_its_results() -> None:
    status = section("Status")
    long = [c for c in table_cells(status) if len(c) > MAX_CELL]
    assert long == [], f"status cells over {MAX_CELL} characters"
    rows = [ln for ln in status.splitlines() if ln.startswith("| ") and "---" not in ln][1:]
    assert len(rows) >= 10
    for row in rows:
        last = row.strip().strip("|").split(" | ")[-1].strip()
        assert last == "—" or re.fullmatch(r"\[[^]]+\]\(benchmarks/results/[^)]+\)", last), row


def test_no_history() -> None:
    text = readme()
    assert not re.search(r"\bsessions?\b", text, re.I), "history goes to docs/results.md"
    hashes = [h for h in re.findall(r"\b[0-9a-f]{7,40}\b", text) if re.search(r"[a-f]", h)]
    assert [h for h in hashes if re.search(r"\d", h)] == [], "no commit hashes in the README"


def test_glossary_defines_the_words_it_uses() -> None:
    glossary = section("Glossary")
    terms = re.findall(r"^- \*\*([^*]+)\*\*", glossary, re.M)
    for word in GLOSSARY:
        assert any(word.lower() in t.lower() for t in terms), f"{word} not in the glossary"


def test_mbp_has_one_name() -> None:
    text = readme()
    assert "map backbone profiling" in text  # the paper's name
    assert "backbone pruning" not in text


@pytest.mark.parametrize("target", sorted(set(links(readme()) + named_paths(readme()))))
def test_every_path_it_links_or_names_exists(target: str) -> None:
    assert target in ALLOWED_MISSING or (ROOT / target).exists(), target


def test_every_file_it_mentions_exists() -> None:
    text = readme()
    linked = {Path(t).name for t in links(text)}
    missing = [
        name
        for name in mentioned_files(text)
        if not name.startswith(OUTPUTS)
        and name not in ALLOWED_MISSING | linked
        and not (ROOT / name).exists()
    ]
    assert missing == [], "the README mentions files that are not in the repository"


def test_the_checks_can_fail() -> None:
    bad = "## Status\n| a | b |\n|---|---|\n| " + "x" * 200 + " | [f](missing.md) |\n"
    assert [len(c) for c in table_cells(bad)] == [1, 1, 200, 15]
    assert links(bad) == ["missing.md"]
    assert links("[a](https://x.org) [b](#top) ![c](docs/c.png#s)") == ["docs/c.png"]
    assert mentioned_files("see DESIGN.md and (docs/a.md), not x.mdx") == ["DESIGN.md", "docs/a.md"]
    assert named_paths("`lab/run/x.py`, `out/demo/`, `services/<tier>/`, `make test`") == [
        "lab/run/x.py"
    ]
