"""asyncio transport for ``common.protocol``: TCP (optionally TLS) clients and servers.

The sans-I/O :class:`~common.protocol.session.Session` does the protocol; this module only
moves bytes, arms one timer per connection (``loop.call_at`` on ``Session.get_timer()``)
and runs the application's handler.

A service uses it like this::

    async def on_message(d: Delivery) -> None:      # runs once per message, in order
        ...                                          # when it returns, the message is acked

    server = Server(SessionConfig("edge", "edge-0", secret), on_message)
    host, port = await server.start("0.0.0.0", 7000)
    await server.send("robot-1", Blob(0, b"..."))    # waits while that outbox is full

    client = Client(SessionConfig("robot", "robot-1", secret), on_message, host, port)
    await client.start()                             # connects, reconnects with backoff
    seq = await client.send(Blob(0, b"..."))         # queued even while disconnected
    await client.flush()                             # until the peer's handler took all
    client.counters()                                # plain-data traffic counters

Delivery is exactly-once and in order per link across reconnects. Across a restart of the
receiving process it is exactly-once when a :class:`~common.protocol.store.DeliveryStore`
gives back the saved position (see ``common/protocol/store.py``). A handler that raises
does not ack: the connection is dropped and the message is redelivered after reconnect.
A handler that replies to the same peer should use ``send_nowait`` (or a separate task)
rather than await a full outbox: two handlers each waiting for the other to deliver would
wait forever. Agent ids must be unique: a second connection with the same id replaces the
first.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import random
import ssl as ssl_module
from collections.abc import Awaitable, Callable, Coroutine
from dataclasses import dataclass
from typing import Any, TypeVar

from common.protocol import (
    Acknowledged,
    CloseCode,
    HandshakeComplete,
    InboundPosition,
    LocalProtocolError,
    Message,
    MessageReceived,
    PeerAuthenticated,
    PeerClosed,
    ProtocolError,
    Session,
    SessionConfig,
    encode_frame,
)
from common.protocol.link import Link
from common.protocol.messages import Close, encode_payload
from common.protocol.store import DeliveryStore

logger = logging.getLogger(__name__)

T = TypeVar("T")


@dataclass(frozen=True)
class TransportConfig:
    """Socket-level settings (protocol limits live in ``SessionConfig``).

    Attributes:
        max_peers: concurrent connections a server accepts; more are refused with a reason.
        accept_roles: roles a server serves (None = any authenticated role).
        read_chunk_bytes: bytes per socket read.
        write_chunk_bytes: bytes of frames handed to the socket before awaiting drain.
        reconnect_initial_delay: first client reconnect delay (s), doubled per failure.
        reconnect_max_delay: cap of the reconnect delay (s).
        reconnect_jitter: each delay is multiplied by uniform(1 - j, 1 + j).
        connect_timeout: TCP (+TLS) connect timeout (s).
    """

    max_peers: int = 64
    accept_roles: tuple[str, ...] | None = None
    read_chunk_bytes: int = 256 * 1024
    write_chunk_bytes: int = 1024 * 1024
    reconnect_initial_delay: float = 0.05
    reconnect_max_delay: float = 5.0
    reconnect_jitter: float = 0.5
    connect_timeout: float = 10.0


@dataclass(frozen=True)
class Delivery:
    """One message handed to the application: from ``peer`` (agent id), stream position."""

    peer: str
    role: str
    message: Message
    seq: int
    stream_id: bytes


Handler = Callable[[Delivery], Awaitable[None]]


def run(main: Coroutine[Any, Any, T], *, use_uvloop: bool = True) -> T:
    """Run ``main`` on a fresh event loop, uvloop when installed."""
    factory = None
    if use_uvloop:
        try:
            import uvloop
        except ImportError:
            pass
        else:
            factory = uvloop.new_event_loop
    with asyncio.Runner(loop_factory=factory) as runner:
        return runner.run(main)


class Peer:
    """The link to one remote agent plus its runtime: senders, delivery task, connection."""

    def __init__(
        self, name: str, link: Link, handler: Handler, store: DeliveryStore | None
    ) -> None:
        self.agent_id = name
        self.role = ""
        self.link = link
        self._handler = handler
        self._store = store
        self._conn: _Connection | None = None
        self._space = asyncio.Event()
        self._established = asyncio.Event()
        self._inbox: asyncio.Queue[MessageReceived] = asyncio.Queue()
        self._delivery = asyncio.create_task(self._deliver_loop(), name=f"deliver-{name}")
        self.attach_lock = asyncio.Lock()

    @property
    def connected(self) -> bool:
        """True while an authenticated connection carries this link."""
        return self._conn is not None and self._conn.session.established

    def counters(self) -> dict[str, Any]:
        """Traffic counters of this link (plain data, see ``accounting.py``)."""
        snap = self.link.counters.snapshot()
        snap["outbox_messages"] = len(self.link.outbox)
        snap["outbox_bytes"] = self.link.outbox_bytes
        snap["connected"] = self.connected
        return snap

    def send_nowait(self, message: Message) -> int:
        """Queue ``message``; raises ``OutboxFullError`` instead of waiting."""
        seq = self.link.enqueue(message)
        self._kick()
        return seq

    async def send(self, message: Message) -> int:
        """Queue ``message`` (waits while the outbox is full) and return its sequence."""
        entry = self.link.encode(message)
        while not self.link.has_room(len(entry.payload)):
            self._space.clear()
            await self._space.wait()
        seq = self.link.enqueue(entry)
        self._kick()
        return seq

    async def flush(self) -> None:
        """Wait until the peer's application delivered everything queued so far."""
        target = self.link.next_seq - 1
        while self.link.first_unacked <= target:
            self._space.clear()
            await self._space.wait()

    async def wait_connected(self) -> None:
        await self._established.wait()

    # ------------------------------------------------------------------ internals
    def _kick(self) -> None:
        if self._conn is not None:
            self._conn.kick()

    def _attach(self, conn: _Connection) -> None:
        self._conn = conn

    def _detach(self, conn: _Connection) -> None:
        if self._conn is conn:
            self._conn = None
            self._established.clear()

    def _on_event(self, ev: object) -> None:
        if isinstance(ev, MessageReceived):
            self._inbox.put_nowait(ev)
        elif isinstance(ev, Acknowledged):
            self._space.set()
        elif isinstance(ev, HandshakeComplete):
            self.agent_id, self.role = ev.agent_id, ev.role
            self._established.set()
            self._space.set()

    async def _deliver_loop(self) -> None:
        while True:
            ev = await self._inbox.get()
            delivery = Delivery(self.agent_id, self.role, ev.message, ev.seq, ev.stream_id)
            try:
                await self._handler(delivery)
            except asyncio.CancelledError:
                raise
            except Exception:
                logger.exception(
                    "handler failed on %s seq %d from %s; dropping the connection, the "
                    "message will be redelivered",
                    type(ev.message).__name__,
                    ev.seq,
                    self.agent_id,
                )
                self._rewind()
                continue
            if ev.stream_id != self.link.in_stream_id:
                continue  # the peer restarted on a new stream meanwhile: nothing to ack
            if self._store is not None:
                self._store.save(self.agent_id, InboundPosition(ev.stream_id, ev.seq))
            conn = self._conn
            if conn is not None and conn.session.established:
                conn.session.mark_delivered(ev.seq, asyncio.get_running_loop().time())
                conn.kick()
                conn.arm_timer()
            else:
                self.link.mark_delivered(ev.seq)

    def _rewind(self) -> None:
        while not self._inbox.empty():
            self._inbox.get_nowait()
        self.link.rewind_inbound()
        if self._conn is not None:
            self._conn.close(CloseCode.HANDLER_FAILED, "handler failed; resume to redeliver")

    async def _stop(self) -> None:
        self._delivery.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await self._delivery


