"""Mixed camera teams: each robot's sensor.yaml states its own camera, images have its size, and
a fisheye renders the scene where its model projects it."""

from __future__ import annotations

import argparse
import json
import re
from pathlib import Path

import cv2
import numpy as np
import pytest

from common.camera import PinholeEquidistant, camera_model
from common.data.euroc import EurocSequence
from common.data.synth import CAMERA_PRESETS, SynthConfig, SynthError, generate_dataset
from common.data.synth.render import RenderConfig, Renderer
from common.data.synth.scene import vicon_room
from common.data.synth.textures import build_atlas
from common.geometry import make_T
from recslam.commands import dataset as dataset_cmd

TEAM = ("euroc", "wide", "fisheye")
CLEAN = RenderConfig(noise_std=0.0, blur_sigma=0.0, vignetting=0.0, exposure_amplitude=0.0)
# Camera axes (x right, y down, z forward) as columns, looking along world -x (at wall x = -4).
R_LOOK_MINUS_X = np.array([[0.0, 0.0, -1.0], [1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


def _cli(argv: list[str]) -> int:
    parser = argparse.ArgumentParser()
    dataset_cmd.register(parser.add_subparsers())
    args = parser.parse_args(argv)
    return args.func(args)


@pytest.fixture(scope="module")
def team(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("team")
    argv = ["dataset", "synth", "--out", str(out), "--robots", "3", "--seconds", "0.25"]
    argv += ["--seed", "4", "--cameras", ",".join(TEAM), "--no-progress"]
    assert _cli(argv) == 0
    return out


def _yaml_field(text: str, key: str) -> str:
    m = re.search(rf"^{key}: (.*?)( #.*)?$", text, re.MULTILINE)
    assert m is not None, key
    return m.group(1)


@pytest.mark.slow
def test_each_robot_states_its_own_camera_and_images_have_its_size(team: Path) -> None:
    meta = json.loads((team / "dataset.json").read_text())
    assert meta["config"]["cameras"] == list(TEAM)
    assert [s["camera"] for s in meta["sequences"]] == list(TEAM)
    mounts = []
    for k, name in enumerate(TEAM):
        model = CAMERA_PRESETS[name].model
        cam0 = team / f"robot{k}" / "mav0" / "cam0"
        text = (cam0 / "sensor.yaml").read_text()
        expected = "equidistant" if isinstance(model, PinholeEquidistant) else "radial-tangential"
        assert _yaml_field(text, "distortion_model") == expected
        assert _yaml_field(text, "resolution") == f"[{model.width}, {model.height}]"
        coeffs = json.loads(_yaml_field(text, "distortion_coefficients"))
        np.testing.assert_allclose(coeffs, model.dist_coeffs, rtol=1e-12)
        T = np.array(json.loads(re.search(r"data: (\[.*?\])", text, re.DOTALL).group(1)))
        np.testing.assert_allclose(T.reshape(4, 4), CAMERA_PRESETS[name].T_body_cam, atol=1e-12)
        mounts.append(T)
        images = sorted((cam0 / "data").glob("*.png"))
        assert len(images) == 6
        for path in images[:2]:
            img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
            assert img.shape == (model.height, model.width) and img.dtype == np.uint8
            assert img.std() > 10
    assert not np.allclose(mounts[0], mounts[1])  # the wide camera has its own mount
    for k, name in enumerate(TEAM):  # and the reader gives back the very model
        cam0 = EurocSequence(team / f"robot{k}").cam0
        assert camera_model(cam0) == CAMERA_PRESETS[name].model
        np.testing.assert_array_equal(cam0.T_body_cam, CAMERA_PRESETS[name].T_body_cam)


def test_fisheye_renders_the_scene_where_its_model_projects_it() -> None:
    """Landmarks found by an independent pinhole camera at the same pose (its ray hits) are on
    the same face in the fisheye render at the model's projection, at the same depth, with the
    same texture."""
    scene = vicon_room()
    atlas = build_atlas(scene, seed=3)
    fisheye = CAMERA_PRESETS["fisheye"].model
    pinhole = CAMERA_PRESETS["wide"].model
    R = R_LOOK_MINUS_X @ cv2.Rodrigues(np.array([0.15, -0.4, 0.1]))[0]
    o = np.array([-1.0, 1.0, 1.6])
    T_world_cam = make_T(R, o)
    ref = Renderer(scene, atlas, pinhole, CLEAN).render_radiance(T_world_cam)
    fe = Renderer(scene, atlas, fisheye, CLEAN).render_radiance(T_world_cam)
    rng = np.random.default_rng(1)
    uv_ref = np.stack([rng.integers(5, 635, 3000), rng.integers(5, 475, 3000)], axis=1)
    ray = pinhole.unproject(uv_ref.astype(float))
    depth = ref.depth[uv_ref[:, 1], uv_ref[:, 0]].astype(np.float64)
    p_cam = ray * depth[:, None]  # landmarks on the scene's surfaces, camera frame
    uv = fisheye.project(p_cam)
    px = np.rint(uv).astype(int)
    inside = ((px >= 0) & (px < [fisheye.width, fisheye.height])).all(axis=1)
    assert inside.mean() > 0.99  # the fisheye sees all the pinhole sees
    px, uv_ref, p_cam = px[inside], uv_ref[inside], p_cam[inside]
    same_face = fe.face[px[:, 1], px[:, 0]] == ref.face[uv_ref[:, 1], uv_ref[:, 0]]
    assert same_face.mean() > 0.99  # only pixels at face boundaries may differ
    r_fe = fisheye.unproject(px.astype(float))
    d_fe = fe.depth[px[:, 1], px[:, 0]]
    # The fisheye pixel's surface point is the landmark, up to the 0.5 px rounding.
    hit = r_fe[same_face] * d_fe[same_face][:, None]
    dist = np.linalg.norm(hit - p_cam[same_face], axis=1)
    pixel_angle = 1.0 / fisheye.fx  # rad per px on axis; larger off axis
    assert np.median(dist / np.linalg.norm(p_cam[same_face], axis=1)) < 2 * pixel_angle
    # Same texture: the fisheye's radiance at the projection matches the pinhole's.
    a = cv2.remap(
        fe.radiance,
        uv[inside, 0].astype(np.float32)[None],
        uv[inside, 1].astype(np.float32)[None],
        cv2.INTER_LINEAR,
    )[0]
    b = ref.radiance[uv_ref[:, 1], uv_ref[:, 0]]
    assert np.corrcoef(a, b)[0, 1] > 0.93  # 0.96; fx 3 % off or k1 = 0.03: 0.78-0.84


def test_camera_list_must_name_one_known_preset_per_robot(tmp_path, capsys) -> None:
    with pytest.raises(SynthError, match="one per robot"):
        SynthConfig(robots=2, cameras=("euroc",))
    with pytest.raises(SynthError, match="unknown camera preset 'pinhole'"):
        SynthConfig(robots=1, cameras=("pinhole",))
    argv = ["dataset", "synth", "--out", str(tmp_path), "--robots", "2", "--seconds", "0.1"]
    assert _cli([*argv, "--cameras", "euroc,fish"]) == 2
    assert "unknown camera preset" in capsys.readouterr().err
    generate_dataset(tmp_path / "default", SynthConfig(robots=1, seconds=0.1, progress=False))
    meta = json.loads((tmp_path / "default" / "dataset.json").read_text())
    assert "cameras" not in meta["config"] and "camera" not in meta["sequences"][0]
