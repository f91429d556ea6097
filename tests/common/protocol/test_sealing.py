"""Issue 18's attacks on a live session, in memory: a man in the middle who changes, injects,
replays, reorders or drops frames after the handshake, and peers who hold one credential and
claim another identity. Nothing the sender did not send is ever delivered."""

from __future__ import annotations

import struct
import zlib

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from common.protocol import (
    AuthenticationError,
    Blob,
    Identity,
    Keyring,
    LocalProtocolError,
    MessageReceived,
    PeerAuthenticated,
    RemoteProtocolError,
    Session,
    SessionConfig,
)
from common.protocol.auth import agent_credential, role_key
from common.protocol.framing import FLAG_SEALED, HEADER_SIZE, FrameDecoder, encode_frame
from common.protocol.messages import encode_payload
from common.protocol.sealing import TAG_SIZE, FrameSealer, session_keys

OPERATOR = b"operator-secret-0123456789abcdef"
ROBOT_KEY = role_key(OPERATOR, "robot")


def robot_keys(name: str) -> Keyring:
    return Keyring(own=Identity("robot", name, agent_credential(ROBOT_KEY, name)))


EDGE_KEYS = Keyring(role_keys=(("robot", ROBOT_KEY),))


class Wire:
    """A robot client and an edge server session with a man in the middle on the wire."""

    def __init__(self, client_keys: Keyring, agent: str = "robot0", **kw) -> None:
        ccfg = SessionConfig("robot", agent, keys=client_keys, **kw)
        self.scfg = SessionConfig("edge", "edge", keys=EDGE_KEYS, **kw)
        self.link = ccfg.new_link()
        self.c = Session(ccfg, client=True, now=0.0, link=self.link)
        self.s = Session(self.scfg, client=False, now=0.0)
        self.server_link = self.scfg.new_link()
        self.delivered: list[bytes] = []
        self.authenticated: list[PeerAuthenticated] = []

    def server_events(self) -> None:
        while (ev := self.s.next_event()) is not None:
            if isinstance(ev, PeerAuthenticated):
                self.authenticated.append(ev)
                self.s.attach(self.server_link, 0.0)
            elif isinstance(ev, MessageReceived):
                self.delivered.append(ev.message.data)
                self.s.mark_delivered(ev.seq, 0.0)

    def handshake(self) -> None:
        for _ in range(4):
            for data in self.c.data_to_send(0.0):
                self.s.receive_data(data, 0.0)
            self.server_events()
            for data in self.s.data_to_send(0.0):
                self.c.receive_data(data, 0.0)
            while self.c.next_event() is not None:
                pass
        assert self.c.established and self.s.established

    def client_frames(self, payloads: list[bytes]) -> list[bytes]:
        for p in payloads:
            self.link.enqueue(Blob(1, p))
        return self.c.data_to_send(0.0)

    def feed(self, frames: list[bytes]) -> None:
        self.s.receive_data(b"".join(frames), 0.0)
        self.server_events()


def _refix_crc(frame: bytes) -> bytes:
    """The attacker recomputes the frame CRC (it is not a MAC)."""
    prefix, payload = frame[: HEADER_SIZE - 4], frame[HEADER_SIZE:]
    crc = zlib.crc32(payload, zlib.crc32(prefix))
    return prefix + struct.pack("!I", crc) + payload


def test_payload_is_encrypted_and_the_wire_carries_the_tag():
    w = Wire(robot_keys("robot0"))
    w.handshake()
    (frame,) = w.client_frames([b"a very recognisable plaintext"])
    assert b"recognisable" not in frame
    assert frame[3] & FLAG_SEALED
    plain = encode_payload(Blob(1, b"a very recognisable plaintext"))
    assert len(frame) == HEADER_SIZE + len(plain) + TAG_SIZE
    w.feed([frame])
    assert w.delivered == [b"a very recognisable plaintext"]


@pytest.mark.parametrize(
    "attack",
    ["flip-payload", "change-header-ts", "replay", "reorder", "drop", "inject-unsealed"],
)
def test_man_in_the_middle_frames_close_the_connection_and_are_never_delivered(attack):
    w = Wire(robot_keys("robot0"))
    w.handshake()
    f = w.client_frames([b"m0", b"m1", b"m2"])
    if attack == "flip-payload":
        bad = bytearray(f[1])
        bad[HEADER_SIZE + 1] ^= 0x01
        f[1] = _refix_crc(bytes(bad))
    elif attack == "change-header-ts":  # e.g. the ack field (bytes 10..13)
        bad = bytearray(f[1])
        bad[13] ^= 0x01
        f[1] = _refix_crc(bytes(bad))
    elif attack == "replay":
        f = [f[0], f[0], f[1]]
    elif attack == "reorder":
        f = [f[0], f[2], f[1]]
    elif attack == "drop":
        f = [f[0], f[2]]
    else:  # a well-formed frame that the attacker built himself, without the keys
        f = [f[0], encode_frame(0x0100, encode_payload(Blob(1, b"evil")), seq=2, ack=0)]
    w.feed(f[:1])
    with pytest.raises(RemoteProtocolError, match=r"failed authentication|unsealed"):
        w.feed(f[1:])
    assert w.s.closed
    assert w.delivered == [b"m0"]  # only what came before the attack


