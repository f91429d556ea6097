"""Real IMUs: the edge's VIO on real flights' recorded IMU, beside the generator's IMU.

Two datasets rendered along the same recorded flights (same images): one with the IMU
recorded on each flight (``recslam dataset synth --trajectory GT,... --imu IMU,...``), one
with the generator's simulated IMU (the same command without ``--imu``). For every robot the
robot's front end and codecs run in process, the edge decodes (:mod:`lab.vio_replay`, cached
in ``--cache``) and the VIO runs: time from the flight's first motion to VI initialisation,
ATE [m] of the tracked frames (SE(3) and Sim(3)), the Sim(3) scale error, the gyro and accel
biases at the end against the ground truth's, and the IMU noise measured in flight against
the calibration. ``--real15`` / ``--sim15``: the same flights rendered with an unsynchronised
IMU (``--time-offset-ms 15``), replayed with the VIO's time-offset estimation on and off (each
frame's IMU batch reaches ``t + offset`` once the VIO has one, as the robot batches after the
edge told it). ``--live NAME=report.json`` adds the joint ATE of whole robot/edge/cloud runs
(``recslam demo --data DIR --out OUT``: ``OUT/report.json``).

Run: ``.venv/bin/python benchmarks/bench_real_imu.py --real /tmp/rd/v2r_3x60 --sim
/tmp/rd/v2_sim_3x60 --real15 /tmp/rd/v2r15_3x60 --sim15 /tmp/rd/v2_sim15_3x60
--live real=/tmp/td/demo_v2r_3x60/report.json ...``; writes
``benchmarks/results/real_imu.md`` and ``real_imu.png``.
"""

from __future__ import annotations

import argparse
import json
import logging
import platform
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from common.data.euroc import EurocSequence
from common.evaluation import AlignMode, AteConfig, Trajectory, compute_ate
from lab.links import git_commit
from lab.vio_replay import decode_sequence, load_decoded, save_decoded, score
from services.edge.vio.manager import VioManager
from services.edge.vio.types import TrackingStatus, ViInitConfig, VioConfig

log = logging.getLogger("bench_real_imu")
RESULTS = Path(__file__).resolve().parent / "results"


@dataclass(frozen=True)
class Row:
    imu: str
    robot: str
    motion_s: float  # first motion after the sequence's start [s]
    init_after_motion_s: float  # first metric (VI-initialised) frame after the first motion [s]
    tracked: float  # share of frames tracked in a metric map
    maps: int
    ate_se3_m: float
    ate_sim3_m: float
    scale_error: float
    gyro_bias_err: float  # |estimated - ground truth| at the end [rad/s]
    accel_bias_err: float  # [m/s²]
    noise_ratio: tuple[float, float]  # measured / calibrated white noise (gyro, accel)
    true_offset_ms: float = 0.0  # the dataset's camera-IMU offset (t_imu = t_cam + offset)
    estimate: bool = True  # the VIO estimated the offset
    offset_ms: float = 0.0  # the offset the VIO used at the end
    offset_sigma_ms: float = float("nan")  # of its last estimate
    ate_from_m: float = float("nan")  # SE(3) ATE of the tracked frames from ATE_FROM_S on
    vi_runs: int = 0  # VI initialisations and refinements run


ATE_FROM_S = 8.0
"""Variants that initialise at different times are compared on the same frames: those from
this long after the flight's first motion (every variant has initialised by then)."""


def first_motion_s(seq: EurocSequence) -> float:
    """Seconds from the first frame to the ground truth's first speed above 0.1 m/s or rate
    above 0.1 rad/s (the flight's first motion)."""
    gt = seq.groundtruth
    assert gt is not None
    t = (gt.timestamps_ns - seq.frame_timestamps_ns[0]) * 1e-9
    speed = np.linalg.norm(np.gradient(gt.p_world_body, t, axis=0), axis=1)
    moving = np.flatnonzero((speed > 0.1) & (t >= 0))
    return float(t[moving[0]]) if len(moving) else float("nan")


def scene_of(dataset: Path) -> str:
    """ "scene seed N, W world" of a generated dataset (dataset.json)."""
    cfg = json.loads((dataset / "dataset.json").read_text()).get("config", {})
    seed = cfg.get("scene_seed", cfg.get("seed", 0))
    return f"scene seed {seed}, {cfg.get('world', 'vicon')} world"


