"""MBP during operation, live (issue 17, item 2): the whole job with and without pruning.

Run: ``.venv/bin/python benchmarks/bench_mbp_live.py --data DATASET [...] [--every 40]
[--repeats 1] [--root DIR] [--record]`` runs, per dataset and repeat, the whole job as
``recslam demo --data DATASET --no-dashboard --rate realtime --no-mbp`` runs it
(:func:`lab.links.run_job`) and then the same with ``--mbp-every N`` (alternating, so that the
load of the machine falls on both alike), each into its own folder under ``--root``
(``--record``: with its uplink recorded beside it, for ``bench_mbp_midrun.py``);
``--from-runs`` only reads the folders a run left there; ``--resume`` runs only the folders
that hold no finished run yet (e.g. ``--repeats 4`` after a run with 2). Writes
``benchmarks/results/mbp_live.md`` and ``mbp_live.png``.

A live run is the only faithful test of a configuration that changes the corrections sent to
the edges: the edge applies them and sends its later updates in the corrected frame (see
``bench_mbp_midrun.py``). Live runs are not deterministic (robots, edge and cloud race on the
machine's cores), so the table shows every run and the spread per dataset.

Per run (the demo's ``report.json``): keyframes the edges uplinked and kept at the end, MBP
passes, joint ATE (SE(3), every keyframe received), and the wall time of the whole job.
"""

from __future__ import annotations

import argparse
import json
import logging
import platform
import time
from pathlib import Path

import numpy as np

from common.links import WireFormat
from lab.comparison import mean_shift
from lab.links import git_commit, run_job
from lab.seeds import read_report

log = logging.getLogger("bench_mbp_live")
RESULTS = Path(__file__).resolve().parent / "results"


def folder(root: Path, data: Path, variant: str, repeat: int) -> Path:
    return root / data.name / f"{variant}-{repeat}"


def rebase_stats(out: Path) -> dict | None:
    """The cloud's ``CloudStats.rebase`` of a run (None: a run made before it existed)."""
    path = out / "run" / "stats" / "cloud.json"
    if not path.is_file():
        return None
    return json.loads(path.read_text()).get("rebase") or None


def rebase_cell(rb: dict | None) -> str:
    if rb is None:
        return "–"
    return f"{rb['moved']} / {rb['anchored']} ({100 * rb['max_m']:.1f})"


def summary(out: Path) -> dict:
    """The numbers of one run folder this table shows (:func:`lab.seeds.read_report`)."""
    r = read_report(out)
    return {
        "rebase": rebase_stats(out),
        "run": out.name,
        "uplinked": r["keyframes_uplinked"],
        "kept": r["keyframes_kept"],
        "passes": r["mbp_passes"],
        "maps": r["maps"],
        "joint_m": r["joint_m"],
        "wall_s": r["wall_s"],
        "failed": r["failed"],
    }


