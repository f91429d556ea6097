"""MBP during operation (issue 17, item 2): keyframes kept and joint ATE, same recordings.

Run: ``.venv/bin/python benchmarks/bench_mbp_midrun.py --ab RECORDING:DATASET [...] [--every 40]
[--settle 30] [--variant LABEL:KEY=VALUE[,KEY=VALUE...] ...] [--rows 'LABEL;LABEL']``; writes
``benchmarks/results/mbp_midrun.md`` (one row per recording and run, then per run over the
recordings: the change of joint ATE against no MBP on the same recording) and
``mbp_midrun.png``.

Each recording (``recslam demo --record-uplink``) is replayed through the cloud service's own
core (:func:`lab.table3.replay`, modelled schedule, solves taking no time: the result does not
depend on the load of the machine) with the service's defaults (VI full BA every 100
keyframes and at shutdown) and:

- **no MBP**;
- **MBP at shutdown** (the service's default);
- **MBP every N keyframes** while running, once per ``--settle`` value S (a pass while running
  keeps each agent's S newest keyframes, ``MbpScheduleConfig.settle_keyframes``; the
  final pass at shutdown keeps ``keep_recent`` = 5), each twice: the pass right after
  the pose graph that finds it due, and the pass after a full BA of the map that this pose
  graph then schedules (``MbpScheduleConfig.after_full_ba``);
- one row per ``--variant``: the last of those (every N, last settle, after a full BA) with
  ``KEY=VALUE`` overrides, ``KEY`` a dotted path into ``CloudServiceConfig``
  (``mbp.every_keyframes``, ``mbp.running.cover_ratio``, ``full_ba.every_keyframes``,
  ``domain.full_ba.imu_factors``, ...; values parsed as int, float, true/false, none, else
  string).

A replay is open-loop: the recorded edge applied the corrections of the *live* cloud, and its
later updates (map points re-observed on a revisit) are in its corrected frame. In recordings
made before the edge named the frame of its messages (``FrameAnchor``) the cloud
placed them through the robot's one map-from-edge transform, so a configuration whose
corrections differ from the live run's received them in a frame that no longer fit its own
keyframes, and a replay was faithful only for the configuration the recording was made with.
In newer recordings each message lands through the replaying cloud's own pose of its anchor
(``services.cloud.fusion.rebase``): a rigid fix per message, close to faithful for other
configurations; still compare live (``bench_mbp_live.py``).

Keyframes: the atlas at the end over the keyframes received. ATE: joint RMSE (SE(3)) of every
keyframe received (a pruned one through the kept keyframe it is anchored to), as the cloud's
report computes it; "kept" is the same over the kept keyframes only; "Sim(3)" the joint ATE
after a similarity alignment and its scale (how much of a run's error is the whole map's
scale). Full BAs: how many ran
(shutdown included) and their solve time here, the price of the extra full BAs.
"""

from __future__ import annotations

import argparse
import concurrent.futures
import dataclasses
import functools
import logging
import platform
import time
from pathlib import Path
from typing import Any

import numpy as np

from common.evaluation.metrics import AlignMode
from common.evaluation.results import load_groundtruth
from common.vocabulary import DEFAULT_VOCABULARY_PATH, Vocabulary
from lab.links import git_commit
from lab.table3 import ReplayResult, joint_ate, replay_recording, service_config
from services.cloud.core_actions import SolveKind, SolveRequest, SolveResult, solve
from services.cloud.runner import find_camera
from services.cloud.service_config import CloudServiceConfig

log = logging.getLogger("bench_mbp_midrun")
RESULTS = Path(__file__).resolve().parent / "results"


def _value(text: str) -> Any:  # a field value of any type, checked by the dataclass
    low = text.lower()
    if low in ("true", "false"):
        return low == "true"
    if low == "none":
        return None
    for kind in (int, float):
        try:
            return kind(text)
        except ValueError:
            pass
    return text


def _replaced(obj: Any, path: list[str], value: Any) -> Any:
    """The dataclass ``obj`` with the field at the dotted ``path`` set to ``value``."""
    name, *rest = path
    return dataclasses.replace(
        obj, **{name: _replaced(getattr(obj, name), rest, value) if rest else value}
    )


def overridden(cfg: CloudServiceConfig, spec: str) -> CloudServiceConfig:
    """``cfg`` with ``KEY=VALUE[,KEY=VALUE...]`` applied (module docstring)."""
    for item in filter(None, spec.split(",")):
        key, _, text = item.partition("=")
        cfg = _replaced(cfg, key.split("."), _value(text))
    return cfg


def variants(
    every: int, settles: list[int], extra: list[str]
) -> list[tuple[str, CloudServiceConfig]]:
    """(label, configuration) of every row of one recording."""
    rows = [
        ("no MBP", service_config(False)),
        ("MBP at shutdown", service_config(True)),
    ]
    for s in settles:
        cfg = overridden(
            service_config(True, every), f"mbp.settle_keyframes={s},mbp.after_full_ba=false"
        )
        rows.append((f"every {every}, settle {s}, after its pose graph", cfg))
        cfg = overridden(cfg, "mbp.after_full_ba=true")
        rows.append((f"every {every}, settle {s}, after a full BA", cfg))
    base = rows[-1][1]
    for spec in extra:
        label, _, keys = spec.partition(":")
        rows.append((label, overridden(base, keys)))
    return rows


