"""``recslam dataset``: build the synthetic multi-robot dataset, or describe a dataset folder.

``recslam dataset synth --out DIR --robots 3 --seconds 60 --seed 0`` renders the embedded
textured room for every robot and writes ``DIR/robotK/mav0`` (EuRoC layout), ``dataset.json``,
``contact_sheet.png`` and ``trajectories_top.png``; ``--cameras euroc,wide,fisheye`` gives
each robot its own camera preset (default all ``euroc``). Harder worlds (issue 17):
``--flight figure8+aggressive`` (families ring, figure8, lawnmower, inward, vertical; modifiers
+hover, +aggressive), ``--world hall`` (vicon, room-random, hall), ``--trajectory FILE[,FILE]``
(fly recorded TUM / EuRoC ground truths, one per robot) with ``--imu FILE[,FILE]`` (the IMU
recorded on each flight instead of a simulated one), ``--time-offset-ms MS`` (an
unsynchronised camera and IMU), ``--exposure-steps`` and
``--motion-blur-ms MS``; ``dataset.json`` records them. ``recslam dataset info PATH`` prints
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
    s.add_argument(
        "--robots",
        type=int,
        default=None,
        help="number of robots (default 3, or one per --trajectory file)",
    )
    s.add_argument("--seconds", type=float, default=60.0, help="length per robot (default 60)")
    s.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    s.add_argument(
        "--scene-seed",
        type=int,
        default=None,
        metavar="N",
        help="seed of the room's look (textures, posters, room-random's furniture) instead of "
        "--seed: datasets of one scene seed and other seeds fly through the same room (e.g. a "
        "second mission in the first one's saved map); default: --seed",
    )
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
    s.add_argument(
        "--flight",
        default="ring",
        metavar="FAMILY[+MODIFIER...]",
        help="trajectory family: ring (default: loops looking outward), figure8, lawnmower, "
        "inward (looking at the room's centre), vertical (up-and-down sweeps); modifiers "
        "+hover (a few seconds nearly still first, as in EuRoC), +aggressive (bursts up to "
        "~2 m/s and ~2.5 rad/s); e.g. figure8+aggressive",
    )
    s.add_argument(
        "--world",
        default="vicon",
        help="scene: vicon (default, the 8 x 7 m room), room-random (that room with "
        "furniture drawn per seed), hall (a 20 x 16 x 8 m machine hall)",
    )
    s.add_argument(
        "--trajectory",
        default="",
        metavar="FILE[,FILE...]",
        help="fly recorded ground truths instead of a family, one file per robot: TUM "
        "(t x y z qx qy qz qw) or EuRoC state_groundtruth_estimate0/data.csv; smoothed by "
        "quintic smoothing splines, recentred in the world",
    )
    s.add_argument(
        "--imu",
        default="",
        metavar="FILE[,FILE...]",
        help="fly the IMU recorded on each --trajectory flight instead of a simulated one, one "
        "EuRoC imu0/data.csv per trajectory file, on the ground truth's clock (real biases, "
        "vibration and timing); dataset.json says so",
    )
    s.add_argument(
        "--time-offset-ms",
        type=float,
        default=0.0,
        metavar="MS",
        help="an unsynchronised camera and IMU: the IMU clock runs MS ahead of the camera's "
        "(t_imu = t_cam + MS, as OpenVINS' calib_camimu_dt); default 0",
    )
    s.add_argument(
        "--exposure-steps",
        action="store_true",
        help="auto-exposure steps: the gain jumps every 1.5-4 s by x0.5-2 (within 0.4-2)",
    )
    s.add_argument(
        "--motion-blur-ms",
        type=float,
        default=0.0,
        metavar="MS",
        help="exposure time [ms] for motion blur: the mean of sub-renders over the exposure "
        "(one per 2 ms, 2 to 9); default 0 (none)",
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
    from common.data.synth.render import EffectsConfig
    from common.folders import FolderError, writable_folder

    files = tuple(f.strip() for f in args.trajectory.split(",") if f.strip())
    try:
        writable_folder(args.out, "--out")
        robots = args.robots if args.robots is not None else (len(files) or 3)
        if files and len(files) != robots:
            raise SynthError(
                f"--trajectory gives {len(files)} files for --robots {robots}: one per robot"
            )
        config = SynthConfig(
            robots=robots,
            seconds=args.seconds,
            seed=args.seed,
            scene_seed=args.scene_seed,
            progress=not args.no_progress,
            cameras=tuple(c.strip() for c in args.cameras.split(",") if c.strip()),
            flight=args.flight,
            world=args.world,
            trajectory_files=files,
            imu_files=tuple(f.strip() for f in args.imu.split(",") if f.strip()),
            time_offset_ms=args.time_offset_ms,
            effects=EffectsConfig(
                exposure_steps=args.exposure_steps, motion_blur_ms=args.motion_blur_ms
            ),
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
    print(f"  {describe_harder(config.harder())}")
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
                    and {k: meta.get(k) for k in ("generator", "robots", "seconds", "seed")}
                    | {"harder": harder_of(meta)},
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
        print(f"  {describe_harder(harder_of(meta))}")
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


def harder_of(meta: dict) -> dict:
    """The issue-17 options of a ``dataset.json`` (their defaults where it states none)."""
    from common.data.synth.generate import DEFAULT_HARDER

    return DEFAULT_HARDER | meta.get("harder", {})


def describe_harder(h: dict) -> str:
    """One line: flight (or the recorded files), world, exposure steps, motion blur."""
    flight = f"flight {h['flight']}"
    if h["trajectory_files"]:
        flight = "recorded flights " + ", ".join(h["trajectory_files"])
    steps = "exposure steps" if h["exposure_steps"] else "no exposure steps"
    blur = f"motion blur {h['motion_blur_ms']:g} ms" if h["motion_blur_ms"] else "no motion blur"
    imu = "recorded IMU " + ", ".join(h["imu_files"]) if h.get("imu_files") else "simulated IMU"
    if h.get("time_offset_ms"):
        imu += f", IMU clock {h['time_offset_ms']:g} ms ahead of the camera's"
    return f"{flight}, world {h['world']}, {steps}, {blur}, {imu}"


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
