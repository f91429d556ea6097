"""Aligning an estimated trajectory to its reference: Umeyama/Horn SE(3), Sim(3), origin.

The estimate lives in its own map frame; the reference in the ground truth's world. An
alignment is the similarity ``p_ref ≈ scale * R_ref_est @ p_est + t_ref_est`` that minimises
the summed squared position differences of associated poses (Umeyama 1991, the closed form
evo uses), optionally from only the first ``n`` pairs. ``ORIGIN`` instead maps the first
estimated pose exactly onto the first reference pose (evo's ``--align_origin``).
"""

from __future__ import annotations

import enum
import logging
from dataclasses import dataclass

import numpy as np

from common.evaluation.errors import AlignmentError
from common.evaluation.trajectory import Trajectory
from common.geometry import DegenerateAlignmentError, umeyama_alignment

log = logging.getLogger(__name__)


class AlignMode(enum.Enum):
    """How the estimate is brought into the reference frame before errors are measured."""

    NONE = "none"  # identity: the estimate is assumed to be in the reference frame already
    SE3 = "se3"  # rotation + translation (Horn / Umeyama without scale)
    SIM3 = "sim3"  # rotation + translation + scale (Umeyama)
    SCALE = "scale"  # scale only, estimated by Umeyama with scale (evo's correct_only_scale)
    ORIGIN = "origin"  # first estimated pose onto first reference pose (rigid, full pose)


@dataclass(frozen=True)
class SimilarityTransform:
    """``x_ref = scale * R_ref_est @ x_est + t_ref_est``; ``R_ref_est`` (3, 3), ``t`` (3,) m."""

    R_ref_est: np.ndarray
    t_ref_est: np.ndarray
    scale: float = 1.0

    @classmethod
    def identity(cls) -> SimilarityTransform:
        return cls(np.eye(3), np.zeros(3), 1.0)

    @property
    def matrix(self) -> np.ndarray:
        """(4, 4) homogeneous matrix ``[[s R, t], [0, 1]]``."""
        M = np.eye(4)
        M[:3, :3] = self.scale * self.R_ref_est
        M[:3, 3] = self.t_ref_est
        return M

    @property
    def scale_error(self) -> float:
        """``scale - 1``: relative scale drift of the estimate (0 for rigid alignments)."""
        return float(self.scale - 1.0)

    def apply_points(self, p_est: np.ndarray) -> np.ndarray:
        """(N, 3) points in the estimate frame -> (N, 3) in the reference frame."""
        p = np.asarray(p_est, dtype=np.float64).reshape(-1, 3)
        return self.scale * (p @ self.R_ref_est.T) + self.t_ref_est

    def apply(self, traj: Trajectory) -> Trajectory:
        """Trajectory expressed in the reference frame (rotations turned by ``R_ref_est``)."""
        return traj.transformed(self.R_ref_est, self.t_ref_est, self.scale)

    @classmethod
    def from_dict(cls, d: dict[str, object]) -> SimilarityTransform:
        """Inverse of :meth:`as_dict`; AlignmentError for anything else."""
        try:
            R = np.array(d["R_ref_est"], np.float64)
            t = np.array(d["t_ref_est"], np.float64)
            scale = float(d.get("scale", 1.0))  # type: ignore[arg-type]
        except (KeyError, TypeError, ValueError) as exc:
            raise AlignmentError(f"not a transform: {exc}") from exc
        if R.shape != (3, 3) or t.shape != (3,) or not np.isfinite([*R.ravel(), *t, scale]).all():
            raise AlignmentError(f"not a transform: R {R.shape}, t {t.shape}")
        return cls(R, t, scale)

    def as_dict(self) -> dict[str, object]:
        """JSON-friendly form (lists of floats)."""
        return {
            "R_ref_est": self.R_ref_est.tolist(),
            "t_ref_est": self.t_ref_est.tolist(),
            "scale": float(self.scale),
        }


def umeyama(p_src: np.ndarray, p_dst: np.ndarray, with_scale: bool = False) -> SimilarityTransform:
    """Least-squares similarity ``p_dst ≈ s R p_src + t`` for (N, 3) point sets (Umeyama 1991).

    :func:`common.geometry.umeyama_alignment` as a :class:`SimilarityTransform`. Without scale
    this is Horn's / Kabsch's rigid solution. Raises AlignmentError when fewer than three
    points are given or the cross-covariance has rank < 2 (e.g. collinear points), where the
    rotation is not unique.
    """
    try:
        R, t, s = umeyama_alignment(p_src, p_dst, with_scale)
    except DegenerateAlignmentError as exc:
        raise AlignmentError(str(exc)) from exc
    return SimilarityTransform(R, t, s)


def origin_alignment(ref: Trajectory, est: Trajectory) -> SimilarityTransform:
    """Rigid transform mapping the first estimated pose onto the first reference pose."""
    if len(ref) == 0 or len(est) == 0:
        raise AlignmentError("origin alignment needs at least one pose in each trajectory")
    R_ref_body = ref.R_world_body[0]
    R_est_body = est.R_world_body[0]
    R = R_ref_body @ R_est_body.T
    t = ref.p_world_body[0] - R @ est.p_world_body[0]
    return SimilarityTransform(R, t, 1.0)


def estimate_alignment(
    p_ref: np.ndarray,
    p_est: np.ndarray,
    mode: AlignMode,
    n_first: int | None = None,
) -> SimilarityTransform:
    """Alignment from associated positions (N, 3) for the point-based modes.

    ``n_first``: use only the first ``n_first`` pairs (all when None). ``ORIGIN`` needs full
    poses and is handled by :func:`align`.
    """
    if mode is AlignMode.NONE:
        return SimilarityTransform.identity()
    if mode is AlignMode.ORIGIN:
        raise AlignmentError("ORIGIN alignment needs poses; call align() instead")
    if n_first is not None:
        if n_first < 1:
            raise AlignmentError(f"n_first must be >= 1, got {n_first}")
        p_ref = p_ref[:n_first]
        p_est = p_est[:n_first]
    sim = umeyama(p_est, p_ref, with_scale=mode in (AlignMode.SIM3, AlignMode.SCALE))
    if mode is AlignMode.SCALE:
        return SimilarityTransform(np.eye(3), np.zeros(3), sim.scale)
    log.debug("alignment %s: scale %.6f, t %s", mode.value, sim.scale, sim.t_ref_est)
    return sim


def align(
    ref: Trajectory, est: Trajectory, mode: AlignMode, n_first: int | None = None
) -> SimilarityTransform:
    """Alignment of an associated pair (``ref[i]`` pairs with ``est[i]``, same length)."""
    if len(ref) != len(est):
        raise AlignmentError(
            f"associated trajectories must have equal length, got {len(ref)} and {len(est)}"
        )
    if mode is AlignMode.ORIGIN:
        return origin_alignment(ref, est)
    return estimate_alignment(ref.p_world_body, est.p_world_body, mode, n_first)
