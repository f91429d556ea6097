"""EuRoC reader: the real V1_01 excerpt, ground-truth parsing, and every broken-input case."""

from __future__ import annotations

import re
import shutil
from pathlib import Path

import numpy as np
import pytest

from common.data.euroc import (
    EurocError,
    EurocSequence,
    read_camera_csv,
    read_groundtruth,
    read_imu_csv,
)
from common.errors import RecslamError

# Two rows in the exact format of V1_01's state_groundtruth_estimate0/data.csv.
GT_TEXT = (
    "#timestamp, p_RS_R_x [m], p_RS_R_y [m], p_RS_R_z [m], q_RS_w [], q_RS_x [], q_RS_y [], "
    "q_RS_z [], v_RS_R_x [m s^-1], v_RS_R_y [m s^-1], v_RS_R_z [m s^-1], b_w_RS_S_x [rad s^-1], "
    "b_w_RS_S_y [rad s^-1], b_w_RS_S_z [rad s^-1], b_a_RS_S_x [m s^-2], b_a_RS_S_y [m s^-2], "
    "b_a_RS_S_z [m s^-2]\n"
    "1403715274302142976,0.878612,2.142470,0.947262,0.060514,-0.828459,-0.058956,-0.553641,"
    "0.009474,-0.014009,-0.002145,-0.002229,0.020700,0.076350,-0.012492,0.547666,0.069073\n"
    "1403715274307142912,0.878658,2.142400,0.947250,0.060486,-0.828427,-0.058934,-0.553697,"
    "0.009237,-0.013841,-0.002375,-0.002229,0.020700,0.076350,-0.012492,0.547666,0.069073\n"
)


@pytest.fixture(scope="module")
def seq(euroc_micro: Path) -> EurocSequence:
    return EurocSequence(euroc_micro)


# ------------------------------------------------------------------ the real excerpt


def test_excerpt_calibration(seq: EurocSequence, euroc_micro: Path) -> None:
    assert len(seq) == 95
    assert seq.name == euroc_micro.name  # "euroc-micro-V1_01" unless relocated
    c = seq.cam0
    assert (c.width, c.height) == (752, 480)
    assert (c.fx, c.fy, c.cx, c.cy) == (458.654, 457.296, 367.215, 248.375)
    assert c.distortion == (-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05)
    assert c.rate_hz == 20.0
    np.testing.assert_array_equal(
        c.T_body_cam[0], [0.0148655429818, -0.999880929698, 0.00414029679422, -0.0216401454975]
    )
    np.testing.assert_array_equal(
        c.T_body_cam[2], [-0.0257744366974, 0.00375618835797, 0.999660727178, 0.00981073058949]
    )
    np.testing.assert_array_equal(c.T_body_cam[3], [0, 0, 0, 1])
    assert seq.cam1 is None
    assert seq.cameras == ["cam0"]
    imu = seq.imu
    assert imu.gyro_noise_density == 1.6968e-04
    assert imu.gyro_random_walk == 1.9393e-05
    assert imu.accel_noise_density == 2.0e-3
    assert imu.accel_random_walk == 3.0e-3
    assert imu.rate_hz == 200.0
    np.testing.assert_array_equal(imu.T_body_imu, np.eye(4))
    assert seq.groundtruth is None


def test_excerpt_arrays(seq: EurocSequence) -> None:
    ts = seq.frame_timestamps_ns
    assert ts.dtype == np.int64 and ts.shape == (95,)
    assert ts[0] == 1403715273262142976 and ts[-1] == 1403715277962142976
    assert len(seq.image_paths) == 95 and seq.image_paths[0].name == "1403715273262142976.png"
    m = len(seq.imu_timestamps_ns)
    assert m == 29120 and seq.gyro.shape == (m, 3) and seq.accel.shape == (m, 3)
    assert seq.imu_timestamps_ns.dtype == np.int64
    # first row of imu0/data.csv, parsed exactly
    assert seq.gyro[0].tolist() == [
        -0.0020943951023931952,
        0.017453292519943295,
        0.07749261878854824,
    ]
    assert seq.accel[0, 0] == 9.0874956666666655
    # the IMU runs far beyond the images (145 s vs 4.7 s)
    assert seq.imu_timestamps_ns[-1] - ts[-1] > 100e9
    assert not seq.gyro.flags.writeable


