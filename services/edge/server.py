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
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from common.protocol import OutboxFullError, SessionConfig
from common.protocol.auth import Keyring, as_keyring
from common.protocol.messages import Message
from common.transport import Client, Server, TransportConfig
from common.transport.tls import TlsFiles
from common.vocabulary import Vocabulary
from services.edge.app import EdgeApp, EdgeConfig
from services.edge.journal import JournalStore
from services.edge.worker import WorkerFactory, make_worker

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class EdgeServiceConfig:
    """Network-side options: the edge's agent id, the cloud address (None: no cloud; the
    uplink is dropped and counted), heartbeat/idle timeouts (s), journal fsync batch (s)."""

    agent_id: str = "edge"
    cloud_host: str | None = None
    cloud_port: int = 7100
    heartbeat_interval_s: float = 1.0
    idle_timeout_s: float = 10.0
    fsync_interval_s: float = 0.2


def flat_counters(snap: dict[str, Any]) -> dict[str, int]:
    """Flatten a link's counter snapshot to ``{"rx.bytes": .., "rx.RobotFrame": bytes, ..}``."""
    out: dict[str, int] = {}
    for direction in ("tx", "rx"):
        d = snap.get(direction, {})
        out[f"{direction}.messages"] = int(d.get("messages", 0))
        out[f"{direction}.bytes"] = int(d.get("bytes", 0))
        for name, e in d.get("by_type", {}).items():
            out[f"{direction}.{name}"] = int(e["bytes"])
    for key in ("retransmitted_messages", "retransmitted_bytes", "duplicates_dropped"):
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
                stop_on_reject=False,  # a refused keyframe is logged; the other robots go on
            )
        self.dropped_feedback = 0
        self.dropped_uplink = 0
        self.replayed_frames = 0
        self.address: tuple[str, int] | None = None

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
        if self.cloud is None:
            self.dropped_uplink += 1
            return
        await self.cloud.send(message)

    def link_counters(self, agent_id: str) -> dict[str, int]:
        peer = self.server.peers.get(agent_id)
        return {} if peer is None else flat_counters(peer.counters())

    # ------------------------------------------------------------------ lifecycle
    async def start(self, host: str = "127.0.0.1", port: int = 0) -> tuple[str, int]:
        """Connect to the cloud, replay the journals, then listen; returns the bound address."""
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

    async def stop(self) -> None:
        """Close the robots' connections, stop the workers, close journals and the cloud link."""
        await self.server.close()
        await self.app.close()
        if self.cloud is not None:
            await self.cloud.close()
        if self.store is not None:
            self.store.close()

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
            "cloud": None
            if self.cloud is None or self.cloud.peer is None
            else self.cloud.counters(),
        }
