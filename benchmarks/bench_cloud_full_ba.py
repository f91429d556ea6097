"""Cloud full bundle adjustment (paper Eq. 20, full stage): time vs map size, and joint ATE of
a recorded run replayed with and without it.

Run: ``.venv/bin/python benchmarks/bench_cloud_full_ba.py [--quick]
[--recording FILE --data DATASET]``; writes ``benchmarks/results/cloud_full_ba.md``.

Part 1 (synthetic, :mod:`sim.cloud`): one agent on a circle in a room of
landmarks; keyframe poses (1 cm / 0.6° per axis) and points (3 cm) perturbed; problem build
(atlas -> plain arrays, on the service's worker) and solve (in the optimiser process) timed
separately, one run each, with the service's default options.

Part 2 (``--recording``): :func:`lab.table3.replay` of an uplink recording with the
service's default configuration (MBP on), pose graph only vs pose graph + full BA on the
server's schedule; joint ATE (SE(3), the cloud report's) of the keyframe trajectories, and
the size and solve time of every full BA the replay ran.
"""

from __future__ import annotations

import argparse
import logging
import platform
import tempfile
import time
from pathlib import Path

import numpy as np

from common.geometry import so3_exp
from services.cloud.atlas.atlas import Atlas
from services.cloud.config import FullBAConfig, GlobalOptimizationConfig
from services.cloud.optimization.full_ba import FullBAProblem, build_full_ba, solve_full_ba
from sim.cloud import circle_poses, default_camera, make_session, make_world

log = logging.getLogger("bench_cloud_full_ba")
RESULTS = Path(__file__).resolve().parent / "results" / "cloud_full_ba.md"


def perturbed_atlas(n_keyframes: int, n_landmarks: int, seed: int = 0) -> Atlas:
    """A synthetic single-agent atlas with perturbed keyframe poses and points."""
    cam = default_camera()
    world = make_world(seed, n_points=n_landmarks)
    poses = circle_poses(n_keyframes, turns=max(1.0, n_keyframes / 60))
    kfs, mps = make_session(world, cam, 0, poses, np.eye(4), seed=seed + 1)
    atlas = Atlas()
    for k in kfs:
        atlas.add_keyframe(k)
    for m in mps:
        atlas.add_map_point(m)
    rng = np.random.default_rng(seed + 2)
    keys = atlas.keyframe_keys()
    poses_new = {}
    for k in keys[1:]:
        D = np.eye(4)
        D[:3, :3] = so3_exp(rng.normal(0.0, 0.01, 3))
        D[:3, 3] = rng.normal(0.0, 0.01, 3)
        poses_new[k] = atlas.T_map_body(k) @ D
    atlas.set_keyframe_poses(poses_new)
    pk = np.array(atlas.map_point_keys(), np.int64)
    P = atlas.map_point_positions(pk) + rng.normal(0.0, 0.03, (pk.size, 3))
    atlas.set_map_point_positions(dict(zip(pk.tolist(), P, strict=True)))
    return atlas


def synthetic_rows(sizes: list[tuple[int, int]]) -> list[str]:
    cam = default_camera()
    cfg, gcfg = FullBAConfig(), GlobalOptimizationConfig()
    rows = []
    for n_kf, n_lm in sizes:
        atlas = perturbed_atlas(n_kf, n_lm)
        t0 = time.perf_counter()
        problem = build_full_ba(atlas, 0, cam, cfg, gcfg)
        t_build = time.perf_counter() - t0
        res = solve_full_ba(problem, cfg, gcfg)
        rows.append(
            f"| {n_kf} | {problem.point_keys.size} | {problem.n_observations} | "
            f"{t_build:.3f} | {res.seconds:.2f} | {res.iterations} | "
            f"{res.seconds / max(res.iterations, 1):.2f} | {res.initial_rms_px:.2f} | "
            f"{res.final_rms_px:.2f} |"
        )
        log.info("%s", rows[-1])
    return rows