def true_offset_ms(dataset: Path) -> float:
    """The camera-IMU offset a generated dataset was rendered with (dataset.json)."""
    meta = json.loads((dataset / "dataset.json").read_text())
    return float(meta.get("harder", {}).get("time_offset_ms", 0.0))


def run(
    dataset: Path,
    robot: str,
    seconds: float,
    cache: Path,
    imu: str,
    estimate: bool = True,
    options: VioConfig | None = None,
) -> Row:
    seq = EurocSequence(dataset / robot)
    file = cache / f"{dataset.name}_{robot}_{seconds:g}s.npz"
    if file.exists():
        frames = load_decoded(file)
    else:
        frames = decode_sequence(seq.root, seconds)
        save_decoded(file, frames)
    options = options or VioConfig(estimate_time_offset=estimate)
    vio = VioManager(seq.cam0, seq.imu, options, robot)
    # The robot's IMU, batched as a robot that was told the VIO's offset batches it: each
    # frame's batch reaches the first sample at or after t + offset (t alone while it is 0).
    imu_t = np.concatenate([f.imu_t_ns for f in frames])
    gyro = np.concatenate([f.gyro for f in frames]).reshape(-1, 3)
    accel = np.concatenate([f.accel for f in frames]).reshape(-1, 3)
    results, j = [], 0
    for f in frames:
        reach = f.obs.timestamp_ns + max(0, vio.time_offset_ns)
        k = min(int(np.searchsorted(imu_t, reach, side="left")) + 1, len(imu_t))
        if k > j:
            vio.feed_imu(imu_t[j:k], gyro[j:k], accel[j:k])
            j = k
        results.append(vio.feed_frame(f.obs))
    gt = seq.groundtruth
    assert gt is not None
    s = score(results, gt)
    motion = first_motion_s(seq)
    t0 = results[0].timestamp_ns
    ok = [r for r in results if r.status is TrackingStatus.TRACKING]
    init = (ok[0].timestamp_ns - t0) * 1e-9 - motion if ok else float("nan")
    bg_err = ba_err = float("nan")
    state = vio.get_state()
    if state is not None:
        bg_err = float(np.linalg.norm(state.bias_gyro - np.nanmean(gt.bias_gyro, axis=0)))
        ba_err = float(np.linalg.norm(state.bias_accel - np.nanmean(gt.bias_accel, axis=0)))
    late = [
        r
        for r in ok
        if (r.timestamp_ns - t0) * 1e-9 - motion >= ATE_FROM_S and r.map_id == ok[-1].map_id
    ]
    ate_from = float("nan")
    if len(late) >= 3:
        est = Trajectory.from_poses(
            np.array([r.timestamp_ns for r in late], np.int64),
            np.stack([r.T_world_body for r in late]),
        )
        ref = Trajectory.from_groundtruth(gt)
        ate_from = float(compute_ate(ref, est, AteConfig(align=AlignMode.SE3)).stats.rmse)
    g_nd, a_nd = vio.stats.imu_noise_measured
    ratio = (g_nd / seq.imu.gyro_noise_density, a_nd / seq.imu.accel_noise_density)
    return Row(
        imu,
        robot,
        motion,
        init,
        len(ok) / max(len(results), 1),
        s.maps,
        s.ate_se3_m,
        s.ate_sim3_m,
        s.scale_error,
        bg_err,
        ba_err,
        ratio,
        true_offset_ms(dataset),
        estimate,
        vio.time_offset_ns * 1e-6,
        vio.stats.time_offset_sigma_ms,
        ate_from,
        len(vio.stats.vi_init_s),
    )


