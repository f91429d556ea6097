"""The edge network service: robots connect, frames flow in, estimates flow out.

:class:`EdgeServer` owns the lifecycle: a :class:`common.transport.Server` for the robots
(role "robot", agent id = robot name), a :class:`common.transport.Client` to the cloud (role
"edge"), the robots' journals (``state_dir``) and the :class:`~services.edge.app.EdgeApp`.

Each robot brings its own calibration (its stream's first message, ``RobotSensors``): the
edge has none of its own.

Restart without loss (with ``state_dir``): each robot's journal is both the record of its raw
messages and the transport's delivery store (``services/edge/journal.py``). On ``start`` the
journals are replayed (sensors first: the robot's session rebuilt from them, codec state
rebuilt, VIO fast-forwarded) *before* listening; the restored positions make each robot
replay exactly what was not journaled. Without ``state_dir`` a restarted edge starts from
nothing: a robot reconnecting mid-stream then sends frames without the sensor description
that opened its stream, which the edge refuses with that reason (the robot stops; restarted,
its new stream opens with its sensors again).

The edge's link to the cloud is not persisted: after a restart it is a new stream; the VIO
replay re-sends keyframes (the cloud treats ``KeyframeUpdate`` as idempotent).

Stopping with a backlog for the cloud: :meth:`EdgeServer.stop` closes the robots' side, stops
the workers and then flushes the cloud uplink for at most ``stop_flush_timeout_s``, logging
how many messages and bytes are queued and, if the cloud does not take them in time, how many
are left unsent (with ``state_dir`` they are not lost: the robots' frames are in the journal
and the next start's VIO replay sends their keyframes again; without it they are). The cloud
link gives up (``give_up_after_s`` > 0) when there has been no session with the cloud for that
long: :meth:`EdgeServer.wait_cloud_failed` returns the reason (as it does when the cloud
refused the edge's credential) and the process exits non-zero (``runner.py``).
"""

from __future__ import annotations

import asyncio
import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from common.protocol import OutboxFullError, PeerRejectedError, SessionConfig
from common.protocol.auth import Keyring, as_keyring
from common.protocol.messages import Message
from common.transport import Client, Server, TransportConfig, link_load
from common.transport.stalls import StallMonitor
from common.transport.tls import TlsFiles
from common.vocabulary import Vocabulary
from services.edge.app import EdgeApp, EdgeConfig
from services.edge.journal import JournalStore
from services.edge.worker import WorkerFactory, make_worker

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class EdgeServiceConfig:
    """Network-side options: the edge's agent id, the cloud address (None: no cloud; the
    uplink is dropped and counted), heartbeat/idle timeouts (s), journal fsync batch (s),
    the longest flush of the cloud uplink at stop (s), and how long the cloud link goes on
    without a session before the edge gives up (s, 0 = never; see the module docstring).

    ``robot_ack_delay_s``: the longest a robot's message waits for its acknowledgement. The
    edge sends each robot a pose for every frame its VIO finishes, and every frame's header
    carries the cumulative acknowledgement (TCP's delayed ACK): with one camera period
    (50 ms at 20 Hz) most acknowledgements ride on a pose instead of costing a 39-byte ``Ack``
    frame of their own (~4.7 kbit/s of the downlink at 20 Hz with the protocol's 5 ms)."""

    agent_id: str = "edge"
    cloud_host: str | None = None
    cloud_port: int = 7100
    heartbeat_interval_s: float = 1.0
    idle_timeout_s: float = 10.0
    fsync_interval_s: float = 0.2
    stop_flush_timeout_s: float = 10.0
    give_up_after_s: float = 0.0
    robot_ack_delay_s: float = 0.05

    def __post_init__(self) -> None:
        if not 0 < self.robot_ack_delay_s <= 1.0:
            raise ValueError(f"robot_ack_delay_s must be in (0, 1] s: {self.robot_ack_delay_s}")
        if not self.stop_flush_timeout_s >= 0:
            raise ValueError(f"stop_flush_timeout_s must be >= 0: {self.stop_flush_timeout_s}")
        if not self.give_up_after_s >= 0:
            raise ValueError(f"give_up_after_s must be >= 0 (0 = never): {self.give_up_after_s}")


