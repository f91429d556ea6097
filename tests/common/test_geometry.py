import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from common.geometry import (
    DegenerateAlignmentError,
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
    umeyama_alignment,
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


@settings(max_examples=60, deadline=None)
@given(
    seed=st.integers(0, 2**32 - 1),
    n=st.integers(3, 40),
    scale=st.floats(0.05, 20.0),
    with_scale=st.booleans(),
)
def test_umeyama_recovers_any_similarity(seed: int, n: int, scale: float, with_scale: bool) -> None:
    """Exact pairs ``p_dst = s R p_src + t``: the alignment gives back R, t (and s), and with
    noise it is no worse than the true transform (it is the least-squares optimum)."""
    g = np.random.default_rng(seed)
    p_src = g.normal(size=(n, 3)) * g.uniform(0.1, 10.0, size=3)
    R_true = so3_exp(g.uniform(-np.pi, np.pi, 3) * 0.99)
    t_true = g.normal(size=3) * 5.0
    s_true = scale if with_scale else 1.0
    p_dst = s_true * p_src @ R_true.T + t_true
    R, t, s = umeyama_alignment(p_src, p_dst, with_scale)
    check_rotation(R)
    np.testing.assert_allclose(R, R_true, atol=1e-7)
    np.testing.assert_allclose(t, t_true, atol=1e-6 * (1.0 + np.abs(p_dst).max()))
    assert s == pytest.approx(s_true, rel=1e-7)
    noisy = p_dst + g.normal(scale=0.1, size=p_dst.shape)
    R, t, s = umeyama_alignment(p_src, noisy, with_scale)
    cost = np.sum((noisy - (s * p_src @ R.T + t)) ** 2)
    assert cost <= np.sum((noisy - p_dst) ** 2) * (1 + 1e-9)


def test_umeyama_rejects_degenerate_point_sets() -> None:
    line = np.outer(np.arange(10.0), [1.0, 2.0, 3.0])
    with pytest.raises(DegenerateAlignmentError, match="collinear"):
        umeyama_alignment(line, line + 1.0)
    with pytest.raises(DegenerateAlignmentError, match="collinear"):
        umeyama_alignment(np.ones((5, 3)), np.ones((5, 3)), with_scale=True)
    with pytest.raises(DegenerateAlignmentError, match="at least 3"):
        umeyama_alignment(line[:2], line[:2])
    with pytest.raises(DegenerateAlignmentError, match=r"\(N, 3\)"):
        umeyama_alignment(line, line[:, :2])