def plot(rows: list[Row], out: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    robots = sorted({r.robot for r in rows})
    fig, ax = plt.subplots(1, 3, figsize=(14, 3.8))
    x = np.arange(len(robots))
    sync = [r for r in rows if r.true_offset_ms == 0.0]
    for k, imu in enumerate(("generator", "real")):
        by = {r.robot: r for r in sync if r.imu == imu}
        ate = [100 * by[n].ate_se3_m if n in by else np.nan for n in robots]
        scale = [100 * by[n].scale_error if n in by else np.nan for n in robots]
        ax[0].bar(x + 0.38 * (k - 0.5), ate, 0.36, label=f"{imu} IMU")
        ax[1].bar(x + 0.38 * (k - 0.5), scale, 0.36, label=f"{imu} IMU")
    ax[0].axhline(3.0, color="k", ls="--", lw=0.8, label="goal 3 cm")
    ax[0].set_ylabel("ATE SE(3) [cm], synchronised")
    ax[1].set_ylabel("scale error [%], synchronised")
    late = [r for r in rows if r.true_offset_ms != 0.0]
    for k, (imu, est) in enumerate(
        (("generator", True), ("real", True), ("generator", False), ("real", False))
    ):
        by = {r.robot: r for r in late if r.imu == imu and r.estimate == est}
        ate = [100 * by[n].ate_se3_m if n in by else np.nan for n in robots]
        label = f"{imu}, offset {'estimated' if est else 'unknown'}"
        ax[2].bar(x + 0.2 * (k - 1.5), ate, 0.18, label=label)
    ax[2].set_ylabel("ATE SE(3) [cm], IMU 15 ms late")
    for a in ax:
        a.set_xticks(x, robots)
        a.legend(fontsize=7)
    fig.suptitle("edge VIO on real flights (V2_01/02/03): recorded vs generator IMU, same images")
    fig.tight_layout()
    fig.savefig(out, dpi=110)


def fmt(v: float, scale: float = 1.0, digits: int = 2) -> str:
    return "—" if not np.isfinite(v) else f"{v * scale:.{digits}f}"


HEADER = (
    "| IMU | robot | offset estimation | first motion s | VI init after motion s | tracked "
    "| maps | ATE SE(3) cm | ATE Sim(3) cm | scale err % | gyro bias err rad/s "
    "| accel bias err m/s² | noise measured / datasheet (gyro, accel) | offset used ms |\n"
    "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"
)


def table_row(r: Row) -> str:
    sigma = f" ± {r.offset_sigma_ms:.2f}" if np.isfinite(r.offset_sigma_ms) else ""
    return (
        f"| {r.imu} | {r.robot} | {'on' if r.estimate else 'off'} | {fmt(r.motion_s, 1, 1)} "
        f"| {fmt(r.init_after_motion_s, 1, 1)} | {fmt(r.tracked, 100, 0)} % | {r.maps} "
        f"| {fmt(r.ate_se3_m, 100)} | {fmt(r.ate_sim3_m, 100)} | {fmt(r.scale_error, 100, 1)} "
        f"| {fmt(r.gyro_bias_err, 1, 4)} | {fmt(r.accel_bias_err, 1, 3)} "
        f"| {fmt(r.noise_ratio[0], 1, 1)}x, {fmt(r.noise_ratio[1], 1, 1)}x "
        f"| {r.offset_ms:+.2f}{sigma} |"
    )


OFFSET_VARIANTS: tuple[tuple[str, bool, float | None, ViInitConfig], ...] = (
    # name, the dataset with the late IMU, offset given to the VIO (None: estimated), VI init
    ("synchronised, estimated", False, None, ViInitConfig()),
    ("synchronised, estimated, wait 6 s", False, None, ViInitConfig(wait_for_time_offset_s=6)),
    ("15 ms, given", True, 15.0, ViInitConfig()),
    (
        "15 ms, estimated, no refinement on change",
        True,
        None,
        ViInitConfig(refine_on_offset_change_ms=0.0),
    ),
    ("15 ms, estimated (default)", True, None, ViInitConfig()),
    ("15 ms, estimated, wait 6 s", True, None, ViInitConfig(wait_for_time_offset_s=6)),
)


def offset_variants(args: argparse.Namespace) -> None:
    """``--offset-variants OUT.md``: the VI initialisation's handling of an unknown offset,
    on ``--real`` and ``--real15``, each variant replayed per robot."""
    rows: list[tuple[str, Row]] = []
    for name, late, given, vi_init in OFFSET_VARIANTS:
        dataset = args.real15 if late else args.real
        options = VioConfig(
            estimate_time_offset=given is None,
            time_offset_ns=round((given or 0.0) * 1e6),
            vi_init=vi_init,
        )
        for robot in args.robots.split(","):
            t = time.perf_counter()
            row = run(dataset, robot, args.seconds, args.cache, "real", given is None, options)
            rows.append((name, row))
            print(f"{name} {robot}: {row} ({time.perf_counter() - t:.0f} s)", flush=True)
    commit = git_commit()
    robots = args.robots.split(",")
    mean_from = {
        n: float(np.mean([r.ate_from_m for m, r in rows if m == n])) for n, *_ in OFFSET_VARIANTS
    }
    lines = [
        "# An unknown camera-IMU offset and the VI initialisation (real V2 flights, real IMU)",
        "",
        f"`benchmarks/bench_real_imu.py --real {args.real} --real15 {args.real15} --sim "
        f"{args.sim} --seconds {args.seconds:g} --offset-variants {args.offset_variants}`; "
        f"commit {commit}, Python {platform.python_version()}; {scene_of(args.real)}. Each "
        "robot's edge VIO replayed on its decoded frames (deterministic: one run each). "
        f"`from {ATE_FROM_S:g} s`: SE(3) ATE over the frames from {ATE_FROM_S:g} s after the "
        "flight's first motion, the same frames for every variant (a later initialisation "
        "otherwise drops the first seconds, the hardest, from its ATE). The 15 ms dataset is "
        "rendered apart (`--time-offset-ms 15`), so its images are not the synchronised ones: "
        "`15 ms, given` is the reference an estimate can reach.",
        "",
        "| variant | robot | init after motion s | ATE cm | ATE from "
        f"{ATE_FROM_S:g} s cm | offset used ms | VI runs |",
        "|---|---|---|---|---|---|---|",
    ]
    for name, r in rows:
        lines.append(
            f"| {name} | {r.robot} | {fmt(r.init_after_motion_s, digits=1)} | "
            f"{fmt(r.ate_se3_m, 100)} | {fmt(r.ate_from_m, 100)} | {r.offset_ms:+.2f} | "
            f"{r.vi_runs} |"
        )
    given = mean_from["15 ms, given"]
    sync = mean_from["synchronised, estimated"]
    lines += [
        "",
        f"Mean over the robots of the ATE from {ATE_FROM_S:g} s, and against `15 ms, given` "
        "and `synchronised, estimated`:",
        "",
        "| variant | mean cm | ÷ given | ÷ synchronised |",
        "|---|---|---|---|",
        *(
            f"| {n} | {100 * m:.2f} | {m / given:.2f} | {m / sync:.2f} |"
            for n, m in mean_from.items()
        ),
    ]
    args.offset_variants.write_text("\n".join(lines) + "\n")
    _plot_variants(rows, robots, args.offset_variants.with_suffix(".png"))
    print(args.offset_variants.read_text())


def _plot_variants(rows: list[tuple[str, Row]], robots: list[str], out: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = [n for n, *_ in OFFSET_VARIANTS]
    fig, ax = plt.subplots(figsize=(11, 4))
    width = 0.8 / len(names)
    x = np.arange(len(robots))
    for k, name in enumerate(names):
        by = {r.robot: r for n, r in rows if n == name}
        ate = [100 * by[b].ate_from_m if b in by else np.nan for b in robots]
        ax.bar(x + width * (k - (len(names) - 1) / 2), ate, width, label=name)
    ax.set_xticks(x, robots)
    ax.set_ylabel(f"ATE from {ATE_FROM_S:g} s after motion [cm]")
    ax.set_title("Unknown camera-IMU offset: VI initialisation variants (real V2 flights)")
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(out, dpi=110)
    plt.close(fig)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--real", type=Path, required=True, help="dataset with the recorded IMUs")
    ap.add_argument("--sim", type=Path, required=True, help="same flights, generator's IMU")
    ap.add_argument("--real15", type=Path, help="--real rendered with --time-offset-ms 15")
    ap.add_argument("--sim15", type=Path, help="--sim rendered with --time-offset-ms 15")
    ap.add_argument("--robots", default="robot0,robot1,robot2")
    ap.add_argument("--seconds", type=float, default=60.0)
    ap.add_argument("--cache", type=Path, default=Path("/tmp/real_imu_cache"))
    ap.add_argument("--live", action="append", default=[], metavar="NAME=REPORT_JSON")
    ap.add_argument("--out", type=Path, default=RESULTS / "real_imu.md")
    ap.add_argument(
        "--offset-variants",
        type=Path,
        metavar="OUT.md",
        help="instead: the VI initialisation variants for an unknown offset (--real, --real15)",
    )
    args = ap.parse_args()
    logging.basicConfig(level=logging.WARNING)
    args.cache.mkdir(parents=True, exist_ok=True)
    if args.offset_variants is not None:
        if args.real15 is None:
            ap.error("--offset-variants needs --real15")
        offset_variants(args)
        return
    runs: list[tuple[str, Path, bool]] = [("generator", args.sim, True), ("real", args.real, True)]
    for imu, late in (("generator", args.sim15), ("real", args.real15)):
        if late is not None:
            runs += [(imu, late, True), (imu, late, False)]
    rows = []
    for imu, dataset, estimate in runs:
        for robot in args.robots.split(","):
            t = time.perf_counter()
            rows.append(run(dataset, robot, args.seconds, args.cache, imu, estimate))
            print(f"{imu} {robot}: {rows[-1]} ({time.perf_counter() - t:.0f} s)", flush=True)
    commit = git_commit()
    late_args = "".join(
        f" --{k} {v}" for k, v in (("real15", args.real15), ("sim15", args.sim15)) if v
    )
    lines = [
        "# Real IMUs: the edge VIO on real flights, recorded IMU beside the generator's",
        "",
        f"`benchmarks/bench_real_imu.py --real {args.real} --sim {args.sim}{late_args} "
        f"--seconds {args.seconds:g}`; commit {commit}, Python {platform.python_version()}. "
        "Images rendered along EuRoC V2_01 / V2_02 / V2_03 (robot0 / 1 / 2, "
        f"{scene_of(args.real)}); `real`: the ADIS16448 IMU recorded on each flight "
        "(`recslam dataset synth --trajectory GT,... --imu IMU,...`), `generator`: the "
        "simulated IMU on the same images. One run each (the VIO is deterministic on cached "
        "inputs).",
        "",
        "## Synchronised camera and IMU",
        "",
        HEADER,
        *(table_row(r) for r in rows if r.true_offset_ms == 0.0),
    ]
    late_rows = [r for r in rows if r.true_offset_ms != 0.0]
    if late_rows:
        lines += [
            "",
            f"## IMU clock {late_rows[0].true_offset_ms:g} ms ahead of the camera's",
            "",
            "Same images, the IMU stamped late (`--time-offset-ms`); `offset used` is what the "
            "VIO reads its IMU at at the end (0 when not estimated), with its last estimate's "
            "jackknife sigma. The offset between the recorded IMU and the images is itself "
            "known only to about a millisecond (the synchronised rows' own estimate shows it).",
            "",
            HEADER,
            *(table_row(r) for r in late_rows),
        ]
    if args.live:
        lines += [
            "",
            "## Whole runs",
            "",
            "Robots, edge and cloud as processes on loopback (`recslam demo --data DIR --out "
            "OUT --no-dashboard`), the edge estimating the offset and telling the robots:",
            "",
            "| run | maps | joint ATE cm | per robot ATE cm | frames decoded / sent |",
            "|---|---|---|---|---|",
        ]
        for item in args.live:
            name, path = item.split("=", 1)
            lines.append(live_row(name, Path(path)))
    args.out.write_text("\n".join(lines) + "\n")
    plot(rows, args.out.with_suffix(".png"))
    print(args.out.read_text())


def live_row(name: str, path: Path) -> str:
    """One table row from a ``recslam demo`` report.json (as :mod:`lab.run.report` writes)."""
    if not path.exists():
        return f"| {name} | not run ({path} missing) | | | |"
    rep = json.loads(path.read_text())
    robots = rep.get("robots", {})

    def cm(v: float | None) -> str:
        return fmt(float("nan") if v is None else float(v), 100)

    per = ", ".join(f"{n} {cm(r.get('ate_rmse_m'))}" for n, r in sorted(robots.items()))
    sent = sum(int(r.get("frames_sent") or 0) for r in robots.values())
    decoded = sum(int(r.get("frames_decoded") or 0) for r in robots.values())
    maps = rep.get("map", {}).get("maps", "?")
    joint = rep.get("ate", {}).get("joint_rmse_m")
    return f"| {name} | {maps} | {cm(joint)} | {per} | {decoded} / {sent} |"


if __name__ == "__main__":
    main()
