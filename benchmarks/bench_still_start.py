"""A long stationary start on a real IMU: still for 5.5 s, then the flight.

EuRoC's MAVs stand on the ground before they take off (V1_01: about 5.5 s; the V2 flights in
``shared/``: 3.4 / 0 / 4.3 s). To fly a 5.5 s standstill with a real IMU, the recording's own
standstill is made longer: the first ``extra`` seconds of V2_01's ground truth and of its IMU
(both still, as recorded: bias, noise, gravity) are copied in front of it, so the images and
the IMU stand still for ``--still-s`` before the recorded take-off. The dataset is rendered
with ``recslam dataset synth --trajectory GT --imu IMU``; the robot's front end, codecs and
the edge's VIO replay it (as ``bench_real_imu.py`` does): time from the first motion to VI
initialisation, ATE, scale, biases. The real EuRoC excerpt (95 real frames of V1_01, all
still) goes through the same robot and VIO: it must make no metric map out of a standstill
and say why.

Run: ``.venv/bin/python benchmarks/bench_still_start.py --flights ../shared/datasets/
euroc-V2-flights --micro ../shared/datasets/euroc-micro-V1_01``; writes
``benchmarks/results/still_start.md``.
"""

from __future__ import annotations

import argparse
import collections
import logging
import platform
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
from bench_real_imu import fmt, run

from lab.vio_replay import decode_sequence, run_vio

log = logging.getLogger("bench_still_start")
RESULTS = Path(__file__).resolve().parent / "results"


def first_motion_ns(gt_rows: np.ndarray) -> int:
    """First ground-truth time with a speed above 0.1 m/s (EuRoC rows: t, p, q, v, ...)."""
    moving = np.flatnonzero(np.linalg.norm(gt_rows[:, 8:11], axis=1) > 0.1)
    return int(gt_rows[moving[0], 0])


def longer_standstill(flight: Path, still_s: float, out: Path) -> float:
    """Write ``flight``'s ground truth and IMU into ``out`` (EuRoC layout) with its standstill
    made ``still_s`` long (the first seconds copied in front); the extra seconds."""
    gt_csv = flight / "mav0" / "state_groundtruth_estimate0" / "data.csv"
    imu_csv = flight / "mav0" / "imu0" / "data.csv"
    gt = np.loadtxt(gt_csv, delimiter=",", comments="#")
    imu = np.loadtxt(imu_csv, delimiter=",", comments="#")
    t0 = int(gt[0, 0])
    still = (first_motion_ns(gt) - t0) * 1e-9
    extra = still_s - still
    if not 0 < extra < still - 0.5:
        raise SystemExit(f"{flight}: stands still {still:.1f} s; cannot make it {still_s} s")
    d = int(extra * 1e9)
    gt_pre = gt[(gt[:, 0] >= t0) & (gt[:, 0] < t0 + d)].copy()
    gt_pre[:, 0] -= d
    imu_pre = imu[(imu[:, 0] >= t0) & (imu[:, 0] < t0 + d)].copy()
    imu_pre[:, 0] -= d
    new_imu = np.concatenate([imu[imu[:, 0] < t0 - d], imu_pre, imu[imu[:, 0] >= t0]])
    for path, rows, src in (
        (
            out / "mav0" / "state_groundtruth_estimate0" / "data.csv",
            np.vstack([gt_pre, gt]),
            gt_csv,
        ),
        (out / "mav0" / "imu0" / "data.csv", new_imu, imu_csv),
    ):
        path.parent.mkdir(parents=True, exist_ok=True)
        header = src.read_text().splitlines()[0]
        lines = [header] + [f"{int(r[0])}," + ",".join(f"{v:.9g}" for v in r[1:]) for r in rows]
        path.write_text("\n".join(lines) + "\n")
    return extra


def micro_check(micro: Path) -> tuple[collections.Counter, str, bool]:
    """The real excerpt through the robot and the VIO: statuses, the last reason, whether a
    metric (VI-initialised) map came out of it."""
    from common.data.euroc import EurocSequence

    seq = EurocSequence(micro)
    frames = decode_sequence(micro)
    results = run_vio(frames, seq.cam0, seq.imu, name="micro")
    counts = collections.Counter(r.status.value for r in results)
    metric = any(r.status.value == "tracking" for r in results)
    return counts, results[-1].reason, metric


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--flights", type=Path, required=True, help="euroc-V2-flights folder")
    ap.add_argument("--flight", default="V2_01")
    ap.add_argument("--micro", type=Path, required=True, help="euroc-micro-V1_01 folder")
    ap.add_argument("--still-s", type=float, default=5.5)
    ap.add_argument("--seconds", type=float, default=40.0)
    ap.add_argument("--work", type=Path, default=None, help="keep the dataset here")
    ap.add_argument("--out", type=Path, default=RESULTS / "still_start.md")
    args = ap.parse_args()
    logging.basicConfig(level=logging.WARNING)
    work = args.work or Path(tempfile.mkdtemp(prefix="still_start_"))
    src = work / "recording"
    extra = longer_standstill(args.flights / args.flight, args.still_s, src)
    data = work / "dataset"
    gt = src / "mav0" / "state_groundtruth_estimate0" / "data.csv"
    imu = src / "mav0" / "imu0" / "data.csv"
    cmd = [sys.executable, "-m", "recslam", "dataset", "synth", "--out", str(data)]
    cmd += ["--trajectory", str(gt), "--imu", str(imu), "--seconds", f"{args.seconds:g}"]
    cmd += ["--world", "vicon", "--no-progress"]
    print(" ".join(cmd), flush=True)
    subprocess.run(cmd, check=True)
    row = run(data, "robot0", args.seconds, work, "real")
    print(row, flush=True)
    counts, reason, metric = micro_check(args.micro)
    commit = subprocess.run(
        ["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True, check=False
    ).stdout.strip()
    lines = [
        "# A long stationary start on a real IMU",
        "",
        f"`benchmarks/bench_still_start.py --flights {args.flights} --micro {args.micro} "
        f"--still-s {args.still_s:g} --seconds {args.seconds:g}`; commit {commit}, Python "
        f"{platform.python_version()}. {args.flight}'s ground truth and recorded IMU with its "
        f"standstill made {args.still_s:g} s long ({extra:.1f} s of its own standstill copied "
        "in front), rendered in the vicon world (scene seed 0) and replayed through the "
        "robot's front end and codecs into the edge's VIO (time offset estimated).",
        "",
        "| flight | still s | VI init after motion s | tracked | maps | ATE SE(3) cm "
        "| ATE Sim(3) cm | scale err % | gyro bias err rad/s | accel bias err m/s² |",
        "|---|---|---|---|---|---|---|---|---|---|",
        f"| {args.flight} + standstill | {fmt(row.motion_s, 1, 1)} "
        f"| {fmt(row.init_after_motion_s, 1, 1)} | {fmt(row.tracked, 100, 0)} % | {row.maps} "
        f"| {fmt(row.ate_se3_m, 100)} | {fmt(row.ate_sim3_m, 100)} "
        f"| {fmt(row.scale_error, 100, 1)} | {fmt(row.gyro_bias_err, 1, 4)} "
        f"| {fmt(row.accel_bias_err, 1, 3)} |",
        "",
        f"The real excerpt ({args.micro.name}: 95 real frames, the MAV still): frames by VIO "
        f"status {dict(counts)}; a metric map made of the standstill: "
        f"{'yes (wrong)' if metric else 'no'}; the last frame's reason: {reason or '—'}.",
    ]
    args.out.write_text("\n".join(lines) + "\n")
    print(args.out.read_text())


if __name__ == "__main__":
    main()
