"""Exposure steps and motion blur: schedules as specified, images brighter / darker by the
step's gain, blur as the mean of the exposure's sub-renders (softer when moving, the same when
still), and a generated dataset that records and shows them."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from common.data.euroc import EurocSequence
from common.data.synth import SynthConfig, SynthError, generate_dataset
from common.data.synth.cameras import EUROC_CAM0
from common.data.synth.render import EffectsConfig, RenderConfig, Renderer
from common.data.synth.scene import vicon_room
from common.data.synth.textures import build_atlas
from common.geometry import make_T

SHARP = RenderConfig(noise_std=0.0, vignetting=0.0, exposure_amplitude=0.0)
R_LOOK_MINUS_X = np.array([[0.0, 0.0, -1.0], [1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


@pytest.fixture(scope="module")
def renderer() -> Renderer:
    scene = vicon_room()
    return Renderer(scene, build_atlas(scene, seed=3), EUROC_CAM0, SHARP)


def _pose(yaw: float) -> np.ndarray:
    R = R_LOOK_MINUS_X @ cv2.Rodrigues(np.array([0.0, yaw, 0.0]))[0]
    return make_T(R, np.array([1.0, 0.5, 1.6]))


def test_subframes_cover_the_exposure() -> None:
    assert len(EffectsConfig().subframe_offsets_s()) == 0
    off = EffectsConfig(motion_blur_ms=8.0).subframe_offsets_s()
    np.testing.assert_allclose(off, [-0.004, -0.002, 0.0, 0.002, 0.004])
    assert len(EffectsConfig(motion_blur_ms=1.0).subframe_offsets_s()) == 2
    assert len(EffectsConfig(motion_blur_ms=40.0).subframe_offsets_s()) == 9


def test_exposure_schedule_steps_within_bounds() -> None:
    cfg = EffectsConfig(exposure_steps=True)
    times, gains = cfg.exposure_schedule(120.0, np.random.default_rng(4))
    assert times[0] == 0.0 and gains[0] == 1.0 and len(times) >= 30
    gaps = np.diff(times)
    assert gaps.min() >= 1.5 and gaps.max() <= 4.0
    assert gains.min() >= 0.4 and gains.max() <= 2.0
    ratio = gains[1:] / gains[:-1]
    assert np.all((ratio >= 0.5 - 1e-9) & (ratio <= 2.0 + 1e-9))
    assert np.abs(np.log(ratio)).mean() > 0.2  # real steps, not jitter
    off_t, off_g = EffectsConfig().exposure_schedule(120.0, np.random.default_rng(4))
    assert off_t.tolist() == [0.0] and off_g.tolist() == [1.0]


def test_gain_scales_the_image(renderer: Renderer) -> None:
    T = _pose(0.0)
    base = renderer.render(T, 0.0, np.random.default_rng(0)).astype(float)
    dark = renderer.render(T, 0.0, np.random.default_rng(0), gain=0.6).astype(float)
    assert dark.mean() / base.mean() == pytest.approx(0.6, rel=0.01)


def test_motion_blur_is_the_mean_of_sub_renders(renderer: Renderer) -> None:
    still = np.stack([_pose(0.0)] * 3)
    sharp = renderer.render(still[0], 0.0, np.random.default_rng(0))
    same = renderer.render(still[0], 0.0, np.random.default_rng(0), exposure_poses=still)
    assert np.abs(same.astype(int) - sharp.astype(int)).max() <= 1
    # 2.5 rad/s of yaw during 8 ms: about 9 px of smear at the image centre.
    moving = np.stack([_pose(y) for y in np.linspace(-0.01, 0.01, 5)])
    blurred = renderer.render(moving[2], 0.0, np.random.default_rng(0), exposure_poses=moving)
    mean = np.mean([renderer.render_radiance(T).radiance for T in moving], axis=0)
    mean = cv2.GaussianBlur(mean.astype(np.float32), (0, 0), SHARP.blur_sigma)
    expected = np.clip(np.rint(mean), 0, 255)
    assert np.abs(blurred.astype(float) - expected).max() <= 1.0
    centre = renderer.render(moving[2], 0.0, np.random.default_rng(0))

    def sharpness(img: np.ndarray) -> float:
        return float(cv2.Laplacian(img.astype(np.float32), cv2.CV_32F).var())

    assert sharpness(blurred) < 0.6 * sharpness(centre)


@pytest.mark.slow
def test_generated_dataset_with_steps_and_blur(tmp_path: Path) -> None:
    effects = EffectsConfig(exposure_steps=True, step_every_s=(0.4, 0.7), motion_blur_ms=4.0)
    cfg = SynthConfig(
        robots=1,
        seconds=1.5,
        seed=2,
        flight="ring+hover",
        world="room-random",
        effects=effects,
        progress=False,
        contact_sheet=False,
    )
    generate_dataset(tmp_path, cfg)
    meta = json.loads((tmp_path / "dataset.json").read_text())
    assert meta["harder"] == {
        "flight": "ring+hover",
        "world": "room-random",
        "trajectory_files": [],
        "exposure_steps": True,
        "motion_blur_ms": 4.0,
        "imu_files": [],
        "time_offset_ms": 0.0,
    }
    assert meta["config"]["effects"]["step_every_s"] == [0.4, 0.7]
    assert meta["room"]["name"] == "room-random"
    steps = meta["sequences"][0]["exposure_steps"]
    assert len(steps["t_s"]) >= 3
    # Still camera (hover): frame brightness follows the schedule's gain.
    seq = EurocSequence(tmp_path / "robot0")
    t = (seq.frame_timestamps_ns - seq.frame_timestamps_ns[0]) * 1e-9
    gain = np.array(steps["gain"])[np.searchsorted(steps["t_s"], t, side="right") - 1]
    means = np.array([seq.load_image(i).astype(float).mean() for i in range(len(seq))])
    norm = means / gain
    assert norm.std() / norm.mean() < 0.03
    assert np.ptp(gain) > 0.2


def test_bad_effects_are_refused() -> None:
    with pytest.raises(SynthError, match="motion blur 60"):
        SynthConfig(effects=EffectsConfig(motion_blur_ms=60.0))
    with pytest.raises(SynthError, match="--flight 'spiral'"):
        SynthConfig(flight="spiral")
    with pytest.raises(SynthError, match="world 'moon'"):
        SynthConfig(world="moon")
    with pytest.raises(SynthError, match="2 trajectory files for 1 robots"):
        SynthConfig(robots=1, trajectory_files=("a.tum", "b.tum"))
