"""Recorded flights (``--trajectory FILE``): TUM and EuRoC read alike, smoothed close to the
samples, recentred into the room, speeds as recorded, malformed or oversized files refused
with the file (and line) named."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from common.data.synth.recorded import read_recording, recorded_flights
from common.data.synth.scene import vicon_room
from common.data.synth.trajectory import TrajectoryConfig, TrajectoryError, check_trajectory
from common.data.synth.worlds import make_world

SCENE = vicon_room()
REGION = (SCENE.room_lo, SCENE.room_hi)


def _fly(*files: Path, seconds: float = 8.0, scene=SCENE, region=REGION, world="vicon"):
    return recorded_flights(scene, region, tuple(str(f) for f in files), seconds, world)


def test_tum_flight_is_smoothed_recentred_and_in_bounds(hand_made_tum: Path) -> None:
    rec = read_recording(hand_made_tum)
    assert rec.format == "tum" and len(rec.t) == 17 and rec.t[-1] == pytest.approx(8.0)
    (f,) = _fly(hand_made_tum)
    assert check_trajectory(SCENE, f, 8.0, TrajectoryConfig()) is None
    # The bounding box's centre went to the room's centre (z: mid-height).
    lo, hi = rec.p.min(axis=0), rec.p.max(axis=0)
    np.testing.assert_allclose(np.asarray(f.offset) + (lo + hi) / 2, [0.0, 0.0, 1.75], atol=1e-12)
    # Smoothed within a few mm of the samples, attitude within 0.5 degrees.
    st = f.evaluate(rec.t)
    assert np.abs(st.p_world_body - (rec.p + f.offset)).max() < 0.01
    from common.geometry import quat_wxyz_to_R, so3_log

    R = quat_wxyz_to_R(rec.q_wxyz)
    err = [np.linalg.norm(so3_log(a.T @ b)) for a, b in zip(R, st.R_world_body, strict=True)]
    assert max(err) < np.radians(0.5)
    # Speed and rate as recorded: ~0.55 m/s along the arc, ~0.5 rad/s of yaw.
    dense = f.evaluate(np.arange(0.0, 8.0, 0.005))
    speed = np.linalg.norm(dense.v_world_body, axis=1)
    rate = np.linalg.norm(dense.omega_body, axis=1)
    assert 0.45 < speed.mean() < 0.7 and speed.max() < 0.8
    assert 0.4 < np.median(rate) < 0.6 and rate.max() < 0.8
    # Analytic derivatives of the smoothed motion (the IMU comes from them).
    h, t = 1e-4, np.linspace(0.5, 7.5, 15)
    sp, sm, s0 = f.evaluate(t + h), f.evaluate(t - h), f.evaluate(t)
    np.testing.assert_allclose(
        s0.v_world_body, (sp.p_world_body - sm.p_world_body) / (2 * h), atol=1e-6
    )
    np.testing.assert_allclose(
        s0.a_world_body, (sp.v_world_body - sm.v_world_body) / (2 * h), atol=1e-4
    )


def test_euroc_file_and_flipped_quaternion_signs_give_the_same_flight(
    hand_made_tum: Path, tmp_path: Path
) -> None:
    rows = [line.split() for line in hand_made_tum.read_text().splitlines()[1:]]
    csv = tmp_path / "data.csv"
    lines = ["#timestamp, p_RS_R_x [m], p_RS_R_y [m], p_RS_R_z [m], q_RS_w [], q_RS_x [], ..."]
    flipped = []
    for i, r in enumerate(rows):
        t_ns = round(float(r[0]) * 1e9)
        qx, qy, qz, qw = (float(v) for v in r[4:8])
        lines.append(f"{t_ns},{r[1]},{r[2]},{r[3]},{qw},{qx},{qy},{qz}")
        s = -1.0 if i % 3 == 1 else 1.0
        flipped.append(" ".join([*r[:4], *(f"{s * float(v):.4f}" for v in r[4:8])]))
    csv.write_text("\n".join(lines) + "\n")
    tum2 = tmp_path / "flipped.tum"
    tum2.write_text("\n".join(flipped) + "\n")
    assert read_recording(csv).format == "euroc"
    t = np.linspace(0.0, 8.0, 50)
    (a,), (b,), (c,) = _fly(hand_made_tum), _fly(csv), _fly(tum2)
    for other in (b, c):
        sa, so = a.evaluate(t), other.evaluate(t)
        np.testing.assert_allclose(so.p_world_body, sa.p_world_body, atol=1e-6)
        np.testing.assert_allclose(so.R_world_body, sa.R_world_body, atol=1e-6)


def test_malformed_files_name_the_file_and_line(hand_made_tum: Path, tmp_path: Path) -> None:
    lines = hand_made_tum.read_text().splitlines()
    bad = tmp_path / "bad.tum"
    bad.write_text("\n".join([*lines[:4], "1403715274.600 1.0 2.0 3.0 0 0 1", *lines[4:]]))
    with pytest.raises(TrajectoryError, match=r"bad\.tum:5: expected 8 fields"):
        read_recording(bad)
    csv = tmp_path / "bad.csv"
    csv.write_text("1000,0,0,1,1,0,0,0\n2000,0,x,1,1,0,0,0\n")
    with pytest.raises(TrajectoryError, match=r"bad\.csv:2: column 3"):
        read_recording(csv)
    with pytest.raises(TrajectoryError, match=r"missing\.tum: no such file"):
        read_recording(tmp_path / "missing.tum")
    few = tmp_path / "few.tum"
    few.write_text("\n".join(lines[:4]) + "\n")
    with pytest.raises(TrajectoryError, match=r"few\.tum: 3 poses"):
        read_recording(few)


def test_flights_that_do_not_fit_are_refused(hand_made_tum: Path, tmp_path: Path) -> None:
    with pytest.raises(TrajectoryError, match=r"lasts 8\.00 s, less than --seconds 20"):
        _fly(hand_made_tum, seconds=20.0)
    big = tmp_path / "big.tum"
    rows = [line.split() for line in hand_made_tum.read_text().splitlines()[1:]]
    big.write_text(
        "\n".join(" ".join([r[0], *(f"{5 * float(v):.3f}" for v in r[1:4]), *r[4:]]) for r in rows)
    )
    with pytest.raises(TrajectoryError, match=r"do not fit the vicon world.*try --world hall"):
        _fly(big)
    hall = make_world("hall", 0)
    (f,) = _fly(big, scene=hall.scene, region=hall.region, world="hall")
    assert check_trajectory(hall.scene, f, 8.0, TrajectoryConfig(max_speed=4.0)) is None
