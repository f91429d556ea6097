"""``recslam robot`` refuses to start on a bad calibration: exit code 2 and
``recslam robot: error: <file>...<field>`` before any connection is tried."""

from __future__ import annotations

from pathlib import Path

import pytest

from recslam.cli import main
from services.robot.__main__ import main as module_main

EDGE = ["--edge", "127.0.0.1:9", "--agent-id", "r1", "--rate", "max"]

CAMCHAIN = """cam0:
  camera_model: pinhole
  distortion_coeffs: [-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05]
  distortion_model: radtan
  intrinsics: [458.654, 457.296, 367.215, 248.375]
  resolution: [752, 480]
  T_cam_imu:
  - [0.0148655429818, 0.999557249008, -0.0257744366974, 0.0652229095355]
  - [-0.999880929698, 0.0149672133247, 0.00375618835797, -0.0207064727088]
  - [0.00414029679422, 0.025715529948, 0.999660727178, -0.00805460821922]
  - [0.0, 0.0, 0.0, 1.0]
"""
IMU = """accelerometer_noise_density: 2.0e-3
accelerometer_random_walk: 3.0e-3
gyroscope_noise_density: 1.6968e-04
gyroscope_random_walk: 1.9393e-05
update_rate: 200.0
"""


def kalibr(folder: Path, camchain: str) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "imu.yaml").write_text(IMU)
    (folder / "camchain.yaml").write_text(camchain)
    return folder / "camchain.yaml"


def euroc_calibration(folder: Path, euroc_micro: Path, old: str, new: str) -> Path:
    """A copy of the excerpt's cam0/imu0 sensor.yaml with ``old`` replaced in cam0's."""
    src = euroc_micro / "mav0"
    (folder / "cam0").mkdir(parents=True)
    (folder / "imu0").mkdir()
    text = (src / "cam0" / "sensor.yaml").read_text()
    assert old in text
    (folder / "cam0" / "sensor.yaml").write_text(text.replace(old, new))
    (folder / "imu0" / "sensor.yaml").write_text((src / "imu0" / "sensor.yaml").read_text())
    return folder / "cam0" / "sensor.yaml"


def refused(argv: list[str], capsys: pytest.CaptureFixture) -> str:
    assert main(["robot", *argv, *EDGE]) == 2
    err = capsys.readouterr().err
    assert err.startswith("recslam robot: error: "), err
    return err


@pytest.mark.parametrize(
    ("edit", "needles"),
    [
        (("[752, 480]", "[640, 480]"), ["image is 752x480, sensor.yaml says 640x480"]),
        (("radial-tangential", "fisheye"), ["distortion_model is 'fisheye'", "supported"]),
        (("[0.0148655429818,", "[0.5148655429818,"), ["T_BS is not a rigid transform"]),
        (("rate_hz: 20\n", ""), ["missing field 'rate_hz'"]),
        (("1.76187114e-05]", "1.76187114e-05, 0.0]"), ["distortion_coefficients has 5"]),
    ],
)
def test_bad_euroc_calibration_refuses_to_start(
    tmp_path: Path, euroc_micro: Path, capsys: pytest.CaptureFixture, edit, needles
) -> None:
    calib = euroc_calibration(tmp_path / "calib", euroc_micro, *edit)
    err = refused(["--dataset", str(euroc_micro), "--calibration", str(calib)], capsys)
    assert str(calib) in err, err
    for needle in needles:
        assert needle in err, err


@pytest.mark.parametrize(
    ("old", "new", "needle"),
    [
        ("[0.0, 0.0, 0.0, 1.0]", "[0.0, 0.0, 0.0, 2.0]", "cam0.T_cam_imu is not a rigid"),
        ("camera_model: pinhole", "camera_model: ds", "cam0.camera_model is 'ds'"),
        ("  resolution: [752, 480]\n", "", "missing field 'cam0.resolution'"),
        ("[752, 480]", "[512, 512]", "image is 752x480, camchain.yaml says 512x512"),
    ],
)
def test_bad_kalibr_calibration_refuses_to_start(
    tmp_path: Path, euroc_micro: Path, capsys: pytest.CaptureFixture, old, new, needle
) -> None:
    camchain = kalibr(tmp_path, CAMCHAIN.replace(old, new))
    err = refused(["--dataset", str(euroc_micro), "--calibration", str(camchain)], capsys)
    assert str(camchain) in err and needle in err, err


def test_bag_needs_a_calibration(
    tmp_path: Path, capsys: pytest.CaptureFixture, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.delenv("RECSLAM_DATASET", raising=False)
    bag = tmp_path / "run.bag"
    bag.write_bytes(b"")
    err = refused(["--bag", str(bag), "--image-topic", "/cam0", "--imu-topic", "/imu0"], capsys)
    assert "--bag" in err and "needs --calibration" in err, err
    err = refused([], capsys)
    assert "--dataset FOLDER or --bag PATH" in err, err
    err = refused(["--dataset", str(tmp_path), "--bag", str(bag)], capsys)
    assert "not both" in err, err


def test_module_entry_point_refuses_too(
    tmp_path: Path, euroc_micro: Path, capsys: pytest.CaptureFixture
) -> None:
    camchain = kalibr(tmp_path, CAMCHAIN.replace("distortion_model: radtan", "distortion_model: x"))
    argv = ["--dataset", str(euroc_micro), "--calibration", str(camchain), *EDGE]
    with pytest.raises(SystemExit) as exit_:
        module_main(argv)
    assert exit_.value.code == 2
    err = capsys.readouterr().err
    assert err.startswith("python -m services.robot: error: ") and "cam0.distortion_model" in err


def test_bag_arguments_build_the_config(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    import argparse

    from recslam.commands import robot

    monkeypatch.setenv("RECSLAM_DATASET", str(tmp_path / "from-env"))  # gives way to --bag
    parser = argparse.ArgumentParser()
    robot.register(parser.add_subparsers(dest="command", required=True))
    argv = ["robot", "--bag", "run.bag", "--calibration", "camchain.yaml", *EDGE]
    cfg = robot.build_config(
        parser.parse_args([*argv, "--image-topic", "/cam0", "--imu-topic", "/imu0"])
    )
    assert cfg.dataset is None and cfg.bag == Path("run.bag")
    assert cfg.calibration == Path("camchain.yaml")
    assert (cfg.image_topic, cfg.imu_topic) == ("/cam0", "/imu0")
