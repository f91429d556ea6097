"""``recslam experiment bandwidth``: the whole job with the robot→edge links rate-limited.

(``recslam experiment table3``: keyframes, map points and ATE with and without MBP from a
recorded run, and loop-detection precision / recall; see :mod:`lab.table3`.
``recslam experiment links``: the bit budget of every link, raw vs coded wire; see
:mod:`lab.links`.)

    recslam experiment bandwidth --data data/synth --budgets unlimited,500,200,100,50

For each budget (kbit/s per robot link, each direction) the cloud, the edge and the robots run
as separate processes (``recslam.orchestration``); every robot connects to the edge through
its own throttling TCP proxy (``common.faultproxy.FaultProxy`` with ``rate_bytes_per_s``, in a
thread of this process): an application-level token bucket on the byte stream. Kernel ``tbf``
shaping in network namespaces (``common.netem``) is not used by this command: the services
would have to run inside the namespaces; see docs/deployment.md for tc-netem with Docker.

Below the robots' data rate nothing is lost — the robots' outboxes absorb the backlog (up to
``recslam robot --backlog-minutes``) and frames arrive late. Per budget the table gives:

- ATE: joint RMSE (cloud's report) and the mean of the per-robot RMSEs (own alignment), m
- frames sent / decoded at the edge (lost = sent - decoded)
- achieved robot→edge rate: bytes received from all robots / streaming time / robots, kbit/s
- frame delay: when the edge decoded frame i, minus when the camera took it (first decoded
  frame + i / 20 Hz), from the edge's once-a-second counters; mean and max over frames, s
- KF lag: last keyframe at the cloud minus the robots' nominal end of stream, s

Writes ``OUT/bandwidth.md``, ``bandwidth.json`` and ``bandwidth.png``; each run's folder and
report under ``OUT/<budget>/``.
"""

from __future__ import annotations

import argparse
import json
import logging
import time
from pathlib import Path
from typing import Any

log = logging.getLogger(__name__)

CAMERA_HZ = 20.0


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "experiment",
        help="experiments over the whole system (bandwidth budgets, MBP table 3)",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    which = p.add_subparsers(dest="experiment", metavar="EXPERIMENT", required=True)
    b = which.add_parser("bandwidth", help="ATE, latency and achieved rate against link budget")
    b.add_argument("--data", type=Path, default=Path("data/synth"), help="dataset folder")
    b.add_argument(
        "--budgets",
        default="unlimited,500,200,100,50",
        help="comma-separated kbit/s per robot link, or 'unlimited' (default %(default)s)",
    )
    b.add_argument("--robots", default="", help="comma-separated sequence folders (default: all)")
    b.add_argument("--out", type=Path, default=Path("out/bandwidth"), help="output folder")
    b.add_argument("--timeout", type=float, default=1800.0, help="per-run timeout (s)")
    b.set_defaults(func=run)
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
    t.add_argument("--camera", type=Path, default=None, help="EuRoC cam0 sensor.yaml")
    t.add_argument("--vocabulary", type=Path, default=None, help="vocabulary file")
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
    k.add_argument("--out", type=Path, default=Path("out/links"), help="output folder")
    k.add_argument(
        "--results",
        type=Path,
        default=Path("benchmarks/results"),
        help="also copy links.md and links.png here (default %(default)s; '' = no copy)",
    )
    k.add_argument(
        "--rate", choices=("realtime", "max"), default="realtime", help="robots' playback rate"
    )
    k.add_argument("--timeout", type=float, default=1800.0, help="per-run timeout (s)")
    k.add_argument(
        "--from-runs",
        action="store_true",
        help="do not run: build the tables from the finished runs already under --out",
    )
    k.set_defaults(func=run_links)


def parse_budgets(text: str) -> list[float | None]:
    """``"unlimited,500,50"`` -> ``[None, 500.0, 50.0]`` (kbit/s; None = unlimited)."""
    from common.errors import RecslamError

    out: list[float | None] = []
    for item in text.split(","):
        item = item.strip().lower()
        if item in ("unlimited", "inf", "none"):
            out.append(None)
            continue
        try:
            value = float(item)
        except ValueError:
            raise RecslamError(f"--budgets: {item!r} is not a number or 'unlimited'") from None
        if value <= 0:
            raise RecslamError(f"--budgets: {item!r} must be positive")
        out.append(value)
    return out


