"""Both uplinks at camera rate over finished demo runs: robot -> edge per robot and
edge -> cloud for all, by message type, with each run's joint ATE.

Each ``--run NAME=OUT`` is the ``--out`` folder of one ``recslam demo`` (runs of one NAME are
one condition, e.g. one commit; conditions A/B on the same data). Rates are the link
counters' bytes (``OUT/run/stats/robot-<r>.json`` and ``edge.json``, framing and control
messages included) over the sequence's camera time (frames / ``--rate-hz``), 1 kbit = 1000
bit: what each link carries when everything keeps up with the camera.

Run: ``.venv/bin/python benchmarks/bench_link_bits.py --run before=OUT1 --run after=OUT2
--out benchmarks/results/link_bits.md --note "how the runs were made"`` (writes the .md and a
.png beside it).
"""

from __future__ import annotations

import argparse
import json
from dataclasses import dataclass
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt

from lab.links import git_commit

RESULTS = Path(__file__).resolve().parent / "results"
CLOUD_TYPES = ("KeyframeUpdateCoded", "MapPointUpdateCoded", "KeyframePoses", "FramePoses")


@dataclass(frozen=True)
class RunBits:
    """One run: robot -> edge kbit/s per robot, edge -> cloud kbit/s (total and by type),
    the joint ATE [cm] and the number of maps."""

    condition: str
    run: str
    robots: dict[str, float]
    cloud: float
    cloud_types: dict[str, float]
    ate_cm: float
    maps: int


def run_bits(name: str, out: Path, rate_hz: float) -> RunBits:
    """The :class:`RunBits` of the demo in ``out``."""
    stats = out / "run" / "stats"
    robots, seconds = {}, 0.0
    for path in sorted(stats.glob("robot-*.json")):
        s = json.loads(path.read_text())
        seconds = max(seconds, s["frames"] / rate_hz)
        robots[path.stem.removeprefix("robot-")] = s["counters"]["tx"]["bytes"] * 8 / 1e3
    robots = {r: kbit / seconds for r, kbit in robots.items()}
    tx = json.loads((stats / "edge.json").read_text())["cloud"]["tx"]
    types = {t: v["bytes"] * 8 / 1e3 / seconds for t, v in tx["by_type"].items()}
    report = json.loads((out / "report.json").read_text())
    ate = report.get("ate", {}).get("joint_rmse_m")
    maps = len(report.get("map", {}).get("maps", []) or [])
    return RunBits(
        name,
        out.name,
        robots,
        tx["bytes"] * 8 / 1e3 / seconds,
        types,
        100 * float(ate) if ate is not None else float("nan"),
        maps,
    )


def table(rows: list[RunBits]) -> list[str]:
    robots = sorted({r for row in rows for r in row.robots})
    head = ["condition", "run", *(f"{r}→edge" for r in robots), "edge→cloud"]
    head += [*(f"↳ {t}" for t in CLOUD_TYPES), "joint ATE cm", "maps"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for row in rows:
        cells = [row.condition, f"`{row.run}`"]
        cells += [f"{row.robots.get(r, float('nan')):.1f}" for r in robots]
        cells += [f"**{row.cloud:.1f}**"]
        cells += [f"{row.cloud_types.get(t, 0.0):.1f}" for t in CLOUD_TYPES]
        cells += [f"{row.ate_cm:.2f}", str(row.maps)]
        lines.append("| " + " | ".join(cells) + " |")
    return lines


def plot(rows: list[RunBits], path: Path) -> None:
    """Each condition's first run: kbit/s per robot and to the cloud, side by side."""
    firsts: dict[str, RunBits] = {}
    for row in rows:
        firsts.setdefault(row.condition, row)
    robots = sorted({r for row in rows for r in row.robots})
    links = [*(f"{r}→edge" for r in robots), "edge→cloud"]
    fig, ax = plt.subplots(figsize=(8, 4))
    width = 0.8 / max(1, len(firsts))
    for i, row in enumerate(firsts.values()):
        vals = [row.robots.get(r, 0.0) for r in robots] + [row.cloud]
        ax.bar([k + i * width for k in range(len(links))], vals, width, label=row.condition)
    ax.axhline(150, color="gray", ls="--", lw=0.8, label="targets (150 / 600)")
    ax.axhline(600, color="gray", ls="--", lw=0.8)
    ax.set_xticks([k + 0.4 - width / 2 for k in range(len(links))], links)
    ax.set_ylabel("kbit/s at camera rate")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--run", action="append", required=True, metavar="NAME=OUT")
    ap.add_argument("--rate-hz", type=float, default=20.0, help="camera rate (20 Hz)")
    ap.add_argument("--out", type=Path, default=RESULTS / "link_bits.md")
    ap.add_argument("--note", default="", help="a sentence on how the runs were made")
    args = ap.parse_args()
    rows = []
    for spec in args.run:
        name, _, out = spec.partition("=")
        rows.append(run_bits(name, Path(out), args.rate_hz))
    png = args.out.with_suffix(".png")
    plot(rows, png)
    lines = [
        "# Both uplinks by condition (robot → edge per robot, edge → cloud)",
        "",
        f"`benchmarks/bench_link_bits.py` (table written with the script of {git_commit()}). "
        + args.note,
        "",
        *table(rows),
        "",
        f"![both uplinks]({png.name})",
    ]
    args.out.write_text("\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
