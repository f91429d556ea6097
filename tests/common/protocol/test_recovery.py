"""The retransmission timer: adapts to the time to an ack, resends only to a silent peer."""

from __future__ import annotations

import pytest

from common.protocol import Blob, MessageReceived
from common.protocol.recovery import RetransmitTimer
from tests.common.protocol.test_session import Pair, cfg


def test_timeout_starts_at_the_floor_and_grows_with_slow_acks():
    t = RetransmitTimer(min_s=1.0, max_s=30.0)
    assert t.rto_s == 1.0
    for seq in range(1, 20):  # every ack takes 4 s (a busy handler)
        t.on_sent(seq, now=10.0 * seq, resent=False)
        t.on_acked(seq, now=10.0 * seq + 4.0)
    assert t.srtt_s == pytest.approx(4.0, rel=0.05)
    assert 4.0 < t.rto_s < 6.0
    for seq in range(20, 80):  # fast again: back towards the floor, never below
        t.on_sent(seq, now=10.0 * seq, resent=False)
        t.on_acked(seq, now=10.0 * seq + 0.01)
    assert t.rto_s == 1.0


def test_karn_no_sample_from_a_resent_message_and_cap():
    t = RetransmitTimer(min_s=1.0, max_s=8.0)
    t.on_sent(1, now=0.0, resent=False)
    t.on_sent(1, now=5.0, resent=True)
    t.on_acked(1, now=50.0)
    assert t.srtt_s is None and t.rto_s == 1.0
    t.on_sent(2, now=0.0, resent=False)
    t.on_acked(2, now=100.0)
    assert t.rto_s == 8.0  # capped


def test_due_resends_only_to_a_silent_peer_and_backs_off():
    t = RetransmitTimer(min_s=2.0, max_s=16.0)
    t.arm(now=0.0)
    assert not t.due(1.0, last_rx=0.0)  # not yet
    assert not t.due(2.0, last_rx=1.5)  # peer talked meanwhile: late ack, re-armed
    assert t.late_acks == 1 and t.deadline == 4.0
    assert t.due(4.0, last_rx=1.5)  # silent since 2.0: resend, doubled
    assert t.rto_s == 4.0 and t.deadline == 8.0
    assert t.due(8.0, last_rx=1.5)
    assert t.rto_s == 8.0


def test_rejects_inverted_bounds():
    with pytest.raises(ValueError, match="min_s"):
        RetransmitTimer(min_s=5.0, max_s=1.0)


def test_session_busy_handler_peer_heartbeating_gets_no_duplicate():
    """The receiver holds a message in its handler for 30 s while heartbeating: the sender
    never resends it (before: a resend every timeout, each one a dropped duplicate)."""
    p = Pair(
        cfg("r", "robot", retransmit_timeout=1.0, heartbeat_interval=0.5, idle_timeout=5.0),
        cfg("e", "edge", heartbeat_interval=0.5, idle_timeout=5.0),
    )
    p.pump()
    p.auto_deliver = False
    p.client_link.enqueue(Blob(0, b"slow"))
    p.s.receive_data(b"".join(p.c.data_to_send(0.0)), 0.0)
    received = p.s.next_event()
    assert isinstance(received, MessageReceived)
    now = 0.0
    while now < 30.0:
        now += 0.25
        for sess in (p.c, p.s):
            timer = sess.get_timer()
            if timer is not None and timer <= now:
                sess.handle_timer(now)
        p.c.receive_data(b"".join(p.s.data_to_send(now)), now)  # heartbeats (no ack yet)
        p.s.receive_data(b"".join(p.c.data_to_send(now)), now)
        while p.s.next_event() is not None:
            pass
    c = p.client_link.counters
    assert c.retransmitted_messages == 0
    assert c.late_acks >= 5
    assert p.server_links["r"].counters.duplicates_dropped == 0
    p.s.mark_delivered(received.seq, now)  # the handler returns: acked at last
    later = now + 1.0
    p.s.handle_timer(later)
    p.c.receive_data(b"".join(p.s.data_to_send(later)), later)
    assert p.client_link.first_unacked == 2
