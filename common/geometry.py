"""Rotation and rigid-transform helpers (pure numpy; SO(3), SE(3), Sim(3), quaternions).

Conventions: ``R_a_b`` rotates vectors from frame ``b`` into frame ``a``; ``T_a_b`` (4, 4)
maps homogeneous points from ``b`` to ``a``. Quaternions are Hamilton, stored ``(w, x, y, z)``
as EuRoC writes them unless a name says ``xyzw`` (TUM order).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from common.errors import RecslamError


class GeometryError(RecslamError):
    """Input is not a valid rotation, transform or quaternion."""


class DegenerateAlignmentError(GeometryError):
    """A point alignment has no unique solution (too few, collinear or identical points)."""


Sim3 = tuple[np.ndarray, np.ndarray, float]
"""``(R_dst_src (3, 3), t_dst_src (3,), scale)`` of ``p_dst = scale * R_dst_src @ p_src + t``."""


def hat(w: np.ndarray) -> np.ndarray:
    """(3,) vector -> (3, 3) skew-symmetric matrix with ``hat(a) @ b == cross(a, b)``."""
    x, y, z = np.asarray(w, dtype=np.float64).reshape(3)
    return np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])


def check_rotation(R: np.ndarray, atol: float = 1e-6) -> np.ndarray:
    """Return ``R`` as float (3, 3) or raise GeometryError if it is not a proper rotation."""
    R = np.asarray(R, dtype=np.float64)
    if R.shape != (3, 3):
        raise GeometryError(f"rotation must be (3, 3), got {R.shape}")
    if not np.allclose(R.T @ R, np.eye(3), atol=atol) or np.linalg.det(R) < 0:
        raise GeometryError("matrix is not a proper rotation (R^T R != I or det < 0)")
    return R


def so3_exp(w: np.ndarray) -> np.ndarray:
    """Rodrigues: rotation vector (3,) [rad] -> (3, 3) rotation."""
    w = np.asarray(w, dtype=np.float64).reshape(3)
    theta = float(np.linalg.norm(w))
    K = hat(w)
    if theta < 1e-8:
        return np.eye(3) + K + 0.5 * K @ K
    a = np.sin(theta) / theta
    b = (1.0 - np.cos(theta)) / theta**2
    return np.eye(3) + a * K + b * K @ K


def so3_log(R: np.ndarray) -> np.ndarray:
    """(3, 3) rotation -> rotation vector (3,) [rad], angle in [0, pi]."""
    R = check_rotation(R)
    cos = np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0)
    theta = float(np.arccos(cos))
    if theta < 1e-8:
        return np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]]) / 2.0
    if np.pi - theta < 1e-6:
        # Near pi: take the axis from the symmetric part.
        M = (R + np.eye(3)) / 2.0
        axis = np.sqrt(np.clip(np.diag(M), 0.0, None))
        i = int(np.argmax(axis))
        axis = M[:, i] / np.sqrt(M[i, i])
        return axis * theta
    w = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    return w * theta / (2.0 * np.sin(theta))


def make_T(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Build a (4, 4) transform from a (3, 3) rotation and a (3,) translation."""
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = np.asarray(t, dtype=np.float64).reshape(3)
    return T


def inverse_T(T: np.ndarray) -> np.ndarray:
    """Inverse of a (4, 4) rigid transform (or a stack (N, 4, 4))."""
    T = np.asarray(T, dtype=np.float64)
    R = T[..., :3, :3]
    t = T[..., :3, 3]
    Rt = np.swapaxes(R, -1, -2)
    out = np.zeros_like(T)
    out[..., :3, :3] = Rt
    out[..., :3, 3] = -np.einsum("...ij,...j->...i", Rt, t)
    out[..., 3, 3] = 1.0
    return out


def transform_points(T: np.ndarray, p: np.ndarray) -> np.ndarray:
    """Apply a (4, 4) transform to points (N, 3) -> (N, 3)."""
    p = np.asarray(p, dtype=np.float64).reshape(-1, 3)
    return p @ T[:3, :3].T + T[:3, 3]


