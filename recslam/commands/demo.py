"""``recslam demo`` — the main job behind the README's first command.

Builds the embedded synthetic multi-robot dataset (if missing, or if ``--robots``,
``--seconds``, ``--seed`` or ``--cameras`` ask for other settings than an existing one was
made with: without them an existing dataset is used as it is;
a ``--data`` folder of downloaded sequences, e.g. EuRoC ``MH_01_easy/mav0``..., is used as
is, one robot per sequence),
starts the cloud, the edge (``--edges N`` or ``--sites``: several, each robot on one of them;
``--move`` hands a robot over to another edge mid-run) and one robot process per sequence on
loopback (free ports, a
generated secret), shows progress every few seconds, prints the dashboard URL, waits for the
robots to finish, lets the edge and cloud drain, stops them (SIGTERM: the cloud writes its
trajectories and ATE report) and writes the report folder::

    OUT/report.md, report.json, trajectories_*.png, ate_over_time.png
    OUT/run/  logs/, stats/, state/, results/ (see lab.run.orchestration)

With --resume-map PREV (the --out folder of an earlier demo), the cloud starts from a copy of
PREV's saved map (PREV/run/state/cloud, left as it is) as a new mission: the robots relocalise
against it and merge into it, the report says when each merged and gives the joint ATE in
PREV's frame (under PREV's alignment, PREV/run/results/eval/ate.json). Give it a dataset of
the same room, e.g. another seed: ``recslam demo --data data/synth2 --seed 2 --out out/m2
--resume-map out/demo``.

Exit code 0 when every service exited cleanly, 1 otherwise.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from common.links import WireFormat
from services.cloud import runner as cloud
from services.edge import runner as edge


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "demo",
        help="build the synthetic dataset (if missing) and run the main job",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--data", type=Path, default=Path("data/synth"), help="dataset folder")
    p.add_argument(
        "--robots",
        type=int,
        default=None,
        help="number of robots of the synthetic dataset (default: an existing dataset's, 3 "
        "for a new one)",
    )
    p.add_argument(
        "--seconds",
        type=float,
        default=None,
        help="sequence length (default: an existing dataset's, 60 for a new one)",
    )
    p.add_argument(
        "--seed",
        type=int,
        default=None,
        help="random seed (default: an existing dataset's, 0 for a new one)",
    )
    p.add_argument(
        "--cameras",
        default="",
        help="one camera preset per robot for the synthetic dataset, comma-separated, from "
        "euroc, wide, fisheye (e.g. euroc,wide,fisheye: a mixed team); default: an existing "
        "dataset's cameras, all euroc for a new one",
    )
    p.add_argument(
        "--edges",
        type=int,
        default=1,
        metavar="N",
        help="number of edges (sites), robots assigned round-robin (default 1)",
    )
    p.add_argument(
        "--sites",
        default=None,
        metavar="EDGE=ROBOT,...;EDGE=...",
        help="which edge serves which robots, e.g. 'edgeA=robot0,robot1;edgeB=robot2' "
        "(instead of --edges)",
    )
    p.add_argument(
        "--move",
        action="append",
        default=[],
        metavar="ROBOT@FRAME=EDGE",
        help="from frame FRAME on, ROBOT ends its session with its edge and continues with EDGE "
        "(repeat)",
    )
    p.add_argument(
        "--restart-edge",
        action="append",
        default=[],
        metavar="EDGE@SECONDS",
        help="fault drill: SIGKILL edge EDGE this many seconds after the robots started and "
        "restart it on its state directory (repeat)",
    )
    p.add_argument("--out", type=Path, default=Path("out/demo"), help="report folder")
    p.add_argument(
        "--resume-map",
        type=Path,
        default=None,
        metavar="PREV",
        help="start inside the map an earlier demo left (its --out folder): a new mission "
        "whose robots merge into that map (default: a fresh map)",
    )
    p.add_argument(
        "--mission",
        default=None,
        metavar="NAME",
        help="the new mission's name with --resume-map (default: the --out folder's name)",
    )
    cloud.add_dashboard_argument(p)
    p.add_argument("--no-dashboard", action="store_true", help="do not serve the dashboard")
    p.add_argument(
        "--rate", choices=("realtime", "max"), default="realtime", help="robots' playback rate"
    )
    p.add_argument("--timeout", type=float, default=1800.0, help="give up after this many seconds")
    # The cloud's and the edge's own options, passed on to the services this demo starts.
    cloud.add_map_arguments(p)
    cloud.add_record_argument(p, "--record-uplink")
    edge.add_wire_argument(p)
    edge.add_time_offset_arguments(p)
    p.set_defaults(func=run)


def _cameras(text: str) -> tuple[str, ...]:
    return tuple(c.strip() for c in text.split(",") if c.strip())


NEW_DATASET = {"robots": 3, "seconds": 60.0, "seed": 0}
"""The settings of a synthetic dataset ``recslam demo`` builds where none exists."""


def _dataset_matches(
    folder: Path,
    robots: int | None,
    seconds: float | None,
    seed: int | None,
    cameras: tuple[str, ...] | None = None,
) -> bool:
    """Whether ``folder`` holds a synthetic dataset built with these settings; a setting that
    is None (not given on the command line) matches any value, so an existing dataset is
    reused as it is unless the command asks for something else."""
    from common.data.synth import dataset_settings

    have = dataset_settings(folder)
    if have is None:
        return False
    want = {"robots": robots, "seconds": seconds, "seed": seed, "cameras": cameras}
    return all(v is None or have[k] == v for k, v in want.items())


def build_dataset(args: argparse.Namespace) -> None:
    """Build (if needed) and summarise the synthetic dataset."""
    from common.data.euroc import EurocSequence
    from common.data.synth import SynthConfig, dataset_settings, generate_dataset

    start = time.perf_counter()
    cameras = _cameras(args.cameras)
    if _dataset_matches(args.data, args.robots, args.seconds, args.seed, cameras or None):
        print(f"dataset: {args.data} (already built with these settings)")
    elif not (args.data / "dataset.json").exists() and any(args.data.glob("*/mav0")):
        print(f"dataset: {args.data} (not synthetic: every */mav0 sequence is a robot)")
    else:
        given = {"robots": args.robots, "seconds": args.seconds, "seed": args.seed}
        want = {k: NEW_DATASET[k] if v is None else v for k, v in given.items()}
        which = f", cameras {','.join(cameras)}" if cameras else ""
        old = dataset_settings(args.data)
        if old is not None:  # asked for other settings than the dataset there was built with
            print(
                f"dataset: {args.data} holds {old['robots']} robots x {old['seconds']:g} s "
                f"(seed {old['seed']}); replacing it as asked"
            )
        print(
            f"dataset: building {want['robots']} robots x {want['seconds']:g} s "
            f"(seed {want['seed']}{which})"
        )
        config = SynthConfig(
            robots=int(want["robots"]),
            seconds=float(want["seconds"]),
            seed=int(want["seed"]),
            cameras=cameras,
        )
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
    print(f"dataset ready in {built:.1f} s\n", flush=True)


def run(args: argparse.Namespace) -> int:
    import shutil

    from lab.run.orchestration import JobConfig, progress_line, run_and_report
    from lab.run.sites import parse_move, parse_restart, parse_sites

    start = time.perf_counter()
    prior = None
    if args.resume_map is not None:
        prior = args.resume_map / "run"
        if not (prior / "state" / "cloud" / "cloud.sqlite").is_file():
            print(f"--resume-map {args.resume_map}: no saved map (run/state/cloud/cloud.sqlite)")
            return 2
        if args.resume_map.resolve() == args.out.resolve():
            print("--resume-map: give the new mission another --out folder than the old one's")
            return 2
    build_dataset(args)
    run_dir = args.out / "run"
    if run_dir.exists():
        shutil.rmtree(run_dir)
    mission = prior_frame = None
    if prior is not None:
        shutil.copytree(prior / "state" / "cloud", run_dir / "state" / "cloud")
        mission = args.mission or args.out.resolve().name
        ate = prior / "results" / "eval" / "ate.json"
        prior_frame = ate.resolve() if ate.is_file() else None
        print(f"starting mission {mission!r} inside the map of {args.resume_map}")
    port = 0 if args.no_dashboard else args.dashboard_port
    record = args.record_uplink.resolve() if args.record_uplink is not None else None
    config = JobConfig(
        dataset=args.data,
        run_dir=run_dir,
        dashboard_port=port,
        rate=args.rate,
        record_uplink=record,
        mbp=args.mbp,
        mbp_every=args.mbp_every,
        early_loop_candidates=args.early_loop_candidates,
        wire=WireFormat(args.wire),
        time_offset_ms=args.time_offset_ms,
        offset_wait_s=args.offset_wait,
        edges=args.edges,
        sites=parse_sites(args.sites) if args.sites else None,
        moves=tuple(parse_move(m) for m in args.move),
        edge_restarts=tuple(parse_restart(r) for r in args.restart_edge),
        mission=mission,
        prior_frame=prior_frame,
    )
    last_print = [0.0]

    def progress(sample: dict, elapsed: float) -> None:
        if elapsed - last_print[0] >= 5.0:
            last_print[0] = elapsed
            print(progress_line(sample, elapsed), flush=True)

    def say(line: str) -> None:
        print(line, flush=True)

    data = run_and_report(config, args.out, args.timeout, progress, say)
    print()
    print((args.out / "report.md").read_text())
    print(f"report: {args.out / 'report.md'} (total {time.perf_counter() - start:.0f} s)")
    if data["failed"]:
        print(f"failed services: {', '.join(data['failed'])}")
        return 1
    return 0
