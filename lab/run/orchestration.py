"""Process supervision for a whole run: cloud, edges and N robots as separate processes.

Used by ``recslam demo``, ``recslam experiment`` and the end-to-end tests. Everything runs on
loopback with free ports and a freshly generated shared secret (a 0600 file in the run
folder). Each service writes its log to ``RUN_DIR/logs/<name>.log``; the edges and the cloud
also rewrite their counters every second (``--stats-out``, ``RUN_DIR/stats/cloud.json`` and
:func:`edge_stats_name` per edge), which is where progress and bandwidth come from.

Sites: one edge named ``edge`` by default; ``edges=N`` starts ``edge0``..``edgeN-1`` with the
robots assigned round-robin, ``sites`` names the edges and their robots (``parse_sites``:
``edgeA=robot0,robot1;edgeB=robot2``). ``moves`` hands a robot over to another edge at a frame
(``recslam robot --handover``). Each edge has its own port, key file, state directory and log;
they all reach the one cloud, which keeps their agents apart by (edge, robot, edge map).

Run folder layout::

    RUN_DIR/keys/             operator secret and one key file per process (0600)
    RUN_DIR/logs/*.log        one log per process (stdout + stderr)
    RUN_DIR/stats/*.json      edge and cloud counters (last sample), stats/samples.jsonl history
    RUN_DIR/state/<edge>, state/cloud the services' state directories
    RUN_DIR/results/          the cloud's trajectories/ and eval/ (written at its exit)
"""

from __future__ import annotations

import json
import logging
import os
import re
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from common.errors import RecslamError
from common.links import WireFormat
from common.protocol.credentials import issue_keys
from lab.run.sites import SINGLE_EDGE, assign_sites, edge_stats_name, merge_edge_stats

log = logging.getLogger(__name__)


class OrchestrationError(RecslamError):
    """A service did not start, or failed."""