class _TimedSolve:
    """The service's in-thread solve, timed per kind of request."""

    def __init__(self) -> None:
        self.seconds: dict[SolveKind, float] = {}

    def __call__(self, request: SolveRequest) -> SolveResult:
        t0 = time.perf_counter()
        try:
            return solve(request)
        finally:
            dt = time.perf_counter() - t0
            self.seconds[request.kind] = self.seconds.get(request.kind, 0.0) + dt


def run_one(rec: Path, data: Path, label: str, cfg: CloudServiceConfig, vocab: Vocabulary) -> dict:
    camera = find_camera(None, data)
    timed = _TimedSolve()
    r: ReplayResult = replay_recording(rec, camera, vocab, cfg, label, full_ba=True, solve_fn=timed)
    refs, _ = load_groundtruth(sorted(r.trajectories), data)
    ate = joint_ate(refs, r.trajectories)
    sim = joint_ate(refs, r.trajectories, AlignMode.SIM3)
    kept = joint_ate(refs, r.kept_trajectories)
    return {
        "label": label,
        "keyframes": r.keyframes,
        "received": r.keyframes_received,
        "map_points": r.map_points,
        "maps": len(r.maps),
        "loops": r.loops,
        "passes": r.mbp_passes,
        "full_bas": r.full_bas,
        "full_ba_s": timed.seconds.get(SolveKind.FULL_BA, 0.0),
        "joint_m": None if ate is None else ate.stats.rmse,
        "sim3_m": None if sim is None else sim.stats.rmse,
        "scale": None if sim is None else sim.transform.scale,
        "kept_m": None if kept is None else kept.stats.rmse,
        "per_robot_m": {}
        if ate is None
        else {n: a.stats.rmse for n, a in sorted(ate.under_joint.items())},
        "seconds": r.seconds,
    }


def summary(results: dict[str, list[dict]]) -> list[str]:
    """Per row label over the recordings: the change of joint ATE against no MBP on the same
    recording (mean, median, range, how many worse) and the keyframes kept."""
    changes: dict[str, list[float]] = {}
    sim_changes: dict[str, list[float]] = {}
    kept: dict[str, list[float]] = {}
    for rows in results.values():
        base, base_sim = rows[0]["joint_m"], rows[0].get("sim3_m")
        for r in rows[1:]:
            if base and r["joint_m"] is not None:
                changes.setdefault(r["label"], []).append(100 * (r["joint_m"] / base - 1))
                kept.setdefault(r["label"], []).append(100 * r["keyframes"] / max(r["received"], 1))
            if base_sim and r.get("sim3_m") is not None:
                sim_changes.setdefault(r["label"], []).append(100 * (r["sim3_m"] / base_sim - 1))
    if not changes:
        return []
    lines = [
        "| run | recordings | change vs no MBP: mean | median | range | worse on | kept % "
        "| Sim(3) change: mean | worse on |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for label, c in changes.items():
        sc = sim_changes.get(label, [])
        sim_cells = (
            f"{np.mean(sc):+.1f} % | {sum(x > 0 for x in sc)} of {len(sc)}" if sc else "– | –"
        )
        lines.append(
            f"| {label} | {len(c)} | {np.mean(c):+.1f} % | {np.median(c):+.1f} % "
            f"| {min(c):+.0f} .. {max(c):+.0f} % | {sum(x > 0 for x in c)} of {len(c)} "
            f"| {min(kept[label]):.0f}-{max(kept[label]):.0f} | {sim_cells} |"
        )
    return lines


def plot(results: dict[str, list[dict]], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.4, 4.0))
    markers = "osD^v<>"
    for i, (rec, rows) in enumerate(results.items()):
        xs = [100 * r["keyframes"] / max(r["received"], 1) for r in rows]
        ys = [100 * (r["joint_m"] or float("nan")) for r in rows]
        ax.plot(xs, ys, ls=":", color="0.6", lw=0.8)
        for x, y, r in zip(xs, ys, rows, strict=True):
            ax.plot(x, y, markers[i % len(markers)], color=f"C{rows.index(r)}", ms=6)
        ax.plot([], [], markers[i % len(markers)], color="0.3", label=rec)
    for j, r in enumerate(next(iter(results.values()))):
        ax.plot([], [], "s", color=f"C{j}", label=r["label"])
    ax.axvline(60, color="#e45756", ls="--", lw=1)
    ax.set_xlabel("keyframes kept at the end, % of received")
    ax.set_ylabel("joint ATE cm")
    ax.set_title("MBP during operation vs none / at shutdown")
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


@functools.cache
def _vocabulary() -> Vocabulary:
    return Vocabulary.load(DEFAULT_VOCABULARY_PATH)


