"""lab.edge_load reads a run folder's stalls, timeouts and duplicates and tables them."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from lab.edge_load import read_run, timeouts, write_table


def _run(folder: Path, duplicates: int, timeout_lines: int) -> Path:
    run = folder / "run"
    (run / "stats").mkdir(parents=True)
    (run / "logs").mkdir()
    robots = {
        "robot0": {"ate_rmse_m": 0.012, "frames_sent": 100, "frames_decoded": 100},
        "robot1": {"ate_rmse_m": 0.019, "frames_sent": 100, "frames_decoded": 99},
    }
    rep = {"robots": robots, "ate": {"joint_rmse_m": 0.015}, "map": {"maps": [{"id": 1}]}}
    (folder / "report.json").write_text(json.dumps(rep))
    links = {
        "robot0": {"connections": 1, "duplicates_dropped": 0, "late_acks": 3},
        "robot1": {"connections": 3, "duplicates_dropped": duplicates},
    }
    edge = {"loop_stalls": {"max_s": 2.5, "over_1s": 4}, "links": links}
    (run / "stats" / "edge.json").write_text(json.dumps(edge))
    lines = ["2026 INFO fine"] + [
        "2026 WARNING connection closed: PeerTimeoutError: peer silent for 10.0s"
    ] * timeout_lines
    (run / "logs" / "robot1.log").write_text("\n".join(lines))
    (run / "logs" / "edge.log").write_text("nothing\n")
    return folder


def test_read_run_counts_what_the_run_left(tmp_path):
    r = read_run(_run(tmp_path / "a", duplicates=7, timeout_lines=2))
    assert r["robots"] == 2 and r["maps"] == 1
    assert r["stall_max_s"] == 2.5 and r["stalls_over_1s"] == 4
    assert r["timeouts"] == {"robot1": 2}
    assert r["duplicates"] == 7 and r["reconnects"] == 2 and r["frames_lost"] == 1
    assert r["per_robot"]["robot0"]["late_acks"] == 3
    assert timeouts(tmp_path / "a" / "run" / "logs") == {"robot1": 2}


@pytest.mark.slow
def test_write_table_rows_and_plot(tmp_path):
    runs = [
        read_run(_run(tmp_path / "a", duplicates=0, timeout_lines=0)),
        read_run(_run(tmp_path / "b", duplicates=5, timeout_lines=1)),
    ]
    md = tmp_path / "out" / "edge_robots.md"
    png = write_table(runs, md, "# header")
    rows = [line for line in md.read_text().splitlines() if line.startswith("| 2 ")]
    assert len(rows) == 2
    assert "| 2.50 | 4 | 0 | 2 | 0 | 1 | 3 | 1 | 1.50 | 1.90 |" in rows[0]
    assert "| 1 | 2 | 5 |" in rows[1]
    assert png.exists() and png.stat().st_size > 1000
