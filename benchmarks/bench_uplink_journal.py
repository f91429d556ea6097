"""What each robot's uplink carried, from the edge's journals of finished runs (issue 47).

The edge journals every ``RobotFrame`` it accepted (``services.edge.journal``), so a run's
robot -> edge link can be split afterwards, without re-running it: per robot the frames and
keyframes sent, kbit/s of keyframe features, non-keyframe features and IMU, and the
keyframes' spacing (how often a keyframe came sooner than the budget's plan, i.e. for lost
tracking).

``PYTHONPATH=. .venv/bin/python benchmarks/bench_uplink_journal.py --runs
before=DIR1,DIR2 after=DIR3,DIR4 --out benchmarks/results/NAME_parts.md``; each DIR is a
``bench_budget.py --work`` folder of one row (``DIR/<row>/run/state/edge``) or an edge state
folder itself.
"""

from __future__ import annotations

import argparse
import itertools
import statistics
from pathlib import Path

from common.links.robot_edge import RobotFrame
from lab.journal_replay import journal_agents, journal_messages

HEADER = (
    "| condition | run | robot | frames sent | keyframes | keyframe kB (median) | "
    "keyframe gap s (median / min) | gaps < 1.5 s | keyframes kbit/s | non-keyframes kbit/s | "
    "IMU kbit/s | total kbit/s |\n|---|---|---|---|---|---|---|---|---|---|---|---|"
)


def _state_dirs(path: Path) -> list[Path]:
    """The edge state folders under a bench folder (or the folder itself)."""
    if (path / "journals").is_dir() or any(path.glob("*.journal")):
        return [path]
    return sorted(p for p in path.glob("*/run/state/edge") if p.is_dir())


def rows(condition: str, run: Path) -> list[str]:
    """One table line per robot journalled in ``run``."""
    out = []
    for state in _state_dirs(run):
        for agent in journal_agents(state):
            frames = [m for m in journal_messages(state, agent) if isinstance(m, RobotFrame)]
            if len(frames) < 2:
                continue
            span = (frames[-1].timestamp_ns - frames[0].timestamp_ns) * 1e-9
            kf = [m for m in frames if m.keyframe]
            gaps = [(b.timestamp_ns - a.timestamp_ns) * 1e-9 for a, b in itertools.pairwise(kf)]
            kbps = [
                8e-3 * sum(len(m.features) for m in kf) / span,
                8e-3 * sum(len(m.features) for m in frames if not m.keyframe) / span,
                8e-3 * sum(len(m.imu) for m in frames) / span,
            ]
            size = statistics.median(len(m.features) for m in kf) / 1000 if kf else 0.0
            gap = f"{statistics.median(gaps):.2f} / {min(gaps):.2f}" if gaps else "–"
            out.append(
                f"| {condition} | {run.name} | {agent} | {len(frames)} | {len(kf)} | "
                f"{size:.1f} | {gap} | {sum(g < 1.5 for g in gaps)} | "
                + " | ".join(f"{x:.1f}" for x in kbps)
                + f" | **{sum(kbps):.1f}** |"
            )
    return out


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--runs", nargs="+", required=True, help="NAME=DIR[,DIR...] per condition")
    p.add_argument("--out", type=Path, required=True)
    args = p.parse_args()
    lines = [HEADER]
    for spec in args.runs:
        name, _, dirs = spec.partition("=")
        for d in dirs.split(","):
            lines += rows(name, Path(d))
    text = "\n".join(lines) + "\n"
    args.out.write_text(text)
    print(text)


if __name__ == "__main__":
    main()
