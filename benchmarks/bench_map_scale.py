"""Where the map's scale goes (issue 46): each stage's scale error on recorded whole runs.

Run: ``.venv/bin/python benchmarks/bench_map_scale.py --ab LABEL=RECORDING:DATASET [...]
[--variant LABEL:KEY=VALUE[,KEY=VALUE...] ...] [--jobs 2]``; prints one table per recording
and with ``--write`` writes ``benchmarks/results/map_scale_table.md``.

Each recording (``recslam demo --record-uplink``) is replayed through the cloud service's own
core (:func:`lab.table3.replay`, modelled schedule, deterministic) once per variant (the
service's defaults, and each ``--variant``: dotted paths into ``CloudServiceConfig``, e.g.
``domain.full_ba.max_seconds`` or ``full_ba.at_shutdown_s``, as ``bench_mbp_midrun.py`` takes
them), and :mod:`lab.map_scale` measures the map scale error (``map size
/ true size - 1``, Sim(3) alignment to the ground truth) of: the edge's keyframe poses as
uplinked (each robot in its own edge frame, first and last pose sent), and the cloud's keyframes
before and after every full BA and at the end (joint: all robots under one alignment; per robot:
each alone).
"""

from __future__ import annotations

import argparse
import concurrent.futures
import logging
import platform
import time
from pathlib import Path

from bench_mbp_midrun import overridden

from common.evaluation.results import load_groundtruth
from common.vocabulary import DEFAULT_VOCABULARY_PATH, Vocabulary
from lab.links import git_commit
from lab.map_scale import SolveTrace, StageScale, stage_scale, stage_scales, uplinked_trajectories
from lab.table3 import replay_recording, service_config
from services.cloud.runner import find_camera

log = logging.getLogger("bench_map_scale")
RESULTS = Path(__file__).resolve().parent / "results"


def _pct(x: float) -> str:
    return f"{100 * x:+.2f}"


def _robots(row: StageScale) -> str:
    return " / ".join(f"{_pct(row.per_robot[n])}" for n in sorted(row.per_robot))


def run_one(label: str, rec: Path, data: Path, variant: str, spec: str) -> list[str]:
    """The table rows of one recording replayed with one variant."""
    cfg = overridden(service_config(True), spec)
    vocab = Vocabulary.load(DEFAULT_VOCABULARY_PATH)
    trace = SolveTrace()
    t0 = time.perf_counter()
    r = replay_recording(
        rec, find_camera(None, data), vocab, cfg, label, full_ba=True, solve_fn=trace
    )
    refs, _ = load_groundtruth(sorted(r.trajectories), data)
    rows = []
    for s in stage_scales(trace.snapshots, r.info, refs):
        if "full BA" in s.label:
            rows.append(
                f"| {label} | {variant} | {s.label} (map {s.map_id}) | {s.keyframes} "
                f"| {_pct(s.joint)} | {_robots(s)} | {100 * s.ate_se3_m:.2f} "
                f"| {100 * s.ate_sim3_m:.2f} |"
            )
    fin = stage_scale("final", -1, refs, r.trajectories)
    if fin is not None:
        rows.append(
            f"| {label} | {variant} | **final** (maps {r.maps}) | {fin.keyframes} "
            f"| **{_pct(fin.joint)}** | {_robots(fin)} | **{100 * fin.ate_se3_m:.2f}** "
            f"| {100 * fin.ate_sim3_m:.2f} |"
        )
    log.info("%s / %s: %.0f s", label, variant, time.perf_counter() - t0)
    return rows


def uplinked_rows(label: str, rec: Path, data: Path) -> list[str]:
    refs, _ = load_groundtruth(["robot0", "robot1", "robot2"], data)
    out = []
    for last in (False, True):
        up = uplinked_trajectories(rec, last=last)
        per = {n: stage_scale("edge", 0, refs, {n: t}) for n, t in sorted(up.items())}
        text = " / ".join(_pct(s.joint) if s else "—" for s in per.values())
        out.append(f"| {label} | edge, {'last' if last else 'first'} pose uplinked | {text} |")
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--ab", action="append", required=True, help="LABEL=RECORDING:DATASET")
    ap.add_argument("--variant", action="append", default=[], help="LABEL:KEY=VALUE,...")
    ap.add_argument(
        "--base",
        default="",
        help="KEY=VALUE,... applied to every variant first (e.g. domain.full_ba.max_seconds=10000: "
        "solves not cut by the wall-time budget, so that a loaded machine gives the same result)",
    )
    ap.add_argument("--jobs", type=int, default=1)
    ap.add_argument("--write", type=Path, default=None, help="write the tables to this file")
    args = ap.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(name)s: %(message)s")
    for noisy in ("services", "lab", "common"):
        logging.getLogger(noisy).setLevel(logging.WARNING)
    runs = []
    for item in args.ab:
        label, _, rest = item.partition("=")
        rec, _, data = rest.partition(":")
        runs.append((label, Path(rec), Path(data)))
    variants = [("default", "")] + [tuple(v.split(":", 1)) for v in args.variant]
    jobs = [
        (lab, rec, data, v, ",".join(filter(None, (args.base, spec))))
        for lab, rec, data in runs
        for v, spec in variants
    ]
    with concurrent.futures.ProcessPoolExecutor(max_workers=args.jobs) as pool:
        results = list(pool.map(run_one, *zip(*jobs, strict=True)))
    lines = [
        f"Command: `benchmarks/bench_map_scale.py {' '.join('--ab ' + a for a in args.ab)} "
        f"--base {args.base!r} "
        f"{' '.join(repr('--variant ' + v) for v in args.variant)}`; commit {git_commit()}; "
        f"{time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}; {platform.machine()}.",
        "",
        "Scale error: map size / true size - 1 (Sim(3) alignment to the ground truth), %; "
        "per robot: robot0 / robot1 / robot2 each aligned alone.",
        "",
        "| recording | stage | per robot % |",
        "|---|---|---|",
    ]
    for label, rec, data in runs:
        lines += uplinked_rows(label, rec, data)
    lines += [
        "",
        "| recording | variant | stage | keyframes | joint scale % | per robot % | ATE SE(3) cm "
        "| ATE Sim(3) cm |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for rows in results:
        lines += rows
    text = "\n".join(lines) + "\n"
    print(text)
    if args.write is not None:
        args.write.write_text(text)


if __name__ == "__main__":
    main()