def flat_counters(snap: dict[str, Any]) -> dict[str, int]:
    """Flatten a link's counter snapshot to ``{"rx.bytes": .., "rx.RobotFrame": bytes, ..}``."""
    out: dict[str, int] = {}
    for direction in ("tx", "rx"):
        d = snap.get(direction, {})
        out[f"{direction}.messages"] = int(d.get("messages", 0))
        out[f"{direction}.bytes"] = int(d.get("bytes", 0))
        for name, e in d.get("by_type", {}).items():
            out[f"{direction}.{name}"] = int(e["bytes"])
    for key in ("retransmitted_messages", "retransmitted_bytes", "duplicates_dropped", "late_acks"):
        out[key] = int(snap.get(key, 0))
    return out


class EdgeServer:
    """The edge service. ``await start(host, port)`` ... ``await stop()``.

    Args:
        secret: the edge's keys (a Keyring: its credential and the robots' role key), or
            the operator secret (>= 16 bytes), which derives every credential.
        vocabulary: the shared ORB vocabulary (codec word ids).
        config: application options (worker kind, VIO, feedback policy).
        service: network options.
        state_dir: journal directory (None: restarts lose state; see module docstring).
        transport: socket settings of the robot server.
        worker_factory: builds each robot's VIO worker (tests inject faulty ones).
        tls: TLS towards the robots (a certificate) and the cloud (a CA); default none.
    """

    def __init__(
        self,
        secret: bytes | Keyring,
        vocabulary: Vocabulary,
        config: EdgeConfig | None = None,
        service: EdgeServiceConfig | None = None,
        state_dir: str | Path | None = None,
        transport: TransportConfig | None = None,
        worker_factory: WorkerFactory = make_worker,
        tls: TlsFiles | None = None,
    ) -> None:
        self.service = service or EdgeServiceConfig()
        tls = tls or TlsFiles()
        keys = as_keyring(secret)
        self.config = config or EdgeConfig()
        sv = self.service
        self.store = JournalStore(state_dir, sv.fsync_interval_s) if state_dir else None
        self.robot_session = SessionConfig(
            "edge",
            sv.agent_id,
            keys=keys,
            heartbeat_interval=sv.heartbeat_interval_s,
            idle_timeout=sv.idle_timeout_s,
            ack_delay=sv.robot_ack_delay_s,
        )
        self.app = EdgeApp(vocabulary, self, self.config, self.store, worker_factory)
        tr = transport or TransportConfig(accept_roles=("robot",))
        self.server = Server(
            self.robot_session,
            self.app.on_robot_message,
            transport=tr,
            ssl=tls.server_context(),
            store=self.store,
        )
        self.cloud: Client | None = None
        if sv.cloud_host is not None:
            cloud_cfg = SessionConfig(
                "edge",
                sv.agent_id,
                keys=keys,
                heartbeat_interval=sv.heartbeat_interval_s,
                idle_timeout=sv.idle_timeout_s,
            )
            self.cloud = Client(
                cloud_cfg,
                self.app.on_cloud_message,
                sv.cloud_host,
                sv.cloud_port,
                server_name="cloud",
                ssl=tls.client_context(),
                server_hostname=sv.cloud_host,
                transport=TransportConfig(give_up_after=sv.give_up_after_s),
                stop_on_reject=False,  # a refused keyframe is logged; the other robots go on
            )
        self.dropped_feedback = 0
        self.dropped_uplink = 0
        self.replayed_frames = 0
        self.address: tuple[str, int] | None = None
        self.stalls = StallMonitor("edge")

    # ------------------------------------------------------------------ Sink
    def to_robot(self, agent_id: str, message: Message) -> bool:
        peer = self.server.peers.get(agent_id)
        if peer is None:
            self.dropped_feedback += 1
            return False
        try:
            peer.send_nowait(message)
        except OutboxFullError:
            self.dropped_feedback += 1
            logger.warning("robot %s: outbox full, %s dropped", agent_id, type(message).__name__)
            return False
        return True

    async def to_cloud(self, message: Message) -> None:
        if self.cloud is None or self.cloud.failure is not None:
            self.dropped_uplink += 1
            return
        try:
            await self.cloud.send(message)
        except PeerRejectedError:  # the link was given up meanwhile (the client said why)
            self.dropped_uplink += 1

    def link_counters(self, agent_id: str) -> dict[str, int]:
        peer = self.server.peers.get(agent_id)
        return {} if peer is None else flat_counters(peer.counters())

    def cloud_load(self) -> tuple[int, int]:
        return link_load(self.cloud)

    # ------------------------------------------------------------------ lifecycle
    async def start(self, host: str = "127.0.0.1", port: int = 0) -> tuple[str, int]:
        """Connect to the cloud, replay the journals, then listen; returns the bound address."""
        self.stalls.start()
        if self.cloud is not None:
            await self.cloud.start()
        self.replayed_frames = await self.app.replay()
        await self.app.start_workers()
        if self.replayed_frames:
            logger.info(
                "replayed %d journaled frames of %d robots",
                self.replayed_frames,
                len(self.app.robots),
            )
        self.address = await self.server.start(host, port)
        return self.address

    async def flush(self, timeout: float | None = None) -> None:
        """Until every queued frame is processed and the cloud delivered all uplink."""
        await self.app.wait_idle()
        if self.cloud is not None:
            await self.cloud.flush()

    async def wait_cloud_failed(self) -> PeerRejectedError:
        """Return once the cloud link was given up (credential refused, or no session for
        ``give_up_after_s``); never returns without a cloud."""
        if self.cloud is None:
            await asyncio.Event().wait()
        assert self.cloud is not None
        return await self.cloud.wait_failed()

    async def stop(self) -> None:
        """Close the robots' connections, stop the workers, flush the cloud uplink for at most
        ``stop_flush_timeout_s`` (logged), close the cloud link and the journals."""
        await self.server.close()
        await self.app.close()
        if self.cloud is not None:
            await self._flush_cloud_at_stop()
            await self.cloud.close()
        if self.store is not None:
            self.store.close()
        await self.stalls.stop()

    async def _flush_cloud_at_stop(self) -> None:
        assert self.cloud is not None and self.cloud.peer is not None
        c = self.cloud.counters()
        queued, size = c["outbox_messages"], c["outbox_bytes"]
        if queued == 0 or self.cloud.failure is not None:
            if queued:
                logger.warning(
                    "edge stopping: %d messages (%d B) for the cloud unsent (the link was "
                    "given up); %s",
                    queued,
                    size,
                    self._unsent_fate(),
                )
            return
        timeout = self.service.stop_flush_timeout_s
        logger.log(
            logging.INFO if c["connected"] else logging.WARNING,  # the cloud away: say it loud
            "edge stopping: %d messages (%d B) queued for the cloud at %s:%d; flushing them for "
            "at most %.3g s",
            queued,
            size,
            self.cloud.host,
            self.cloud.port,
            timeout,
        )
        try:
            await asyncio.wait_for(self.cloud.flush(), timeout)
        except (TimeoutError, PeerRejectedError):
            c = self.cloud.counters()
            logger.warning(
                "edge stopping: the cloud did not take the backlog within %.3g s: giving up "
                "with %d messages (%d B) unsent; %s",
                timeout,
                c["outbox_messages"],
                c["outbox_bytes"],
                self._unsent_fate(),
            )
        else:
            logger.info("edge stopping: the cloud took all %d queued messages", queued)

    def _unsent_fate(self) -> str:
        if self.store is not None:
            return (
                f"not lost: the robots' frames are journaled in {self.store.directory} and the "
                "next start replays them, sending their keyframes again"
            )
        return "they are lost (no --state-dir: nothing is journaled)"

    async def __aenter__(self) -> EdgeServer:
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.stop()

    def stats(self) -> dict[str, Any]:
        """Plain-data counters of the service and every robot."""
        return {
            "robots": self.app.stats(),
            "replayed_frames": self.replayed_frames,
            "dropped_feedback": self.dropped_feedback,
            "dropped_uplink": self.dropped_uplink,
            "loop_stalls": self.stalls.stats.snapshot(),
            "cloud": None
            if self.cloud is None or self.cloud.peer is None
            else self.cloud.counters(),
        }
