"""The Table 3 replay on a tiny recording made from the cloud's simulation."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from common.vocabulary import Vocabulary
from lab.table3 import replay, service_config
from services.cloud.recording import RecordingWriter, read_recording
from services.cloud.simulation import (
    circle_poses,
    default_camera,
    encode_session,
    make_session,
    make_world,
    yaw_T,
)


@pytest.fixture(scope="module")
def vocab() -> Vocabulary:
    return Vocabulary.load()


@pytest.fixture(scope="module")
def recording(tmp_path_factory, vocab):
    """Two robots in one room (r1's map offset by a yaw + translation), dense keyframes; each
    keyframe then its new map points, as an edge sends them, 0.2 s apart."""
    world = make_world(31, n_points=2000)
    cam = default_camera()
    sessions = {
        "r0": make_session(
            world, cam, 0, circle_poses(30, turns=0.5), np.eye(4), seed=6, dt=0.2, track_gap=30
        ),
        "r1": make_session(
            world,
            cam,
            1,
            circle_poses(12, turns=0.2, phase=0.3),
            yaw_T(0.7, np.array([1.0, -0.5, 0.0])),
            seed=7,
            dt=0.2,
            t0=10.0,
            track_gap=30,
        ),
    }
    path = tmp_path_factory.mktemp("rec") / "uplink.rec"
    t, seq = 100.0, 0
    with RecordingWriter(path) as w:
        for name, (kfs, mps) in sessions.items():
            for msgs in encode_session(kfs, mps, name, vocab, 7):
                for m in msgs:
                    seq += 1
                    t += 0.2
                    w.write("edge", b"stream", seq, m, t)
    return path


def test_replay_with_and_without_mbp(recording, vocab, tmp_path):
    results = {}
    for mbp in (False, True):
        cfg = dataclasses.replace(
            service_config(mbp),
            optimize_every_keyframes=5,
            mbp_every_keyframes=10,
            mbp_keep_recent=2,
        )
        results[mbp] = replay(
            read_recording(recording), default_camera(), vocab, cfg, tmp_path / str(mbp), "x"
        )
    off, on = results[False], results[True]
    assert off.keyframes_received == on.keyframes_received == 42
    assert off.keyframes == 42 and off.mbp_passes == 0 and off.optimizations > 0
    assert on.mbp_passes > 0 and on.keyframes < off.keyframes
    assert on.map_points <= off.map_points
    assert set(on.trajectories) == {"r0", "r1"}
    assert on.backbone["keyframes"] == on.keyframes
    assert off.backbone["kept_by_one_more_pass"] <= off.keyframes
    # Every new keyframe was queried against what the cloud held; the second robot's map
    # was merged into the first through an accepted detection.
    assert len(on.queries) == 42 and on.queries[0].held_keys.size == 0
    assert off.merges >= 1 and off.maps == [0]
    assert any(d.kind == "merge" for d in off.detections)
    merge = next(d for d in off.detections if d.kind == "merge")
    assert off.info[merge.query_key].robot == "r1" and off.info[merge.match_key].robot == "r0"


def test_record_options_parse_and_reach_the_cloud_command(tmp_path):
    import argparse

    from recslam.commands import cloud, demo, experiment
    from recslam.orchestration import Job, JobConfig

    parser = argparse.ArgumentParser()
    sub = parser.add_subparsers()
    for mod in (cloud, demo, experiment):
        mod.register(sub)
    args = parser.parse_args(["experiment", "table3", "--recording", "r.rec", "--data", "d"])
    assert args.func is experiment.run_table3 and str(args.recording) == "r.rec"
    args = parser.parse_args(["cloud", "--state-dir", "s", "--record", "u.rec"])
    assert str(args.record) == "u.rec"
    assert parser.parse_args(["cloud", "--state-dir", "s"]).record is None
    assert str(parser.parse_args(["demo", "--record-uplink", "u.rec"]).record_uplink) == "u.rec"
    (tmp_path / "data" / "robot0" / "mav0").mkdir(parents=True)
    rec = tmp_path / "u.rec"
    job = Job(JobConfig(dataset=tmp_path / "data", run_dir=tmp_path / "run", record_uplink=rec))
    argv = job.cloud_argv()
    assert argv[argv.index("--record") + 1] == str(rec) and argv.index("cloud") < argv.index(
        "--record"
    )
    plain = Job(JobConfig(dataset=tmp_path / "data", run_dir=tmp_path / "run2"))
    assert "--record" not in plain.cloud_argv()
