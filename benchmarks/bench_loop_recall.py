"""Loop-closure recall (issue 17, item 4): early candidates with ORB-SLAM3's covisibility check
against consecutive-keyframe consistency alone, side by side on the same recordings.

Run: ``.venv/bin/python benchmarks/bench_loop_recall.py --ab RECORDING:DATASET [...]
[--early 0,1] [--fuse 1,0] [--live LABEL:RUN_DIR:DATASET ...]``; writes
``benchmarks/results/loop_recall.md`` and ``loop_recall.png``.

**Replays.** Each recording (``recslam demo --no-mbp --record-uplink``) is replayed through the
cloud service's own core (:func:`lab.table3.replay`, modelled schedule, solves taking no time:
deterministic, whatever the machine's load) with the service's defaults (VI full BA; no MBP
at shutdown, so that the map at the end holds every keyframe for the linked recall, and MBP
only runs after the last detection), ``PlaceRecognitionConfig.early_candidates`` set to each
``--early`` value and ``MergeConfig.fuse_loop_points`` to each ``--fuse`` value.
Detections are scored against the dataset's ground truth by :func:`lab.loop_scoring.
score_loops` (TP within 0.3 m / 10 deg, revisit partner within 1 m / 30 deg; definitions in
``loop_detection.md``). Replays are open-loop (the recorded edge applied the live cloud's
corrections), so their ATE is faithful only for the configuration the recording was made with:
the ``recorded with`` column says which.

**Live.** ``--live`` rows summarise whole runs of ``recslam demo`` (their ``report.json``) and
check every loop / merge constraint the cloud ended with against the ground truth
(:func:`lab.seeds.constraint_check`): the accuracy A/B that is not open-loop.
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
import platform
import sys
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt

from common.evaluation.results import load_groundtruth
from common.vocabulary import DEFAULT_VOCABULARY_PATH, Vocabulary
from lab.links import git_commit
from lab.loop_scoring import GroundTruthPoses, LoopCriterion, score_loops
from lab.seeds import constraint_check, read_report
from lab.table3 import joint_ate, replay_recording, service_config
from services.cloud.runner import find_camera

log = logging.getLogger("bench_loop_recall")
RESULTS = Path(__file__).resolve().parent / "results"


def replay_row(
    recording: Path, dataset: Path, early: int, vocab: Vocabulary, fuse: bool = True
) -> dict[str, Any]:
    """One replay of ``recording`` with ``early_candidates = early`` and
    ``MergeConfig.fuse_loop_points = fuse``, scored."""
    camera = find_camera(None, dataset)
    cfg = service_config(mbp=False)  # the map at the end with every keyframe (linked recall)
    pr = dataclasses.replace(cfg.domain.place_recognition, early_candidates=early)
    merge = dataclasses.replace(cfg.domain.merge, fuse_loop_points=fuse)
    domain = dataclasses.replace(cfg.domain, place_recognition=pr, merge=merge)
    cfg = dataclasses.replace(cfg, domain=domain)
    label = f"early {early}, fuse {int(fuse)}"
    r = replay_recording(recording, camera, vocab, cfg, label, full_ba=True, covisibility=True)
    names = sorted(r.trajectories)
    refs, _ = load_groundtruth(names, dataset)
    crit = LoopCriterion()
    gt = GroundTruthPoses(refs, camera.T_body_cam, crit.max_gt_gap_s)
    s = score_loops(
        r.detections,
        r.queries,
        r.info,
        gt,
        final_covisible=r.covisible,
    )
    ate = joint_ate(refs, r.trajectories)
    stages = r.stages
    per_kf = {
        k: 1e3 * v["seconds"] / max(1, r.keyframes_received)
        for k, v in stages.items()
        if k in ("stage.place_recognition", "stage.verification")
    }
    return {
        "recording": recording.name,
        "early": early,
        "fuse": int(fuse),
        "accepted": len(s.accepted),
        "tp": s.true_positives,
        "fp": s.false_positives,
        "precision": s.precision,
        "with_partner": s.queries_with_partner,
        "found": s.found,
        "recall": s.recall,
        "recall_unconnected": s.recall_unconnected,
        "recall_linked": s.recall_linked,
        "rejected": len(s.rejected),
        "rejected_reasons": dict(s.rejected_reasons),
        "optimizations": r.optimizations,
        "maps": len(r.maps),
        "joint_cm": None if ate is None else 100 * ate.stats.rmse,
        "pr_ms": per_kf.get("stage.place_recognition"),
        "verify_ms": per_kf.get("stage.verification"),
    }


def _f(v: float | None, fmt: str) -> str:
    return "–" if v is None else format(v, fmt)


def write(rows: list[dict], live: list[dict], out: Path, argv: str) -> None:
    lines = [
        "# Loop-closure recall: early candidates with the covisibility check",
        "",
        f"Command: `benchmarks/bench_loop_recall.py {argv}`; commit {git_commit()}; "
        f"{platform.node()}. Method and definitions: the script's docstring and "
        "`loop_detection.md`. `early 0`: a candidate must be consistent over 3 consecutive "
        "keyframes of its robot (ORB-SLAM2's rule, the cloud before this change); `early 1`: "
        "the best candidate that is not yet consistent is verified at once and accepted when "
        "2 of the query's 5 best covisible keyframes see the candidate's points where the "
        "verified pose puts them (ORB-SLAM3), the default. `fuse 1`: a loop within one map "
        "fuses its verified point pairs (`MergeConfig.fuse_loop_points`, the default since "
        "session 22); the revisit's later keyframes then share map points with the first lap, "
        "are no longer loop candidates and leave the `unconnected` recall's denominator.",
        "",
        "## Replays (same recording, each setting)",
        "",
        "| recording | early | fuse | accepted | TP | FP | precision | with revisit partner "
        "| found | recall | recall, unconnected | recall, linked | rejected "
        "| pose graphs + full BAs | maps | joint ATE cm "
        "| place recognition ms/KF | verification ms/KF |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| `{r['recording']}` | {r['early']} | {r.get('fuse', 0)} | {r['accepted']} | "
            f"{r['tp']} | {r['fp']} | "
            f"{_f(r['precision'], '.3f')} | {r['with_partner']} | {r['found']} | "
            f"{_f(r['recall'], '.3f')} | {_f(r['recall_unconnected'], '.3f')} | "
            f"{_f(r.get('recall_linked'), '.3f')} | "
            f"{r['rejected']} | {r['optimizations']} | {r['maps']} | "
            f"{_f(r['joint_cm'], '.2f')} | {_f(r['pr_ms'], '.1f')} | {_f(r['verify_ms'], '.1f')} |"
        )
    lines.append("")
    for r in rows:
        if r["rejected_reasons"]:
            why = ", ".join(f"{k} {v}" for k, v in sorted(r["rejected_reasons"].items()))
            lines.append(
                f"- `{r['recording']}`, early {r['early']}, fuse {r.get('fuse', 0)}: "
                f"rejected by {why}"
            )
    if live:
        lines += [
            "",
            "## Live runs (`recslam demo --no-mbp --early-loop-candidates N`)",
            "",
            "| run | joint ATE cm | worst robot cm | maps | merges | loops "
            "| constraints wrong / checked | largest constraint error | frames lost | wall s |",
            "|---|---|---|---|---|---|---|---|---|---|",
        ]
        for r in live:
            err = (
                "–"
                if r.get("max_constraint_err_m") is None
                else f"{100 * r['max_constraint_err_m']:.1f} cm, {r['max_constraint_err_deg']:.1f}°"
            )
            lines.append(
                f"| {r['label']} | {_f(r['joint_m'] and 100 * r['joint_m'], '.2f')} | "
                f"{_f(r['worst_robot_m'] and 100 * r['worst_robot_m'], '.2f')} | {r['maps']} | "
                f"{r['merges']} | {r['loops']} | {r.get('wrong_constraints')} / "
                f"{r.get('constraints')} | {err} | {r['frames_lost']} | "
                f"{_f(r['wall_s'], '.0f')} |"
            )
    lines += ["", "![loop_recall.png](loop_recall.png)", ""]
    (out / "loop_recall.md").write_text("\n".join(lines))
    plot(rows, out / "loop_recall.png")


def plot(rows: list[dict], path: Path) -> None:
    recs = sorted({r["recording"] for r in rows})
    settings = sorted({(r["early"], r.get("fuse", 0)) for r in rows})
    fig, axes = plt.subplots(1, 4, figsize=(17, 3.8))
    width = 0.8 / max(1, len(settings))
    for j, (e, f) in enumerate(settings):
        by = {r["recording"]: r for r in rows if (r["early"], r.get("fuse", 0)) == (e, f)}
        xs = [i + j * width for i in range(len(recs))]
        label = f"early {e}, fuse {f}"
        axes[0].bar(xs, [by[k]["recall"] or 0 for k in recs], width, label=label)
        axes[1].bar(xs, [by[k]["recall_unconnected"] or 0 for k in recs], width, label=label)
        axes[2].bar(xs, [by[k]["recall_linked"] or 0 for k in recs], width, label=label)
        axes[3].bar(xs, [by[k]["joint_cm"] or 0 for k in recs], width, label=label)
    titles = ("recall", "recall, unconnected", "recall, linked", "joint ATE, cm (replay)")
    for ax, title in zip(axes, titles, strict=True):
        ax.set_xticks([i + 0.4 - width / 2 for i in range(len(recs))], recs, fontsize=7)
        ax.set_title(title)
        ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--ab", action="append", default=[], metavar="RECORDING:DATASET")
    ap.add_argument("--early", default="0,1", help="early_candidates values (default 0,1)")
    ap.add_argument("--fuse", default="1", help="fuse_loop_points values, 1 and/or 0 (default 1)")
    ap.add_argument("--live", action="append", default=[], metavar="LABEL:RUN_DIR:DATASET")
    ap.add_argument("--out", type=Path, default=RESULTS)
    args = ap.parse_args()
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    vocab = Vocabulary.load(DEFAULT_VOCABULARY_PATH)
    rows = []
    for spec in args.ab:
        rec, data = spec.split(":")
        for e in (int(v) for v in args.early.split(",")):
            for f in (v == "1" for v in args.fuse.split(",")):
                print(f"replaying {rec} with early {e}, fuse {int(f)}", flush=True)
                rows.append(replay_row(Path(rec), Path(data), e, vocab, f))
                if len({Path(a.split(":")[0]).name for a in args.ab}) < len(args.ab):
                    rows[-1]["recording"] = f"{Path(rec).parent.name}/{Path(rec).name}"
                r = rows[-1]
                print(
                    f"  recall {r['recall']:.3f} (unconnected {r['recall_unconnected']}, "
                    f"linked {r['recall_linked']}), "
                    f"precision {r['precision']}, joint {r['joint_cm']}",
                    flush=True,
                )
    live = []
    for spec in args.live:
        label, run_dir, data = spec.split(":")
        rep = read_report(Path(run_dir))
        rep.update(constraint_check(Path(run_dir), Path(data)))
        live.append({"label": label, **rep})
    args.out.mkdir(parents=True, exist_ok=True)
    write(rows, live, args.out, " ".join(sys.argv[1:]))
    print(f"wrote {args.out / 'loop_recall.md'}")


if __name__ == "__main__":
    main()
