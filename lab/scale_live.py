"""The live half of :mod:`lab.scale`: a team's uplink played to a real cloud process over TCP.

:func:`run_live` starts ``recslam cloud`` as its own process (``taskset -c CPU`` when asked:
the cloud and its optimizer process share that one core), issues a key for each fake edge,
connects one :class:`common.transport.Client` per edge (role ``edge``, as the real edge's
uplink), plays the timeline at its times (:func:`play`), and meanwhile samples every
``sample_every_s``:

- the **queue**: messages the edges sent and the cloud has not applied yet (the edges'
  outboxes: the transport acknowledges after the cloud's handler returned);
- the cloud's ``--stats-out`` (messages applied, keyframes, the worker's queue);
- the cloud's **memory** (RSS of the process and its children, ``/proc``) and **CPU** time.

Every ``PoseCorrection`` the edges get back is kept with its arrival time. After the last
message it waits until the cloud applied everything and ``drain_s`` more (the corrections of
the last keyframes), reads the final stats, then stops the cloud (SIGTERM; killed if its
shutdown outlasts ``stop_timeout_s``).
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import os
import signal
import subprocess
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from common.errors import RecslamError
from common.links.edge_cloud import MapPlacement, PoseCorrection, PoseCorrectionCoded
from common.protocol import SessionConfig
from common.protocol.credentials import issue_keys, load_keys
from common.transport import Client, Delivery
from lab.scale import KeyframeKey, Received, Send, received

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class LiveConfig:
    """How a live replay runs.

    Attributes:
        cloud_cpu: ``taskset -c`` list for the cloud process (None: not pinned).
        replayer_cpu: CPUs this process (the fake edges) is pinned to meanwhile (None: not
            pinned), so that it does not take the cloud's core.
        sample_every_s: sampling period of the queue, stats, memory and CPU.
        drain_s: wait this long after the cloud applied the last message.
        flush_timeout_s: give up waiting for the cloud to apply everything after this.
        stop_timeout_s: SIGKILL the cloud if its shutdown takes longer.
        cloud_args: more ``recslam cloud`` arguments.
    """

    cloud_cpu: str | None = "0"
    replayer_cpu: tuple[int, ...] | None = (1,)
    sample_every_s: float = 0.5
    drain_s: float = 15.0
    flush_timeout_s: float = 240.0
    stop_timeout_s: float = 30.0
    cloud_args: tuple[str, ...] = ()


@dataclass
class LiveResult:
    """What a live replay observed (times in seconds after the first message's slot)."""

    arrivals: dict[KeyframeKey, float]
    corrections: list[Received]
    samples: list[dict[str, Any]]
    stats: dict[str, Any]
    duration_s: float
    applied_s: float
    late_max_s: float
    cloud_cpu_s: float
    rss_max_mb: float
    sent: int
    edges: int
    log_tail: str = ""
    rejected: list[str] = field(default_factory=list)
    drained: bool = True
    """The cloud applied every message within ``flush_timeout_s`` after the last one."""


class LiveError(RecslamError):
    """The cloud process did not start or died during a live replay."""


def _proc_rss_cpu(pid: int) -> tuple[float, float]:
    """RSS (MB) and CPU seconds (user + system) of ``pid`` and its children; (0, 0) when
    it is gone."""
    tick = os.sysconf("SC_CLK_TCK")
    pids = [pid]
    with contextlib.suppress(OSError):
        for entry in os.listdir("/proc"):
            if not entry.isdigit():
                continue
            with contextlib.suppress(OSError):
                stat = Path(f"/proc/{entry}/stat").read_text()
                if int(stat.rsplit(")", 1)[1].split()[1]) == pid:
                    pids.append(int(entry))
    rss = cpu = 0.0
    for p in pids:
        with contextlib.suppress(OSError, ValueError, IndexError):
            fields = Path(f"/proc/{p}/stat").read_text().rsplit(")", 1)[1].split()
            cpu += (int(fields[11]) + int(fields[12])) / tick
            for line in Path(f"/proc/{p}/status").read_text().splitlines():
                if line.startswith("VmRSS:"):
                    rss += int(line.split()[1]) / 1024.0
    return rss, cpu


def _read_json(path: Path) -> dict[str, Any]:
    try:
        return dict(json.loads(path.read_text()))
    except (OSError, ValueError):
        return {}


def start_cloud(work: Path, edges: Sequence[str], config: LiveConfig) -> tuple[Any, int, Path]:
    """Issue the keys and start ``recslam cloud`` on a free loopback port; (process, port,
    keys folder) once it listens."""
    from lab.run.orchestration import free_port

    keys = work / "keys"
    issue_keys(keys, list(edges), [])
    port = free_port()
    argv = [
        sys.executable,
        "-m",
        "recslam",
        "cloud",
        "--listen",
        f"127.0.0.1:{port}",
        "--state-dir",
        str(work / "state"),
        "--dashboard-port",
        "0",
        "--key-file",
        str(keys / "cloud.keys"),
        "--output-every",
        "0",
        "--stats-out",
        str(work / "cloud.json"),
        *config.cloud_args,
    ]
    env = dict(os.environ)
    if config.cloud_cpu is not None:  # one core: no BLAS / OpenMP thread pools on it
        argv = ["taskset", "-c", config.cloud_cpu, *argv]
        env.update(OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1", MKL_NUM_THREADS="1")
    log_path = work / "cloud.log"
    out = log_path.open("ab")
    proc = subprocess.Popen(
        argv, stdout=out, stderr=subprocess.STDOUT, start_new_session=True, env=env
    )
    out.close()
    deadline = time.monotonic() + 120.0
    while "cloud listening" not in log_path.read_text(errors="replace"):
        if proc.poll() is not None or time.monotonic() > deadline:
            proc.kill()
            tail = log_path.read_text(errors="replace")[-2000:]
            raise LiveError(f"the cloud did not start (log {log_path}):\n{tail}")
        time.sleep(0.1)
    return proc, port, keys


def stop_cloud(proc: Any, timeout_s: float) -> None:
    """SIGTERM the cloud we started, SIGKILL it after ``timeout_s``."""
    if proc.poll() is not None:
        return
    proc.send_signal(signal.SIGTERM)
    try:
        proc.wait(timeout_s)
    except subprocess.TimeoutExpired:
        log.warning("cloud still stopping after %.0f s: killed", timeout_s)
        proc.kill()
        proc.wait()


async def play(
    sends: Sequence[Send],
    port: int,
    keys: Path,
    pid: int,
    stats_path: Path,
    config: LiveConfig,
) -> LiveResult:
    """Play ``sends`` to the cloud on ``port`` (module docstring)."""
    loop = asyncio.get_running_loop()
    edges = sorted({s.edge for s in sends})
    corrections: list[Received] = []
    rejected: list[str] = []
    t0 = 0.0  # loop time of the timeline's zero (set once every edge is connected)

    async def on_message(d: Delivery) -> None:
        m = d.message
        if isinstance(m, PoseCorrection | PoseCorrectionCoded):
            corrections.append(received(loop.time() - t0, m))
        elif not isinstance(m, MapPlacement):  # placements come with corrections: not timed
            rejected.append(f"{d.peer}: unexpected {type(m).__name__}")

            rejected.append(f"{d.peer}: unexpected {type(m).__name__}")

    clients: dict[str, Client] = {}
    for e in edges:
        keyring = load_keys(keys / f"edge-{e}.keys", identity=("edge", e))
        clients[e] = Client(
            SessionConfig("edge", e, keys=keyring),
            on_message,
            "127.0.0.1",
            port,
            server_name="cloud",
            stop_on_reject=False,
        )
        await clients[e].start()
    await asyncio.gather(*(c.wait_connected(60.0) for c in clients.values()))
    t0 = loop.time()
    arrivals: dict[KeyframeKey, float] = {}
    late = [0.0]
    sent = [0]
    samples: list[dict[str, Any]] = []
    cpu0 = _proc_rss_cpu(pid)[1]
    done = asyncio.Event()

    async def sender(edge: str) -> None:
        client = clients[edge]
        for s in (s for s in sends if s.edge == edge):
            wait = t0 + s.t - loop.time()
            if wait > 0:
                await asyncio.sleep(wait)
            late[0] = max(late[0], loop.time() - t0 - s.t)
            await client.send(s.message)
            sent[0] += 1
            if s.keyframe is not None:
                arrivals[s.keyframe] = s.t  # its slot: queueing counts in its latency

    async def sampler() -> None:
        while not done.is_set():
            queue = sum(
                int(c.peer.counters()["outbox_messages"]) for c in clients.values() if c.peer
            )
            rss, cpu = _proc_rss_cpu(pid)
            st = _read_json(stats_path)
            samples.append(
                {
                    "t": loop.time() - t0,
                    "queue": queue,
                    "sent": sent[0],
                    "applied": st.get("messages"),
                    "keyframes": st.get("keyframes"),
                    "worker_queue": st.get("worker_queue"),
                    "rss_mb": rss,
                    "cpu_s": cpu - cpu0,
                    "corrections": len(corrections),
                }
            )
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(done.wait(), config.sample_every_s)

    sampling = asyncio.create_task(sampler())
    try:
        await asyncio.gather(*(sender(e) for e in edges))
        duration = loop.time() - t0
        drained = True
        try:
            await asyncio.wait_for(
                asyncio.gather(*(c.flush() for c in clients.values())), config.flush_timeout_s
            )
        except TimeoutError:
            drained = False
            log.warning(
                "the cloud had not applied everything %.0f s after the last message",
                config.flush_timeout_s,
            )
        applied = loop.time() - t0
        await asyncio.sleep(config.drain_s)
        await asyncio.sleep(1.5)  # one more stats file
        done.set()
        await sampling
    finally:
        done.set()
        for c in clients.values():
            await c.close()
    rss, cpu = _proc_rss_cpu(pid)
    return LiveResult(
        arrivals=arrivals,
        corrections=corrections,
        samples=samples,
        stats=_read_json(stats_path),
        duration_s=duration,
        applied_s=applied,
        late_max_s=late[0],
        cloud_cpu_s=cpu - cpu0,
        rss_max_mb=max([rss, *(s["rss_mb"] for s in samples)]),
        sent=sent[0],
        edges=len(edges),
        rejected=rejected,
        drained=drained,
    )


def run_live(sends: Sequence[Send], work: Path, config: LiveConfig) -> LiveResult:
    """Start a cloud in ``work`` (must not hold a previous state), play ``sends`` to it,
    stop it; the observations."""
    from common.transport import run

    if (work / "state").exists():
        raise LiveError(f"{work}: holds a previous run's state")
    work.mkdir(parents=True, exist_ok=True)
    edges = sorted({s.edge for s in sends})
    proc, port, keys = start_cloud(work, edges, config)
    affinity = os.sched_getaffinity(0)
    try:
        if config.replayer_cpu is not None:
            os.sched_setaffinity(0, set(config.replayer_cpu))
        result = run(play(sends, port, keys, proc.pid, work / "cloud.json", config))
    finally:
        os.sched_setaffinity(0, affinity)
        stop_cloud(proc, config.stop_timeout_s)
    result.log_tail = (work / "cloud.log").read_text(errors="replace")[-3000:]
    return result