def _run_job(job: tuple[str, str, str, CloudServiceConfig]) -> dict:
    rec, data, label, cfg = job
    logging.basicConfig(level=logging.WARNING, format="%(asctime)s %(name)s: %(message)s")
    row = run_one(Path(rec), Path(data), label, cfg, _vocabulary())
    log.info("%s: %s: %s", Path(rec).name, label, row)
    return row


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument(
        "--ab", action="append", required=True, metavar="RECORDING:DATASET", help="repeatable"
    )
    ap.add_argument("--every", type=int, default=40, help="MBP every N new keyframes")
    ap.add_argument("--settle", default="30", help="settle values, comma-separated")
    ap.add_argument(
        "--variant",
        action="append",
        default=[],
        metavar="LABEL:KEY=VALUE[,KEY=VALUE...]",
        help="one more row (module docstring); repeatable",
    )
    ap.add_argument(
        "--rows",
        default="",
        metavar="LABEL[;LABEL...]",
        help="only these rows (labels as in the table, ';'-separated; 'no MBP' is always run, "
        "as the base of the changes); default all",
    )
    ap.add_argument("--jobs", type=int, default=1, help="replays run in parallel (processes)")
    ap.add_argument("--out", type=Path, default=RESULTS, help="folder of the md and png")
    args = ap.parse_args()
    logging.basicConfig(level=logging.WARNING, format="%(asctime)s %(name)s: %(message)s")
    log.setLevel(logging.INFO)
    settles = [int(s) for s in args.settle.split(",") if s]
    rows_of = variants(args.every, settles, args.variant)
    if args.rows:
        keep = {"no MBP", *filter(None, args.rows.split(";"))}
        unknown = keep - {label for label, _ in rows_of}
        if unknown:
            ap.error(f"--rows: no row labelled {sorted(unknown)}")
        rows_of = [(label, cfg) for label, cfg in rows_of if label in keep]
    jobs = []
    for spec in args.ab:
        rec_s, data_s = spec.split(":", 1)
        jobs += [(rec_s, data_s, label, cfg) for label, cfg in rows_of]
    t0 = time.perf_counter()
    log.info("%d replays, %d at a time", len(jobs), args.jobs)
    with concurrent.futures.ProcessPoolExecutor(args.jobs) as pool:
        done = list(pool.map(_run_job, jobs))
    results: dict[str, list[dict]] = {}
    names = [Path(spec.split(":", 1)[0]) for spec in args.ab]
    short = len({p.name for p in names}) == len(names)  # else also the folder of each
    for (rec_s, _, _, _), row in zip(jobs, done, strict=True):
        rec = Path(rec_s)
        results.setdefault(rec.name if short else f"{rec.parent.name}/{rec.name}", []).append(row)
    commit = git_commit()
    lines = [
        "# MBP during operation: keyframes kept and joint ATE on the same recordings",
        "",
        f"Command: `benchmarks/bench_mbp_midrun.py {' '.join('--ab ' + a for a in args.ab)} "
        f"--every {args.every} --settle {args.settle}"
        + "".join(f" --variant '{v}'" for v in args.variant)
        + (f" --rows '{args.rows}'" if args.rows else "")
        + f"`; commit {commit}; "
        f"{time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}; {platform.machine()}, "
        f"{time.perf_counter() - t0:.0f} s in all ({args.jobs} at a time). Replays through the "
        "service's core, modelled schedule with solves taking no time (deterministic; see the "
        "script's docstring). Keyframes: kept at the end / received. Kept ATE: over the kept "
        "keyframes only. Full BAs: count, and their solve time here.",
        "",
        "| recording | run | keyframes | kept % | map points | maps | loops | MBP passes "
        "| full BAs | joint ATE cm | change vs no MBP | kept ATE cm | per robot cm "
        "| joint Sim(3) cm | scale |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for rec, rows in results.items():
        base = rows[0]["joint_m"]
        for r in rows:
            j, k = r["joint_m"], r["kept_m"]
            change = (
                ""
                if j is None or base is None or r is rows[0]
                else f"{100 * (j / base - 1):+.1f} %"
            )
            per = ", ".join(f"{100 * v:.2f}" for v in r["per_robot_m"].values())
            sim, scale = r.get("sim3_m"), r.get("scale")
            lines.append(
                f"| `{rec}` | {r['label']} | {r['keyframes']} / {r['received']} "
                f"| {100 * r['keyframes'] / max(r['received'], 1):.0f} | {r['map_points']} "
                f"| {r['maps']} | {r['loops']} | {r['passes']} "
                f"| {r['full_bas']} ({r['full_ba_s']:.0f} s) "
                f"| {'–' if j is None else f'{100 * j:.2f}'} | {change} "
                f"| {'–' if k is None else f'{100 * k:.2f}'} | {per} "
                f"| {'–' if sim is None else f'{100 * sim:.2f}'} "
                f"| {'–' if scale is None else f'{scale:.4f}'} |"
            )
    lines += ["", *summary(results), "", "![mbp_midrun.png](mbp_midrun.png)", ""]
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "mbp_midrun.md").write_text("\n".join(lines))
    plot(results, args.out / "mbp_midrun.png")
    log.info("wrote %s", args.out / "mbp_midrun.md")


if __name__ == "__main__":
    main()
