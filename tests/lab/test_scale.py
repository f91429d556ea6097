"""The scale experiment's replayer on a tiny recording: copies, renaming, schedules, the
correction latency, and one live replay to a real cloud process."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from common.links.edge_cloud import (
    KeyframeUpdate,
    KeyframeUpdateCoded,
    encode_pose_correction,
)
from lab.scale import (
    Received,
    ScaleError,
    correction_latencies,
    load_recordings,
    plan_copies,
    received,
    robots_of,
    summarize,
    team_row,
    timeline,
)


def test_copies_go_round_robin_and_rounds_are_shifted():
    robots = [("robot0", "robot1", "robot2")] * 4
    copies = plan_copies(robots, 24, shift_s=7.0)
    assert len(copies) == 8 and sum(len(c.robots) for c in copies) == 24
    assert [c.recording for c in copies] == [0, 1, 2, 3, 0, 1, 2, 3]
    assert [c.shift_s for c in copies] == [0.0] * 4 + [7.0] * 4
    assert len({c.edge for c in copies}) == len({c.prefix for c in copies}) == 8
    # A team that is not a multiple of the recordings' robots: the last copy takes a part.
    part = plan_copies([("a", "b", "c")], 4)
    assert [c.robots for c in part] == [("a", "b", "c"), ("a",)] and part[1].shift_s == 5.0
    with pytest.raises(ScaleError):
        plan_copies([()], 3)


@pytest.mark.parametrize("schedule", ["recorded", "camera"])
def test_timeline_renames_every_robot_and_keeps_each_robots_order(recording, schedule):
    recs = load_recordings([recording])
    assert robots_of(recs[0]) == ("r0", "r1")
    copies = plan_copies([robots_of(recs[0])], 4, shift_s=3.0)
    sends = timeline(recs, copies, schedule)
    assert len(sends) == 2 * len(recs[0])
    names = {s.message.agent_id for s in sends}
    assert names == {"s0-r0", "s0-r1", "s1-r0", "s1-r1"}
    assert {s.edge for s in sends} == {"site0", "site1"}
    assert all(s.message.agent_id.startswith(f"s{s.edge[-1]}-") for s in sends)
    assert [s.t for s in sends] == sorted(s.t for s in sends)
    # Each copy's messages of one robot in the recording's order, each keyframe once.
    kf = [s.keyframe for s in sends if s.keyframe is not None]
    assert len(kf) == len(set(kf)) == 2 * 42
    for name in names:
        ids = [s.keyframe[2] for s in sends if s.keyframe and s.keyframe[0] == name]
        assert ids == sorted(ids)
    first = {s.keyframe: s for s in sends if s.keyframe is not None}
    for key, s in first.items():
        assert isinstance(s.message, KeyframeUpdate | KeyframeUpdateCoded)
        assert (s.message.agent_id, s.message.map_id, s.message.keyframe_id) == key
    if schedule == "camera":  # at its camera time (r1 starts 10 s after r0) + the shift
        t_kf = {k: s.t for k, s in first.items()}
        assert t_kf["s0-r1", 7, 0] == pytest.approx(10.0)
        assert t_kf["s1-r1", 7, 0] == pytest.approx(13.0)
        assert t_kf["s0-r0", 7, 5] == pytest.approx(1.0)
    else:  # when the recording's cloud received it, the first at 0
        assert sends[0].t == 0.0 and sends[-1].t == pytest.approx(3.0 + recs[0][-1].t_recv - 100.2)


def test_correction_latency_is_to_the_first_correction_covering_the_keyframe():
    arrivals = {("a", 0, 1): 1.0, ("a", 0, 2): 2.0, ("b", 0, 1): 1.5, ("a", 1, 1): 0.0}
    corrections = [
        Received(4.0, "a", 0, (1, 2)),
        Received(1.8, "a", 0, (1,)),
        Received(0.5, "b", 0, (1,)),  # before b's keyframe arrived: not its correction
        Received(6.0, "b", 0, (1, 7)),
    ]
    lat = correction_latencies(arrivals, corrections)
    assert lat == {
        ("a", 0, 1): pytest.approx(0.8),
        ("a", 0, 2): pytest.approx(2.0),
        ("b", 0, 1): pytest.approx(4.5),
    }  # ("a", 1, 1): map 1 of a never corrected
    s = summarize(lat.values())
    assert s["n"] == 3 and s["median"] == pytest.approx(2.0) and s["max"] == pytest.approx(4.5)
    assert np.isnan(summarize([])["median"])


def test_a_correction_is_read_as_the_edge_reads_it():
    T = np.tile(np.eye(4), (3, 1, 1))
    for coded in (False, True):
        msg = encode_pose_correction("s2-robot1", 4, np.array([3, 9, 5]), T, coded)
        r = received(2.5, msg)
        assert (r.robot, r.map_id, sorted(r.keyframe_ids), r.t) == ("s2-robot1", 4, [3, 5, 9], 2.5)


@pytest.mark.slow
def test_live_replay_to_a_cloud_process(recording, tmp_path):
    """Four agents (two copies of the tiny recording, two fake edges), sped up 10x, to a real
    ``recslam cloud``: every message applied, the copies merged, keyframes corrected. The
    recording holds no robot calibrations (``AgentSensors``), so the cloud is given the
    simulator's camera as its fallback (``--camera``)."""
    from common.data.euroc_write import EurocWriter
    from lab.scale_live import LiveConfig, run_live
    from sim.cloud import default_camera

    with EurocWriter(tmp_path / "camera") as writer:
        writer.add_camera("cam0", default_camera(), "sim.cloud's camera")
    camera = tmp_path / "camera" / "mav0" / "cam0" / "sensor.yaml"

    recs = load_recordings([recording])
    copies = plan_copies([robots_of(recs[0])], 4, shift_s=1.0)
    sends = [dataclasses.replace(s, t=0.1 * s.t) for s in timeline(recs, copies, "recorded")]
    cfg = LiveConfig(
        cloud_cpu=None,
        replayer_cpu=None,
        drain_s=2.0,
        sample_every_s=0.2,
        stop_timeout_s=10.0,
        cloud_args=("--no-full-ba", "--no-mbp", "--camera", str(camera)),
    )
    live = run_live(sends, tmp_path / "live", cfg)
    assert live.sent == len(sends) and live.edges == 2 and not live.rejected
    assert live.stats["messages"] == len(sends) and live.stats["keyframes"] == 84
    assert live.stats["merges"] >= 1
    stages = live.stats["stages"]
    assert stages["stage.place_recognition"]["messages"] == 84
    assert live.samples and live.rss_max_mb > 50 and live.cloud_cpu_s > 0
    row = team_row(4, live)
    assert row.keyframes == 84 and row.messages == len(sends)
    assert 0 < row.corrected <= 1 and row.latency["median"] >= 0
    assert row.stage_ms["place recognition"] > 0 and row.worker_queue_max <= 2
    shed = live.stats["overload"]  # (10x faster than the camera: it may well shed)
    assert row.overloaded_s == shed["overloaded_s"] >= 0
    assert row.full_bas_deferred == shed["full_bas_deferred"] == 0  # (no full BA at all)
    # The report of that one team: its row in the table and the plot.
    from lab.scale import ScaleConfig
    from lab.scale_report import write_scale

    config = ScaleConfig(recordings=(recording,), agents=(4,), work=tmp_path, out=tmp_path)
    md, png = write_scale(config, [[row]], [copies])[0], tmp_path / "scale.png"
    text = md.read_text()
    assert f"| 4 | 2 | 84 | {len(sends)} |" in text and "site1: recording 0" in text
    assert "| shed s |" in text
    assert png.stat().st_size > 10_000


@pytest.mark.slow
def test_core_replay_times_every_stage(recording, tmp_path):
    from lab.scale import core_replay

    recs = load_recordings([recording])
    sends = timeline(recs, plan_copies([robots_of(recs[0])], 2), "camera")
    row = core_replay(sends, 2, tmp_path / "core", full_ba=False)
    assert row.keyframes == 42 and row.messages == len(sends)
    assert row.merges >= 1 and row.optimizations >= 1
    assert row.stage_ms["place recognition"] > 0 and row.stage_ms["pose graph solve"] > 0
    assert row.stage_ms["full BA solve"] == 0.0
    assert row.worker_ms_per_keyframe >= row.stage_ms["verification"]
