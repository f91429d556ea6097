"""End to end: the generator's EuRoC output reads back, is deterministic, and looks usable."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from common.calibration import EUROC_IMU
from common.data.euroc import EurocSequence
from common.data.synth import EUROC_CAM0, SynthConfig, generate_dataset
from common.data.synth.imu_sim import ideal_imu
from common.data.synth.scene import vicon_room
from common.data.synth.trajectory import T_IMU_CAM, make_trajectories
from common.geometry import quat_wxyz_to_R
from recslam.commands import dataset as dataset_cmd

ROBOTS, SECONDS, SEED = 2, 0.5, 7


def _cli(argv: list[str]) -> int:
    parser = argparse.ArgumentParser()
    sub = parser.add_subparsers()
    dataset_cmd.register(sub)
    args = parser.parse_args(argv)
    return args.func(args)


@pytest.fixture(scope="module")
def generated(tmp_path_factory) -> tuple[Path, Path]:
    a = tmp_path_factory.mktemp("synth_a")
    b = tmp_path_factory.mktemp("synth_b")
    generate_dataset(a, SynthConfig(robots=ROBOTS, seconds=SECONDS, seed=SEED, progress=False))
    argv = [
        "dataset",
        "synth",
        "--out",
        str(b),
        "--robots",
        str(ROBOTS),
        "--seconds",
        str(SECONDS),
        "--seed",
        str(SEED),
        "--no-progress",
    ]
    assert _cli(argv) == 0
    return a, b


@pytest.mark.slow
def test_same_seed_gives_identical_bytes(generated) -> None:
    a, b = generated
    files_a = sorted(p.relative_to(a) for p in a.rglob("*") if p.is_file())
    files_b = sorted(p.relative_to(b) for p in b.rglob("*") if p.is_file())
    assert files_a == files_b
    assert len(files_a) > 2 * 11
    for rel in files_a:
        assert (a / rel).read_bytes() == (b / rel).read_bytes(), rel


def test_layout_and_metadata(generated) -> None:
    out, _ = generated
    meta = json.loads((out / "dataset.json").read_text())
    assert (meta["robots"], meta["seconds"], meta["seed"]) == (ROBOTS, SECONDS, SEED)
    assert meta["generator"].startswith("recslam-synth")
    assert [s["name"] for s in meta["sequences"]] == ["robot0", "robot1"]
    for name in ("contact_sheet.png", "trajectories_top.png"):
        img = cv2.imread(str(out / name))
        assert img is not None and img.shape[0] > 200 and img.std() > 10


def test_sequences_read_back(generated) -> None:
    out, _ = generated
    flights = make_trajectories(vicon_room(), ROBOTS, SECONDS, SEED)
    starts = []
    for k, traj in enumerate(flights):
        seq = EurocSequence(out / f"robot{k}")
        assert len(seq) == 11
        its, fts = seq.imu_timestamps_ns, seq.frame_timestamps_ns
        assert len(its) == 101 and np.all(np.diff(its) == 5_000_000)
        np.testing.assert_array_equal(fts, its[::10])  # frames on the IMU clock grid
        starts.append(int(its[0]))
        cam = seq.cam0
        assert (cam.width, cam.height) == (752, 480)
        assert (cam.fx, cam.fy, cam.cx, cam.cy) == (458.654, 457.296, 367.215, 248.375)
        assert cam.distortion == (-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05)
        np.testing.assert_array_equal(cam.T_body_cam, T_IMU_CAM)
        assert seq.imu.gyro_noise_density == EUROC_IMU.gyro_noise_density
        assert seq.imu.accel_random_walk == EUROC_IMU.accel_random_walk
        gt = seq.groundtruth
        assert gt is not None and len(gt) == len(its)
        np.testing.assert_array_equal(gt.timestamps_ns, its)
        t = (its - its[0]) * 1e-9
        st = traj.evaluate(t)
        np.testing.assert_allclose(gt.p_world_body, st.p_world_body, atol=1e-12)
        np.testing.assert_allclose(gt.v_world_body, st.v_world_body, atol=1e-12)
        np.testing.assert_allclose(quat_wxyz_to_R(gt.q_world_body_wxyz), st.R_world_body, atol=1e-9)
        # Measurements = truth + the written biases + white noise (within 5 sigma).
        gyro, accel = ideal_imu(traj, t)
        sg = EUROC_IMU.gyro_noise_density * 200**0.5
        sa = EUROC_IMU.accel_noise_density * 200**0.5
        assert np.abs(seq.gyro - gt.bias_gyro - gyro).max() < 5 * sg
        assert np.abs(seq.accel - gt.bias_accel - accel).max() < 5 * sa
        assert np.abs(gt.bias_gyro).max() > 0  # biases are really there
    assert starts[1] > starts[0]  # robots start at different times


def test_frames_are_textured_and_feature_rich(generated) -> None:
    out, _ = generated
    orb = cv2.ORB_create(nfeatures=1000)
    for k in range(ROBOTS):
        seq = EurocSequence(out / f"robot{k}")
        for i in (0, 10):
            img = seq.load_image(i)
            assert 40 < img.mean() < 210 and img.std() > 30
            assert (img < 8).mean() < 0.05 and (img > 250).mean() < 0.05
            assert len(orb.detect(img, None)) >= 300
        # Consecutive frames differ (motion, noise) but not wildly.
        a, b = seq.load_image(9).astype(float), seq.load_image(10).astype(float)
        assert 0.5 < np.abs(a - b).mean() < 60


def test_calibration_states_the_distortion_used_for_rendering(generated) -> None:
    out, _ = generated
    seq = EurocSequence(out / "robot0")
    cam = seq.cam0
    assert (cam.fx, cam.cx, cam.distortion[0]) == (EUROC_CAM0.fx, EUROC_CAM0.cx, EUROC_CAM0.k1)


def test_info_command(generated, capsys) -> None:
    out, _ = generated
    assert _cli(["dataset", "info", str(out)]) == 0
    text = capsys.readouterr().out
    assert "robot0" in text and "robot1" in text and "752x480" in text
    assert "flight ring, world vicon, no exposure steps, no motion blur" in text
    assert _cli(["dataset", "info", str(out / "missing")]) == 2


def test_groundtruth_quaternions_are_continuous(generated) -> None:
    from common.data.synth.trajectory import continuous_quaternions

    q = np.array([[1.0, 0, 0, 0], [0.0, 0, 0, 1], [-0.1, 0, 0, 0.995], [-1.0, 0, 0, 0]])
    out = continuous_quaternions(q)
    assert np.all(np.einsum("ij,ij->i", out[1:], out[:-1]) >= 0)
    np.testing.assert_array_equal(np.abs(out), np.abs(q))
    gt = EurocSequence(generated[0] / "robot1").groundtruth
    assert gt is not None
    dots = np.einsum("ij,ij->i", gt.q_world_body_wxyz[1:], gt.q_world_body_wxyz[:-1])
    assert dots.min() > 0.99


@pytest.mark.slow
def test_rerun_replaces_previous_output(tmp_path) -> None:
    cfg = SynthConfig(robots=2, seconds=0.1, seed=1, progress=False, contact_sheet=False)
    generate_dataset(tmp_path, cfg)
    (tmp_path / "notes.txt").write_text("keep me")
    generate_dataset(
        tmp_path, SynthConfig(robots=1, seconds=0.1, seed=1, progress=False, contact_sheet=False)
    )
    assert not (tmp_path / "robot1").exists()  # stale robot removed
    assert (tmp_path / "notes.txt").read_text() == "keep me"  # foreign files untouched
    assert json.loads((tmp_path / "dataset.json").read_text())["robots"] == 1


def test_bad_settings_are_refused(tmp_path, capsys) -> None:
    from common.data.synth import SynthError

    with pytest.raises(SynthError, match="robots"):
        SynthConfig(robots=0)
    with pytest.raises(SynthError, match="multiple"):
        SynthConfig(camera_rate_hz=30.0)
    assert _cli(["dataset", "synth", "--out", str(tmp_path), "--robots", "0"]) == 2
    assert "robots" in capsys.readouterr().err


@pytest.mark.slow
def test_cli_harder_options_are_recorded_and_shown(tmp_path, capsys) -> None:
    out = tmp_path / "hard"
    argv = ["dataset", "synth", "--out", str(out), "--robots", "1", "--seconds", "0.3"]
    argv += ["--flight", "figure8+aggressive", "--world", "hall", "--exposure-steps"]
    argv += ["--motion-blur-ms", "4", "--no-progress"]
    assert _cli(argv) == 0
    assert "flight figure8+aggressive, world hall, exposure steps, motion blur 4 ms" in (
        capsys.readouterr().out
    )
    meta = json.loads((out / "dataset.json").read_text())
    assert meta["harder"]["flight"] == "figure8+aggressive" and meta["harder"]["world"] == "hall"
    assert meta["trajectories"][0]["family"] == "figure8"
    assert meta["room"]["hi"] == [10.0, 8.0, 8.0]
    assert _cli(["dataset", "info", str(out)]) == 0
    assert "flight figure8+aggressive, world hall" in capsys.readouterr().out
    assert _cli(["dataset", "info", str(out), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["dataset"]["harder"]["motion_blur_ms"] == 4.0
    for bad, why in (
        (["--flight", "spiral"], "spiral"),
        (["--world", "moon"], "moon"),
        (["--motion-blur-ms", "60"], "motion blur 60"),
    ):
        assert _cli(["dataset", "synth", "--out", str(tmp_path / "x"), *bad]) == 2
        assert why in capsys.readouterr().err


@pytest.mark.slow
def test_cli_flies_a_recorded_trajectory(tmp_path, hand_made_tum, capsys) -> None:
    out = tmp_path / "rec"
    argv = ["dataset", "synth", "--out", str(out), "--seconds", "0.3", "--no-progress"]
    assert _cli([*argv, "--trajectory", str(hand_made_tum)]) == 0
    meta = json.loads((out / "dataset.json").read_text())
    assert meta["robots"] == 1 and meta["harder"]["trajectory_files"] == [str(hand_made_tum)]
    assert meta["trajectories"][0]["family"] == "recorded"
    assert "quintic smoothing spline" in meta["trajectories"][0]["smoothing"]
    gt = EurocSequence(out / "robot0").groundtruth
    assert gt is not None and np.abs(gt.p_world_body[:, :2]).max() < 2.0
    capsys.readouterr()
    assert _cli(["dataset", "info", str(out)]) == 0
    assert f"recorded flights {hand_made_tum}" in capsys.readouterr().out
    two = ["--trajectory", f"{hand_made_tum},{hand_made_tum}", "--robots", "1"]
    assert _cli([*argv, *two]) == 2
    assert "2 files for --robots 1" in capsys.readouterr().err
    assert _cli([*argv, "--trajectory", str(tmp_path / "none.tum")]) == 2
    assert "none.tum: no such file" in capsys.readouterr().err
