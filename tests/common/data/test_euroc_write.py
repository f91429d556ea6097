"""EuRoC writer: exact write -> read round trip, EuRoC file formats, interop, misuse."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import yaml
from hypothesis import given
from hypothesis import strategies as st

from common.calibration import EUROC_IMU, CameraCalibration, ImuCalibration
from common.data.euroc import (
    GROUNDTRUTH_CSV_HEADER,
    EurocError,
    EurocGroundTruth,
    EurocSequence,
    read_camera_yaml,
    read_imu_yaml,
)
from common.data.euroc_write import EurocWriter, format_float
from common.geometry import R_to_quat_wxyz, make_T, so3_exp

W, H = 64, 48


def _camera(seed: int) -> CameraCalibration:
    rng = np.random.default_rng(seed)
    return CameraCalibration(
        width=W,
        height=H,
        fx=40.123456789 + seed,
        fy=41.0 + 1e-9,
        cx=31.7,
        cy=23.3,
        distortion=(-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05),
        T_body_cam=make_T(so3_exp(rng.normal(size=3)), rng.normal(size=3)),
        rate_hz=20.0,
    )


def _imu_calib() -> ImuCalibration:
    return ImuCalibration(
        gyro_noise_density=1.6968e-04,
        gyro_random_walk=1e-5,  # repr '1e-05': must still read back as a float
        accel_noise_density=2.0e-3,
        accel_random_walk=3.0e-3,
        rate_hz=200.0,
        T_body_imu=make_T(so3_exp(np.array([0.1, -0.2, 0.3])), np.array([0.01, 0.0, -0.02])),
    )


def _groundtruth(ts: np.ndarray, rng: np.random.Generator) -> EurocGroundTruth:
    k = len(ts)
    q = R_to_quat_wxyz(np.stack([so3_exp(w) for w in rng.normal(size=(k, 3))]))
    return EurocGroundTruth(
        timestamps_ns=ts,
        p_world_body=rng.normal(size=(k, 3)),
        q_world_body_wxyz=q,
        v_world_body=rng.normal(size=(k, 3)),
        bias_gyro=rng.normal(scale=1e-3, size=(k, 3)),
        bias_accel=rng.normal(scale=1e-2, size=(k, 3)),
    )


def _assert_same_camera(a: CameraCalibration, b: CameraCalibration) -> None:
    assert (a.width, a.height, a.fx, a.fy, a.cx, a.cy) == (
        b.width,
        b.height,
        b.fx,
        b.fy,
        b.cx,
        b.cy,
    )
    assert a.distortion == b.distortion and a.rate_hz == b.rate_hz
    np.testing.assert_array_equal(a.T_body_cam, b.T_body_cam)


@pytest.fixture
def written(tmp_path: Path) -> dict:
    """A 6-frame stereo sequence with 200 Hz IMU (starting before the images) and ground truth."""
    rng = np.random.default_rng(7)
    t0 = 1_403_715_273_262_142_976
    frame_ts = t0 + np.arange(6, dtype=np.int64) * 50_000_000
    imu_ts = t0 - 100_000_000 + np.arange(100, dtype=np.int64) * 5_000_000
    gyro = rng.normal(size=(100, 3))
    accel = rng.normal(size=(100, 3)) * 10
    gyro[0] = [0.1 + 0.2, 1e-300, -0.0]  # awkward values survive exactly
    images = {c: rng.integers(0, 256, size=(6, H, W), dtype=np.uint8) for c in ("cam0", "cam1")}
    cams = {"cam0": _camera(0), "cam1": _camera(1)}
    gt = _groundtruth(imu_ts[::2], rng)
    root = tmp_path / "synthetic_seq"
    with EurocWriter(root, body_yaml_comment="synthetic robot 0") as w:
        for c in ("cam0", "cam1"):
            w.add_camera(c, cams[c], comment=f"synthetic {c}")
        for i, t in enumerate(frame_ts):
            for c in ("cam0", "cam1"):
                w.add_image(c, int(t), images[c][i])
        w.write_imu(_imu_calib(), imu_ts, gyro, accel)
        w.write_groundtruth(gt)
    return dict(
        root=root,
        frame_ts=frame_ts,
        imu_ts=imu_ts,
        gyro=gyro,
        accel=accel,
        images=images,
        cams=cams,
        gt=gt,
    )


def test_round_trip_exact(written: dict) -> None:
    seq = EurocSequence(written["root"])
    assert seq.name == "synthetic_seq" and len(seq) == 6
    assert seq.cameras == ["cam0", "cam1"]
    _assert_same_camera(seq.cam0, written["cams"]["cam0"])
    assert seq.cam1 is not None
    _assert_same_camera(seq.cam1, written["cams"]["cam1"])
    calib = _imu_calib()
    for f in ("gyro_noise_density", "gyro_random_walk", "accel_noise_density", "rate_hz"):
        assert getattr(seq.imu, f) == getattr(calib, f)
    np.testing.assert_array_equal(seq.imu.T_body_imu, calib.T_body_imu)
    np.testing.assert_array_equal(seq.frame_timestamps_ns, written["frame_ts"])
    np.testing.assert_array_equal(seq.imu_timestamps_ns, written["imu_ts"])
    np.testing.assert_array_equal(seq.gyro, written["gyro"])  # bit-exact, not approx
    np.testing.assert_array_equal(seq.accel, written["accel"])
    assert math.copysign(1.0, seq.gyro[0, 2]) == -1.0 and seq.gyro[0, 1] == 1e-300
    for i in range(6):
        np.testing.assert_array_equal(seq.load_image(i, cam=0), written["images"]["cam0"][i])
        np.testing.assert_array_equal(seq.load_image(i, cam=1), written["images"]["cam1"][i])
    gt, ref = seq.groundtruth, written["gt"]
    assert gt is not None
    for f in ("timestamps_ns", "p_world_body", "q_world_body_wxyz", "v_world_body"):
        np.testing.assert_array_equal(getattr(gt, f), getattr(ref, f))
    np.testing.assert_array_equal(gt.bias_gyro, ref.bias_gyro)
    np.testing.assert_array_equal(gt.bias_accel, ref.bias_accel)
    assert seq.summary()["has_groundtruth"] is True


def test_round_trip_frames_with_preroll(written: dict) -> None:
    seq = EurocSequence(written["root"])
    frames = list(seq.frames(cam=1))
    # IMU starts 100 ms (20 samples) before the first image: frame 0 gets them all + its own
    assert len(frames[0].imu) == 21
    assert [len(f.imu) for f in frames[1:]] == [10] * 5
    np.testing.assert_array_equal(frames[3].image, written["images"]["cam1"][3])


def test_files_have_euroc_format(written: dict) -> None:
    mav0 = written["root"] / "mav0"
    cam_csv = (mav0 / "cam0" / "data.csv").read_text().splitlines()
    assert cam_csv[0] == "#timestamp [ns],filename"
    assert cam_csv[1] == f"{written['frame_ts'][0]},{written['frame_ts'][0]}.png"
    gt_lines = (mav0 / "state_groundtruth_estimate0" / "data.csv").read_text().splitlines()
    assert gt_lines[0] == GROUNDTRUTH_CSV_HEADER
    assert gt_lines[0].startswith("#timestamp, p_RS_R_x [m], p_RS_R_y [m], p_RS_R_z [m], q_RS_w []")
    assert gt_lines[0].endswith("b_a_RS_S_x [m s^-2], b_a_RS_S_y [m s^-2], b_a_RS_S_z [m s^-2]")
    assert len(gt_lines[1].split(",")) == 17
    imu_lines = (mav0 / "imu0" / "data.csv").read_text().splitlines()
    assert imu_lines[1].split(",")[1:4] == [repr(0.1 + 0.2), "1e-300", "-0.0"]
    assert (mav0 / "body.yaml").read_text() == "%YAML:1.0\ncomment: 'synthetic robot 0'\n"
    cam_yaml = (mav0 / "cam0" / "sensor.yaml").read_text()
    assert cam_yaml.startswith("%YAML:1.0\n")
    for line in (
        "sensor_type: camera",
        "rate_hz: 20",
        "resolution: [64, 48]",
        "camera_model: pinhole",
        "distortion_model: radial-tangential",
    ):
        assert line in cam_yaml.splitlines()
    imu_yaml = (mav0 / "imu0" / "sensor.yaml").read_text()
    assert "gyroscope_random_walk: 1.0e-05" in imu_yaml and "rate_hz: 200" in imu_yaml


def test_readable_by_other_tools(written: dict) -> None:
    """evo reads our ground truth; numpy.loadtxt reads our IMU CSV with '#' comments."""
    from evo.tools import file_interface

    mav0 = written["root"] / "mav0"
    traj = file_interface.read_euroc_csv_trajectory(
        mav0 / "state_groundtruth_estimate0" / "data.csv"
    )
    np.testing.assert_allclose(traj.positions_xyz, written["gt"].p_world_body, rtol=0, atol=1e-12)
    np.testing.assert_allclose(traj.timestamps, written["gt"].timestamps_ns * 1e-9)
    imu = np.loadtxt(mav0 / "imu0" / "data.csv", delimiter=",", comments="#")
    np.testing.assert_array_equal(imu[:, 1:4], written["gyro"])


def test_rewrites_real_calibration_exactly(tmp_path: Path, euroc_micro: Path) -> None:
    cam = read_camera_yaml(euroc_micro / "mav0" / "cam0" / "sensor.yaml")
    imu = read_imu_yaml(euroc_micro / "mav0" / "imu0" / "sensor.yaml")
    w = EurocWriter(tmp_path)
    w.add_camera("cam0", cam, comment="VI-Sensor cam0 (MT9M034)")
    w.write_imu(imu, np.array([0, 5_000_000]), np.zeros((2, 3)), np.ones((2, 3)))
    w.close()
    _assert_same_camera(read_camera_yaml(tmp_path / "mav0" / "cam0" / "sensor.yaml"), cam)
    again = read_imu_yaml(tmp_path / "mav0" / "imu0" / "sensor.yaml")
    assert again.gyro_noise_density == imu.gyro_noise_density == EUROC_IMU.gyro_noise_density
    assert again.accel_random_walk == imu.accel_random_walk
    text = (tmp_path / "mav0" / "cam0" / "sensor.yaml").read_text()
    assert "intrinsics: [458.654, 457.296, 367.215, 248.375] #fu, fv, cu, cv" in text
    assert "comment: 'VI-Sensor cam0 (MT9M034)'" in text
    # the cam0 data.csv of a camera without images is just the header
    assert (tmp_path / "mav0" / "cam0" / "data.csv").read_text() == "#timestamp [ns],filename\n"


@given(st.floats(allow_nan=False, allow_infinity=False))
def test_format_float_round_trips_through_yaml(x: float) -> None:
    s = format_float(x)
    assert float(s) == x
    loaded = yaml.safe_load(f"v: {s}")["v"]
    assert isinstance(loaded, float | int) and loaded == x


def test_writer_rejects_misuse(tmp_path: Path) -> None:
    w = EurocWriter(tmp_path)
    img = np.zeros((H, W), np.uint8)
    with pytest.raises(EurocError, match="add_camera first"):
        w.add_image("cam0", 1, img)
    with pytest.raises(EurocError, match="camera name"):
        w.add_camera("left", _camera(0))
    w.add_camera("cam0", _camera(0))
    with pytest.raises(EurocError, match="added twice"):
        w.add_camera("cam0", _camera(0))
    with pytest.raises(EurocError, match="uint8"):
        w.add_image("cam0", 1, img.astype(np.float32))
    with pytest.raises(EurocError, match="uint8"):
        w.add_image("cam0", 1, np.zeros((W, H), np.uint8))
    w.add_image("cam0", 10, img)
    with pytest.raises(EurocError, match="not after previous"):
        w.add_image("cam0", 10, img)
    ts = np.array([1, 2, 2])
    with pytest.raises(EurocError, match="not strictly increasing at index 2"):
        w.write_imu(EUROC_IMU, ts, np.zeros((3, 3)), np.zeros((3, 3)))
    with pytest.raises(EurocError, match="must be"):
        w.write_imu(EUROC_IMU, np.array([1, 2]), np.zeros((2, 3)), np.zeros((3, 3)))
    with pytest.raises(EurocError, match="non-finite"):
        w.write_imu(EUROC_IMU, np.array([1, 2]), np.full((2, 3), np.nan), np.zeros((2, 3)))
    with pytest.raises(EurocError, match="integer"):
        w.write_imu(EUROC_IMU, np.array([1.0, 2.0]), np.zeros((2, 3)), np.zeros((2, 3)))
    w.close()
    with pytest.raises(EurocError, match="closed"):
        w.add_image("cam0", 20, img)
    assert (tmp_path / "mav0" / "cam0" / "data.csv").read_text().splitlines()[1] == "10,10.png"
