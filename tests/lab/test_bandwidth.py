"""``lab.bandwidth``: budgets, the timing estimates and the table files (the full runs are
exercised by tests/e2e and benchmarks/results/bandwidth.md)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from common.errors import RecslamError
from lab.bandwidth import (
    BandwidthConfig,
    budget_name,
    parse_budgets,
    peak_rate,
    resolve_shaper,
    run_bandwidth,
    timing,
    write_table,
)


def test_parse_budgets() -> None:
    assert parse_budgets("unlimited,200,50") == [None, 200.0, 50.0]
    assert parse_budgets(" inf , 12.5 ") == [None, 12.5]
    with pytest.raises(RecslamError, match="'fast'"):
        parse_budgets("unlimited,fast")
    with pytest.raises(RecslamError, match="positive"):
        parse_budgets("0")
    assert [budget_name(b) for b in (None, 200.0, 12.5)] == ["unlimited", "200kbit", "12.5kbit"]


def test_timing_from_samples(tmp_path) -> None:
    # Robot "a" (10 frames): frames 0-4 decoded at t=100 (on time for frame 0), the rest at
    # t=102; camera time of frame i is 100 + i/20, so frame 9 is 102 - 100.45 = 1.55 s late.
    def sample(t: float, frames: int, keyframes: int) -> dict:
        return {
            "time": t,
            "edge": {"robots": {"a": {"frames_decoded": frames}}},
            "cloud": {"keyframes": keyframes},
        }

    samples = [sample(100.0, 5, 1), sample(102.0, 10, 2), sample(103.0, 10, 2)]
    path = tmp_path / "samples.jsonl"
    path.write_text("".join(json.dumps(s) + "\n" for s in samples))
    t = timing(path, {"a": 10})
    assert t["frame_delay_max_s"] == pytest.approx(2.0 - 5 / 20)
    late = [102.0 - (100.0 + i / 20) for i in range(5, 10)]
    assert t["frame_delay_mean_s"] == pytest.approx(
        sum(late) / 10 - sum(i / 20 for i in range(5)) / 10
    )
    assert t["kf_lag_s"] == pytest.approx(102.0 - (100.0 + 10 / 20))


def _row(budget: float | None, failed: bool = False) -> dict:
    return {
        "budget_kbit_s": budget,
        "ate_joint_m": 0.02,
        "ate_own_mean_m": None if budget == 50.0 else 0.015,
        "frames_sent": 100,
        "frames_decoded": 97,
        "achieved_kbit_s": 40.0 if budget else 120.0,
        "stream_s": 12.0,
        "keyframes": 30,
        "failed": failed,
        "frame_delay_mean_s": 0.5,
        "frame_delay_max_s": None,
        "kf_lag_s": 1.0,
    }


def test_write_table_writes_the_three_files(tmp_path: Path) -> None:
    rows = [_row(None), _row(200.0), _row(50.0)]
    text = write_table(rows, tmp_path, "a note")
    assert (tmp_path / "bandwidth.md").read_text() == text
    assert json.loads((tmp_path / "bandwidth.json").read_text()) == rows
    assert (tmp_path / "bandwidth.png").stat().st_size > 0
    lines = text.splitlines()
    assert lines[0] == "# Bandwidth experiment" and lines[2] == "a note"
    assert lines[6].startswith("| unlimited | 0.020 | 0.015 | 100 | 97 | 3 | 120.0 | 0.5 / – |")
    assert lines[8].startswith("| 50 | 0.020 | – |")


def test_run_bandwidth_rejects_a_missing_dataset(tmp_path: Path) -> None:
    config = BandwidthConfig(data=tmp_path / "nope", budgets=(None,), out=tmp_path / "out")
    with pytest.raises(RecslamError, match="no such dataset folder"):
        run_bandwidth(config)
    assert not (tmp_path / "out").exists()


def test_shapers_resolve_and_a_bad_one_is_named(monkeypatch) -> None:
    import lab.netns
    import sim.netem

    assert resolve_shaper("proxy") == "proxy"
    monkeypatch.setattr(sim.netem, "shaping_unavailable", lambda: "network namespaces need root")
    monkeypatch.setattr(lab.netns, "shaping_unavailable", lambda: "network namespaces need root")
    assert resolve_shaper("auto") == "proxy"
    with pytest.raises(RecslamError, match="need root"):
        resolve_shaper("tbf")
    monkeypatch.setattr(sim.netem, "shaping_unavailable", lambda: None)
    assert resolve_shaper("auto") == "tbf"
    with pytest.raises(RecslamError, match="'bogus'"):
        BandwidthConfig(data=Path("d"), budgets=(None,), shaper="bogus")


def test_a_star_places_robots_in_their_namespaces_and_the_edge_in_the_hub(tmp_path) -> None:
    """What the tbf shaper hands the orchestration: argv prefixes and the addresses."""
    from lab.netns import Leaf, Star
    from lab.run.orchestration import Job, JobConfig

    for name in ("robot0", "robot1"):
        (tmp_path / "data" / name / "mav0").mkdir(parents=True)
    leaves = {
        f"robot{i}": Leaf(f"robot{i}", f"ns{i}", f"10.9.{i}.2", f"10.9.{i}.1", "r", "h")
        for i in range(2)
    }
    placement = Star("hub", leaves, None).placement()
    job = Job(JobConfig(dataset=tmp_path / "data", run_dir=tmp_path / "run", placement=placement))
    assert placement.prefix["edge"] == placement.prefix["cloud"] == ("ip", "netns", "exec", "hub")
    assert placement.prefix["robot1"] == ("ip", "netns", "exec", "ns1")
    edge = job.edge_argv()
    assert edge[edge.index("--listen") + 1] == f"0.0.0.0:{job.edge_port}"
    assert edge[edge.index("--cloud") + 1] == f"127.0.0.1:{job.cloud_port}"
    robot = job.robot_argv("robot1")
    assert robot[robot.index("--edge") + 1] == f"10.9.1.1:{job.edge_port}"
    plain = Job(JobConfig(dataset=tmp_path / "data", run_dir=tmp_path / "plain"))
    robot = plain.robot_argv("robot1")
    assert robot[robot.index("--edge") + 1] == f"127.0.0.1:{plain.edge_port}"


def test_peak_rate_is_the_busiest_window_of_any_link_on_the_edges_clock(tmp_path) -> None:
    # robot a: 10 kB/s for 30 s, then 50 kB/s for 30 s; robot b: 1 kB/s; the sampler's own
    # clock ("time") runs late and bunched, the edge's ("edge.time") is what counts.
    samples = []
    a = b = 0
    for t in range(61):
        samples.append(
            {
                "time": 1000.0 + (t // 5) * 5,
                "edge": {
                    "time": 100.0 + t,
                    "links": {"a": {"rx": {"bytes": a}}, "b": {"rx": {"bytes": b}}},
                },
            }
        )
        a += 10_000 if t < 30 else 50_000
        b += 1_000
    path = tmp_path / "samples.jsonl"
    path.write_text("".join(json.dumps(s) + "\n" for s in samples))
    assert peak_rate(path, 30.0) == pytest.approx(8 * 50_000 / 1000)  # 400 kbit/s
    assert peak_rate(path, 60.0) == pytest.approx(8 * (30 * 10_000 + 30 * 50_000) / 60 / 1000)
    assert peak_rate(path, 61.0) is None
