"""What a robot's uplink carries, part by part, for codec variants on the same frames.

Each robot of ``--data`` (EuRoC layout, e.g. ``recslam dataset synth``) goes through the
robot's own pipeline in-process (``services.robot.app.RobotApp``: tracking, keyframe decision,
coding; no edge, so no IMU feedback for the tracker) once per variant, and the coded bits are
split by the codec's parts (information content of each model; ``overhead`` = header, CRC,
coder padding): keyframes, non-keyframes, IMU, in kbit/s at camera rate (bits over frames /
``--rate-hz``). The variants change only what is coded, not what is tracked:

- ``paper``: continued features coded against their track's descriptor (the paper's [55]
  inter mode) and one affine flow for a non-keyframe's tracks;
- ``carry``: continued features carry their track's descriptor (no bits);
- ``default``: ``carry`` and non-keyframe tracks predicted from their last step.

Run: ``.venv/bin/python benchmarks/bench_uplink_split.py --data DATA --out
benchmarks/results/uplink_split.md``.
"""

from __future__ import annotations

import argparse
import collections
import dataclasses
import logging
import time
from pathlib import Path

from common.data.euroc import EurocSequence
from common.vocabulary import Vocabulary
from lab.links import git_commit
from services.robot.app import RobotApp
from services.robot.config import FrontEndConfig

RESULTS = Path(__file__).resolve().parent / "results"
VARIANTS = {
    "paper": {"carry_track_descriptors": False, "track_velocity": False},
    "carry": {"carry_track_descriptors": True, "track_velocity": False},
    "default": {"carry_track_descriptors": True, "track_velocity": True},
}
logger = logging.getLogger(__name__)


def split(seq: EurocSequence, vocab: Vocabulary, variant: str, rate_hz: float) -> dict:
    """kbit/s by part of one robot's frames under ``variant``."""
    opts = VARIANTS[variant]
    front_end = FrontEndConfig(carry_track_descriptors=opts["carry_track_descriptors"])
    app = RobotApp(front_end, seq.cam0, seq.imu, vocab)
    enc = app.frame_coder.encoder  # (the front end has no say in the non-keyframe model)
    enc.config = dataclasses.replace(enc.config, track_velocity=opts["track_velocity"])
    kf: collections.Counter[str] = collections.Counter()
    nkf: collections.Counter[str] = collections.Counter()
    imu_bits = n_kf = 0
    n = len(seq.frame_timestamps_ns)
    for frame in seq.frames(0, n):
        msg = app.process(frame.timestamp_ns, frame.image, frame.imu)
        enc = app.frame_coder.encoder
        bits = dict(enc.last_bits, overhead=enc.last_overhead_bits)
        (kf if msg.keyframe else nkf).update(bits)
        n_kf += int(msg.keyframe)
        imu_bits += 8 * len(msg.imu)
    seconds = n / rate_hz
    return {
        "keyframes": n_kf,
        "kf": sum(kf.values()) / seconds / 1e3,
        "kf_parts": {k: v / seconds / 1e3 for k, v in kf.most_common()},
        "nkf": sum(nkf.values()) / seconds / 1e3,
        "nkf_parts": {k: v / seconds / 1e3 for k, v in nkf.most_common()},
        "imu": imu_bits / seconds / 1e3,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, required=True)
    ap.add_argument("--robots", default="", help="comma-separated sequence folders (all)")
    ap.add_argument("--variants", default=",".join(VARIANTS))
    ap.add_argument("--rate-hz", type=float, default=20.0)
    ap.add_argument("--out", type=Path, default=RESULTS / "uplink_split.md")
    args = ap.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s")
    vocab = Vocabulary.load()
    robots = [r for r in args.robots.split(",") if r] or sorted(
        p.name for p in args.data.iterdir() if (p / "mav0").is_dir()
    )
    lines = [
        "| robot | variant | keyframes | keyframes kbit/s | non-keyframes kbit/s | IMU kbit/s |"
        " total kbit/s | keyframe parts | non-keyframe parts |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    t0 = time.perf_counter()
    for robot in robots:
        seq = EurocSequence(args.data / robot)
        for variant in args.variants.split(","):
            s = split(seq, vocab, variant, args.rate_hz)
            total = s["kf"] + s["nkf"] + s["imu"]
            logger.info("%s %s: %.1f kbit/s", robot, variant, total)
            parts = [
                ", ".join(f"{k} {v:.1f}" for k, v in s[p].items())
                for p in ("kf_parts", "nkf_parts")
            ]
            lines.append(
                f"| {robot} | {variant} | {s['keyframes']} | {s['kf']:.1f} | {s['nkf']:.1f} | "
                f"{s['imu']:.1f} | **{total:.1f}** | {parts[0]} | {parts[1]} |"
            )
    text = [
        "# A robot's uplink by part, per codec variant",
        "",
        f"`benchmarks/bench_uplink_split.py --data {args.data} --variants {args.variants}`; "
        f"commit {git_commit()}; {time.perf_counter() - t0:.0f} s. In-process (no edge: the "
        "tracker runs without the edge's IMU feedback, so keyframes can differ by a few from a "
        "live run's). Parts: the codec's information content per model, kbit/s at camera rate.",
        "",
        *lines,
    ]
    args.out.write_text("\n".join(text) + "\n")
    print("\n".join(text))


if __name__ == "__main__":
    main()
