"""Two sans-I/O sessions wired together in memory: handshake, reliability, timers."""

from __future__ import annotations

import logging
import random

import pytest

from common.protocol import (
    AuthenticationError,
    Blob,
    CloseCode,
    HandshakeComplete,
    InboundPosition,
    LocalProtocolError,
    MessageReceived,
    PeerAuthenticated,
    PeerClosed,
    PeerTimeoutError,
    RemoteProtocolError,
    Session,
    SessionConfig,
)
from common.protocol.framing import FLAG_RETRANSMIT, PROTOCOL_VERSION, FrameDecoder, encode_frame
from common.protocol.messages import SCHEMA_VERSION, Auth, Hello, encode_payload
from common.protocol.sealing import TAG_SIZE

SECRET = b"0123456789abcdef-secret"


def cfg(agent: str, role: str, **kw) -> SessionConfig:
    return SessionConfig(role=role, agent_id=agent, secret=kw.pop("secret", SECRET), **kw)


class Pair:
    """A client and a server session plus their links, with a byte pump between them."""

    def __init__(self, ccfg: SessionConfig, scfg: SessionConfig, now: float = 0.0) -> None:
        self.ccfg, self.scfg = ccfg, scfg
        self.client_link = ccfg.new_link()
        self.server_links: dict[str, object] = {}
        self.delivered_by_server: list[tuple[int, bytes]] = []
        self.delivered_by_client: list[tuple[int, bytes]] = []
        self.auto_deliver = True
        self.connect(now)

    def connect(self, now: float) -> None:
        self.c = Session(self.ccfg, client=True, now=now, link=self.client_link)
        self.s = Session(self.scfg, client=False, now=now)

    def _events(self, sess: Session, now: float, sink: list) -> None:
        while (ev := sess.next_event()) is not None:
            if isinstance(ev, PeerAuthenticated):
                link = self.server_links.get(ev.agent_id)
                if link is None:
                    link = self.server_links[ev.agent_id] = self.scfg.new_link()
                sess.attach(link, now)
            elif isinstance(ev, MessageReceived) and self.auto_deliver:
                sink.append((ev.seq, ev.message.data))
                sess.mark_delivered(ev.seq, now)

    def pump(self, now: float = 0.0, rounds: int = 50, cut_after: int | None = None) -> int:
        """Move bytes both ways until quiet; if cut_after, stop after that many bytes."""
        moved = 0
        for _ in range(rounds):
            progress = False
            for src, dst, sink in (
                (self.c, self.s, self.delivered_by_server),
                (self.s, self.c, self.delivered_by_client),
            ):
                data = b"".join(src.data_to_send(now))
                if cut_after is not None and moved + len(data) > cut_after:
                    dst.receive_data(data[: cut_after - moved], now)
                    self._events(dst, now, sink)  # the app still handles what it accepted
                    return -1
                if data:
                    progress = True
                    moved += len(data)
                    dst.receive_data(data, now)
                self._events(dst, now, sink)
            self._events(self.c, now, self.delivered_by_client)
            self._events(self.s, now, self.delivered_by_server)
            if not progress:
                break
        return moved


def test_handshake_establishes_both_sides():
    p = Pair(cfg("robot-1", "robot"), cfg("edge", "edge"))
    p.pump()
    assert p.c.established and p.s.established
    assert p.s.peer_agent_id == "robot-1" and p.c.peer_role == "edge"
    assert p.server_links["robot-1"].peer == "robot-1"


def test_messages_delivered_in_order_and_acked_only_after_delivery():
    p = Pair(cfg("r", "robot"), cfg("e", "edge"))
    p.pump()
    p.auto_deliver = False
    seqs = [p.client_link.enqueue(Blob(0, bytes([i]) * i)) for i in range(10)]
    assert seqs == list(range(1, 11))
    data = b"".join(p.c.data_to_send(0.0))
    p.s.receive_data(data, 0.0)
    received = []
    while (ev := p.s.next_event()) is not None:
        received.append(ev)
    assert [e.seq for e in received] == seqs
    # bytes arrived but nothing delivered: the server acks nothing, the outbox is intact
    p.s.handle_timer(1.0)
    p.c.receive_data(b"".join(p.s.data_to_send(1.0)), 1.0)
    assert len(p.client_link.outbox) == 10
    for e in received[:4]:
        p.s.mark_delivered(e.seq, 1.0)
    p.s.handle_timer(1.1)
    p.c.receive_data(b"".join(p.s.data_to_send(1.1)), 1.1)
    assert list(p.client_link.outbox) == seqs[4:]
    with pytest.raises(LocalProtocolError):
        p.s.mark_delivered(9, 1.2)  # out of order