def test_excerpt_imu_batches_tile_timeline(seq: EurocSequence) -> None:
    frames = list(seq.frames(load_images=False))
    assert [f.index for f in frames] == list(range(95))
    assert all(f.image is None for f in frames)
    prev = None
    for f in frames:
        bts = f.imu.timestamps_ns
        assert f.imu.gyro.shape == (len(bts), 3) and f.imu.accel.shape == (len(bts), 3)
        assert np.all(bts <= f.timestamp_ns)
        if prev is not None:
            assert 9 <= len(f.imu) <= 11, (f.index, len(f.imu))
            assert np.all(bts > prev)
        prev = f.timestamp_ns
    joined = np.concatenate([f.imu.timestamps_ns for f in frames])
    expected = seq.imu_timestamps_ns[seq.imu_timestamps_ns <= frames[-1].timestamp_ns]
    np.testing.assert_array_equal(joined, expected)  # no gaps, no overlaps
    np.testing.assert_array_equal(
        np.concatenate([f.imu.gyro for f in frames]), seq.gyro[: len(expected)]
    )
    # the IMU starts with the first image here: frame 0 gets that single sample
    assert frames[0].imu.timestamps_ns.tolist() == [frames[0].timestamp_ns]


def test_excerpt_images_and_partial_iteration(seq: EurocSequence) -> None:
    frames = list(seq.frames(start=92, stop=95))
    assert [f.index for f in frames] == [92, 93, 94]
    for f in frames:
        assert f.image is not None
        assert f.image.dtype == np.uint8 and f.image.shape == (480, 752)
        assert 0 < f.image.mean() < 255
    full = list(seq.frames(load_images=False))
    np.testing.assert_array_equal(frames[0].imu.timestamps_ns, full[92].imu.timestamps_ns)
    np.testing.assert_array_equal(seq.load_image(94), frames[-1].image)
    assert seq.load_image(0).shape == (480, 752)
    batch = seq.imu_between(int(full[10].timestamp_ns), int(full[11].timestamp_ns))
    np.testing.assert_array_equal(batch.timestamps_ns, full[11].imu.timestamps_ns)
    with pytest.raises(IndexError):
        list(seq.frames(start=5, stop=96))
    with pytest.raises(EurocError, match="no cam1"):
        seq.load_image(0, cam=1)


def test_excerpt_mav0_root_and_summary(seq: EurocSequence, euroc_micro: Path) -> None:
    other = EurocSequence(euroc_micro / "mav0")
    assert other.name == seq.name and len(other) == len(seq)
    s = seq.summary()
    assert s["frames"] == 95
    assert s["duration_s"] == pytest.approx(4.7)
    assert s["imu_rate_hz"] == pytest.approx(200.0, rel=1e-6)
    assert s["imu_duration_s"] == pytest.approx(145.595, abs=1e-3)
    assert s["has_groundtruth"] is False
    assert s["cameras"] == ["cam0"]


# ------------------------------------------------------------------ standalone readers


def test_read_groundtruth_euroc_format(tmp_path: Path) -> None:
    p = tmp_path / "data.csv"
    p.write_text(GT_TEXT.replace("\n", "\r\n"))  # CRLF tolerated
    gt = read_groundtruth(p)
    assert len(gt) == 2 and gt.timestamps_ns.dtype == np.int64
    assert gt.timestamps_ns[1] == 1403715274307142912
    assert gt.p_world_body[0].tolist() == [0.878612, 2.142470, 0.947262]
    assert gt.q_world_body_wxyz[0].tolist() == [0.060514, -0.828459, -0.058956, -0.553641]
    assert gt.v_world_body[1].tolist() == [0.009237, -0.013841, -0.002375]
    assert gt.bias_gyro[0].tolist() == [-0.002229, 0.020700, 0.076350]
    assert gt.bias_accel[0].tolist() == [-0.012492, 0.547666, 0.069073]
    T = gt.T_world_body()
    assert T.shape == (2, 4, 4)
    np.testing.assert_allclose(
        T[:, :3, :3] @ T[:, :3, :3].transpose(0, 2, 1), [np.eye(3)] * 2, atol=1e-12
    )
    np.testing.assert_array_equal(T[0, :3, 3], gt.p_world_body[0])


