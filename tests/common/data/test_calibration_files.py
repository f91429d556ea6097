"""Calibration files as users have them: Kalibr camchain + imu.yaml, EuRoC / TUM-VI
sensor.yaml (radtan and equidistant), which one a folder holds, and every bad calibration
named by file and field."""

from __future__ import annotations

import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from common.data.calibration_files import (
    CalibrationFileError,
    CalibrationFormat,
    find_calibration,
    load_calibration,
    read_camera_yaml,
    read_kalibr,
)
from common.data.euroc import EurocSequence
from common.data.sources import open_source
from common.geometry import inverse_T
from recslam.cli import main as recslam_main

# Kalibr's output format (camchain-imucam-<bag>.yaml), values of EuRoC's cam0.
T_CAM_IMU = [
    [0.0148655429818, 0.999557249008, -0.0257744366974, 0.0652229095355],
    [-0.999880929698, 0.0149672133247, 0.00375618835797, -0.0207064727088],
    [0.00414029679422, 0.025715529948, 0.999660727178, -0.00805460821922],
    [0.0, 0.0, 0.0, 1.0],
]
CAMCHAIN = f"""cam0:
  cam_overlaps: []
  camera_model: pinhole
  distortion_coeffs: [-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05]
  distortion_model: radtan
  intrinsics: [458.654, 457.296, 367.215, 248.375]
  resolution: [752, 480]
  rostopic: /cam0/image_raw
  timeshift_cam_imu: 0.0015
  T_cam_imu:
  - {T_CAM_IMU[0]}
  - {T_CAM_IMU[1]}
  - {T_CAM_IMU[2]}
  - {T_CAM_IMU[3]}
"""
IMU_FLAT = """#Accelerometers
accelerometer_noise_density: 2.0e-3
accelerometer_random_walk: 3.0e-3
#Gyroscopes
gyroscope_noise_density: 1.6968e-04
gyroscope_random_walk: 1.9393e-05
rostopic: /imu0
update_rate: 200.0
"""
IMU_NESTED = """%YAML:1.0
imu0:
  T_i_b:
    - [1.0, 0.0, 0.0, 0.0]
    - [0.0, 1.0, 0.0, 0.0]
    - [0.0, 0.0, 1.0, 0.0]
    - [0.0, 0.0, 0.0, 1.0]
  accelerometer_noise_density: 2.0e-3
  accelerometer_random_walk: 3.0e-3
  gyroscope_noise_density: 1.6968e-04
  gyroscope_random_walk: 1.9393e-05
  rostopic: /imu0
  update_rate: 200.0
"""


def kalibr_files(folder: Path, camchain: str = CAMCHAIN, imu: str = IMU_FLAT) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "camchain.yaml").write_text(camchain)
    (folder / "imu.yaml").write_text(imu)
    return folder / "camchain.yaml"


def test_kalibr_camchain_and_imu(tmp_path: Path) -> None:
    camchain = kalibr_files(tmp_path)
    cal = read_kalibr(camchain, tmp_path / "imu.yaml")
    assert cal.format is CalibrationFormat.KALIBR
    c = cal.cam0
    assert (c.width, c.height, c.model) == (752, 480, "radtan")
    assert (c.fx, c.fy, c.cx, c.cy) == (458.654, 457.296, 367.215, 248.375)
    assert c.distortion == (-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05)
    # Kalibr's T_cam_imu maps IMU points into the camera; the body is the IMU.
    np.testing.assert_allclose(c.T_body_cam, inverse_T(np.array(T_CAM_IMU)), atol=1e-12)
    np.testing.assert_allclose(c.T_body_cam @ np.array(T_CAM_IMU), np.eye(4), atol=1e-12)
    np.testing.assert_array_equal(cal.imu.T_body_imu, np.eye(4))
    assert cal.imu.gyro_noise_density == 1.6968e-04 and cal.imu.accel_random_walk == 3.0e-3
    assert cal.imu.rate_hz == 200.0
    assert cal.timeshift_cam_imu_s == 0.0015 and not cal.camera_rate_stated
    assert (cal.image_topic, cal.imu_topic) == ("/cam0/image_raw", "/imu0")
    assert cal.with_camera_rate(25.0).cam0.rate_hz == 25.0
    # The same from the nested imu0 form (Kalibr's results, OpenVINS) and from a folder.
    kalibr_files(tmp_path / "nested", imu=IMU_NESTED)
    nested = load_calibration(tmp_path / "nested")
    np.testing.assert_array_equal(nested.cam0.T_body_cam, c.T_body_cam)
    assert nested.imu.gyro_random_walk == cal.imu.gyro_random_walk
    # OpenVINS writes the inverse as T_imu_cam.
    rows = inverse_T(np.array(T_CAM_IMU)).tolist()
    text = (
        CAMCHAIN.split("  T_cam_imu:")[0] + "  T_imu_cam:\n" + "".join(f"  - {r}\n" for r in rows)
    )
    inv = load_calibration(kalibr_files(tmp_path / "ov", camchain=text))
    np.testing.assert_allclose(inv.cam0.T_body_cam, c.T_body_cam, atol=1e-12)