class ThrottledLinks:
    """One throttling FaultProxy per robot, served by an asyncio loop in a thread."""

    def __init__(self, kbit_s: float | None) -> None:
        import asyncio
        import threading

        self.kbit_s = kbit_s
        self.loop = asyncio.new_event_loop()
        self.thread = threading.Thread(target=self.loop.run_forever, daemon=True)
        self.thread.start()
        self.proxies: list[Any] = []

    def link(self, robot: str, edge_port: int) -> int:
        """Start a proxy to the edge for ``robot``; returns its port (JobConfig.robot_links)."""
        import asyncio

        from common.faultproxy import FaultConfig, FaultProxy

        if self.kbit_s is None:
            return edge_port
        # Small pieces: the proxy sleeps per forwarded piece, so a 64 KiB read forwarded whole
        # would arrive after 10 s of silence at 50 kbit/s (and trip the peers' timeouts).
        config = FaultConfig(rate_bytes_per_s=self.kbit_s * 1000.0 / 8.0, max_write_bytes=1460)
        proxy = FaultProxy("127.0.0.1", edge_port, config)
        _, port = asyncio.run_coroutine_threadsafe(proxy.start(), self.loop).result(10)
        self.proxies.append(proxy)
        log.info("%s: %g kbit/s proxy on port %d", robot, self.kbit_s, port)
        return port

    def close(self) -> None:
        import asyncio

        for proxy in self.proxies:
            asyncio.run_coroutine_threadsafe(proxy.close(), self.loop).result(10)
        self.loop.call_soon_threadsafe(self.loop.stop)
        self.thread.join(10)
        self.loop.close()


def timing(samples_path: Path, frames: dict[str, int]) -> dict[str, Any]:
    """Frame delays and the last keyframe's lag from ``stats/samples.jsonl`` (see docstring)."""
    samples = [json.loads(line) for line in samples_path.read_text().splitlines() if line]
    delays: list[float] = []
    first_times = []
    for name, n in frames.items():
        series = [
            (s["time"], s["edge"]["robots"][name]["frames_decoded"])
            for s in samples
            if name in s["edge"].get("robots", {})
        ]
        if not series:
            continue
        t0 = next(t for t, f in series if f > 0)
        first_times.append(t0)
        for i in range(n):
            t = next((t for t, f in series if f > i), None)
            if t is not None:
                delays.append(t - (t0 + i / CAMERA_HZ))
    kf = [(s["time"], s["cloud"].get("keyframes", 0)) for s in samples]
    last_kf = max((c for _, c in kf), default=0)
    t_last = next((t for t, c in kf if c == last_kf), None)
    end = (min(first_times) + max(frames.values()) / CAMERA_HZ) if first_times else None
    return {
        "frame_delay_mean_s": sum(delays) / len(delays) if delays else None,
        "frame_delay_max_s": max(delays) if delays else None,
        "kf_lag_s": (t_last - end) if t_last is not None and end is not None else None,
    }


def run_budget(data: Path, robots: tuple[str, ...], kbit_s: float | None, out: Path,
               timeout: float) -> dict[str, Any]:  # fmt: skip
    """One run at ``kbit_s`` (None = unlimited); returns its table row."""
    import shutil

    from recslam.orchestration import Job, JobConfig, robot_frames
    from recslam.report import RunFacts, write_report

    if out.exists():
        shutil.rmtree(out)
    links = ThrottledLinks(kbit_s)
    try:
        config = JobConfig(dataset=data, run_dir=out / "run", robots=robots,
                           robot_links=links.link)  # fmt: skip
        t0 = time.perf_counter()
        with Job(config) as job:
            job.start()
            t_robots = time.perf_counter()
            job.wait_robots(timeout, every_s=0.5)
            stream_s = time.perf_counter() - t_robots
            job.wait_edge_idle()
            codes = job.stop()
            frames = robot_frames(data, job.robot_names)
    finally:
        links.close()
    report = write_report(out / "run", out, RunFacts(stream_s, time.perf_counter() - t0, codes,
                                                    frames))  # fmt: skip
    rs = report["robots"]
    own = [r["ate_rmse_m"] for r in rs.values() if r["ate_rmse_m"] is not None]
    robot_links = [v for k, v in report["links"].items() if not k.endswith("->cloud")]
    row = {
        "budget_kbit_s": kbit_s,
        "ate_joint_m": report["ate"]["joint_rmse_m"],
        "ate_own_mean_m": sum(own) / len(own) if own else None,
        "frames_sent": sum(r["frames_sent"] for r in rs.values()),
        "frames_decoded": sum(r["frames_decoded"] for r in rs.values()),
        "achieved_kbit_s": (
            sum(v["kbit_s"] for v in robot_links) / len(robot_links) if robot_links else None
        ),
        "stream_s": stream_s,
        "keyframes": report["map"]["keyframes_after_mbp"],
        "failed": report["failed"],
    }
    row.update(timing(out / "run" / "stats" / "samples.jsonl", frames))
    return row