def test_read_groundtruth_pose_only(tmp_path: Path) -> None:
    p = tmp_path / "pose.csv"
    p.write_text("#t,x,y,z,qw,qx,qy,qz\n5,1,2,3,1,0,0,0\n6,1,2,3,0,1,0,0\n")
    gt = read_groundtruth(p)
    assert gt.p_world_body.tolist() == [[1, 2, 3], [1, 2, 3]]
    assert np.isnan(gt.v_world_body).all() and np.isnan(gt.bias_accel).all()


def test_read_imu_and_camera_csv(tmp_path: Path) -> None:
    imu = tmp_path / "imu.csv"
    imu.write_text("#h\n10,1,2,3,4,5,6\n20,0.1,1e-5,-3,4,5,6.5\n")
    b = read_imu_csv(imu)
    assert b.timestamps_ns.tolist() == [10, 20]
    assert b.gyro[1].tolist() == [0.1, 1e-5, -3.0] and b.accel[1].tolist() == [4, 5, 6.5]
    (tmp_path / "data").mkdir()
    (tmp_path / "data" / "10.png").write_bytes(b"")
    cam = tmp_path / "cam.csv"
    cam.write_text("#timestamp [ns],filename\n10,10.png\n")
    s = read_camera_csv(cam)
    assert s.timestamps_ns.tolist() == [10] and s.image_paths == (tmp_path / "data" / "10.png",)
    assert s.csv_lines == (2,)


# ------------------------------------------------------------------ broken inputs


@pytest.fixture
def small(tmp_path: Path, euroc_micro: Path) -> Path:
    """A 5-frame, 200-sample copy of the excerpt in tmp_path (never touches /work/shared)."""
    src, dst = euroc_micro / "mav0", tmp_path / "seq" / "mav0"
    (dst / "cam0" / "data").mkdir(parents=True)
    (dst / "imu0").mkdir()
    for f in ("cam0/sensor.yaml", "imu0/sensor.yaml", "body.yaml"):
        shutil.copy(src / f, dst / f)
    cam_lines = (src / "cam0" / "data.csv").read_text().splitlines()[:6]
    (dst / "cam0" / "data.csv").write_text("\n".join(cam_lines) + "\n")
    for line in cam_lines[1:]:
        name = line.split(",")[1]
        shutil.copy(src / "cam0" / "data" / name, dst / "cam0" / "data" / name)
    imu_lines = (src / "imu0" / "data.csv").read_text().splitlines()[:201]
    (dst / "imu0" / "data.csv").write_text("\n".join(imu_lines) + "\n")
    return (tmp_path / "seq").resolve()  # messages name resolved paths


def _edit_line(path: Path, lineno: int, new: str | None) -> None:
    """Replace (or with None, delete) 1-based line ``lineno``."""
    lines = path.read_text().splitlines()
    if new is None:
        del lines[lineno - 1]
    else:
        lines[lineno - 1] = new
    path.write_text("\n".join(lines) + "\n")


def _replace(path: Path, old: str, new: str) -> None:
    text = path.read_text()
    assert old in text
    path.write_text(text.replace(old, new, 1))


def test_small_copy_reads(small: Path) -> None:
    s = EurocSequence(small)
    assert len(s) == 5 and len(s.imu_timestamps_ns) == 200
    assert s.load_image(4).shape == (480, 752)