def quat_wxyz_to_R(q: np.ndarray) -> np.ndarray:
    """Hamilton quaternion(s) (..., 4) in (w, x, y, z) -> rotation(s) (..., 3, 3). Normalises."""
    q = np.asarray(q, dtype=np.float64)
    n = np.linalg.norm(q, axis=-1, keepdims=True)
    if np.any(n < 1e-12):
        raise GeometryError("zero-norm quaternion")
    w, x, y, z = np.moveaxis(q / n, -1, 0)
    R = np.stack(
        [
            1 - 2 * (y * y + z * z),
            2 * (x * y - z * w),
            2 * (x * z + y * w),
            2 * (x * y + z * w),
            1 - 2 * (x * x + z * z),
            2 * (y * z - x * w),
            2 * (x * z - y * w),
            2 * (y * z + x * w),
            1 - 2 * (x * x + y * y),
        ],
        axis=-1,
    )
    return R.reshape(*q.shape[:-1], 3, 3)


def R_to_quat_wxyz(R: np.ndarray) -> np.ndarray:
    """Rotation(s) (..., 3, 3) -> unit quaternion(s) (..., 4) (w, x, y, z) with w >= 0."""
    from scipy.spatial.transform import Rotation

    R = np.asarray(R, dtype=np.float64)
    flat = R.reshape(-1, 3, 3)
    xyzw = Rotation.from_matrix(flat).as_quat()
    wxyz = np.concatenate([xyzw[:, 3:], xyzw[:, :3]], axis=1)
    wxyz *= np.where(wxyz[:, :1] < 0, -1.0, 1.0)
    return wxyz.reshape(*R.shape[:-2], 4)


def nearest_rotation(R: np.ndarray) -> np.ndarray:
    """The rotation closest (Frobenius) to a (3, 3) matrix: re-orthonormalises a rotation
    that repeated products have pushed off SO(3)."""
    U, _, Vt = np.linalg.svd(np.asarray(R, dtype=np.float64))
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    return U @ D @ Vt


def rigid_problem(T: np.ndarray, atol: float) -> str:
    """Why the (4, 4) ``T`` is not a rigid transform within ``atol`` per entry ("" if it is
    one): its shape, its last row (not ``0 0 0 1``), its rotation (not orthonormal, or a
    reflection)."""
    T = np.asarray(T, np.float64)
    if T.shape != (4, 4):
        return f"shape {T.shape}, not (4, 4)"
    if np.abs(T[3] - [0.0, 0.0, 0.0, 1.0]).max() > atol:
        return f"last row is {T[3].tolist()}, not [0, 0, 0, 1]"
    R = T[:3, :3]
    ortho = float(np.abs(R.T @ R - np.eye(3)).max())
    if ortho > atol:
        return f"rotation is not orthonormal (|RᵀR - I| up to {ortho:.3g})"
    if np.linalg.det(R) < 0:
        return "rotation is a reflection (det < 0)"
    return ""


def orthonormalize_T(T: np.ndarray) -> np.ndarray:
    """A copy of the (4, 4) transform ``T`` with its rotation block snapped onto SO(3)."""
    out = np.array(T, dtype=np.float64)
    out[:3, :3] = nearest_rotation(out[:3, :3])
    return out


def refit_inliers(
    fit: Callable[[np.ndarray, np.ndarray], np.ndarray],
    p_src: np.ndarray,
    p_dst: np.ndarray,
    min_residual: float,
) -> tuple[np.ndarray, np.ndarray]:
    """``fit(p_src, p_dst)`` -> ``T (4, 4)`` (``p_dst ≈ T p_src``, rigid or a similarity) on
    the (N, 3) point pairs, then again on the pairs within ``max(3 × median, min_residual)`` of
    the first fit. Returns ``(T, inlier mask (N,))``; the fit's own errors pass through."""
    T = fit(p_src, p_dst)
    r = np.linalg.norm(transform_points(T, p_src) - p_dst, axis=1)
    keep = r <= max(3.0 * float(np.median(r)), min_residual)
    if keep.sum() >= 3 and not keep.all():
        T = fit(p_src[keep], p_dst[keep])
    return T, keep