def test_frames_of_one_connection_cannot_be_replayed_into_the_next():
    w = Wire(robot_keys("robot0"))
    w.handshake()
    old = w.client_frames([b"m0"])
    # the robot reconnects: new handshake, new nonces, new keys
    w2 = Wire(robot_keys("robot0"))
    w2.handshake()
    with pytest.raises(RemoteProtocolError, match="failed authentication"):
        w2.feed(old)
    assert w2.delivered == []


def test_a_credential_proves_one_identity_only():
    # robot0's credential claiming to be robot1: the edge derives robot1's, the proofs differ
    with pytest.raises(LocalProtocolError, match="no credential for robot 'robot1'"):
        Wire(robot_keys("robot0"), agent="robot1")
    forged = Keyring(own=Identity("robot", "robot1", agent_credential(ROBOT_KEY, "robot0")))
    w = Wire(forged, agent="robot1")
    with pytest.raises(AuthenticationError, match="does not hold the credential"):
        w.handshake()
    assert w.authenticated == []
    # a robot credential claiming the edge role: the edge holds no edge role key at all
    as_edge = Keyring(own=Identity("edge", "robot0", agent_credential(ROBOT_KEY, "robot0")))
    ccfg = SessionConfig("edge", "robot0", keys=as_edge)
    c = Session(ccfg, client=True, now=0.0, link=ccfg.new_link())
    s = Session(SessionConfig("edge", "edge", keys=EDGE_KEYS), client=False, now=0.0)
    with pytest.raises(AuthenticationError, match="no credential for edge"):
        s.receive_data(b"".join(c.data_to_send(0.0)), 0.0)


def test_the_right_credential_is_accepted_and_names_the_peer():
    w = Wire(robot_keys("robot7"), agent="robot7")
    w.handshake()
    assert [(a.role, a.agent_id) for a in w.authenticated] == [("robot", "robot7")]


def test_session_keys_differ_per_direction_and_per_transcript():
    c2s, s2c = session_keys(b"k" * 32, b"hello", b"challenge")
    c2s_b, _ = session_keys(b"k" * 32, b"hello2", b"challenge")
    sealed = c2s.seal(b"h" * 18, b"payload")
    assert s2c.seal(b"h" * 18, b"payload") != sealed
    assert c2s_b.seal(b"h" * 18, b"payload") != sealed
    opener = session_keys(b"k" * 32, b"hello", b"challenge")[0]
    assert opener.open(b"h" * 18, sealed, "Blob") == b"payload"
    with pytest.raises(RemoteProtocolError):
        opener.open(b"h" * 18, sealed, "Blob")  # the counter moved on: a replay fails


def test_sealer_rejects_wrong_key_sizes():
    with pytest.raises(LocalProtocolError):
        FrameSealer(b"short", b"\0" * 12)


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    n=st.integers(1, 6),
    edits=st.lists(
        st.tuples(st.integers(0, 10_000), st.integers(0, 255), st.sampled_from("xdi")),
        min_size=1,
        max_size=4,
    ),
    cut=st.integers(0, 10_000),
)
def test_fuzz_mutated_post_handshake_stream_delivers_only_what_was_sent(n, edits, cut):
    """A real session's byte stream after the handshake, mutated (bytes changed, deleted or
    inserted anywhere, CRC left as is or not): the receiver delivers a prefix of what the
    sender sent, in order, and nothing else; it never raises anything but the protocol's
    RemoteProtocolError."""
    w = Wire(robot_keys("robot0"))
    w.handshake()
    sent = [bytes([i]) * (i + 1) for i in range(n)]
    stream = bytearray(b"".join(w.client_frames(sent)))
    original = bytes(stream)
    for pos, value, kind in edits:
        pos %= len(stream) + 1
        if kind == "x" and pos < len(stream):
            stream[pos] ^= value or 1
        elif kind == "d" and pos < len(stream):
            del stream[pos]
        else:
            stream.insert(pos, value)
    data = bytes(stream)
    try:
        w.s.receive_data(data[: cut % (len(data) + 1)], 0.0)
        w.server_events()
        w.s.receive_data(data[cut % (len(data) + 1) :], 0.0)
        w.server_events()
    except RemoteProtocolError:
        pass
    assert w.delivered == sent[: len(w.delivered)]
    if data == original:
        assert w.delivered == sent
    # the decoder's own view: whatever it accepted was sealed
    dec = FrameDecoder()
    dec.receive_data(original)
    while (frame := dec.next_frame()) is not None:
        assert frame.flags & FLAG_SEALED
