"""Renderer: pixels show the texture of the surface along their (distorted) ray; mip-mapping
removes aliasing; the fast caster agrees with the reference caster."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from common.data.synth.generate import EUROC_CAM0
from common.data.synth.render import RenderConfig, Renderer
from common.data.synth.scene import vicon_room
from common.data.synth.textures import build_atlas
from common.geometry import make_T

CAM = EUROC_CAM0  # EuRoC MH/V cam0 intrinsics and radial-tangential distortion
CLEAN = RenderConfig(noise_std=0.0, blur_sigma=0.0, vignetting=0.0, exposure_amplitude=0.0)
# Camera axes (x right, y down, z forward) as columns, looking along world -x (at wall x = -4).
R_LOOK_MINUS_X = np.array([[0.0, 0.0, -1.0], [1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


@pytest.fixture(scope="module")
def scene_atlas():
    scene = vicon_room()
    return scene, build_atlas(scene, seed=3)


def test_wall_point_renders_its_texture_value(scene_atlas) -> None:
    scene, atlas = scene_atlas
    renderer = Renderer(scene, atlas, CAM, CLEAN)
    # Look at the free upper part of the x = -4 wall from 1.4 m away, slightly rotated.
    R = R_LOOK_MINUS_X @ cv2.Rodrigues(np.array([0.1, -0.2, 0.05]))[0]
    o = np.array([-2.6, 1.5, 2.4])
    res = renderer.render_radiance(make_T(R, o))
    face_index = 0  # room_lox
    face = scene.faces[face_index]
    rng = np.random.default_rng(0)
    uv = np.stack([rng.integers(40, 712, 200), rng.integers(40, 440, 200)], axis=1)
    rays_world = CAM.unproject(uv.astype(float)) @ R.T
    t = (face.offset - o[0]) / rays_world[:, 0]
    p_world = o + t[:, None] * rays_world
    p_cam = (p_world - o) @ R
    np.testing.assert_allclose(CAM.project(p_cam), uv, atol=1e-6)  # point projects to pixel
    on_wall = res.face[uv[:, 1], uv[:, 0]] == face_index
    assert on_wall.mean() > 0.9
    uv, p_world, t = uv[on_wall], p_world[on_wall], t[on_wall]
    np.testing.assert_allclose(res.depth[uv[:, 1], uv[:, 0]], t, rtol=1e-4)
    # Independent trilinear lookup of the face texture at the renderer's mip level.
    st = face.texcoords(p_world)
    lod = res.lod[uv[:, 1], uv[:, 0]].astype(np.float64)
    expected = np.empty(len(st))
    for i, (s, level) in enumerate(zip(st, lod, strict=True)):
        lo = min(int(level), atlas.levels - 2)
        a = atlas.sample(face_index, s[None], lo)[0]
        b = atlas.sample(face_index, s[None], lo + 1)[0]
        expected[i] = a + (b - a) * (level - lo)
    shade = res.radiance[uv[:, 1], uv[:, 0]] / expected
    np.testing.assert_allclose(shade, shade[0], rtol=0.03, atol=0)  # one shade per face
    got = res.radiance[uv[:, 1], uv[:, 0]] / shade[0]
    assert np.abs(got - expected).max() < 2.0
    assert expected.std() > 10.0  # the wall is textured, so the match is meaningful
    # The face's level-0 texels cover the whole wall at the configured texel size.
    w, h = atlas.rect[face_index][2:]
    assert (w, h) == tuple(np.ceil(np.array(face.size) / atlas.texel_m[face_index]).astype(int))


def test_clean_image_is_quantised_radiance(scene_atlas) -> None:
    scene, atlas = scene_atlas
    cam = CAM.scaled(0.5)
    renderer = Renderer(scene, atlas, cam, CLEAN)
    T = make_T(R_LOOK_MINUS_X, [1.0, -1.0, 1.5])
    img = renderer.render(T, 0.0, np.random.default_rng(0))
    rad = renderer.render_radiance(T).radiance
    assert img.dtype == np.uint8 and img.shape == (240, 376)
    np.testing.assert_array_equal(img, np.clip(np.rint(rad), 0, 255).astype(np.uint8))
    assert 40 < img.mean() < 220 and img.std() > 25


def test_fast_caster_agrees_with_reference(scene_atlas) -> None:
    scene, atlas = scene_atlas
    cam = CAM.scaled(0.25)
    renderer = Renderer(scene, atlas, cam, CLEAN)
    rng = np.random.default_rng(5)
    for _ in range(6):
        R = cv2.Rodrigues(rng.normal(0, 1.5, 3))[0]
        o = rng.uniform([-3.0, -2.5, 0.8], [3.0, 2.5, 2.5])
        if scene.clearance(o[None])[0] < 0.3:
            continue
        res = renderer.render_radiance(make_T(R, o))
        rays = cam.pixel_rays().reshape(-1, 3) @ R.T
        t_ref, face_ref = scene.ray_cast(o, rays)
        same = res.face.reshape(-1) == face_ref
        assert same.mean() > 0.995
        np.testing.assert_allclose(res.depth.reshape(-1)[same], t_ref[same], rtol=1e-4, atol=1e-4)


def test_mipmapping_removes_aliasing_on_grazing_floor(scene_atlas) -> None:
    """Against a 4x4 supersampled reference, the mip-mapped render is much closer than a
    render forced to the finest level (which aliases on the far, grazing floor)."""
    scene, atlas = scene_atlas
    cam = CAM.scaled(0.5)
    # Low over the floor, looking along the room's length, pitched 15 degrees down.
    R = R_LOOK_MINUS_X @ cv2.Rodrigues(np.array([-0.26, 0.0, 0.0]))[0]
    R = cv2.Rodrigues(np.array([0.0, 0.0, np.pi]))[0] @ R  # look along +x
    T = make_T(R, [-3.0, 2.0, 0.6])
    mip = Renderer(scene, atlas, cam, CLEAN).render_radiance(T).radiance
    nomip = (
        Renderer(
            scene,
            atlas,
            cam,
            RenderConfig(
                noise_std=0.0,
                blur_sigma=0.0,
                vignetting=0.0,
                exposure_amplitude=0.0,
                lod_bias=-20.0,
            ),
        )
        .render_radiance(T)
        .radiance
    )
    big = Renderer(scene, atlas, CAM.scaled(2.0), CLEAN).render_radiance(T).radiance
    ref = cv2.resize(big, (cam.width, cam.height), interpolation=cv2.INTER_AREA)
    floor = Renderer(scene, atlas, cam, CLEAN).render_radiance(T)
    far = (floor.face == 4) & (floor.depth > 3.0)
    assert far.sum() > 2000
    err_mip = np.abs(mip - ref)[far].mean()
    err_nomip = np.abs(nomip - ref)[far].mean()
    assert err_mip < 0.75 * err_nomip