def _line(small: Path, rel: str, lineno: int) -> str:
    return f"{small / 'mav0' / rel}:{lineno}:"


def _fields(path: Path, lineno: int) -> list[str]:
    return path.read_text().splitlines()[lineno - 1].split(",")


@pytest.mark.parametrize(
    ("case", "rel", "lineno", "needle"),
    [
        ("imu_columns", "imu0/data.csv", 7, "expected 7 columns, found 6"),
        ("imu_text", "imu0/data.csv", 12, "'abc' is not a finite number"),
        ("imu_nan", "imu0/data.csv", 13, "'nan' is not a finite number"),
        ("imu_ts_float", "imu0/data.csv", 9, "not an integer"),
        ("imu_duplicate", "imu0/data.csv", 31, "duplicate timestamp"),
        ("imu_decreasing", "imu0/data.csv", 50, "decreasing timestamp"),
        ("cam_missing_image", "cam0/data.csv", 4, "not found"),
        ("cam_columns", "cam0/data.csv", 3, "expected 2 columns, found 1"),
        ("cam_decreasing", "cam0/data.csv", 5, "decreasing timestamp"),
        ("yaml_intrinsics", "cam0/sensor.yaml", 19, "intrinsics must be a list of 4"),
        ("yaml_T_BS", "cam0/sensor.yaml", 7, "not a rigid transform"),
        ("yaml_distortion_model", "cam0/sensor.yaml", 20, "supported: radial-tangential"),
        ("yaml_syntax", "cam0/sensor.yaml", 18, "invalid YAML"),
        ("yaml_imu_noise", "imu0/sensor.yaml", 17, "gyroscope_noise_density must be a number"),
        ("yaml_rate", "imu0/sensor.yaml", 14, "rate_hz must be a finite positive"),
    ],
)
def test_broken_input_names_file_and_line(
    small: Path, case: str, rel: str, lineno: int, needle: str
) -> None:
    p = small / "mav0" / rel
    f = _fields(p, lineno)
    if case == "imu_columns":
        _edit_line(p, lineno, ",".join(f[:6]))
    elif case == "imu_text":
        _edit_line(p, lineno, ",".join([*f[:3], "abc", *f[4:]]))
    elif case == "imu_nan":
        _edit_line(p, lineno, ",".join([*f[:6], "nan"]))
    elif case == "imu_ts_float":
        _edit_line(p, lineno, ",".join([f[0] + ".5", *f[1:]]))
    elif case in ("imu_duplicate", "imu_decreasing", "cam_decreasing"):
        prev = _fields(p, lineno - (1 if case == "imu_duplicate" else 2))[0]
        _edit_line(p, lineno, ",".join([prev, *f[1:]]))
    elif case == "cam_missing_image":
        (p.parent / "data" / f[1]).unlink()
    elif case == "cam_columns":
        _edit_line(p, lineno, f[0])
    elif case == "yaml_intrinsics":
        _replace(p, "intrinsics: [458.654, 457.296, 367.215, 248.375]", "intrinsics: [1, 2, 3]")
    elif case == "yaml_T_BS":
        _replace(p, "[0.0148655429818,", "[2.0148655429818,")
    elif case == "yaml_distortion_model":
        _replace(p, "radial-tangential", "fov")
    elif case == "yaml_syntax":
        _replace(p, "resolution: [752, 480]", "resolution: [752, 480")
    elif case == "yaml_imu_noise":
        _replace(p, "gyroscope_noise_density: 1.6968e-04", "gyroscope_noise_density: fast")
    elif case == "yaml_rate":
        _replace(p, "rate_hz: 200", "rate_hz: 0")
    with pytest.raises(EurocError) as err:
        EurocSequence(small)
    msg = str(err.value)
    assert _line(small, rel, lineno) in msg, msg
    assert needle in msg, msg
    assert isinstance(err.value, RecslamError)


