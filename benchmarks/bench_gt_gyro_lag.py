"""How far a flight's gyro runs from its ground truth's rotation, window by window.

EuRoC's ``state_groundtruth_estimate0`` is a fusion of the Vicon poses and the IMU; recslam's
rendered datasets take their images from it (``recslam dataset synth --trajectory``), so the lag
at which its body rates match the gyro is the camera-IMU offset of a rendered dataset with the
recorded IMU (0 by construction where the fusion follows the gyro). For each window of
``--window`` s (every ``--step`` s), the lag (a ``--resolution`` grid within ±``--range``) that
minimises ``|gyro(t + lag) - b_g(t) - w_gt(t)|²`` over the ground truth's samples: ``w_gt`` from
consecutive ground-truth orientations, ``b_g`` the ground truth's gyro bias. Positive: the IMU
clock reads later than the ground truth's (``t_imu = t_cam + lag``, as ``--time-offset-ms``).

Run: ``.venv/bin/python benchmarks/bench_gt_gyro_lag.py --flights ../shared/datasets/
euroc-V2-flights``; writes ``benchmarks/results/gt_gyro_lag.md``.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from lab.links import git_commit

RESULTS = Path(__file__).resolve().parent / "results"


def window_lags(
    flight: Path, window_s: float, step_s: float, range_ms: float, resolution_ms: float
) -> list[tuple[float, float]]:
    """``(window start s, lag ms)`` of ``flight`` (a folder holding ``mav0``)."""
    mav0 = flight / "mav0"
    gt = np.loadtxt(mav0 / "state_groundtruth_estimate0" / "data.csv", delimiter=",", comments="#")
    imu = np.loadtxt(mav0 / "imu0" / "data.csv", delimiter=",", comments="#")
    t = gt[:, 0] * 1e-9
    q_wxyz = gt[:, 4:8]
    rot = Rotation.from_quat(np.c_[q_wxyz[:, 1:], q_wxyz[:, :1]])
    w_gt = (rot[:-1].inv() * rot[1:]).as_rotvec() / np.diff(t)[:, None]  # (N-1, 3) rad/s
    t_w = 0.5 * (t[1:] + t[:-1])
    bias = np.stack([np.interp(t_w, t, gt[:, 11 + k]) for k in range(3)], axis=1)
    t_imu = imu[:, 0] * 1e-9
    lags = np.arange(-range_ms, range_ms + 0.5 * resolution_ms, resolution_ms) * 1e-3
    out = []
    for start in np.arange(t[0], t[-1] - window_s + 1e-9, step_s):
        m = (t_w >= start) & (t_w < start + window_s)
        cost = [
            np.sum(
                (
                    np.stack([np.interp(t_w[m] + lag, t_imu, imu[:, 1 + k]) for k in range(3)], 1)
                    - bias[m]
                    - w_gt[m]
                )
                ** 2
            )
            for lag in lags
        ]
        out.append((float(start - t[0]), 1e3 * float(lags[int(np.argmin(cost))])))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--flights", type=Path, required=True, help="folder of EuRoC flights")
    ap.add_argument("--window", type=float, default=20.0)
    ap.add_argument("--step", type=float, default=10.0)
    ap.add_argument("--range", type=float, default=15.0, help="ms either way")
    ap.add_argument("--resolution", type=float, default=0.2, help="ms")
    ap.add_argument("--out", type=Path, default=RESULTS / "gt_gyro_lag.md")
    args = ap.parse_args()
    flights = sorted(p for p in args.flights.iterdir() if (p / "mav0").is_dir())
    rows = {
        f.name: window_lags(f, args.window, args.step, args.range, args.resolution) for f in flights
    }
    starts = sorted({s for r in rows.values() for s, _ in r})
    lines = [
        "# Gyro against the ground truth's rotation, window by window",
        "",
        f"`benchmarks/bench_gt_gyro_lag.py --flights {args.flights}` at {git_commit()}: the "
        "lag [ms] at which the gyro matches the ground truth's body rates, "
        f"{args.window:g} s windows every {args.step:g} s ({args.resolution:g} ms grid). "
        "Positive: the IMU clock reads later.",
        "",
        "| window start s | " + " | ".join(rows) + " |",
        "|---" * (len(rows) + 1) + "|",
    ]
    for s in starts:
        cells = [next((f"{lag:+.1f}" for s2, lag in r if s2 == s), "—") for r in rows.values()]
        lines.append(f"| {s:.0f} | " + " | ".join(cells) + " |")
    args.out.write_text("\n".join(lines) + "\n")
    print(args.out.read_text())


if __name__ == "__main__":
    main()
