"""Real IMUs: the edge's VIO on real flights' recorded IMU, beside the generator's IMU.

Two datasets rendered along the same recorded flights (same images): one with the IMU
recorded on each flight (``recslam dataset synth --trajectory GT,... --imu IMU,...``), one
with the generator's simulated IMU (the same command without ``--imu``). For every robot the
robot's front end and codecs run in process, the edge decodes (:mod:`lab.vio_replay`, cached
in ``--cache``) and the VIO runs: time from the flight's first motion to VI initialisation,
ATE [m] of the tracked frames (SE(3) and Sim(3)), the Sim(3) scale error, the gyro and accel
biases at the end against the ground truth's, and the IMU noise measured in flight against
the calibration. ``--live NAME=report.json`` adds the joint ATE of whole robot/edge/cloud
runs (``recslam demo --data DIR --out OUT``: ``OUT/report.json``).

Run: ``.venv/bin/python benchmarks/bench_real_imu.py --real /tmp/rd/v2_real_3x60 --sim
/tmp/rd/v2_sim_3x60 --live real=/tmp/rd/demo_real/report.json
--live sim=/tmp/rd/demo_sim/report.json``; writes ``benchmarks/results/real_imu.md`` and
``real_imu.png``.
"""

from __future__ import annotations

import argparse
import json
import logging
import platform
import subprocess
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from common.data.euroc import EurocSequence
from lab.vio_replay import decode_sequence, load_decoded, save_decoded, score
from services.edge.vio.manager import VioManager
from services.edge.vio.types import TrackingStatus

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


def first_motion_s(seq: EurocSequence) -> float:
    """Seconds from the first frame to the ground truth's first speed above 0.1 m/s or rate
    above 0.1 rad/s (the flight's first motion)."""
    gt = seq.groundtruth
    assert gt is not None
    t = (gt.timestamps_ns - seq.frame_timestamps_ns[0]) * 1e-9
    speed = np.linalg.norm(np.gradient(gt.p_world_body, t, axis=0), axis=1)
    moving = np.flatnonzero((speed > 0.1) & (t >= 0))
    return float(t[moving[0]]) if len(moving) else float("nan")


def run(dataset: Path, robot: str, seconds: float, cache: Path, imu: str) -> Row:
    seq = EurocSequence(dataset / robot)
    file = cache / f"{dataset.name}_{robot}_{seconds:g}s.npz"
    if file.exists():
        frames = load_decoded(file)
    else:
        frames = decode_sequence(seq.root, seconds)
        save_decoded(file, frames)
    vio = VioManager(seq.cam0, seq.imu, robot_name=robot)
    results = []
    for f in frames:
        if len(f.imu_t_ns):
            vio.feed_imu(f.imu_t_ns, f.gyro, f.accel)
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
    )


def plot(rows: list[Row], out: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    robots = sorted({r.robot for r in rows})
    fig, ax = plt.subplots(1, 2, figsize=(10, 3.8))
    x = np.arange(len(robots))
    for k, imu in enumerate(("generator", "real")):
        by = {r.robot: r for r in rows if r.imu == imu}
        ate = [100 * by[n].ate_se3_m if n in by else np.nan for n in robots]
        scale = [100 * by[n].scale_error if n in by else np.nan for n in robots]
        ax[0].bar(x + 0.38 * (k - 0.5), ate, 0.36, label=f"{imu} IMU")
        ax[1].bar(x + 0.38 * (k - 0.5), scale, 0.36, label=f"{imu} IMU")
    ax[0].axhline(3.0, color="k", ls="--", lw=0.8, label="goal 3 cm")
    ax[0].set_ylabel("ATE SE(3) [cm]")
    ax[1].set_ylabel("scale error [%]")
    for a in ax:
        a.set_xticks(x, robots)
        a.legend(fontsize=8)
    fig.suptitle("edge VIO on real flights (V2_01/02/03): recorded vs generator IMU, same images")
    fig.tight_layout()
    fig.savefig(out, dpi=110)


def fmt(v: float, scale: float = 1.0, digits: int = 2) -> str:
    return "—" if not np.isfinite(v) else f"{v * scale:.{digits}f}"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--real", type=Path, required=True, help="dataset with the recorded IMUs")
    ap.add_argument("--sim", type=Path, required=True, help="same flights, generator's IMU")
    ap.add_argument("--robots", default="robot0,robot1,robot2")
    ap.add_argument("--seconds", type=float, default=60.0)
    ap.add_argument("--cache", type=Path, default=Path("/tmp/real_imu_cache"))
    ap.add_argument("--live", action="append", default=[], metavar="NAME=REPORT_JSON")
    ap.add_argument("--out", type=Path, default=RESULTS / "real_imu.md")
    args = ap.parse_args()
    logging.basicConfig(level=logging.WARNING)
    args.cache.mkdir(parents=True, exist_ok=True)
    rows = []
    for imu, dataset in (("generator", args.sim), ("real", args.real)):
        for robot in args.robots.split(","):
            t = time.perf_counter()
            rows.append(run(dataset, robot, args.seconds, args.cache, imu))
            print(f"{imu} {robot}: {rows[-1]} ({time.perf_counter() - t:.0f} s)", flush=True)
    commit = subprocess.run(
        ["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True, check=False
    ).stdout.strip()
    lines = [
        "# Real IMUs: the edge VIO on real flights, recorded IMU beside the generator's",
        "",
        f"`benchmarks/bench_real_imu.py --real {args.real} --sim {args.sim} --seconds "
        f"{args.seconds:g}`; commit {commit}, Python {platform.python_version()}. Images "
        "rendered along EuRoC V2_01 / V2_02 / V2_03 (robot0 / 1 / 2, scene seed 0, vicon "
        "world); `real`: the ADIS16448 IMU recorded on each flight "
        "(`recslam dataset synth --trajectory GT,... --imu IMU,...`), `generator`: the "
        "simulated IMU on the same images. One run each (the VIO is deterministic on cached "
        "inputs).",
        "",
        "| IMU | robot | first motion s | VI init after motion s | tracked | maps "
        "| ATE SE(3) cm | ATE Sim(3) cm | scale err % | gyro bias err rad/s "
        "| accel bias err m/s² | noise measured / datasheet (gyro, accel) |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r.imu} | {r.robot} | {fmt(r.motion_s, 1, 1)} | {fmt(r.init_after_motion_s, 1, 1)} "
            f"| {fmt(r.tracked, 100, 0)} % | {r.maps} | {fmt(r.ate_se3_m, 100)} "
            f"| {fmt(r.ate_sim3_m, 100)} | {fmt(r.scale_error, 100, 1)} "
            f"| {fmt(r.gyro_bias_err, 1, 4)} | {fmt(r.accel_bias_err, 1, 3)} "
            f"| {fmt(r.noise_ratio[0], 1, 1)}x, {fmt(r.noise_ratio[1], 1, 1)}x |"
        )
    if args.live:
        lines += [
            "",
            "Whole runs (robots, edge and cloud as processes on loopback, `recslam demo --data "
            "DIR --out OUT --no-dashboard`):",
            "",
            "| IMU | maps | joint ATE cm | per robot ATE cm | frames decoded / sent |",
            "|---|---|---|---|---|",
        ]
        for item in args.live:
            name, path = item.split("=", 1)
            lines.append(live_row(name, Path(path)))
    args.out.write_text("\n".join(lines) + "\n")
    plot(rows, args.out.with_suffix(".png"))
    print(args.out.read_text())


def live_row(name: str, path: Path) -> str:
    """One table row from a ``recslam demo`` report.json (as :mod:`recslam.report` writes)."""
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
