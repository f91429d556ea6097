"""``recslam experiment``: experiments over the whole system; the logic is in :mod:`lab`.

- ``recslam experiment bandwidth``: ATE, latency and achieved rate with the robot→edge links
  rate-limited (:mod:`lab.bandwidth`).
- ``recslam experiment budget``: the rate–accuracy–latency curve, the recorder against fresh
  before complete (:mod:`lab.budget`).
- ``recslam experiment table3``: keyframes, map points and ATE with and without MBP from a
  recorded run, and loop-detection precision / recall (:mod:`lab.table3`).
- ``recslam experiment links``: the bit budget of every link, raw vs coded wire
  (:mod:`lab.links`).
- ``recslam experiment scale``: the cloud's cost against agents and keyframes, recordings
  replayed as teams to a cloud process on one core (:mod:`lab.scale`).

``recslam experiment EXPERIMENT --help`` describes each one's method and output files.
"""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

from lab import bandwidth, budget
from lab.bandwidth import BandwidthConfig, parse_budgets, resolve_shaper


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "experiment",
        help="experiments over the whole system (bandwidth budgets, MBP table 3)",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    which = p.add_subparsers(dest="experiment", metavar="EXPERIMENT", required=True)
    b = which.add_parser(
        "bandwidth",
        help="ATE, latency and achieved rate against link budget",
        description=bandwidth.__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    b.add_argument("--data", type=Path, default=Path("data/synth"), help="dataset folder")
    b.add_argument(
        "--budgets",
        default="unlimited,500,200,100,50",
        help="comma-separated kbit/s per robot link, or 'unlimited' (default %(default)s)",
    )
    b.add_argument("--robots", default="", help="comma-separated sequence folders (default: all)")
    b.add_argument("--out", type=Path, default=Path("out/bandwidth"), help="output folder")
    b.add_argument("--timeout", type=float, default=1800.0, help="per-run timeout (s)")
    b.add_argument(
        "--shaper",
        choices=("auto", "tbf", "proxy"),
        default="auto",
        help="tbf: kernel tbf on veth pairs, robots in network namespaces (root); proxy: an "
        "application-level token bucket per robot link; auto (default): tbf where namespaces "
        "can be made, else proxy",
    )
    b.set_defaults(func=run)
    g = which.add_parser(
        "budget",
        help="the rate-accuracy-latency curve: recorder vs fresh-before-complete per link rate",
        description=budget.__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    g.add_argument("--data", type=Path, default=Path("data/synth"), help="dataset folder")
    g.add_argument(
        "--rows",
        default="unlimited,unlimited/fresh,50,50/fresh,50/auto,25/fresh",
        help="comma-separated LINK[/fresh|/auto] (default %(default)s)",
    )
    g.add_argument("--robots", default="", help="comma-separated sequence folders (default: all)")
    g.add_argument("--out", type=Path, default=Path("out/budget"), help="output folder")
    g.add_argument("--timeout", type=float, default=1800.0, help="per-run timeout (s)")
    g.add_argument("--shaper", choices=("auto", "tbf", "proxy"), default="auto")
    g.set_defaults(func=run_budget_rows)
    t = which.add_parser(
        "table3",
        help="keyframes, map points and ATE with / without MBP, loop precision / recall, "
        "from a recording (recslam demo --record-uplink)",
    )
    t.add_argument("--recording", type=Path, required=True, help="uplink recording file")
    t.add_argument("--data", type=Path, required=True, help="dataset folder (ground truth)")
    t.add_argument("--out", type=Path, default=Path("out/table3"), help="output folder")
    t.add_argument(
        "--results",
        type=Path,
        default=Path("benchmarks/results"),
        help="also copy table3.md, loop_detection.md and table3.png here "
        "(default %(default)s; '' = no copy)",
    )
    t.add_argument(
        "--camera",
        type=Path,
        default=None,
        help="EuRoC cam0 sensor.yaml of the fallback camera, for robots the recording holds "
        "no calibration of (recordings made before calibrations travelled)",
    )
    t.add_argument("--vocabulary", type=Path, default=None, help="vocabulary file")
    t.add_argument(
        "--solve-latency",
        type=float,
        default=1.0,
        metavar="SCALE",
        help="a solve takes SCALE times its wall time here on the replay's clock, so records "
        "received meanwhile are handled before its result applies, as in the service "
        "(default %(default)s; 0: solves take no time)",
    )
    t.set_defaults(func=run_table3)
    k = which.add_parser(
        "links",
        help="kbit/s per link, direction and message type, bits per message, codec CPU and "
        "ATE: raw vs coded wire, side by side (whole runs)",
        description="Runs the whole job (as 'recslam demo --no-dashboard') per dataset, run "
        "and wire format into OUT/<dataset>/<wire>/run<k>/ and writes OUT/links.md, "
        "links.json and links.png (see lab/links.py). A run takes ~5 min on 2 cores.",
    )
    k.add_argument(
        "--data",
        action="append",
        default=None,
        metavar="DIR[,DIR...]",
        help="dataset folder(s), repeatable or comma-separated (default data/synth)",
    )
    k.add_argument("--runs", type=int, default=1, help="runs per dataset and format (default 1)")
    k.add_argument(
        "--wire", default="raw,coded", help="comma-separated formats (default %(default)s)"
    )
    _whole_run_options(k, "links", 1800.0, "build the tables from")
    k.set_defaults(func=run_links)
    sd = which.add_parser(
        "seeds",
        help="joint / per-robot ATE, maps, merges, loops and failures of the whole job over "
        "the generator's seeds (median and worst against the targets)",
        description="Builds the synthetic dataset of each seed under DATA_ROOT/seed-<s> (once), "
        "runs the whole job (as 'recslam demo --no-dashboard') into OUT/seed-<s>/ and writes "
        "OUT/seeds.md, seeds.json and seeds.png (see lab/seeds.py). With generator options "
        "(--flight, --world, --exposure-steps, --motion-blur-ms) the datasets and runs are "
        "named <tag>-seed-<s>, OUT defaults to out/seeds_hard and the tables are "
        "seeds_hard.*, headed by the generator settings. A 60 s run takes ~4 min on 2 cores, "
        "a dataset ~2 min to build.",
    )
    sd.add_argument("--seeds", default="0-9", help="seeds, e.g. 0-9 or 0,3,7 (default 0-9)")
    sd.add_argument("--robots", type=int, default=3, help="robots per dataset (default 3)")
    sd.add_argument("--seconds", type=float, default=60.0, help="sequence length (default 60)")
    sd.add_argument(
        "--data-root", type=Path, default=Path("data/seeds"), help="where the datasets live"
    )
    sd.add_argument(
        "--flight",
        default="ring",
        help="generator's trajectory family[+modifiers] (as 'recslam dataset synth --flight'; "
        "default ring)",
    )
    sd.add_argument(
        "--world", default="vicon", help="generator's world: vicon (default), room-random, hall"
    )
    sd.add_argument("--exposure-steps", action="store_true", help="generator: exposure steps")
    sd.add_argument("--motion-blur-ms", type=float, default=0.0, help="generator: motion blur [ms]")
    sd.add_argument(
        "--name",
        default="",
        help="base name of the tables (default seeds, or seeds_hard with any generator option)",
    )
    _whole_run_options(sd, "seeds", 2400.0, "report")
    # --out defaults to out/seeds, or out/seeds_hard with a generator option (seeds_config).
    sd.set_defaults(func=run_seeds, out=None)
    sc = which.add_parser(
        "scale",
        help="the cloud's cost against agents and keyframes: recordings replayed as 3, 6, 12, "
        "24 ... agents to a real cloud process on one core (queue, CPU per stage, correction "
        "latency, memory)",
        description="Replays uplink recordings (recslam demo --record-uplink) as teams of "
        "renamed copies, one fake edge per copy, over TCP to a 'recslam cloud' pinned to one "
        "core, and writes scale.md and scale.png (see lab/scale.py). A team takes the "
        "recordings' duration plus the cloud's start and drain.",
    )
    sc.add_argument(
        "--recordings",
        required=True,
        metavar="FILE[,FILE...]",
        help="uplink recordings, comma-separated (e.g. one per seed of the generator)",
    )
    sc.add_argument("--agents", default="3,6,12,24", help="team sizes (default %(default)s)")
    sc.add_argument(
        "--schedule",
        choices=("camera", "recorded"),
        default="camera",
        help="camera: each message at its robot's latest keyframe's camera time (default); "
        "recorded: when the recording's cloud received it",
    )
    sc.add_argument(
        "--shift", type=float, default=5.0, help="time shift per reuse of a recording (s)"
    )
    sc.add_argument("--runs", type=int, default=1, help="live replays per team size")
    sc.add_argument(
        "--work", type=Path, default=Path("out/scale"), help="scratch folder (states, logs)"
    )
    sc.add_argument(
        "--results",
        type=Path,
        default=Path("benchmarks/results"),
        help="where scale.md and scale.png go (default %(default)s)",
    )
    sc.add_argument(
        "--cloud-cpu", default="0", help="taskset -c list of the cloud process ('' = unpinned)"
    )
    sc.add_argument(
        "--replayer-cpu",
        default="1",
        help="CPUs of the replaying process, comma-separated ('' = unpinned)",
    )
    sc.add_argument(
        "--cloud-arg",
        action="append",
        default=[],
        metavar="ARG",
        help="one more 'recslam cloud' argument (repeatable), e.g. --cloud-arg=--no-full-ba",
    )
    sc.add_argument(
        "--core",
        action="store_true",
        help="also replay each team through the cloud's core in-process (CPU per stage on "
        "the same input every time)",
    )
    sc.add_argument(
        "--from-work",
        action="store_true",
        help="do not run: rewrite scale.md and scale.png from --work's scale.json",
    )
    sc.set_defaults(func=run_scale)


def _whole_run_options(
    p: argparse.ArgumentParser, name: str, timeout_s: float, from_runs: str
) -> None:
    """The options of an experiment made of whole runs: ``--out`` (default ``out/NAME``),
    ``--results`` (where NAME.md and NAME.png are copied), ``--rate``, ``--timeout`` and
    ``--from-runs`` (``from_runs``: what it does with the finished runs under ``--out``)."""
    p.add_argument("--out", type=Path, default=Path(f"out/{name}"), help="output folder")
    p.add_argument(
        "--results",
        type=Path,
        default=Path("benchmarks/results"),
        help=f"also copy {name}.md and {name}.png here (default %(default)s; '' = no copy)",
    )
    p.add_argument(
        "--rate", choices=("realtime", "max"), default="realtime", help="robots' playback rate"
    )
    p.add_argument("--timeout", type=float, default=timeout_s, help="per-run timeout (s)")
    p.add_argument(
        "--from-runs",
        action="store_true",
        help=f"do not run: {from_runs} the finished runs already under --out",
    )


def bandwidth_config(args: argparse.Namespace) -> BandwidthConfig:
    """The :class:`lab.bandwidth.BandwidthConfig` of ``recslam experiment bandwidth`` arguments."""
    return BandwidthConfig(
        data=args.data,
        budgets=tuple(parse_budgets(args.budgets)),
        robots=tuple(r for r in args.robots.split(",") if r),
        out=args.out,
        timeout_s=args.timeout,
        shaper=resolve_shaper(args.shaper),
    )


def run(args: argparse.Namespace) -> int:
    """``recslam experiment bandwidth`` (logic in :mod:`lab.bandwidth`)."""
    from lab.bandwidth import run_bandwidth

    rows, table = run_bandwidth(bandwidth_config(args), progress=lambda m: print(m, flush=True))
    print(table)
    return 1 if any(r["failed"] for r in rows) else 0


def run_budget_rows(args: argparse.Namespace) -> int:
    """``recslam experiment budget`` (logic in :mod:`lab.budget`): OUT/budget.md and .png."""
    from lab.budget import parse_rows, plot, run_rows, table

    results = run_rows(
        args.data,
        tuple(r for r in args.robots.split(",") if r),
        parse_rows(args.rows),
        args.out,
        args.timeout,
        resolve_shaper(args.shaper),
        progress=lambda m: print(m, flush=True),
    )
    text = table(results)
    (args.out / "budget.md").write_text(text)
    plot(results, args.out / "budget.png")
    print(text)
    return 1 if any(r["failed"] for r in results) else 0


def run_table3(args: argparse.Namespace) -> int:
    """``recslam experiment table3`` (logic in :mod:`lab.table3`)."""
    from common.errors import RecslamError
    from common.vocabulary import DEFAULT_VOCABULARY_PATH, Vocabulary
    from lab.table3 import run_table3 as table3
    from lab.table3_report import write_table3
    from recslam.commands.cloud import find_camera

    if not args.recording.is_file():
        raise RecslamError(f"--recording {args.recording}: no such file")
    if not args.data.is_dir():
        raise RecslamError(f"--data {args.data}: no such dataset folder")
    camera = find_camera(args.camera, args.data)
    vocab = Vocabulary.load(args.vocabulary or DEFAULT_VOCABULARY_PATH)
    args.out.mkdir(parents=True, exist_ok=True)
    result = table3(
        args.recording,
        args.data,
        camera,
        vocab,
        work_dir=args.out,
        progress=lambda m: print(m, flush=True),
        latency_scale=args.solve_latency,
    )
    results = args.results if str(args.results) not in ("", ".") else None
    files = write_table3(result, args.out, results)
    print((args.out / "table3.md").read_text())
    print((args.out / "loop_detection.md").read_text())
    print("wrote " + ", ".join(str(f) for f in files))
    return 0


def links_config(args: argparse.Namespace, argv: list[str] | None = None):
    """The :class:`lab.links.LinksConfig` of ``recslam experiment links`` arguments."""
    import shlex
    import sys

    from lab.links import LinksConfig, parse_datasets, parse_wires

    words = sys.argv[1:] if argv is None else argv
    return LinksConfig(
        datasets=parse_datasets(args.data or ["data/synth"]),
        out=args.out,
        runs=args.runs,
        wires=parse_wires(args.wire),
        results=args.results if str(args.results) not in ("", ".") else None,
        timeout_s=args.timeout,
        rate=args.rate,
        from_runs=args.from_runs,
        command=shlex.join(["recslam", *words]),
    )


def seeds_config(args: argparse.Namespace, argv: list[str] | None = None):
    """The :class:`lab.seeds.SeedsConfig` of ``recslam experiment seeds`` arguments."""
    import shlex
    import sys

    from lab.seeds import GeneratorOptions, SeedsConfig, parse_seeds

    words = sys.argv[1:] if argv is None else argv
    generator = GeneratorOptions(
        flight=args.flight,
        world=args.world,
        exposure_steps=args.exposure_steps,
        motion_blur_ms=args.motion_blur_ms,
    )
    table = args.name or ("seeds" if generator.is_default else "seeds_hard")
    return SeedsConfig(
        seeds=() if args.from_runs else parse_seeds(args.seeds),
        out=args.out if args.out is not None else Path("out") / table,
        data_root=args.data_root,
        robots=args.robots,
        seconds=args.seconds,
        results=args.results if str(args.results) not in ("", ".") else None,
        rate=args.rate,
        timeout_s=args.timeout,
        from_runs=args.from_runs,
        command="recslam " + shlex.join(words),
        generator=generator,
        name=args.name,
    )


def run_seeds(args: argparse.Namespace) -> int:
    """``recslam experiment seeds`` (logic in :mod:`lab.seeds_run`)."""
    from lab.seeds_run import run_seeds as seeds

    logging.getLogger("lab").setLevel(logging.INFO)  # progress: one line per run step
    config = seeds_config(args)
    return _printed(config.out / f"{config.table_name}.md", *seeds(config))


def run_links(args: argparse.Namespace) -> int:
    """``recslam experiment links`` (logic in :mod:`lab.links_run`)."""
    from lab.links_run import run_links as links

    logging.getLogger("lab").setLevel(logging.INFO)  # progress: one line per run step
    return _printed(args.out / "links.md", *links(links_config(args)))


def _printed(table: Path, data: dict, files: list[Path]) -> int:
    """Print an experiment's table and the files it wrote; exit 1 if a run failed."""
    print(table.read_text())
    print("wrote " + ", ".join(str(f) for f in files))
    return 1 if data["errors"] else 0


def scale_config(args: argparse.Namespace, argv: list[str] | None = None):
    """The :class:`lab.scale.ScaleConfig` and :class:`lab.scale_live.LiveConfig` of
    ``recslam experiment scale`` arguments."""
    import shlex
    import sys

    from lab.scale import ScaleConfig
    from lab.scale_live import LiveConfig

    words = sys.argv[1:] if argv is None else argv
    config = ScaleConfig(
        recordings=tuple(Path(p) for p in args.recordings.split(",") if p),
        agents=tuple(int(a) for a in args.agents.split(",") if a),
        schedule=args.schedule,
        shift_s=args.shift,
        work=args.work,
        out=args.results,
        runs=args.runs,
        command="recslam " + shlex.join(words),
        core=args.core,
    )
    live = LiveConfig(
        cloud_cpu=args.cloud_cpu or None,
        replayer_cpu=tuple(int(c) for c in args.replayer_cpu.split(",") if c) or None,
        cloud_args=tuple(args.cloud_arg),
    )
    return config, live


def run_scale(args: argparse.Namespace) -> int:
    """``recslam experiment scale`` (logic in :mod:`lab.scale_run`)."""
    from lab.scale_run import run_scale as scale

    logging.getLogger("lab").setLevel(logging.INFO)  # progress: one line per team
    config, live = scale_config(args)
    if args.from_work:
        from lab.scale import load_recordings, plan_copies, robots_of
        from lab.scale_report import rows_from_json, write_scale

        rows = rows_from_json(config.work / "scale.json")
        robots = [robots_of(r) for r in load_recordings(config.recordings)]
        plans = [plan_copies(robots, runs[0].agents, config.shift_s) for runs in rows]
        write_scale(config, rows, plans)
    else:
        scale(config, live)
    print((config.out / "scale.md").read_text())
    return 0
