import numpy as np
import pytest

from common.geometry import (
    GeometryError,
    R_to_quat_wxyz,
    check_rotation,
    hat,
    inverse_T,
    make_T,
    quat_wxyz_to_R,
    so3_exp,
    so3_log,
    transform_points,
)

rng = np.random.default_rng(7)


def random_rotvecs(n: int) -> np.ndarray:
    axes = rng.normal(size=(n, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    return axes * rng.uniform(0.0, np.pi - 1e-3, size=(n, 1))


def test_hat_is_cross_product() -> None:
    a, b = rng.normal(size=3), rng.normal(size=3)
    np.testing.assert_allclose(hat(a) @ b, np.cross(a, b))


@pytest.mark.parametrize("w", [*random_rotvecs(20), np.zeros(3), np.array([1e-10, 0, 0])])
def test_exp_log_round_trip(w: np.ndarray) -> None:
    R = so3_exp(w)
    check_rotation(R)
    np.testing.assert_allclose(so3_log(R), w, atol=1e-7)


def test_log_near_pi() -> None:
    w = np.array([0.0, 0.0, np.pi - 1e-9])
    np.testing.assert_allclose(so3_exp(so3_log(so3_exp(w))), so3_exp(w), atol=1e-6)


def test_log_rejects_non_rotation() -> None:
    with pytest.raises(GeometryError):
        so3_log(np.diag([1.0, 1.0, -1.0]))
    with pytest.raises(GeometryError):
        so3_log(np.ones((3, 3)))


def test_inverse_times_T_is_identity() -> None:
    Ts = np.stack([make_T(so3_exp(w), rng.normal(size=3)) for w in random_rotvecs(5)])
    np.testing.assert_allclose(inverse_T(Ts) @ Ts, np.broadcast_to(np.eye(4), Ts.shape), atol=1e-12)
    p = rng.normal(size=(10, 3))
    np.testing.assert_allclose(transform_points(inverse_T(Ts[0]), transform_points(Ts[0], p)), p)


def test_quaternion_round_trip_and_convention() -> None:
    # 90 degrees about z: (w, x, y, z) = (cos 45, 0, 0, sin 45)
    q = np.array([np.cos(np.pi / 4), 0.0, 0.0, np.sin(np.pi / 4)])
    np.testing.assert_allclose(quat_wxyz_to_R(q) @ [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], atol=1e-12)
    Rs = np.stack([so3_exp(w) for w in random_rotvecs(10)])
    np.testing.assert_allclose(quat_wxyz_to_R(R_to_quat_wxyz(Rs)), Rs, atol=1e-12)
    assert np.all(R_to_quat_wxyz(Rs)[:, 0] >= 0)
    with pytest.raises(GeometryError):
        quat_wxyz_to_R(np.zeros(4))


def test_nearest_rotation_repairs_drift() -> None:
    from common.geometry import nearest_rotation, orthonormalize_T

    R = so3_exp(np.array([0.3, -0.2, 0.1]))
    drifted = R + 1e-3 * rng.normal(size=(3, 3))
    fixed = nearest_rotation(drifted)
    check_rotation(fixed, atol=1e-12)
    assert np.linalg.norm(fixed - R) < 5e-3
    T = make_T(drifted, [1.0, 2.0, 3.0])
    out = orthonormalize_T(T)
    check_rotation(out[:3, :3], atol=1e-12)
    np.testing.assert_array_equal(out[:3, 3], [1.0, 2.0, 3.0])
