"""``recslam demo`` — the main job behind the README's first command.

Today it builds the embedded synthetic multi-robot dataset (if missing or made with other
settings) and prints its summary. The full robot→edge→cloud run grows into this command as the
services land.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "demo",
        help="build the synthetic dataset (if missing) and run the main job",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--data", type=Path, default=Path("data/synth"), help="dataset folder")
    p.add_argument("--robots", type=int, default=3, help="number of robots (default 3)")
    p.add_argument("--seconds", type=float, default=60.0, help="sequence length (default 60)")
    p.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    p.set_defaults(func=run)


def _dataset_matches(folder: Path, robots: int, seconds: float, seed: int) -> bool:
    meta = folder / "dataset.json"
    if not meta.is_file():
        return False
    info = json.loads(meta.read_text())
    return (
        info.get("robots") == robots
        and float(info.get("seconds", -1)) == seconds
        and info.get("seed") == seed
    )


def run(args: argparse.Namespace) -> int:
    from common.data.euroc import EurocSequence
    from common.data.synth import SynthConfig, generate_dataset

    start = time.perf_counter()
    if _dataset_matches(args.data, args.robots, args.seconds, args.seed):
        print(f"dataset: {args.data} (already built with these settings)")
    else:
        print(f"dataset: building {args.robots} robots x {args.seconds:g} s (seed {args.seed})")
        config = SynthConfig(robots=args.robots, seconds=args.seconds, seed=args.seed)
        generate_dataset(args.data, config)
    built = time.perf_counter() - start

    robots = sorted(p.parent for p in args.data.glob("*/mav0"))
    print(f"\n{'robot':<10}{'frames':>8}{'seconds':>9}{'imu':>8}{'path m':>9}  ground truth")
    for folder in robots:
        seq = EurocSequence(folder)
        s = seq.summary()
        gt = seq.groundtruth
        path_m = 0.0
        if gt is not None:
            path_m = float(
                sum(((gt.p_world_body[1:] - gt.p_world_body[:-1]) ** 2).sum(axis=1) ** 0.5)
            )
        has_gt = "yes" if gt is not None else "no"
        print(
            f"{folder.name:<10}{s['frames']:>8}{s['duration_s']:>9.1f}{s['imu_samples']:>8}"
            f"{path_m:>9.1f}  {has_gt}"
        )
    for name in ("contact_sheet.png", "trajectories_top.png"):
        if (args.data / name).is_file():
            print(f"plot: {args.data / name}")
    print(f"\ndone in {built:.1f} s")
    return 0
