"""The robot <-> edge link, message type by message type, over finished demo runs.

Each ``--run NAME=OUT`` is the ``--out`` folder of one ``recslam demo``; runs of one NAME are
one condition (e.g. two commits on the same data, A/B). For each robot the link counters its
``recslam robot --stats-out`` wrote (``OUT/run/stats/robot-<name>.json``) give the bytes per
message type both ways, as kbit/s at camera rate (the bytes over the sequence's duration,
frames / ``--rate-hz``), and the report gives its pose latency (camera frame -> its pose on
the robot) and the joint ATE. The table gives every run; the plot the up- and downlink per
message type of each condition's first run.

Run: ``.venv/bin/python benchmarks/bench_robot_link.py --run before=OUT1 --run after=OUT2
--out benchmarks/results/robot_link.md`` (writes the .md and a .png beside it).
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


@dataclass(frozen=True)
class RobotLink:
    """One robot's link in one run: kbit/s at camera rate each way, and by message type
    ``{type: (messages, kbit/s)}``; its pose latency (median, p95, max s, as the report
    prints them) and the run's joint ATE [cm]."""

    condition: str
    run: str
    robot: str
    up_kbps: float
    up_types: dict[str, tuple[int, float]]
    down_kbps: float
    down_types: dict[str, tuple[int, float]]
    latency: tuple[str, str, str]
    ate_cm: float


def robot_links(name: str, out: Path, rate_hz: float) -> list[RobotLink]:
    """One :class:`RobotLink` per robot of the run in ``out``."""
    report = json.loads((out / "report.json").read_text())
    ate_m = report.get("ate", {}).get("joint_rmse_m")
    rows = []
    for path in sorted((out / "run" / "stats").glob("robot-*.json")):
        stats = json.loads(path.read_text())
        robot = path.stem.removeprefix("robot-")
        seconds = stats["frames"] / rate_hz
        per: dict[str, tuple[float, dict[str, tuple[int, float]]]] = {}
        for direction in ("tx", "rx"):
            c = stats["counters"][direction]
            types = {
                t: (int(v["messages"]), v["bytes"] * 8 / seconds / 1e3)
                for t, v in c["by_type"].items()
            }
            per[direction] = (c["bytes"] * 8 / seconds / 1e3, types)
        lat = report.get("robots", {}).get(robot, {}).get("pose_latency_s") or {}
        latency = (
            (f"{lat['median']:.2f}", f"{lat['p95']:.2f}", f"{lat['max']:.2f}")
            if lat
            else ("—", "—", "—")
        )
        rows.append(
            RobotLink(
                name,
                out.name,
                robot,
                per["tx"][0],
                per["tx"][1],
                per["rx"][0],
                per["rx"][1],
                latency,
                100 * float(ate_m) if ate_m is not None else float("nan"),
            )
        )
    return rows


def kinds(types: dict[str, tuple[int, float]]) -> str:
    big = sorted(types.items(), key=lambda kv: -kv[1][1])
    return ", ".join(f"{t} {n}× {k:.1f}" for t, (n, k) in big if k >= 0.05)


def plot(rows: list[RobotLink], path: Path) -> None:
    firsts: dict[str, RobotLink] = {}
    for r in rows:
        firsts.setdefault(r.condition, r)
    names = list(firsts)
    fig, axes = plt.subplots(1, 2, figsize=(10, 3.6))
    for ax, up, title in zip(axes, (True, False), ("robot → edge", "edge → robot"), strict=True):
        by = {n: firsts[n].up_types if up else firsts[n].down_types for n in names}
        bottom = [0.0] * len(names)
        for t in sorted({t for d in by.values() for t in d}):
            vals = [by[n].get(t, (0, 0.0))[1] for n in names]
            if max(vals) < 0.05:
                continue
            ax.bar(names, vals, bottom=bottom, label=t)
            bottom = [b + v for b, v in zip(bottom, vals, strict=True)]
        ax.set_title(f"{title}, kbit/s at camera rate")
        ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--run", action="append", required=True, metavar="NAME=OUT")
    ap.add_argument("--rate-hz", type=float, default=20.0, help="camera rate (20 Hz)")
    ap.add_argument("--out", type=Path, default=RESULTS / "robot_link.md")
    ap.add_argument("--note", default="", help="a sentence on how the runs were made")
    args = ap.parse_args()
    rows = []
    for item in args.run:
        name, _, out = item.partition("=")
        rows += robot_links(name, Path(out), args.rate_hz)
    commit = git_commit()
    lines = [
        "# The robot <-> edge link by message type",
        "",
        f"`benchmarks/bench_robot_link.py` (table written at {commit}). {args.note}",
        "",
        "| condition | run | robot | robot→edge kbit/s | by type (messages, kbit/s) "
        "| edge→robot kbit/s | by type (messages, kbit/s) | pose latency median / p95 / max s "
        "| joint ATE cm |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r.condition} | `{r.run}` | {r.robot} | {r.up_kbps:.1f} | {kinds(r.up_types)} "
            f"| **{r.down_kbps:.1f}** | {kinds(r.down_types)} | {' / '.join(r.latency)} "
            f"| {r.ate_cm:.2f} |"
        )
    args.out.write_text("\n".join(lines) + "\n")
    plot(rows, args.out.with_suffix(".png"))
    print(args.out.read_text())


if __name__ == "__main__":
    main()
