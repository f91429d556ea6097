"""The rate–accuracy–latency experiment's rows, table and plot (the runs are benchmarks)."""

from __future__ import annotations

import pytest

from common.errors import RecslamError
from lab.budget import Row, parse_rows, plot, table


def test_rows_name_what_each_run_passes_to_the_services():
    rows = parse_rows("unlimited, unlimited/fresh,50,50/fresh,25/auto")
    assert [r.name for r in rows] == ["unlimited", "unlimited/fresh", "50", "50/fresh", "25/auto"]
    assert rows[0].robot_args() == () and rows[0].edge_args() == ()
    assert rows[1].robot_args() == ("--live",)  # no budget on an unlimited link
    assert rows[3].robot_args() == ("--live", "--uplink-budget", "50")
    assert rows[3].edge_args() == ("--max-vio-lag", "0.5")
    assert rows[4].robot_args() == ("--live", "--uplink-budget", "auto")
    for bad, why in (("50/fast", "mode"), ("fast", "kbit/s"), ("-5", "positive"), ("", "no rows")):
        with pytest.raises(RecslamError, match=why):
            parse_rows(bad)


def test_table_counts_lost_frames_and_the_plot_is_written(tmp_path):
    base = dict(
        achieved_kbit_s=48.0,
        down_kbit_s=20.0,
        to_cloud_kbit_s=300.0,
        frames_in=1201,
        frames_sent=400,
        frames_decoded=400,
        left_out=801,
        dropped_live=0,
        skipped_stale=3,
        poses_received=390,
        latency_median_s=0.3,
        latency_p95_s=0.9,
        latency_max_s=2.0,
        keyframes=50,
        maps=1,
        ate_joint_m=0.004,
        frames_ate_joint_m=0.006,
        ate_own_mean_m=0.003,
        stream_s=70.0,
    )
    results = [
        {**base, "row": Row(50.0, "fresh").name},
        {**base, "row": "50", "frames_decoded": 399},
    ]
    text = table(results)
    assert "| 50/fresh | 48.0 | 20.0 | 300.0 | 1201 / 400 / 400 | 0 | 801 |" in text
    assert "| 50 | 48.0 |" in text and "/ 400 / 399 | 1 |" in text
    assert "0.30 / 0.90 / 2.00" in text and "| 0.40 | 0.60 |" in text
    plot(results, tmp_path / "b.png")
    assert (tmp_path / "b.png").stat().st_size > 10_000


def test_a_cut_row_names_its_outage():
    rows = parse_rows("50/fresh/cut,50/cut")
    assert [r.name for r in rows] == ["50/fresh/cut", "50/cut"]
    assert rows[0].cut and rows[0].mode == "fresh" and rows[1].cut and rows[1].mode == ""
    with pytest.raises(RecslamError, match="mode"):
        parse_rows("50/cut/fresh")


def test_a_cloud_budget_row_passes_it_to_the_edge():
    rows = parse_rows("100/fresh/cloud150,100/fresh/cloudauto/cut,unlimited/cloud300")
    assert [r.name for r in rows] == [
        "100/fresh/cloud150",
        "100/fresh/cloudauto/cut",
        "unlimited/cloud300",
    ]
    assert rows[0].edge_args() == ("--max-vio-lag", "0.5", "--cloud-budget", "150")
    assert rows[1].cut and rows[1].edge_args()[-1] == "auto"
    assert rows[2].edge_args() == ("--cloud-budget", "300") and rows[2].robot_args() == ()
    for bad in ("100/fresh/cloudfast", "100/fresh/cloud", "100/fresh/cloud-5"):
        with pytest.raises(RecslamError, match="cloudN"):
            parse_rows(bad)
    with pytest.raises(RecslamError, match="mode"):
        parse_rows("100/cloud150/fresh")


def test_recovery_is_when_the_latency_stays_under_a_second_after_reconnecting():
    from lab.bandwidth import recovery_s

    s = 1_000_000_000
    series = [[0, 0.1], [10 * s, 0.2], [55 * s, 20.0], [56 * s, 0.5], [58 * s, 3.0], [59 * s, 0.4]]
    assert recovery_s(series, 50.0) == pytest.approx(9.0)  # 59 s is the first for good
    assert recovery_s([[0, 0.1], [60 * s, 5.0]], 50.0) is None  # never back
    assert recovery_s([[0, 0.1], [51 * s, 0.2]], 50.0) == pytest.approx(1.0)
    assert recovery_s([], 50.0) is None