def test_wrong_secret_refused_by_client_and_server():
    # client with the wrong secret: the server's proof does not verify at the client
    p = Pair(cfg("r", "robot", secret=b"x" * 20), cfg("e", "edge"))
    with pytest.raises(AuthenticationError):
        p.pump()
    assert not p.s.established
    # a forged Auth from an impostor who cannot compute the MAC: the server refuses
    s = Session(cfg("e", "edge"), client=False, now=0.0)
    link = cfg("r", "robot").new_link()
    v = SCHEMA_VERSION
    hello = Hello(
        PROTOCOL_VERSION,
        v,
        "robot",
        "mallory",
        b"n" * 32,
        link.out_stream_id,
        1,
        b"",
        0,
        8,
        1 << 20,
    )
    s.receive_data(encode_frame(1, encode_payload(hello)), 0.0)
    assert s.data_to_send(0.0)  # the Challenge
    with pytest.raises(AuthenticationError, match="mallory"):
        s.receive_data(encode_frame(3, encode_payload(Auth(b"\0" * 32))), 0.0)
    assert s.closed and s.next_event() is None
    closing = FrameDecoder()
    closing.receive_data(b"".join(s.data_to_send(0.0)))
    assert closing.next_frame().type_id == 7  # Close with the reason goes out


def test_application_message_before_authentication_is_refused():
    s = Session(cfg("e", "edge"), client=False, now=0.0)
    with pytest.raises(RemoteProtocolError, match=r"before authentication|not allowed"):
        s.receive_data(encode_frame(0x100, encode_payload(Blob(1, b"x")), seq=1), 0.0)
    assert s.closed


def test_resume_after_random_cuts_is_exactly_once_in_order():
    rng = random.Random(7)
    p = Pair(cfg("r", "robot", window_messages=16), cfg("e", "edge", window_messages=16))
    sent = []
    cuts = 0
    for i in range(600):
        p.client_link.enqueue(Blob(1, i.to_bytes(4, "big") * rng.randint(1, 50)))
        sent.append(i)
        if rng.random() < 0.15 and p.pump(cut_after=rng.randint(0, 1000)) == -1:
            cuts += 1
            p.connect(0.0)  # new connection, same links
    for step in range(1, 20):
        p.c.handle_timer(step * 0.01)  # delayed acks go out
        p.s.handle_timer(step * 0.01)
        p.pump(step * 0.01)
    got = [int.from_bytes(d[:4], "big") for _, d in p.delivered_by_server]
    assert cuts > 20
    assert got == sent
    assert not p.client_link.outbox


def test_server_to_client_direction_and_counters_match_wire_bytes():
    p = Pair(cfg("r", "robot"), cfg("e", "edge"))
    p.pump()
    link = p.server_links["r"]
    for i in range(5):
        link.enqueue(Blob(2, b"z" * (100 * i)))
    moved = p.pump()
    assert [len(d) for _, d in p.delivered_by_client] == [0, 100, 200, 300, 400]
    c = p.client_link.counters.snapshot()
    s = link.counters.snapshot()
    assert c["tx"]["bytes"] == s["rx"]["bytes"] and s["tx"]["bytes"] == c["rx"]["bytes"]
    assert s["tx"]["by_type"]["Blob"]["messages"] == 5
    assert s["tx"]["by_type"]["Blob"]["bytes"] == sum(
        22 + TAG_SIZE + len(encode_payload(Blob(2, b"z" * (100 * i)))) for i in range(5)
    )
    assert s["tx"]["by_type"]["Blob"]["bytes"] == (22 + 16) * 5 + 1000 + 3 * 4 + 2 * 5
    assert moved > 0


