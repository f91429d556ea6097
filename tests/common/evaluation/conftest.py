"""Shared fixtures for the evaluation tests: smooth random trajectories and evo conversion."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from common.evaluation.trajectory import Trajectory
from common.geometry import R_to_quat_wxyz, so3_exp

T0_NS = 1_403_636_579_763_555_527  # an EuRoC-like epoch stamp, to exercise ns precision


def smooth_trajectory(
    rng: np.random.Generator,
    n: int = 600,
    rate_hz: float = 200.0,
    t0_ns: int = T0_NS,
    name: str = "",
    extent_m: float = 3.0,
) -> Trajectory:
    """Random smooth 3-D motion: sums of sinusoids for position and attitude angles."""
    t = np.arange(n) / rate_hz
    p = np.zeros((n, 3))
    angles = np.zeros((n, 3))
    for k in range(3):
        for _ in range(3):
            f = rng.uniform(0.05, 0.4)
            p[:, k] += (
                extent_m
                / 3
                * rng.uniform(0.3, 1.0)
                * np.sin(2 * np.pi * f * t + rng.uniform(0, 2 * np.pi))
            )
            angles[:, k] += rng.uniform(0.1, 0.6) * np.sin(
                2 * np.pi * f * t + rng.uniform(0, 2 * np.pi)
            )
    R = np.stack([so3_exp(a) for a in angles])
    ts = t0_ns + np.round(t * 1e9).astype(np.int64)
    return Trajectory(ts, p, R_to_quat_wxyz(R), name)


def random_rotation(rng: np.random.Generator) -> np.ndarray:
    return so3_exp(rng.normal(size=3) * 1.2)


def perturbed(
    rng: np.random.Generator,
    traj: Trajectory,
    pos_sigma_m: float = 0.02,
    rot_sigma_rad: float = 0.01,
) -> Trajectory:
    """Same stamps, noisy positions and attitudes."""
    p = traj.p_world_body + rng.normal(scale=pos_sigma_m, size=traj.p_world_body.shape)
    dR = np.stack([so3_exp(w) for w in rng.normal(scale=rot_sigma_rad, size=(len(traj), 3))])
    q = R_to_quat_wxyz(traj.R_world_body @ dR)
    return Trajectory(traj.timestamps_ns, p, q, traj.name)


def to_evo(traj: Trajectory):
    """Our trajectory as evo's PoseTrajectory3D (stamps as float seconds)."""
    from evo.core.trajectory import PoseTrajectory3D

    return PoseTrajectory3D(
        positions_xyz=np.array(traj.p_world_body),
        orientations_quat_wxyz=np.array(traj.q_wxyz),
        timestamps=traj.timestamps_ns.astype(np.float64) * 1e-9,
    )


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(20261122)


@pytest.fixture
def tools() -> SimpleNamespace:
    """Helpers: ``smooth``, ``perturbed``, ``random_rotation``, ``to_evo``, ``T0_NS``."""
    return SimpleNamespace(
        smooth=smooth_trajectory,
        perturbed=perturbed,
        random_rotation=random_rotation,
        to_evo=to_evo,
        T0_NS=T0_NS,
    )