def similarity_scale(T: np.ndarray) -> float:
    """The scale ``s`` of a similarity ``T (4, 4)`` with rotation block ``s R`` (1 if rigid)."""
    return float(np.cbrt(np.linalg.det(np.asarray(T, dtype=np.float64)[:3, :3])))


def yaw_alignment(p_src: np.ndarray, p_dst: np.ndarray, with_scale: bool = False) -> Sim3:
    """Least-squares ``p_dst ≈ s R p_src + t`` for (N, 3) point sets with ``R`` a rotation
    about z (gravity-aligned maps: yaw only) in closed form; ``s = 1`` without scale. The yaw
    that maximises the correlation is the same with or without scale; then
    ``s = Σ (R a)·b / Σ |a|²`` over the centred points. Raises DegenerateAlignmentError for
    fewer than three pairs or points that coincide."""
    x = np.asarray(p_src, dtype=np.float64)
    y = np.asarray(p_dst, dtype=np.float64)
    if x.shape != y.shape or x.ndim != 2 or x.shape[1] != 3 or x.shape[0] < 3:
        raise DegenerateAlignmentError(
            f"need >= 3 point pairs of equal (N, 3) shape, got {x.shape} / {y.shape}"
        )
    cx, cy = x.mean(0), y.mean(0)
    a, b = x - cx, y - cy
    yaw = np.arctan2(
        np.sum(a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]), np.sum(a[:, 0] * b[:, 0] + a[:, 1] * b[:, 1])
    )
    c, sn = np.cos(yaw), np.sin(yaw)
    R = np.array([[c, -sn, 0.0], [sn, c, 0.0], [0.0, 0.0, 1.0]])
    scale = 1.0
    if with_scale:
        spread = float(np.sum(a * a))
        if not spread > 1e-12:
            raise DegenerateAlignmentError("degenerate alignment: the source points coincide")
        scale = float(np.sum((a @ R.T) * b)) / spread
    return R, cy - scale * (R @ cx), scale


def umeyama_alignment(p_src: np.ndarray, p_dst: np.ndarray, with_scale: bool = False) -> Sim3:
    """Least-squares similarity ``p_dst ≈ s R p_src + t`` for (N, 3) point sets (Umeyama 1991,
    the closed form evo uses); ``s = 1`` without scale (Horn's / Kabsch's rigid solution).

    The one copy of this primitive: evaluation, the cloud's map merging and the VIO's
    simulation all call it. Raises DegenerateAlignmentError when fewer than three points are
    given or the cross-covariance has rank < 2 (collinear or identical points), where the
    rotation is not unique.
    """
    x = np.asarray(p_src, dtype=np.float64)
    y = np.asarray(p_dst, dtype=np.float64)
    if x.shape != y.shape or x.ndim != 2 or x.shape[1] != 3:
        raise DegenerateAlignmentError(
            f"point sets must both be (N, 3), got {x.shape} and {y.shape}"
        )
    n = x.shape[0]
    if n < 3:
        raise DegenerateAlignmentError(f"alignment needs at least 3 point pairs, got {n}")
    mean_x = x.mean(axis=0)
    mean_y = y.mean(axis=0)
    xc = x - mean_x
    yc = y - mean_y
    U, d, Vt = np.linalg.svd((yc.T @ xc) / n)
    # Rank < 2 (relative to the largest singular value): the rotation about the line is free.
    if not d[1] > 1e-10 * d[0]:
        raise DegenerateAlignmentError(
            f"degenerate alignment: the {n} points are (nearly) collinear or identical, "
            f"singular values of the cross-covariance {d.tolist()}"
        )
    S = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0.0:
        S[2, 2] = -1.0
    R = U @ S @ Vt
    s = float(np.trace(np.diag(d) @ S)) / (float(np.sum(xc * xc)) / n) if with_scale else 1.0
    return R, mean_y - s * (R @ mean_x), s