def test_kalibr_without_distortion(tmp_path: Path) -> None:
    text = CAMCHAIN.replace("distortion_model: radtan", "distortion_model: none")
    zero = text.replace("[-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05]", "[]")
    cal = load_calibration(kalibr_files(tmp_path, camchain=zero))
    assert cal.cam0.model == "radtan" and cal.cam0.distortion == (0.0, 0.0, 0.0, 0.0)
    with pytest.raises(CalibrationFileError, match="distortion_coeffs must be empty"):
        load_calibration(kalibr_files(tmp_path, camchain=text))


def test_kalibr_T_i_b_moves_the_body(tmp_path: Path) -> None:
    imu = IMU_NESTED.replace("[1.0, 0.0, 0.0, 0.0]", "[1.0, 0.0, 0.0, 0.5]", 1)
    cal = load_calibration(kalibr_files(tmp_path, imu=imu))
    T_body_imu = np.eye(4)
    T_body_imu[0, 3] = -0.5  # T_i_b maps body points into the IMU frame
    np.testing.assert_allclose(cal.imu.T_body_imu, T_body_imu)
    np.testing.assert_allclose(
        cal.cam0.T_body_cam, T_body_imu @ inverse_T(np.array(T_CAM_IMU)), atol=1e-12
    )


def write_tumvi_sequence(root: Path, frames: int = 3, size: int = 512) -> Path:
    """A TUM-VI-like folder as downloaded (EuRoC layout, 512x512 16-bit, equidistant)."""
    mav0 = root / "mav0"
    (mav0 / "cam0" / "data").mkdir(parents=True)
    (mav0 / "imu0").mkdir()
    rng = np.random.default_rng(0)
    t0 = 1520530308199447626
    lines = ["#timestamp [ns],filename"]
    for i in range(frames):
        t = t0 + i * 50_000_000
        image = rng.integers(0, 65535, (size, size), dtype=np.uint16)  # "_16": 16-bit PNGs
        cv2.imwrite(str(mav0 / "cam0" / "data" / f"{t}.png"), image)
        lines.append(f"{t},{t}.png")
    (mav0 / "cam0" / "data.csv").write_text("\n".join(lines) + "\n")
    imu = ["#timestamp [ns],w_x,w_y,w_z,a_x,a_y,a_z"]
    imu += [f"{t0 + k * 5_000_000},0.01,0.02,0.03,0.1,0.2,9.8" for k in range(10 * frames)]
    (mav0 / "imu0" / "data.csv").write_text("\n".join(imu) + "\n")
    (mav0 / "cam0" / "sensor.yaml").write_text(
        "sensor_type: camera\n"
        "comment: VI-Sensor cam0 (TUM-VI)\n"
        "T_BS:\n  cols: 4\n  rows: 4\n"
        "  data: [-0.99952504, 0.00750192, -0.02989013, 0.04557484,\n"
        "         0.02961534, -0.03439736, -0.99896935, -0.07116180,\n"
        "         -0.00852233, -0.99938008, 0.03415885, -0.04468125,\n"
        "         0.0, 0.0, 0.0, 1.0]\n"
        "rate_hz: 20\n"
        f"resolution: [{size}, {size}]\n"
        "camera_model: pinhole\n"
        "intrinsics: [190.97847715128717, 190.9733070521226, 254.93170605935475, "
        "256.8974428996504]\n"
        "distortion_model: equidistant\n"
        "distortion_coefficients: [0.0034823894022493434, 0.0007150348452162257, "
        "-0.0020532361418706202, 0.00020293673591811182]\n"
    )
    (mav0 / "imu0" / "sensor.yaml").write_text(
        "sensor_type: imu\n"
        "T_BS:\n  cols: 4\n  rows: 4\n"
        "  data: [1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0]\n"
        "rate_hz: 200\n"
        "gyroscope_noise_density: 0.00016\n"
        "gyroscope_random_walk: 0.000022\n"
        "accelerometer_noise_density: 0.0028\n"
        "accelerometer_random_walk: 0.00086\n"
    )
    return root


