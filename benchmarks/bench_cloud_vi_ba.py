"""Cloud visual-inertial global BA (paper Eq. 20 with ``e_imu``): time vs keyframes, and joint
ATE with / without IMU factors on the same recordings.

Run: ``.venv/bin/python benchmarks/bench_cloud_vi_ba.py [--sizes 1000,5000,20000] [--landmarks 600]
[--ab RECORDING:DATASET ...]``; writes ``benchmarks/results/cloud_vi_ba.md``.

Part 1 (synthetic, :func:`sim.cloud.vi_circle_atlas`): one agent on a circle
in a room of landmarks, keyframes every 0.25 s with the exact IMU between them (constant gyro
and specific force of a circular flight, EuRoC noise densities in the factors), keyframe
positions, points and velocities scaled by 1.03 about the first keyframe plus 1 cm / 0.6°
pose noise; one batch VI full BA (Levenberg–Marquardt, the service's
``FullBAConfig`` with ``imu_factors`` on, at most ``--iterations`` iterations and 600 s) per
size, build and solve timed separately, and the map's scale after it.

Part 2 (``--ab``): :func:`lab.table3.replay` of each recording with ``schedule="recorded"``
(the live run's cloud, solve for solve) twice, IMU factors off and on, everything else the
service's defaults; joint ATE of the keyframe trajectories with SE(3) and Sim(3) alignment
and the Sim(3) scale error.
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
import os
import platform
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from common.calibration import ImuCalibration
from common.evaluation.alignment import umeyama
from services.cloud.config import FullBAConfig, GlobalOptimizationConfig
from services.cloud.optimization.full_ba import build_full_ba, solve_full_ba
from services.cloud.optimization.incremental_ba import forget, solve_full_ba_incremental
from sim.cloud import default_camera, map_scale, problem_prefix, vi_circle_atlas

log = logging.getLogger("bench_cloud_vi_ba")
RESULTS = Path(__file__).resolve().parent / "results" / "cloud_vi_ba.md"


def _one_imu(imu: ImuCalibration) -> Callable[[int], ImuCalibration]:
    return lambda _agent: imu


def synthetic_rows(sizes: list[int], n_landmarks: int, max_iterations: int) -> list[str]:
    cam = default_camera()
    gcfg = GlobalOptimizationConfig()
    cfg = dataclasses.replace(FullBAConfig(), imu_factors=True, max_iterations=max_iterations)
    cfg = dataclasses.replace(cfg, max_seconds=600.0)
    rows = []
    for n in sizes:
        t0 = time.perf_counter()
        atlas, store, truth = vi_circle_atlas(n, n_landmarks=n_landmarks, scale=1.03, seed=0)
        imu = truth.imu
        t_make = time.perf_counter() - t0
        t0 = time.perf_counter()
        problem = build_full_ba(atlas, 0, cam, cfg, gcfg, store, _one_imu(imu))
        t_build = time.perf_counter() - t0
        res = solve_full_ba(problem, cfg, gcfg)
        s0 = map_scale(problem.T_world_body, truth.T_world_body)
        s1 = map_scale(res.T_world_body, truth.T_world_body)
        n_imu = 0 if problem.imu is None else problem.imu.n_pairs
        rows.append(
            f"| {n} | {problem.point_keys.size} | {problem.n_observations} | {n_imu} | "
            f"{t_build:.2f} | {res.seconds:.1f} | {res.iterations} | "
            f"{res.seconds / max(res.iterations, 1):.2f} | {s0:.4f} | {s1:.4f} | "
            f"{res.final_rms_px:.2f} |"
        )
        log.info("(made in %.1f s) %s", t_make, rows[-1])
    return rows


def _position_rms_cm(T_est: np.ndarray, T_true: np.ndarray) -> float:
    """RMS keyframe position error (N, 4, 4) after a rigid (SE(3)) alignment, cm."""
    a, t = T_est[:, :3, 3], T_true[:, :3, 3]
    S = umeyama(a, t)
    return float(100 * np.sqrt(np.mean(np.sum((a @ S.R_ref_est.T + S.t_ref_est - t) ** 2, 1))))


def incremental_rows(
    sizes: list[int],
    n_landmarks: int,
    batch: int,
    solvers: list[tuple[int, int, bool]],
    full_check_max: int,
) -> list[str]:
    """The service's incremental solver (:func:`solve_full_ba_incremental`) fed each
    synthetic problem in time order (:func:`problem_prefix`), ``batch`` keyframes more per
    full BA, with each (``incremental_max_updates``, ``relinearize_budget``,
    ``partial_relinearization_check``) of ``solvers`` (those with the full check only up to
    ``full_check_max`` keyframes); then one batch solve of the whole problem for comparison."""
    cam = default_camera()
    gcfg = GlobalOptimizationConfig()
    base = dataclasses.replace(
        FullBAConfig(), imu_factors=True, incremental=True, incremental_min_keyframes=0
    )
    rows = []
    for n in sizes:
        atlas, store, truth = vi_circle_atlas(n, n_landmarks=n_landmarks, scale=1.03, seed=0)
        problem = build_full_ba(atlas, 0, cam, base, gcfg, store, _one_imu(truth.imu))
        ref = solve_full_ba(problem, dataclasses.replace(base, max_seconds=600.0), gcfg)
        for max_updates, budget, partial in solvers:
            if not partial and n > full_check_max:
                log.info("%d keyframes: the full relinearisation check skipped", n)
                continue
            cfg = dataclasses.replace(
                base,
                incremental_max_updates=max_updates,
                relinearize_budget=budget,
                partial_relinearization_check=partial,
            )
            session = f"bench-{n}-{max_updates}-{budget}-{partial}"
            times, resets, first = [], 0, float("nan")
            for m in range(min(100, n), n + 1, batch):
                res = solve_full_ba_incremental(problem_prefix(problem, m), cfg, gcfg, session, 0)
                if res.mode == "isam2":
                    times.append(res.seconds)
                else:
                    resets += 1
                    first = res.seconds
                if len(times) % 20 == 0:
                    log.info("%d keyframes: last full BA %.3f s (%s)", m, res.seconds, res.mode)
            forget(session)
            t = np.array(times)
            last = t[-max(1, len(t) // 10) :]
            rows.append(
                f"| {n} | {'partial' if partial else 'full'} | {max_updates} | {budget or 'none'} "
                f"| {len(t)} | {resets} ({first:.2f} s) "
                f"| {np.median(t):.3f} | {np.percentile(t, 90):.3f} | {last.mean():.3f} | "
                f"{t.max():.3f} | {t.sum():.1f} | "
                f"{map_scale(res.T_world_body, truth.T_world_body):.4f} / "
                f"{_position_rms_cm(res.T_world_body, truth.T_world_body):.2f} | "
                f"{map_scale(ref.T_world_body, truth.T_world_body):.4f} / "
                f"{_position_rms_cm(ref.T_world_body, truth.T_world_body):.2f} "
                f"({ref.seconds:.1f} s, {ref.iterations} it.) |"
            )
            log.info("%s", rows[-1])
    return rows


VARIANTS = {
    "off": ("off", False, False),
    "batch": ("on, batch", True, False),
    "isam2": ("on, iSAM2", True, True),
}


def ab_rows(pairs: list[tuple[Path, Path]], variants: list[str]) -> list[str]:
    """Each recording replayed (recorded schedule) with each variant: IMU factors off, on
    with the batch solve, on with the incremental (iSAM2) one."""
    import lab.table3 as table3
    from common.evaluation.alignment import AlignMode
    from common.evaluation.metrics import AteConfig, compute_joint_ate
    from common.evaluation.results import load_groundtruth
    from common.vocabulary import DEFAULT_VOCABULARY_PATH, Vocabulary
    from services.cloud.core_actions import SolveRequest, solve
    from services.cloud.optimization.full_ba import FullBAResult
    from services.cloud.runner import find_camera
    from services.cloud.service_config import CloudServiceConfig
    from services.cloud.store.recording import read_schedule

    vocab = Vocabulary.load(DEFAULT_VOCABULARY_PATH)
    rows = [
        "| recording | IMU factors, solver | keyframes | maps | loops | pose graphs | full BAs "
        "(rebuilt) | full BA s median / max | ATE per robot m (SE(3), joint alignment) | "
        "joint ATE m SE(3) | joint ATE m Sim(3) | scale error % | replay s |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for recording, data in pairs:
        camera = find_camera(None, data)
        for v in variants:
            label, imu, incremental = VARIANTS[v]
            base = CloudServiceConfig()
            full = dataclasses.replace(
                base.domain.full_ba,
                imu_factors=imu,
                incremental=incremental,
                incremental_min_keyframes=0,  # (iSAM2 at any size: the solvers compared)
            )
            cfg = dataclasses.replace(base, domain=dataclasses.replace(base.domain, full_ba=full))
            solves: list[FullBAResult] = []

            def timed(request: SolveRequest, solves: list[FullBAResult] = solves):
                out = solve(request)
                if isinstance(out, FullBAResult):
                    solves.append(out)
                return out

            with tempfile.TemporaryDirectory() as tmp:
                r = table3.replay(
                    read_schedule(recording, allow_truncated_tail=True),
                    camera,
                    vocab,
                    cfg,
                    Path(tmp),
                    f"imu {label}",
                    full_ba=True,
                    solve_fn=timed,
                    schedule="recorded",
                )
            names = sorted(r.trajectories)
            refs, _ = load_groundtruth(names, data)
            est = {n: t for n, t in r.trajectories.items() if n in refs and len(t) >= 3}
            ref = {n: refs[n] for n in est}
            se3 = compute_joint_ate(ref, est, AteConfig())
            sim3 = compute_joint_ate(ref, est, AteConfig(align=AlignMode.SIM3))
            per = ", ".join(f"{n} {a.stats.rmse:.4f}" for n, a in sorted(se3.under_joint.items()))
            secs = np.array([x.seconds for x in solves]) if solves else np.zeros(1)
            rebuilt = sum(x.mode == "isam2-reset" for x in solves)
            rows.append(
                f"| `{recording.name}` | {label} | {r.keyframes} | "
                f"{len(r.maps)} | {r.loops} | {r.optimizations} | {len(solves)} ({rebuilt}) | "
                f"{np.median(secs):.2f} / {secs.max():.2f} | {per} | "
                f"{se3.stats.rmse:.4f} | {sim3.stats.rmse:.4f} | "
                f"{100 * sim3.scale_error:+.2f} | {r.seconds:.0f} |"
            )
            log.info("%s", rows[-1])
    return rows


def _solver(spec: str) -> tuple[int, int, bool]:
    """``MAX_UPDATES:BUDGET[:full]`` -> (max updates, budget, partial check)."""
    parts = spec.split(":")
    if len(parts) not in (2, 3) or (len(parts) == 3 and parts[2] != "full"):
        raise SystemExit(f"--solvers: {spec!r} is not MAX_UPDATES:BUDGET[:full]")
    return int(parts[0]), int(parts[1]), len(parts) == 2


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sizes", default="1000,5000,20000", help="keyframe counts, comma-separated")
    ap.add_argument("--landmarks", type=int, default=600, help="landmarks in the room")
    ap.add_argument("--iterations", type=int, default=10, help="Levenberg–Marquardt iterations")
    ap.add_argument(
        "--ab", action="append", default=[], help="RECORDING:DATASET to replay off / on"
    )
    ap.add_argument(
        "--incremental", default="", help="keyframe counts for the iSAM2 timing, comma-separated"
    )
    ap.add_argument("--batch", type=int, default=25, help="keyframes per iSAM2 update")
    ap.add_argument(
        "--solvers",
        default="4:0,1:0,4:0:full,1:0:full",
        help="incremental solver settings to time, comma-separated "
        "MAX_UPDATES:RELINEARIZE_BUDGET[:full] (0: no budget; full: iSAM2's full "
        "relinearisation check instead of the partial one)",
    )
    ap.add_argument(
        "--full-check-max",
        type=int,
        default=5000,
        help="largest keyframe count the :full solver settings run at (their updates take "
        "seconds each beyond it)",
    )
    ap.add_argument(
        "--variants",
        default="off,batch",
        help="what each --ab recording is replayed with, comma-separated: off (no IMU "
        "factors), batch (IMU factors, batch solve), isam2 (IMU factors, iSAM2)",
    )
    ap.add_argument("--out", type=Path, default=RESULTS, help="markdown file to write")
    args = ap.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(message)s")
    sizes = [int(s) for s in args.sizes.split(",") if s]
    inc = [int(s) for s in args.incremental.split(",") if s]
    lines = [
        "# Cloud visual-inertial global BA (Eq. 20 with IMU factors)",
        "",
        f"Machine: {platform.processor() or platform.machine()}, Python "
        f"{platform.python_version()}, {len(os.sched_getaffinity(0))} core(s) allowed; "
        f"`benchmarks/bench_cloud_vi_ba.py --sizes "
        f"{args.sizes} --landmarks {args.landmarks} --iterations {args.iterations}"
        + (
            f" --incremental {args.incremental} --solvers {args.solvers} "
            f"--full-check-max {args.full_check_max}"
            if inc
            else ""
        )
        + "".join(f" --ab {a}" for a in args.ab)
        + "`.",
    ]
    if sizes:
        lines += [
            "",
            "## Time per batch VI global BA vs keyframes (synthetic)",
            "",
            "Batch Levenberg–Marquardt over every keyframe (pose, velocity, bias), point and IMU "
            "factor (what the service runs). Start: the map scaled by "
            "1.03 (scale column: least-squares scale of the keyframe positions to the truth about "
            "the first keyframe), plus 1 cm / 0.6° pose noise.",
            "",
            "| keyframes | points | observations | IMU factors | build s | solve s | iterations "
            "| s / iteration | scale before | scale after | RMS after px |",
            "|---|---|---|---|---|---|---|---|---|---|---|",
            *synthetic_rows(sizes, args.landmarks, args.iterations),
        ]
    if inc:
        lines += [
            "",
            "## Time per incremental (iSAM2) full BA vs keyframes (synthetic)",
            "",
            "The service's incremental solver (`services/cloud/optimization/incremental_ba.py`, "
            "`FullBAConfig.incremental`) fed the same problems in time order "
            "(`sim.cloud.problem_prefix`), `--batch` keyframes more per full "
            "BA from 100 keyframes: the first builds the graph from a batch solve (rebuilt "
            "column), every later one is an iSAM2 update of what changed and at most "
            "`incremental_max_updates` - 1 more relinearisation steps, each relinearising at "
            "most `relinearize_budget` variables (relinearisation check: iSAM2's partial "
            "check, from the Bayes tree's root down while a clique has a variable past the "
            "threshold, or the full one over every variable); its time is everything the "
            "optimiser process "
            "spends on it (the difference, the updates, reading the estimate out). Last "
            "columns: the map's scale and RMS keyframe position error (SE(3)-aligned, cm) "
            "after the last update, and after one batch solve of the whole problem from the "
            "start values.",
            "",
            "| keyframes | relinearisation check | updates per full BA | relinearisation "
            "budget | full BAs | rebuilt (s) | median s | p90 s | mean of the last 10 % s | "
            "max s | total s | scale / error cm after | batch: scale / error cm (time, "
            "iterations) |",
            "|---|---|---|---|---|---|---|---|---|---|---|---|---|",
            *incremental_rows(
                inc,
                args.landmarks,
                args.batch,
                [_solver(x) for x in args.solvers.split(",") if x],
                args.full_check_max,
            ),
        ]
    if args.ab:
        pairs = []
        for a in args.ab:
            rec, _, data = a.partition(":")
            pairs.append((Path(rec), Path(data)))
        lines += [
            "",
            "## Joint ATE with / without IMU factors (recorded schedule)",
            "",
            "`lab.table3.replay(..., schedule='recorded')` of each recording: the live run's "
            "cloud, with the service's defaults (full BA after every 100 keyframes' changes "
            "and at shutdown, MBP at shutdown) and `FullBAConfig.imu_factors` off / on.",
            "",
            *ab_rows(pairs, [v for v in args.variants.split(",") if v]),
        ]
    args.out.write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