def test_receiver_restart_with_saved_position_has_no_duplicates():
    p = Pair(cfg("r", "robot"), cfg("e", "edge"))
    for i in range(5):
        p.client_link.enqueue(Blob(0, bytes([i])))
    p.pump()
    saved = p.server_links["r"].inbound_position()
    assert saved.last_delivered == 5
    # client sends 3 more; server "crashes" before delivering them (bytes lost)
    for i in range(5, 8):
        p.client_link.enqueue(Blob(0, bytes([i])))
    p.c.data_to_send(0.0)
    p.server_links = {"r": p.scfg.new_link(inbound=saved)}  # restarted process
    p.connect(1.0)
    p.pump(1.0)
    assert [d[0] for _, d in p.delivered_by_server] == list(range(8))


def test_sender_restart_without_outbox_starts_new_stream(caplog):
    p = Pair(cfg("r", "robot"), cfg("e", "edge"))
    p.client_link.enqueue(Blob(0, b"a"))
    p.pump()
    p.client_link = p.ccfg.new_link()  # sender lost its state: new stream from seq 1
    p.client_link.enqueue(Blob(0, b"b"))
    p.connect(1.0)
    with caplog.at_level(logging.WARNING):
        p.pump(1.0)
    assert [d for _, d in p.delivered_by_server] == [b"a", b"b"]
    assert "new stream" in caplog.text


def test_sender_restart_with_persisted_outbox_replays_it():
    p = Pair(cfg("r", "robot"), cfg("e", "edge"))
    for i in range(3):
        p.client_link.enqueue(Blob(0, bytes([i])))
    p.c.data_to_send(0.0)  # sent but lost with the crash
    state = p.client_link.outbound_state()
    p.client_link = p.ccfg.new_link(outbound=state)
    p.connect(0.0)
    p.pump()
    assert [d[0] for _, d in p.delivered_by_server] == [0, 1, 2]
    assert p.client_link.counters.retransmitted_messages == 3


def test_heartbeat_idle_timeout_and_handshake_timeout():
    p = Pair(cfg("r", "robot", heartbeat_interval=1.0, idle_timeout=3.0), cfg("e", "edge"))
    p.pump()
    assert p.c.get_timer() == pytest.approx(1.0)
    p.c.handle_timer(1.0)
    assert p.client_link.counters.snapshot()["tx"]["by_type"]["Heartbeat"]["messages"] == 1
    p.c.handle_timer(2.0)
    with pytest.raises(PeerTimeoutError):
        p.c.handle_timer(3.5)  # the server never answered
    lone = Session(cfg("e", "edge", handshake_timeout=2.0), client=False, now=0.0)
    assert lone.get_timer() == 2.0
    with pytest.raises(PeerTimeoutError, match="handshake"):
        lone.handle_timer(2.0)


def test_own_stall_is_not_the_peers_silence():
    """Our process did not run for 12 s (idle timeout 3 s): the peer's frames may be unread in
    the socket, so the first timer after the stall does not declare it dead; real silence
    afterwards still does."""
    p = Pair(cfg("r", "robot", heartbeat_interval=1.0, idle_timeout=3.0), cfg("e", "edge"))
    p.pump()
    p.c.handle_timer(1.0)
    p.c.handle_timer(13.0)  # back after a 12 s stall: not a timeout
    assert p.c.established
    with pytest.raises(PeerTimeoutError):
        p.c.handle_timer(14.0)  # 1 s before the stall + 1 s of it + 1 s after: 3 s silent


def test_retransmit_on_timeout_and_duplicate_dropped():
    p = Pair(cfg("r", "robot", retransmit_timeout=1.0), cfg("e", "edge"))
    p.pump()
    p.auto_deliver = False
    p.client_link.enqueue(Blob(0, b"once"))
    p.s.receive_data(b"".join(p.c.data_to_send(0.0)), 0.0)
    first = p.s.next_event()
    assert isinstance(first, MessageReceived)
    p.c.handle_timer(1.0)  # no ack within the timeout: resend the oldest
    again = b"".join(p.c.data_to_send(1.0))
    dec = FrameDecoder()
    dec.receive_data(again)
    assert dec.next_frame().flags & FLAG_RETRANSMIT
    p.s.receive_data(again, 1.0)
    assert p.s.next_event() is None  # duplicate dropped
    assert p.server_links["r"].counters.duplicates_dropped == 1
    assert p.c.get_timer() <= 3.0  # backoff doubled to 2 s