def test_tumvi_folder_as_downloaded(tmp_path: Path) -> None:
    root = write_tumvi_sequence(tmp_path / "dataset-room1_512_16")
    seq = open_source(dataset=root)  # the first image is checked against 512x512
    assert isinstance(seq, EurocSequence)
    c = seq.cam0
    assert (c.width, c.height, c.model) == (512, 512, "equidistant")
    assert c.distortion == (
        0.0034823894022493434,
        0.0007150348452162257,
        -0.0020532361418706202,
        0.00020293673591811182,
    )
    assert seq.calibration_info.format is CalibrationFormat.EUROC
    assert len(seq) == 3 and seq.imu.accel_noise_density == 0.0028
    frame = next(iter(seq.frames(0, 1)))
    assert frame.image is not None and frame.image.shape == (512, 512)
    assert frame.image.dtype == np.uint8  # the reader gives 8-bit gray


def test_folder_calibration_is_chosen_by_what_it_holds(
    tmp_path: Path, euroc_micro: Path, capsys: pytest.CaptureFixture
) -> None:
    euroc = find_calibration(euroc_micro)
    assert euroc is not None and euroc.format is CalibrationFormat.EUROC
    # A EuRoC-layout recording with Kalibr files instead of sensor.yaml.
    seq_dir = tmp_path / "myrobot"
    (seq_dir / "mav0" / "cam0").mkdir(parents=True)
    shutil.copytree(euroc_micro / "mav0" / "imu0", seq_dir / "mav0" / "imu0")
    (seq_dir / "mav0" / "imu0" / "sensor.yaml").unlink()
    shutil.copy(euroc_micro / "mav0" / "cam0" / "data.csv", seq_dir / "mav0" / "cam0")
    (seq_dir / "mav0" / "cam0" / "data").symlink_to(euroc_micro / "mav0" / "cam0" / "data")
    assert find_calibration(seq_dir) is None
    kalibr_files(seq_dir)
    seq = EurocSequence(seq_dir)
    assert seq.calibration_info.format is CalibrationFormat.KALIBR
    assert seq.cam0.rate_hz == pytest.approx(20.0)  # measured: Kalibr states no rate
    # Kalibr's timeshift puts the frames on the IMU clock (t_imu = t_cam + shift).
    plain = EurocSequence(euroc_micro)
    np.testing.assert_array_equal(seq.frame_timestamps_ns, plain.frame_timestamps_ns + 1_500_000)
    np.testing.assert_allclose(seq.cam0.T_body_cam, plain.cam0.T_body_cam, atol=1e-6)
    assert recslam_main(["dataset", "info", str(seq_dir)]) == 0
    assert (
        f"calibration: kalibr calibration ({seq_dir / 'camchain.yaml'}" in capsys.readouterr().out
    )
    # An explicit calibration overrides the folder's.
    other = open_source(dataset=euroc_micro, calibration=seq_dir / "camchain.yaml")
    assert other.calibration_info.format is CalibrationFormat.KALIBR
    assert load_calibration(euroc_micro / "mav0" / "cam0" / "sensor.yaml").imu.rate_hz == 200.0
    (seq_dir / "camchain-other.yaml").write_text(CAMCHAIN)
    with pytest.raises(CalibrationFileError, match="several Kalibr camchain files"):
        find_calibration(seq_dir)
    (tmp_path / "imu_only").mkdir()
    (tmp_path / "imu_only" / "camchain.yaml").write_text(CAMCHAIN)
    with pytest.raises(CalibrationFileError, match="no IMU calibration beside it"):
        load_calibration(tmp_path / "imu_only")
    with pytest.raises(CalibrationFileError, match="no calibration here"):
        load_calibration(tmp_path / "myrobot" / "mav0" / "cam0")


def _bad_camchain(case: str) -> str:
    text = CAMCHAIN
    if case == "missing_intrinsics":
        return text.replace("  intrinsics: [458.654, 457.296, 367.215, 248.375]\n", "")
    if case == "missing_T_cam_imu":
        return text.split("  T_cam_imu:")[0]
    if case == "not_rigid":
        return text.replace(
            "[0.0148655429818, 0.999557249008,", "[0.5148655429818, 0.999557249008,"
        )
    if case == "last_row":
        return text.replace("[0.0, 0.0, 0.0, 1.0]", "[0.0, 0.0, 0.1, 1.0]")
    if case == "reflection":
        r = np.array(T_CAM_IMU)
        r[2, :3] *= -1
        rows = "".join(f"  - {row}\n" for row in r.tolist())
        return text.split("  T_cam_imu:")[0] + "  T_cam_imu:\n" + rows
    if case == "camera_model":
        return text.replace("camera_model: pinhole", "camera_model: omni")
    if case == "distortion_model":
        return text.replace("distortion_model: radtan", "distortion_model: fov")
    if case == "coefficients":
        return text.replace("1.76187114e-05]", "1.76187114e-05, 0.1]")
    if case == "equidistant_count":
        return text.replace("distortion_model: radtan", "distortion_model: equidistant").replace(
            ", 1.76187114e-05]", "]"
        )
    if case == "resolution":
        return text.replace("[752, 480]", "[752.5, 480]")
    raise AssertionError(case)