def plot(rows: dict[str, dict[str, list[dict]]], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.4, 4.0))
    for i, (name, by) in enumerate(rows.items()):
        for j, runs in enumerate(by.values()):
            xs = [100 * r["kept"] / max(r["uplinked"], 1) for r in runs]
            ys = [100 * (r["joint_m"] or float("nan")) for r in runs]
            ax.plot(xs, ys, "os"[j], color=f"C{i}", ms=7, alpha=0.8, mfc="none" if j else None)
        ax.plot([], [], "o", color=f"C{i}", label=name)
    ax.plot([], [], "o", color="0.4", label="no MBP")
    ax.plot([], [], "s", color="0.4", mfc="none", label="MBP while running")
    ax.axvline(60, color="#e45756", ls="--", lw=1)
    ax.set_xlabel("keyframes kept at the end, % of uplinked")
    ax.set_ylabel("joint ATE cm")
    ax.set_title("Live runs: MBP while running vs none")
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", type=Path, action="append", required=True, help="repeatable")
    ap.add_argument("--every", type=int, default=40, help="MBP every N new keyframes")
    ap.add_argument("--repeats", type=int, default=1, help="runs of each variant per dataset")
    ap.add_argument("--root", type=Path, default=Path("runs/mbp_live"), help="run folders")
    ap.add_argument("--from-runs", action="store_true", help="only summarise the folders")
    ap.add_argument("--timeout", type=float, default=1800.0, help="seconds a run may take")
    ap.add_argument("--out", type=Path, default=RESULTS, help="folder of the md and png")
    ap.add_argument(
        "--record", action="store_true", help="record each run's uplink (RUN/uplink.rec)"
    )
    ap.add_argument(
        "--resume",
        action="store_true",
        help="skip the runs whose folder already holds a finished run (its report.json)",
    )
    ap.add_argument(
        "--only",
        choices=("none", "mbp"),
        help="run only this variant (the other's folders, e.g. linked from an earlier run of "
        "the same commit line, are read as they are)",
    )
    args = ap.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s: %(message)s")
    variants = {"no MBP": 0, f"MBP every {args.every}": args.every}
    t0 = time.perf_counter()
    if not args.from_runs:
        for data in args.data:
            for k in range(args.repeats):
                for name, every in variants.items():
                    if args.only and (every > 0) != (args.only == "mbp"):
                        continue
                    out = folder(args.root, data, f"mbp{every}", k)
                    label = f"[{data.name} {name} #{k}]"
                    if args.resume and (out / "report.json").is_file():
                        log.info("%s already done in %s", label, out)
                        continue
                    run_job(
                        data,
                        out,
                        WireFormat.CODED,
                        "realtime",
                        args.timeout,
                        label,
                        mbp=every > 0,
                        mbp_every=every,
                        record_uplink=out.parent / f"{out.name}.rec" if args.record else None,
                    )
    rows: dict[str, dict[str, list[dict]]] = {}
    for data in args.data:
        by = rows.setdefault(data.name, {})
        for name, every in variants.items():
            for k in range(args.repeats):
                out = folder(args.root, data, f"mbp{every}", k)
                if (out / "report.json").is_file():
                    by.setdefault(name, []).append(summary(out))
    commit = git_commit()
    lines = [
        "# MBP during operation, live: the whole job with and without pruning",
        "",
        f"Command: `benchmarks/bench_mbp_live.py {' '.join('--data ' + str(d) for d in args.data)}"
        f" --every {args.every} --repeats {args.repeats} --root {args.root}"
        f"{' --from-runs' if args.from_runs else ''}"
        f"{f' --only {args.only}' if args.only else ''}"
        f"{' --resume' if args.resume else ''}`; commit {commit}; "
        f"{time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}; {platform.machine()}"
        f"{'' if args.from_runs else f', {time.perf_counter() - t0:.0f} s in all'}. Each run: "
        "`recslam demo --data DATASET --no-dashboard --rate realtime` with `--no-mbp` or "
        f"`--mbp-every {args.every}` (the cloud's defaults otherwise: VI full BA, each pass "
        "after a full BA, 30 newest keyframes per robot kept while running).",
        "",
        "| dataset | variant | run | keyframes kept / uplinked | kept % | MBP passes | maps "
        "| joint ATE cm | wall s | re-placed / anchored (max cm) |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for name, by in rows.items():
        for variant, runs in by.items():
            for r in runs:
                j = r["joint_m"]
                lines.append(
                    f"| {name} | {variant} | {r['run']} | {r['kept']} / {r['uplinked']} "
                    f"| {100 * r['kept'] / max(r['uplinked'], 1):.0f} | {r['passes']} "
                    f"| {r['maps']} | {'–' if j is None else f'{100 * j:.2f}'} "
                    f"| {r['wall_s']:.0f}{' (failed)' if r['failed'] else ''} "
                    f"| {rebase_cell(r['rebase'])} |"
                )
    lines += [
        "",
        "Last column: the edge's coded messages that named their frame (`FrameAnchor`) and "
        "how many of them the cloud placed more than 1 mm / 1 mrad away from the agent's fixed "
        "transform (sent before the edge applied a correction, or after the cloud refined the "
        "anchor), with the largest such move (`CloudStats.rebase`).",
        "",
        "Summary: means and medians over the runs; *p*: the chance that the MBP runs' mean "
        "is this far above (or further) when the runs' labels are shuffled (one-sided "
        "permutation test, `lab.comparison.mean_shift`): small means pruning really costs "
        "accuracy on that dataset, near 1 that it really helps.",
        "",
        "| dataset | runs | mean joint ATE, no MBP | mean joint ATE, MBP | change "
        "| medians | p (MBP worse) |",
        "|---|---|---|---|---|---|---|",
    ]
    for name, by in rows.items():
        js = [
            [r["joint_m"] for r in by.get(variant, []) if r["joint_m"] is not None]
            for variant in variants
        ]
        counts = f"{len(js[0])} / {len(js[1])}"
        if min(len(j) for j in js) < 2:
            lines.append(f"| {name} | {counts} | – | – | – | – | – |")
            continue
        shift = mean_shift(js[0], js[1])
        medians = " / ".join(f"{100 * float(np.median(j)):.2f}" for j in js)
        lines.append(
            f"| {name} | {counts} | {100 * shift.mean_a:.2f} cm | {100 * shift.mean_b:.2f} cm "
            f"| {100 * shift.change:+.0f} % | {medians} cm | {shift.p_greater:.3f} |"
        )
    lines += ["", "![mbp_live.png](mbp_live.png)", ""]
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "mbp_live.md").write_text("\n".join(lines))
    plot(rows, args.out / "mbp_live.png")
    log.info("wrote %s", args.out / "mbp_live.md")


if __name__ == "__main__":
    main()
