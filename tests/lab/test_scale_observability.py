"""The inertial-only scale profile: it finds the scale the exact IMU implies, and a flight
that accelerates more fixes the scale more firmly."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from common.calibration import EUROC_IMU
from lab.scale_observability import nominal, scale_profile
from services.cloud.config import FullBAConfig, GlobalOptimizationConfig
from services.cloud.optimization.full_ba import build_full_ba
from services.cloud.optimization.inertial import ImuTerms
from sim.cloud import default_camera, vi_circle_atlas

CFG = FullBAConfig()


def _problem(scale: float = 1.0, amp: float = 0.3):
    atlas, store, _ = vi_circle_atlas(40, n_landmarks=300, scale=scale, pose_noise=0.0, amp=amp)
    problem = build_full_ba(
        atlas, 0, default_camera(), CFG, GlobalOptimizationConfig(), store, lambda _a: EUROC_IMU
    )
    assert problem.imu is not None
    return problem, problem.imu


@pytest.mark.parametrize("scale", [1.0, 1.006])
def test_the_profile_finds_the_scale_the_imu_implies(scale):
    problem, terms = _problem(scale)
    prof = scale_profile(problem.T_world_body, problem.fixed, terms, CFG, span=0.01)
    # A map 0.6 % too large: the IMU wants it scaled by 1 / 1.006.
    assert prof.best_scale == pytest.approx(1.0 / scale, abs=5e-4)
    assert prof.pairs == 39
    assert prof.costs.shape == prof.scales.shape == (9,)
    assert np.argmin(prof.costs) == np.argmin(np.abs(prof.scales - 1.0 / scale))


def test_more_acceleration_and_less_noise_fix_the_scale_more_firmly():
    calm, calm_terms = _problem(amp=0.05)
    lively, lively_terms = _problem(amp=0.3)
    s_calm = scale_profile(calm.T_world_body, calm.fixed, calm_terms, CFG, span=0.02).sigma
    s_lively = scale_profile(lively.T_world_body, lively.fixed, lively_terms, CFG).sigma
    assert s_lively < 0.5 * s_calm, (s_lively, s_calm)
    # Noise assumed 3x the calibration (the full BA's default): sigma ~3x the calibrated one.
    s_nominal = scale_profile(lively.T_world_body, lively.fixed, lively_terms, nominal(CFG)).sigma
    assert CFG.imu_noise_scale == 3.0
    assert s_lively / s_nominal == pytest.approx(3.0, rel=0.15)


def test_a_map_without_imu_or_a_bad_grid_is_refused():
    problem, terms = _problem()
    empty = dataclasses.replace(terms, pair_i=terms.pair_i[:0], pair_j=terms.pair_j[:0])
    assert isinstance(empty, ImuTerms)
    with pytest.raises(ValueError, match="no IMU factors"):
        scale_profile(problem.T_world_body, problem.fixed, empty, CFG)
    with pytest.raises(ValueError, match="steps >= 3"):
        scale_profile(problem.T_world_body, problem.fixed, terms, CFG, steps=2)