@pytest.mark.parametrize(
    ("case", "field", "needle"),
    [
        ("missing_intrinsics", "cam0.intrinsics", "missing field"),
        ("missing_T_cam_imu", "cam0.T_cam_imu", "missing field"),
        ("not_rigid", "cam0.T_cam_imu", "not orthonormal"),
        ("last_row", "cam0.T_cam_imu", "last row"),
        ("reflection", "cam0.T_cam_imu", "reflection"),
        ("camera_model", "cam0.camera_model", "'omni', supported: pinhole"),
        ("distortion_model", "cam0.distortion_model", "'fov', supported: radtan, equidistant"),
        ("coefficients", "cam0.distortion_coeffs", "has 5 coefficients; radtan takes 4"),
        ("equidistant_count", "cam0.distortion_coeffs", "has 3 coefficients; equidistant"),
        ("resolution", "cam0.resolution", "two positive integers"),
    ],
)
def test_bad_kalibr_camchain_names_file_and_field(
    tmp_path: Path, case: str, field: str, needle: str
) -> None:
    camchain = kalibr_files(tmp_path, camchain=_bad_camchain(case))
    with pytest.raises(CalibrationFileError) as err:
        load_calibration(tmp_path)
    msg = str(err.value)
    assert str(camchain) in msg and field in msg and needle in msg, msg


@pytest.mark.parametrize(
    ("old", "new", "field", "needle"),
    [
        ("update_rate: 200.0\n", "", "update_rate", "missing field"),
        ("gyroscope_noise_density: 1.6968e-04", "gyroscope_noise_density: -1", "gyroscope", ""),
        ("[0.0, 1.0, 0.0, 0.0]", "[0.0, 2.0, 0.0, 0.0]", "imu0.T_i_b", "not a rigid transform"),
    ],
)
def test_bad_kalibr_imu_names_file_and_field(
    tmp_path: Path, old: str, new: str, field: str, needle: str
) -> None:
    assert old in IMU_NESTED
    kalibr_files(tmp_path, imu=IMU_NESTED.replace(old, new))
    with pytest.raises(CalibrationFileError) as err:
        load_calibration(tmp_path / "camchain.yaml")
    msg = str(err.value)
    assert str(tmp_path / "imu.yaml") in msg and field in msg and needle in msg, msg


def test_bad_euroc_sensor_yaml_names_file_and_field(tmp_path: Path) -> None:
    root = write_tumvi_sequence(tmp_path / "seq", frames=1, size=64)
    y = root / "mav0" / "cam0" / "sensor.yaml"
    text = y.read_text()
    cases = {
        "distortion_model: equidistant": ("distortion_model: kb8", "distortion_model"),
        "distortion_coefficients: [": ("distortion_coefficients: [0.1, ", "coefficients"),
        "camera_model: pinhole": ("camera_model: omni", "camera_model"),
        "  data: [-0.99952504,": ("  data: [-1.99952504,", "T_BS"),
    }
    for old, (new, field) in cases.items():
        y.write_text(text.replace(old, new))
        with pytest.raises(CalibrationFileError) as err:
            read_camera_yaml(y)
        assert f"{y}:" in str(err.value) and field in str(err.value), str(err.value)


def test_a_transform_printed_with_few_digits_is_one_the_edge_accepts(tmp_path: Path) -> None:
    """A camchain that prints 5 decimals is rigid within the file tolerance (1e-4) but not
    within the robot->edge link's (1e-6): the loader snaps its rotation onto SO(3), so the
    robot's RobotSensors decode at the edge. One printed exactly is kept as it is."""
    from common.links.sensors import Sensors, decode_sensors, encode_sensors

    rounded = [[round(x, 5) for x in row] for row in T_CAM_IMU]
    text = CAMCHAIN
    for full, short in zip(T_CAM_IMU, rounded, strict=True):
        text = text.replace(str(full), str(short))
    assert text != CAMCHAIN
    cal = load_calibration(kalibr_files(tmp_path, camchain=text))
    R = cal.cam0.T_body_cam[:3, :3]
    np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-12)
    np.testing.assert_allclose(cal.cam0.T_body_cam, inverse_T(np.array(rounded)), atol=1e-4)
    sent = Sensors(cal.cam0, cal.imu)
    assert decode_sensors(encode_sensors(sent)).same_as(sent)
    exact = load_calibration(kalibr_files(tmp_path / "exact"))
    np.testing.assert_allclose(exact.cam0.T_body_cam, inverse_T(np.array(T_CAM_IMU)), atol=1e-12)
