"""Scene geometry and textures: clearance, face parametrisation, seeded and non-repetitive
textures with plenty of ORB corners."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from common.data.synth.scene import Box, Scene, SceneError, vicon_room
from common.data.synth.textures import TextureConfig, build_atlas

FAST = TextureConfig(
    texel_m=0.02, box_texel_m=0.02, ceiling_texel_m=0.03, levels=4, atlas_width=2048
)


def test_clearance_of_known_points() -> None:
    scene = Scene((0.0, 0.0, 0.0), (8.0, 7.0, 3.5), (Box((3.0, 3.0, 0.0), (4.0, 4.0, 1.0)),))
    d = scene.clearance(
        np.array(
            [[1.0, 1.0, 1.5], [3.5, 3.5, 2.0], [3.5, 3.5, 0.5], [-1.0, 1.0, 1.0], [5.0, 3.5, 0.5]]
        )
    )
    np.testing.assert_allclose(d, [1.0, 1.0, -0.5, -1.0, 0.5])
    with pytest.raises(SceneError, match="leaves the room"):
        Scene((0.0, 0.0, 0.0), (1.0, 1.0, 1.0), (Box((0.5, 0.5, 0.0), (1.5, 0.8, 0.5)),))


def test_faces_round_trip_and_read_upright() -> None:
    scene = vicon_room()
    assert len(scene.faces) == 6 + 6 * len(scene.boxes)
    rng = np.random.default_rng(0)
    for face in scene.faces:
        st = rng.uniform(0, 1, (20, 2)) * face.size
        p = face.point(st)
        np.testing.assert_allclose(face.texcoords(p), st, atol=1e-12)
        np.testing.assert_allclose(p[:, face.axis], face.offset)
        if face.kind in ("wall", "box_side"):
            # Texture rows grow downwards (t = 0 at the top edge).
            top = face.point(np.array([[0.0, 0.0]]))[0, 2]
            assert top == pytest.approx(face.v_range[1])
            # s grows to the right of a viewer looking at the face along -normal.
            n = np.eye(3)[face.axis] * face.normal_sign
            right = np.cross([0.0, 0.0, 1.0], n)
            ds = face.point(np.array([[1.0, 0.0]]))[0] - face.point(np.array([[0.0, 0.0]]))[0]
            assert ds @ right == pytest.approx(1.0)


def test_atlas_deterministic_per_seed() -> None:
    scene = vicon_room()
    a = build_atlas(scene, 11, FAST)
    b = build_atlas(scene, 11, FAST)
    c = build_atlas(scene, 12, FAST)
    np.testing.assert_array_equal(a.image, b.image)
    assert np.mean(a.face_texture(0) != c.face_texture(0)) > 0.8


def test_mip_levels_are_box_filtered_level_zero() -> None:
    atlas = build_atlas(vicon_room(), 1, FAST)
    l0 = atlas.level(0).astype(np.float32)
    l1 = atlas.level(1).astype(np.float32)
    down = cv2.resize(l0, (l0.shape[1] // 2, l0.shape[0] // 2), interpolation=cv2.INTER_AREA)
    assert np.abs(down - l1).max() <= 1.0


def test_faces_look_different_and_have_corners() -> None:
    """No two walls share texture (normalised cross-correlation of equal crops is low), and
    each wall offers plenty of ORB keypoints."""
    scene = vicon_room()
    atlas = build_atlas(scene, 0)
    walls = [i for i, f in enumerate(scene.faces) if f.kind == "wall"]
    crops = [atlas.face_texture(i)[:800, :1600].astype(np.float32) for i in walls]
    small = [cv2.resize(c, (200, 100), interpolation=cv2.INTER_AREA) for c in crops]
    for i in range(len(small)):
        for j in range(i + 1, len(small)):
            ncc = cv2.matchTemplate(small[i], small[j][10:90, 20:180], cv2.TM_CCOEFF_NORMED)
            assert ncc.max() < 0.5, (walls[i], walls[j], ncc.max())
    orb = cv2.ORB_create(nfeatures=3000)
    for i in walls:
        tex = atlas.face_texture(i)
        view = cv2.resize(tex, (tex.shape[1] // 3, tex.shape[0] // 3), interpolation=cv2.INTER_AREA)
        assert len(orb.detect(view, None)) > 1000
