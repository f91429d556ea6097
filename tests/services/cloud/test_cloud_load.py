"""The worker's busy share (services/cloud/load.py)."""

from __future__ import annotations

import pytest

from services.cloud.load import BusyMeter, LoadError


def test_share_of_the_trailing_window():
    m = BusyMeter(10.0)
    assert m.share(5.0) == 0.0  # nothing yet
    m.add(0.0, 2.0)
    assert m.share(4.0) == pytest.approx(0.5)  # 2 of the 4 s since the first interval
    m.add(4.0, 14.0)
    assert m.share(14.0) == pytest.approx(1.0)  # [4, 14] fills the window
    assert m.share(16.0) == pytest.approx(0.8)  # [6, 16]: 8 s busy
    assert m.share(30.0) == 0.0  # everything fell out of the window


def test_straddling_and_overlapping_intervals_are_clipped():
    m = BusyMeter(10.0)
    m.add(0.0, 1.0)
    m.add(0.5, 3.0)  # overlaps the last one: counted once
    assert m.share(3.0) == pytest.approx(1.0)
    m.add(20.0, 25.0)
    assert m.share(28.0) == pytest.approx(0.5)  # [18, 28]: 5 s
    m.add(27.0, 33.0)
    assert m.share(30.0) == pytest.approx(0.8)  # (an interval reported past now is cut at it)


def test_misuse_is_refused():
    with pytest.raises(LoadError, match="window_s"):
        BusyMeter(0.0)
    with pytest.raises(LoadError, match="ends before it starts"):
        BusyMeter(1.0).add(2.0, 1.0)
