"""Connection machinery of the asyncio transport: settings, deliveries, one peer's link
and the per-connection reader/writer/timer (:class:`Peer`, :class:`_Connection`).

See :mod:`common.transport` for the overview and usage."""

from __future__ import annotations

import asyncio
import contextlib
import functools
import logging
import ssl as ssl_module
from collections.abc import Awaitable, Callable, Coroutine
from dataclasses import dataclass
from typing import Any, TypeVar

from common.protocol import (
    Acknowledged,
    CloseCode,
    HandshakeComplete,
    InboundPosition,
    Message,
    MessageReceived,
    PeerAuthenticated,
    PeerClosed,
    PeerRejected,
    PeerRejectedError,
    ProtocolError,
    RejectedMessageError,
    Session,
)
from common.protocol.link import Link
from common.protocol.store import DeliveryStore

logger = logging.getLogger(__name__)

T = TypeVar("T")


@dataclass(frozen=True)
class TransportConfig:
    """Socket-level settings (protocol limits live in ``SessionConfig``).

    Attributes:
        max_peers: authenticated peers a server serves at once; one more is refused with a
            reason once it has authenticated (a known peer reconnecting always gets in).
        max_pending: connections a server holds that have not authenticated yet (each for
            at most the handshake timeout); a newcomer beyond this drops the oldest pending
            connection of the source address that holds the most, so sockets that connect
            and stall cannot keep peers out: they are counted apart from the peers and only
            ever push each other out.
        max_pending_per_source: likewise per source address: a newcomer beyond this drops
            the oldest pending connection from the same address.
        accept_roles: roles a server serves (None = any authenticated role).
        read_chunk_bytes: bytes per socket read.
        write_chunk_bytes: bytes of frames handed to the socket before awaiting drain.
        reconnect_initial_delay: first client reconnect delay (s), doubled per failure.
        reconnect_max_delay: cap of the reconnect delay (s).
        reconnect_jitter: each delay is multiplied by uniform(1 - j, 1 + j).
        connect_timeout: TCP (+TLS) connect timeout (s).
        unreachable_warning_interval: a client that cannot connect warns at the first
            failure and then at most this often (s), with the attempt count.
        give_up_after: a client that has had no session with its server for this long (s;
            since it started or since its last session ended: the server unreachable,
            timing out or closing before the handshake) stops reconnecting, logs one line
            why and raises PeerUnreachableError from ``send`` and ``flush``; 0 = never
            (see ``reconnect.py``). A refused credential stops it at once either way.
        handler_retry_initial: a handler that raised (other than ``RejectedMessageError``,
            e.g. a full disk) is retried on the same connection after this delay (s),
            doubled per failure; the sender is held back by the receive window meanwhile.
        handler_retry_max: cap of that delay (s).
    """

    max_peers: int = 64
    max_pending: int = 256
    max_pending_per_source: int = 32
    accept_roles: tuple[str, ...] | None = None
    read_chunk_bytes: int = 256 * 1024
    write_chunk_bytes: int = 1024 * 1024
    reconnect_initial_delay: float = 0.05
    reconnect_max_delay: float = 5.0
    reconnect_jitter: float = 0.5
    connect_timeout: float = 10.0
    unreachable_warning_interval: float = 30.0
    give_up_after: float = 0.0
    handler_retry_initial: float = 0.5
    handler_retry_max: float = 30.0


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
    """The link to one remote agent plus its runtime: senders, delivery task, connection.

    Handler failures are split by blame. ``RejectedMessageError`` (the sender's fault: an
    undecodable payload, a calibration that does not fit, a message about an agent the
    sender does not serve): that message counts as delivered, the sender gets a ``Reject``
    with the reason and never resends it. Any other exception (a local fault: disk full,
    read-only state, a bug): the same delivery is retried with a doubling delay on the same
    connection, while the receive window holds the sender back: no reconnect, no replay.

    Args:
        stop_on_reject: when the peer rejects one of *our* messages, later ``send`` and
            ``flush`` calls raise PeerRejectedError (a robot: its stream cannot go on
            without that message); False logs the reason and carries on (an edge's uplink).
    """

    def __init__(
        self,
        name: str,
        link: Link,
        handler: Handler,
        store: DeliveryStore | None,
        transport: TransportConfig | None = None,
        *,
        stop_on_reject: bool = True,
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
        self.rejected: str | None = None  # the peer's reason when it refused our message
        self._given_up: PeerRejectedError | None = None  # why our client stopped on its own
        self.rejections: list[tuple[int, str]] = []  # (seq, reason) the peer refused, latest 100
        self.stop_on_reject = stop_on_reject
        self._transport = transport or TransportConfig()
        self.handler_failures = 0

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
            self._check_rejected()
            self._space.clear()
            await self._space.wait()
        self._check_rejected()
        seq = self.link.enqueue(entry)
        self._kick()
        return seq

    async def flush(self) -> None:
        """Wait until the peer's application delivered everything queued so far."""
        target = self.link.next_seq - 1
        while self.link.first_unacked <= target:
            self._check_rejected()
            self._space.clear()
            await self._space.wait()
        self._check_rejected()  # a message was refused (and so counts as acknowledged)

    def reject(self, reason: str) -> None:
        """Give the link up with ``reason`` (the peer refused a message of ours or our
        credential): senders and flushers waiting on it raise PeerRejectedError from now on."""
        self.rejected = reason
        self._space.set()

    def give_up(self, error: PeerRejectedError) -> None:
        """Give the link up because our client stopped trying (its credential refused, or
        no session within its give-up time): senders and flushers raise ``error``."""
        self._given_up = error
        self.rejected = str(error)
        self._space.set()

    def _check_rejected(self) -> None:
        if self._given_up is not None:
            raise self._given_up
        if self.rejected is not None:
            raise PeerRejectedError(f"{self.agent_id} refused our message: {self.rejected}")

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
        elif isinstance(ev, PeerRejected):
            logger.error("%s refused our message seq %d: %s", self.agent_id, ev.seq, ev.reason)
            self.rejections = [*self.rejections[-99:], (ev.seq, ev.reason)]
            if self.stop_on_reject:
                self.reject(ev.reason)

    async def _deliver_loop(self) -> None:
        while True:
            ev = await self._inbox.get()
            delivery = Delivery(self.agent_id, self.role, ev.message, ev.seq, ev.stream_id)
            refused: str | None = None
            try:
                await self._retrying(ev, functools.partial(self._handler, delivery), "handler")
            except RejectedMessageError as exc:  # the sender's fault: refuse it, once
                refused = str(exc)
                logger.warning(
                    "%s seq %d from %s refused: %s (the sender is told; not redelivered)",
                    type(ev.message).__name__,
                    ev.seq,
                    self.agent_id,
                    refused,
                )
            except _StaleDeliveryError:
                continue
            if ev.stream_id != self.link.in_stream_id:
                continue  # the peer restarted on a new stream meanwhile: nothing to ack
            store = self._store
            if store is not None:
                position = InboundPosition(ev.stream_id, ev.seq)
                try:
                    await self._retrying(
                        ev, _awaitable(store.save, self.agent_id, position), "save"
                    )
                except _StaleDeliveryError:
                    continue
            conn = self._conn
            now = asyncio.get_running_loop().time()
            if conn is not None and conn.session.established:
                if refused is None:
                    conn.session.mark_delivered(ev.seq, now)
                else:
                    conn.session.reject(ev.seq, refused, now)
                conn.kick()
                conn.arm_timer()
            else:
                self.link.mark_delivered(ev.seq)

    async def _retrying(
        self, ev: MessageReceived, action: Callable[[], Awaitable[None]], what: str
    ) -> None:
        """Run ``action`` until it succeeds; RejectedMessageError propagates (the sender's
        fault), anything else is a local fault retried with a doubling, capped delay."""
        delay = self._transport.handler_retry_initial
        failures = 0
        while True:
            try:
                await action()
                return
            except (asyncio.CancelledError, RejectedMessageError):
                raise
            except Exception as exc:
                failures += 1
                self.handler_failures += 1
                name = type(ev.message).__name__
                if failures == 1:
                    logger.exception(
                        "%s failed on %s seq %d from %s; retrying in %.1fs (held back, "
                        "nothing is lost)",
                        what,
                        name,
                        ev.seq,
                        self.agent_id,
                        delay,
                    )
                else:
                    logger.error(
                        "%s still failing on %s seq %d from %s after %d attempts: %s: %s; "
                        "retrying in %.1fs",
                        what,
                        name,
                        ev.seq,
                        self.agent_id,
                        failures,
                        type(exc).__name__,
                        exc,
                        delay,
                    )
            await asyncio.sleep(delay)
            delay = min(2 * delay, self._transport.handler_retry_max)
            if ev.stream_id != self.link.in_stream_id:
                raise _StaleDeliveryError

    async def _stop(self) -> None:
        self._delivery.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await self._delivery


class _StaleDeliveryError(Exception):
    """The peer moved to a new stream while a delivery was being retried: drop it."""


def _awaitable(fn: Callable[..., None], *args: Any) -> Callable[[], Awaitable[None]]:
    async def call() -> None:
        fn(*args)

    return call


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
        self.peer_closed: PeerClosed | None = None  # the peer's Close, when it sent one
        self.failure: ProtocolError | None = None  # what the peer did wrong, if anything
        info = writer.get_extra_info("peername")
        self.name = f"{info[0]}:{info[1]}" if isinstance(info, tuple) else str(info)
        self.source = str(info[0]) if isinstance(info, tuple) else self.name
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
                    self.failure = exc
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
                self.peer_closed = ev
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
