"""The trajectory type every evaluation function takes: stamped body poses in a world frame.

A :class:`Trajectory` holds ``N`` poses ``T_world_body`` as timestamps (int64 ns), positions
(m) and Hamilton unit quaternions ``(w, x, y, z)``. ``world`` is whatever frame the producer
used: the ground truth's world for a reference, the (merged) map frame for an estimate.
Instances are immutable; every operation returns a new one.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

from common.evaluation.errors import TrajectoryError
from common.geometry import R_to_quat_wxyz, quat_wxyz_to_R


class PoseSeries(Protocol):
    """Anything with ground-truth pose arrays, e.g. ``common.data.euroc.EurocGroundTruth``.

    Read-only members, so that frozen dataclasses match."""

    @property
    def timestamps_ns(self) -> np.ndarray: ...
    @property
    def p_world_body(self) -> np.ndarray: ...
    @property
    def q_world_body_wxyz(self) -> np.ndarray: ...


def _readonly(a: np.ndarray) -> np.ndarray:
    a = np.array(a, copy=True)
    a.setflags(write=False)
    return a


@dataclass(frozen=True)
class Trajectory:
    """Stamped poses ``T_world_body``.

    ``timestamps_ns`` (N,) int64, strictly increasing; ``p_world_body`` (N, 3) float64 [m];
    ``q_wxyz`` (N, 4) float64 Hamilton ``R_world_body`` as unit quaternions (normalised on
    construction; a zero quaternion is an error). ``name`` labels plots and tables.
    """

    timestamps_ns: np.ndarray
    p_world_body: np.ndarray
    q_wxyz: np.ndarray
    name: str = field(default="")

    def __post_init__(self) -> None:
        label = f"trajectory {self.name!r}" if self.name else "trajectory"
        ts = np.asarray(self.timestamps_ns)
        if ts.ndim != 1:
            raise TrajectoryError(f"{label}: timestamps_ns must be (N,), got {ts.shape}")
        if ts.size and not np.issubdtype(ts.dtype, np.integer):
            raise TrajectoryError(f"{label}: timestamps_ns must be integers (ns), got {ts.dtype}")
        ts = ts.astype(np.int64)
        n = ts.shape[0]
        p = np.asarray(self.p_world_body, dtype=np.float64)
        q = np.asarray(self.q_wxyz, dtype=np.float64)
        if p.shape != (n, 3):
            raise TrajectoryError(f"{label}: p_world_body must be ({n}, 3), got {p.shape}")
        if q.shape != (n, 4):
            raise TrajectoryError(f"{label}: q_wxyz must be ({n}, 4), got {q.shape}")
        if not (np.all(np.isfinite(p)) and np.all(np.isfinite(q))):
            bad = int(np.flatnonzero(~np.isfinite(np.hstack([p, q])).all(axis=1))[0])
            raise TrajectoryError(f"{label}: non-finite pose at index {bad}")
        if n > 1:
            steps = np.diff(ts)
            if np.any(steps <= 0):
                i = int(np.flatnonzero(steps <= 0)[0])
                raise TrajectoryError(
                    f"{label}: timestamps must strictly increase; index {i + 1} "
                    f"({ts[i + 1]} ns) follows {ts[i]} ns"
                )
        norms = np.linalg.norm(q, axis=1)
        if np.any(norms < 1e-12):
            raise TrajectoryError(
                f"{label}: zero quaternion at index {int(np.flatnonzero(norms < 1e-12)[0])}"
            )
        object.__setattr__(self, "timestamps_ns", _readonly(ts))
        object.__setattr__(self, "p_world_body", _readonly(p))
        object.__setattr__(self, "q_wxyz", _readonly(q / norms[:, None]))

    def __len__(self) -> int:
        return int(self.timestamps_ns.shape[0])

    @classmethod
    def from_poses(
        cls, timestamps_ns: np.ndarray, T_world_body: np.ndarray, name: str = ""
    ) -> Trajectory:
        """Build from (N,) int64 stamps and (N, 4, 4) rigid transforms."""
        T = np.asarray(T_world_body, dtype=np.float64)
        if T.ndim != 3 or T.shape[1:] != (4, 4):
            raise TrajectoryError(f"T_world_body must be (N, 4, 4), got {T.shape}")
        return cls(timestamps_ns, T[:, :3, 3], R_to_quat_wxyz(T[:, :3, :3]), name)

    @classmethod
    def from_groundtruth(cls, gt: PoseSeries, name: str = "") -> Trajectory:
        """Pose part of a ``common.data.euroc.EurocGroundTruth`` (or any :class:`PoseSeries`)."""
        return cls(gt.timestamps_ns, gt.p_world_body, gt.q_world_body_wxyz, name)

    @property
    def timestamps_s(self) -> np.ndarray:
        """(N,) float64 seconds (loses sub-µs precision at epoch-scale stamps; for plots)."""
        return self.timestamps_ns.astype(np.float64) * 1e-9

    @property
    def R_world_body(self) -> np.ndarray:
        """(N, 3, 3) rotations body -> world."""
        return quat_wxyz_to_R(self.q_wxyz)

    @property
    def T_world_body(self) -> np.ndarray:
        """(N, 4, 4) rigid transforms body -> world."""
        T = np.zeros((len(self), 4, 4))
        T[:, :3, :3] = self.R_world_body
        T[:, :3, 3] = self.p_world_body
        T[:, 3, 3] = 1.0
        return T

    @property
    def duration_s(self) -> float:
        """Time between first and last pose [s] (0 for fewer than two poses)."""
        if len(self) < 2:
            return 0.0
        return float(self.timestamps_ns[-1] - self.timestamps_ns[0]) * 1e-9

    @property
    def path_length_m(self) -> float:
        """Sum of distances between consecutive positions [m]."""
        return float(np.sum(np.linalg.norm(np.diff(self.p_world_body, axis=0), axis=1)))

    def select(self, indices: Sequence[int] | np.ndarray) -> Trajectory:
        """Poses at the given increasing indices."""
        idx = np.asarray(indices, dtype=np.int64)
        return Trajectory(
            self.timestamps_ns[idx], self.p_world_body[idx], self.q_wxyz[idx], self.name
        )

    def renamed(self, name: str) -> Trajectory:
        """Same poses, another label."""
        return Trajectory(self.timestamps_ns, self.p_world_body, self.q_wxyz, name)

    def transformed(
        self, R_new_world: np.ndarray, t_new_world: np.ndarray, scale: float = 1.0
    ) -> Trajectory:
        """Apply the similarity ``x_new = scale * R_new_world @ x_world + t_new_world``.

        Positions are mapped as points; orientations become ``R_new_world @ R_world_body``
        (scale does not touch rotations), as evo's ``align`` with scale correction does.
        """
        R = np.asarray(R_new_world, dtype=np.float64).reshape(3, 3)
        t = np.asarray(t_new_world, dtype=np.float64).reshape(3)
        p = scale * (self.p_world_body @ R.T) + t
        q = R_to_quat_wxyz(R @ self.R_world_body) if len(self) else self.q_wxyz
        return Trajectory(self.timestamps_ns, p, q, self.name)
