"""Edge VIO on the real pipeline's data: rendered images → robot → codecs → VIO → ATE.

For each robot of a rendered synthetic dataset (``recslam dataset synth``): the robot's front
end and codecs run in process (no network, no feedback), the edge decodes the frames
(:mod:`lab.vio_replay`), the decoded inputs are cached in ``--cache`` (reused when
present), and the VIO runs on the first ``--seconds``. ATE [m] of the frames tracked in the
last map after SE(3) and Sim(3) alignment, the Sim(3) scale error, maps started and when
tracking (metric, VI-initialised) began.

Run: ``.venv/bin/python benchmarks/bench_vio_pipeline.py --dataset /tmp/synth_default
/tmp/synth_seed1 /tmp/synth_seed2 [--seconds 60]`` (datasets from ``recslam dataset synth
--out DIR --seed N``); writes ``benchmarks/results/vio_pipeline.md``.
"""

from __future__ import annotations

import argparse
import logging
import platform
import time
from pathlib import Path

from common.data.euroc import EurocSequence
from lab.vio_replay import decode_sequence, load_decoded, run_vio, save_decoded, score

log = logging.getLogger("bench_vio_pipeline")
RESULTS = Path(__file__).resolve().parent / "results" / "vio_pipeline.md"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument(
        "--dataset",
        type=Path,
        nargs="+",
        default=[Path("/tmp/synth_default")],
        help="one or more rendered datasets (e.g. seeds 0, 1, 2)",
    )
    ap.add_argument("--robots", default="robot0,robot1,robot2")
    ap.add_argument("--seconds", type=float, default=60.0)
    ap.add_argument("--cache", type=Path, default=Path("/tmp/vio_pipeline_cache"))
    ap.add_argument("--out", type=Path, default=RESULTS, help="markdown table written")
    args = ap.parse_args()
    logging.basicConfig(level=logging.WARNING)
    args.cache.mkdir(parents=True, exist_ok=True)
    rows = []
    for dataset in args.dataset:
        for name in args.robots.split(","):
            seq = EurocSequence(dataset / name)
            cache = args.cache / f"{dataset.name}_{name}_{args.seconds:g}s.npz"
            if cache.exists():
                frames = load_decoded(cache)
            else:
                frames = decode_sequence(seq.root, args.seconds)
                save_decoded(cache, frames)
            t0 = time.process_time()
            results = run_vio(frames, seq.cam0, seq.imu, name=name)
            cpu_ms = (time.process_time() - t0) * 1e3 / max(len(frames), 1)
            s = score(results, seq.groundtruth)
            rows.append((dataset.name, name, s, cpu_ms))
            print(dataset.name, name, s, f"{cpu_ms:.1f} ms/frame", flush=True)
    lines = [
        "# Edge VIO on the real pipeline (rendered synthetic robots)",
        "",
        f"Datasets {', '.join(f'`{d}`' for d in args.dataset)}, first {args.seconds:g} s per "
        "robot: rendered images → "
        "robot front end (LK + ORB keyframes) → feature/IMU codecs → edge decoding → "
        "VioManager (`benchmarks/bench_vio_pipeline.py`, in process, no feedback). ATE over "
        "the frames tracked (metric) in the last map.",
        "",
        f"Machine: {platform.processor() or platform.machine()}, Python "
        f"{platform.python_version()}.",
        "",
        "VIO CPU = process time of the VIO per frame (one core; the machine is shared).",
        "",
        "| dataset | robot | frames | tracked | maps | tracking from [s] | ATE SE(3) [cm] "
        "| ATE Sim(3) [cm] | scale error [%] | VIO CPU [ms/frame] |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for ds, name, s, cpu_ms in rows:
        lines.append(
            f"| {ds} | {name} | {s.frames} | {s.tracked} | {s.maps} | {s.first_tracking_s:.2f} "
            f"| {s.ate_se3_m * 100:.1f} | {s.ate_sim3_m * 100:.1f} "
            f"| {s.scale_error * 100:+.2f} | {cpu_ms:.1f} |"
        )
    args.out.write_text("\n".join(lines) + "\n")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
