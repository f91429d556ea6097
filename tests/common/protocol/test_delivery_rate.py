"""The link's delivery rate from its acknowledgements (common/protocol/delivery_rate.py)."""

from __future__ import annotations

import pytest

from common.protocol.delivery_rate import DeliveryRate


def test_backlogged_intervals_give_the_ratio_of_sums() -> None:
    r = DeliveryRate(window_s=10.0)
    acked = 0
    r.on_link(0.0, 10_000, acked)
    # 6250 B/s (50 kbit/s), one big ack per second: 0 B, then 12 500 B, alternately
    for k in range(1, 7):
        acked += 0 if k % 2 else 12_500
        r.on_link(float(k), 10_000, acked)
    assert r.rate_Bps() == pytest.approx(6250.0)


def test_an_idle_link_says_nothing_and_a_stall_is_not_a_rate() -> None:
    r = DeliveryRate()
    r.on_link(0.0, 0, 0)
    r.on_link(1.0, 0, 5_000)  # nothing was waiting: the link idled, not its capacity
    r.on_link(2.0, 0, 10_000)
    assert r.rate_Bps() is None
    for k in range(3, 6):  # backlogged, 1000 B/s
        r.on_link(float(k), 4_000, 10_000 + 1_000 * (k - 2))
    assert r.rate_Bps() == pytest.approx(1000.0)
    for k in range(6, 20):  # a cut: data waits, nothing acknowledged
        r.on_link(float(k), 4_000, 13_000)
    assert r.rate_Bps() == pytest.approx(1000.0)  # the last estimate holds
    assert r.stalled(19.0, 2.0) and not r.stalled(5.5, 2.0)


def test_samples_closer_than_the_minimum_interval_are_merged() -> None:
    r = DeliveryRate()
    r.on_link(0.0, 1_000, 0)
    for k in range(1, 31):  # every 0.1 s, 100 B each: 1000 B/s measured over 0.2 s steps
        r.on_link(k * 0.1, 1_000, 100 * k)
    assert r.rate_Bps() == pytest.approx(1000.0)


def test_window_must_be_positive() -> None:
    with pytest.raises(ValueError, match="window_s"):
        DeliveryRate(window_s=0.0)