def test_undecodable_image_names_file(small: Path) -> None:
    csv = small / "mav0" / "cam0" / "data.csv"
    name = _fields(csv, 4)[1]
    (small / "mav0" / "cam0" / "data" / name).write_bytes(b"\x89PNG\r\n\x1a\n garbage")
    s = EurocSequence(small)  # images are lazy: construction succeeds
    s.load_image(0)
    with pytest.raises(EurocError) as err:
        s.load_image(2)
    assert name in str(err.value) and f"{csv}:4" in str(err.value)
    with pytest.raises(EurocError, match="does not decode"):
        list(s.frames())


def test_wrong_image_size(small: Path) -> None:
    _replace(small / "mav0" / "cam0" / "sensor.yaml", "[752, 480]", "[640, 480]")
    with pytest.raises(EurocError, match=re.escape("752x480, sensor.yaml says 640x480")):
        EurocSequence(small).load_image(0)


@pytest.mark.parametrize(
    ("remove", "needle"),
    [
        ("imu0", "missing IMU folder"),
        ("imu0/data.csv", "missing file"),
        ("imu0/sensor.yaml", "missing file"),
        ("cam0/data.csv", "missing file"),
        ("cam0/data", "missing image folder"),
        ("cam0", "no mav0"),  # then imu0 too: mav0 given directly is no sequence at all
    ],
)
def test_missing_parts(small: Path, remove: str, needle: str) -> None:
    target = small / "mav0" / remove
    if target.is_dir():
        shutil.rmtree(target)
    else:
        target.unlink()
    if remove == "cam0":
        with pytest.raises(EurocError, match="missing camera folder"):
            EurocSequence(small)
        shutil.rmtree(small / "mav0" / "imu0")
        with pytest.raises(EurocError, match=needle):
            EurocSequence(small / "mav0")
        return
    with pytest.raises(EurocError) as err:
        EurocSequence(small)
    assert needle in str(err.value) and str(target) in str(err.value)


def test_missing_field_and_empty_csv(small: Path, tmp_path: Path) -> None:
    y = small / "mav0" / "cam0" / "sensor.yaml"
    _replace(y, "resolution: [752, 480]\n", "")
    with pytest.raises(EurocError, match=re.escape("sensor.yaml: missing field 'resolution'")):
        EurocSequence(small)
    empty = tmp_path / "empty.csv"
    empty.write_text(
        "#timestamp [ns],w_RS_S_x [rad s^-1],w_RS_S_y [rad s^-1],w_RS_S_z [rad s^-1],"
        "a_RS_S_x [m s^-2],a_RS_S_y [m s^-2],a_RS_S_z [m s^-2]\n"
    )
    with pytest.raises(EurocError, match=re.escape("empty.csv: no data rows")):
        read_imu_csv(empty)
    with pytest.raises(EurocError, match=r"not a sequence|does not exist"):
        EurocSequence(tmp_path / "nowhere")


def test_broken_groundtruth(small: Path) -> None:
    gt_dir = small / "mav0" / "state_groundtruth_estimate0"
    gt_dir.mkdir()
    p = gt_dir / "data.csv"
    p.write_text(GT_TEXT)
    assert EurocSequence(small).groundtruth is not None
    _edit_line(p, 3, ",".join(_fields(p, 3)[:16]))
    with pytest.raises(EurocError, match=re.escape(f"{p}:3: expected 17 columns, found 16")):
        EurocSequence(small)
    p.write_text(GT_TEXT.replace("0.060486,", "0.560486,"))
    with pytest.raises(EurocError, match=re.escape(f"{p}:3: quaternion norm")):
        read_groundtruth(p)
    p.write_text(GT_TEXT.replace("\n1403715274307142912,", "\n1403715274302142976,"))
    with pytest.raises(EurocError, match=re.escape(f"{p}:3: duplicate timestamp")):
        read_groundtruth(p)
    p.write_text("#t\n1,2,3\n")
    with pytest.raises(EurocError, match=re.escape(f"{p}:2: expected 17 or 8 columns, found 3")):
        read_groundtruth(p)
