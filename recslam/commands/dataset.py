"""``recslam dataset``: build the synthetic multi-robot dataset, or describe a dataset folder.

``recslam dataset synth --out DIR --robots 3 --seconds 60 --seed 0`` renders the embedded
textured room for every robot and writes ``DIR/robotK/mav0`` (EuRoC layout), ``dataset.json``,
``contact_sheet.png`` and ``trajectories_top.png``; ``--cameras euroc,wide,fisheye`` gives
each robot its own camera preset (default all ``euroc``). ``recslam dataset info PATH`` prints
the facts of a dataset folder (several ``*/mav0`` sequences), of a single EuRoC-layout sequence
(EuRoC, TUM-VI), or of a ROS bag (``.bag`` file or ROS 2 bag folder: topics, message types,
counts, durations and rates).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "dataset",
        help="build the synthetic dataset or describe a dataset folder",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    inner = p.add_subparsers(dest="dataset_command", metavar="{synth,info}")
    inner.required = True
    s = inner.add_parser("synth", help="generate the synthetic multi-robot EuRoC-layout dataset")
    s.add_argument("--out", type=Path, required=True, help="output folder")
    s.add_argument("--robots", type=int, default=3, help="number of robots (default 3)")
    s.add_argument("--seconds", type=float, default=60.0, help="length per robot (default 60)")
    s.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    s.add_argument(
        "--no-noise",
        action="store_true",
        help="noise-free IMU and images (no biases, no read noise)",
    )
    s.add_argument(
        "--cameras",
        default="",
        help="one camera preset per robot, comma-separated, from "
        "euroc (752x480 radtan), wide (640x480 radtan, pitched mount), fisheye (512x512 "
        "equidistant); default all euroc",
    )
    s.add_argument("--no-progress", action="store_true", help="no progress bar")
    s.set_defaults(func=run_synth)
    i = inner.add_parser("info", help="describe a dataset folder, one sequence or a ROS bag")
    i.add_argument("path", type=Path, help="dataset folder (robotK/mav0 ...), sequence, or ROS bag")
    i.add_argument("--json", action="store_true", help="print JSON instead of a table")
    i.set_defaults(func=run_info)


def run_synth(args: argparse.Namespace) -> int:
    from dataclasses import replace

    from common.data.synth import SynthConfig, SynthError, generate_dataset
    from common.folders import FolderError, writable_folder

    try:
        writable_folder(args.out, "--out")
        config = SynthConfig(
            robots=args.robots,
            seconds=args.seconds,
            seed=args.seed,
            progress=not args.no_progress,
            cameras=tuple(c.strip() for c in args.cameras.split(",") if c.strip()),
        )
        if args.no_noise:
            config = replace(
                config,
                imu_noise=replace(config.imu_noise, enabled=False),
                render=replace(config.render, noise_std=0.0),
            )
        summary = generate_dataset(args.out, config)
    except (SynthError, FolderError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    print(f"dataset: {summary.out} ({summary.version}, seed {summary.seed})")
    for s in summary.sequences:
        print(
            f"  {s.name}: {s.frames} frames, {s.imu_samples} IMU samples, "
            f"path {s.path_length_m:.1f} m, max {s.max_speed_mps:.2f} m/s, "
            f"{s.max_rate_radps:.2f} rad/s"
        )
    print(f"wall time {summary.wall_time_s:.1f} s, rendering {summary.render_fps:.1f} frames/s")
    return 0


def run_info(args: argparse.Namespace) -> int:
    import numpy as np

    from common.data.euroc import EurocSequence
    from common.data.rosbag import is_bag
    from common.errors import RecslamError

    root: Path = args.path
    if not root.exists():
        print(f"error: {root}: no such file or folder", file=sys.stderr)
        return 2
    if is_bag(root):
        return _bag_info(root, args.json)
    meta_path = root / "dataset.json"
    meta = json.loads(meta_path.read_text()) if meta_path.is_file() else None
    folders = sorted(p.parent for p in root.glob("*/mav0")) or [root]
    rows = []
    try:
        for folder in folders:
            seq = EurocSequence(folder)
            s = seq.summary()
            gt = seq.groundtruth
            if gt is not None and len(gt) > 1:
                steps = np.diff(gt.p_world_body, axis=0)
                s["path_length_m"] = float(np.linalg.norm(steps, axis=1).sum())
            rows.append(s)
    except RecslamError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    if args.json:
        print(
            json.dumps(
                {
                    "dataset": meta
                    and {k: meta.get(k) for k in ("generator", "robots", "seconds", "seed")},
                    "sequences": rows,
                },
                indent=2,
            )
        )
        return 0
    if meta is not None:
        print(
            f"{root}: {meta.get('generator')} robots={meta.get('robots')} "
            f"seconds={meta.get('seconds')} seed={meta.get('seed')}"
        )
    print(
        f"{'sequence':<12}{'frames':>8}{'cam Hz':>8}{'imu':>8}{'imu Hz':>8}{'secs':>8}"
        f"{'res':>10}{'gt':>7}{'path m':>8}"
    )
    for s in rows:
        res = "x".join(str(v) for v in s["resolution"])
        path = s.get("path_length_m")
        print(
            f"{s['name']:<12}{s['frames']:>8}{s['camera_rate_hz']:>8.1f}{s['imu_samples']:>8}"
            f"{s['imu_rate_hz']:>8.1f}{s['duration_s']:>8.1f}{res:>10}"
            f"{s['groundtruth_samples']:>7}{'-' if path is None else f'{path:.1f}':>8}"
        )
    if len(rows) == 1:
        print(f"calibration: {rows[0]['calibration']}")
    return 0


def _bag_info(path: Path, as_json: bool) -> int:
    from common.data.rosbag import BagError, bag_summary

    try:
        s = bag_summary(path)
    except BagError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    if as_json:
        print(json.dumps(s, indent=2))
        return 0
    print(f"{s['path']}: {s['format']}, {s['messages']} messages, {s['duration_s']:.2f} s")
    print(f"{'topic':<28}{'type':<34}{'messages':>9}{'secs':>8}{'Hz':>8}")
    for t in s["topics"]:
        print(
            f"{t['topic']:<28}{t['type']:<34}{t['messages']:>9}{t['duration_s']:>8.2f}"
            f"{t['rate_hz']:>8.1f}"
        )
    return 0