def free_port() -> int:
    """A TCP port on 127.0.0.1 that was free a moment ago."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@dataclass(frozen=True)
class Placement:
    """Where the processes of a run live, when not all on this host's loopback.

    Attributes:
        prefix: service name ("cloud", "edge", a robot's name) -> the argv prefix that runs it
            there (e.g. ``ip netns exec NS``); a missing name runs as is.
        edge_listen_host: the address the edge listens on (e.g. 0.0.0.0 in a hub namespace).
        edge_host: robot name -> the edge's address as that robot reaches it (default
            127.0.0.1). The cloud listens on, and the edge reaches it at, 127.0.0.1 of theirs.
    """

    prefix: Mapping[str, tuple[str, ...]] = field(default_factory=dict)
    edge_listen_host: str = "127.0.0.1"
    edge_host: Mapping[str, str] = field(default_factory=dict)


@dataclass(frozen=True)
class JobConfig:
    """One run of the whole system.

    Attributes:
        dataset: dataset folder holding one EuRoC-layout sequence per robot (``*/mav0``).
        run_dir: run folder (created).
        robots: sequence folder names under ``dataset`` to play (default: all, sorted).
        dashboard_port: the cloud's dashboard port, 0 = none (default 0).
        rate: robots' playback rate, "realtime" (default) or "max".
        worker: the edge's VIO workers, "process" (default) or "thread".
        max_frames: play at most this many frames per robot (default: all).
        robot_links: optional hook ``(robot name, edge port) -> port the robot connects to``
            (an application-level throttle, see ``recslam.commands.experiment``).
        start_timeout_s: seconds a service may take to listen (default 120, imports are slow).
        record_uplink: the cloud records every applied uplink message to this file
            (``recslam cloud --record``; default: no recording).
        mbp: run the cloud with map backbone profiling (``recslam cloud --mbp``, one pass at
            shutdown; default on, like the cloud).
        mbp_every: ... and every this many new keyframes while running (``--mbp-every``;
            default 0: not).
        early_loop_candidates: ``recslam cloud --early-loop-candidates`` (None: the cloud's
            default).
        wire: how the edge encodes what it sends to the robots and the cloud (``recslam edge
            --wire``; default coded; robots and cloud accept both).
        time_offset_ms: ``recslam edge --time-offset-ms`` (None: auto, estimated online).
        offset_wait_s: ``recslam edge --offset-wait`` (default 0).
        placement: where each process runs (default: all on loopback here), e.g. the robots
            in network namespaces of their own (``lab.netns``).
        edges: number of edges (sites), robots round-robin (default 1: one edge ``edge``).
        sites: edge name -> its robots (overrides ``edges``; see :func:`parse_sites`).
        moves: ``(robot, frame, edge)``: from that frame on the robot plays to that edge
            (``recslam robot --handover``; default none).
        edge_restarts: ``(edge, seconds)``: a fault drill, that edge is killed (SIGKILL) this
            long after the robots started and restarted at once on its state directory
            (default none).
        mission: the cloud serves this named mission (``recslam cloud --mission``; None: the
            state directory's current one), e.g. in a saved map copied to ``state/cloud``.
        prior_frame: the earlier mission's ``eval/ate.json`` (``recslam cloud --prior-frame``).
        robot_args: more arguments for every robot (e.g. ``--uplink-budget 50 --live``).
        edge_args: more arguments for every edge (e.g. ``--max-vio-lag 0.5``).
    """

    dataset: Path
    run_dir: Path
    robots: tuple[str, ...] = ()
    dashboard_port: int = 0
    rate: str = "realtime"
    worker: str = "process"
    max_frames: int | None = None
    robot_links: Callable[[str, int], int] | None = None
    start_timeout_s: float = 120.0
    record_uplink: Path | None = None
    mbp: bool = True
    mbp_every: int = 0
    early_loop_candidates: int | None = None
    wire: WireFormat = WireFormat.CODED
    time_offset_ms: float | None = None
    offset_wait_s: float = 0.0
    placement: Placement = field(default_factory=Placement)
    edges: int = 1
    sites: Mapping[str, tuple[str, ...]] | None = None
    moves: tuple[tuple[str, int, str], ...] = ()
    edge_restarts: tuple[tuple[str, float], ...] = ()
    mission: str | None = None
    prior_frame: Path | None = None
    robot_args: tuple[str, ...] = ()
    edge_args: tuple[str, ...] = ()


@dataclass
class Service:
    """A supervised process."""

    name: str
    argv: list[str]
    log_path: Path
    proc: subprocess.Popen | None = None
    started_at: float = 0.0
    exit_codes: list[int] = field(default_factory=list)

    def poll(self) -> int | None:
        return None if self.proc is None else self.proc.poll()

    def log_text(self) -> str:
        return self.log_path.read_text(errors="replace") if self.log_path.exists() else ""


class Job:
    """Start, watch and stop one run. ``start()`` ... ``wait_robots()`` ... ``stop()``."""

    def __init__(self, config: JobConfig) -> None:
        self.config = config
        self.run_dir = Path(config.run_dir)
        for sub in ("logs", "stats", "state", "results"):
            (self.run_dir / sub).mkdir(parents=True, exist_ok=True)
        names = config.robots or tuple(
            sorted(p.parent.name for p in Path(config.dataset).glob("*/mav0"))
        )
        if not names:
            raise OrchestrationError(f"{config.dataset}: no */mav0 sequence folders")
        self.robot_names = names
        self.sites = assign_sites(names, config.edges, config.sites)
        self.edge_names = tuple(self.sites)
        self.site_of = {r: e for e, rs in self.sites.items() for r in rs}
        for robot, _, edge in config.moves:
            if robot not in self.site_of or edge not in self.sites:
                raise OrchestrationError(f"move of {robot!r} to {edge!r}: no such robot or edge")
        for edge, _ in config.edge_restarts:
            if edge not in self.sites:
                raise OrchestrationError(f"restart of {edge!r}: no such edge")
        self._restarts = sorted(config.edge_restarts, key=lambda r: r[1])
        # One identity per process: the operator secret stays here, each process gets its
        # own key file (the robots only their own credential).
        self.keys_dir = self.run_dir / "keys"
        issue_keys(self.keys_dir, list(self.edge_names), names)
        self.cloud_port = free_port()
        self.edge_ports = {e: free_port() for e in self.edge_names}
        self.edge_port = self.edge_ports[self.edge_names[0]]
        self.services: dict[str, Service] = {}
        self.robot_started_at: float = 0.0
        self.samples_path = self.run_dir / "stats" / "samples.jsonl"

    # ------------------------------------------------------------------ commands
    def _recslam(self, *args: str) -> list[str]:
        return [sys.executable, "-m", "recslam", *args]

    def cloud_argv(self) -> list[str]:
        c = self.config
        record = [] if c.record_uplink is None else ["--record", str(c.record_uplink)]
        if c.mission is not None:
            record += ["--mission", c.mission]
        if c.prior_frame is not None:
            record += ["--prior-frame", str(c.prior_frame)]
        if c.early_loop_candidates is not None:
            record += ["--early-loop-candidates", str(c.early_loop_candidates)]
        return self._recslam(
            "cloud",
            "--listen",
            f"127.0.0.1:{self.cloud_port}",
            "--state-dir",
            str(self.run_dir / "state" / "cloud"),
            "--dashboard-port",
            str(c.dashboard_port),
            "--results",
            str(self.run_dir / "results"),
            "--groundtruth",
            str(c.dataset),
            "--key-file",
            str(self.keys_dir / "cloud.keys"),
            "--output-every",
            "0",
            "--stats-out",
            str(self.run_dir / "stats" / "cloud.json"),
            "--mbp" if c.mbp else "--no-mbp",
            "--mbp-every",
            str(c.mbp_every),
            "--wire",
            c.wire.value,
            *record,
        )

    def edge_argv(self, name: str | None = None) -> list[str]:
        """The command of edge ``name`` (default: the first)."""
        c = self.config
        name = name or self.edge_names[0]
        return self._recslam(
            "edge",
            "--listen",
            f"{c.placement.edge_listen_host}:{self.edge_ports[name]}",
            "--cloud",
            f"127.0.0.1:{self.cloud_port}",
            "--agent-id",
            name,
            "--state-dir",
            str(self.run_dir / "state" / name),
            "--key-file",
            str(self.keys_dir / f"edge-{name}.keys"),
            "--worker",
            c.worker,
            "--wire",
            c.wire.value,
            "--stats-out",
            str(self.run_dir / "stats" / f"{edge_stats_name(name)}.json"),
            "--time-offset-ms",
            "auto" if c.time_offset_ms is None else f"{c.time_offset_ms:g}",
            "--offset-wait",
            f"{c.offset_wait_s:g}",
            *c.edge_args,
        )

    def _edge_address(self, robot: str, edge: str) -> str:
        c = self.config
        port = self.edge_ports[edge]
        port = port if c.robot_links is None else c.robot_links(robot, port)
        return f"{c.placement.edge_host.get(robot, '127.0.0.1')}:{port}"

    def robot_argv(self, name: str) -> list[str]:
        c = self.config
        argv = self._recslam(
            "robot",
            "--dataset",
            str(Path(c.dataset) / name),
            "--edge",
            self._edge_address(name, self.site_of[name]),
            "--agent-id",
            name,
            "--rate",
            c.rate,
            "--key-file",
            str(self.keys_dir / f"robot-{name}.keys"),
            "--pose-out",
            str(self.run_dir / "results" / "poses" / f"{name}.tum"),
            "--global-pose-out",
            str(self.run_dir / "results" / "poses_global" / f"{name}.tum"),
            "--stats-out",
            str(self.run_dir / "stats" / f"robot-{name}.json"),
        )
        for robot, frame, edge in sorted(c.moves, key=lambda m: m[1]):
            if robot == name:
                argv += ["--handover", f"{frame}={self._edge_address(name, edge)}"]
        if c.max_frames is not None:
            argv += ["--max-frames", str(c.max_frames)]
        return argv + list(c.robot_args)

    # ------------------------------------------------------------------ processes
    def launch(self, name: str, argv: list[str]) -> Service:
        """Start (or restart) process ``name`` (where ``placement`` puts it); its output is
        appended to its log."""
        argv = [*self.config.placement.prefix.get(name, ()), *argv]
        svc = self.services.get(name)
        if svc is None:
            svc = Service(name, argv, self.run_dir / "logs" / f"{name}.log")
            self.services[name] = svc
        env = dict(os.environ, PYTHONUNBUFFERED="1")
        env.pop("RECSLAM_SECRET", None)
        with svc.log_path.open("ab") as out:
            out.write(f"$ {' '.join(argv)}\n".encode())
            out.flush()
            svc.proc = subprocess.Popen(
                argv, stdout=out, stderr=subprocess.STDOUT, env=env, start_new_session=True
            )
        svc.started_at = time.monotonic()
        log.info("started %s (pid %d)", name, svc.proc.pid)
        return svc

    def _wait_for_line(self, svc: Service, marker: str, count: int = 1) -> None:
        deadline = time.monotonic() + self.config.start_timeout_s
        while svc.log_text().count(marker) < count:
            if svc.poll() is not None:
                raise OrchestrationError(
                    f"{svc.name} exited with {svc.poll()} before listening; "
                    f"log {svc.log_path}:\n{svc.log_text()[-2000:]}"
                )
            if time.monotonic() > deadline:
                wait = self.config.start_timeout_s
                raise OrchestrationError(f"{svc.name} not listening after {wait:.0f} s")
            time.sleep(0.1)

    def start(self) -> None:
        """Start the cloud, then the edges, then every robot (each once the previous listens)."""
        self._wait_for_line(self.launch("cloud", self.cloud_argv()), "cloud listening")
        for edge in self.edge_names:
            self.start_edge(edge)
        self.robot_started_at = time.time()
        for name in self.robot_names:
            self.launch(name, self.robot_argv(name))

    def dashboard_url(self) -> str | None:
        """The URL (with its access token) the cloud announced for its dashboard."""
        found = re.search(r"dashboard at (\S+)", self.services["cloud"].log_text())
        return found.group(1) if found else None

    def start_edge(self, name: str | None = None) -> None:
        """Start (or restart, on the same state directory) edge ``name`` (default: the first)
        and wait until it listens."""
        name = name or self.edge_names[0]
        svc = self.services.get(name)
        count = 1 + (svc.log_text().count("edge listening") if svc is not None else 0)
        self._wait_for_line(self.launch(name, self.edge_argv(name)), "edge listening", count)

    def kill(self, name: str, sig: int = signal.SIGKILL) -> int:
        """Send ``sig`` to service ``name`` and wait for it; returns its exit code."""
        svc = self.services[name]
        assert svc.proc is not None
        if svc.proc.poll() is None:
            svc.proc.send_signal(sig)
        code = svc.proc.wait(60)
        svc.exit_codes.append(code)
        return code

    def stats(self, which: str) -> dict[str, Any]:
        """The last counters ``which`` ("cloud", or an edge's name) wrote ({} before the
        first); "edge" is every edge's robots together (:func:`merge_edge_stats`)."""
        if which == "edge" and self.edge_names != (SINGLE_EDGE,):
            return merge_edge_stats({e: self.stats(e) for e in self.edge_names})
        stem = edge_stats_name(which) if which in self.edge_names else which
        path = self.run_dir / "stats" / f"{stem}.json"
        try:
            return json.loads(path.read_text())
        except (OSError, ValueError):
            return {}

    def sample(self) -> dict[str, Any]:
        """Current edge and cloud counters, also appended to ``stats/samples.jsonl``: "edge"
        all edges' robots together, "edges" each edge's own counters."""
        edges = {e: self.stats(e) for e in self.edge_names}
        s = {
            "time": time.time(),
            "edge": merge_edge_stats(edges),
            "edges": edges,
            "cloud": self.stats("cloud"),
        }
        with self.samples_path.open("a") as f:
            f.write(json.dumps(s) + "\n")
        return s

    def failed(self) -> list[str]:
        """Names of services that exited unexpectedly (non-zero while the run goes on)."""
        bad = []
        for svc in self.services.values():
            code = svc.poll()
            if code is not None and code != 0:
                bad.append(f"{svc.name} (exit {code})")
            elif code == 0 and svc.name in ("cloud", *self.edge_names):
                bad.append(f"{svc.name} (exited early)")
        return bad

    def wait_robots(
        self,
        timeout_s: float,
        progress: Callable[[dict[str, Any]], None] | None = None,
        every_s: float = 1.0,
        on_tick: Callable[[Job, dict[str, Any]], None] | None = None,
    ) -> dict[str, int]:
        """Wait until every robot process exits; returns their exit codes.

        Raises OrchestrationError when an edge or the cloud dies, or after ``timeout_s``.
        ``on_tick`` (tests: kill/restart an edge mid-run) runs after every sample.
        """
        deadline = time.monotonic() + timeout_s
        while True:
            s = self.sample()
            if progress is not None:
                progress(s)
            if on_tick is not None:
                on_tick(self, s)
            while self._restarts and time.time() - self.robot_started_at >= self._restarts[0][1]:
                edge, at = self._restarts.pop(0)
                code = self.kill(edge, signal.SIGKILL)
                log.warning(
                    "drill: killed %s (exit %d) %.0f s into the run; restarting", edge, code, at
                )
                self.start_edge(edge)
            codes = {n: self.services[n].poll() for n in self.robot_names}
            if all(c is not None for c in codes.values()):
                return {n: int(c) for n, c in codes.items() if c is not None}
            for name in ("cloud", *self.edge_names):
                if self.services[name].poll() is not None:
                    raise OrchestrationError(
                        f"{name} exited with {self.services[name].poll()}; log "
                        f"{self.services[name].log_path}:\n{self.services[name].log_text()[-2000:]}"
                    )
            if time.monotonic() > deadline:
                raise OrchestrationError(f"robots not done after {timeout_s:.0f} s")
            time.sleep(every_s)

    def wait_edge_idle(self, timeout_s: float = 120.0, quiet_s: float = 3.0) -> None:
        """Wait until the edge processed every decoded frame and the cloud's keyframe count
        stopped changing for ``quiet_s`` seconds (or ``timeout_s``)."""
        deadline = time.monotonic() + timeout_s
        last, since = None, time.monotonic()
        while time.monotonic() < deadline:
            s = self.sample()
            robots = s["edge"].get("robots", {})
            busy = any(  # (a frame skipped as stale, --max-vio-lag, is done with)
                r["frames_processed"] + r.get("frames_skipped_stale", 0) < r["frames_decoded"]
                or r["queued"]
                for r in robots.values()
            )
            key = (s["cloud"].get("keyframes"), s["cloud"].get("messages"))
            if key != last or busy:
                last, since = key, time.monotonic()
            elif time.monotonic() - since >= quiet_s:
                return
            time.sleep(0.5)
        log.warning("edge/cloud still busy after %.0f s; stopping anyway", timeout_s)

    def stop(self, timeout_s: float = 120.0) -> dict[str, int]:
        """SIGTERM robots still running, then the edge, then the cloud (which writes its
        results); SIGKILL after ``timeout_s``. Returns every service's last exit code."""
        order = [*self.robot_names, *self.edge_names, "cloud"]
        codes: dict[str, int] = {}
        for name in order:
            svc = self.services.get(name)
            if svc is None or svc.proc is None:
                continue
            if svc.proc.poll() is None:
                svc.proc.send_signal(signal.SIGTERM)
                try:
                    svc.proc.wait(timeout_s)
                except subprocess.TimeoutExpired:
                    log.error("%s did not stop within %.0f s; killing it", name, timeout_s)
                    svc.proc.kill()
                    svc.proc.wait(10)
            codes[name] = int(svc.proc.returncode)
        return codes

    def __enter__(self) -> Job:
        """SIGTERM now raises KeyboardInterrupt (main thread), so that ``__exit__`` kills the
        children (they run in their own sessions and would outlive a plain exit)."""
        self._old_sigterm = None
        if threading.current_thread() is threading.main_thread():
            self._old_sigterm = signal.signal(signal.SIGTERM, _raise_interrupt)
        return self

    def __exit__(self, *exc: object) -> None:
        if self._old_sigterm is not None:
            signal.signal(signal.SIGTERM, self._old_sigterm)
        for svc in self.services.values():
            if svc.proc is not None and svc.proc.poll() is None:
                svc.proc.kill()
                svc.proc.wait(10)


def _raise_interrupt(signum: int, frame: object) -> None:
    raise KeyboardInterrupt(f"signal {signum}")


def robot_frames(dataset: Path, names: Sequence[str]) -> dict[str, int]:
    """Number of camera frames of each robot's sequence (``mav0/cam0/data.csv`` rows)."""
    out = {}
    for name in names:
        csv = Path(dataset) / name / "mav0" / "cam0" / "data.csv"
        lines = [ln for ln in csv.read_text().splitlines() if ln and not ln.startswith("#")]
        out[name] = len(lines)
    return out


def progress_line(sample: dict[str, Any], elapsed: float) -> str:
    """One progress line from a :meth:`Job.sample` (edge and cloud counters; with several
    edges each robot is prefixed by its edge)."""
    robots = sample["edge"].get("robots", {})
    edges = sample.get("edges", {})
    where = sample["edge"].get("edge_of", {}) if len(edges) > 1 else {}
    parts = [
        f"{'/'.join(where.get(n, []))}{':' if n in where else ''}{n} "
        f"{r['frames_decoded']}f/{r['keyframes_uplinked']}kf {r['state']}"
        for n, r in sorted(robots.items())
    ]
    c = sample["cloud"]
    cloud = (
        f"cloud {c.get('keyframes', 0)} kf, {c.get('map_points', 0)} pts, maps {c.get('maps')}, "
        f"merges {c.get('merges', 0)}, loops {c.get('loops', 0)}"
    )
    return f"[{elapsed:6.1f} s] " + (" | ".join(parts) or "robots connecting") + " | " + cloud


def run_and_report(
    config: JobConfig,
    report_dir: Path,
    timeout_s: float = 1800.0,
    progress: Callable[[dict[str, Any], float], None] | None = None,
    say: Callable[[str], None] = log.info,
) -> dict[str, Any]:
    """One whole run as ``recslam demo`` does it, then its report.

    Starts the cloud, the edge and the robots, waits for the robots (at most ``timeout_s``),
    lets the edge and the cloud drain, stops them and writes ``report_dir/report.{md,json}``
    from ``config.run_dir`` (``lab.run.report``). ``progress(sample, elapsed_s)`` sees every
    sample (about one a second), ``say`` the few milestone lines. Returns the report data.
    """
    from lab.run.report import RunFacts, write_report

    t0 = time.perf_counter()

    def tick(sample: dict[str, Any]) -> None:
        if progress is not None:
            progress(sample, time.perf_counter() - t0)

    with Job(config) as job:
        sites = "; ".join(f"{e}: {', '.join(rs)}" for e, rs in job.sites.items())
        say(
            f"starting cloud, {len(job.edge_names)} edge(s) and {len(job.robot_names)} robots "
            f"({sites}; run folder {job.run_dir})"
        )
        job.start()
        if config.dashboard_port:
            say(f"dashboard: {job.dashboard_url()}")
        robots_t0 = time.perf_counter()
        codes = job.wait_robots(timeout_s, tick)
        stream_s = time.perf_counter() - robots_t0
        say(f"robots done in {stream_s:.1f} s: exit codes {codes}; draining edge and cloud")
        job.wait_edge_idle()
        say(progress_line(job.sample(), time.perf_counter() - t0))
        codes = job.stop()
        frames = robot_frames(config.dataset, job.robot_names)
    facts = RunFacts(stream_s, time.perf_counter() - t0, codes, frames)
    return write_report(job.run_dir, report_dir, facts)
