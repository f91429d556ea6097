"""Cloud visual-inertial global BA (paper Eq. 20 with ``e_imu``): time vs keyframes, and joint
ATE with / without IMU factors on the same recordings.

Run: ``.venv/bin/python benchmarks/bench_cloud_vi_ba.py [--sizes 1000,5000,20000] [--landmarks 600]
[--ab RECORDING:DATASET ...]``; writes ``benchmarks/results/cloud_vi_ba.md``.

Part 1 (synthetic, :func:`services.cloud.simulation.vi_circle_atlas`): one agent on a circle
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
import platform
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import gtsam
import numpy as np

from common.calibration import ImuCalibration
from services.cloud.config import FullBAConfig, GlobalOptimizationConfig
from services.cloud.full_ba import FullBAProblem, build_full_ba, solve_full_ba
from services.cloud.inertial import initial_velocities, preintegrated
from services.cloud.simulation import default_camera, map_scale, vi_circle_atlas

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


def incremental_times(
    problem: FullBAProblem, cfg: FullBAConfig, batch: int
) -> tuple[list[float], np.ndarray]:
    """Feed ``problem`` to iSAM2 in time order, ``batch`` keyframes per update (the service
    optimises every 25 new keyframes): each update adds the new keyframes' pose, velocity and
    bias, their IMU factors, and their reprojection factors (a point enters with its second
    observation). Returns the wall time of every update, s, and the final poses (N, 4, 4)."""
    X, V, B, L = (
        gtsam.symbol_shorthand.X,
        gtsam.symbol_shorthand.V,
        gtsam.symbol_shorthand.B,
        gtsam.symbol_shorthand.L,
    )
    assert problem.imu is not None
    terms = problem.imu
    pims = [preintegrated(terms, k, cfg) for k in range(terms.n_pairs)]
    vel = initial_velocities(terms, pims, problem.T_world_body, cfg.gravity_mps2)
    pair_of_j = {int(j): k for k, j in enumerate(terms.pair_j.tolist())}
    params = gtsam.ISAM2Params()
    params.setRelinearizeThreshold(0.01)
    isam = gtsam.ISAM2(params)
    K = gtsam.Cal3_S2(1.0, 1.0, 0.0, 0.0, 0.0)
    huber = gtsam.noiseModel.mEstimator.Huber.Create(cfg.kernel_scale)
    obs_of_kf: dict[int, list[int]] = {}
    for o, kf in enumerate(problem.obs_kf.tolist()):
        obs_of_kf.setdefault(kf, []).append(o)
    pending: dict[int, list[int]] = {}
    inserted: set[int] = set()
    body_P_cam = gtsam.Pose3(problem.T_body_cam[0])
    bias_prior = gtsam.noiseModel.Diagonal.Sigmas(
        np.array([cfg.bias_prior_accel] * 3 + [cfg.bias_prior_gyro] * 3)
    )
    times = []
    n = problem.keys.shape[0]
    for start in range(0, n, batch):
        graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        for i in range(start, min(n, start + batch)):
            values.insert(X(i), gtsam.Pose3(problem.T_world_body[i]))
            values.insert(V(i), np.asarray(vel[i]))
            bias = gtsam.imuBias.ConstantBias(terms.bias_accel[i], terms.bias_gyro[i])
            values.insert(B(i), bias)
            if i == 0:
                graph.add(
                    gtsam.PriorFactorPose3(
                        X(0),
                        gtsam.Pose3(problem.T_world_body[0]),
                        gtsam.noiseModel.Isotropic.Sigma(6, 1e-6),
                    )
                )
                graph.add(gtsam.PriorFactorConstantBias(B(0), bias, bias_prior))
            else:
                k = pair_of_j[i]
                a = int(terms.pair_i[k])
                graph.add(gtsam.CombinedImuFactor(X(a), V(a), X(i), V(i), B(a), B(i), pims[k]))
            for o in obs_of_kf.get(i, []):
                pt = int(problem.obs_point[o])
                noise = gtsam.noiseModel.Robust.Create(
                    huber, gtsam.noiseModel.Isotropic.Sigma(2, float(problem.obs_sigma[o]))
                )
                f = gtsam.GenericProjectionFactorCal3_S2(
                    problem.obs_xy[o], noise, X(i), L(pt), K, body_P_cam
                )
                if pt in inserted:
                    graph.add(f)
                    continue
                pending.setdefault(pt, []).append(0)
                pending[pt][-1] = o
                if len(pending[pt]) >= 2:
                    for o2 in pending.pop(pt):
                        kf2 = int(problem.obs_kf[o2])
                        n2 = gtsam.noiseModel.Robust.Create(
                            huber,
                            gtsam.noiseModel.Isotropic.Sigma(2, float(problem.obs_sigma[o2])),
                        )
                        graph.add(
                            gtsam.GenericProjectionFactorCal3_S2(
                                problem.obs_xy[o2], n2, X(kf2), L(pt), K, body_P_cam
                            )
                        )
                    values.insert(L(pt), np.asarray(problem.p_world[pt], np.float64))
                    inserted.add(pt)
        t0 = time.perf_counter()
        isam.update(graph, values)
        times.append(time.perf_counter() - t0)
    est = isam.calculateEstimate()
    return times, np.array([est.atPose3(X(i)).matrix() for i in range(n)])


def incremental_rows(sizes: list[int], n_landmarks: int, batch: int) -> list[str]:
    cam = default_camera()
    gcfg = GlobalOptimizationConfig()
    cfg = dataclasses.replace(FullBAConfig(), imu_factors=True)
    rows = []
    for n in sizes:
        atlas, store, truth = vi_circle_atlas(n, n_landmarks=n_landmarks, scale=1.03, seed=0)
        imu = truth.imu
        problem = build_full_ba(atlas, 0, cam, cfg, gcfg, store, _one_imu(imu))
        times, T_out = incremental_times(problem, cfg, batch)
        t = np.array(times)
        last = t[-max(1, len(t) // 10) :]
        rows.append(
            f"| {n} | {batch} | {len(t)} | {np.median(t):.3f} | {last.mean():.3f} | "
            f"{t.max():.3f} | {t.sum():.1f} | {map_scale(T_out, truth.T_world_body):.4f} |"
        )
        log.info("%s", rows[-1])
    return rows


def ab_rows(pairs: list[tuple[Path, Path]]) -> list[str]:
    """Each recording replayed (recorded schedule) with IMU factors off and on."""
    import lab.table3 as table3
    from common.evaluation.alignment import AlignMode
    from common.evaluation.metrics import AteConfig, compute_joint_ate
    from common.evaluation.results import load_groundtruth
    from common.vocabulary import DEFAULT_VOCABULARY_PATH, Vocabulary
    from services.cloud.config import CloudServiceConfig
    from services.cloud.recording import read_schedule
    from services.cloud.runner import find_camera

    vocab = Vocabulary.load(DEFAULT_VOCABULARY_PATH)
    rows = [
        "| recording | IMU factors | keyframes | maps | loops | pose graphs | ATE per robot m "
        "(SE(3), joint alignment) | joint ATE m SE(3) | joint ATE m Sim(3) | scale error % "
        "| replay s |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for recording, data in pairs:
        camera = find_camera(None, data)
        for imu in (False, True):
            base = CloudServiceConfig()
            full = dataclasses.replace(base.domain.full_ba, imu_factors=imu)
            cfg = dataclasses.replace(base, domain=dataclasses.replace(base.domain, full_ba=full))
            with tempfile.TemporaryDirectory() as tmp:
                r = table3.replay(
                    read_schedule(recording, allow_truncated_tail=True),
                    camera,
                    vocab,
                    cfg,
                    Path(tmp),
                    f"imu {'on' if imu else 'off'}",
                    full_ba=True,
                    schedule="recorded",
                )
            names = sorted(r.trajectories)
            refs, _ = load_groundtruth(names, data)
            est = {n: t for n, t in r.trajectories.items() if n in refs and len(t) >= 3}
            ref = {n: refs[n] for n in est}
            se3 = compute_joint_ate(ref, est, AteConfig())
            sim3 = compute_joint_ate(ref, est, AteConfig(align=AlignMode.SIM3))
            per = ", ".join(f"{n} {a.stats.rmse:.4f}" for n, a in sorted(se3.under_joint.items()))
            rows.append(
                f"| `{recording.name}` | {'on' if imu else 'off'} | {r.keyframes} | "
                f"{len(r.maps)} | {r.loops} | {r.optimizations} | {per} | "
                f"{se3.stats.rmse:.4f} | {sim3.stats.rmse:.4f} | "
                f"{100 * sim3.scale_error:+.2f} | {r.seconds:.0f} |"
            )
            log.info("%s", rows[-1])
    return rows


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
    ap.add_argument("--out", type=Path, default=RESULTS, help="markdown file to write")
    args = ap.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(message)s")
    sizes = [int(s) for s in args.sizes.split(",") if s]
    lines = [
        "# Cloud visual-inertial global BA (Eq. 20 with IMU factors)",
        "",
        f"Machine: {platform.processor() or platform.machine()}, Python "
        f"{platform.python_version()}, one core; `benchmarks/bench_cloud_vi_ba.py --sizes "
        f"{args.sizes} --landmarks {args.landmarks} --iterations {args.iterations}"
        f"{' --incremental ' + args.incremental if args.incremental else ''}"
        + "".join(f" --ab {a}" for a in args.ab)
        + "`.",
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
    inc = [int(s) for s in args.incremental.split(",") if s]
    if inc:
        lines += [
            "",
            "## Time per incremental (iSAM2) update vs keyframes (synthetic, benchmark only)",
            "",
            "The same problems fed to gtsam's iSAM2 in time order, `--batch` keyframes per "
            "update (pose, velocity, bias, IMU and reprojection factors of the new keyframes; "
            "relinearize threshold 0.01). This measures what an incremental VI-GBA would cost; "
            "the service itself runs the batch solve above.",
            "",
            "| keyframes | keyframes per update | updates | median update s | mean of the "
            "last 10 % s | max s | total s | scale after |",
            "|---|---|---|---|---|---|---|---|",
            *incremental_rows(inc, args.landmarks, args.batch),
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
            *ab_rows(pairs),
        ]
    args.out.write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
