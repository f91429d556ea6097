"""``recslam eval RESULT_DIR``: ATE (per agent and joint), RPE, tables and plots of a run.

Result-folder convention (services write it at the end of a run)::

    RESULT_DIR/
      trajectories/<agent>.tum   estimated body (IMU) poses T_map_body, TUM format
                                 ("timestamp tx ty tz qx qy qz qw", seconds with 9 decimals),
                                 ALL agents in ONE common map frame (the cloud's merged map)
      groundtruth/<agent>.tum    optional ground truth, used when --groundtruth is omitted
      eval/                      default --out: ate.json, ate.md, trajectories_joint.png,
                                 trajectories_individual.png, ate_over_time.png

``<agent>`` equals the folder name of the agent's sequence in the dataset, so that
``--groundtruth DATASET`` finds ``DATASET/<agent>/mav0/state_groundtruth_estimate0/data.csv``
(EuRoC layout) or ``DATASET/<agent>.tum``. A single sequence folder, ``data.csv`` or ``.tum``
file is accepted when the result has one agent. Details: ``common.evaluation.results``.

``ate.json``: ``{align, n_align, max_diff_ns, offset_ns, sources: {agent: gt file},
joint: {agents, stats_m, rot_stats_deg, transform: {R_ref_est, t_ref_est, scale},
scale_error}, agents: {agent: {n_est, n_ref, n_matched, individual: {stats_m, rot_stats_deg,
transform, scale_error}, under_joint: {stats_m, rot_stats_deg}, rpe: {delta, unit, pairs,
trans_stats_m, rot_stats_deg} | null}}}``; every ``stats`` holds rmse, mean, median, std, min,
max, sse, count. ``joint`` aligns all agents with ONE transform (a map-merge error shows up);
``individual`` aligns each agent alone.
"""

from __future__ import annotations

import argparse
from pathlib import Path


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "eval",
        help="trajectory accuracy (ATE per agent and joint, RPE) of a result folder",
        description=(
            "Evaluate RESULT_DIR/trajectories/<agent>.tum against ground truth: ATE after "
            "alignment per agent and joint (one transform for all agents), RPE, ate.json, "
            "ate.md and PNG plots."
        ),
    )
    p.add_argument("result_dir", type=Path, metavar="RESULT_DIR", help="result folder of a run")
    p.add_argument(
        "--groundtruth",
        "-g",
        type=Path,
        default=None,
        metavar="PATH_OR_DATASET_DIR",
        help="dataset folder (<agent>/mav0/... or <agent>.tum), sequence folder, data.csv or "
        ".tum (default: RESULT_DIR/groundtruth/)",
    )
    p.add_argument(
        "--align",
        choices=("se3", "sim3", "scale", "origin", "none"),
        default="se3",
        help="alignment before ATE (default se3; sim3 also reports the scale error)",
    )
    p.add_argument(
        "--n-align",
        type=int,
        default=None,
        metavar="N",
        help="align with only the first N associated poses (of each agent)",
    )
    p.add_argument(
        "--max-diff-ms",
        type=float,
        default=10.0,
        help="max timestamp difference for association [ms] (default 10)",
    )
    p.add_argument(
        "--offset-ms",
        type=float,
        default=0.0,
        help="time offset added to the estimate's stamps [ms] (default 0)",
    )
    p.add_argument(
        "--rpe-delta", type=float, default=1.0, help="RPE step (default 1.0, see --rpe-unit)"
    )
    p.add_argument(
        "--rpe-unit", choices=("m", "frames"), default="m", help="RPE step unit (default m)"
    )
    p.add_argument("--no-plots", action="store_true", help="skip the PNG plots")
    p.add_argument(
        "--out", type=Path, default=None, metavar="DIR", help="output folder (RESULT_DIR/eval)"
    )
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from common.evaluation.alignment import AlignMode
    from common.evaluation.association import AssociationConfig
    from common.evaluation.errors import EvaluationError
    from common.evaluation.metrics import AteConfig, DeltaUnit, RpeConfig
    from common.evaluation.report import EvalConfig, evaluate_run, markdown_table

    if args.n_align is not None and args.n_align < 1:
        raise EvaluationError(f"--n-align must be >= 1, got {args.n_align}")
    if args.max_diff_ms < 0:
        raise EvaluationError(f"--max-diff-ms must be >= 0, got {args.max_diff_ms}")
    assoc = AssociationConfig(
        max_diff_ns=round(args.max_diff_ms * 1e6), offset_ns=round(args.offset_ms * 1e6)
    )
    config = EvalConfig(
        ate=AteConfig(align=AlignMode(args.align), n_align=args.n_align, association=assoc),
        rpe=RpeConfig(delta=args.rpe_delta, unit=DeltaUnit(args.rpe_unit)),
        plots=not args.no_plots,
    )
    report = evaluate_run(args.result_dir, args.groundtruth, args.out, config)
    print(markdown_table(report.joint, report.rpe, report.maps), end="")
    print(f"wrote {', '.join(str(f) for f in report.files)}")
    return 0