class _Connection:
    """Drives one Session over one asyncio stream pair."""

    def __init__(
        self,
        reader: asyncio.StreamReader,
        writer: asyncio.StreamWriter,
        session: Session,
        transport: TransportConfig,
        *,
        peer: Peer | None = None,
        on_authenticated: Callable[[_Connection, PeerAuthenticated], Awaitable[Peer | None]]
        | None = None,
    ) -> None:
        self.reader, self.writer, self.session = reader, writer, session
        self.transport = transport
        self.peer = peer
        self._on_authenticated = on_authenticated
        self._loop = asyncio.get_running_loop()
        self._wake = asyncio.Event()
        self._done: asyncio.Future[str] = self._loop.create_future()
        self._timer: asyncio.TimerHandle | None = None
        self._timer_at: float | None = None
        self.established_once = False
        info = writer.get_extra_info("peername")
        self.name = f"{info[0]}:{info[1]}" if isinstance(info, tuple) else str(info)
        if peer is not None:
            peer._attach(self)

    async def run(self) -> str:
        """Serve until the connection ends; returns the reason."""
        self.kick()
        self.arm_timer()
        tasks = [
            asyncio.create_task(self._read_loop(), name=f"read-{self.name}"),
            asyncio.create_task(self._write_loop(), name=f"write-{self.name}"),
        ]
        try:
            return await asyncio.shield(self._done)
        finally:
            # synchronous part first, so that a cancelled caller still releases everything
            for task in tasks:
                task.cancel()
            if self._timer is not None:
                self._timer.cancel()
            if self.peer is not None:
                self.peer._detach(self)
            with contextlib.suppress(OSError, RuntimeError, ssl_module.SSLError):
                self.writer.writelines(self.session.data_to_send(self._loop.time()))
            self.writer.close()
            await asyncio.gather(*tasks, return_exceptions=True)
            with contextlib.suppress(OSError, TimeoutError, ssl_module.SSLError):
                await asyncio.wait_for(self.writer.wait_closed(), 1.0)

    def kick(self) -> None:
        self._wake.set()

    def close(self, code: CloseCode, reason: str) -> None:
        """Send Close and end the connection once it is written."""
        self.session.close(code, reason)
        self.kick()

    def abort(self, reason: str) -> None:
        self._finish(reason)

    @property
    def finished(self) -> asyncio.Future[str]:
        return self._done

    def arm_timer(self) -> None:
        when = self.session.get_timer()
        if when == self._timer_at and self._timer is not None:
            return
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None
        self._timer_at = when
        if when is not None:
            self._timer = self._loop.call_at(when, self._on_timer)

    def _on_timer(self) -> None:
        self._timer = None
        self._timer_at = None
        try:
            self.session.handle_timer(self._loop.time())
        except ProtocolError as exc:
            self._finish(f"{type(exc).__name__}: {exc}", level=logging.WARNING)
            return
        self.kick()
        self.arm_timer()

    def _finish(self, reason: str, level: int = logging.INFO) -> None:
        if not self._done.done():
            logger.log(level, "connection %s (%s) closed: %s", self.name, self._who(), reason)
            self.session.close(CloseCode.NORMAL, reason)  # stop driving the link at once
            self._done.set_result(reason)

    def _who(self) -> str:
        return self.session.peer_agent_id or "unauthenticated"

    async def _read_loop(self) -> None:
        try:
            while True:
                data = await self.reader.read(self.transport.read_chunk_bytes)
                if not data:
                    self._finish(self.session.close_reason or "connection closed by peer")
                    return
                try:
                    self.session.receive_data(data, self._loop.time())
                except ProtocolError as exc:
                    self._finish(f"{type(exc).__name__}: {exc}", level=logging.WARNING)
                    return
                await self._process_events()
                self.kick()
                self.arm_timer()
        except (OSError, ssl_module.SSLError) as exc:
            self._finish(f"read failed: {exc!r}")

    async def _process_events(self) -> None:
        while (ev := self.session.next_event()) is not None:
            if isinstance(ev, PeerAuthenticated):
                assert self._on_authenticated is not None
                peer = await self._on_authenticated(self, ev)
                if peer is None or self.session.closed:
                    return
                self.peer = peer
                peer._attach(self)
                try:
                    self.session.attach(peer.link, self._loop.time())
                except ProtocolError as exc:
                    self._finish(f"{type(exc).__name__}: {exc}", level=logging.WARNING)
                    return
            elif isinstance(ev, PeerClosed):
                self._finish(f"peer closed (code {ev.code}): {ev.reason}")
            else:
                if isinstance(ev, HandshakeComplete):
                    self.established_once = True
                    logger.info(
                        "link %s (%s) established via %s, replaying %d",
                        ev.agent_id,
                        ev.role,
                        self.name,
                        ev.replay,
                    )
                if self.peer is not None:
                    self.peer._on_event(ev)

    async def _write_loop(self) -> None:
        try:
            while True:
                self._wake.clear()
                chunks = self.session.data_to_send(
                    self._loop.time(), self.transport.write_chunk_bytes
                )
                if chunks:
                    self.writer.writelines(chunks)
                    await self.writer.drain()
                    self.arm_timer()
                    continue
                if self.session.closed:
                    self._finish(self.session.close_reason or "closed")
                    return
                await self._wake.wait()
        except (OSError, RuntimeError, ssl_module.SSLError) as exc:
            self._finish(f"write failed: {exc!r}")


