"""Fixtures of the lab's tests: the vocabulary and a tiny uplink recording."""

from __future__ import annotations

import numpy as np
import pytest

from common.vocabulary import Vocabulary
from services.cloud.store.recording import RecordingWriter
from sim.cloud import (
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
