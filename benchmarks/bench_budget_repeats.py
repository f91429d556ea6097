"""Repeated budget rows, condition against condition (issue 47): the spread of each row.

The rows of ``bench_budget.py`` vary between runs more than between commits, so a change is
shown only by repeating them. Run ``bench_budget.py --work DIR`` N times per condition (each
from a git worktree of the commit), then:

``PYTHONPATH=. .venv/bin/python benchmarks/bench_budget_repeats.py --runs
before=DIR1,DIR2,DIR3 after=DIR4,DIR5,DIR6 --name NAME`` -> ``benchmarks/results/NAME.md``
(one line per condition and row: median and range over the runs, every run's value) and
``NAME.png``. Each DIR holds the ``budget.json`` that ``bench_budget.py`` writes.
"""

from __future__ import annotations

import argparse
import json
import statistics
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt

RESULTS = Path(__file__).resolve().parent / "results"

COLUMNS = (  # (key, header, scale, format)
    ("latency_p95_s", "latency p95 s", 1.0, "{:.2f}"),
    ("latency_median_s", "latency median s", 1.0, "{:.2f}"),
    ("n_maps", "maps", 1.0, "{:.0f}"),
    ("ate_joint_m", "joint ATE keyframes cm", 100.0, "{:.2f}"),
    ("frames_ate_joint_m", "joint ATE every frame cm", 100.0, "{:.2f}"),
    ("ate_own_mean_m", "robots' own ATE (mean) cm", 100.0, "{:.2f}"),
    ("achieved_kbit_s", "up kbit/s", 1.0, "{:.1f}"),
    ("frames_sent", "frames sent", 1.0, "{:.0f}"),
    ("lost", "lost", 1.0, "{:.0f}"),
)


def load(dirs: list[Path]) -> list[dict[str, Any]]:
    """Every row of every run: the ``budget.json`` of each directory, with ``run`` (its
    position), ``n_maps`` and ``lost`` (frames sent but not decoded) added."""
    rows = []
    for i, d in enumerate(dirs):
        path = d / "budget.json"
        if not path.is_file():
            raise SystemExit(f"{path}: no budget.json (run bench_budget.py --work {d} first)")
        for r in json.loads(path.read_text()):
            r = dict(r, run=i, n_maps=len(r.get("maps") or []) or None)
            r["lost"] = r["frames_sent"] - r["frames_decoded"]
            rows.append(r)
    return rows


def cell(values: list[Any], scale: float, fmt: str) -> str:
    """'median [min-max] (each run)' over the runs (– for a run without the value)."""
    each = [None if v is None else v * scale for v in values]
    have = [v for v in each if v is not None]
    runs = ", ".join("–" if v is None else fmt.format(v) for v in each)
    if not have:
        return "–"
    med = fmt.format(statistics.median(have))
    return f"**{med}** [{fmt.format(min(have))}–{fmt.format(max(have))}] ({runs})"


def table(conditions: dict[str, list[dict[str, Any]]]) -> str:
    head = "| condition | row | runs | " + " | ".join(c[1] for c in COLUMNS) + " |"
    lines = [head, "|" + "---|" * (3 + len(COLUMNS))]
    for name, rows in conditions.items():
        for row in dict.fromkeys(r["row"] for r in rows):
            mine = [r for r in rows if r["row"] == row]
            cells = [cell([r.get(k) for r in mine], s, f) for k, _, s, f in COLUMNS]
            lines.append(f"| {name} | {row} | {len(mine)} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def plot(conditions: dict[str, list[dict[str, Any]]], path: Path) -> None:
    """Per row: each run's pose latency p95, maps and joint ATE, condition by condition."""
    rows = list(dict.fromkeys(r["row"] for rs in conditions.values() for r in rs))
    panels = (
        ("latency_p95_s", "pose latency p95 at the robot [s]", 1.0, 1.0),
        ("n_maps", "maps at the end (1 = one map)", 1.0, 1.0),
        ("ate_joint_m", "joint ATE, keyframes [cm] (log)", 100.0, None),
    )
    fig, axes = plt.subplots(1, len(panels), figsize=(5 * len(panels), 4))
    width = 0.8 / max(1, len(conditions))
    for ax, (key, label, scale, target) in zip(axes, panels, strict=True):
        for c, (name, rs) in enumerate(conditions.items()):
            for x, row in enumerate(rows):
                ys = [r[key] * scale for r in rs if r["row"] == row and r.get(key) is not None]
                xs = [x + (c - (len(conditions) - 1) / 2) * width] * len(ys)
                ax.scatter(xs, ys, s=25, color=f"C{c}", label=name if x == 0 else None)
        if target is not None:
            ax.axhline(target, color="k", ls="--", lw=1)
        if key == "ate_joint_m":
            ax.set_yscale("log")
        ax.set_xticks(range(len(rows)), rows)
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--runs", nargs="+", required=True, help="NAME=DIR,DIR,... per condition")
    p.add_argument("--name", default="budget_repeats")
    args = p.parse_args()
    conditions = {}
    for spec in args.runs:
        name, _, dirs = spec.partition("=")
        if not dirs:
            raise SystemExit(f"{spec!r}: give NAME=DIR[,DIR...]")
        conditions[name] = load([Path(d) for d in dirs.split(",")])
    png = RESULTS / f"{args.name}.png"
    plot(conditions, png)
    text = f"![plot]({png.name})\n\n" + table(conditions)
    (RESULTS / f"{args.name}.md").write_text(text)
    print(text)


if __name__ == "__main__":
    main()