def _jittered(delay: float, jitter: float) -> float:
    return delay * random.uniform(1.0 - jitter, 1.0 + jitter)


class Client:
    """Connecting side of one link; keeps reconnecting until :meth:`close`.

    Args:
        config: protocol settings (role, agent id, secret, limits).
        handler: ``async def handler(delivery)``, called once per message from the server.
        host, port: server address.
        transport: socket-level settings.
        ssl: client ``SSLContext`` for TLS (None = plain TCP); ``server_hostname`` for SNI.
        store: durable inbound position (None = in memory only).
        server_name: key of this link in ``store``.
        link: an existing link to resume (e.g. restored outbox); default a fresh one.
    """

    def __init__(
        self,
        config: SessionConfig,
        handler: Handler,
        host: str,
        port: int,
        *,
        transport: TransportConfig | None = None,
        ssl: ssl_module.SSLContext | None = None,
        server_hostname: str | None = None,
        store: DeliveryStore | None = None,
        server_name: str = "server",
        link: Link | None = None,
    ) -> None:
        self.config = config
        self.transport = transport or TransportConfig()
        self.host, self.port = host, port
        self._ssl, self._server_hostname = ssl, server_hostname
        self._handler, self._store, self._server_name = handler, store, server_name
        self._link = link
        self.peer: Peer | None = None
        self._task: asyncio.Task[None] | None = None
        self._closing = False
        self._closed = asyncio.Event()
        self._conn: _Connection | None = None
        self.connections = 0

    async def start(self) -> None:
        """Start connecting in the background (returns at once)."""
        if self._task is not None:
            raise LocalProtocolError("client already started")
        link = self._link
        if link is None:
            inbound = self._store.load(self._server_name) if self._store else None
            link = self.config.new_link(inbound=inbound, peer=self._server_name)
        self.peer = Peer(self._server_name, link, self._handler, self._store)
        self._task = asyncio.create_task(self._run(), name=f"client-{self.config.agent_id}")

    async def wait_connected(self, timeout: float | None = None) -> None:
        assert self.peer is not None, "start() first"
        await asyncio.wait_for(self.peer.wait_connected(), timeout)

    async def send(self, message: Message) -> int:
        assert self.peer is not None, "start() first"
        return await self.peer.send(message)

    async def flush(self) -> None:
        assert self.peer is not None, "start() first"
        await self.peer.flush()

    def counters(self) -> dict[str, Any]:
        assert self.peer is not None, "start() first"
        return self.peer.counters()

    def cut(self) -> None:
        """Drop the current connection abruptly (tests, benchmarks); it will reconnect."""
        if self._conn is not None:
            self._conn.writer.transport.abort()

    async def close(self) -> None:
        """Close the connection (sending Close) and stop reconnecting."""
        self._closing = True
        self._closed.set()
        if self._conn is not None:
            self._conn.close(CloseCode.NORMAL, "client closing")
        if self._task is not None:
            done, _ = await asyncio.wait([self._task], timeout=3.0)
            if not done:
                self._task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._task
        if self.peer is not None:
            await self.peer._stop()

    async def _run(self) -> None:
        assert self.peer is not None
        t = self.transport
        delay = t.reconnect_initial_delay
        loop = asyncio.get_running_loop()
        while not self._closing:
            try:
                reader, writer = await asyncio.wait_for(
                    asyncio.open_connection(
                        self.host,
                        self.port,
                        ssl=self._ssl,
                        server_hostname=self._server_hostname if self._ssl else None,
                        limit=t.read_chunk_bytes,
                    ),
                    t.connect_timeout,
                )
            except (OSError, TimeoutError, ssl_module.SSLError) as exc:
                logger.info("connect to %s:%d failed: %r", self.host, self.port, exc)
            else:
                self.connections += 1
                session = Session(self.config, client=True, now=loop.time(), link=self.peer.link)
                self._conn = _Connection(reader, writer, session, t, peer=self.peer)
                await self._conn.run()
                if self._conn.established_once:
                    delay = t.reconnect_initial_delay
                self._conn = None
            if self._closing:
                break
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(self._closed.wait(), _jittered(delay, t.reconnect_jitter))
            delay = min(2 * delay, t.reconnect_max_delay)