def _f(x: Any, spec: str) -> str:
    return "–" if x is None else format(x, spec)


def write_table(rows: list[dict[str, Any]], out: Path, note: str) -> str:
    """``bandwidth.md`` text, plus ``bandwidth.json`` and ``bandwidth.png`` in ``out``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    lines = [
        "# Bandwidth experiment",
        "",
        note,
        "",
        "| budget kbit/s | ATE joint m | ATE per robot (mean) m | frames sent | decoded | lost "
        "| achieved kbit/s | frame delay mean / max s | KF lag s | streaming s | keyframes |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        budget = "unlimited" if r["budget_kbit_s"] is None else f"{r['budget_kbit_s']:g}"
        lines.append(
            f"| {budget} | {_f(r['ate_joint_m'], '.3f')} | {_f(r['ate_own_mean_m'], '.3f')} | "
            f"{r['frames_sent']} | {r['frames_decoded']} | "
            f"{r['frames_sent'] - r['frames_decoded']} | {_f(r['achieved_kbit_s'], '.1f')} | "
            f"{_f(r['frame_delay_mean_s'], '.1f')} / {_f(r['frame_delay_max_s'], '.1f')} | "
            f"{_f(r['kf_lag_s'], '.1f')} | {r['stream_s']:.0f} | {r['keyframes']} |"
        )
    text = "\n".join(lines) + "\n"
    (out / "bandwidth.md").write_text(text)
    (out / "bandwidth.json").write_text(json.dumps(rows, indent=2))

    limited = [r for r in rows if r["budget_kbit_s"] is not None]
    fig, axes = plt.subplots(1, 3, figsize=(13, 3.8))
    xs = [r["budget_kbit_s"] for r in limited]
    for ax, key, label in (
        (axes[0], "ate_own_mean_m", "ATE per robot, mean (m)"),
        (axes[1], "frame_delay_max_s", "max frame delay (s)"),
        (axes[2], "achieved_kbit_s", "achieved rate per robot (kbit/s)"),
    ):
        ax.plot(xs, [r[key] for r in limited], "o-", label="limited")
        base = [r[key] for r in rows if r["budget_kbit_s"] is None and r[key] is not None]
        if base:
            ax.axhline(base[0], color="grey", ls="--", label="unlimited")
        ax.set_xscale("log")
        ax.set_xlabel("budget per robot link (kbit/s)")
        ax.set_ylabel(label)
        ax.legend()
    axes[2].plot(xs, xs, ":", color="k", label="budget")
    fig.tight_layout()
    fig.savefig(out / "bandwidth.png", dpi=110)
    plt.close(fig)
    return text


def run(args: argparse.Namespace) -> int:
    from common.errors import RecslamError

    budgets = parse_budgets(args.budgets)
    if not args.data.is_dir():
        raise RecslamError(f"--data {args.data}: no such dataset folder (recslam dataset synth)")
    robots = tuple(r for r in args.robots.split(",") if r)
    args.out.mkdir(parents=True, exist_ok=True)
    rows = []
    for kbit_s in budgets:
        name = "unlimited" if kbit_s is None else f"{kbit_s:g}kbit"
        print(f"== budget {name}", flush=True)
        t = time.perf_counter()
        row = run_budget(args.data, robots, kbit_s, args.out / name, args.timeout)
        rows.append(row)
        print(f"   done in {time.perf_counter() - t:.0f} s: {row}", flush=True)
    note = (
        f"Dataset `{args.data}`, robots {', '.join(robots) or 'all'}; application-level token "
        "bucket (throttling TCP proxy per robot→edge link, both directions), not kernel tbf. "
        "Frame delay = edge decode time − camera time (first decoded frame + i/20 Hz), sampled "
        "once a second; KF lag = last keyframe at the cloud − nominal end of the robots' "
        "streams."
    )
    print(write_table(rows, args.out, note))
    return 1 if any(r["failed"] for r in rows) else 0


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
    result = table3(args.recording, args.data, camera, vocab, work_dir=args.out,
                    progress=lambda m: print(m, flush=True))  # fmt: skip
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


def run_links(args: argparse.Namespace) -> int:
    """``recslam experiment links`` (logic in :mod:`lab.links`)."""
    from lab.links import run_links as links

    logging.getLogger("lab").setLevel(logging.INFO)  # progress: one line per run step
    data, files = links(links_config(args))
    print((args.out / "links.md").read_text())
    print("wrote " + ", ".join(str(f) for f in files))
    return 1 if data["errors"] else 0
