"""Session: handshake and reliability state machine for one connection (sans-I/O).

Like h11/aioquic, a :class:`Session` never touches a socket or a clock: bytes go in with
:meth:`Session.receive_data`, events come out of :meth:`Session.next_event`, bytes to write
come from :meth:`Session.data_to_send`, and time enters only as the ``now`` argument
(seconds, any monotonic origin) with :meth:`Session.get_timer` / :meth:`Session.handle_timer`.

Handshake: Hello, Challenge, Auth, then Welcome (drawn in :mod:`common.protocol.handshake`,
which holds the states and the authentication steps); every legal transition is in
``_TRANSITIONS``, and every frame after Auth is sealed (``sealing.py``).

Reliability: application messages sit in the link's outbox until the peer's *application*
delivered them (the receiver acks after ``mark_delivered``, never on arrival); acks are
cumulative and ride in every frame header (explicit ``Ack`` after ``ack_delay`` or
``ack_every`` deliveries); on (re)connect both sides exchange stream ids, first unacked and
last delivered sequences and the sender replays everything unacknowledged; duplicates are
dropped; the oldest in-flight message is retransmitted on timeout with exponential backoff,
but only to a peer silent since (``recovery.py``: on a live TCP connection a late ack is a busy
handler, not a loss; the timeout adapts to the measured time to an ack);
heartbeats keep an idle link alive and silence beyond ``idle_timeout`` is a dead peer.
The receiver bounds what it holds with a window (messages and bytes) that the sender honours.
"""

from __future__ import annotations

import logging
from collections import deque
from collections.abc import Callable

from common.protocol import auth, sealing
from common.protocol.accounting import TrafficCounters
from common.protocol.config import SessionConfig
from common.protocol.errors import (
    AuthenticationError,
    LocalProtocolError,
    PeerTimeoutError,
    ProtocolError,
    RemoteProtocolError,
)
from common.protocol.events import (
    Acknowledged,
    CloseCode,
    Event,
    HandshakeComplete,
    MessageReceived,
    PeerClosed,
    PeerRejected,
)
from common.protocol.framing import (
    FLAG_RETRANSMIT,
    PROTOCOL_VERSION,
    Frame,
    FrameDecoder,
    encode_frame,
)
from common.protocol.handshake import Handshake, State
from common.protocol.link import Link
from common.protocol.messages import (
    SCHEMA_VERSION,
    Ack,
    Auth,
    Challenge,
    Close,
    Heartbeat,
    Hello,
    Message,
    Reject,
    Welcome,
    decode_payload,
    encode_payload,
    message_class,
)
from common.protocol.recovery import RetransmitTimer

logger = logging.getLogger(__name__)

HANDSHAKE_MAX_FRAME = 4096  # bytes; handshake frames are < 300 B


