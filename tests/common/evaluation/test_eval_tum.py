"""TUM files: exact round trip, evo reads ours and we read evo's, errors name file and line."""

from __future__ import annotations

import numpy as np
import pytest
from evo.tools import file_interface

from common.evaluation.errors import TrajectoryError, TumFormatError
from common.evaluation.trajectory import Trajectory
from common.evaluation.tum import (
    format_timestamp_ns,
    parse_timestamp_ns,
    parse_tum,
    read_tum,
    write_tum,
)


def test_round_trip_is_exact(tools, rng, tmp_path):
    traj = tools.smooth(rng, n=300, name="robot_a")
    path = write_tum(tmp_path / "sub" / "robot_a.tum", traj)
    back = read_tum(path)
    assert back.name == "robot_a"
    np.testing.assert_array_equal(back.timestamps_ns, traj.timestamps_ns)
    np.testing.assert_array_equal(back.p_world_body, traj.p_world_body)
    np.testing.assert_allclose(back.q_wxyz, traj.q_wxyz, rtol=0, atol=4e-16)
    first = path.read_text().splitlines()[1].split(" ")
    assert first[0] == "1403636579.763555527"
    assert len(first) == 8


def test_evo_reads_our_files(tools, rng, tmp_path):
    traj = tools.smooth(rng, n=200)
    path = write_tum(tmp_path / "est.tum", traj)
    evo_traj = file_interface.read_tum_trajectory_file(str(path))
    assert evo_traj.num_poses == len(traj)
    np.testing.assert_allclose(evo_traj.timestamps, traj.timestamps_ns * 1e-9, rtol=1e-15)
    np.testing.assert_array_equal(evo_traj.positions_xyz, traj.p_world_body)
    np.testing.assert_allclose(evo_traj.orientations_quat_wxyz, traj.q_wxyz, atol=1e-15)


def test_we_read_evo_files(tools, rng, tmp_path):
    traj = tools.smooth(rng, n=100)
    path = tmp_path / "evo.tum"
    file_interface.write_tum_trajectory_file(str(path), tools.to_evo(traj))
    ours = read_tum(path)
    # evo stores stamps as float64 seconds: sub-µs digits of epoch stamps are lost there.
    assert np.max(np.abs(ours.timestamps_ns - traj.timestamps_ns)) < 1_000
    np.testing.assert_allclose(ours.p_world_body, traj.p_world_body, rtol=1e-15)
    np.testing.assert_allclose(ours.q_wxyz, traj.q_wxyz, atol=1e-15)


@pytest.mark.parametrize(
    ("text", "ns"),
    [
        ("1403636579.763555527", 1_403_636_579_763_555_527),
        ("1.403636579763555527e+09", 1_403_636_579_763_555_527),
        ("0.5", 500_000_000),
        ("12", 12_000_000_000),
        ("-0.000000001", -1),
        ("1.0000000005", 1_000_000_000),  # half-even rounding at the ns digit
    ],
)
def test_timestamp_text_conversions(text, ns):
    assert parse_timestamp_ns(text) == ns


def test_timestamp_formatting():
    assert format_timestamp_ns(1_403_636_579_763_555_527) == "1403636579.763555527"
    assert format_timestamp_ns(5) == "0.000000005"
    assert format_timestamp_ns(-1_500_000_000) == "-1.500000000"


def test_comments_blank_lines_and_tabs_are_accepted():
    text = "# header\n\n1.0 0 0 0 0 0 0 1\n2.0\t1 2 3 0 0 1 0\n"
    traj = parse_tum(text)
    np.testing.assert_array_equal(traj.timestamps_ns, [1_000_000_000, 2_000_000_000])
    np.testing.assert_array_equal(traj.q_wxyz[1], [0, 0, 0, 1])  # stored (w, x, y, z)
    np.testing.assert_array_equal(traj.p_world_body[1], [1, 2, 3])


@pytest.mark.parametrize(
    ("text", "match"),
    [
        ("1.0 0 0 0 0 0 0 1\n2.0 0 0 0 0 0 1\n", r"f\.tum:2: expected 8 fields"),
        ("1.0 0 0 0 0 0 0 1\nabc 0 0 0 0 0 0 1\n", r"f\.tum:2: not a number"),
        ("1.0 0 0 0 0 0 0 1\n2.0 0 nan 0 0 0 0 1\n", r"f\.tum:2: non-finite"),
        ("# c\n1.0 0 0 0 0 0 0 2\n", r"f\.tum:2: quaternion norm 2"),
        ("1.0 0 0 0 0 0 0 1\n# c\n1.0 0 0 0 0 0 0 1\n", r"f\.tum:3: timestamp 1\.0+ s does not"),
        ("# only comments\n", r"f\.tum: no poses"),
    ],
)
def test_malformed_files_name_file_and_line(tmp_path, text, match):
    path = tmp_path / "f.tum"
    path.write_text(text)
    with pytest.raises(TumFormatError, match=match):
        read_tum(path)


def test_missing_file_is_a_clear_error(tmp_path):
    with pytest.raises(TumFormatError, match="no such TUM file"):
        read_tum(tmp_path / "nope.tum")


def test_trajectory_validates_its_arrays():
    ts = np.array([0, 1, 2], dtype=np.int64)
    p = np.zeros((3, 3))
    q = np.tile([1.0, 0, 0, 0], (3, 1))
    traj = Trajectory(ts, p, q)
    with pytest.raises(ValueError):
        traj.p_world_body[0, 0] = 1.0  # read-only
    with pytest.raises(TrajectoryError, match="strictly increase"):
        Trajectory(np.array([0, 2, 2]), p, q)
    with pytest.raises(TrajectoryError, match="integers"):
        Trajectory(np.array([0.0, 1.0, 2.0]), p, q)
    with pytest.raises(TrajectoryError, match=r"p_world_body must be \(3, 3\)"):
        Trajectory(ts, np.zeros((2, 3)), q)
    with pytest.raises(TrajectoryError, match="zero quaternion at index 1"):
        Trajectory(ts, p, np.array([[1.0, 0, 0, 0], [0, 0, 0, 0], [1, 0, 0, 0]]))
    with pytest.raises(TrajectoryError, match="non-finite pose at index 2"):
        Trajectory(ts, np.array([[0, 0, 0], [0, 0, 0], [0, np.inf, 0]]), q)
    T = traj.T_world_body
    assert T.shape == (3, 4, 4)
    np.testing.assert_array_equal(Trajectory.from_poses(ts, T).p_world_body, p)