def test_window_is_honoured_and_enforced():
    # unsealed frames: the hostile client below holds the keys (an authenticated peer)
    p = Pair(
        cfg("r", "robot", seal_frames=False), cfg("e", "edge", window_messages=4, seal_frames=False)
    )
    p.pump()
    p.auto_deliver = False
    for i in range(10):
        p.client_link.enqueue(Blob(0, bytes([i])))
    frames = p.c.data_to_send(0.0)
    assert len(frames) == 4  # the server's window
    # a hostile client ignoring the window is cut off
    for f in frames:
        p.s.receive_data(f, 0.0)
    extra = encode_frame(0x100, encode_payload(Blob(0, b"x")), seq=5)
    with pytest.raises(RemoteProtocolError, match="window"):
        p.s.receive_data(extra, 0.0)


@pytest.mark.parametrize(
    ("frame", "match"),
    [
        (encode_frame(0x100, encode_payload(Blob(0, b"")), seq=7), "gap"),
        (encode_frame(0x100, encode_payload(Blob(0, b"")), seq=1, ack=99), "never sent"),
        (encode_frame(0x100, b"\x92\xa1x\xc4\x00", seq=1), "channel"),
        (encode_frame(0x7777, b"", seq=0), "unknown message type"),
        (encode_frame(0x0006, b"\x90", seq=3), "control frame"),
    ],
)
def test_hostile_frames_after_handshake(frame, match):
    """An authenticated peer that breaks the rules (sealing off: it would seal these)."""
    p = Pair(cfg("r", "robot", seal_frames=False), cfg("e", "edge", seal_frames=False))
    p.pump()
    with pytest.raises(RemoteProtocolError, match=match):
        p.s.receive_data(frame, 0.0)
    assert p.s.closed


def test_orderly_close_reaches_peer():
    p = Pair(cfg("r", "robot"), cfg("e", "edge"))
    p.pump()
    p.c.close(CloseCode.NORMAL, "bye")
    p.s.receive_data(b"".join(p.c.data_to_send(0.0)), 0.0)
    ev = p.s.next_event()
    assert isinstance(ev, PeerClosed) and ev.reason == "bye" and p.s.closed


def test_handshake_complete_reports_replay_count():
    p = Pair(cfg("r", "robot"), cfg("e", "edge"))
    for i in range(3):
        p.client_link.enqueue(Blob(0, bytes([i])))
    p.s.receive_data(b"".join(p.c.data_to_send(0.0)), 0.0)
    p.c.receive_data(b"".join(p.s.data_to_send(0.0)), 0.0)
    p.s.receive_data(b"".join(p.c.data_to_send(0.0)), 0.0)
    ev = p.s.next_event()
    assert isinstance(ev, PeerAuthenticated)
    p.s.attach(p.scfg.new_link(inbound=InboundPosition(b"", 0)), 0.0)
    p.c.receive_data(b"".join(p.s.data_to_send(0.0)), 0.0)
    done = p.c.next_event()
    assert isinstance(done, HandshakeComplete) and done.replay == 3


def test_large_frames_refused_before_authentication():
    s = Session(cfg("e", "edge"), client=False, now=0.0)
    big = encode_frame(0x100, encode_payload(Blob(0, b"x" * 5000)), seq=1)
    with pytest.raises(RemoteProtocolError, match="exceeds max_frame_size 4096"):
        s.receive_data(big[:22], 0.0)  # refused on the header alone
    p = Pair(cfg("r", "robot"), cfg("e", "edge"))
    p.pump()
    p.client_link.enqueue(Blob(0, b"x" * 100_000))  # fine once established
    p.pump()
    assert [len(d) for _, d in p.delivered_by_server] == [100_000]
