"""Connecting and accepting sides of the asyncio transport (:class:`Client`, :class:`Server`).

See :mod:`common.transport` for the overview and usage."""

from __future__ import annotations

import asyncio
import contextlib
import logging
import ssl as ssl_module
from typing import Any

from common.protocol import (
    AuthenticationError,
    CloseCode,
    LocalProtocolError,
    Message,
    PeerAuthenticated,
    PeerRejectedError,
    PeerUnreachableError,
    Session,
    SessionConfig,
)
from common.protocol.link import Link
from common.protocol.store import DeliveryStore
from common.transport.connection import (
    Handler,
    Peer,
    TransportConfig,
    _Connection,
)
from common.transport.reconnect import GiveUp, ReconnectPolicy

logger = logging.getLogger(__name__)


class Client:
    """Connecting side of one link; keeps reconnecting (``reconnect.py``: backoff, a
    warning at the first failure and then every ``unreachable_warning_interval``) until
    :meth:`close`, or until the handshake fails authentication (a wrong key or secret cannot
    get better by retrying), or until it has had no session for
    ``TransportConfig.give_up_after`` seconds (when > 0). On those two it logs one ERROR line
    saying why, :attr:`failure` holds the error, :meth:`wait_failed` returns it and
    ``send``/``flush`` raise it (PeerRejectedError; PeerUnreachableError for the give-up), as
    they raise PeerRejectedError after the server's application refused a message of ours
    (``Reject``) when ``stop_on_reject`` (default; False logs the refusal and carries on).

    Args:
        config: protocol settings (role, agent id, secret, limits).
        handler: ``async def handler(delivery)``, called once per message from the server.
        host, port: server address.
        transport: socket-level settings.
        ssl: client ``SSLContext`` for TLS (None = plain TCP); ``server_hostname`` for SNI.
        store: durable inbound position (None = in memory only).
        server_name: key of this link in ``store``.
        link: an existing link to resume (e.g. restored outbox); default a fresh one.
        stop_on_reject: see above.
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
        stop_on_reject: bool = True,
    ) -> None:
        self.config = config
        self._stop_on_reject = stop_on_reject
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
        self._failure: PeerRejectedError | None = None
        self._failed = asyncio.Event()

    async def start(self) -> None:
        """Start connecting in the background (returns at once)."""
        if self._task is not None:
            raise LocalProtocolError("client already started")
        link = self._link
        if link is None:
            inbound = self._store.load(self._server_name) if self._store else None
            link = self.config.new_link(inbound=inbound, peer=self._server_name)
        self.peer = Peer(
            self._server_name,
            link,
            self._handler,
            self._store,
            self.transport,
            stop_on_reject=self._stop_on_reject,
        )
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

    @property
    def failure(self) -> PeerRejectedError | None:
        """Why the client stopped on its own (credential refused, or no session within
        ``give_up_after``), or None while it goes on or after :meth:`close`."""
        return self._failure

    async def wait_failed(self) -> PeerRejectedError:
        """Return once the client has stopped on its own; the error says why."""
        await self._failed.wait()
        assert self._failure is not None
        return self._failure

    def _fail(self, error: PeerRejectedError) -> None:
        logger.error("%s", error)  # the one line that says why the link was given up
        self._failure = error
        assert self.peer is not None
        self.peer.give_up(error)
        self._failed.set()

    async def _run(self) -> None:
        assert self.peer is not None
        t = self.transport
        loop = asyncio.get_running_loop()
        policy = ReconnectPolicy(t, loop.time())
        where = f"{self.host}:{self.port}"
        who = f"{self.config.role} {self.config.agent_id}"
        while not self._closing:
            established = False
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
                reason = f"cannot connect: {exc!r}" if not str(exc) else f"cannot connect: {exc}"
            else:
                self.connections += 1
                session = Session(self.config, client=True, now=loop.time(), link=self.peer.link)
                self._conn = _Connection(reader, writer, session, t, peer=self.peer)
                reason = await self._conn.run()
                established = self._conn.established_once
                closed, failure = self._conn.peer_closed, self._conn.failure
                self._conn = None
                refusal = None
                if isinstance(failure, AuthenticationError):
                    refusal = str(failure)
                elif closed is not None and closed.code == CloseCode.AUTH_FAILED:
                    refusal = f"{where} refused our credential: {closed.reason}"
                if refusal is not None:
                    self._fail(
                        PeerRejectedError(
                            f"{who}: authentication failed, not reconnecting (check "
                            f"--key-file / the secret): {refusal}"
                        )
                    )
                    break
            if self._closing:
                break
            step = policy.attempt_ended(loop.time(), established=established)
            if isinstance(step, GiveUp):
                self._fail(
                    PeerUnreachableError(
                        f"{who}: giving up on {where}: no session for {step.down_s:.1f} s "
                        f"({step.attempts} attempts; give-up time {t.give_up_after:g} s); "
                        f"last failure: {reason}"
                    )
                )
                break
            if step.warn:
                logger.warning(
                    "%s: no session with %s (%d attempts in %.0f s, retrying): %s",
                    who,
                    where,
                    step.attempts,
                    step.down_s,
                    reason,
                )
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(self._closed.wait(), step.delay)


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
        self._pending: dict[_Connection, None] = {}  # not authenticated yet, oldest first
        self._authed: dict[_Connection, str] = {}  # authenticated: the peer's agent id
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
        loop = asyncio.get_running_loop()
        session = Session(self.config, client=False, now=loop.time())
        conn = _Connection(
            reader, writer, session, self.transport, on_authenticated=self._authenticated
        )
        self._make_room_for(conn.source)
        self._connections.add(conn)
        self._pending[conn] = None
        try:
            await conn.run()
        finally:
            self._connections.discard(conn)
            self._pending.pop(conn, None)
            self._authed.pop(conn, None)

    def _make_room_for(self, source: str) -> None:
        """Drop the oldest unauthenticated connection of ``source`` if it holds its share,
        else of the busiest source if all pending places are taken."""
        t = self.transport
        by_source: dict[str, list[_Connection]] = {}
        for pending in self._pending:
            by_source.setdefault(pending.source, []).append(pending)
        mine = by_source.get(source, [])
        if len(mine) >= t.max_pending_per_source:
            victim, why = mine[0], f"{t.max_pending_per_source} from {source}"
        elif len(self._pending) >= t.max_pending:
            busiest = max(by_source.values(), key=len)
            victim, why = busiest[0], f"{t.max_pending} in all"
        else:
            return
        del self._pending[victim]
        logger.warning(
            "connections not authenticated yet: %s; dropping the oldest (%s)", why, victim.name
        )
        victim.abort("dropped before authenticating: newer connections arrived")

    async def _authenticated(self, conn: _Connection, ev: PeerAuthenticated) -> Peer | None:
        self._pending.pop(conn, None)
        roles = self.transport.accept_roles
        if roles is not None and ev.role not in roles:
            conn.session.refuse(CloseCode.REFUSED, f"role {ev.role!r} not served here")
            conn.kick()
            return None
        served = set(self._authed.values())
        if ev.agent_id not in served and len(served) >= self.transport.max_peers:
            logger.warning("refusing %s: %d peers connected", ev.agent_id, len(served))
            conn.session.refuse(
                CloseCode.REFUSED, f"server full ({self.transport.max_peers} peers)"
            )
            conn.kick()
            return None
        self._authed[conn] = ev.agent_id
        peer = self.peers.get(ev.agent_id)
        if peer is None:
            inbound = self._store.load(ev.agent_id) if self._store else None
            link = self.config.new_link(inbound=inbound, peer=ev.agent_id)
            peer = Peer(
                ev.agent_id, link, self._handler, self._store, self.transport, stop_on_reject=False
            )
            self.peers[ev.agent_id] = peer
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


def link_load(client: Client | None) -> tuple[int, int]:
    """A client's link to its server: (bytes unacknowledged, bytes acknowledged so far);
    (0, 0) before it started."""
    if client is None or client.peer is None:
        return 0, 0
    link = client.peer.link
    return link.outbox_bytes, link.acked_bytes