class Session(Handshake):
    """One connection's protocol state. See the module docstring.

    Args:
        config: endpoint settings.
        client: True for the connecting side.
        now: current time (s).
        link: the client's link (required for clients; servers get it via ``attach``).
        nonce_factory: source of handshake nonces (tests may pass a deterministic one).
    """

    def __init__(
        self,
        config: SessionConfig,
        *,
        client: bool,
        now: float,
        link: Link | None = None,
        nonce_factory: Callable[[], bytes] = auth.new_nonce,
    ) -> None:
        if client and link is None:
            raise LocalProtocolError("a client session needs its Link")
        self.config = config
        self.client = client
        self.link = link
        self.counters = link.counters if link is not None else TrafficCounters()
        self.counters.connections += 1
        self.peer_role: str | None = None
        self.peer_agent_id: str | None = None
        self.close_reason: str | None = None
        # until the peer is authenticated only small handshake frames are accepted, so an
        # unauthenticated connection can make us buffer at most HANDSHAKE_MAX_FRAME bytes
        self._decoder = FrameDecoder(min(HANDSHAKE_MAX_FRAME, config.max_frame_size))
        self._events: deque[Event] = deque()
        self._out: list[bytes] = []
        self._nonce = nonce_factory()
        self._hello_payload = b""
        self._challenge_payload = b""
        self._key = config.own_credential() if client else b""  # the client's credential
        self._keys = sealing.ConnectionKeys()  # frame sealing, once the handshake agreed
        self._hello: Hello | None = None
        self._handshake_deadline: float | None = now + config.handshake_timeout
        self._last_rx = now
        self._last_tx = now
        self._last_run = now  # the last call of ours: time we were not running is not silence
        self._ack_sent = 0
        self._ack_deadline: float | None = None
        self._recovery = RetransmitTimer(config.retransmit_timeout, config.max_retransmit_timeout)
        self._next_tx = 1
        self._inflight_bytes = 0
        self._peer_window = (1, 1)
        self.state = State.HELLO_SENT if client else State.AWAIT_HELLO
        if client:
            assert link is not None
            hello = Hello(
                PROTOCOL_VERSION,
                SCHEMA_VERSION,
                config.role,
                config.agent_id,
                self._nonce,
                link.out_stream_id,
                link.first_unacked,
                link.in_stream_id,
                link.last_delivered,
                config.window_messages,
                config.window_bytes,
            )
            self._hello_payload = encode_payload(hello)
            self._emit_payload(Hello, self._hello_payload)

    # ------------------------------------------------------------------ public API
    @property
    def established(self) -> bool:
        return self.state is State.ESTABLISHED

    @property
    def closed(self) -> bool:
        return self.state is State.CLOSED

    def receive_data(self, data: bytes, now: float) -> None:
        """Feed bytes from the connection. Raises RemoteProtocolError on a bad peer."""
        if self.state is State.CLOSED:
            return
        self._attend(now)
        try:
            self._decoder.receive_data(data)
            while self.state is not State.CLOSED:
                frame = self._decoder.next_frame()
                if frame is None:
                    break
                self._handle_frame(frame, now)
        except RemoteProtocolError as exc:
            code = (
                CloseCode.AUTH_FAILED
                if isinstance(exc, AuthenticationError)
                else CloseCode.PROTOCOL_ERROR
            )
            self._fail(exc, code)

    def next_event(self) -> Event | None:
        """Next pending event, or None."""
        return self._events.popleft() if self._events else None

    def attach(self, link: Link, now: float) -> None:
        """Server: bind the authenticated peer to its link and finish the handshake."""
        if self.client or self.state is not State.AUTHENTICATED:
            raise LocalProtocolError(f"attach() in state {self.state.value}")
        assert self._hello is not None
        self.link = link
        link.peer = self.peer_agent_id
        link.counters.merge(self.counters)
        self.counters = link.counters
        hello = self._hello
        welcome = Welcome(
            link.out_stream_id,
            link.first_unacked,
            link.in_stream_id,
            link.last_delivered,
            self.config.window_messages,
            self.config.window_bytes,
        )
        try:
            self._resume(
                hello.out_stream_id,
                hello.first_unacked,
                hello.in_stream_id,
                hello.last_delivered,
                (hello.window_messages, hello.window_bytes),
            )
        except RemoteProtocolError as exc:
            self._fail(exc, CloseCode.PROTOCOL_ERROR)
        self._emit(welcome)
        self._establish()

    def refuse(self, code: CloseCode, reason: str) -> None:
        """Server: decline an authenticated peer (e.g. too many peers, role not served)."""
        self.close(code, reason)

    def close(self, code: CloseCode = CloseCode.NORMAL, reason: str = "") -> None:
        """Queue a Close frame and stop (idempotent)."""
        if self.state is State.CLOSED:
            return
        self._emit(Close(int(code), reason[:200]))
        self.state = State.CLOSED
        self.close_reason = self.close_reason or f"closed locally: {reason}"

    def mark_delivered(self, seq: int, now: float) -> None:
        """The application handled message ``seq``; it will be acknowledged."""
        assert self.link is not None
        self.link.mark_delivered(seq)
        if self.state is not State.ESTABLISHED:
            return
        threshold = min(self.config.ack_every, max(1, self.config.window_messages // 2))
        if self.link.last_delivered - self._ack_sent >= threshold:
            self._emit(Ack())
        elif self._ack_deadline is None:
            self._ack_deadline = now + self.config.ack_delay

    def reject(self, seq: int, reason: str, now: float) -> None:
        """The application refused message ``seq`` for good: it counts as delivered (it is
        acknowledged and never redelivered) and the peer is told why with a ``Reject``."""
        self.mark_delivered(seq, now)
        if self.state is State.ESTABLISHED:
            self._emit(Reject(seq, reason[:500]))

    def data_to_send(self, now: float, limit: int = 1 << 20) -> list[bytes]:
        """Frames to write, in order: queued control frames, then outbox entries in window.

        Returns at most about ``limit`` bytes of application frames per call.
        """
        if self.state is State.ESTABLISHED:
            self._transmit_outbox(limit, now)
        out, self._out = self._out, []
        if out:
            self._last_tx = now
            if (
                self.state is State.ESTABLISHED
                and self._recovery.deadline is None
                and self._next_tx > self._first_inflight()
            ):
                self._recovery.arm(now)
        return out

    def get_timer(self) -> float | None:
        """Earliest time at which :meth:`handle_timer` must run, or None."""
        if self.state is State.CLOSED:
            return None
        if self.state is not State.ESTABLISHED:
            return self._handshake_deadline
        times = [
            self._last_rx + self.config.idle_timeout,
            self._last_tx + self.config.heartbeat_interval,
        ]
        if self._ack_deadline is not None:
            times.append(self._ack_deadline)
        if self._recovery.deadline is not None:
            times.append(self._recovery.deadline)
        return min(times)

    def handle_timer(self, now: float) -> None:
        """Run due timers. Raises PeerTimeoutError for a dead peer or a stalled handshake."""
        if self.state is State.CLOSED:
            return
        self._attend(now)
        if self.state is not State.ESTABLISHED:
            if self._handshake_deadline is not None and now >= self._handshake_deadline:
                limit = self.config.handshake_timeout
                self._fail(
                    PeerTimeoutError(f"handshake not complete after {limit}s"), CloseCode.TIMEOUT
                )
            return
        if now >= self._last_rx + self.config.idle_timeout:
            self._fail(
                PeerTimeoutError(f"peer silent for {now - self._last_rx:.1f}s"), CloseCode.TIMEOUT
            )
        if self._ack_deadline is not None and now >= self._ack_deadline:
            self._emit(Ack())
        late = self._recovery.late_acks
        if self._recovery.due(now, self._last_rx):
            self._retransmit_oldest(now)
        self.counters.late_acks += self._recovery.late_acks - late
        if now >= self._last_tx + self.config.heartbeat_interval and not self._out:
            self._emit(Heartbeat())
            self._last_tx = now

    # --------------------------------------------------------------- frame handling
    def _handle_frame(self, frame: Frame, now: float) -> None:
        cls = message_class(frame.type_id)
        self._last_rx = now
        self.counters.record("rx", cls.__name__, frame.size)
        # the one unsealed frame allowed after Auth: the server refused it, so had no keys
        refused = cls is Close and self.state is State.AUTH_SENT
        frame = self._keys.open(frame, cls.__name__, unsealed_ok=refused)
        if not cls.CONTROL:
            self._on_application(cls, frame)
        else:
            if frame.seq != 0:
                raise RemoteProtocolError(f"control frame {cls.__name__} with seq {frame.seq}")
            method = _TRANSITIONS.get((self.client, self.state, cls))
            if method is None and cls is Close:
                method = Session._on_close
            if method is None:
                raise RemoteProtocolError(
                    f"{cls.__name__} not allowed in state {self.state.value} "
                    f"({'client' if self.client else 'server'})"
                )
            method(self, decode_payload(frame.type_id, frame.payload), frame)
        if self.state is State.ESTABLISHED:
            self._on_ack(frame.ack, now)

    def _on_application(self, cls: type[Message], frame: Frame) -> None:
        if self.state is not State.ESTABLISHED:
            raise RemoteProtocolError(
                f"application message {cls.__name__} before authentication "
                f"(state {self.state.value})"
            )
        link = self.link
        assert link is not None
        if frame.seq <= link.last_accepted:
            self.counters.duplicates_dropped += 1
            if self._ack_deadline is None:
                self._ack_deadline = self._last_rx + self.config.ack_delay
            return
        if frame.seq != link.last_accepted + 1:
            raise RemoteProtocolError(
                f"sequence gap: got {frame.seq}, expected {link.last_accepted + 1}"
            )
        size = len(frame.payload)
        window_messages, window_bytes = self.config.window_messages, self.config.window_bytes
        if link.pending_messages and (
            link.pending_messages + 1 > window_messages or link.pending_bytes + size > window_bytes
        ):
            raise RemoteProtocolError(
                f"peer exceeded the receive window ({window_messages} messages / "
                f"{window_bytes} bytes)"
            )
        message = decode_payload(frame.type_id, frame.payload)
        link.accept(frame.seq, size)
        self._events.append(MessageReceived(message, frame.seq, link.in_stream_id, frame.size))

    def _on_ack(self, ack: int, now: float) -> None:
        link = self.link
        assert link is not None
        if ack <= link.first_unacked - 1:
            return
        if ack >= link.next_seq:
            raise RemoteProtocolError(f"ack {ack} for a message never sent (next {link.next_seq})")
        for seq, size in link.acknowledge(ack):
            if seq < self._next_tx:
                self._inflight_bytes -= size
        self._next_tx = max(self._next_tx, ack + 1)
        self._recovery.on_acked(ack, now)
        if self._next_tx > link.first_unacked:
            self._recovery.arm(now)
        else:
            self._recovery.disarm()
        self._events.append(Acknowledged(ack))

    # control frame handlers (Hello, Challenge, Auth: handshake.py) ---------------
    def _on_welcome(self, msg: Welcome, frame: Frame) -> None:
        self._resume(
            msg.out_stream_id,
            msg.first_unacked,
            msg.in_stream_id,
            msg.last_delivered,
            (msg.window_messages, msg.window_bytes),
        )
        self._establish()

    def _on_close(self, msg: Close, frame: Frame) -> None:
        self.state = State.CLOSED
        self.close_reason = f"peer closed (code {msg.code}): {msg.reason}"
        self._events.append(PeerClosed(msg.code, msg.reason))

    def _on_reject(self, msg: Reject, frame: Frame) -> None:
        assert self.link is not None
        if not 0 < msg.seq < self.link.next_seq:
            raise RemoteProtocolError(f"Reject of seq {msg.seq}, never sent")
        self._events.append(PeerRejected(msg.seq, msg.reason))

    def _on_noop(self, msg: Message, frame: Frame) -> None:
        """Ack and Heartbeat: the header ack and the receive time are all they carry."""

    # ------------------------------------------------------------------ internals
    def _resume(
        self,
        peer_out_stream: bytes,
        peer_first_unacked: int,
        peer_in_stream: bytes,
        peer_last_delivered: int,
        peer_window: tuple[int, int],
    ) -> None:
        link = self.link
        assert link is not None
        if min(peer_window) < 1:
            raise RemoteProtocolError("invalid window in handshake")
        link.resume(peer_out_stream, peer_first_unacked, peer_in_stream, peer_last_delivered)
        self._next_tx = link.first_unacked
        self._recovery.forget()
        self._inflight_bytes = 0
        self._peer_window = peer_window
        self._ack_sent = link.last_delivered

    def _establish(self) -> None:
        assert self.link is not None
        self.state = State.ESTABLISHED
        self._handshake_deadline = None
        self._decoder.max_frame_size = self.config.max_frame_size
        replay = self.link.next_seq - self.link.first_unacked
        self._events.append(
            HandshakeComplete(self.peer_role or "", self.peer_agent_id or "", replay)
        )

    def _attend(self, now: float) -> None:
        """We run at ``now``. The transport runs us at least once per heartbeat interval
        (``get_timer``); if we had not run for more than two (our own process stalled: a busy
        loop, a starved CPU), the peer's frames of that time may sit unread in the socket: the
        time beyond one interval is not counted as the peer's silence."""
        away = now - self._last_run
        if away > 2 * self.config.heartbeat_interval:
            self._last_rx += away - self.config.heartbeat_interval
        self._last_run = max(self._last_run, now)

    def _first_inflight(self) -> int:
        assert self.link is not None
        return self.link.first_unacked

    def _transmit_outbox(self, limit: int, now: float) -> None:
        link = self.link
        assert link is not None
        window_messages, window_bytes = self._peer_window
        sent = 0
        while self._next_tx < link.next_seq and sent < limit:
            entry = link.outbox[self._next_tx]
            size = len(entry.payload)
            inflight = self._next_tx - link.first_unacked
            if inflight and (
                inflight + 1 > window_messages or self._inflight_bytes + size > window_bytes
            ):
                break
            seq = self._next_tx
            flags = FLAG_RETRANSMIT if seq <= link.highest_sent else 0
            frame = self._frame(entry.type_id, entry.payload, seq, flags)
            self._count_tx(entry.type_name, len(frame), flags)
            self._recovery.on_sent(seq, now, resent=bool(flags))
            self._out.append(frame)
            link.highest_sent = max(link.highest_sent, seq)
            self._next_tx += 1
            self._inflight_bytes += size
            sent += len(frame)

    def _retransmit_oldest(self, now: float) -> None:
        link = self.link
        assert link is not None
        first = link.first_unacked
        if self._next_tx <= first:
            self._recovery.disarm()
            return
        entry = link.outbox[first]
        frame = self._frame(entry.type_id, entry.payload, first, FLAG_RETRANSMIT)
        self._count_tx(entry.type_name, len(frame), FLAG_RETRANSMIT)
        self._out.append(frame)
        self._recovery.on_sent(first, now, resent=True)

    def _frame(self, type_id: int, payload: bytes, seq: int, flags: int) -> bytes:
        ack = 0
        if self.state is State.ESTABLISHED and self.link is not None:
            ack = self.link.last_delivered
            self._ack_sent = ack
            self._ack_deadline = None
        return encode_frame(
            type_id,
            payload,
            seq=seq,
            ack=ack,
            flags=flags,
            max_frame_size=self.config.max_frame_size,
            seal=self._keys.seal,
            seal_overhead=sealing.TAG_SIZE,
        )

    def _count_tx(self, type_name: str, nbytes: int, flags: int) -> None:
        self.counters.record("tx", type_name, nbytes)
        if flags & FLAG_RETRANSMIT:
            self.counters.retransmitted_messages += 1
            self.counters.retransmitted_bytes += nbytes

    def _emit(self, msg: Message) -> None:
        self._emit_payload(type(msg), encode_payload(msg))

    def _emit_payload(self, cls: type[Message], payload: bytes) -> None:
        frame = self._frame(cls.TYPE_ID, payload, 0, 0)
        self._count_tx(cls.__name__, len(frame), 0)
        self._out.append(frame)

    def _fail(self, exc: ProtocolError, code: CloseCode) -> None:
        if self.state is not State.CLOSED:
            self._emit(Close(int(code), str(exc)[:200]))
            self.state = State.CLOSED
            self.close_reason = str(exc)
        raise exc


_TRANSITIONS: dict[tuple[bool, State, type[Message]], Callable[..., None]] = {
    (True, State.HELLO_SENT, Challenge): Session._on_challenge,
    (True, State.AUTH_SENT, Welcome): Session._on_welcome,
    (False, State.AWAIT_HELLO, Hello): Session._on_hello,
    (False, State.CHALLENGE_SENT, Auth): Session._on_auth,
    (True, State.ESTABLISHED, Ack): Session._on_noop,
    (False, State.ESTABLISHED, Ack): Session._on_noop,
    (True, State.ESTABLISHED, Heartbeat): Session._on_noop,
    (False, State.ESTABLISHED, Heartbeat): Session._on_noop,
    (True, State.ESTABLISHED, Reject): Session._on_reject,
    (False, State.ESTABLISHED, Reject): Session._on_reject,
}
