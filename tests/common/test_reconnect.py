"""The client's reconnect policy, driven with explicit ``now`` values (no sockets, no sleeps)."""

from __future__ import annotations

from common.transport import TransportConfig
from common.transport.reconnect import GiveUp, ReconnectPolicy, Retry


def no_jitter(a: float, b: float) -> float:
    return (a + b) / 2


def policy(give_up: float = 0.0, start: float = 100.0, **kw) -> ReconnectPolicy:
    t = TransportConfig(
        reconnect_initial_delay=0.5,
        reconnect_max_delay=4.0,
        unreachable_warning_interval=30.0,
        give_up_after=give_up,
        **kw,
    )
    return ReconnectPolicy(t, start, uniform=no_jitter)


def test_delays_double_to_the_cap_and_never_give_up_by_default() -> None:
    p = policy()
    delays = []
    now = 100.0
    for _ in range(8):
        step = p.attempt_ended(now, established=False)
        assert isinstance(step, Retry)
        delays.append(step.delay)
        now += 1000.0  # an outage of hours: still retrying
    assert delays == [0.5, 1.0, 2.0, 4.0, 4.0, 4.0, 4.0, 4.0]


def test_warns_at_the_first_failure_then_once_per_interval() -> None:
    p = policy()
    warned = [p.attempt_ended(100.0 + t, established=False).warn for t in (0, 5, 29, 31, 40, 62)]
    assert warned == [True, False, False, True, False, True]


def test_gives_up_at_the_first_failure_past_the_deadline_with_the_outage() -> None:
    p = policy(give_up=2.0)
    first = p.attempt_ended(100.2, established=False)
    assert isinstance(first, Retry) and first.attempts == 1
    second = p.attempt_ended(101.9, established=False)
    # the wait never runs past the deadline (here 0.1 s left, the backoff says 1 s)
    assert isinstance(second, Retry) and abs(second.delay - 0.1) < 1e-9
    last = p.attempt_ended(102.0, established=False)
    assert last == GiveUp(attempts=3, down_s=2.0)


def test_an_established_session_starts_a_new_outage_and_resets_the_backoff() -> None:
    p = policy(give_up=10.0)
    for t in (101.0, 105.0, 109.0):
        assert isinstance(p.attempt_ended(t, established=False), Retry)
    ended = p.attempt_ended(300.0, established=True)  # a session ran from ~109 s to 300 s
    assert isinstance(ended, Retry) and ended.delay == 0.5 and not ended.warn
    again = p.attempt_ended(309.0, established=False)
    assert isinstance(again, Retry) and again.attempts == 1 and again.warn
    assert again.down_s == 9.0
    assert p.attempt_ended(310.0, established=False) == GiveUp(attempts=2, down_s=10.0)
