"""Whole runs on real IMUs, repeated: the joint ATE's run-to-run spread, SE(3) and Sim(3).

Each ``--run NAME=OUT:DATASET`` is one ``recslam demo --data DATASET --out OUT`` (robots,
edge and cloud as processes); runs of one NAME are one condition (e.g. synchronised, 15 ms
offset estimated, 15 ms offset given to the edge). For each run the cloud's keyframe
trajectories (``OUT/run/results/trajectories``) are aligned to the dataset's ground truth
with one transform for all robots, SE(3) and Sim(3) (the latter's scale is the map's scale
error), and the edge's final camera-IMU offsets are read from ``OUT/run/stats/edge.json``.
The table gives every run and each condition's mean and range; the plot shows the runs.

Run: ``.venv/bin/python benchmarks/bench_real_imu_live.py --run synchronised=OUT1:DATA ...
--out benchmarks/results/real_imu_live.md`` (writes the .md and a .png beside it).
"""

from __future__ import annotations

import argparse
import json
import subprocess
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from common.evaluation import (
    AlignMode,
    AteConfig,
    compute_joint_ate,
    load_groundtruth,
    read_result_trajectories,
)

RESULTS = Path(__file__).resolve().parent / "results"


@dataclass(frozen=True)
class LiveRun:
    name: str
    out: Path
    joint_se3_m: float
    joint_sim3_m: float
    scale_error: float  # the map's size over the true size, minus 1 (Sim(3), joint)
    per_robot_se3_m: dict[str, float]
    offsets_ms: dict[str, float]
    maps: int


def evaluate(name: str, out: Path, dataset: Path) -> LiveRun:
    """One run's joint ATE (SE(3) and Sim(3)) against ``dataset``'s ground truth."""
    est = read_result_trajectories(out / "run" / "results")
    refs, _ = load_groundtruth(sorted(est), dataset)
    se3 = compute_joint_ate(refs, est, AteConfig(align=AlignMode.SE3))
    sim3 = compute_joint_ate(refs, est, AteConfig(align=AlignMode.SIM3))
    edge = json.loads((out / "run" / "stats" / "edge.json").read_text())
    offsets = {
        r: float(s.get("time_offset_ms", float("nan")))
        for r, s in sorted(edge.get("robots", {}).items())
    }
    report = json.loads((out / "report.json").read_text())
    maps = report.get("map", {}).get("maps") or []
    return LiveRun(
        name,
        out,
        se3.stats.rmse,
        sim3.stats.rmse,
        1.0 / sim3.transform.scale - 1.0,
        {a: r.stats.rmse for a, r in sorted(se3.individual.items())},
        offsets,
        len(maps),
    )


def plot(runs: list[LiveRun], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = list(dict.fromkeys(r.name for r in runs))
    fig, ax = plt.subplots(1, 2, figsize=(11, 3.8))
    for i, name in enumerate(names):
        mine = [r for r in runs if r.name == name]
        x = np.full(len(mine), i) + np.linspace(-0.12, 0.12, len(mine))
        ax[0].scatter(x, [100 * r.joint_se3_m for r in mine], label="SE(3)", color="C0")
        ax[0].scatter(x, [100 * r.joint_sim3_m for r in mine], label="Sim(3)", color="C1")
        ax[1].scatter(x, [100 * r.scale_error for r in mine], color="C2")
    for a in ax:
        a.set_xticks(range(len(names)), names, fontsize=8)
        a.grid(alpha=0.3)
    handles, labels = ax[0].get_legend_handles_labels()
    ax[0].legend(handles[:2], labels[:2], fontsize=8)
    ax[0].set_ylabel("joint ATE [cm]")
    ax[1].set_ylabel("map scale error [%] (Sim(3))")
    fig.suptitle("whole runs on real V2 IMUs, one dot per run")
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def cm(v: float) -> str:
    return f"{100 * v:.2f}"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--run", action="append", required=True, metavar="NAME=OUT:DATASET")
    ap.add_argument("--out", type=Path, default=RESULTS / "real_imu_live.md")
    ap.add_argument("--note", default="", help="a sentence on how the runs were made")
    args = ap.parse_args()
    runs = []
    for item in args.run:
        name, _, rest = item.partition("=")
        out, _, data = rest.partition(":")
        runs.append(evaluate(name, Path(out), Path(data)))
    commit = subprocess.run(
        ["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True, check=False
    ).stdout.strip()
    lines = [
        "# Whole runs on real IMUs: run-to-run spread",
        "",
        f"`benchmarks/bench_real_imu_live.py` (tables written at {commit}). {args.note}",
        "",
        "| condition | runs | joint ATE SE(3) cm, mean [min-max] | joint ATE Sim(3) cm, mean "
        "| map scale error %, mean [min-max] | maps |",
        "|---|---|---|---|---|---|",
    ]
    for name in dict.fromkeys(r.name for r in runs):
        mine = [r for r in runs if r.name == name]
        se3 = np.array([r.joint_se3_m for r in mine])
        sim3 = np.array([r.joint_sim3_m for r in mine])
        sc = np.array([r.scale_error for r in mine])
        lines.append(
            f"| {name} | {len(mine)} | {cm(se3.mean())} [{cm(se3.min())}-{cm(se3.max())}] "
            f"| {cm(sim3.mean())} | {100 * sc.mean():+.2f} [{100 * sc.min():+.2f}, "
            f"{100 * sc.max():+.2f}] | {', '.join(str(r.maps) for r in mine)} |"
        )
    lines += [
        "",
        "| condition | run | joint SE(3) cm | joint Sim(3) cm | scale error % | per robot SE(3) "
        "cm | offsets at the end ms |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in runs:
        per = " / ".join(cm(v) for v in r.per_robot_se3_m.values())
        offs = " / ".join(f"{v:.2f}" for v in r.offsets_ms.values())
        lines.append(
            f"| {r.name} | `{r.out.name}` | {cm(r.joint_se3_m)} | {cm(r.joint_sim3_m)} "
            f"| {100 * r.scale_error:+.2f} | {per} | {offs} |"
        )
    args.out.write_text("\n".join(lines) + "\n")
    plot(runs, args.out.with_suffix(".png"))
    print(args.out.read_text())


if __name__ == "__main__":
    main()