def replay_rows(recording: Path, data: Path) -> list[str]:
    """Replay with and without full BA (MBP on in both); table rows."""
    import lab.table3 as table3
    from common.evaluation.results import load_groundtruth
    from common.vocabulary import DEFAULT_VOCABULARY_PATH, Vocabulary
    from services.cloud.core_actions import SolveRequest, SolveResult, solve
    from services.cloud.optimization.full_ba import FullBAResult
    from services.cloud.runner import find_camera
    from services.cloud.store.recording import read_recording

    camera = find_camera(None, data)
    vocab = Vocabulary.load(DEFAULT_VOCABULARY_PATH)
    solves: list[tuple[FullBAProblem, float, int, float, float]] = []

    def timed(request: SolveRequest) -> SolveResult:
        res = solve(request)
        if isinstance(res, FullBAResult) and isinstance(request.problem, FullBAProblem):
            solves.append(
                (request.problem, res.seconds, res.iterations, res.initial_rms_px, res.final_rms_px)
            )
        return res

    results = {}
    with tempfile.TemporaryDirectory() as tmp:
        for full in (False, True):
            label = "pose graph + full BA" if full else "pose graph only"
            records = read_recording(recording, allow_truncated_tail=True)
            results[full] = table3.replay(
                records,
                camera,
                vocab,
                table3.service_config(True),
                Path(tmp) / str(full),
                label,
                full_ba=full,
                solve_fn=timed,
            )
            log.info("%s: %.0f s", label, results[full].seconds)
        names = sorted(set(results[False].trajectories) | set(results[True].trajectories))
        refs, _ = load_groundtruth(names, data)
        sweep = sigma_sweep(Path(tmp) / "False", camera, vocab, refs)
    rows = [
        "| | keyframes | maps | loops | full BA passes | ATE per robot m | "
        "ATE joint m | replay s |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for full in (False, True):
        r = results[full]
        ate = table3.joint_ate(refs, r.trajectories)
        under = sorted(ate.under_joint.items()) if ate else []
        per = ", ".join(f"{n} {a.stats.rmse:.3f}" for n, a in under)
        joint = f"{ate.stats.rmse:.4f}" if ate else "n/a"
        rows.append(
            f"| {r.label} | {r.keyframes} | {len(r.maps)} | {r.loops} | "
            f"{len(solves) if full else 0} | {per} | {joint} | {r.seconds:.0f} |"
        )
    rows += [
        "",
        "Every full BA of the replay (in order):",
        "",
        "| keyframes | points | observations | solve s | iterations | RMS before px | "
        "RMS after px |",
        "|---|---|---|---|---|---|---|",
    ]
    for p, s, it, r0, r1 in solves:
        rows.append(
            f"| {p.keys.size} | {p.point_keys.size} | {p.n_observations} | {s:.1f} | "
            f"{it} | {r0:.2f} | {r1:.2f} |"
        )
    rows += [
        "",
        "One full BA of the final map of the pose-graph-only replay, by the sigmas of the "
        "relative-pose terms (their measurement is the current estimate, drift included):",
        "",
        "| odometry sigmas rad / m | iterations | solve s | RMS after px | ATE joint m "
        "(SE(3)) | ATE joint m (Sim(3)) |",
        "|---|---|---|---|---|---|",
        *sweep,
    ]
    return rows


def sigma_sweep(state_dir: Path, camera: object, vocab: object, refs: dict) -> list[str]:
    """Full BA of the final map of a replay's state directory with several odometry sigmas."""
    import dataclasses

    import lab.table3 as table3
    from common.evaluation.alignment import AlignMode
    from common.evaluation.metrics import AteConfig, compute_joint_ate
    from services.cloud.optimization.full_ba import apply_full_ba

    app = table3.open_app(state_dir, camera, vocab, table3.service_config(True))  # type: ignore[arg-type]
    try:
        atlas = app.atlas
        m = max(atlas.maps(), key=atlas.n_keyframes)
        keys = atlas.keyframe_keys(map_id=m)
        T0 = {k: atlas.T_map_body(k) for k in keys}
        pk = np.array(atlas.map_point_keys(), np.int64)
        P0 = atlas.map_point_positions(pk)

        def ate(mode: AlignMode) -> float:
            trajs, _ = app.trajectories()
            est = {n: t for n, t in trajs.items() if n in refs}
            cfg = dataclasses.replace(AteConfig(), align=mode)
            return compute_joint_ate({n: refs[n] for n in est}, est, cfg).stats.rmse

        rows = [
            f"| (before: pose graph only) | | | | {ate(AlignMode.SE3):.4f} | "
            f"{ate(AlignMode.SIM3):.4f} |"
        ]
        for rot, trans in ((0.01, 0.02), (0.05, 0.1), (0.1, 0.2), (0.3, 0.6), (1.0, 2.0)):
            atlas.set_keyframe_poses(T0)
            atlas.set_map_point_positions(dict(zip(pk.tolist(), P0, strict=True)))
            cfg = dataclasses.replace(
                FullBAConfig(), odometry_sigma_rot_rad=rot, odometry_sigma_trans_m=trans
            )
            gcfg = GlobalOptimizationConfig()
            res = solve_full_ba(build_full_ba(atlas, m, camera, cfg, gcfg), cfg, gcfg)  # type: ignore[arg-type]
            apply_full_ba(atlas, res)
            rows.append(
                f"| {rot} / {trans} | {res.iterations} | {res.seconds:.1f} | "
                f"{res.final_rms_px:.2f} | {ate(AlignMode.SE3):.4f} | "
                f"{ate(AlignMode.SIM3):.4f} |"
            )
        return rows
    finally:
        app.close()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="small sizes only")
    ap.add_argument("--recording", type=Path, default=None, help="uplink recording to replay")
    ap.add_argument("--data", type=Path, default=None, help="dataset folder (ground truth)")
    args = ap.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(message)s")
    sizes = (
        [(20, 1500), (50, 3000)]
        if args.quick
        else [(20, 1500), (50, 3000), (100, 6000), (200, 12000)]
    )
    cfg = FullBAConfig()
    lines = [
        "# Cloud full bundle adjustment (Eq. 20, full stage)",
        "",
        f"Machine: {platform.processor() or platform.machine()}, Python "
        f"{platform.python_version()}; `benchmarks/bench_cloud_full_ba.py`"
        f"{' --quick' if args.quick else ''}. Options: Huber {cfg.kernel_scale} on the "
        f"reprojection terms, at most {cfg.max_iterations} Levenberg–Marquardt iterations, "
        f"relative tolerance {cfg.relative_error_tol:g}.",
        "",
        "## Time vs map size (synthetic, perturbed poses and points)",
        "",
        "Build: atlas -> plain problem (service worker thread). Solve: gtsam graph construction "
        "+ Levenberg–Marquardt (optimiser process). RMS: reprojection error of the used "
        "observations (pixel noise of the simulation: 0.5 px, distorted).",
        "",
        "| keyframes | points | observations | build s | solve s | iterations | s / iteration "
        "| RMS before px | RMS after px |",
        "|---|---|---|---|---|---|---|---|---|",
        *synthetic_rows(sizes),
    ]
    if args.recording is not None:
        if args.data is None:
            ap.error("--recording needs --data")
        lines += [
            "",
            "## Replay of a recorded run: joint ATE with and without full BA",
            "",
            f"Recording `{args.recording}`, ground truth `{args.data}`; "
            "`lab.table3.replay` with the service's defaults (MBP on), pose graph only vs "
            "pose graph + full BA on the server's schedule (every "
            "`full_ba.every_keyframes`, on quiet, and at the end).",
            "",
            *replay_rows(args.recording, args.data),
        ]
    RESULTS.write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
