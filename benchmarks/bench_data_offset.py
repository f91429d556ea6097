"""The camera–IMU offset a rendered real flight carries, measured with perfect vision.

``recslam dataset synth --trajectory GT --imu IMU`` renders the images along EuRoC's
``state_groundtruth_estimate0`` (a fusion of the Vicon poses with the IMU) and writes the
recorded IMU beside them. Which time offset does that data hold between its images and its
IMU? Two measures, per window of ``--window`` s every ``--step`` s:

- ``perfect vision``: the edge's own estimator (``services.edge.vio.time_offset``) fed the
  ground truth's orientations at 20 Hz camera times instead of the VIO's tracked rotations, with
  the ground truth's median gyro bias: relative rotations over 0.05–0.8 s, i.e. the low
  frequencies, where the fusion follows the Vicon (the images' clock);
- ``rates``: the lag minimising ``|gyro(t + lag) - b_g(t) - w_gt(t)|²`` over the ground truth's
  200 Hz body rates: the high frequencies, where the fusion follows the gyro (0 by construction).

Positive: the IMU clock reads later (``t_imu = t_cam + offset``, as ``--time-offset-ms``).

Run: ``.venv/bin/python benchmarks/bench_data_offset.py --flights ../shared/datasets/
euroc-V2-flights``; writes ``benchmarks/results/data_offset.md``.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from lab.links import git_commit
from services.edge.vio.time_offset import estimate_time_offset

RESULTS = Path(__file__).resolve().parent / "results"


def window_offsets(flight: Path, window_s: float, step_s: float) -> list[tuple[float, str, float]]:
    """``(window start s, perfect-vision estimate as text, rate lag ms)`` of ``flight``."""
    mav0 = flight / "mav0"
    gt = np.loadtxt(mav0 / "state_groundtruth_estimate0" / "data.csv", delimiter=",", comments="#")
    imu = np.loadtxt(mav0 / "imu0" / "data.csv", delimiter=",", comments="#")
    t_gt = gt[:, 0].astype(np.int64)
    rot = Rotation.from_quat(np.c_[gt[:, 5:8], gt[:, 4:5]])  # EuRoC (w, x, y, z) -> (x, y, z, w)
    t_cam = np.arange(t_gt[0] + 100_000_000, t_gt[-1] - 100_000_000, 50_000_000, dtype=np.int64)
    R_cam = Slerp(t_gt.astype(float), rot)(t_cam.astype(float)).as_matrix()
    bias = np.median(gt[:, 11:14], axis=0)
    t = t_gt * 1e-9
    w_gt = (rot[:-1].inv() * rot[1:]).as_rotvec() / np.diff(t)[:, None]  # (N-1, 3) rad/s
    t_w = 0.5 * (t[1:] + t[:-1])
    b_w = np.stack([np.interp(t_w, t, gt[:, 11 + k]) for k in range(3)], axis=1)
    t_imu = imu[:, 0] * 1e-9
    lags = np.arange(-15.0, 15.1, 0.2) * 1e-3
    out = []
    span = (t_cam[-1] - t_cam[0]) * 1e-9
    for start in np.arange(0.0, span - window_s + 1e-9, step_s):
        a = t_cam[0] + int(start * 1e9)
        m = (t_cam >= a) & (t_cam < a + int(window_s * 1e9))
        mi = (imu[:, 0] >= t_cam[m][0] - 1e8) & (imu[:, 0] <= t_cam[m][-1] + 1e8)
        est = estimate_time_offset(
            t_cam[m], R_cam[m], imu[mi, 0].astype(np.int64), imu[mi, 1:4], bias
        )
        text = est if isinstance(est, str) else f"{est.offset_ns * 1e-6:+.2f} ± {est.sigma_ms:.2f}"
        mw = (t_w >= a * 1e-9) & (t_w < a * 1e-9 + window_s)
        cost = [
            np.sum(
                (
                    np.stack([np.interp(t_w[mw] + lag, t_imu, imu[:, 1 + k]) for k in range(3)], 1)
                    - b_w[mw]
                    - w_gt[mw]
                )
                ** 2
            )
            for lag in lags
        ]
        out.append((float(start), text, 1e3 * float(lags[int(np.argmin(cost))])))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--flights", type=Path, required=True, help="folder of EuRoC flights")
    ap.add_argument("--window", type=float, default=60.0, help="s (the VIO's window_s)")
    ap.add_argument("--step", type=float, default=10.0)
    ap.add_argument("--out", type=Path, default=RESULTS / "data_offset.md")
    args = ap.parse_args()
    flights = sorted(p for p in args.flights.iterdir() if (p / "mav0").is_dir())
    lines = [
        "# The camera–IMU offset a rendered real flight carries",
        "",
        f"`benchmarks/bench_data_offset.py --flights {args.flights}` at {git_commit()}; "
        f"{args.window:g} s windows every {args.step:g} s. ms, positive: the IMU clock reads "
        "later. `perfect vision`: the edge's estimator on the ground truth's orientations "
        "(± its jackknife sigma); `rates`: the 200 Hz body-rate lag (see the script).",
        "",
        "| flight | window s | perfect vision ms | rates ms |",
        "|---|---|---|---|",
    ]
    for f in flights:
        for start, text, lag in window_offsets(f, args.window, args.step):
            lines.append(
                f"| {f.name} | {start:.0f}–{start + args.window:.0f} | {text} | {lag:+.1f} |"
            )
    args.out.write_text("\n".join(lines) + "\n")
    print(args.out.read_text())


if __name__ == "__main__":
    main()
