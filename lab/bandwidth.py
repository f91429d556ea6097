"""``recslam experiment bandwidth``: the whole job with the robot→edge links rate-limited.

    recslam experiment bandwidth --data data/synth --budgets unlimited,500,200,100,50

For each budget (kbit/s per robot link, each direction) the cloud, the edge and the robots run
as separate processes (``lab.run.orchestration``), shaped by one of two shapers (``--shaper``):

- ``tbf``: kernel shaping of real TCP. Every robot runs in a network namespace of its own,
  linked to a hub namespace (where the edge and the cloud run) by a veth pair with a ``tbf``
  qdisc on each end (``lab.netns``; the services are started with ``ip netns exec``). Needs
  root and iproute2; nothing is changed in the host's own namespace, and the namespaces are
  deleted afterwards, also after a failure. ``unlimited`` runs in the same namespaces, unshaped.
- ``proxy``: every robot connects to the edge on loopback through its own throttling TCP proxy
  (``sim.faultproxy.FaultProxy`` with ``rate_bytes_per_s``, in a thread of this process): an
  application-level token bucket on the byte stream.

``auto`` (the default) is ``tbf`` where namespaces with tbf can be made, else ``proxy``.

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

import json
import logging
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from common.errors import RecslamError

log = logging.getLogger(__name__)

CAMERA_HZ = 20.0


@dataclass(frozen=True)
class BandwidthConfig:
    """Options of the experiment (built once by the CLI).

    data: dataset folder. budgets: kbit/s per robot link, None = unlimited, run in this order.
    robots: sequence folders to run (empty = all). out: output folder. timeout_s: per run.
    shaper: "proxy" or "tbf" (see the module docstring; :func:`resolve_shaper` turns "auto"
    into one of them).
    """

    data: Path
    budgets: tuple[float | None, ...]
    robots: tuple[str, ...] = ()
    out: Path = Path("out/bandwidth")
    timeout_s: float = 1800.0
    shaper: str = "proxy"

    def __post_init__(self) -> None:
        if self.shaper not in SHAPERS:
            raise RecslamError(f"shaper must be one of {SHAPERS}, got {self.shaper!r}")


SHAPERS = ("proxy", "tbf")


def resolve_shaper(name: str) -> str:
    """``auto`` -> ``tbf`` where network namespaces with tbf can be made here, else
    ``proxy``; ``tbf`` where they cannot -> RecslamError naming why; else ``name``."""
    from sim.netem import shaping_unavailable

    if name == "auto":
        reason = shaping_unavailable()
        if reason is not None:
            log.info("shaper: proxy (kernel tbf in namespaces unavailable: %s)", reason)
        return "proxy" if reason is not None else "tbf"
    if name == "tbf":
        from lab.netns import check_available

        check_available()
    elif name not in SHAPERS:
        raise RecslamError(f"--shaper must be auto, {' or '.join(SHAPERS)}; got {name!r}")
    return name


def parse_budgets(text: str) -> list[float | None]:
    """``"unlimited,500,50"`` -> ``[None, 500.0, 50.0]`` (kbit/s; None = unlimited)."""
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

        from sim.faultproxy import FaultConfig, FaultProxy

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


PEAK_WINDOW_S = 30.0


def peak_rate(samples_path: Path, window_s: float = PEAK_WINDOW_S) -> float | None:
    """The highest robot→edge rate of any robot over any ``window_s`` seconds, kbit/s: the
    bytes the edge received on that robot's link (its counters, protocol headers included)
    between two of its once-a-second stats writes at least ``window_s`` apart, timed by the
    edge's own clock (``edge.time``). Where a link is shaped and has a backlog, this sits at
    the budget; None without two such writes."""
    samples = [json.loads(line) for line in samples_path.read_text().splitlines() if line]
    series: dict[str, list[tuple[float, int]]] = {}
    for s in samples:
        edge = s.get("edge", {})
        if "time" not in edge:
            continue
        for name, link in edge.get("links", {}).items():
            points = series.setdefault(name, [])
            if not points or edge["time"] > points[-1][0]:
                points.append((float(edge["time"]), int(link["rx"]["bytes"])))
    best: float | None = None
    for points in series.values():
        j = 0
        for t0, b0 in points:
            while j < len(points) and points[j][0] - t0 < window_s:
                j += 1
            if j == len(points):
                break
            t1, b1 = points[j]
            rate = 8 * (b1 - b0) / (t1 - t0) / 1000
            best = rate if best is None else max(best, rate)
    return best


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


def run_budget(
    data: Path,
    robots: tuple[str, ...],
    kbit_s: float | None,
    out: Path,
    timeout: float,
    shaper: str = "proxy",
    robot_args: tuple[str, ...] = (),
    edge_args: tuple[str, ...] = (),
    cut: tuple[float, float] | None = None,
) -> dict[str, Any]:
    """One run at ``kbit_s`` (None = unlimited) shaped by ``shaper``; returns its table row.
    ``robot_args`` / ``edge_args``: more arguments for every robot / edge; ``cut``: (at, for)
    seconds after the robots started, every robot link is down (tbf only)."""
    import shutil

    from lab.run.orchestration import JobConfig

    if out.exists():
        shutil.rmtree(out)
    t0 = time.perf_counter()
    if shaper == "tbf":
        from lab.netns import Tbf, star

        names = robots or tuple(sorted(p.parent.name for p in data.glob("*/mav0")))
        with star(names, None if kbit_s is None else Tbf(kbit_s)) as topology:
            config = JobConfig(
                dataset=data,
                run_dir=out / "run",
                robots=robots,
                placement=topology.placement(),
                robot_args=robot_args,
                edge_args=edge_args,
            )
            timers = []
            if cut is not None:
                import threading

                timers = [
                    threading.Timer(cut[0], topology.set_links, (False,)),
                    threading.Timer(cut[0] + cut[1], topology.set_links, (True,)),
                ]
            try:
                stream_s, codes, frames = _run_job(config, timeout, timers)
            finally:
                for timer in timers:
                    timer.cancel()
    else:
        if cut is not None:
            raise RecslamError("a link cut needs the tbf shaper (network namespaces)")
        links = ThrottledLinks(kbit_s)
        try:
            config = JobConfig(
                dataset=data,
                run_dir=out / "run",
                robots=robots,
                robot_links=links.link,
                robot_args=robot_args,
                edge_args=edge_args,
            )
            stream_s, codes, frames = _run_job(config, timeout)
        finally:
            links.close()
    return _row(out, kbit_s, stream_s, time.perf_counter() - t0, codes, frames)


def _run_job(
    config: Any, timeout: float, timers: list[Any] | None = None
) -> tuple[float, dict[str, int], dict[str, int]]:
    """Start the job of ``config`` (and ``timers``, threading.Timers, with the robots), wait
    for the robots and the edge, stop it: the streaming time, the exit codes and the frames
    per robot."""
    from lab.run.orchestration import Job, robot_frames

    with Job(config) as job:
        job.start()
        for timer in timers or ():
            timer.start()
        t_robots = time.perf_counter()
        job.wait_robots(timeout, every_s=0.5)
        stream_s = time.perf_counter() - t_robots
        job.wait_edge_idle()
        codes = job.stop()
        frames = robot_frames(config.dataset, job.robot_names)
    return stream_s, codes, frames


def _row(
    out: Path,
    kbit_s: float | None,
    stream_s: float,
    wall_s: float,
    codes: dict[str, int],
    frames: dict[str, int],
) -> dict[str, Any]:
    from lab.run.report import RunFacts, write_report

    facts = RunFacts(stream_s, wall_s, codes, frames)
    report = write_report(out / "run", out, facts)
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
    row["peak_kbit_s"] = peak_rate(out / "run" / "stats" / "samples.jsonl")
    row.update(freshness(report))
    return row


def recovery_s(series: list[list[float]], reconnect_s: float, bound_s: float = 1.0) -> float | None:
    """How long after ``reconnect_s`` (camera time since the first pose [s]) the pose latency
    came back under ``bound_s`` for good: the camera time of the first pose after which every
    latency is below it, minus ``reconnect_s`` (None: never, or no poses)."""
    if not series:
        return None
    t0 = series[0][0]
    last_bad = reconnect_s
    for t_ns, latency in series:
        t = (t_ns - t0) * 1e-9
        if t >= reconnect_s and latency >= bound_s:
            last_bad = t
    tail = [t for t, _ in series if (t - t0) * 1e-9 > last_bad]
    return None if not tail else (tail[0] - t0) * 1e-9 - reconnect_s


def freshness(report: dict[str, Any]) -> dict[str, Any]:
    """What the fresh-before-complete rules did and what the robots felt, from a run's report:
    frames left out by the uplink budget, dropped by a live robot behind its camera, skipped by
    a late VIO; the pose latency at the robot (the worst robot's median, p95 and max [s]);
    per-frame joint ATE, maps, both directions' rates."""
    rs = report["robots"].values()
    lat = [r["pose_latency_s"] for r in rs if r.get("pose_latency_s", {}).get("p95") is not None]

    def worst(key: str) -> float | None:
        vals = [x[key] for x in lat if x.get(key) == x.get(key)]  # (NaN: no pose)
        return max(vals) if vals else None

    links = report["links"]
    up = [v for k, v in links.items() if not k.endswith("->cloud")]
    return {
        "frames_in": sum(r.get("frames_in") or 0 for r in rs),
        "left_out": sum(r.get("frames_left_out") or 0 for r in rs),
        "dropped_live": sum(r.get("frames_dropped_live") or 0 for r in rs),
        "skipped_stale": sum(r.get("frames_skipped_stale") or 0 for r in rs),
        "kept_on_edge": sum(r.get("keyframes_kept_on_edge") or 0 for r in rs),
        "keyframes_uplinked": sum(r.get("keyframes_uplinked") or 0 for r in rs),
        "poses_received": sum(r.get("poses_received") or 0 for r in rs),
        "latency_median_s": worst("median"),
        "latency_p95_s": worst("p95"),
        "latency_max_s": worst("max"),
        "frames_ate_joint_m": report["ate"].get("frames_joint_rmse_m"),
        "maps": report["map"].get("maps"),
        "down_kbit_s": (sum(v.get("reverse_kbit_s") or 0 for v in up) / len(up) if up else None),
        "to_cloud_kbit_s": sum(
            v.get("kbit_s") or 0 for k, v in links.items() if k.endswith("->cloud")
        ),
    }


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
        "| achieved kbit/s | frame delay mean / max s | KF lag s | streaming s | keyframes "
        f"| peak {PEAK_WINDOW_S:g} s kbit/s |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        budget = "unlimited" if r["budget_kbit_s"] is None else f"{r['budget_kbit_s']:g}"
        lines.append(
            f"| {budget} | {_f(r['ate_joint_m'], '.3f')} | {_f(r['ate_own_mean_m'], '.3f')} | "
            f"{r['frames_sent']} | {r['frames_decoded']} | "
            f"{r['frames_sent'] - r['frames_decoded']} | {_f(r['achieved_kbit_s'], '.1f')} | "
            f"{_f(r['frame_delay_mean_s'], '.1f')} / {_f(r['frame_delay_max_s'], '.1f')} | "
            f"{_f(r['kf_lag_s'], '.1f')} | {r['stream_s']:.0f} | {r['keyframes']} | "
            f"{_f(r.get('peak_kbit_s'), '.1f')} |"
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


def budget_name(kbit_s: float | None) -> str:
    """The run folder's name under ``OUT/``: ``unlimited`` or ``<kbit_s>kbit``."""
    return "unlimited" if kbit_s is None else f"{kbit_s:g}kbit"


def run_bandwidth(
    config: BandwidthConfig, progress: Callable[[str], None] = log.info
) -> tuple[list[dict[str, Any]], str]:
    """Every budget of ``config`` in turn; writes the table files and returns the rows and
    ``bandwidth.md``'s text (``progress`` gets one line before and after each run)."""
    if not config.data.is_dir():
        raise RecslamError(f"--data {config.data}: no such dataset folder (recslam dataset synth)")
    config.out.mkdir(parents=True, exist_ok=True)
    rows = []
    for kbit_s in config.budgets:
        name = budget_name(kbit_s)
        progress(f"== budget {name}")
        t = time.perf_counter()
        row = run_budget(
            config.data, config.robots, kbit_s, config.out / name, config.timeout_s, config.shaper
        )
        rows.append(row)
        progress(f"   done in {time.perf_counter() - t:.0f} s: {row}")
    if config.shaper == "tbf":
        from lab.netns import Tbf

        qdisc = Tbf(1.0)  # the default burst and latency every budget's qdisc has
        shaped = (
            "kernel tbf: each robot in its own network namespace, linked to the namespace of "
            "the edge and the cloud by a veth pair with `tbf rate BUDGET burst "
            f"{qdisc.burst_bytes} latency {qdisc.latency_ms}ms` on both ends (both "
            "directions; `unlimited`: the same namespaces, no qdisc)"
        )
    else:
        shaped = (
            "application-level token bucket (throttling TCP proxy per robot→edge link, both "
            "directions), not kernel tbf"
        )
    note = (
        f"Dataset `{config.data}`, robots {', '.join(config.robots) or 'all'}; {shaped}. "
        "Frame delay = edge decode time − camera time (first decoded frame + i/20 Hz), "
        "sampled once a second; KF lag = last keyframe at the cloud − nominal end of the robots' "
        "streams; peak = the highest rate of any robot's link over any "
        f"{PEAK_WINDOW_S:g} s (the edge's counters and clock)."
    )
    return rows, write_table(rows, config.out, note)