class Server:
    """Accepting side: one :class:`Peer` per client agent id; peers join and leave freely.

    Args:
        config: protocol settings of this server.
        handler: ``async def handler(delivery)``, called once per message, in order per peer.
        transport: socket-level settings (max peers, accepted roles).
        ssl: server ``SSLContext`` for TLS (None = plain TCP).
        store: durable inbound positions per client agent id (None = in memory only).
    """

    def __init__(
        self,
        config: SessionConfig,
        handler: Handler,
        *,
        transport: TransportConfig | None = None,
        ssl: ssl_module.SSLContext | None = None,
        store: DeliveryStore | None = None,
    ) -> None:
        self.config = config
        self.transport = transport or TransportConfig()
        self._handler, self._ssl, self._store = handler, ssl, store
        self.peers: dict[str, Peer] = {}
        self._connections: set[_Connection] = set()
        self._tasks: set[asyncio.Task[Any]] = set()
        self._server: asyncio.base_events.Server | None = None
        self.address: tuple[str, int] | None = None

    async def start(self, host: str = "127.0.0.1", port: int = 0) -> tuple[str, int]:
        """Listen; returns the bound (host, port)."""
        self._server = await asyncio.start_server(
            self._on_client,
            host,
            port,
            ssl=self._ssl,
            ssl_handshake_timeout=self.config.handshake_timeout if self._ssl else None,
            limit=self.transport.read_chunk_bytes,
        )
        sockname = self._server.sockets[0].getsockname()
        self.address = (sockname[0], sockname[1])
        logger.info("listening on %s:%d (tls=%s)", *self.address, self._ssl is not None)
        return self.address

    def peer(self, agent_id: str) -> Peer:
        """The peer with this agent id (LocalProtocolError if it never connected)."""
        try:
            return self.peers[agent_id]
        except KeyError:
            raise LocalProtocolError(f"no peer {agent_id!r} has connected") from None

    async def send(self, agent_id: str, message: Message) -> int:
        """Queue ``message`` for ``agent_id`` (waits while its outbox is full)."""
        return await self.peer(agent_id).send(message)

    async def forget(self, agent_id: str) -> None:
        """Drop a peer that left for good: close its connection, discard its link state
        (unacknowledged messages to it are lost; its next connection starts afresh)."""
        peer = self.peers.pop(agent_id, None)
        if peer is None:
            return
        if peer._conn is not None:
            peer._conn.close(CloseCode.NORMAL, "forgotten by the server")
            with contextlib.suppress(asyncio.TimeoutError):
                await asyncio.wait_for(asyncio.shield(peer._conn.finished), 2.0)
        await peer._stop()

    def counters(self) -> dict[str, dict[str, Any]]:
        """Per-peer traffic counters, keyed by agent id (plain data)."""
        return {agent: peer.counters() for agent, peer in self.peers.items()}

    def cut_all(self) -> None:
        """Abort every connection abruptly (tests, benchmarks)."""
        for conn in list(self._connections):
            conn.writer.transport.abort()

    async def close(self) -> None:
        """Stop listening, close every connection with a reason, stop deliveries."""
        if self._server is not None:
            self._server.close()
        for conn in list(self._connections):
            conn.close(CloseCode.NORMAL, "server shutting down")
        if self._tasks:
            await asyncio.wait(list(self._tasks), timeout=2.0)
        for task in list(self._tasks):
            task.cancel()
        await asyncio.gather(*self._tasks, return_exceptions=True)
        for peer in self.peers.values():
            await peer._stop()
        if self._server is not None:
            await self._server.wait_closed()

    async def __aenter__(self) -> Server:
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()

    async def _on_client(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        task = asyncio.current_task()
        assert task is not None
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)
        if len(self._connections) >= self.transport.max_peers:
            logger.warning("refusing connection: %d peers connected", len(self._connections))
            reason = f"server full ({self.transport.max_peers} peers)"
            with contextlib.suppress(OSError, RuntimeError):
                close = Close(int(CloseCode.REFUSED), reason)
                writer.write(encode_frame(Close.TYPE_ID, encode_payload(close)))
                writer.close()
                await writer.wait_closed()
            return
        loop = asyncio.get_running_loop()
        session = Session(self.config, client=False, now=loop.time())
        conn = _Connection(
            reader, writer, session, self.transport, on_authenticated=self._authenticated
        )
        self._connections.add(conn)
        try:
            await conn.run()
        finally:
            self._connections.discard(conn)

    async def _authenticated(self, conn: _Connection, ev: PeerAuthenticated) -> Peer | None:
        roles = self.transport.accept_roles
        if roles is not None and ev.role not in roles:
            conn.session.refuse(CloseCode.REFUSED, f"role {ev.role!r} not served here")
            conn.kick()
            return None
        peer = self.peers.get(ev.agent_id)
        if peer is None:
            inbound = self._store.load(ev.agent_id) if self._store else None
            link = self.config.new_link(inbound=inbound, peer=ev.agent_id)
            peer = self.peers[ev.agent_id] = Peer(ev.agent_id, link, self._handler, self._store)
        async with peer.attach_lock:
            old = peer._conn
            if old is not None and old is not conn:
                logger.info("agent %s reconnected; closing its previous connection", ev.agent_id)
                old.close(CloseCode.REPLACED, "replaced by a newer connection")
                with contextlib.suppress(asyncio.TimeoutError):
                    await asyncio.wait_for(asyncio.shield(old.finished), 2.0)
                old.abort("replaced")
                await asyncio.sleep(0)
        return peer
